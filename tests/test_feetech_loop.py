"""The whole Feetech path with the processes separate: `hrp2-drake sim-servo --robot
so101` (the SO-101's six STS3215 on a pseudo-terminal, Feetech's protocol, the arm's
physics behind every ID) and `hrp2-drake record --port`, `identify`, `control --port`,
which talk to it through Feetech's own client, scservo_sdk.

The emulator runs in lock step (its clock is the bus traffic), so what these tests
assert does not depend on the machine's speed."""

import subprocess

import numpy as np
import pytest
from bus_helpers import CLI, SimServo, control, motor_model, report

from hrp2_drake.assembly.builders import torque_chain_parts
from hrp2_drake.assembly.robot_control import load_on_robot
from hrp2_drake.control.fused import FusedController
from hrp2_drake.description import load_robot_description
from hrp2_drake.hardware.in_process import run_on_bus_in_process
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.robot.ground_truth import true_motor_model
from hrp2_drake.robot.station import StationConfig
from hrp2_drake.tools.control import ControlConfig, control_reference

ROBOT = "so101"


@pytest.mark.slow
def test_control_on_the_feetech_bus_equals_the_fused_controller_in_process(tmp_path):
    """Through scservo_sdk, the pseudo-terminal and the emulated STS3215s, the loop
    computes what the fused controller computes in process with the same bus timing
    (positions and goals cross the wire as whole pulses, sign-magnitude)."""
    model_path = motor_model(tmp_path, ROBOT)
    servo = SimServo(ROBOT)
    try:
        done = control(tmp_path, ROBOT, servo.port, model_path, 1.0)
    finally:
        servo.stop()
    assert done.returncode == 0, done.stderr[-3000:]
    result = report(tmp_path)
    assert result["fault"] == "" and result["torque_share"] == 1.0
    config, _ = load_on_robot(ControlConfig, load_robot_description(ROBOT))
    config.robot, config.duration = ROBOT, 1.0
    description = config.description()
    reference = control_reference(config)
    controller = FusedController(
        torque_chain_parts(
            description,
            reference,
            MotorModel.load(model_path),
            config.torque_control_at_period(),
            period=config.period(),
        )
    )
    station = StationConfig(robot=ROBOT, scenario="fixed_base")
    direct = run_on_bus_in_process(station, controller, reference, result["ticks"])
    signals = np.load(tmp_path / "control" / "control.npz")
    q_cmd = np.array([q for q, _ in direct])
    np.testing.assert_allclose(signals["q_cmd"], q_cmd, rtol=0, atol=1e-9)
    assert np.abs(signals["q_cmd"] - signals["q_ref"]).max() > 1e-3


@pytest.mark.slow
@pytest.mark.parametrize(
    "fault, expected",
    [
        (
            "silent:3@1.0",
            "servo ID 3 (elbow_flex): no status in 3 periods in a row",
        ),
        (
            "hardware:2@1.0:overload",
            "servo ID 2 (shoulder_lift): hardware error: overload",
        ),
        (
            "crc:5@1.0x20",
            "servo ID 5 (wrist_roll): a corrupt status in 3 periods in a row",
        ),
    ],
)
def test_a_feetech_bus_fault_ramps_with_a_report_and_one_line(
    tmp_path, fault, expected
):
    model = motor_model(tmp_path, ROBOT)
    servo = SimServo(ROBOT, "--fault", fault)
    try:
        done = control(tmp_path, ROBOT, servo.port, model, 2.0)
    finally:
        servo.stop()
    assert done.returncode == 1, done.stderr[-3000:]
    last = done.stderr.strip().splitlines()[-1]
    assert expected in last, done.stderr[-2000:]
    result = report(tmp_path)
    assert expected in result["fault"] and result["ramped"]
    assert 1.0 <= result["fault_time"] < 1.1
    text = (tmp_path / "control" / "control.md").read_text()
    assert expected in text and "servos' own position loop holds the robot" in text
    # Counted per servo: the first servo with a count is the one named (a silent
    # servo silences the ones after it in a sync read: they count too).
    servos = result["link"]["servos"]
    faulty = next(i for i, s in servos.items() if any(s.values()))
    assert f"servo ID {faulty} " in expected


@pytest.mark.slow
def test_the_port_gone_and_a_wrong_id_are_one_line(tmp_path):
    model = motor_model(tmp_path, ROBOT)
    servo = SimServo(ROBOT, "--fault", "close@0.5")
    try:
        done = control(tmp_path, ROBOT, servo.port, model, 2.0)
    finally:
        servo.stop()
    assert done.returncode == 1, done.stderr[-3000:]
    assert "the bus is gone" in done.stderr.strip().splitlines()[-1]
    assert "Traceback" not in done.stderr
    servo = SimServo(ROBOT, "--ids", "1,2,3,4,5,7")
    try:
        done = control(tmp_path, ROBOT, servo.port, model, 1.0)
    finally:
        servo.stop()
    assert done.returncode == 2, done.stderr[-2000:]
    last = done.stderr.strip().splitlines()[-1]
    assert "servo ID 6 (gripper): no answer to PING" in last
    assert "Traceback" not in done.stderr


