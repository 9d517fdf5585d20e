"""`hrp2-drake validate --robot R --motor-model M.yaml --log L [L ...]`: an identified
motor model, or a digital twin (a servo file, `calibrate --log`'s servo.yaml), judged
by rollout on real logs (issue 18, item 3; issue 28).

For each log, the servo that obeys the model at the log's gain (`MotorModel.at_gain`,
`rollout.MotorModelServo`, saturated where the robot's position loop saturates), or
the emulated servo with the servo file's parameters at the log's gain
(`rollout.twin_servo`), replays the logged command open loop from the logged initial
position (`rollout.rollout`); the simulated position is compared with the measured
one: MAE and maximum |error| (mrad) over the whole log and over its servo-on samples
(where the servo is off a motor model has nothing to say: the joint falls freely,
with no friction). The way BAM and PACE report an actuator model.

Outputs, in the output folder: `validate_<log>.png` (per log: measured and
simulated position, the command, servo-off stretches shaded), `validate.md` (a
table, one row per log and joint, and the mean) and `validate.json`.

Everything is read and checked before the first rollout: a motor model that is
missing or malformed, one without every joint of the robot, a log that does not
import, a model that holds at a gain with a log that states none: one ValueError
(or OSError) each, which the command reports on one line.
"""

import json
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import yaml

from hrp2_drake import console
from hrp2_drake.description import RobotDescription
from hrp2_drake.identification.logs import RobotLog, read_robot_log
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.report import legend_beside, markdown_table, pyplot, save_figure
from hrp2_drake.robot.rollout import (
    RolloutErrors,
    RolloutResult,
    ServoFactory,
    model_servo,
    rollout,
    rollout_errors,
    twin_servo,
)
from hrp2_drake.robot.servo import ServoParams, load_servo_params

#: What `validate` rolls out: an identified motor model, or a servo file (a twin).
Model = MotorModel | ServoParams


