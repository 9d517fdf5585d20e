"""RobotDescription: HRP-2's and the iiwa's descriptions, and every bad description
gets one error that names the field."""

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hrp2_drake.cli import main
from hrp2_drake.control.balance import BalanceConfig
from hrp2_drake.control.safety import (
    SafetyConfig,
    SafetySupervisorStep,
    supervisor_sensors,
    with_sensor_ranges,
)
from hrp2_drake.description import load_robot_description, robot_file
from hrp2_drake.description.sensors import SensorsConfig
from hrp2_drake.paper import hrp2
from hrp2_drake.robot.station import StationConfig, make_station, sensor_sizes
from hrp2_drake.tools.simulate import SimulateConfig, run_simulate

MODELS = Path(__file__).resolve().parents[1] / "models"


def test_hrp2_description_is_the_model_modules_names():
    robot = load_robot_description()
    assert robot.name == "hrp2" and robot.base == "floating"
    assert tuple(robot.joints) == hrp2.JOINT_NAMES and len(robot.joints) == 30
    assert tuple(robot.controlled_joints) == hrp2.RIGHT_LEG
    assert robot.sensor_names() == list(hrp2.FT_SENSORS)
    np.testing.assert_array_equal(robot.home_positions(), robot.load_trajectory()[1][0])
    station = make_station(StationConfig(scenario="fixed_base"))
    for name in sensor_sizes(robot):
        assert station.HasOutputPort(name)


def test_iiwa_description_fixed_base_without_imu():
    iiwa = load_robot_description("iiwa14")
    assert robot_file("iiwa14") == (MODELS / "iiwa14" / "robot.yaml").resolve()
    assert iiwa.base == "fixed" and not iiwa.has_imu()
    plant = iiwa.make_plant()
    assert plant.num_velocities() == 7 and plant.num_actuators() == 7
    station = make_station(StationConfig(robot="iiwa14", scenario="fixed_base"))
    assert not station.HasOutputPort("imu_linear_acceleration")
    assert list(sensor_sizes(iiwa)) == ["q_measured", "wrench_wrist"]
    with pytest.raises(ValueError, match="fixed-base: only 'fixed_base'"):
        StationConfig(robot="iiwa14", scenario="hanging").validate()


def _write(tmp_path: Path, source: str, edit) -> Path:
    """A copy of models/<source>/robot.yaml with `edit` applied to its text, its model
    file given by absolute path."""
    folder = MODELS / source
    text = (folder / "robot.yaml").read_text()
    for key in ("model_file", "trajectory_file", "servo_file", "control_file"):
        text = re.sub(
            rf"^{key}: (\S+)",
            lambda m, key=key: f"{key}: {folder / m.group(1)}",
            text,
            flags=re.M,
        )
    path = tmp_path / "robot.yaml"
    path.write_text(edit(text))
    return path


@pytest.mark.parametrize(
    "source, old, new, message",
    [
        (
            "iiwa14",
            "frame: ft_sensor_link",
            "frame: no_such_frame",
            r"force_torque_sensors\.wrist\.frame: no frame 'no_such_frame'",
        ),
        # The body above the sensor's weld: not "beyond" its frame.
        (
            "iiwa14",
            "body: ft_sensor_link",
            "body: iiwa_link_7",
            r"force_torque_sensors\.wrist\.body: 'iiwa_link_7' is above its frame",
        ),
        (
            "iiwa14",
            "iiwa_joint_1",
            "iiwa_joint_0",  # everywhere: a joint the model lacks
            r"joints\[0\]: no joint 'iiwa_joint_0'",
        ),
        (
            "iiwa14",
            "controlled_joints: [iiwa_joint_1,",
            "controlled_joints: [elbow,",
            r"controlled_joints: \['elbow'\] are not in joints",
        ),
        (
            "hrp2",
            "imu_frame: imu",
            "imu_frame: r_sole",
            r"imu_frame: 'r_sole' is below F/T sensor 'right_foot'",
        ),
        (
            "hrp2",
            "imu_frame: imu ",
            "imu_frame: '' ",
            r"imu_frame: empty, but a floating-base robot needs an IMU",
        ),
        (
            "hrp2",
            "climbing32.pos.gz",
            "missing.pos.gz",
            r"trajectory_file: '.*missing.pos.gz' not found",
        ),
        (
            "iiwa14",
            "base_body: base",
            "base_body: basis",
            r"base_body: no body 'basis'",
        ),
        (
            "iiwa14",
            "tool_frame: tool_tip",
            "tool_frame: tip",
            r"tool_frame: no frame 'tip'",
        ),
        (
            "iiwa14",
            "force_sensor: wrist",
            "force_sensor: elbow",
            r"force_sensor: 'elbow' is not one of",
        ),
        ("iiwa14", "name: iiwa14", "nam: iiwa14", r"unknown key\(s\) \['nam'\]"),
        (
            "iiwa14",
            "initial_positions: [0.0, 0.2691,",
            "initial_positions: [0.2691,",
            r"initial_positions: 6 values for 7 joints",
        ),
        (
            "iiwa14",
            "{joint: iiwa_joint_7,",
            "{joint: iiwa_joint_8,",
            r"identification\.sinusoids\[6\]\.joint: 'iiwa_joint_8' is not in joints",
        ),
        (
            "hrp2",
            "RLEG_JOINT5: [0.240, 6.0]",
            "RLEG_JOINT9: [0.240, 6.0]",
            r"published_motor_model: 'RLEG_JOINT9' is not in joints",
        ),
        (
            "hrp2",
            "RLEG_JOINT5: [0.240, 6.0]",
            "RLEG_JOINT5: [0.240]",
            r"published_motor_model\.RLEG_JOINT5: expected \[10³ Kτ, 10³ Kv\]",
        ),
        ("hrp2", "force: 2000.0", "force: -1.0", r"sensor_ranges\.force: must be"),
        (
            "hrp2",
            "  friction: 0.3",
            "  friction: 1.5",
            r"balance\.friction: 1\.5 exceeds contacts\.friction 1\.0",
        ),
        ("hrp2", "com_kp: 150.0", "com_kp: -3.0", r"balance\.com_kp: must be finite"),
    ],
)
def test_bad_description_names_the_field(tmp_path, source, old, new, message):
    count = -1 if old == "iiwa_joint_1" else 1
    path = _write(tmp_path, source, lambda text: text.replace(old, new, count))
    with pytest.raises(ValueError, match=message) as error:
        load_robot_description(path)
    assert str(path) in str(error.value)


