"""A robot's own torque-control settings (`RobotDescription.control_file`,
hrp2_drake/assembly/robot_control.py): `hrp2-drake control` and `track` start from them.

- The XL330 pendulum ships K_p = 1 (models/xl330_pendulum/control.yaml): its commands
  run with it without --config; HRP-2 (no file) keeps the paper's K_p = 2.
- The order: the command's defaults < the robot's file < the user's --config < the
  options. A --config key wins; a key it leaves out keeps the robot's value.
- A bad robot file is one line naming the file and the key, before anything runs.

The runs are replaced by a capture of what the command would run with: nothing here
simulates or talks to a robot.
"""

import shutil
from pathlib import Path

import pytest
from cli_errors import refused

import hrp2_drake
from hrp2_drake.assembly.robot_control import (
    TorqueControlSources,
    load_on_robot,
    robot_torque_control,
)
from hrp2_drake.assembly.torque_control import TorqueControlConfig
from hrp2_drake.cli import main
from hrp2_drake.description import load_robot_description
from hrp2_drake.tools.control import ControlConfig
from hrp2_drake.tools.track import TrackConfig

MODELS = Path(hrp2_drake.__file__).resolve().parents[1] / "models"
XL330 = "xl330_pendulum"
RIGHT_LEG = [f"RLEG_JOINT{k}" for k in range(6)]


def motor_model(joints: list[str]) -> str:
    n = len(joints)
    return (
        f"joint_names: [{', '.join(joints)}]\nk_tau: [{', '.join(['1e-4'] * n)}]\n"
        f"k_v: [{', '.join(['1e-2'] * n)}]\n"
    )


@pytest.fixture
def captured(monkeypatch):
    """What `track` and `control` would run with: {"config": ..., "sources": ...}
    (their runs replaced by a capture)."""
    from hrp2_drake.tools import control, track

    seen = {}

    def run_track(config, motor_model, out, sources=None):
        seen.update(command="track", config=config, sources=sources)
        return {"tracking": {}}

    def run_control(config, motor_model, out, sources=None, **link):
        seen.update(command="control", config=config, sources=sources)
        raise ValueError("captured")  # the CLI's one line: no summary to print

    monkeypatch.setattr(track, "run_track", run_track)
    monkeypatch.setattr(control, "run_control", run_control)
    return seen


def run(tmp_path, command: str, robot: str | None, *options: str, joints=None):
    """`hrp2-drake <command>` on `robot` (None: the default) with a motor model of
    `joints` (default: the robot's controlled joints), link options for control."""
    spec = robot or "hrp2"
    joints = joints or load_robot_description(spec).controlled_joints
    (tmp_path / "motor.yaml").write_text(motor_model(joints))
    argv = [command, "--motor-model", str(tmp_path / "motor.yaml")]
    argv += ["--robot", robot] if robot else []
    if command == "control":
        argv += ["--lcm", "memq://"]
    return main(argv + list(options) + ["--out", str(tmp_path / "out")])


@pytest.mark.parametrize("command", ["track", "control"])
def test_the_xl330_runs_with_its_own_kp_1_without_config(tmp_path, captured, command):
    run(tmp_path, command, XL330)
    assert captured["command"] == command
    control = captured["config"].torque_control
    assert control.controller.kp == [1.0]
    # The rest stays the command's own defaults.
    defaults = {"track": TrackConfig, "control": ControlConfig}[command]()
    assert control.estimator == defaults.torque_control.estimator
    assert control.supervisor == defaults.torque_control.supervisor
    sources = captured["sources"]
    assert Path(sources.robot_file) == MODELS / XL330 / "control.yaml"
    assert sources.user_file == ""


@pytest.mark.parametrize("command", ["track", "control"])
def test_hrp2_keeps_the_papers_kp_2(tmp_path, captured, command):
    run(tmp_path, command, None if command == "control" else "hrp2")
    assert captured["config"].torque_control.controller.kp == [2.0]
    assert captured["sources"] == TorqueControlSources()
    assert load_robot_description("hrp2").control_path() is None


def test_a_config_key_wins_and_the_others_keep_the_robots(tmp_path, captured):
    config = tmp_path / "mine.yaml"
    config.write_text("torque_control:\n  controller:\n    k6: 0.5\nduration: 2.0\n")
    run(tmp_path, "control", XL330, "--config", str(config), "--motion", "hold")
    result = captured["config"]
    # The user's key, the robot's key, the command's default, the option.
    assert result.torque_control.controller.k6 == 0.5
    assert result.torque_control.controller.kp == [1.0]
    assert result.torque_control.estimator.window == 41  # ControlConfig's own
    assert (result.duration, result.motion) == (2.0, "hold")
    assert captured["sources"].user_file == str(config)

    config.write_text("torque_control:\n  controller:\n    kp: [2.0]\n")
    run(tmp_path, "track", XL330, "--config", str(config))
    assert captured["config"].torque_control.controller.kp == [2.0]


def test_a_config_without_torque_control_is_not_named(tmp_path, captured):
    config = tmp_path / "mine.yaml"
    config.write_text("duration: 1.0\nk6: [1.0]\n")
    run(tmp_path, "track", XL330, "--config", str(config))
    assert captured["config"].torque_control.controller.kp == [1.0]
    assert captured["config"].duration == 1.0
    assert captured["sources"].user_file == ""


