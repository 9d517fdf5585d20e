"""A robot's own torque-control settings: the file its description names
(`RobotDescription.control_file`, e.g. models/xl330_pendulum/control.yaml), which
`hrp2-drake control` and `track` start from.

The file holds what a user's --config holds for the torque control, a
`torque_control:` mapping (`TorqueControlConfig`), stated like every setting at 1 kHz
(`at_period` states it at the robot's rate). A command's settings, each over the one
before (a key it sets wins, a key it leaves out keeps the value below):

1. the command's built-in defaults (`TrackConfig`, `ControlConfig`: the paper's);
2. the robot's control file (`robot_torque_control`);
3. the user's --config (`load_on_robot`);
4. the command's options.

The robot's file is checked on its own, where it is read: a bad key or value is one
line naming the file and the key (`models/r/control.yaml:
TorqueControlConfig.controller.kp: ...`). `TorqueControlSources` says where a run's
settings came from, for its report.
"""

import copy
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from hrp2_drake.assembly.torque_control import (
    TorqueControlConfig,
    check_for_robot,
)
from hrp2_drake.config import load_config, parse_yaml, read_yaml_text, validate_config
from hrp2_drake.description import RobotDescription

T = TypeVar("T")


@dataclass
class RobotControlFile:
    """A robot's control file (`RobotDescription.control_file`).

    Args:
        torque_control: the torque control's settings that work on the robot at its
            rate, over a command's defaults (stated at 1 kHz, as a --config's are).
    """

    torque_control: TorqueControlConfig = field(default_factory=TorqueControlConfig)

    def validate(self) -> None:
        self.torque_control.validate()


def robot_torque_control(
    robot: RobotDescription, defaults: TorqueControlConfig
) -> TorqueControlConfig:
    """`defaults` (a command's built-in torque control) with the robot's control file
    over them: a copy; `defaults` itself if the robot has none.

    Raises:
        ValueError: one line naming the file and the key: a syntax error, an unknown
            key, a wrong type, a value the settings refuse, settings that do not fit
            the robot (its joints, a `kp` per joint, the windows' signals).
    """
    path = robot.control_path()
    if path is None:
        return defaults
    source = str(path)
    loaded = load_config(
        RobotControlFile,
        filename=path,
        defaults=RobotControlFile(copy.deepcopy(defaults)),
        validate=False,
    )
    validate_config(loaded, source)
    control = loaded.torque_control
    where = f"{source}: torque_control"
    check_for_robot(control, robot, where)
    return control


@dataclass(frozen=True)
class TorqueControlSources:
    """Where a command's torque-control settings came from, over its defaults.

    Args:
        robot_file: the robot's control file ("": none).
        user_file: the user's --config, if it sets `torque_control` ("": it does not).
    """

    robot_file: str = ""
    user_file: str = ""

    def summary(self) -> dict:
        """For a run's JSON summary."""
        return dataclasses.asdict(self)

    def markdown(self, config: TorqueControlConfig) -> str:
        """One sentence for a report: the files, in order, and the gains they give."""
        layers = ["the command's defaults"]
        if self.robot_file:
            layers.append(f"the robot's control file `{_shown(self.robot_file)}`")
        if self.user_file:
            layers.append(f"--config `{_shown(self.user_file)}`")
        kp = ", ".join(f"{k:g}" for k in config.controller.kp)
        return (
            f"**Torque-control settings:** {', then '.join(layers)}"
            + (" (each over the one before)" if len(layers) > 1 else "")
            + f": K_p = {kp}, estimator window {config.estimator.window} samples at "
            "1 kHz."
        )


def _shown(path: str) -> str:
    """`path` relative to the working directory if it lies in it, else as given."""
    try:
        return str(Path(path).resolve().relative_to(Path.cwd()))
    except ValueError:
        return path


def load_on_robot(
    schema: type[T],
    robot: RobotDescription,
    filename: str | Path | None = None,
) -> tuple[T, TorqueControlSources]:
    """A command's config (`schema`: a config with a `torque_control` field) for
    `robot`: its defaults, the robot's control file over their `torque_control`
    (`robot_torque_control`), the user's file `filename` (a --config, or None) over
    both. Not validated: the command applies its options first.

    Returns:
        The config, and where its torque-control settings came from.
    """
    defaults: Any = schema()
    defaults.torque_control = robot_torque_control(robot, defaults.torque_control)
    config = (
        load_config(schema, filename=filename, defaults=defaults, validate=False)
        if filename
        else defaults
    )
    sets = filename and _sets_torque_control(filename)
    control = robot.control_path()
    return config, TorqueControlSources(
        str(control) if control else "", str(filename) if sets else ""
    )


def _sets_torque_control(filename: str | Path) -> bool:
    """Whether the YAML file `filename` sets a key of `torque_control`."""
    raw = parse_yaml(read_yaml_text(filename), str(filename))
    return isinstance(raw, dict) and bool(raw.get("torque_control"))
