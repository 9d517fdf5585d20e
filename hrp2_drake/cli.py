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
import dataclasses
import json
import math
import os
import sys
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import yaml

from hrp2_drake import console
from hrp2_drake.config import (
    field_at,
    load_config,
    one_line,
    parse_yaml,
    read_yaml_text,
    validate_config,
)
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


def _config_on_robot(schema, args: argparse.Namespace, robot_key: str):
    """(config, sources): the --config file read into `schema` (a config with a
    `torque_control`) over the robot's torque-control settings (`load_on_robot`: the
    command's defaults < the robot's control file < --config < the options, which the
    command applies after); not validated yet. The robot: --robot, else the file's
    (its field at `robot_key`, e.g. "station.robot"), else the schema's default.
    `sources` (a `TorqueControlSources`) says where the settings came from."""
    from hrp2_drake.description import load_robot_description
    from hrp2_drake.tools.robot_control import load_on_robot

    spec = args.robot or field_at(_config(schema, args), robot_key)
    return load_on_robot(schema, load_robot_description(spec or None), args.config)


def _config_sets(args: argparse.Namespace, key: str) -> bool:
    """Whether the --config file sets `key`, a field's path ("force_task",
    "station.scenario"); else the default holds."""
    path = getattr(args, "config", None)
    if not path:
        return False
    raw = parse_yaml(read_yaml_text(path), path)
    for name in key.split("."):
        if not isinstance(raw, dict) or name not in raw:
            return False
        raw = raw[name]
    return True


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


def _use_robot(
    station, args: argparse.Namespace, key: str = "station", floating: str = ""
) -> None:
    """--robot and --scenario into the StationConfig at `key` of the --config file,
    before it is validated. Its scenario is the first given of: --scenario, the
    file's, the robot's default (a fixed robot: "fixed_base"; a floating one:
    `floating`, if given, else the config's default). A scenario given is never
    replaced: one the robot cannot have is refused by the validation."""
    if args.robot:
        station.robot = args.robot
    if getattr(args, "scenario", None):
        station.scenario = args.scenario
    elif not _config_sets(args, f"{key}.scenario"):
        if station.description().base == "fixed":
            station.scenario = "fixed_base"
        elif floating:
            station.scenario = floating


def _set_given(config, args: argparse.Namespace, *names: str, **fields: str) -> None:
    """Sets each option given on the command line (not None) on `config`: the options
    `names` on the fields of the same name, and `fields` as field="option"."""
    for field, name in [*zip(names, names), *fields.items()]:
        value = getattr(args, name)
        if value is not None:
            setattr(config, field, value)


def _validated_out(config, args: argparse.Namespace) -> Path:
    """Validates `config` once the options are applied (`_validate`), then creates the
    --out folder (`_output_folder`): bad input is reported before anything runs."""
    _validate(config, args)
    return _output_folder(args.out)


def _configured(schema, args: argparse.Namespace, *options: str):
    """(config, out): the --config file read into `schema` (`_config`) with the given
    `options` on the fields of the same name (`_set_given`), validated; and the --out
    folder, created (`_validated_out`)."""
    config = _config(schema, args)
    _set_given(config, args, *options)
    return config, _validated_out(config, args)


def _simulate(args: argparse.Namespace) -> int:
    from hrp2_drake.tools.simulate import SimulateConfig, run_simulate, summarize

    config = _config(SimulateConfig, args)
    _use_robot(config.station, args)
    _set_given(config, args, "duration", "trajectory")
    if args.seed is not None:
        config.station.sensors = dataclasses.replace(
            config.station.sensors_config(), seed=args.seed
        )
    out = _validated_out(config, args)

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
    _set_given(config, args, "duration_scale")
    if args.fit is not None:
        config.fit = args.fit.replace("-", "_")
    if args.log:  # the robot's description and the fitting keys; no simulation
        _validate_alone(config, args)
        out = _output_folder(args.out)
    else:
        out = _validated_out(config, args)
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
    """`config.validate()` without its nested configs (`_validate` checks them all):
    `identify --log` reads the robot's logs, not a simulated station's servo file."""
    try:
        config.validate()
    except ValueError as error:
        if not args.config:
            raise
        raise ValueError(f"{args.config}: {error}") from error


