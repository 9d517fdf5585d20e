"""`hrp2-drake calibrate --robot R --log ...`: a robot's digital twin from its logs.

Parses, calls, reports: reads the logs (`identification.logs.read_robot_log`), checks
there is enough of them, cross-validates across their gains and fits the twin on all
of them (`robot.twin_calibration`: the emulated servo's parameters by rollout), and
writes servo.yaml, calibrate.md, calibrate.json and a figure per gain.
"""

import json
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from hrp2_drake.description import RobotDescription
from hrp2_drake.identification.logs import RobotLog, read_robot_log
from hrp2_drake.report import legend_beside, markdown_table, pyplot, save_figure
from hrp2_drake.robot.rollout import rollout, twin_servo
from hrp2_drake.robot.servo import ServoParams, load_servo_params, save_servo_params
from hrp2_drake.robot.twin_calibration import (
    TWIN_PARAMETERS,
    CrossValidation,
    TwinConfig,
    TwinFit,
    check_enough_data,
    cross_validate,
    fit_twin,
    twin_errors,
)

# ------------------------------------------------------------------ the command
#: The project's goal for a twin (issue 18): its cross-gain mean rollout MAE at least
#: this much below the least-squares motor model's on the same logs.
TWIN_GOAL = 0.20


def run_calibrate_logs(
    robot: RobotDescription,
    log_paths: Sequence[str | Path],
    out: Path,
    config: TwinConfig | None = None,
    install: bool = False,
) -> dict:
    """The whole `hrp2-drake calibrate --robot R --log ...`: cross-validation across
    the logs' gains (if they have several), then the twin fitted on every log, written
    as out/servo.yaml (and the robot's servo file with `install`), with
    calibrate.md, calibrate.json and a figure per gain."""
    config = config or TwinConfig()
    config.validate()
    if not log_paths:
        raise ValueError("--log: no log given")
    logs = [read_robot_log(path, robot.logs, robot.joints) for path in log_paths]
    several = _gains(logs) > 1
    check_enough_data(logs, config)  # before the first rollout, as every fit does
    for gain in sorted({log.gain for log in logs if log.gain is not None}) * several:
        check_enough_data([log for log in logs if log.gain == gain], config)
    prior = load_servo_params("", robot.source_file)
    out.mkdir(parents=True, exist_ok=True)
    cross = cross_validate(robot, logs, prior, config) if several else []
    final = fit_twin(robot, logs, prior, config, label="twin on every log")
    fitted_mae = {
        k: v["mae"] for k, v in twin_errors(robot, logs, final.params).items()
    }
    header = [
        f"{robot.name}'s emulated servo: a digital twin calibrated to {len(logs)} real "
        f"logs by rollout (hrp2-drake calibrate --log; {final.evaluations} rollouts of "
        f"every log, scipy least_squares). Logs: {', '.join(final.logs)}.",
        f"Prior: the servo file before ({robot.servo_path('').name}). k5 = "
        "stall_current / no_load_speed (one mechanism: a voltage-driven DC servo).",
    ]
    save_servo_params(final.params, out / "servo.yaml", header)
    if install:
        save_servo_params(final.params, robot.servo_path(""), header)
    summary = _summary(robot, logs, prior, final, fitted_mae, cross)
    (out / "calibrate.json").write_text(json.dumps(summary, indent=2))
    figures = _plot(robot, logs, final, out)
    (out / "calibrate.md").write_text(_markdown(robot, summary, figures, install))
    return summary


def _gains(logs: Sequence[RobotLog]) -> int:
    return len({log.gain for log in logs if log.gain is not None})


def _summary(
    robot,
    logs,
    prior,
    final: TwinFit,
    fitted_mae: dict[str, float],
    cross: list[CrossValidation],
) -> dict:
    def values(params: ServoParams) -> dict[str, dict[str, float]]:
        return {
            joint: {
                name: getattr(params.joints[joint], name)
                for name in list(TWIN_PARAMETERS) + ["k5"]
            }
            for joint in robot.joints
        }

    summary = {
        "robot": robot.name,
        "logs": [log.name for log in logs],
        "fit": {
            "rollouts": final.evaluations,
            "wall_time_s": final.wall_time,
            "rms_error_start_mrad": math.sqrt(final.cost_start / len(logs)) * 1e3,
            "rms_error_end_mrad": math.sqrt(final.cost_end / len(logs)) * 1e3,
            "message": final.message,
        },
        "parameters": values(final.params),
        "prior": values(prior),
        "mae_on_fitted_logs_mrad": {k: v * 1e3 for k, v in fitted_mae.items()},
    }
    if cross:
        rows = []
        for c in cross:
            for name in c.twin_errors:
                rows.append(
                    {
                        "train_gain": c.train_gain,
                        "log": name,
                        "twin_mae_mrad": c.twin_errors[name]["mae"] * 1e3,
                        "model_mae_mrad": c.model_errors[name]["mae"] * 1e3,
                        "twin_max_mrad": c.twin_errors[name]["max"] * 1e3,
                        "model_max_mrad": c.model_errors[name]["max"] * 1e3,
                    }
                )
        twin = float(np.mean([r["twin_mae_mrad"] for r in rows]))
        model = float(np.mean([r["model_mae_mrad"] for r in rows]))
        summary["cross_gain"] = {
            "rows": rows,
            "twin_mean_mae_mrad": twin,
            "least_squares_mean_mae_mrad": model,
            "twin_below_least_squares": 1.0 - twin / model,
            "goal": TWIN_GOAL,
            "goal_met": bool(1.0 - twin / model >= TWIN_GOAL),
        }
    return summary