def test_the_robot_in_the_config_file_picks_its_control_file(tmp_path, captured):
    """No --robot: the --config's robot (control: `robot`; track: `station.robot`)."""
    config = tmp_path / "mine.yaml"
    config.write_text(f"robot: {XL330}\n")
    run(tmp_path, "control", None, "--config", str(config), joints=["servo"])
    assert captured["config"].torque_control.controller.kp == [1.0]
    config.write_text(f"station: {{robot: {XL330}, scenario: fixed_base}}\n")
    run(tmp_path, "track", None, "--config", str(config), joints=["servo"])
    assert captured["config"].torque_control.controller.kp == [1.0]


def test_load_on_robot_without_a_command():
    robot = load_robot_description(XL330)
    config, sources = load_on_robot(TrackConfig, robot)
    assert config.torque_control.controller.kp == [1.0]
    assert config.torque_control.estimator.offset_calibration_time == 0.3  # track's
    assert sources.robot_file and not sources.user_file
    # The defaults given are not changed.
    defaults = TorqueControlConfig()
    assert robot_torque_control(robot, defaults).controller.kp == [1.0]
    assert defaults.controller.kp == [2.0]
    for name in ("hrp2", "iiwa14", "open_manipulator_x"):
        other = load_robot_description(name)
        assert robot_torque_control(other, defaults) == defaults


def test_the_report_names_where_the_settings_came_from():
    control = TorqueControlConfig()
    control.controller.kp = [1.0]
    robot_file = str(MODELS / XL330 / "control.yaml")
    line = TorqueControlSources(robot_file, "/elsewhere/mine.yaml").markdown(control)
    assert "the command's defaults, then the robot's control file" in line
    assert "control.yaml`, then --config `/elsewhere/mine.yaml`" in line
    assert "K_p = 1," in line
    alone = TorqueControlSources().markdown(TorqueControlConfig())
    assert alone.startswith("**Torque-control settings:** the command's defaults: ")
    assert "K_p = 2," in alone


# ------------------------------------------------ a bad robot control file
def robot_with_control(tmp_path: Path, text: str, name: str = "control.yaml") -> Path:
    """A copy of the XL330's description (no logs) whose control file holds `text`."""
    folder = tmp_path / "robot"
    shutil.copytree(MODELS / XL330, folder, ignore=shutil.ignore_patterns("logs"))
    (folder / "control.yaml").unlink()
    if text is not None:
        (folder / name).write_text(text)
    return folder / "robot.yaml"


@pytest.mark.parametrize(
    "text, culprits",
    [
        pytest.param(
            "torque_control:\n  controller:\n    kq: [1.0]\n",
            ["'torque_control.controller.kq'", "known in torque_control.controller"],
            id="unknown key",
        ),
        pytest.param(
            "torque_control:\n  controller:\n    kp: fast\n",
            ["torque_control.controller.kp: expected a list"],
            id="wrong type",
        ),
        pytest.param(
            "torque_control:\n  controller:\n    kp: [-1.0]\n",
            ["TorqueControlConfig.controller.kp: [-1.0]", ">= 0"],
            id="negative gain",
        ),
        pytest.param(
            "torque_control:\n  controller:\n    kp: [1.0, 2.0]\n",
            ["torque_control.controller.kp: 2 values, expected one or 1"],
            id="a gain per joint of another robot",
        ),
        pytest.param(
            "torque_control:\n  estimator:\n    windows: {RLEG_JOINT0: 21}\n",
            ["torque_control.estimator.windows: ['RLEG_JOINT0']"],
            id="another robot's joint",
        ),
        pytest.param(
            "torque_control:\n  supervisor:\n    period: 0.002\n",
            ["'period' moved to", "sensors.period"],
            id="the supervisor at another rate",
        ),
        pytest.param(
            "torque_control:\n  controller: [kp: 1.0\n",
            ["invalid YAML at line 3"],
            id="syntax",
        ),
    ],
)
@pytest.mark.parametrize("command", ["track", "control"])
def test_a_bad_robot_control_file_is_one_line(
    tmp_path, capsys, captured, command, text, culprits
):
    robot = robot_with_control(tmp_path, text)
    (tmp_path / "motor.yaml").write_text(motor_model(["servo"]))
    argv = [
        command,
        "--robot",
        str(robot),
        "--motor-model",
        str(tmp_path / "motor.yaml"),
    ]
    argv += ["--lcm", "memq://"] if command == "control" else []
    line = refused(
        capsys,
        argv + ["--out", str(tmp_path / "out")],
        str(robot.parent / "control.yaml"),
        *culprits,
    )
    assert "config" not in captured, line  # refused before running


def test_a_control_file_that_is_not_there_names_the_description(tmp_path, capsys):
    robot = robot_with_control(tmp_path, None)
    (tmp_path / "motor.yaml").write_text(motor_model(["servo"]))
    argv = ["control", "--robot", str(robot), "--lcm", "memq://"]
    argv += ["--motor-model", str(tmp_path / "motor.yaml")]
    refused(
        capsys,
        argv + ["--out", str(tmp_path / "out")],
        f"{robot}: control_file:",
        "control.yaml' not found",
    )