def _estimate(args: argparse.Namespace) -> int:
    from hrp2_drake.description import load_robot_description
    from hrp2_drake.tools.estimate import run_estimate

    robot = load_robot_description(args.robot or None)
    out = _output_folder(args.out)
    summary = run_estimate(
        robot, Path(args.log), out, args.window, args.calibrate_offsets
    )
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

    config, sources = _config_on_robot(TrackConfig, args, "station.robot")
    # --robot R, floating: hanging unless the file says otherwise (the iiwa's default
    # station is fixed_base).
    _use_robot(config.station, args, floating="hanging" if args.robot else "")
    robot = config.station.description()
    if robot.base == "fixed" and not can_press(robot):
        # Nothing to press with (no tool_frame and force_sensor): unless asked for.
        config.force_task = config.force_task and _config_sets(args, "force_task")
    if args.quick:
        config.duration, config.force_duration, config.k6 = 2.5, 2.0, config.k6[:1]
    out = _validated_out(config, args)
    from hrp2_drake.tools.identify import IdentifyConfig

    identify = IdentifyConfig(
        station=config.station, duration_scale=0.5 if args.quick else 1.0
    )
    summary = run_track(
        config, _motor_model(args, out, config, identify), out, sources=sources
    )
    print(f"report: {out / 'track.md'}")
    for name, errors in summary["tracking"].items():
        print(f"  {name}: maximum error {max(errors['maximum']) * 1e3:.2f} mrad")
    if "force_task" in summary:
        print(f"  force task: RMS error {summary['force_task']['rms_error_N']:.2f} N")
    return 0


def _control(args: argparse.Namespace) -> int:
    from hrp2_drake.tools.control import ControlConfig, run_control, run_ending

    config, sources = _config_on_robot(ControlConfig, args, "robot")
    if args.robot:
        config.robot = args.robot
    _set_given(config, args, "duration", "motion")
    if bool(args.lcm) == bool(args.port):
        raise ValueError("give the robot's link: --lcm URL or --port DEV (one of them)")
    if args.lockstep and not args.port:
        raise ValueError(
            "--lockstep: only with --port (a lock-step robot behind a bus)"
        )
    out = _validated_out(config, args)
    summary = run_control(
        config,
        _motor_model(args, out, config),
        out,
        lcm_url=args.lcm,
        port=args.port,
        lockstep=args.lockstep,
        sources=sources,
    )
    lat = summary["latency_us"]
    print(
        f"report: {out / 'control.md'}; {summary['ticks']} ticks, latency p50 "
        f"{lat['p50']:.0f} µs, p99 {lat['p99']:.0f} µs, {summary['overruns']} over the "
        f"period; torque control {summary['torque_share'] * 100:.1f}% of the run after "
        f"start-up, {len(summary['events'])} fallbacks"
        + (", gave up for good" if summary["gave_up"] else "")
    )
    return _stopped(run_ending(summary) if summary["fault"] else None)


def _sim_robot(args: argparse.Namespace) -> int:
    from hrp2_drake.robot.station import StationConfig
    from hrp2_drake.tools.control import run_sim_robot

    station = StationConfig()
    _use_robot(station, args)
    validate_config(station)
    out = _output_folder(args.out) if args.out else None
    summary = run_sim_robot(
        station,
        args.lcm,
        args.duration,
        out,
        rate=args.realtime_rate,
        lockstep=args.lockstep,
    )
    print(
        f"sim-robot: {summary['simulated']:.2f} s simulated; command watchdog tripped "
        f"{summary['watchdog_trips']} times"
        + (", holding the measured pose at the end" if summary["holding"] else "")
    )
    return _stopped(
        f"{summary['fault']}; held the measured pose" if summary["fault"] else None
    )


def _record(args: argparse.Namespace) -> int:
    from hrp2_drake.tools.record import RecordConfig, run_record

    config = _config(RecordConfig, args)
    if args.robot:
        config.robot = args.robot
    if args.gain:
        config.gains = list(args.gain)
    out = _validated_out(config, args)
    summary = run_record(config, args.port, out, lockstep=args.lockstep)
    for log in summary["logs"]:
        print(
            f"  {out / log['log']}: {log['samples']} samples at P gain {log['gain']:g}"
        )
    print(f"report: {out / 'record.md'}")
    faults = [log["fault"] for log in summary["logs"] if log["fault"]]
    return _stopped(faults[0] if faults else None)