def _markdown(robot, summary: dict, figures: list[str], install: bool) -> str:
    fit = summary["fit"]
    lines = [
        f"# A digital twin of {robot.name} from its logs",
        "",
        f"The emulated servo's parameters fitted by rollout to {len(summary['logs'])} "
        f"logs: {fit['rollouts']} rollouts of every log in {fit['wall_time_s']:.0f} s; "
        f"RMS position error {fit['rms_error_start_mrad']:.1f} mrad with the prior, "
        f"{fit['rms_error_end_mrad']:.1f} mrad after ({fit['message']}). "
        + (
            "Installed as the robot's servo file."
            if install
            else "Written to servo.yaml here (`--install` makes it the robot's)."
        ),
        "",
    ]
    cross = summary.get("cross_gain")
    if cross:
        verdict = "met" if cross["goal_met"] else "NOT met"
        lines += [
            "## Cross-gain validation",
            "",
            "Fitted on the logs of one gain, rolled out on the logs of the other: the "
            "twin, and the least-squares motor model (`identify --fit least-squares`) "
            "identified on the same logs. Position MAE / maximum error (mrad), whole "
            "log.",
            "",
            *_cross_gain_table(cross),
            "",
            f"Project goal (not the paper's): the twin's cross-gain mean MAE at least "
            f"{TWIN_GOAL:.0%} below the least-squares model's: "
            f"{cross['twin_below_least_squares']:.1%} below, **{verdict}**.",
            "",
        ]
    lines += ["## Parameters (prior → twin)", ""]
    lines += markdown_table(
        ["joint", "parameter", "prior", "twin"],
        [
            [
                f"{joint}",
                f"{name}",
                f"{summary['prior'][joint][name]:.4g}",
                f"{value:.4g}",
            ]
            for joint, values in summary["parameters"].items()
            for name, value in values.items()
        ],
        align="llrr",
    )
    lines += ["", "## Rollout MAE of the twin on the logs it was fitted on (mrad)", ""]
    lines += markdown_table(
        ["log", "MAE"],
        [[f"{k}", f"{v:.1f}"] for k, v in summary["mae_on_fitted_logs_mrad"].items()],
    )
    lines += ["", "## Figures", ""] + [f"![{f}]({f})" for f in figures]
    return "\n".join(lines) + "\n"


def _cross_gain_table(cross: dict) -> list[str]:
    """Per log of the other gain: the twin's and the least-squares model's rollout
    errors (mrad), then their mean MAE."""
    rows = [
        [
            f"{r['train_gain']:g}",
            f"{r['log']}",
            f"{r['twin_mae_mrad']:.1f}",
            f"{r['twin_max_mrad']:.1f}",
            f"{r['model_mae_mrad']:.1f}",
            f"{r['model_max_mrad']:.1f}",
        ]
        for r in cross["rows"]
    ]
    rows.append(
        [
            None,
            "**mean**",
            f"**{cross['twin_mean_mae_mrad']:.1f}**",
            None,
            f"**{cross['least_squares_mean_mae_mrad']:.1f}**",
            None,
        ]
    )
    header = [
        "fitted on gain",
        "log",
        "twin MAE",
        "twin max",
        "least squares MAE",
        "least squares max",
    ]
    return markdown_table(header, rows, align="rlrrrr")


def _plot(robot, logs: Sequence[RobotLog], final: TwinFit, out: Path) -> list[str]:
    """Measured vs twin position on the first log of each gain (first joint)."""
    chosen = list({log.gain: log for log in reversed(logs)}.values())[::-1]
    fig, axes = pyplot().subplots(
        len(chosen), 1, figsize=(9, 3.2 * len(chosen)), squeeze=False
    )
    for ax, log in zip(axes[:, 0], chosen):
        q = rollout(robot, log, twin_servo(final.params, log)).q_sim
        ax.plot(log.t, log.q_cmd[:, 0], color="0.6", lw=1, label="command")
        ax.plot(log.t, log.q_measured[:, 0], "k", lw=1.4, label="measured")
        ax.plot(log.t, q[:, 0], "tab:red", lw=1.2, ls="--", label="twin (rollout)")
        ax.set_title(
            f"{log.name} (gain {log.gain:g})" if log.gain else log.name, fontsize=10
        )
        ax.set_xlabel("t (s)")
        ax.set_ylabel(f"{robot.joints[0]} (rad)")
        ax.grid(True, alpha=0.3)
        legend_beside(ax, borderaxespad=None)  # matplotlib's pad from the axes
    name = "calibrate_rollouts.png"
    save_figure(fig, out / name, tight=True)
    return [name]
