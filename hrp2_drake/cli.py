"""The `hrp2-drake` command.

    hrp2-drake simulate [--robot R] [--scenario S] [--duration T]
                        [--trajectory default|FILE] [--config FILE] [--out DIR] [--html]
    hrp2-drake identify [--robot R] [--log LOG] [--config FILE] [--out DIR]
    hrp2-drake estimate [--robot R] --log LOG [--window N] [--out DIR]
    hrp2-drake validate [--robot R] --motor-model M --log LOG [LOG ...] [--out DIR]
    hrp2-drake calibrate [--config FILE] [--out DIR] [--install]
    hrp2-drake experiment NAME | reproduce   (HRP-2, the paper's experiments; see --help)
    hrp2-drake track [--robot R] [--motor-model M] [--quick]
    hrp2-drake tune [--config FILE] [--trials N] [--workers W] [--scheduler ADDRESS]
                    [--motor-model M] [--quick] [--out DIR]
    hrp2-drake control --lcm URL | sim-robot --lcm URL   (torque control over LCM)

--robot is a robot description (models/<name>/robot.yaml, or its name: hrp2, iiwa14);
without it, HRP-2.

Bad input (a file, a YAML key, an array of a log, an option) is reported on one line,
`hrp2-drake <command>: error: <what and where>`, with exit code 2, before anything is
simulated; `hrp2-drake --debug <command> ...` lets the exception propagate instead.
"""

import argparse
import dataclasses
import json
import math
import os
import sys
import zipfile
from pathlib import Path

import numpy as np
import yaml

from hrp2_drake import console
from hrp2_drake.config import load_config, one_line, validate_config
from hrp2_drake.robot.station import SCENARIOS

#: What bad input raises: reported on one line with exit code 2 (--debug: re-raised).
USER_ERRORS = (
    ValueError,
    KeyError,
    OSError,  # FileNotFoundError, IsADirectoryError, PermissionError, ...
    EOFError,
    yaml.YAMLError,
    zipfile.BadZipFile,
)


def _config(schema, args: argparse.Namespace):
    """The --config YAML file read into `schema`, or its defaults: not validated yet,
    the command's options change it first (`_validate`)."""
    if not args.config:
        return schema()
    return load_config(schema, filename=args.config, validate=False)


def _config_sets(args: argparse.Namespace, key: str) -> bool:
    """Whether the --config file sets the top-level `key` (else: the default holds)."""
    if not args.config:
        return False
    raw = yaml.safe_load(Path(args.config).read_text())
    return isinstance(raw, dict) and key in raw


def _validate(config, args: argparse.Namespace) -> None:
    """`validate_config` once the options are applied; errors name the --config file."""
    validate_config(config, args.config or None)


def _output_folder(path: str) -> Path:
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


def _use_robot(station, args: argparse.Namespace) -> None:
    """--robot into a StationConfig; a fixed robot gets the "fixed_base" scenario
    unless --scenario says otherwise."""
    if args.robot:
        station.robot = args.robot
    if not getattr(args, "scenario", None) and station.description().base == "fixed":
        station.scenario = "fixed_base"


def _simulate(args: argparse.Namespace) -> int:
    from hrp2_drake.tools.simulate import SimulateConfig, run_simulate, summarize

    config = _config(SimulateConfig, args)
    _use_robot(config.station, args)
    if args.scenario:
        config.station.scenario = args.scenario
    if args.duration is not None:
        config.duration = args.duration
    if args.trajectory is not None:
        config.trajectory = args.trajectory
    if args.seed is not None:
        config.station.sensors = dataclasses.replace(
            config.station.sensors_config(), seed=args.seed
        )
    _validate(config, args)
    out = _output_folder(args.out)

    result = run_simulate(config, html=args.html)
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
    from hrp2_drake.tools.identify import IdentifyConfig, run_identify

    config = _config(IdentifyConfig, args)
    _use_robot(config.station, args)
    if args.duration_scale is not None:
        config.duration_scale = args.duration_scale
    if args.fit is not None:
        config.fit = args.fit.replace("-", "_")
    _validate(config, args)
    out = _output_folder(args.out)
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


