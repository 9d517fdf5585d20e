"""`hrp2-drake balance`: a floating-base robot on its soles, torque against position
control (`experiments/balance/runner.py`)."""

import argparse

from hrp2_drake.commands import options


def add(commands: options.Commands) -> None:
    options.add_command(
        commands,
        "balance",
        run,
        "a floating-base robot standing on its soles: the whole-body QP over the Δq "
        "torque control of its legs against its position servo (the authors' CoM "
        "sinusoid, pushes)",
        robot=True,
        config="BalanceExperimentConfig YAML file",
        motor_model={
            "help": "MotorModel YAML of the legs (default: identify them, "
            "hrp2-drake identify)"
        },
        quick="shorter runs (CI)",
        out=True,
    )


def run(args: argparse.Namespace) -> int:
    from hrp2_drake.experiments.balance.runner import (
        BalanceExperimentConfig,
        identify_legs,
        run_balance,
        shortened,
    )
    from hrp2_drake.identification.motor_model import MotorModel

    config = options.read_config(BalanceExperimentConfig, args)
    options.use_robot(config.station, args)
    if args.quick:
        config = shortened(config)
    out = options.validated_out(config, args)
    motor_model = (
        MotorModel.load(args.motor_model)
        if args.motor_model
        else identify_legs(config, out / "identify")
    )
    summary = run_balance(config, motor_model, out)
    print(f"report: {out / 'balance.md'}")
    for mode, metrics in summary["com_motion"].items():
        print(
            f"  {mode} control: CoM RMS error {metrics['com_rms_error_m'] * 1e3:.1f} mm"
        )
    for push in summary["pushes"]:
        print(
            f"  {push['mode']} control: largest {push['direction']} push survived "
            f"{push['largest_survived_N']:g} N"
        )
    return 0
