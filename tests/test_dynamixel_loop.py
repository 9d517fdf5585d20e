"""The whole Dynamixel path with the processes separate: `hrp2-drake sim-servo` (the
robot's servos on a pseudo-terminal, Protocol 2.0, its physics behind every ID) and
`hrp2-drake control --port` / `record --port`, which talk to it through
dynamixel-sdk, ROBOTIS' own client.

The emulator runs in lock step (its clock is the bus traffic: one period per sync
read), so that what these tests assert does not depend on the machine's speed: the
bus loop equals the fused controller in process with the same bus timing, and every
bus fault ends in a ramp where the bus still works, a report and one line."""

import subprocess
import sys
import time

import numpy as np
import pytest
from bus_helpers import SimServo, control, motor_model, report

from hrp2_drake.assembly.builders import torque_chain_parts
from hrp2_drake.assembly.robot_control import load_on_robot
from hrp2_drake.control.fused import FusedController
from hrp2_drake.description import load_robot_description
from hrp2_drake.hardware.in_process import run_on_bus_in_process
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.robot.ground_truth import true_motor_model
from hrp2_drake.robot.station import StationConfig
from hrp2_drake.tools.control import ControlConfig, control_reference

CLI = [sys.executable, "-m", "hrp2_drake.cli"]
_motor_model, _control, _report = motor_model, control, report


@pytest.mark.slow
def test_control_on_the_bus_equals_the_fused_controller_in_process(tmp_path):
    """Through dynamixel-sdk, the pseudo-terminal and the emulated servos, the loop
    computes what the fused controller computes in process on the same robot with
    the same bus timing: samples at k·T, the command in the servos at k·T +
    read_to_write, positions and goals in whole pulses. Tolerance 1e-9 rad: the
    numbers cross the wire as integers (pulses) both ways, so they are the same
    numbers; 1e-9 leaves room for nothing but a float printed by the motor model's
    YAML file, which both sides read."""
    robot = "xl330_pendulum"
    model_path = _motor_model(tmp_path, robot)
    servo = SimServo(robot)
    try:
        done = _control(tmp_path, robot, servo.port, model_path, 1.5)
    finally:
        servo.stop()
    assert done.returncode == 0, done.stderr[-3000:]
    report = _report(tmp_path)
    assert report["fault"] == "" and report["ramped"] and report["approach_s"] == 0.0
    signals = np.load(tmp_path / "control" / "control.npz")

    # The command's settings: its defaults under the robot's control file (K_p = 1).
    assert report["torque_control_from"]["robot_file"].endswith("control.yaml")
    config, _ = load_on_robot(ControlConfig, load_robot_description(robot))
    config.robot, config.duration = robot, 1.5
    description = config.description()
    motor_model = MotorModel.load(model_path)
    if motor_model.gain:
        motor_model = motor_model.at_gain(description.position_loop.gain)
    reference = control_reference(config)
    controller = FusedController(
        torque_chain_parts(
            description,
            reference,
            motor_model,
            config.torque_control_at_period(),
            period=config.period(),
        )
    )
    ticks = report["ticks"]
    station = StationConfig(robot=robot, scenario="fixed_base")
    direct = run_on_bus_in_process(station, controller, reference, ticks)
    q_cmd = np.array([q for q, _ in direct])
    np.testing.assert_allclose(signals["q_cmd"], q_cmd, rtol=0, atol=1e-9)
    # Not a trivial run: torque control drove the servo, away from the reference.
    assert report["torque_share"] == 1.0
    assert np.abs(signals["q_cmd"] - signals["q_ref"]).max() > 1e-3


@pytest.fixture
def arm(tmp_path):
    """The OpenMANIPULATOR-X (4 servos on one bus) and its motor model."""
    return "open_manipulator_x", _motor_model(tmp_path, "open_manipulator_x")


@pytest.mark.slow
@pytest.mark.parametrize(
    "fault, expected",
    [
        ("silent:12@1.0", "servo ID 12 (joint2): no status in 3 periods in a row"),
        ("hardware:13@1.0:overload", "servo ID 13 (joint3): hardware error: overload"),
        (
            "crc:11@1.0x20",
            "servo ID 11 (joint1): a corrupt status in 3 periods in a row",
        ),
    ],
)
def test_a_bus_fault_ramps_where_the_bus_works_with_a_report_and_one_line(
    tmp_path, arm, fault, expected
):
    robot, model = arm
    servo = SimServo(robot, "--fault", fault, out=tmp_path / "servo")
    try:
        done = _control(tmp_path, robot, servo.port, model, 3.0)
    finally:
        servo.stop()
    assert done.returncode == 1, done.stderr[-3000:]
    last = done.stderr.strip().splitlines()[-1]
    assert expected in last and last.count("\n") == 0, done.stderr[-2000:]
    report = _report(tmp_path)
    assert expected in report["fault"] and report["ramped"]
    assert 1.0 <= report["fault_time"] < 1.2
    text = (tmp_path / "control" / "control.md").read_text()
    assert expected in text and "servos' own position loop holds the robot" in text
    # The servos the bus still reached took the ramp: their goal ended at the
    # measured pose.
    signals = np.load(tmp_path / "control" / "control.npz")
    assert len(signals["t"]) == report["ticks"]


