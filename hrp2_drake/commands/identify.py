"""`hrp2-drake identify`: the motor model of the robot's controlled joints, from a
simulated collection or from its logs (`tools/identify.py`)."""

import argparse
from pathlib import Path

from hrp2_drake.commands import options


def add(commands: options.Commands) -> None:
    options.add_command(
        commands,
        "identify",
        run,
        "identify the motor model of the robot's controlled joints (paper Sec. 3; "
        "HRP-2: the right leg, hanging): data collection (or --log), non-causal "
        "estimation, every fit, Table 1, Figures 1 and 3",
        robot=True,
        config="IdentifyConfig YAML file",
        log={
            "nargs": "+",
            "help": "identification logs instead of simulating: this project's .npz "
            "(see README), or logs in the robot description's format (`logs`, e.g. "
            "BAM's JSON for xl330_pendulum), at any rate; each log is its own segment",
        },
        fit={
            "choices": ("asymmetric", "least-squares", "coulomb", "two-stage"),
            "help": "the fit motor_model.yaml holds (default asymmetric: conservative, "
            "for the controller; least-squares: for prediction and simulation)",
        },
        duration_scale={
            "type": options.number(float, 0.0),
            "help": "shorten the collection",
        },
        out=True,
    )


def run(args: argparse.Namespace) -> int:
    from hrp2_drake.assembly.identification import IdentifyConfig
    from hrp2_drake.tools.identify import run_identify

    config = options.read_config(IdentifyConfig, args)
    options.use_robot(config.station, args)
    options.set_given(config, args, "duration_scale")
    if args.fit is not None:
        config.fit = args.fit.replace("-", "_")
    if args.log:  # the robot's description and the fitting keys; no simulation
        _validate_alone(config, args)
        out = options.output_folder(args.out)
    else:
        out = options.validated_out(config, args)
    summary = run_identify(config, out, [Path(p) for p in args.log or []])
    gain = f" at servo gain {summary['gain']:g}" if summary["gain"] else ""
    print(
        f"report: {out / 'identification.md'}; model ({config.fit.replace('_', ' ')} "
        f"fit{gain}): {out / 'motor_model.yaml'}"
    )
    for joint, row in summary["joints"].items():
        fitted = row[config.fit]
        line = (
            f"  {joint}: Kτ = {fitted['k_tau'] * 1e3:.4f}e-3, "
            f"Kv = {fitted['k_v'] * 1e3:.3f}e-3"
        )
        if "relative_error_asymmetric" in row:
            e = row["relative_error_asymmetric"]
            line += f" (vs emulator {e['k_tau'] * 100:+.1f}%, {e['k_v'] * 100:+.1f}%)"
        print(line)
    return 0


def _validate_alone(config, args: argparse.Namespace) -> None:
    """`config.validate()` without its nested configs (`options.validate` checks
    them all): `identify --log` reads the robot's logs, not a simulated station's
    servo file."""
    try:
        config.validate()
    except ValueError as error:
        if not args.config:
            raise
        raise ValueError(f"{args.config}: {error}") from error