def _sim_servo(args: argparse.Namespace) -> int:
    from hrp2_drake.hardware.sim_servo import parse_fault, run_sim_servo

    faults = [parse_fault(spec) for spec in args.fault or []]
    ids = [int(x) for x in args.ids.split(",")] if args.ids else None
    out = _output_folder(args.out) if args.out else None
    summary = run_sim_servo(
        args.robot or "",
        lockstep=args.lockstep,
        rate=args.realtime_rate,
        duration=args.duration,
        faults=faults,
        ids=ids,
        out=out,
    )
    stopped = summary.get("stopped", "")
    return _stopped(stopped if stopped and "closed" in stopped else None)


def _balance(args: argparse.Namespace) -> int:
    from hrp2_drake.identification.motor_model import MotorModel
    from hrp2_drake.tools.balance import (
        BalanceExperimentConfig,
        identify_legs,
        run_balance,
        shortened,
    )

    config = _config(BalanceExperimentConfig, args)
    _use_robot(config.station, args)
    if args.quick:
        config = shortened(config)
    out = _validated_out(config, args)
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


def _stopped(reason: str | None) -> int:
    """The exit code of a run that talks to a robot: 1 after one line saying why it
    stopped (`reason`), 0 if it ran to its end (None)."""
    if reason is not None:
        console.say(f"stopped: {reason}")
        return 1
    return 0


def _motor_model(args: argparse.Namespace, out: Path, config=None, identify=None):
    """The --motor-model file (or the config's `motor_model`), checked against the
    joints `config` torque-controls, or one identified now with `identify` (an
    IdentifyConfig; default: `IdentifyConfig()`, the default robot's), saved under
    out/identify."""
    from hrp2_drake.identification.motor_model import MotorModel

    path = args.motor_model or getattr(config, "motor_model", "")
    if path:
        loaded = MotorModel.load(path)
        # The joints the experiment torque-controls: checked before simulating.
        torque_control = getattr(config, "torque_control", None)
        if torque_control is not None:
            station = getattr(config, "station", None)  # ControlConfig: its robot
            robot = (
                station.description() if station is not None else config.description()
            )
            needed = torque_control.controlled_joints(robot)
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


def _motor_model_path(args: argparse.Namespace, out: Path) -> Path:
    """The motor model file `_motor_model(args, out)` read: --motor-model, or the one
    it identified under out/identify."""
    return Path(args.motor_model or out / "identify" / "motor_model.yaml")


def _estimation_experiment(args: argparse.Namespace) -> int:
    """`experiment estimation`: torque-estimation accuracy in closed loop (paper Sec. 2,
    5.1); prints each scenario's best window and its worst right-leg error."""
    from hrp2_drake.paper.estimation import EstimationConfig, run_estimation_experiment

    config, out = _configured(EstimationConfig, args)
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

    config, out = _configured(MotionConfig, args, "end")
    model = _motor_model(args, out, config)
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

    config, out = _configured(ForceConfig, args)
    summary = run_force_experiment(config, _motor_model(args, out, config), out)
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

    config, out = _configured(StabilityConfig, args)
    asymmetric = _motor_model(args, out, config)
    path = _motor_model_path(args, out)
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

    config, out = _configured(FaultCampaignConfig, args)
    _motor_model(args, out)  # checks --motor-model, or identifies one first
    path = _motor_model_path(args, out)
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


def _experiment(args: argparse.Namespace) -> int:
    if args.end is not None and args.name != "motion":
        raise ValueError(
            f"--end: only the motion experiment has an end, not {args.name}"
        )
    if args.name not in _EXPERIMENTS:
        raise ValueError(f"unknown experiment '{args.name}'")
    return _EXPERIMENTS[args.name](args)


def _calibrate(args: argparse.Namespace) -> int:
    from hrp2_drake.description import load_robot_description
    from hrp2_drake.paper.calibrate import CalibrationConfig, calibrate

    if args.log or (args.robot and load_robot_description(args.robot).name != "hrp2"):
        return _calibrate_from_logs(args)
    config, out = _configured(CalibrationConfig, args, "max_iterations", "jobs")
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
    _set_given(config, args, max_evaluations="max_iterations", workers="jobs")
    out = _output_folder(args.out)
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


