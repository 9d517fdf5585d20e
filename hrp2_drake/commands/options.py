"""What every command shares: its options (the shared ones, their argparse types,
--debug) and how a command reads them: the --config file into its config, the
options over it, one validation, the --out folder; the --motor-model file (or one
identified first); the exit code of a run that talks to a robot.

A command is one module of this folder (`add(commands)` registers its parser,
`run(args)` runs it) that imports no other command: only this module.
"""

import argparse
import math
import os
from collections.abc import Callable
from pathlib import Path

from hrp2_drake import console
from hrp2_drake.config import (
    field_at,
    load_config,
    parse_yaml,
    read_yaml_text,
    validate_config,
)
from hrp2_drake.robot.station import SCENARIOS

# ------------------------------------------------------------------ the options


def number(kind: type, low: float | None = None, strict: bool = True):
    """An argparse type: a finite `kind` (float or int), > low (>= low if not
    strict)."""

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected {'an integer' if kind is int else 'a number'}, got '{text}'"
            ) from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"expected a finite number, got '{text}'")
        if low is not None and not (value > low if strict else value >= low):
            raise argparse.ArgumentTypeError(
                f"must be {'>' if strict else '>='} {low:g}, got '{text}'"
            )
        return value

    parse.__name__ = kind.__name__  # argparse names the type in its messages
    return parse


#: An argparse type: an integer >= 1 (a count of trials, workers, processes...).
COUNT = number(int, 1, strict=False)


#: The options several commands share, by name (`--motor-model`: "motor_model"): the
#: add_argument keywords they have in common, which a command completes or overrides
#: (`add_options`).
SHARED_OPTIONS = {
    "robot": {
        "help": "robot description: a robot.yaml or a name in models/ (default: hrp2)"
    },
    "config": {},
    "motor_model": {"help": "MotorModel YAML (default: identify one)"},
    "log": {},
    "port": {
        "help": "the robot on its Dynamixel bus: the serial port (e.g. /dev/ttyUSB0, "
        "or the path sim-servo prints)"
    },
    "lockstep": {
        "action": "store_true",
        "help": "the robot behind the port is a lock-step "
        "simulation (sim-servo --lockstep): nothing waits for the wall clock",
    },
    "lcm": {
        "required": True,
        "help": "LCM URL, e.g. udpm://239.255.76.67:7667?ttl=0 on a robot's network, "
        "tcpq://127.0.0.1:7700 through `python -m hrp2_drake.hardware.tcpq_hub`, or "
        "memq://",
    },
    "scenario": {"choices": SCENARIOS},
    "duration": {"type": number(float, 0.0)},
    "jobs": {"type": COUNT},
    "quick": {"action": "store_true"},
    "out": {"help": "output folder"},  # default: out/<command>
}


#: The subcommands of `hrp2-drake` (argparse's type for them).
Commands = argparse._SubParsersAction


def add_options(
    parser: argparse.ArgumentParser, command: str, /, **options: bool | str | dict
) -> None:
    """Adds the options `--name` of `command`, in the order given. Each value: True,
    the shared option as it is (`SHARED_OPTIONS`; --out defaults to out/<command>); a
    string, its help; a dict, its add_argument keywords, over the shared ones if the
    option is shared."""
    for name, value in options.items():
        keywords = dict(SHARED_OPTIONS.get(name, {}))
        if name == "out":
            keywords["default"] = f"out/{command}"
        if isinstance(value, str):
            keywords["help"] = value
        elif isinstance(value, dict):
            keywords.update(value)
        elif value is not True:
            raise TypeError(f"add_options: --{name}: expected True, a help or keywords")
        parser.add_argument("--" + name.replace("_", "-"), **keywords)


def debug_option() -> argparse.ArgumentParser:
    """--debug, accepted before and after the command name (a parent parser)."""
    debug = argparse.ArgumentParser(add_help=False)
    debug.add_argument(
        "--debug",
        action="store_true",
        default=argparse.SUPPRESS,
        help="let errors propagate with their Python traceback (for developers)",
    )
    return debug


def add_command(
    commands: Commands,
    name: str,
    run: Callable[[argparse.Namespace], int],
    help: str,
    /,
    **options: bool | str | dict,
) -> argparse.ArgumentParser:
    """Adds the command `name`, which `run(args)` runs, with --debug and `options`
    (`add_options`); returns its parser."""
    parser = commands.add_parser(name, parents=[debug_option()], help=help)
    parser.set_defaults(run=run)
    add_options(parser, name, **options)
    return parser


# ------------------------------------------------------------------ reading them


def read_config(schema, args: argparse.Namespace):
    """The --config YAML file read into `schema`, or its defaults: not validated yet,
    the command's options change it first (`validate`)."""
    if not args.config:
        return schema()
    return load_config(schema, filename=args.config, validate=False)


def read_config_on_robot(schema, args: argparse.Namespace, robot_key: str):
    """(config, sources): the --config file read into `schema` (a config with a
    `torque_control`) over the robot's torque-control settings (`load_on_robot`: the
    command's defaults < the robot's control file < --config < the options, which the
    command applies after); not validated yet. The robot: --robot, else the file's
    (its field at `robot_key`, e.g. "station.robot"), else the schema's default.
    `sources` (a `TorqueControlSources`) says where the settings came from."""
    from hrp2_drake.assembly.robot_control import load_on_robot
    from hrp2_drake.description import load_robot_description

    spec = args.robot or field_at(read_config(schema, args), robot_key)
    return load_on_robot(schema, load_robot_description(spec or None), args.config)


