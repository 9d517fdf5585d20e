"""Non-causal estimation over an identification log (paper Sec. 3.4.3).

Offline there is no need to wait for the future: every signal is filtered by a
Savitzky-Golay window centred on its sample (no delay), so q, q̇, q̈, the IMU and F/T
readings, and Δq all refer to the same instant. τ̂ then comes from the same
floating-base estimator as online (`FloatingBaseTorqueEstimator.estimate`).
"""

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from hrp2_drake.estimation.savitzky_golay import savgol_filter_offline
from hrp2_drake.estimation.torque_estimator import FloatingBaseTorqueEstimator


@dataclass
class IdentificationData:
    """Aligned, non-causal estimates of a log, every `stride`-th sample.

    Attributes:
        t: sample times (s), (m,).
        q, dq, ddq: joint positions (rad), velocities (rad/s), accelerations (rad/s²),
            (m, n), estimator joint order.
        tau: estimated joint torques τ̂ (N·m), (m, n).
        delta_q: Δq = q_cmd − q, smoothed by the same window (rad), (m, n).
        phase, excited_joint: the log's labels (see excitation.py), (m,); -1 where
            the log has none.
        tau_true: ground-truth joint torques if the log has them (simulation), else None.
    """

    t: np.ndarray
    q: np.ndarray
    dq: np.ndarray
    ddq: np.ndarray
    tau: np.ndarray
    delta_q: np.ndarray
    phase: np.ndarray
    excited_joint: np.ndarray
    tau_true: np.ndarray | None = None

    def joint(self, j: int, mask: np.ndarray | None = None):
        """(τ̂, q̇, Δq) of joint j (1-D arrays), the samples of `mask` only."""
        mask = slice(None) if mask is None else mask
        return self.tau[mask, j], self.dq[mask, j], self.delta_q[mask, j]


def noncausal_estimates(
    log: dict[str, np.ndarray],
    log_joint_names: Sequence[str],
    estimator: FloatingBaseTorqueEstimator,
    window: int = 81,
    stride: int = 5,
) -> IdentificationData:
    """Filters a log with centred Savitzky-Golay windows and estimates τ̂ per sample.

    Args:
        log: an identification log (excitation.load_log): "t", "q_cmd", "q_measured",
            "imu_linear_acceleration", "imu_angular_velocity", "wrench_<sensor>" for
            every sensor of the estimator.
        log_joint_names: joint names of the log's columns; must contain the
            estimator's joints.
        estimator: the floating-base estimator (its config names joints and sensors).
        window: Savitzky-Golay window N, odd (centred windows need a middle sample; the
            paper's 80 becomes 81). Encoders and Δq: order 2; IMU and F/T: order 1.
        stride: keep every stride-th sample (neighbouring samples at 1 kHz add little).

    Raises:
        ValueError: the log lacks a signal, has NaN, or is shorter than the window.
        KeyError: an estimator joint is not in the log.
    """
    t = np.asarray(log["t"], float)
    if len(t) < window:
        raise ValueError(f"the log has {len(t)} samples, fewer than the window {window}")
    dt = float(np.median(np.diff(t)))
    config = estimator.config()
    column = {name: i for i, name in enumerate(log_joint_names)}
    missing = [j for j in config.joints if j not in column]
    if missing:
        raise KeyError(f"the log has no column for joints {missing}")
    cols = [column[j] for j in config.joints]
    signals = ["imu_linear_acceleration", "imu_angular_velocity"] + [
        f"wrench_{name}" for name in config.sensors
    ]
    absent = [s for s in signals if s not in log]
    if absent:
        raise ValueError(f"the log lacks {absent}, which the estimator needs")

    q, dq, ddq = savgol_filter_offline(log["q_measured"][:, cols], dt, window, 2)
    delta_q = savgol_filter_offline(log["q_cmd"][:, cols] - log["q_measured"][:, cols], dt, window, 2)[0]
    acc = savgol_filter_offline(log["imu_linear_acceleration"], dt, window, 1)[0]
    gyro, alpha, _ = savgol_filter_offline(log["imu_angular_velocity"], dt, window, 1)
    wrenches = np.stack(
        [savgol_filter_offline(log[f"wrench_{name}"], dt, window, 1)[0] for name in config.sensors],
        axis=1,
    )
    keep = np.arange(0, len(t), stride)
    tau = np.empty((len(keep), len(cols)))
    for row, k in enumerate(keep):
        tau[row] = estimator.estimate(q[k], dq[k], ddq[k], acc[k], gyro[k], alpha[k], wrenches[k]).tau
    tau_true = log["joint_torque_true"][keep][:, cols] if "joint_torque_true" in log else None
    # Unlabelled logs (e.g. from a real robot): phase and excited joint -1.
    labels = {
        key: np.asarray(log[key])[keep] if key in log else np.full(len(keep), -1)
        for key in ("phase", "excited_joint")
    }
    return IdentificationData(
        t[keep], q[keep], dq[keep], ddq[keep], tau, delta_q[keep],
        labels["phase"], labels["excited_joint"], tau_true,
    )


def split_blocks(t: np.ndarray, block: float = 1.0, held_out_every: int = 3) -> np.ndarray:
    """Boolean mask of held-out samples: every `held_out_every`-th block of `block`
    seconds (contiguous blocks, so held-out samples are not neighbours of training
    ones)."""
    return (np.floor((t - t[0]) / block).astype(int) % held_out_every) == held_out_every - 1