def _reproduce(args: argparse.Namespace) -> int:
    from hrp2_drake.paper.claims import verdicts
    from hrp2_drake.paper.reproduce import ReproduceConfig, run_reproduce

    config = ReproduceConfig(
        jobs=args.jobs, quick=args.quick, replays=not args.no_replays
    )
    validate_config(config)
    results = run_reproduce(config, _output_folder(args.out))
    for row in verdicts(results):  # the paper's claims, then this project's goals
        kind = "paper" if row.kind == "paper" else "project goal"
        print(
            f"  [{row.verdict}] {kind}: {row.claim} ({row.threshold}): {row.evidence}"
        )
    failed = [
        s for s, r in results.items() if isinstance(r, dict) and r.get("ok") is False
    ]
    return 1 if failed else 0


def _tune(args: argparse.Namespace) -> int:
    from hrp2_drake.paper.tune import TuneConfig, check_environment, run_tune
    from hrp2_drake.tools.identify import IdentifyConfig

    config = _config(TuneConfig, args)
    if args.quick:
        config.quick()
    _set_given(config, args, "trials", "workers", "scheduler")
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
        f"position control {best.user_attrs.get('worst_ratio', float('nan')):.3f} "
        f"(goal {'met' if best.user_attrs.get('goal_met') else 'NOT met'}); "
        f"{result.trials_run} trials in {result.wall_time:.0f} s on {result.executor}"
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


#: An argparse type: an integer >= 1 (a count of trials, workers, processes...).
_COUNT = _number(int, 1, strict=False)

#: The options several commands share, by name (`--motor-model`: "motor_model"): the
#: add_argument keywords they have in common, which a command completes or overrides
#: (`_add_options`).
_SHARED_OPTIONS = {
    "robot": {
        "help": "robot description: a robot.yaml or a name in models/ (default: hrp2)"
    },
    "config": {},
    "motor_model": {"help": "MotorModel YAML (default: identify one)"},
    "log": {},
    "port": {
        "help": "the robot on its Dynamixel bus: the serial port (e.g. /dev/ttyUSB0, "
        "or the path sim-servo prints)"
    },
    "lockstep": {
        "action": "store_true",
        "help": "the robot behind the port is a lock-step "
        "simulation (sim-servo --lockstep): nothing waits for the wall clock",
    },
    "lcm": {
        "required": True,
        "help": "LCM URL, e.g. udpm://239.255.76.67:7667?ttl=0 on a robot's network, "
        "tcpq://127.0.0.1:7700 through `python -m hrp2_drake.hardware.tcpq_hub`, or "
        "memq://",
    },
    "scenario": {"choices": SCENARIOS},
    "duration": {"type": _number(float, 0.0)},
    "jobs": {"type": _COUNT},
    "quick": {"action": "store_true"},
    "out": {"help": "output folder"},  # default: out/<command>
}

#: The subcommands of `hrp2-drake` (argparse's type for them).
_Commands = argparse._SubParsersAction


def _add_options(
    parser: argparse.ArgumentParser, command: str, /, **options: bool | str | dict
) -> None:
    """Adds the options `--name` of `command`, in the order given. Each value: True,
    the shared option as it is (`_SHARED_OPTIONS`; --out defaults to out/<command>); a
    string, its help; a dict, its add_argument keywords, over the shared ones if the
    option is shared."""
    for name, value in options.items():
        keywords = dict(_SHARED_OPTIONS.get(name, {}))
        if name == "out":
            keywords["default"] = f"out/{command}"
        if isinstance(value, str):
            keywords["help"] = value
        elif isinstance(value, dict):
            keywords.update(value)
        elif value is not True:
            raise TypeError(
                f"_add_options: --{name}: expected True, a help or keywords"
            )
        parser.add_argument("--" + name.replace("_", "-"), **keywords)


def _debug_option() -> argparse.ArgumentParser:
    """--debug, accepted before and after the command name (a parent parser)."""
    debug = argparse.ArgumentParser(add_help=False)
    debug.add_argument(
        "--debug",
        action="store_true",
        default=argparse.SUPPRESS,
        help="let errors propagate with their Python traceback (for developers)",
    )
    return debug


def _add_command(
    commands: _Commands,
    name: str,
    run: Callable[[argparse.Namespace], int],
    help: str,
    /,
    **options: bool | str | dict,
) -> argparse.ArgumentParser:
    """Adds the command `name`, which `run(args)` runs, with --debug and `options`
    (`_add_options`); returns its parser."""
    parser = commands.add_parser(name, parents=[_debug_option()], help=help)
    parser.set_defaults(run=run)
    _add_options(parser, name, **options)
    return parser