def config_sets(args: argparse.Namespace, key: str) -> bool:
    """Whether the --config file sets `key`, a field's path ("force_task",
    "station.scenario"); else the default holds."""
    path = getattr(args, "config", None)
    if not path:
        return False
    raw = parse_yaml(read_yaml_text(path), path)
    for name in key.split("."):
        if not isinstance(raw, dict) or name not in raw:
            return False
        raw = raw[name]
    return True


def validate(config, args: argparse.Namespace) -> None:
    """`validate_config` once the options are applied; errors name the --config file."""
    validate_config(config, args.config or None)


def output_folder(path: str) -> Path:
    """The --out folder, created (with its parents) before anything runs, so that a
    path that cannot be a writable folder is reported before simulating."""
    out = Path(path)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise ValueError(f"--out {path}: exists and is not a folder") from None
    except NotADirectoryError:
        raise ValueError(
            f"--out {path}: a parent of it is a file, not a folder"
        ) from None
    except PermissionError:
        raise ValueError(f"--out {path}: permission denied, cannot create it") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise ValueError(f"--out {path}: folder not writable")
    return out


def use_robot(
    station, args: argparse.Namespace, key: str = "station", floating: str = ""
) -> None:
    """--robot and --scenario into the StationConfig at `key` of the --config file,
    before it is validated. Its scenario is the first given of: --scenario, the
    file's, the robot's default (a fixed robot: "fixed_base"; a floating one:
    `floating`, if given, else the config's default). A scenario given is never
    replaced: one the robot cannot have is refused by the validation."""
    if args.robot:
        station.robot = args.robot
    if getattr(args, "scenario", None):
        station.scenario = args.scenario
    elif not config_sets(args, f"{key}.scenario"):
        if station.description().base == "fixed":
            station.scenario = "fixed_base"
        elif floating:
            station.scenario = floating


def set_given(config, args: argparse.Namespace, *names: str, **fields: str) -> None:
    """Sets each option given on the command line (not None) on `config`: the options
    `names` on the fields of the same name, and `fields` as field="option"."""
    for field, name in [*zip(names, names), *fields.items()]:
        value = getattr(args, name)
        if value is not None:
            setattr(config, field, value)


def validated_out(config, args: argparse.Namespace) -> Path:
    """Validates `config` once the options are applied (`validate`), then creates the
    --out folder (`output_folder`): bad input is reported before anything runs."""
    validate(config, args)
    return output_folder(args.out)


def configured(schema, args: argparse.Namespace, *options: str):
    """(config, out): the --config file read into `schema` (`read_config`) with the
    given `options` on the fields of the same name (`set_given`), validated; and the
    --out folder, created (`validated_out`)."""
    config = read_config(schema, args)
    set_given(config, args, *options)
    return config, validated_out(config, args)


def stopped(reason: str | None) -> int:
    """The exit code of a run that talks to a robot: 1 after one line saying why it
    stopped (`reason`), 0 if it ran to its end (None)."""
    if reason is not None:
        console.say(f"stopped: {reason}")
        return 1
    return 0


def motor_model(args: argparse.Namespace, out: Path, config=None, identify=None):
    """The --motor-model file (or the config's `motor_model`), checked against the
    joints `config` torque-controls, or one identified now with `identify` (an
    IdentifyConfig; default: `IdentifyConfig()`, the default robot's), saved under
    out/identify."""
    from hrp2_drake.identification.motor_model import MotorModel

    path = args.motor_model or getattr(config, "motor_model", "")
    if path:
        loaded = MotorModel.load(path)
        # The joints the experiment torque-controls: checked before simulating.
        torque_control = getattr(config, "torque_control", None)
        if hasattr(config, "controlled_joints"):  # a config that knows its run's
            needed = config.controlled_joints()
        elif torque_control is not None:
            station = getattr(config, "station", None)  # ControlConfig: its robot
            robot = (
                station.description() if station is not None else config.description()
            )
            needed = torque_control.controlled_joints(robot)
        else:
            needed = [config.joint] if hasattr(config, "joint") else []
        missing = [j for j in needed if j not in loaded.joint_names]
        if missing:
            raise ValueError(
                f"{path}: the motor model has no joints {missing} (it has "
                f"{loaded.joint_names}), which the experiment torque-controls"
            )
        return loaded
    from hrp2_drake.assembly.identification import (
        IdentifyConfig,
        identify_motor_model,
    )

    console.say("no --motor-model: identifying one first (hrp2-drake identify)")
    return MotorModel.load(
        identify_motor_model(identify or IdentifyConfig(), out / "identify")
    )


def motor_model_path(args: argparse.Namespace, out: Path) -> Path:
    """The motor model file `motor_model(args, out)` read: --motor-model, or the one
    it identified under out/identify."""
    return Path(args.motor_model or out / "identify" / "motor_model.yaml")