def _estimate(args: argparse.Namespace) -> int:
    from hrp2_drake.description import load_robot_description
    from hrp2_drake.tools.estimate import run_estimate

    robot = load_robot_description(args.robot or None)
    out = _output_folder(args.out)
    summary = run_estimate(robot, Path(args.log), out, args.window, args.calibrate_offsets)
    print(f"report: {out / 'estimate.md'}; arrays: {out / 'estimate.npz'}")
    for warning in summary["bias_warnings"]:
        print(f"  warning: {warning}")
    for joint, rms in summary.get("rms_error_vs_truth", {}).items():
        print(f"  {joint}: RMS error vs truth {rms:.4f} N·m")
    return 0


def _validate_logs(args: argparse.Namespace) -> int:
    from hrp2_drake.description import load_robot_description
    from hrp2_drake.tools.validate import run_validate

    robot = load_robot_description(args.robot or None)
    out = _output_folder(args.out)
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


def _track(args: argparse.Namespace) -> int:
    from hrp2_drake.tools.track import TrackConfig, can_press, run_track

    config = _config(TrackConfig, args)
    if args.robot:
        config.station.robot = args.robot
        if config.station.description().base == "floating":
            config.station.scenario = "hanging"
    robot = config.station.description()
    if robot.base == "fixed" and not can_press(robot):
        # Nothing to press with (no tool_frame and force_sensor): unless asked for.
        config.force_task = config.force_task and _config_sets(args, "force_task")
    if args.quick:
        config.duration, config.force_duration, config.k6 = 2.5, 2.0, config.k6[:1]
    _validate(config, args)
    out = _output_folder(args.out)
    from hrp2_drake.tools.identify import IdentifyConfig

    identify = IdentifyConfig(station=config.station, duration_scale=0.5 if args.quick else 1.0)
    summary = run_track(config, _motor_model(args, out, config, identify), out)
    print(f"report: {out / 'track.md'}")
    for name, errors in summary["tracking"].items():
        print(f"  {name}: maximum error {max(errors['maximum']) * 1e3:.2f} mrad")
    if "force_task" in summary:
        print(f"  force task: RMS error {summary['force_task']['rms_error_N']:.2f} N")
    return 0


def _control(args: argparse.Namespace) -> int:
    from hrp2_drake.tools.control import LcmControlConfig, _ending, run_control

    config = _config(LcmControlConfig, args)
    _use_robot(config.station, args)
    if args.duration is not None:
        config.duration = args.duration
    if args.motion:
        config.motion = args.motion
    _validate(config, args)
    out = _output_folder(args.out)
    summary = run_control(config, _motor_model(args, out, config), args.lcm, out)
    lat = summary["latency_us"]
    print(
        f"report: {out / 'control.md'}; {summary['ticks']} ticks, latency p50 "
        f"{lat['p50']:.0f} µs, p99 {lat['p99']:.0f} µs, {summary['overruns']} over the "
        f"period; torque control {summary['torque_share'] * 100:.1f}% of the run after "
        f"start-up, {len(summary['events'])} fallbacks"
        + (", gave up for good" if summary["gave_up"] else "")
    )
    if summary["fault"]:
        console.say(f"stopped: {_ending(summary)}")
        return 1
    return 0


def _sim_robot(args: argparse.Namespace) -> int:
    from hrp2_drake.tools.control import run_sim_robot
    from hrp2_drake.robot.station import StationConfig

    station = StationConfig()
    _use_robot(station, args)
    if args.scenario:
        station.scenario = args.scenario
    validate_config(station)
    out = _output_folder(args.out) if args.out else None
    summary = run_sim_robot(station, args.lcm, args.duration, out, rate=args.realtime_rate)
    print(
        f"sim-robot: {summary['simulated']:.2f} s simulated; command watchdog tripped "
        f"{summary['watchdog_trips']} times"
        + (", holding the measured pose at the end" if summary["holding"] else "")
    )
    if summary["fault"]:
        console.say(f"stopped: {summary['fault']}; held the measured pose")
        return 1
    return 0


