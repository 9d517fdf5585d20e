"""`hrp2-drake calibrate`: the emulated servo fitted to what the real robot did:
HRP-2 to the paper's tables (`paper/calibrate.py`), any robot to its logs
(`tools/twin.py`)."""

import argparse

import numpy as np

from hrp2_drake.commands import options


def add(commands: options.Commands) -> None:
    options.add_command(
        commands,
        "calibrate",
        run,
        "fit the emulated servo's parameters to what the real robot did: HRP-2 to the "
        "paper's measurements (Table 1, position control in Tables 2 and 3); any robot "
        "to its logs by rollout (--robot R --log ...): servo.yaml and a report",
        robot=True,
        log={
            "nargs": "+",
            "help": "the robot's logs (its description's log format): fit its twin to "
            "them by rollout, cross-validated across their servo gains",
        },
        config="CalibrationConfig YAML file (HRP-2, no --log)",
        out=True,
        max_iterations={
            "type": options.COUNT,
            "help": "optimizer evaluations (with --log: rollouts of every log, "
            "default 150)",
        },
        jobs="parallel simulations (1 or 2)",
        install={
            "action": "store_true",
            "help": "also write the robot's servo file (models/<robot>/servo.yaml: the "
            "simulated robot's servo)",
        },
    )


def run(args: argparse.Namespace) -> int:
    from hrp2_drake.description import load_robot_description
    from hrp2_drake.paper.calibrate import CalibrationConfig, calibrate

    if args.log or (args.robot and load_robot_description(args.robot).name != "hrp2"):
        return _calibrate_from_logs(args)
    config, out = options.configured(CalibrationConfig, args, "max_iterations", "jobs")
    summary = calibrate(config, out, install=args.install)
    for label, ratio_max, ratio_avg in zip(
        ("hip roll", "hip pitch", "knee", "ankle pitch", "ankle roll"),
        np.divide(summary["max_error"], summary["paper_max_error"]),
        np.divide(summary["average_error"], summary["paper_average_error"]),
    ):
        print(f"  {label}: max error {ratio_max:.2f}x paper, average {ratio_avg:.2f}x")
    return 0


def _calibrate_from_logs(args: argparse.Namespace) -> int:
    """`calibrate --robot R --log ...`: any robot's twin from its logs."""
    from hrp2_drake.description import load_robot_description
    from hrp2_drake.robot.twin_calibration import TwinConfig
    from hrp2_drake.tools.twin import run_calibrate_logs

    robot = load_robot_description(args.robot)
    if not args.log:
        raise ValueError(
            f"calibrate --robot {args.robot}: give its logs with --log (only HRP-2 is "
            "calibrated to the paper's tables without logs)"
        )
    if args.config:
        raise ValueError(
            "calibrate --log: --config is HRP-2's CalibrationConfig; not used with "
            "--log"
        )
    config = TwinConfig()
    options.set_given(config, args, max_evaluations="max_iterations", workers="jobs")
    out = options.output_folder(args.out)
    summary = run_calibrate_logs(robot, args.log, out, config, install=args.install)
    fit = summary["fit"]
    print(
        f"report: {out / 'calibrate.md'}; twin: {out / 'servo.yaml'}"
        + (f" (installed as {robot.servo_path('')})" if args.install else "")
    )
    print(
        f"  {fit['rollouts']} rollouts of every log: RMS error "
        f"{fit['rms_error_start_mrad']:.1f} -> {fit['rms_error_end_mrad']:.1f} mrad"
    )
    cross = summary.get("cross_gain")
    if cross:
        print(
            f"  cross-gain mean MAE: twin {cross['twin_mean_mae_mrad']:.1f} mrad, "
            f"least-squares model {cross['least_squares_mean_mae_mrad']:.1f} mrad "
            f"({cross['twin_below_least_squares']:.0%} below; goal "
            f"{cross['goal']:.0%}: {'met' if cross['goal_met'] else 'NOT met'})"
        )
    return 0
