"""`hrp2-drake experiment NAME`: one experiment of the paper on HRP-2 (`paper/`)."""

import argparse
import sys

from hrp2_drake.commands import options


def add(commands: options.Commands) -> None:
    experiment = options.add_command(
        commands,
        "experiment",
        run,
        "run one experiment of the paper: estimation (Sec. 2), motion (5.3), force "
        "(5.4), stability (5.2), or the fault campaign of the supervised torque "
        "control (faults); the component analysis (5.5) needs motion and force: see "
        "reproduce",
    )
    experiment.add_argument("name", choices=list(_EXPERIMENTS))
    options.add_options(
        experiment,
        "experiment",
        config="the experiment's config YAML file",
        motor_model=True,
        end={
            "type": options.number(float, 0.0),
            "help": "motion: stop the climbing motion at (s)",
        },
        out=True,
    )


def run(args: argparse.Namespace) -> int:
    if args.end is not None and args.name != "motion":
        raise ValueError(
            f"--end: only the motion experiment has an end, not {args.name}"
        )
    if args.name not in _EXPERIMENTS:
        raise ValueError(f"unknown experiment '{args.name}'")
    return _EXPERIMENTS[args.name](args)


def _estimation_experiment(args: argparse.Namespace) -> int:
    """`experiment estimation`: torque-estimation accuracy in closed loop (paper Sec. 2,
    5.1); prints each scenario's best window and its worst right-leg error."""
    from hrp2_drake.paper.estimation import EstimationConfig, run_estimation_experiment

    config, out = options.configured(EstimationConfig, args)
    summary = run_estimation_experiment(config, out)
    print(f"report: {out / 'estimation.md'}")
    for scenario, analysis in summary["scenarios"].items():
        best = analysis["best_window"]
        worst = analysis["windows"][str(best)]["right_leg_worst_ratio"]
        print(
            f"  {scenario}: best window {best}, worst right-leg RMS/peak "
            f"{worst * 100:.2f}% (goal 3%: "
            f"{'met' if analysis['goal_met'] else 'NOT met'})"
        )
    return 0


def _motion_experiment(args: argparse.Namespace) -> int:
    """`experiment motion`: motion tracking in torque control against position control
    (paper Sec. 5.3); prints on how many joints each controller does better."""
    from hrp2_drake.paper.motion import MotionConfig, run_motion, write_motion_report

    config, out = options.configured(MotionConfig, args, "end")
    model = options.motor_model(args, out, config)
    summary = write_motion_report(run_motion(config, model), out)
    print(f"report: {out / 'motion.md'}")
    for label, verdict in summary["verdicts"].items():
        print(
            f"  {label}: better than position control on "
            f"{len(verdict['average'])}/5 (average), {len(verdict['maximum'])}/5 "
            "(maximum)"
        )
    return 0


def _force_experiment(args: argparse.Namespace) -> int:
    """`experiment force`: force tracking on the block (paper Sec. 5.4); prints the F/T
    reading's overshoot, lag and coupling."""
    from hrp2_drake.paper.force import ForceConfig, run_force_experiment

    config, out = options.configured(ForceConfig, args)
    summary = run_force_experiment(config, options.motor_model(args, out, config), out)
    m = summary["baseline"]["metrics"]["ft_reading"]
    print(
        f"report: {out / 'force.md'}; overshoot {m['overshoot'] * 100:+.1f}%, lag "
        f"{m['lag_ms']:+.0f} ms, coupling on X {m['coupling_x'] * 100:.1f}%"
    )
    return 0


def _stability_experiment(args: argparse.Namespace) -> int:
    """`experiment stability`: open-loop stability of the motor model, the asymmetric
    fit against the least-squares one written beside it (paper Sec. 5.2)."""
    from hrp2_drake.identification.motor_model import MotorModel
    from hrp2_drake.paper.stability import StabilityConfig, run_stability_experiment

    config, out = options.configured(StabilityConfig, args)
    asymmetric = options.motor_model(args, out, config)
    path = options.motor_model_path(args, out)
    least_squares = path.with_name("motor_model_least_squares.yaml")
    if not least_squares.is_file():
        raise FileNotFoundError(
            f"{least_squares}: the stability experiment also needs the symmetric "
            "fit written by `hrp2-drake identify` next to the motor model"
        )
    models = {"asymmetric": asymmetric, "least_squares": MotorModel.load(least_squares)}
    summary = run_stability_experiment(config, models, out)
    print(f"report: {out / 'stability.md'}; contrast shown: {summary['contrast']}")
    return 0


def _fault_campaign(args: argparse.Namespace) -> int:
    """`experiment faults`: the fault campaign of the supervised torque control; exit
    code 1 if a run raised (the campaign could not judge it)."""
    from hrp2_drake.paper.faults import FaultCampaignConfig, run_fault_campaign

    config, out = options.configured(FaultCampaignConfig, args)
    options.motor_model(args, out)  # checks --motor-model, or identifies one first
    path = options.motor_model_path(args, out)
    summary = run_fault_campaign(config, path, out)
    print(f"report: {out / 'faults.md'}")
    for key, value in summary["verdict"].items():
        if isinstance(value, bool):
            print(f"  {key.replace('_', ' ')}: {'yes' if value else 'no'}")
    raised = summary["verdict"]["raised"]
    if raised:  # the campaign could not judge these: not a pass
        runs = ", ".join(raised)
        print(f"faults: {len(raised)} runs raised: {runs}", file=sys.stderr)
    return 1 if raised else 0


#: `hrp2-drake experiment NAME`: the paper's experiments, in the order --help lists
#: them.
_EXPERIMENTS = {
    "estimation": _estimation_experiment,
    "motion": _motion_experiment,
    "force": _force_experiment,
    "stability": _stability_experiment,
    "faults": _fault_campaign,
}