def _run(*args: str, timeout: float = 900) -> subprocess.CompletedProcess:
    return subprocess.run(
        CLI + list(args), capture_output=True, text=True, timeout=timeout
    )


@pytest.mark.slow
def test_record_identify_control_on_the_emulated_so101(tmp_path):
    """An SO-101 owner's path, on the emulated arm: record the identification
    excitation at two P coefficients (16: LeRobot's; 32: the factory's) through the
    bus, identify a motor model from those logs, calibrate the digital twin on them
    (2 rollouts: the command's path, not its optimum), torque-control the arm with
    the model."""
    servo = SimServo(ROBOT)
    try:
        recorded = _run(
            "record", "--robot", ROBOT, "--port", servo.port, "--lockstep",
            "--gain", "16", "--gain", "32", "--out", str(tmp_path / "record"),
        )  # fmt: skip
        assert recorded.returncode == 0, recorded.stderr[-3000:]
        logs = sorted((tmp_path / "record").glob("so101_kp*.csv"))
        assert [log.name for log in logs] == ["so101_kp16.csv", "so101_kp32.csv"]
        identified = _run(
            "identify", "--robot", ROBOT, "--log", *map(str, logs),
            "--fit", "least-squares", "--out", str(tmp_path / "identify"),
        )  # fmt: skip
        assert identified.returncode == 0, identified.stderr[-3000:]
        model = MotorModel.load(tmp_path / "identify" / "motor_model.yaml")
        truth = true_motor_model(load_robot_description(ROBOT))
        k_tau = model.at_gain(32).k_tau
        np.testing.assert_allclose(k_tau, truth.k_tau, rtol=0.1)
        calibrated = _run(
            "calibrate", "--robot", ROBOT, "--log", *map(str, logs),
            "--max-iterations", "2", "--out", str(tmp_path / "calibrate"),
        )  # fmt: skip
        assert calibrated.returncode == 0, calibrated.stderr[-3000:]
        assert (tmp_path / "calibrate" / "servo.yaml").exists()
        done = control(
            tmp_path, ROBOT, servo.port, tmp_path / "identify" / "motor_model.yaml", 2.0
        )
    finally:
        servo.stop()
    assert done.returncode == 0, done.stderr[-3000:]
    result = report(tmp_path)
    assert result["torque_share"] >= 0.99 and result["fault"] == ""
    assert not any(any(s.values()) for s in result["link"]["servos"].values())


@pytest.mark.slow
def test_a_push_force_over_the_bus_equals_the_in_process_push(tmp_path):
    """`sim-servo --fault push-force:...` and `run_on_bus_in_process`'s `on_period`
    push the arm alike: `control --port` (gravity compensation, K6 = 0) computes
    what the fused controller computes in process with the same push from the same
    time (what scripts/so101_hand_guiding.py measures with)."""
    model_path = motor_model(tmp_path, ROBOT)
    config_file = tmp_path / "k6.yaml"
    config_file.write_text("torque_control:\n  controller:\n    k6: 0.0\n")
    servo = SimServo(ROBOT, "--fault", "push-force:gripper_frame_link@1.2:0,0.1,0.2")
    try:
        done = control(
            tmp_path,
            ROBOT,
            servo.port,
            model_path,
            2.0,
            "--motion",
            "hold",
            "--config",
            str(config_file),
        )
    finally:
        servo.stop()
    assert done.returncode == 0, done.stderr[-3000:]
    result = report(tmp_path)
    config, _ = load_on_robot(ControlConfig, load_robot_description(ROBOT))
    config.robot, config.duration, config.motion = ROBOT, 2.0, "hold"
    config.torque_control.controller.k6 = 0.0
    reference = control_reference(config)
    controller = FusedController(
        torque_chain_parts(
            config.description(),
            reference,
            MotorModel.load(model_path),
            config.torque_control_at_period(),
            period=config.period(),
        )
    )

    def push(servos, t):
        if t >= 1.2:
            servos.set_external_force("gripper_frame_link", [0.0, 0.1, 0.2])

    station = StationConfig(robot=ROBOT, scenario="fixed_base")
    direct = run_on_bus_in_process(
        station, controller, reference, result["ticks"], on_period=push
    )
    signals = np.load(tmp_path / "control" / "control.npz")
    q_cmd = np.array([q for q, _ in direct])
    np.testing.assert_allclose(signals["q_cmd"], q_cmd, rtol=0, atol=1e-9)
    moved = signals["q_cmd"][-1] - signals["q_cmd"][int(1.2 / config.period())]
    assert np.abs(moved).max() > 0.01  # the push moved the arm