def _motor_model(args: argparse.Namespace, out: Path, config=None, identify=None):
    """The --motor-model file (or the config's `motor_model`), checked against the
    joints `config` torque-controls, or one identified now with `identify` (an
    IdentifyConfig; default: HRP-2's), saved under out/identify."""
    from hrp2_drake.identification.motor_model import MotorModel

    path = args.motor_model or getattr(config, "motor_model", "")
    if path:
        loaded = MotorModel.load(path)
        # The joints the experiment torque-controls: checked before simulating.
        torque_control = getattr(config, "torque_control", None)
        if torque_control is not None:
            needed = torque_control.controlled_joints(config.station.description())
        else:
            needed = [config.joint] if hasattr(config, "joint") else []
        missing = [j for j in needed if j not in loaded.joint_names]
        if missing:
            raise ValueError(
                f"{path}: the motor model has no joints {missing} (it has "
                f"{loaded.joint_names}), which the experiment torque-controls"
            )
        return loaded
    from hrp2_drake.tools.identify import IdentifyConfig, run_identify

    console.say("no --motor-model: identifying one first (hrp2-drake identify)")
    run_identify(identify or IdentifyConfig(), out / "identify")
    return MotorModel.load(out / "identify" / "motor_model.yaml")


def _experiment(args: argparse.Namespace) -> int:
    if args.end is not None and args.name != "motion":
        raise ValueError(
            f"--end: only the motion experiment has an end, not {args.name}"
        )
    if args.name == "motion":
        from hrp2_drake.paper.motion import MotionConfig, run_motion, write_motion_report

        config = _config(MotionConfig, args)
        if args.end is not None:
            config.end = args.end
        _validate(config, args)
        out = _output_folder(args.out)
        model = _motor_model(args, out, config)
        summary = write_motion_report(run_motion(config, model), out)
        print(f"report: {out / 'motion.md'}")
        for label, verdict in summary["verdicts"].items():
            print(
                f"  {label}: better than position control on "
                f"{len(verdict['average'])}/5 (average), {len(verdict['maximum'])}/5 (maximum)"
            )
        return 0
    if args.name == "estimation":
        from hrp2_drake.paper.estimation import (
            EstimationConfig,
            run_estimation_experiment,
        )

        config = _config(EstimationConfig, args)
        _validate(config, args)
        out = _output_folder(args.out)
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
        from hrp2_drake.paper.force import ForceConfig, run_force_experiment

        config = _config(ForceConfig, args)
        _validate(config, args)
        out = _output_folder(args.out)
        summary = run_force_experiment(config, _motor_model(args, out, config), out)
        m = summary["baseline"]["metrics"]["ft_reading"]
        print(
            f"report: {out / 'force.md'}; overshoot {m['overshoot'] * 100:+.1f}%, lag "
            f"{m['lag_ms']:+.0f} ms, coupling on X {m['coupling_x'] * 100:.1f}%"
        )
        return 0
    if args.name == "stability":
        from hrp2_drake.paper.stability import StabilityConfig, run_stability_experiment
        from hrp2_drake.identification.motor_model import MotorModel

        config = _config(StabilityConfig, args)
        _validate(config, args)
        out = _output_folder(args.out)
        asymmetric = _motor_model(args, out, config)
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
    if args.name == "faults":
        from hrp2_drake.paper.faults import FaultCampaignConfig, run_fault_campaign

        config = _config(FaultCampaignConfig, args)
        _validate(config, args)
        out = _output_folder(args.out)
        _motor_model(args, out)  # checks --motor-model, or identifies one first
        path = Path(args.motor_model or out / "identify" / "motor_model.yaml")
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
    raise ValueError(f"unknown experiment '{args.name}'")


