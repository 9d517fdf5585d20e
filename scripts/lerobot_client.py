"""LeRobot's own motor bus (`lerobot.motors.feetech.FeetechMotorsBus`) driving the
emulated SO-101 as it drives a real arm: connect (its handshake: a ping and the model
number of every servo), broadcast ping, sync reads, writes read back, torque on, a
sync write of goals, torque off, disconnect. A check by a client written by others
(docs/feetech.md), not a test: LeRobot needs PyTorch, which the project does not.

Run, in a virtual environment of its own (LeRobot pins its torch; any CPU build
imports the motor bus):

    python3 -m venv /tmp/lerobot && /tmp/lerobot/bin/pip install --no-deps lerobot
    /tmp/lerobot/bin/pip install torch accelerate datasets draccus deepdiff \
        feetech-servo-sdk pyserial tqdm
    hrp2-drake sim-servo --robot so101 --lockstep &      # prints its port
    /tmp/lerobot/bin/python scripts/lerobot_client.py /dev/pts/N
"""

import sys

from lerobot.motors import Motor, MotorNormMode
from lerobot.motors.feetech import FeetechMotorsBus

#: The SO-101 follower's motors as LeRobot names them (its so101_follower), IDs 1-6.
NAMES = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll"]


def main(port: str) -> int:
    motors = {
        name: Motor(k + 1, "sts3215", MotorNormMode.RANGE_M100_100)
        for k, name in enumerate(NAMES)
    }
    motors["gripper"] = Motor(6, "sts3215", MotorNormMode.RANGE_0_100)
    bus = FeetechMotorsBus(port=port, motors=motors)
    bus.connect()
    print("model numbers:", {name: bus.ping(name) for name in motors})
    print("broadcast ping:", bus.broadcast_ping())
    start = bus.sync_read("Present_Position", normalize=False)
    print("present position:", start)
    print("P coefficient:", bus.sync_read("P_Coefficient"))
    bus.write("P_Coefficient", "elbow_flex", 16)
    print("elbow's P after writing 16:", bus.read("P_Coefficient", "elbow_flex"))
    bus.write("P_Coefficient", "elbow_flex", 32)
    bus.enable_torque()
    goal = dict(start) | {"elbow_flex": start["elbow_flex"] + 100}
    bus.sync_write("Goal_Position", goal, normalize=False)
    for _ in range(50):
        now = bus.sync_read("Present_Position", normalize=False)
    print("50 sync reads after an elbow goal of +100 pulses:", now)
    print("present load:", bus.sync_read("Present_Load", normalize=False))
    print("voltage:", bus.sync_read("Present_Voltage", normalize=False))
    bus.disable_torque()
    bus.disconnect()
    print("disconnected")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
