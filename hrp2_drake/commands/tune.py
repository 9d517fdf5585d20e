"""`hrp2-drake tune`: the torque controller tuned by closed-loop simulation
(`paper/tune.py`)."""

import argparse

from hrp2_drake.commands import options


def add(commands: options.Commands) -> None:
    options.add_command(
        commands,
        "tune",
        run,
        "tune the torque controller (K_p, windows, K_d, observer, predictor) by "
        "closed-loop simulation of the climbing swing with Optuna: DIR/tuned.yaml, "
        "DIR/tune.md, plots; a second run resumes the study",
        config="TuneConfig YAML file",
        motor_model=True,
        trials={"type": options.COUNT, "help": "trials to run (default 40)"},
        workers={
            "type": options.COUNT,
            "help": "trials in flight (default: 2 local processes, or the cluster's "
            "threads)",
        },
        scheduler="a Dask scheduler's address, tcp://host:port (default: local "
        "processes)",
        quick="0.4 s of motion, 4 trials",
        out="output folder (the study)",
    )


def run(args: argparse.Namespace) -> int:
    from hrp2_drake.assembly.identification import IdentifyConfig
    from hrp2_drake.paper.tune import TuneConfig, check_environment, run_tune

    config = options.read_config(TuneConfig, args)
    if args.quick:
        config.quick()
    options.set_given(config, args, "trials", "workers", "scheduler")
    options.validate(config, args)
    check_environment(config)  # optuna, dask, the scheduler: before identifying
    out = options.output_folder(args.out)
    identify = IdentifyConfig(
        station=config.station, duration_scale=0.5 if args.quick else 1.0
    )
    result = run_tune(config, options.motor_model(args, out, config, identify), out)
    best = result.best
    print(
        f"report: {out / 'tune.md'}; tuned: {out / 'tuned.yaml'}; "
        f"study: {out / 'study.journal'}"
    )
    print(
        f"  best trial {best.number}: cost {best.value:.4f}, worst error ratio vs "
        f"position control {best.user_attrs.get('worst_ratio', float('nan')):.3f} "
        f"(goal {'met' if best.user_attrs.get('goal_met') else 'NOT met'}); "
        f"{result.trials_run} trials in {result.wall_time:.0f} s on {result.executor}"
    )
    return 0
