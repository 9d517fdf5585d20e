"""`hrp2-drake estimate --robot FILE --log LOG`: offline torque estimation of a
recorded log (paper Sec. 2 with the non-causal filters of Sec. 3.4.3).

The log is any log the project reads (`identification.logs.read_robot_log`): this
project's .npz (README, "Log format": `t` (s), `q_measured` (rad, one column per joint
of the description, or the columns named by `joint_names`), and the robot's sensors
under their station port names: `imu_linear_acceleration` (m/s²) and
`imu_angular_velocity` (rad/s) if it has an IMU, `wrench_<sensor>` ([N·m; N], sensor
frame) per F/T sensor), or the robot's own format (its description's `logs`: BAM's
JSON for the XL330), resampled to its grid. `hrp2-drake simulate` and `identify`
write .npz logs. If the log holds `joint_torque_true` (simulation), the report
compares τ̂ with it (evaluation only).

F/T sensors carry a bias. `--calibrate-offsets START:END` estimates it from a still
stretch of the log where nothing touches them (the mean compensated reading, as the
online chain's start-up calibration does) and subtracts it; without it, the report
warns when a sensor reads a wrench while the robot is still.

Outputs, in the output folder: `estimate.npz` (t, v, tau, unknown_wrench,
external_wrench_<sensor>), `estimate.md`, `estimate.json` and `estimate_torques.png`.
"""

import json
from pathlib import Path

import numpy as np

from hrp2_drake.description import RobotDescription
from hrp2_drake.estimation.estimator_config import estimator_config
from hrp2_drake.estimation.torque_estimator import FloatingBaseTorqueEstimator
from hrp2_drake.identification.dataset import noncausal_torques
from hrp2_drake.identification.logs import (
    RobotLog,
    check_window_rate,
    log_columns,
    read_robot_log,
)
from hrp2_drake.report import legend_beside, markdown_table, pyplot, save_figure


def read_estimation_log(path: str | Path, robot: RobotDescription) -> RobotLog:
    """The log (`read_robot_log`, without commands), checked: one ValueError naming
    the file and the array for anything the estimator cannot use."""
    log = read_robot_log(path, robot.logs, robot.joints, command=False)
    needed = (
        ["imu_linear_acceleration", "imu_angular_velocity"] if robot.has_imu() else []
    )
    needed += [f"wrench_{name}" for name in robot.force_torque_sensors]
    missing = [key for key in needed if key not in log.sensors]
    if missing:
        raise ValueError(
            f"{path}: the log lacks {missing}, which robot '{robot.name}' needs"
        )
    return log


