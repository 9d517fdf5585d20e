"""`hrp2-drake estimate`: offline torque estimation of a recorded log
(`tools/estimate.py`)."""

import argparse
from pathlib import Path

from hrp2_drake.commands import options


def add(commands: options.Commands) -> None:
    options.add_command(
        commands,
        "estimate",
        run,
        "offline torque estimation of a recorded log (.npz: t, q_measured, the IMU, "
        "wrench_<sensor>; or the robot's own log format): τ̂, compensated and unknown "
        "wrenches, plot",
        robot=True,
        log={
            "required": True,
            "help": "the log (.npz, see README, or the robot's format)",
        },
        window={
            "type": options.number(int, 3),
            "default": 81,
            "help": "Savitzky-Golay window (odd)",
        },
        calibrate_offsets={
            "metavar": "START:END",
            "default": "",
            "help": "estimate the F/T sensors' offsets from this still segment of the "
            "log (s; nothing touching the sensors) and subtract them",
        },
        out=True,
    )


def run(args: argparse.Namespace) -> int:
    from hrp2_drake.description import load_robot_description
    from hrp2_drake.tools.estimate import run_estimate

    robot = load_robot_description(args.robot or None)
    out = options.output_folder(args.out)
    summary = run_estimate(
        robot, Path(args.log), out, args.window, args.calibrate_offsets
    )
    print(f"report: {out / 'estimate.md'}; arrays: {out / 'estimate.npz'}")
    for warning in summary["bias_warnings"]:
        print(f"  warning: {warning}")
    for joint, rms in summary.get("rms_error_vs_truth", {}).items():
        print(f"  {joint}: RMS error vs truth {rms:.4f} N·m")
    return 0
