"""The `hrp2-drake` command.

    hrp2-drake simulate [--scenario S] [--duration T] [--trajectory climbing|FILE]
                        [--config FILE] [--out DIR] [--html]
    hrp2-drake calibrate [--config FILE] [--out DIR] [--install]
    hrp2-drake identify | experiment NAME | reproduce   (see --help)
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from hrp2_drake.config import load_config
from hrp2_drake.robot.station import SCENARIOS


def _config(schema, args: argparse.Namespace):
    """The --config YAML file read into `schema`, or its defaults."""
    return load_config(schema, filename=args.config) if args.config else schema()


def _simulate(args: argparse.Namespace) -> int:
    from hrp2_drake.experiments.simulate import SimulateConfig, run_simulate, summarize

    config = _config(SimulateConfig, args)
    if args.scenario:
        config.station.scenario = args.scenario
    if args.duration is not None:
        config.duration = args.duration
    if args.trajectory is not None:
        config.trajectory = args.trajectory
    if args.seed is not None:
        config.station.sensors.seed = args.seed
    config.validate()

    result = run_simulate(config, html=args.html)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    log = out / f"simulate_{config.station.scenario}.npz"
    np.savez_compressed(log, **result.signals)
    summary = summarize(result, config)
    (out / f"simulate_{config.station.scenario}.json").write_text(
        json.dumps(summary, indent=2)
    )
    print(f"log: {log} ({len(result.signals['t'])} samples)")
    if result.html is not None:
        html = out / f"simulate_{config.station.scenario}.html"
        html.write_text(result.html)
        print(f"replay: {html}")
    for key, value in summary.items():
        print(f"  {key}: {value:.6g}")
    return 0


def _identify(args: argparse.Namespace) -> int:
    from hrp2_drake.experiments.identification import IdentifyConfig, run_identify

    config = _config(IdentifyConfig, args)
    if args.duration_scale is not None:
        config.duration_scale = args.duration_scale
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    summary = run_identify(config, out, Path(args.log) if args.log else None)
    print(f"report: {out / 'identification.md'}; model: {out / 'motor_model.yaml'}")
    for joint, row in summary["joints"].items():
        line = (
            f"  {joint}: Kτ = {row['asymmetric']['k_tau'] * 1e3:.4f}e-3, "
            f"Kv = {row['asymmetric']['k_v'] * 1e3:.3f}e-3"
        )
        if "relative_error_asymmetric" in row:
            e = row["relative_error_asymmetric"]
            line += f" (vs emulator {e['k_tau'] * 100:+.1f}%, {e['k_v'] * 100:+.1f}%)"
        print(line)
    return 0


def _motor_model(args: argparse.Namespace, out: Path):
    """The --motor-model file, or one identified now (saved under out/identify)."""
    from hrp2_drake.identification.motor_model import MotorModel

    if args.motor_model:
        return MotorModel.load(args.motor_model)
    from hrp2_drake.experiments.identification import IdentifyConfig, run_identify

    print("no --motor-model: identifying one first (hrp2-drake identify)", file=sys.stderr)
    run_identify(IdentifyConfig(), out / "identify")
    return MotorModel.load(out / "identify" / "motor_model.yaml")


def _experiment(args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.name == "motion":
        from hrp2_drake.experiments.motion import MotionConfig, run_motion, write_motion_report

        config = _config(MotionConfig, args)
        if args.end is not None:
            config.end = args.end
        model = _motor_model(args, out)
        summary = write_motion_report(run_motion(config, model), out)
        print(f"report: {out / 'motion.md'}")
        for label, verdict in summary["verdicts"].items():
            print(
                f"  {label}: better than position control on "
                f"{len(verdict['average'])}/5 (average), {len(verdict['maximum'])}/5 (maximum)"
            )
        return 0
    if args.name == "estimation":
        from hrp2_drake.experiments.estimation import (
            EstimationConfig,
            run_estimation_experiment,
        )

        config = _config(EstimationConfig, args)
        summary = run_estimation_experiment(config, out)
        print(f"report: {out / 'estimation.md'}")
        for scenario, analysis in summary["scenarios"].items():
            best = analysis["best_window"]
            worst = analysis["windows"][str(best)]["right_leg_worst_ratio"]
            print(
                f"  {scenario}: best window {best}, worst right-leg RMS/peak "
                f"{worst * 100:.2f}% (goal 3%: {'met' if analysis['goal_met'] else 'NOT met'})"
            )
        return 0
    if args.name == "force":
        from hrp2_drake.experiments.force import ForceConfig, run_force_experiment

        config = _config(ForceConfig, args)
        summary = run_force_experiment(config, _motor_model(args, out), out)
        m = summary["baseline"]["metrics"]["ft_reading"]
        print(
            f"report: {out / 'force.md'}; overshoot {m['overshoot'] * 100:+.1f}%, lag "
            f"{m['lag_ms']:+.0f} ms, coupling on X {m['coupling_x'] * 100:.1f}%"
        )
        return 0
    if args.name == "stability":
        from hrp2_drake.experiments.stability import StabilityConfig, run_stability_experiment
        from hrp2_drake.identification.motor_model import MotorModel

        config = _config(StabilityConfig, args)
        asymmetric = _motor_model(args, out)
        path = Path(args.motor_model or out / "identify" / "motor_model.yaml")
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
    raise ValueError(f"unknown experiment '{args.name}'")


def _calibrate(args: argparse.Namespace) -> int:
    from hrp2_drake.experiments.calibrate import CalibrationConfig, calibrate

    config = _config(CalibrationConfig, args)
    if args.max_iterations is not None:
        config.max_iterations = args.max_iterations
    if args.jobs is not None:
        config.jobs = args.jobs
    config.validate()
    summary = calibrate(config, Path(args.out), install=args.install)
    for label, ratio_max, ratio_avg in zip(
        ("hip roll", "hip pitch", "knee", "ankle pitch", "ankle roll"),
        np.divide(summary["max_error"], summary["paper_max_error"]),
        np.divide(summary["average_error"], summary["paper_average_error"]),
    ):
        print(f"  {label}: max error {ratio_max:.2f}x paper, average {ratio_avg:.2f}x")
    return 0


def _reproduce(args: argparse.Namespace) -> int:
    from hrp2_drake.experiments.reproduce import ReproduceConfig, run_reproduce, verdicts

    config = ReproduceConfig(jobs=args.jobs, quick=args.quick, replays=not args.no_replays)
    results = run_reproduce(config, Path(args.out))
    for claim, verdict, evidence in verdicts(results):
        print(f"  [{verdict}] {claim}: {evidence}")
    failed = [s for s, r in results.items() if isinstance(r, dict) and r.get("ok") is False]
    return 1 if failed else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="hrp2-drake",
        description="Torque control without joint-torque sensors on a simulated HRP-2 "
        "(Del Prete et al. 2015) in Drake.",
    )
    commands = parser.add_subparsers(dest="command", required=True)

    sim = commands.add_parser(
        "simulate",
        help="run a scenario with the position servo holding half-sitting or "
        "following a trajectory; write the logged signals (.npz)",
    )
    sim.add_argument("--config", help="SimulateConfig YAML file")
    sim.add_argument("--scenario", choices=SCENARIOS, help="default: standing")
    sim.add_argument("--duration", type=float, help="simulated seconds (default 5)")
    sim.add_argument(
        "--trajectory",
        help="'climbing' (HRP-2 stair climbing) or a file: time + 30 joint angles",
    )
    sim.add_argument("--seed", type=int, help="sensor noise seed")
    sim.add_argument("--out", default="out", help="output folder (default: out)")
    sim.add_argument("--html", action="store_true", help="write a Meshcat HTML replay")
    sim.set_defaults(run=_simulate)

    ident = commands.add_parser(
        "identify",
        help="identify the right leg's motor model (paper Sec. 3): data collection on "
        "the hanging robot (or --log), non-causal estimation, every fit, Table 1, "
        "Figures 1 and 3",
    )
    ident.add_argument("--config", help="IdentifyConfig YAML file")
    ident.add_argument(
        "--log", help="an identification log (.npz, see README) instead of simulating"
    )
    ident.add_argument("--duration-scale", type=float, help="shorten the collection")
    ident.add_argument("--out", default="out/identify", help="output folder")
    ident.set_defaults(run=_identify)

    exp = commands.add_parser(
        "experiment",
        help="run one experiment of the paper: estimation (Sec. 2), motion (5.3), "
        "force (5.4), stability (5.2); the component analysis (5.5) needs motion and "
        "force: see reproduce",
    )
    exp.add_argument("name", choices=["estimation", "motion", "force", "stability"])
    exp.add_argument("--config", help="the experiment's config YAML file")
    exp.add_argument("--motor-model", help="MotorModel YAML (default: identify one)")
    exp.add_argument("--end", type=float, help="motion: stop the climbing motion at (s)")
    exp.add_argument("--out", default="out/experiment", help="output folder")
    exp.set_defaults(run=_experiment)

    cal = commands.add_parser(
        "calibrate",
        help="fit the emulated servo's hidden parameters to the paper's measurements "
        "of the real HRP-2 (Table 1, position control in Tables 2 and 3): servo.yaml "
        "and a report with plots",
    )
    cal.add_argument("--config", help="CalibrationConfig YAML file")
    cal.add_argument("--out", default="out/calibrate", help="output folder")
    cal.add_argument("--max-iterations", type=int, help="optimizer evaluations")
    cal.add_argument("--jobs", type=int, help="parallel simulations (1 or 2)")
    cal.add_argument(
        "--install",
        action="store_true",
        help="also write models/hrp2/servo.yaml (the simulated robot's servo)",
    )
    cal.set_defaults(run=_calibrate)

    rep = commands.add_parser(
        "reproduce",
        help="identification and every experiment of the paper: DIR/report.md, "
        "DIR/results.json, figures and Meshcat replays",
    )
    rep.add_argument("--out", default="out/reproduce", help="output folder")
    rep.add_argument("--jobs", type=int, default=2, help="parallel processes")
    rep.add_argument("--quick", action="store_true", help="CI-sized durations")
    rep.add_argument("--no-replays", action="store_true", help="skip Meshcat replays")
    rep.set_defaults(run=_reproduce)

    args = parser.parse_args(argv)
    try:
        return args.run(args)
    except (ValueError, KeyError, FileNotFoundError) as error:
        print(f"hrp2-drake {args.command}: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