def estimate_log(
    robot: RobotDescription,
    log: RobotLog,
    window: int = 81,
    offsets: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """τ̂, the compensated external wrenches and the unknown wrench at every sample,
    from centred (non-causal) Savitzky-Golay estimates of the log's signals (the same
    path as identification's, `dataset.noncausal_torques`), and q̂̇ ("v"). `offsets`
    (k, 6): the F/T sensors' biases (`calibrate_offsets`)."""
    if window % 2 == 0 or window < 3:
        raise ValueError(f"--window must be odd and >= 3, got {window}")
    check_window_rate(log, window * log.period, f"--window {window} samples")
    estimator = FloatingBaseTorqueEstimator(robot.make_plant(), estimator_config(robot))
    columns = log_columns(log.joint_names, robot.joints)
    estimates, (_, v, _) = noncausal_torques(
        log, columns, estimator, window, np.arange(len(log.t)), offsets
    )
    out = {
        "t": log.t,
        "v": v,
        "tau": np.array([e.tau for e in estimates]),
        "unknown_wrench": np.array([e.unknown_wrench for e in estimates]),
    }
    for s, name in enumerate(robot.sensor_names()):
        out[f"external_wrench_{name}"] = np.array(
            [e.external_wrenches[s] for e in estimates]
        )
    return out


def parse_segment(
    text: str, log: RobotLog, where: str = "--calibrate-offsets"
) -> slice:
    """'START:END' (s, log time) as the log's sample indices; a ValueError naming
    `where` if it is malformed, empty, or outside the log."""
    try:
        start, end = (float(x) for x in text.split(":"))
    except ValueError:
        raise ValueError(
            f"{where} '{text}': expected START:END in seconds, e.g. 0.2:0.5"
        ) from None
    t = log.t
    if not (np.isfinite(start) and np.isfinite(end) and start < end):
        raise ValueError(f"{where} '{text}': START must be < END, both finite")
    if start < t[0] or end > t[-1]:
        raise ValueError(f"{where} '{text}': outside the log ({t[0]:g} to {t[-1]:g} s)")
    rows = np.flatnonzero((t >= start) & (t < end))
    if len(rows) < 10:
        raise ValueError(f"{where} '{text}': {len(rows)} samples, fewer than 10")
    return slice(rows[0], rows[-1] + 1)


def calibrate_offsets(
    robot: RobotDescription, result: dict, segment: slice
) -> np.ndarray:
    """The F/T sensors' biases (k, 6, sensor frame, [N·m; N]): the mean compensated
    reading over `segment`, a still stretch of the log where nothing touches the
    sensors (what the online chain's start-up calibration does)."""
    nested = FloatingBaseTorqueEstimator(
        robot.make_plant(), estimator_config(robot)
    ).nested_sensors()
    if nested:
        raise ValueError(
            f"--calibrate-offsets: robot '{robot.name}' has nested F/T sensors "
            f"{sorted(nested)}: their readings are not separable offline; calibrate "
            "them online (TorqueControlConfig.offset_calibration_time)"
        )
    return np.array(
        [
            result[f"external_wrench_{name}"][segment].mean(axis=0)
            for name in robot.sensor_names()
        ]
    )


#: A still robot: every joint's q̂̇ below this (rad/s) for at least STILL_TIME (s).
STILL_SPEED, STILL_TIME = 0.01, 0.1
#: A bias shows when a still sensor reads more than this (N, N·m).
BIAS_FORCE, BIAS_TORQUE = 1.0, 0.1


def bias_warnings(robot: RobotDescription, result: dict, margin: int) -> list[str]:
    """Sensors that read a wrench while the robot is still (its first still stretch
    after `margin` samples): a bias, or a contact. One sentence each."""
    t, v = result["t"], result["v"]
    still = np.max(np.abs(v), axis=1) < STILL_SPEED
    still[:margin] = still[len(t) - margin :] = False
    dt = float(np.median(np.diff(t)))
    needed = max(int(STILL_TIME / dt), 2)
    run = np.convolve(still, np.ones(needed, int), "valid") == needed
    if not np.any(run):
        return []
    start = int(np.argmax(run))
    rows = slice(start, start + needed)
    warnings = []
    for name in robot.sensor_names():
        mean = result[f"external_wrench_{name}"][rows].mean(axis=0)
        torque, force = np.linalg.norm(mean[:3]), np.linalg.norm(mean[3:])
        if force > BIAS_FORCE or torque > BIAS_TORQUE:
            warnings.append(
                f"sensor '{name}' reads {force:.2f} N and {torque:.3f} N·m while the "
                f"robot is still ({t[rows.start]:.2f} to {t[rows.stop - 1]:.2f} s): a "
                "bias, or a contact. If nothing touched it then, `--calibrate-offsets "
                f"{t[rows.start]:.2f}:{t[rows.stop - 1]:.2f}` removes the bias"
            )
    return warnings


def run_estimate(
    robot: RobotDescription,
    log_path: Path,
    out: Path,
    window: int = 81,
    calibrate: str = "",
) -> dict:
    """The whole `hrp2-drake estimate`: read, estimate (with the F/T offsets of the
    still segment `calibrate`, 'START:END', if given), write the arrays, the report
    and the plot; returns the summary."""
    log = read_estimation_log(log_path, robot)
    segment = parse_segment(calibrate, log) if calibrate else None
    result = estimate_log(robot, log, window)
    offsets = None
    if segment is not None:
        offsets = calibrate_offsets(robot, result, segment)
        result = estimate_log(robot, log, window, offsets)
    np.savez_compressed(
        out / "estimate.npz", joint_names=np.array(robot.joints), **result
    )
    margin = window  # the ends are fitted, not centred
    summary = {
        "robot": robot.name,
        "log": str(log_path),
        "samples": int(len(result["t"])),
        "window": window,
        "peak_torque": dict(
            zip(robot.joints, np.abs(result["tau"]).max(axis=0).tolist())
        ),
        "offsets": None
        if offsets is None
        else {name: row.tolist() for name, row in zip(robot.sensor_names(), offsets)},
        "calibration_segment": calibrate or None,
        "bias_warnings": []
        if offsets is not None
        else bias_warnings(robot, result, margin),
    }
    inside = slice(margin, len(result["t"]) - margin)
    if log.tau_true is not None:
        error = result["tau"][inside] - log.tau_true[inside]
        summary["rms_error_vs_truth"] = dict(
            zip(robot.joints, np.sqrt(np.mean(error**2, axis=0)).tolist())
        )
    (out / "estimate.json").write_text(json.dumps(summary, indent=2))
    _plot(robot, result, log, out / "estimate_torques.png")
    (out / "estimate.md").write_text(_markdown(robot, summary))
    return summary


def _plot(robot: RobotDescription, result: dict, log: RobotLog, path: Path):
    joints = robot.controlled_joints or robot.joints
    fig, axes = pyplot().subplots(
        len(joints), 1, figsize=(9, 1.8 * len(joints)), sharex=True
    )
    axes = np.atleast_1d(axes)
    labels = dict(zip(robot.controlled_joints, robot.labels()))
    for ax, joint in zip(axes, joints):
        j = robot.joints.index(joint)
        if log.tau_true is not None:
            ax.plot(
                result["t"],
                log.tau_true[:, j],
                color="0.6",
                lw=2,
                label="true (simulation)",
            )
        ax.plot(result["t"], result["tau"][:, j], lw=1, label="τ̂")
        ax.set_ylabel(f"{labels.get(joint, joint)}\n(N·m)")
    legend_beside(axes[0])
    axes[-1].set_xlabel("t (s)")
    fig.suptitle(f"{robot.name}: estimated joint torques")
    save_figure(fig, path, dpi=100, tight=True)


def _markdown(robot: RobotDescription, summary: dict) -> str:
    lines = [
        f"# Offline torque estimation: {robot.name}",
        "",
        f"Log `{summary['log']}`, {summary['samples']} samples, centred Savitzky-Golay "
        f"window {summary['window']} (paper Sec. 3.4.3); estimator of paper Sec. 2 "
        f"({'IMU' if robot.has_imu() else 'fixed base, no IMU'}, F/T sensors "
        f"{robot.sensor_names()}). Arrays: `estimate.npz`; plot: "
        "`estimate_torques.png`.",
        "",
    ]
    truth = summary.get("rms_error_vs_truth")  # None: no ground truth in the log
    header = ["joint", "peak τ̂ (N·m)"]
    header += ["RMS error vs truth (N·m)"] if truth is not None else []
    rows = [
        [joint, f"{peak:.2f}"] + ([f"{truth[joint]:.3f}"] if truth is not None else [])
        for joint, peak in summary["peak_torque"].items()
    ]
    lines += markdown_table(header, rows)
    if summary["offsets"]:
        lines += [
            "",
            f"F/T offsets calibrated over {summary['calibration_segment']} s "
            "(mean compensated reading, [τ (N·m); f (N)], sensor frame), subtracted:",
            "",
        ]
        lines += [
            f"- {name}: {np.round(row, 3).tolist()}"
            for name, row in summary["offsets"].items()
        ]
    for warning in summary["bias_warnings"]:
        lines += ["", f"**Warning:** {warning}."]
    return "\n".join(lines) + "\n"
