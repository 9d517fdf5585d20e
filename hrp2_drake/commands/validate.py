"""`hrp2-drake validate`: a motor model or a digital twin judged by rollout on real
logs (`tools/validate.py`)."""

import argparse
from pathlib import Path

from hrp2_drake.commands import options


def add(commands: options.Commands) -> None:
    options.add_command(
        commands,
        "validate",
        run,
        "judge a motor model or a digital twin by rollout on real logs: its servo "
        "replays each logged command; position MAE and max error (mrad), plots, "
        "validate.md",
        robot=True,
        motor_model={
            "required": True,
            "help": "a MotorModel YAML (identify), or a servo file: the digital twin "
            "(calibrate --log's servo.yaml, e.g. models/<robot>/servo.yaml)",
        },
        log={
            "required": True,
            "nargs": "+",
            "help": "the robot's logs (its logs format)",
        },
        out=True,
    )


def run(args: argparse.Namespace) -> int:
    from hrp2_drake.description import load_robot_description
    from hrp2_drake.tools.validate import run_validate

    robot = load_robot_description(args.robot or None)
    out = options.output_folder(args.out)
    summary = run_validate(robot, Path(args.motor_model), args.log, out)
    print(f"report: {out / 'validate.md'}; summary: {out / 'validate.json'}")
    for joint in summary["joints"]:
        mean = {
            key: "n/a" if values[joint] is None else f"{values[joint]:.1f}"
            for key, values in summary["mean"].items()
        }
        print(
            f"  {joint}: mean over {len(summary['logs'])} logs: MAE {mean['mae_mrad']} "
            f"mrad, max {mean['max_error_mrad']} mrad; servo on: MAE "
            f"{mean['mae_servo_on_mrad']}, max {mean['max_error_servo_on_mrad']} mrad"
        )
    return 0
