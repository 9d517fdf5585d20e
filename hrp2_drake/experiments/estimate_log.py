"""`hrp2-drake estimate --robot FILE --log LOG`: offline torque estimation of a
recorded log (paper Sec. 2 with the non-causal filters of Sec. 3.4.3).

The log is robot-independent (README, "Log format"): an .npz with `t` (s), `q_measured`
(rad, one column per joint of the description, or the columns named by `joint_names`),
and the robot's sensors under their station port names: `imu_linear_acceleration`
(m/s²) and `imu_angular_velocity` (rad/s) if it has an IMU, `wrench_<sensor>` ([N·m;
N], sensor frame) per F/T sensor. `hrp2-drake simulate` and `identify` write such logs;
a real robot's logger writes the same arrays. If the log holds `joint_torque_true`
(simulation), the report compares τ̂ with it (evaluation only).

Outputs, in the output folder: `estimate.npz` (t, tau, unknown_wrench,
external_wrench_<sensor>), `estimate.md`, and `estimate_torques.png`.
"""

import json
from pathlib import Path

import numpy as np

from hrp2_drake.description import RobotDescription
from hrp2_drake.estimation.torque_estimator import FloatingBaseTorqueEstimator
from hrp2_drake.identification.dataset import check_log, log_columns, noncausal_torques


def read_estimation_log(path: str | Path, robot: RobotDescription) -> tuple[dict, list[str]]:
    """The log's arrays and its joint names (the description's if it names none); one
    ValueError naming the file and the array for anything the estimator cannot use."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"log '{path}' not found")
    try:
        with np.load(path, allow_pickle=False) as data:
            log = {key: data[key] for key in data.files}
    except (OSError, ValueError, EOFError) as error:
        raise ValueError(f"{path}: not a readable .npz log: {error}") from None
    names = [str(n) for n in log.pop("joint_names", robot.joints)]
    needed = ["t", "q_measured"]
    if robot.has_imu():
        needed += ["imu_linear_acceleration", "imu_angular_velocity"]
    needed += [f"wrench_{name}" for name in robot.force_torque_sensors]
    missing = [key for key in needed if key not in log]
    if missing:
        raise ValueError(
            f"{path}: the log lacks {missing}, which robot '{robot.name}' needs"
        )
    m = len(log["t"])
    for key in needed[1:] + (["joint_torque_true"] if "joint_torque_true" in log else []):
        if log[key].ndim != 2 or log[key].shape[0] != m:
            raise ValueError(
                f"{path}: '{key}' has shape {log[key].shape}, expected ({m}, columns)"
            )
    if log["q_measured"].shape[1] != len(names):
        raise ValueError(
            f"{path}: 'q_measured' has {log['q_measured'].shape[1]} columns for "
            f"{len(names)} joint names"
        )
    if "q_cmd" not in log:  # check_log wants it; the estimator does not
        log["q_cmd"] = log["q_measured"]
    check_log(log, names, str(path), robot.joints)
    return log, names


def estimate_log(
    robot: RobotDescription, log: dict, names: list[str], window: int = 81
) -> dict[str, np.ndarray]:
    """τ̂, the compensated external wrenches and the unknown wrench at every sample,
    from centred (non-causal) Savitzky-Golay estimates of the log's signals (the same
    path as identification's, `dataset.noncausal_torques`)."""
    if window % 2 == 0 or window < 3:
        raise ValueError(f"--window must be odd and >= 3, got {window}")
    t = np.asarray(log["t"], float)
    estimator = FloatingBaseTorqueEstimator(robot.make_plant(), robot.estimator_config())
    columns = log_columns(names, robot.joints)
    estimates, _ = noncausal_torques(log, columns, estimator, window, np.arange(len(t)))
    out = {
        "t": t,
        "tau": np.array([e.tau for e in estimates]),
        "unknown_wrench": np.array([e.unknown_wrench for e in estimates]),
    }
    for s, name in enumerate(robot.sensor_names()):
        out[f"external_wrench_{name}"] = np.array([e.external_wrenches[s] for e in estimates])
    return out


def run_estimate(
    robot: RobotDescription, log_path: Path, out: Path, window: int = 81
) -> dict:
    """The whole `hrp2-drake estimate`: read, estimate, write the arrays, the report
    and the plot; returns the summary."""
    log, names = read_estimation_log(log_path, robot)
    result = estimate_log(robot, log, names, window)
    np.savez_compressed(out / "estimate.npz", joint_names=np.array(robot.joints), **result)
    summary = {
        "robot": robot.name,
        "log": str(log_path),
        "samples": int(len(result["t"])),
        "window": window,
        "peak_torque": dict(zip(robot.joints, np.abs(result["tau"]).max(axis=0).tolist())),
    }
    margin = window  # the ends are fitted, not centred
    inside = slice(margin, len(result["t"]) - margin)
    if "joint_torque_true" in log:
        columns = [names.index(j) for j in robot.joints]
        error = result["tau"][inside] - log["joint_torque_true"][inside][:, columns]
        summary["rms_error_vs_truth"] = dict(
            zip(robot.joints, np.sqrt(np.mean(error**2, axis=0)).tolist())
        )
    (out / "estimate.json").write_text(json.dumps(summary, indent=2))
    _plot(robot, result, log, names, out / "estimate_torques.png")
    (out / "estimate.md").write_text(_markdown(robot, summary))
    return summary


def _plot(robot: RobotDescription, result: dict, log: dict, names: list[str], path: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    joints = robot.controlled_joints or robot.joints
    fig, axes = plt.subplots(len(joints), 1, figsize=(9, 1.8 * len(joints)), sharex=True)
    axes = np.atleast_1d(axes)
    labels = dict(zip(robot.controlled_joints, robot.labels()))
    for ax, joint in zip(axes, joints):
        j = robot.joints.index(joint)
        if "joint_torque_true" in log:
            ax.plot(result["t"], log["joint_torque_true"][:, names.index(joint)],
                    color="0.6", lw=2, label="true (simulation)")
        ax.plot(result["t"], result["tau"][:, j], lw=1, label="τ̂")
        ax.set_ylabel(f"{labels.get(joint, joint)}\n(N·m)")
    axes[0].legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("t (s)")
    fig.suptitle(f"{robot.name}: estimated joint torques")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _markdown(robot: RobotDescription, summary: dict) -> str:
    lines = [
        f"# Offline torque estimation: {robot.name}",
        "",
        f"Log `{summary['log']}`, {summary['samples']} samples, centred Savitzky-Golay "
        f"window {summary['window']} (paper Sec. 3.4.3); estimator of paper Sec. 2 "
        f"({'IMU' if robot.has_imu() else 'fixed base, no IMU'}, F/T sensors "
        f"{robot.sensor_names()}). Arrays: `estimate.npz`; plot: `estimate_torques.png`.",
        "",
        "| joint | peak τ̂ (N·m) |" + (" RMS error vs truth (N·m) |" if "rms_error_vs_truth" in summary else ""),
        "| --- | ---: |" + (" ---: |" if "rms_error_vs_truth" in summary else ""),
    ]
    for joint, peak in summary["peak_torque"].items():
        row = f"| {joint} | {peak:.2f} |"
        if "rms_error_vs_truth" in summary:
            row += f" {summary['rms_error_vs_truth'][joint]:.3f} |"
        lines.append(row)
    return "\n".join(lines) + "\n"