def _add_simulate(commands: _Commands) -> None:
    _add_command(
        commands,
        "simulate",
        _simulate,
        "run a scenario with the position servo holding half-sitting or following a "
        "trajectory; write the logged signals (.npz)",
        robot=True,
        config="SimulateConfig YAML file",
        scenario="default: standing (a fixed robot: fixed_base)",
        duration="simulated seconds (default 5)",
        trajectory="'default' (the robot's own, HRP-2: stair climbing) or a file: time "
        "+ the joint angles",
        seed={"type": _number(int, 0, strict=False), "help": "sensor noise seed"},
        out={"default": "out", "help": "output folder (default: out)"},
        html={"action": "store_true", "help": "write a Meshcat HTML replay"},
    )


def _add_identify(commands: _Commands) -> None:
    _add_command(
        commands,
        "identify",
        _identify,
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
        duration_scale={"type": _number(float, 0.0), "help": "shorten the collection"},
        out=True,
    )


def _add_estimate(commands: _Commands) -> None:
    _add_command(
        commands,
        "estimate",
        _estimate,
        "offline torque estimation of a recorded log (.npz: t, q_measured, the IMU, "
        "wrench_<sensor>; or the robot's own log format): τ̂, compensated and unknown "
        "wrenches, plot",
        robot=True,
        log={
            "required": True,
            "help": "the log (.npz, see README, or the robot's format)",
        },
        window={
            "type": _number(int, 3),
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


def _add_validate(commands: _Commands) -> None:
    _add_command(
        commands,
        "validate",
        _validate_logs,
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


def _add_track(commands: _Commands) -> None:
    _add_command(
        commands,
        "track",
        _track,
        "torque control of any robot against its position servo: joint tracking, and a "
        "force task at the tool (fixed-base robots)",
        robot=True,
        config="TrackConfig YAML file",
        motor_model=True,
        quick="shorter runs (CI)",
        out=True,
    )


def _add_balance(commands: _Commands) -> None:
    _add_command(
        commands,
        "balance",
        _balance,
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


def _add_control(commands: _Commands) -> None:
    _add_command(
        commands,
        "control",
        _control,
        "torque control of a robot over LCM (the robot's bridge or sim-robot: one tick "
        "per encoder message) or on its Dynamixel bus (a serial port, or sim-servo's: "
        "one sync read, one tick, one sync write per period), with per-tick timing",
        robot=True,
        lcm={
            "required": False,
            "default": "",
            "help": "the robot over LCM: its URL (see sim-robot --lcm)",
        },
        port={"default": ""},
        lockstep=True,
        motor_model={"required": True, "help": "MotorModel YAML"},
        config="ControlConfig YAML file",
        duration="seconds (default 5)",
        motion={"choices": ("sinusoid", "hold"), "help": "default: sinusoid"},
        out=True,
    ).set_defaults(scenario=None)


def _add_record(commands: _Commands) -> None:
    _add_command(
        commands,
        "record",
        _record,
        "record a robot's identification logs through its Dynamixel bus: the "
        "description's excitation through the servos' own position control, one log "
        "per P gain, in the robot's log format (for identify, validate, calibrate)",
        robot=True,
        port={"required": True},
        gain={
            "type": _number(int, 0),
            "action": "append",
            "default": None,
            "help": "a position P gain to record at (repeat for several; default: the "
            "description's position_loop.gain)",
        },
        lockstep=True,
        config="RecordConfig YAML file",
        out=True,
    )


def _add_sim_servo(commands: _Commands) -> None:
    _add_command(
        commands,
        "sim-servo",
        _sim_servo,
        "the simulated robot's Dynamixel servos on a pseudo-terminal (Protocol 2.0, "
        "the robot's physics behind every ID, wire time and return delays honoured): "
        "prints the port's path",
        robot=True,
        lockstep={
            "action": "store_true",
            "help": "the robot's clock is the bus traffic "
            "(one period per sync read): deterministic, for tests",
        },
        realtime_rate={
            "type": _number(float, 0.0),
            "default": 1.0,
            "help": "target real-time rate (default 1)",
        },
        duration={
            "default": float("inf"),
            "help": "seconds (default: until Ctrl-C or SIGTERM)",
        },
        fault={
            "action": "append",
            "help": "inject a fault, e.g. silent:1@2.0, crc:1@1.5x20, "
            "hardware:1@2.0:overload, close@3.0, wrong_model:1:XM430-W350 (repeat for "
            "several)",
        },
        ids={
            "default": "",
            "help": "serve these IDs instead of the description's "
            "(comma-separated), e.g. to test a wrong ID",
        },
        out={
            "default": None,
            "help": "write a report (sim_servo.md, sim_servo.json) here on exit",
        },
    )


def _add_sim_robot(commands: _Commands) -> None:
    _add_command(
        commands,
        "sim-robot",
        _sim_robot,
        "the simulated robot behind the LCM channels, in real time: what a real "
        "robot's bridge must do",
        robot=True,
        lcm=True,
        scenario="default: hanging (fixed robots: fixed_base)",
        duration={
            "default": float("inf"),
            "help": "seconds (default: until Ctrl-C or SIGTERM)",
        },
        realtime_rate={
            "type": _number(float, 0.0),
            "default": 1.0,
            "help": "target real-time rate (default 1; < 1 slows the robot's clock, "
            "for tests)",
        },
        lockstep={
            "action": "store_true",
            "help": "advance a period only once the "
            "controller's command for the last one has come (after the first "
            "command: or 0.2 s without one): a clock independent of the machine, "
            "for tests",
        },
        out={
            "default": None,
            "help": "write the ground truth (sim_robot.npz) here on exit",
        },
    )


def _add_calibrate(commands: _Commands) -> None:
    _add_command(
        commands,
        "calibrate",
        _calibrate,
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
            "type": _COUNT,
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


def _add_tune(commands: _Commands) -> None:
    _add_command(
        commands,
        "tune",
        _tune,
        "tune the torque controller (K_p, windows, K_d, observer, predictor) by "
        "closed-loop simulation of the climbing swing with Optuna: DIR/tuned.yaml, "
        "DIR/tune.md, plots; a second run resumes the study",
        config="TuneConfig YAML file",
        motor_model=True,
        trials={"type": _COUNT, "help": "trials to run (default 40)"},
        workers={
            "type": _COUNT,
            "help": "trials in flight (default: 2 local processes, or the cluster's "
            "threads)",
        },
        scheduler="a Dask scheduler's address, tcp://host:port (default: local "
        "processes)",
        quick="0.4 s of motion, 4 trials",
        out="output folder (the study)",
    )


def _add_reproduce(commands: _Commands) -> None:
    _add_command(
        commands,
        "reproduce",
        _reproduce,
        "identification and every experiment of the paper: DIR/report.md, "
        "DIR/results.json, figures and Meshcat replays",
        out=True,
        jobs={"default": 2, "help": "parallel processes"},
        quick="CI-sized durations",
        no_replays={"action": "store_true", "help": "skip Meshcat replays"},
    )


def _add_experiment(commands: _Commands) -> None:
    experiment = _add_command(
        commands,
        "experiment",
        _experiment,
        "run one experiment of the paper: estimation (Sec. 2), motion (5.3), force "
        "(5.4), stability (5.2), or the fault campaign of the supervised torque "
        "control (faults); the component analysis (5.5) needs motion and force: see "
        "reproduce",
    )
    experiment.add_argument("name", choices=list(_EXPERIMENTS))
    _add_options(
        experiment,
        "experiment",
        config="the experiment's config YAML file",
        motor_model=True,
        end={
            "type": _number(float, 0.0),
            "help": "motion: stop the climbing motion at (s)",
        },
        out=True,
    )


#: The commands, in the order `hrp2-drake --help` lists them.
_COMMANDS = (
    _add_simulate,
    _add_identify,
    _add_estimate,
    _add_validate,
    _add_track,
    _add_balance,
    _add_control,
    _add_sim_robot,
    _add_record,
    _add_sim_servo,
    _add_experiment,
    _add_calibrate,
    _add_reproduce,
    _add_tune,
)


def _parser() -> argparse.ArgumentParser:
    """The command line: `hrp2-drake [--debug] <command> [options]`."""
    parser = _Parser(
        prog="hrp2-drake",
        description="Torque control without joint-torque sensors (Del Prete et al. "
        "2015) on a simulated robot in Drake: HRP-2, the paper's, or any robot "
        "description.",
        parents=[_debug_option()],
    )
    commands = parser.add_subparsers(dest="command", required=True)
    for add_command in _COMMANDS:
        add_command(commands)
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