def _calibrate(args: argparse.Namespace) -> int:
    from hrp2_drake.paper.calibrate import CalibrationConfig, calibrate

    from hrp2_drake.description import load_robot_description

    if args.log or (args.robot and load_robot_description(args.robot).name != "hrp2"):
        return _calibrate_from_logs(args)
    config = _config(CalibrationConfig, args)
    if args.max_iterations is not None:
        config.max_iterations = args.max_iterations
    if args.jobs is not None:
        config.jobs = args.jobs
    _validate(config, args)
    summary = calibrate(config, _output_folder(args.out), install=args.install)
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
    from hrp2_drake.tools.twin import TwinConfig, run_calibrate_logs

    robot = load_robot_description(args.robot)
    if not args.log:
        raise ValueError(
            f"calibrate --robot {args.robot}: give its logs with --log (only HRP-2 is "
            "calibrated to the paper's tables without logs)"
        )
    if args.config:
        raise ValueError("calibrate --log: --config is HRP-2's CalibrationConfig; not used with --log")
    config = TwinConfig()
    if args.max_iterations is not None:
        config.max_evaluations = args.max_iterations
    if args.jobs is not None:
        config.workers = args.jobs
    out = _output_folder(args.out)
    summary = run_calibrate_logs(robot, args.log, out, config, install=args.install)
    fit = summary["fit"]
    print(
        f"report: {out / 'calibrate.md'}; twin: {out / 'servo.yaml'}"
        + (f" (installed as {robot.servo_path('')})" if args.install else "")
    )
    print(
        f"  {fit['rollouts']} rollouts of every log: RMS error {fit['rms_error_start_mrad']:.1f} "
        f"-> {fit['rms_error_end_mrad']:.1f} mrad"
    )
    cross = summary.get("cross_gain")
    if cross:
        print(
            f"  cross-gain mean MAE: twin {cross['twin_mean_mae_mrad']:.1f} mrad, least-squares "
            f"model {cross['least_squares_mean_mae_mrad']:.1f} mrad "
            f"({cross['twin_below_least_squares']:.0%} below; goal {cross['goal']:.0%}: "
            f"{'met' if cross['goal_met'] else 'NOT met'})"
        )
    return 0


def _reproduce(args: argparse.Namespace) -> int:
    from hrp2_drake.paper.reproduce import ReproduceConfig, run_reproduce, verdicts

    config = ReproduceConfig(jobs=args.jobs, quick=args.quick, replays=not args.no_replays)
    validate_config(config)
    results = run_reproduce(config, _output_folder(args.out))
    for row in verdicts(results):  # the paper's claims, then this project's goals
        kind = "paper" if row.kind == "paper" else "project goal"
        print(f"  [{row.verdict}] {kind}: {row.claim} ({row.threshold}): {row.evidence}")
    failed = [s for s, r in results.items() if isinstance(r, dict) and r.get("ok") is False]
    return 1 if failed else 0


def _tune(args: argparse.Namespace) -> int:
    from hrp2_drake.tools.identify import IdentifyConfig
    from hrp2_drake.paper.tune import TuneConfig, check_environment, run_tune

    config = _config(TuneConfig, args)
    if args.quick:
        config.quick()
    for name in ("trials", "workers", "scheduler"):
        if getattr(args, name) is not None:
            setattr(config, name, getattr(args, name))
    _validate(config, args)
    check_environment(config)  # optuna, dask, the scheduler: before identifying
    out = _output_folder(args.out)
    identify = IdentifyConfig(
        station=config.station, duration_scale=0.5 if args.quick else 1.0
    )
    result = run_tune(config, _motor_model(args, out, config, identify), out)
    best = result.best
    print(
        f"report: {out / 'tune.md'}; tuned: {out / 'tuned.yaml'}; "
        f"study: {out / 'study.journal'}"
    )
    print(
        f"  best trial {best.number}: cost {best.value:.4f}, worst error ratio vs "
        f"position control {best.user_attrs.get('worst_ratio', float('nan')):.3f} (goal "
        f"{'met' if best.user_attrs.get('goal_met') else 'NOT met'}); {result.trials_run} "
        f"trials in {result.wall_time:.0f} s on {result.executor}"
    )
    return 0


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line (and exit code 2), like the
    command's own."""

    def error(self, message: str):
        hint = f"see {self.prog} --help"
        self.exit(2, f"{self.prog}: error: {one_line(message)} ({hint})\n")