@pytest.mark.parametrize(
    "name", sorted(p.parent.name for p in MODELS.glob("*/robot.yaml"))
)
def test_every_robot_loads_with_the_limits_its_controllers_need(name):
    """Every robot of models/ loads; its supervisor's ranges are all its own (the
    sensors it monitors have a range in its description), and a robot with soles
    gives its balance QP a friction, a least corner force and CoM gains."""
    robot = load_robot_description(name)
    monitored = supervisor_sensors(robot.sensor_names(), imu=robot.has_imu())
    config = with_sensor_ranges(SafetyConfig(), monitored, robot.sensor_ranges)
    SafetySupervisorStep(len(robot.joints), monitored, config, robot.sensors.period)
    if robot.contacts.soles:
        assert not BalanceConfig().for_robot(robot.balance).unset()


def test_ft_sensor_needs_a_fixed_joint_when_loaded(tmp_path):
    # The wrist link hangs from a revolute joint: no reaction force reads an F/T.
    # The description refuses it when it is loaded, naming the file and the field.
    path = _write(
        tmp_path,
        "iiwa14",
        lambda t: t.replace("frame: ft_sensor_link", "frame: iiwa_link_7", 1).replace(
            "body: ft_sensor_link", "body: iiwa_link_7", 1
        ),
    )
    message = r"force_torque_sensors\.wrist\.body: 'iiwa_link_7' hangs from revolute"
    with pytest.raises(ValueError, match=message) as error:
        load_robot_description(path)
    assert str(error.value).startswith(f"{path}: ")
    with pytest.raises(ValueError, match=message):
        make_station(StationConfig(robot=str(path), scenario="fixed_base"))


def test_cli_bad_robot_is_one_line(tmp_path, capsys):
    assert main(["simulate", "--robot", "no_such_robot", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no_such_robot" in err[0] and "iiwa14" in err[0]
    path = _write(
        tmp_path, "iiwa14", lambda t: t.replace("frame: ft_sensor_link", "frame: x", 1)
    )
    assert (
        main(
            ["estimate", "--robot", str(path), "--log", "x.npz", "--out", str(tmp_path)]
        )
        == 2
    )
    assert "force_torque_sensors.wrist.frame" in capsys.readouterr().err


def test_offline_estimate_of_a_fixed_arm_log(tmp_path):
    """`simulate` then `estimate` on the arm (noiseless sensors, holding its pose
    against gravity): τ̂ from the log matches the servo's torques."""
    from hrp2_drake.tools.estimate import run_estimate

    config = SimulateConfig(
        station=StationConfig(
            robot="iiwa14", scenario="fixed_base", sensors=SensorsConfig.noiseless()
        ),
        duration=1.0,
    )
    signals = run_simulate(config).signals
    log = tmp_path / "arm.npz"
    np.savez(log, **signals)
    summary = run_estimate(config.station.description(), log, tmp_path, window=41)
    assert set(summary["rms_error_vs_truth"]) == set(
        config.station.description().joints
    )
    estimate = np.load(tmp_path / "estimate.npz")
    settled = (estimate["t"] >= 0.3) & (estimate["t"] < 0.96)  # after the servo's sag
    error = estimate["tau"][settled] - signals["joint_torque_true"][settled]
    # Measured: RMS 0.003-0.02 N·m (gravity torques up to 48 N·m): the encoders'
    # quantization through the window; the start-up sag itself is 4-7 N·m RMS.
    assert np.sqrt(np.mean(error**2, axis=0)).max() < 0.05
    assert (tmp_path / "estimate_torques.png").is_file()
    assert (
        (tmp_path / "estimate.md").read_text().startswith("# Offline torque estimation")
    )


def test_generic_layers_import_no_robot_and_no_experiment():
    """estimation, identification and control import nothing from robot or
    experiments, directly or through another module (the robot description, the
    bottom layer, they may)."""
    packages = ("estimation", "identification", "control")
    root = Path(__file__).resolve().parents[1] / "hrp2_drake"
    modules = [
        f"hrp2_drake.{p}.{f.stem}"
        for p in packages
        for f in sorted((root / p).glob("*.py"))
    ]
    code = (
        "import sys\n"
        f"for m in {modules!r}: __import__(m)\n"
        "bad = [m for m in sys.modules if m.startswith(('hrp2_drake.robot', "
        "'hrp2_drake.experiments'))]\n"
        "print(bad)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == "[]", out.stdout