def is_servo_file(path: str | Path) -> bool:
    """Whether the YAML file is a servo file (its parameters under `joints`, the
    emulated servo's: a digital twin), not a motor model (`joint_names`, `k_tau`)."""
    try:
        document = yaml.safe_load(Path(path).read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return False  # MotorModel.load names the problem
    return isinstance(document, dict) and "joints" in document


def load_model(robot: RobotDescription, path: str | Path) -> Model:
    """The motor model or the servo file at `path`, for the robot's joints.

    Raises:
        FileNotFoundError, IsADirectoryError: the file is missing.
        ValueError: naming the file: malformed, or without a joint of the robot.
    """
    path = Path(path)
    if is_servo_file(path):
        params = load_servo_params(path, robot.source_file)
        modelled = list(params.joints)
        kind = "servo file"
    else:
        model = MotorModel.load(path)
        modelled = model.joint_names
        kind = "motor model"
    missing = [j for j in robot.joints if j not in modelled]
    if missing:
        raise ValueError(
            f"{kind} {path}: has no joints {missing} of robot '{robot.name}' (it "
            f"models {modelled}; a rollout needs every joint of {list(robot.joints)})"
        )
    return params if kind == "servo file" else model.subset(list(robot.joints))


def servo_of_log(
    robot: RobotDescription, model: Model
) -> Callable[[RobotLog], ServoFactory]:
    """The servo that replays a log: the motor model's at the log's gain, or the
    twin's (the emulated servo with the servo file's parameters)."""
    if isinstance(model, ServoParams):
        return lambda log: twin_servo(model, log)
    return lambda log: model_servo(robot, model, log.gain)


def load_validation_inputs(
    robot: RobotDescription, model_path: str | Path, log_paths: Sequence[str | Path]
) -> tuple[Model, list[RobotLog]]:
    """The motor model or servo file (`load_model`) and the logs, checked.

    Raises:
        FileNotFoundError, IsADirectoryError: a file is missing.
        ValueError: naming the file: a malformed model or log, a model without
            every joint of the robot, a motor model with a gain and a log without.
    """
    model = load_model(robot, model_path)
    if not log_paths:
        raise ValueError("--log: no log given")
    logs = [read_robot_log(path, robot.logs, robot.joints) for path in log_paths]
    gain = getattr(model, "gain", 0.0)  # a motor model's; a twin's is per joint
    for log in logs:
        if gain and log.gain is None:
            raise ValueError(
                f"log {log.source}: states no servo gain, but motor model {model_path} "
                f"holds at gain {gain:g}: its parameters at the log's gain are "
                f"unknown (robot '{robot.name}' logs.gain names where a log states it)"
            )
    return model, logs


def run_validate(
    robot: RobotDescription,
    model_path: str | Path,
    log_paths: Sequence[str | Path],
    out: Path,
    time_step: float = 0.001,
) -> dict:
    """The whole `hrp2-drake validate` (module docstring); returns the summary that
    validate.json holds (errors in mrad, wall times in s)."""
    model, logs = load_validation_inputs(robot, model_path, log_paths)
    servo = servo_of_log(robot, model)
    names = _file_names([log.name for log in logs])
    rows = []
    for k, (log, name) in enumerate(zip(logs, names), start=1):
        console.say(
            f"rollout {k}/{len(logs)}: {log.name} ({log.t[-1]:.2f} s, gain "
            f"{'none' if log.gain is None else f'{log.gain:g}'})"
        )
        start = time.perf_counter()
        result = rollout(robot, log, servo(log), time_step)
        errors = rollout_errors(log, result.q_sim)
        figure = out / f"validate_{name}.png"
        _plot(robot, result, errors, figure, _kind(model))
        rows.append(_row(log, result, errors, figure, time.perf_counter() - start))
        console.say(
            f"rollout {k}/{len(logs)}: MAE {_joined(rows[-1], 'mae_mrad')} mrad, "
            f"servo on {_joined(rows[-1], 'mae_servo_on_mrad')} mrad "
            f"({result.wall_time:.2f} s)"
        )
    summary = {
        "robot": robot.name,
        "motor_model": str(model_path),
        "model_kind": "servo file" if isinstance(model, ServoParams) else "motor model",
        "model_gain": getattr(model, "gain", 0.0) or None,
        "joints": list(robot.joints),
        "time_step": time_step,
        "logs": rows,
        "mean": {
            key: {
                joint: _mean([row[key][joint] for row in rows])
                for joint in robot.joints
            }
            for key in (
                "mae_mrad",
                "max_error_mrad",
                "mae_servo_on_mrad",
                "max_error_servo_on_mrad",
            )
        },
        "mean_rollout_wall_time_s": float(
            np.mean([row["rollout_wall_time_s"] for row in rows])
        ),
    }
    (out / "validate.json").write_text(json.dumps(summary, indent=2))
    (out / "validate.md").write_text(_markdown(robot, model, summary))
    return summary


def _mean(values: list[float | None]) -> float | None:
    """The mean of the values that exist (None: a log without servo-on samples)."""
    present = [v for v in values if v is not None]
    return float(np.mean(present)) if present else None


def _file_names(names: list[str]) -> list[str]:
    """The logs' names for file names, made unique (two logs of the same name from two
    folders get _2, _3, ...)."""
    seen: dict[str, int] = {}
    unique = []
    for name in names:
        seen[name] = seen.get(name, 0) + 1
        unique.append(name if seen[name] == 1 else f"{name}_{seen[name]}")
    return unique


def _row(
    log: RobotLog,
    result: RolloutResult,
    errors: RolloutErrors,
    figure: Path,
    wall: float,
) -> dict:
    def per_joint(values: np.ndarray) -> dict[str, float | None]:
        return {
            j: None if np.isnan(v) else float(v * 1e3)
            for j, v in zip(log.joint_names, values)
        }

    return {
        "log": log.name,
        "source": log.source,
        "gain": log.gain,
        "duration_s": float(log.t[-1]),
        "samples": int(len(log.t)),
        "servo_on_share": float(np.mean(log.valid)),
        "mae_mrad": per_joint(errors.mae),
        "max_error_mrad": per_joint(errors.max_error),
        "mae_servo_on_mrad": per_joint(errors.mae_servo_on),
        "max_error_servo_on_mrad": per_joint(errors.max_error_servo_on),
        "rollout_wall_time_s": result.wall_time,
        "total_wall_time_s": wall,
        "figure": figure.name,
    }


def _joined(row: dict, key: str) -> str:
    values = row[key].values()
    return ", ".join("n/a" if v is None else f"{v:.1f}" for v in values)


def _servo_off_stretches(t: np.ndarray, valid: np.ndarray) -> list[tuple[float, float]]:
    """[(start, end)] (s) of the runs of samples where the servo is off."""
    off = np.concatenate([[False], ~valid, [False]]).astype(np.int8)
    starts = np.flatnonzero(np.diff(off) == 1)
    ends = np.flatnonzero(np.diff(off) == -1) - 1
    return [(float(t[a]), float(t[b])) for a, b in zip(starts, ends)]


def _kind(model: Model) -> str:
    """What is rolled out, in a figure's words."""
    return "twin" if isinstance(model, ServoParams) else "motor model"


def _plot(
    robot: RobotDescription,
    result: RolloutResult,
    errors: RolloutErrors,
    path: Path,
    kind: str = "motor model",
):
    log = result.log
    n = len(log.joint_names)
    fig, axes = pyplot().subplots(
        n, 1, figsize=(9, 2.6 * n), sharex=True, squeeze=False
    )
    labels = dict(zip(robot.controlled_joints, robot.labels()))
    stretches = _servo_off_stretches(log.t, log.valid)
    for j, (ax, joint) in enumerate(zip(axes[:, 0], log.joint_names)):
        for k, (a, b) in enumerate(stretches):
            ax.axvspan(a, b, color="0.9", lw=0, label="servo off" if k == 0 else None)
        ax.plot(log.t, log.q_cmd[:, j], "--", color="0.4", lw=1, label="command")
        ax.plot(log.t, log.q_measured[:, j], color="C0", lw=1.5, label="measured")
        simulated = "twin" if kind == "twin" else "model"
        ax.plot(
            log.t,
            result.q_sim[:, j],
            color="C1",
            lw=1,
            label=f"simulated ({simulated})",
        )
        ax.set_ylabel(f"{labels.get(joint, joint)}\n(rad)")
        ax.set_title(
            f"MAE {errors.mae[j] * 1e3:.1f} mrad, max {errors.max_error[j] * 1e3:.1f} "
            f"mrad; servo on: MAE {errors.mae_servo_on[j] * 1e3:.1f}, max "
            f"{errors.max_error_servo_on[j] * 1e3:.1f} mrad",
            fontsize=9,
        )
    legend_beside(axes[0, 0])
    axes[-1, 0].set_xlabel("t (s)")
    gain = "" if log.gain is None else f", gain {log.gain:g}"
    fig.suptitle(f"{robot.name}: rollout of the {kind} on {log.name}{gain}")
    save_figure(fig, path, dpi=100, tight=True)


def _markdown(robot: RobotDescription, model: Model, summary: dict) -> str:
    lines = [
        f"# Rollout validation: {robot.name}",
        "",
        f"{_what_rolls_out(model, summary)}; each log's command replayed "
        f"open loop from its first measured position at rest (plant step "
        f"{summary['time_step'] * 1e3:g} ms). Errors: |q_sim − q_measured| in mrad, "
        "over the whole log and over its servo-on samples (servo off, a motor model's "
        "joint is free: no friction).",
        "",
    ]
    header = [
        "log",
        "joint",
        "gain",
        "s",
        "servo on",
        "MAE",
        "max",
        "MAE servo on",
        "max servo on",
        "wall (s)",
    ]
    lines += markdown_table(header, _error_rows(summary), align="ll" + "r" * 8)
    lines += [
        "",
        "Figures: " + ", ".join(f"`{row['figure']}`" for row in summary["logs"]),
    ]
    return "\n".join(lines) + "\n"


def _what_rolls_out(model: Model, summary: dict) -> str:
    """The model the rollouts use, in words: a digital twin or a motor model."""
    if isinstance(model, ServoParams):
        return (
            f"Digital twin (servo file) `{summary['motor_model']}`: the emulated servo "
            "with its parameters at each log's gain"
        )
    gain = (
        f" (at servo gain {model.gain:g}, rescaled to each log's)" if model.gain else ""
    )
    return (
        f"Motor model `{summary['motor_model']}`{gain}, eq. 6 solved for the "
        "torque, Δq clamped where the servo's output saturates"
    )


def _error_rows(summary: dict) -> list[list]:
    """The table's rows: one per log and joint, then the mean over the logs."""
    rows = [
        [
            f"{row['log']}",
            joint,
            "—" if row["gain"] is None else f"{row['gain']:g}",
            f"{row['duration_s']:.2f}",
            f"{row['servo_on_share'] * 100:.0f}%",
            *_error_cells(row, joint),
            f"{row['rollout_wall_time_s']:.2f}",
        ]
        for row in summary["logs"]
        for joint in summary["joints"]
    ]
    rows += [  # the mean over the logs: no gain, duration, servo-on share
        [
            f"**mean of {len(summary['logs'])}**",
            joint,
            None,
            None,
            None,
            *_error_cells(summary["mean"], joint),
            f"{summary['mean_rollout_wall_time_s']:.2f}",
        ]
        for joint in summary["joints"]
    ]
    return rows


def _error_cells(values: dict, joint: str) -> list[str]:
    """The joint's MAE and maximum error, whole log and servo on (mrad)."""
    return [
        "n/a" if value is None or np.isnan(value) else f"{value:.1f}"
        for value in (
            values[key][joint]
            for key in (
                "mae_mrad",
                "max_error_mrad",
                "mae_servo_on_mrad",
                "max_error_servo_on_mrad",
            )
        )
    ]
