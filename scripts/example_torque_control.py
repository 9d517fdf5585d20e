"""Example: torque-control a robot's joints with the paper's controller (Sec. 4) and
compare its tracking with the robot's own position servo.

    python scripts/example_torque_control.py --motor-model out/examples/motor_model.yaml
        [--robot iiwa14|hrp2|FILE] [--k6 1.0] [--duration 3]

`build_torque_control` composes the diagram: the station, the estimation chain, the
inverse dynamics (eq. 12), the Δq torque controller (eq. 10-11) and the safety
supervisor; `build_position_control` the baseline. The reference: every controlled joint
on a sinusoid around the home pose (`assembly.sinusoid.sinusoid_reference`). The motor
model comes from `example_identify_motor_model.py` or `hrp2-drake identify --robot`.
"""

import argparse

import numpy as np
from pydrake.systems.analysis import Simulator

from hrp2_drake.assembly.builders import build_position_control, build_torque_control
from hrp2_drake.assembly.sinusoid import sinusoid_reference
from hrp2_drake.assembly.torque_control import (
    ControllerSettings,
    EstimatorSettings,
    TorqueControlConfig,
)
from hrp2_drake.description import load_robot_description
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.multibody import joint_indexing
from hrp2_drake.robot.station import (
    StationConfig,
    initial_joint_positions,
    make_station,
)
from hrp2_drake.tools.track import TrackConfig


def max_errors(control, duration: float, robot) -> np.ndarray:
    """Simulates a ControlDiagram; the maximum error of the true angles of the
    controlled joints after the first half second."""
    simulator = Simulator(control.diagram)
    context = simulator.get_context()
    plant = control.station.GetSubsystemByName("plant")
    q_index = joint_indexing(plant, robot.controlled_joints).q
    rows = [robot.joints.index(j) for j in robot.controlled_joints]
    worst = np.zeros(len(rows))
    for t in np.arange(0.5, duration, 0.002):
        simulator.AdvanceTo(t)
        q_ref = control.diagram.GetOutputPort("q_ref").Eval(context)[rows]
        q = control.diagram.GetOutputPort("state_true").Eval(context)[q_index]
        worst = np.maximum(worst, np.abs(q_ref - q))
    return worst


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robot", default="iiwa14", help="robot description")
    parser.add_argument("--motor-model", required=True, help="MotorModel YAML")
    parser.add_argument(
        "--k6", type=float, default=1.0, help="position gain (Sec. 4.2)"
    )
    parser.add_argument("--duration", type=float, default=3.0, help="simulated seconds")
    args = parser.parse_args()

    robot = load_robot_description(args.robot)
    station = StationConfig(
        robot=args.robot, scenario="fixed_base" if robot.base == "fixed" else "hanging"
    )
    track = TrackConfig()  # its sinusoid's amplitude and frequency
    q0 = initial_joint_positions(station)
    reference = sinusoid_reference(
        robot, q0, track.amplitude, track.frequency, 0.5, args.duration - 0.5
    )
    motor_model = MotorModel.load(args.motor_model)

    position = max_errors(
        build_position_control(robot, make_station(station), reference),
        args.duration,
        robot,
    )
    torque = max_errors(
        build_torque_control(
            robot,
            make_station(station),
            reference,
            motor_model,
            TorqueControlConfig(
                start_time=0.5,
                controller=ControllerSettings(k6=args.k6),
                estimator=EstimatorSettings(window=41),
            ),
            control_period=station.sensors_config().period,
        ),
        args.duration,
        robot,
    )
    print(
        f"{robot.name}: maximum tracking error (mrad), position servo vs torque "
        f"control K6 = {args.k6:g}"
    )
    for name, p, t in zip(robot.labels(), position, torque):
        print(f"  {name:>12}: {p * 1e3:7.2f}  {t * 1e3:7.2f}")


if __name__ == "__main__":
    main()