def _number(kind: type, low: float | None = None, strict: bool = True):
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


def _message(error: BaseException) -> str:
    """One line for a user error: its message, the file's name first for OSError."""
    if isinstance(error, KeyError) and error.args:
        text = str(error.args[0])
    elif isinstance(error, OSError) and error.filename and error.strerror:
        text = f"{error.filename}: {error.strerror}"
    else:
        text = str(error)
    return one_line(text) or type(error).__name__


def main(argv: list[str] | None = None) -> int:
    """Runs the command; bad input is one line on stderr and exit code 2 (`--debug`:
    the exception propagates, with its traceback)."""
    # --debug is accepted before and after the command name.
    debug = argparse.ArgumentParser(add_help=False)
    debug.add_argument(
        "--debug",
        action="store_true",
        default=argparse.SUPPRESS,
        help="let errors propagate with their Python traceback (for developers)",
    )
    parser = _Parser(
        prog="hrp2-drake",
        description="Torque control without joint-torque sensors on a simulated HRP-2 "
        "(Del Prete et al. 2015) in Drake.",
        parents=[debug],
    )
    commands = parser.add_subparsers(dest="command", required=True)

    sim = commands.add_parser(
        "simulate",
        parents=[debug],
        help="run a scenario with the position servo holding half-sitting or "
        "following a trajectory; write the logged signals (.npz)",
    )
    robot_help = "robot description: a robot.yaml or a name in models/ (default: hrp2)"
    sim.add_argument("--robot", help=robot_help)
    sim.add_argument("--config", help="SimulateConfig YAML file")
    sim.add_argument(
        "--scenario", choices=SCENARIOS, help="default: standing (a fixed robot: fixed_base)"
    )
    sim.add_argument(
        "--duration", type=_number(float, 0.0), help="simulated seconds (default 5)"
    )
    sim.add_argument(
        "--trajectory",
        help="'default' (the robot's own, HRP-2: stair climbing) or a file: time + "
        "the joint angles",
    )
    sim.add_argument(
        "--seed", type=_number(int, 0, strict=False), help="sensor noise seed"
    )
    sim.add_argument("--out", default="out", help="output folder (default: out)")
    sim.add_argument("--html", action="store_true", help="write a Meshcat HTML replay")
    sim.set_defaults(run=_simulate)

    ident = commands.add_parser(
        "identify",
        parents=[debug],
        help="identify the motor model of the robot's controlled joints (paper Sec. 3; "
        "HRP-2: the right leg, hanging): data collection (or --log), non-causal "
        "estimation, every fit, Table 1, Figures 1 and 3",
    )
    ident.add_argument("--robot", help=robot_help)
    ident.add_argument("--config", help="IdentifyConfig YAML file")
    ident.add_argument(
        "--log",
        nargs="+",
        help="identification logs instead of simulating: this project's .npz (see "
        "README), or logs in the robot description's format (`logs`, e.g. BAM's JSON "
        "for xl330_pendulum), at any rate; each log is its own segment",
    )
    ident.add_argument(
        "--fit",
        choices=("asymmetric", "least-squares", "coulomb", "two-stage"),
        help="the fit motor_model.yaml holds (default asymmetric: conservative, for "
        "the controller; least-squares: for prediction and simulation)",
    )
    ident.add_argument(
        "--duration-scale", type=_number(float, 0.0), help="shorten the collection"
    )
    ident.add_argument("--out", default="out/identify", help="output folder")
    ident.set_defaults(run=_identify)

    est = commands.add_parser(
        "estimate",
        parents=[debug],
        help="offline torque estimation of a recorded log (.npz: t, q_measured, the "
        "IMU, wrench_<sensor>): τ̂, compensated and unknown wrenches, plot",
    )
    est.add_argument("--robot", help=robot_help)
    est.add_argument("--log", required=True, help="the log (.npz, see README)")
    est.add_argument(
        "--window", type=_number(int, 3), default=81, help="Savitzky-Golay window (odd)"
    )
    est.add_argument(
        "--calibrate-offsets",
        metavar="START:END",
        default="",
        help="estimate the F/T sensors' offsets from this still segment of the log "
        "(s; nothing touching the sensors) and subtract them",
    )
    est.add_argument("--out", default="out/estimate", help="output folder")
    est.set_defaults(run=_estimate)

    val = commands.add_parser(
        "validate",
        parents=[debug],
        help="judge a motor model by rollout on real logs: the model's servo replays "
        "each logged command; position MAE and max error (mrad), plots, validate.md",
    )
    val.add_argument("--robot", help=robot_help)
    val.add_argument("--motor-model", required=True, help="MotorModel YAML")
    val.add_argument(
        "--log", required=True, nargs="+", help="the robot's logs (its logs format)"
    )
    val.add_argument("--out", default="out/validate", help="output folder")
    val.set_defaults(run=_validate_logs)

    track = commands.add_parser(
        "track",
        parents=[debug],
        help="torque control of any robot against its position servo: joint "
        "tracking, and a force task at the tool (fixed-base robots)",
    )
    track.add_argument("--robot", help=robot_help)
    track.add_argument("--config", help="TrackConfig YAML file")
    track.add_argument("--motor-model", help="MotorModel YAML (default: identify one)")
    track.add_argument("--quick", action="store_true", help="shorter runs (CI)")
    track.add_argument("--out", default="out/track", help="output folder")
    track.set_defaults(run=_track)

    lcm_help = (
        "LCM URL, e.g. udpm://239.255.76.67:7667?ttl=0 on a robot's network, "
        "tcpq://127.0.0.1:7700 through `python -m hrp2_drake.hardware.tcpq_hub`, or memq://"
    )
    ctl = commands.add_parser(
        "control",
        parents=[debug],
        help="torque control of a robot over LCM (the robot's bridge or sim-robot): "
        "the fused controller, one tick per encoder message, with per-tick timing",
    )
    ctl.add_argument("--robot", help=robot_help)
    ctl.add_argument("--lcm", required=True, help=lcm_help)
    ctl.add_argument("--motor-model", required=True, help="MotorModel YAML")
    ctl.add_argument("--config", help="LcmControlConfig YAML file")
    ctl.add_argument("--duration", type=_number(float, 0.0), help="seconds (default 5)")
    ctl.add_argument("--motion", choices=("sinusoid", "hold"), help="default: sinusoid")
    rate_help = "target real-time rate (default 1; < 1 slows the robot's clock, for tests)"
    ctl.add_argument("--out", default="out/control", help="output folder")
    ctl.set_defaults(run=_control, scenario=None)

    sim_robot = commands.add_parser(
        "sim-robot",
        parents=[debug],
        help="the simulated robot behind the LCM channels, in real time: what a real "
        "robot's bridge must do",
    )
    sim_robot.add_argument("--robot", help=robot_help)
    sim_robot.add_argument("--lcm", required=True, help=lcm_help)
    sim_robot.add_argument("--scenario", choices=SCENARIOS, help="default: hanging (fixed robots: fixed_base)")
    sim_robot.add_argument(
        "--duration", type=_number(float, 0.0), default=float("inf"),
        help="seconds (default: until Ctrl-C or SIGTERM)",
    )
    sim_robot.add_argument("--realtime-rate", type=_number(float, 0.0), default=1.0, help=rate_help)
    sim_robot.add_argument("--out", help="write the ground truth (sim_robot.npz) here on exit")
    sim_robot.set_defaults(run=_sim_robot)

    exp = commands.add_parser(
        "experiment",
        parents=[debug],
        help="run one experiment of the paper: estimation (Sec. 2), motion (5.3), "
        "force (5.4), stability (5.2), or the fault campaign of the supervised torque "
        "control (faults); the component analysis (5.5) needs motion and force: see "
        "reproduce",
    )
    exp.add_argument(
        "name", choices=["estimation", "motion", "force", "stability", "faults"]
    )
    exp.add_argument("--config", help="the experiment's config YAML file")
    exp.add_argument("--motor-model", help="MotorModel YAML (default: identify one)")
    exp.add_argument(
        "--end",
        type=_number(float, 0.0),
        help="motion: stop the climbing motion at (s)",
    )
    exp.add_argument("--out", default="out/experiment", help="output folder")
    exp.set_defaults(run=_experiment)

    cal = commands.add_parser(
        "calibrate",
        parents=[debug],
        help="fit the emulated servo's parameters to what the real robot did: HRP-2 to "
        "the paper's measurements (Table 1, position control in Tables 2 and 3); any "
        "robot to its logs by rollout (--robot R --log ...): servo.yaml and a report",
    )
    cal.add_argument("--robot", help=robot_help)
    cal.add_argument(
        "--log",
        nargs="+",
        help="the robot's logs (its description's log format): fit its twin to them by "
        "rollout, cross-validated across their servo gains",
    )
    cal.add_argument("--config", help="CalibrationConfig YAML file (HRP-2, no --log)")
    cal.add_argument("--out", default="out/calibrate", help="output folder")
    cal.add_argument(
        "--max-iterations",
        type=_number(int, 1, strict=False),
        help="optimizer evaluations (with --log: rollouts of every log, default 150)",
    )
    cal.add_argument(
        "--jobs",
        type=_number(int, 1, strict=False),
        help="parallel simulations (1 or 2)",
    )
    cal.add_argument(
        "--install",
        action="store_true",
        help="also write the robot's servo file (models/<robot>/servo.yaml: the "
        "simulated robot's servo)",
    )
    cal.set_defaults(run=_calibrate)

    rep = commands.add_parser(
        "reproduce",
        parents=[debug],
        help="identification and every experiment of the paper: DIR/report.md, "
        "DIR/results.json, figures and Meshcat replays",
    )
    rep.add_argument("--out", default="out/reproduce", help="output folder")
    rep.add_argument(
        "--jobs",
        type=_number(int, 1, strict=False),
        default=2,
        help="parallel processes",
    )
    rep.add_argument("--quick", action="store_true", help="CI-sized durations")
    rep.add_argument("--no-replays", action="store_true", help="skip Meshcat replays")
    rep.set_defaults(run=_reproduce)

    tune = commands.add_parser(
        "tune",
        parents=[debug],
        help="tune the torque controller (K_p, windows, K_d, observer, predictor) by "
        "closed-loop simulation of the climbing swing with Optuna: DIR/tuned.yaml, "
        "DIR/tune.md, plots; a second run resumes the study",
    )
    tune.add_argument("--config", help="TuneConfig YAML file")
    tune.add_argument("--motor-model", help="MotorModel YAML (default: identify one)")
    tune.add_argument(
        "--trials",
        type=_number(int, 1, strict=False),
        help="trials to run (default 40)",
    )
    tune.add_argument(
        "--workers",
        type=_number(int, 1, strict=False),
        help="trials in flight (default: 2 local processes, or the cluster's threads)",
    )
    tune.add_argument(
        "--scheduler",
        help="a Dask scheduler's address, tcp://host:port (default: local processes)",
    )
    tune.add_argument("--quick", action="store_true", help="0.4 s of motion, 4 trials")
    tune.add_argument("--out", default="out/tune", help="output folder (the study)")
    tune.set_defaults(run=_tune)

    try:
        args = parser.parse_args(argv)
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