@pytest.mark.slow
def test_the_emulator_killed_ends_the_run_with_a_report_and_one_line(tmp_path, arm):
    robot, model = arm
    servo = SimServo(robot)
    control = subprocess.Popen(
        CLI
        + [
            "control",
            "--robot",
            robot,
            "--port",
            servo.port,
            "--lockstep",
            "--motor-model",
            str(model),
            "--duration",
            "60",
            "--out",
            str(tmp_path / "control"),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not (tmp_path / "started").exists():
            line = control.stderr.readline()
            if "control: running" in line:
                break
        time.sleep(1.0)
        servo.kill()
        _, err = control.communicate(timeout=120)
    finally:
        if control.poll() is None:
            control.kill()
    assert control.returncode == 1, err[-2000:]
    assert "the bus is gone" in err.strip().splitlines()[-1]
    report = _report(tmp_path)
    assert "the bus is gone" in report["fault"] and not report["ramped"]
    assert (
        "the servos hold their last goal position"
        in (tmp_path / "control" / "control.md").read_text()
    )


@pytest.mark.slow
@pytest.mark.parametrize(
    "options, expected",
    [
        (["--ids", "11,12,13,15"], "servo ID 14 (joint4): no answer to PING"),
        (
            ["--fault", "wrong_model:12:XL330-M288"],
            "servo ID 12 (joint2): model number 1200 (XL330-M288), but the description "
            "says XM430-W350 (1020)",
        ),
    ],
)
def test_a_wrong_bus_at_start_up_is_one_line(tmp_path, arm, options, expected):
    robot, model = arm
    servo = SimServo(robot, *options)
    try:
        done = _control(tmp_path, robot, servo.port, model, 1.0)
    finally:
        servo.stop()
    assert done.returncode == 2, done.stderr[-2000:]
    lines = done.stderr.strip().splitlines()
    assert expected in lines[-1] and "Traceback" not in done.stderr


@pytest.mark.slow
def test_record_identify_calibrate_control_on_the_emulated_xl330(tmp_path):
    """A user's path on a real servo, on the emulated one: record the identification
    excitation at two gains through the bus, identify a motor model from those logs,
    then torque-control the servo with it."""
    robot = "xl330_pendulum"
    servo = SimServo(robot)
    try:
        recorded = subprocess.run(
            CLI
            + [
                "record",
                "--robot",
                robot,
                "--port",
                servo.port,
                "--lockstep",
                "--gain",
                "100",
                "--gain",
                "400",
                "--out",
                str(tmp_path / "record"),
            ],
            capture_output=True,
            text=True,
            timeout=900,
        )
        assert recorded.returncode == 0, recorded.stderr[-3000:]
        logs = sorted((tmp_path / "record").glob("xl330_pendulum_kp*.json"))
        assert [log.name for log in logs] == [
            "xl330_pendulum_kp100.json",
            "xl330_pendulum_kp400.json",
        ]
        identified = subprocess.run(
            CLI
            + [
                "identify",
                "--robot",
                robot,
                "--log",
                *map(str, logs),
                "--fit",
                "least-squares",
                "--out",
                str(tmp_path / "identify"),
            ],
            capture_output=True,
            text=True,
            timeout=900,
        )
        assert identified.returncode == 0, identified.stderr[-3000:]
        model = MotorModel.load(tmp_path / "identify" / "motor_model.yaml")
        # The twin's effective Kτ at its servo file's gain, 400 (ground truth, for
        # evaluation): the logs' within 25% (its dead zone, load friction and voltage
        # limit are not in the linear model).
        truth = true_motor_model(StationConfig(robot=robot).description())
        assert model.gain in (100, 400)
        k_tau = model.at_gain(400).k_tau[0]
        assert abs(k_tau / truth.k_tau[0] - 1) < 0.25, (k_tau, truth.k_tau)
        done = _control(
            tmp_path, robot, servo.port, tmp_path / "identify" / "motor_model.yaml", 1.5
        )
    finally:
        servo.stop()
    assert done.returncode == 0, done.stderr[-3000:]
    assert _report(tmp_path)["torque_share"] > 0.9
