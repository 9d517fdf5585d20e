"""The `hrp2-drake` command.

    hrp2-drake simulate [--robot R] [--scenario S] [--duration T]
                        [--trajectory default|FILE] [--config FILE] [--out DIR] [--html]
    hrp2-drake identify [--robot R] [--log LOG] [--config FILE] [--out DIR]
    hrp2-drake estimate [--robot R] --log LOG [--window N] [--out DIR]
    hrp2-drake validate [--robot R] --motor-model M --log LOG [LOG ...] [--out DIR]
    hrp2-drake calibrate [--config FILE] [--out DIR] [--install]
    hrp2-drake experiment NAME | reproduce  (HRP-2, the paper's experiments; see --help)
    hrp2-drake track [--robot R] [--motor-model M] [--quick]
    hrp2-drake tune [--config FILE] [--trials N] [--workers W] [--scheduler ADDRESS]
                    [--motor-model M] [--quick] [--out DIR]
    hrp2-drake control --lcm URL | sim-robot --lcm URL   (torque control over LCM)
    hrp2-drake record --robot R --port DEV    (a Dynamixel robot's identification logs)
    hrp2-drake control --robot R --port DEV --motor-model M   (on its Dynamixel bus)
    hrp2-drake sim-servo --robot R            (its servos emulated on a pseudo-terminal)

--robot is a robot description (models/<name>/robot.yaml, or its name: hrp2, iiwa14);
without it, HRP-2.

Bad input (a file, a YAML key, an array of a log, an option) is reported on one line,
`hrp2-drake <command>: error: <what and where>`, with exit code 2, before anything is
simulated; `hrp2-drake --debug <command> ...` lets the exception propagate instead.
"""

import argparse
import sys
import zipfile

import yaml

from hrp2_drake import console
from hrp2_drake.commands import (
    balance,
    calibrate,
    control,
    estimate,
    experiment,
    identify,
    options,
    record,
    reproduce,
    sim_robot,
    sim_servo,
    simulate,
    track,
    tune,
    validate,
)
from hrp2_drake.config import one_line

#: What bad input raises: reported on one line with exit code 2 (--debug: re-raised).
USER_ERRORS = (
    ValueError,
    KeyError,
    OSError,  # FileNotFoundError, IsADirectoryError, PermissionError, ...
    EOFError,
    yaml.YAMLError,
    zipfile.BadZipFile,
)


#: The commands (each a module of `hrp2_drake.commands`: `add` registers its parser,
#: `run` runs it), in the order `hrp2-drake --help` lists them.
_COMMANDS = (
    simulate,
    identify,
    estimate,
    validate,
    track,
    balance,
    control,
    sim_robot,
    record,
    sim_servo,
    experiment,
    calibrate,
    reproduce,
    tune,
)


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line (and exit code 2), like the
    command's own."""

    def error(self, message: str):
        hint = f"see {self.prog} --help"
        self.exit(2, f"{self.prog}: error: {one_line(message)} ({hint})\n")


def _message(error: BaseException) -> str:
    """One line for a user error: its message, the file's name first for OSError."""
    if isinstance(error, KeyError) and error.args:
        text = str(error.args[0])
    elif isinstance(error, OSError) and error.filename and error.strerror:
        text = f"{error.filename}: {error.strerror}"
    else:
        text = str(error)
    return one_line(text) or type(error).__name__


def _parser() -> argparse.ArgumentParser:
    """The command line: `hrp2-drake [--debug] <command> [options]`."""
    parser = _Parser(
        prog="hrp2-drake",
        description="Torque control without joint-torque sensors (Del Prete et al. "
        "2015) on a simulated robot in Drake: HRP-2, the paper's, or any robot "
        "description.",
        parents=[options.debug_option()],
    )
    commands = parser.add_subparsers(dest="command", required=True)
    for command in _COMMANDS:
        command.add(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Runs the command; bad input is one line on stderr and exit code 2 (`--debug`:
    the exception propagates, with its traceback)."""
    try:
        args = _parser().parse_args(argv)
    except SystemExit as exit:  # --help (0), or a bad option (2), already printed
        code = exit.code
        return code if isinstance(code, int) else 0 if code is None else 2
    prog = f"hrp2-drake {args.command}"
    if getattr(args, "debug", False):
        with console.session(prog):
            return args.run(args)
    try:
        with console.session(prog):  # one log format; repeated warnings counted
            return args.run(args)
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    except USER_ERRORS as error:
        print(f"{prog}: error: {_message(error)}", file=sys.stderr)
        return 2
    except Exception as error:  # a bug, or a simulation that failed: no traceback
        print(
            f"{prog}: internal error: {type(error).__name__}: {_message(error)} "
            "(run with --debug for the traceback)",
            file=sys.stderr,
        )
        return 1


if __name__ == "__main__":
    sys.exit(main())
