"""Non-causal estimation over identification logs (paper Sec. 3.4.3).

Offline there is no need to wait for the future: every signal is filtered by a
Savitzky-Golay window centred on its sample (no delay), so q, q̇, q̈, the IMU and F/T
readings, and Δq all refer to the same instant. τ̂ then comes from the same
floating-base estimator as online (`FloatingBaseTorqueEstimator.estimate`).

In this module q̇ is `v` and q̈ `vdot` (the estimator's names); Δq = q_cmd − q is
`delta_q`.
"""

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from hrp2_drake.estimation.savitzky_golay import savgol_filter_offline
from hrp2_drake.estimation.torque_estimator import FloatingBaseTorqueEstimator
from hrp2_drake.identification.logs import (
    RobotLog,
    check_window_rate,
    log_columns,
    window_samples,
)


@dataclass
class IdentificationData:
    """Aligned, non-causal estimates of logs, every `stride`-th sample.

    Attributes:
        t: sample times (s), (m,).
        q, v, vdot: joint positions (rad), velocities q̇ (rad/s), accelerations q̈
            (rad/s²), (m, n), estimator joint order.
        tau: estimated joint torques τ̂ (N·m), (m, n).
        delta_q: Δq = q_cmd − q, smoothed by the same window (rad), (m, n).
        phase, excited_joint: the log's labels (see excitation.py), (m,); -1 where
            the log has none.
        tau_true: ground-truth joint torques if the log has them (simulation), else
            None.
        segment: the index of the log each sample comes from (`estimate_logs`).
        gain: the servo gain of each sample's log (NaN: the log states none).
        usable: inside its log's filter edges with its whole window valid (servo on).
        saturated: (m, n), the servo's output near its limit within the window.
    """

    t: np.ndarray
    q: np.ndarray
    v: np.ndarray
    vdot: np.ndarray
    tau: np.ndarray
    delta_q: np.ndarray
    phase: np.ndarray
    excited_joint: np.ndarray
    tau_true: np.ndarray | None = None
    segment: np.ndarray | None = None
    gain: np.ndarray | None = None
    usable: np.ndarray | None = None
    saturated: np.ndarray | None = None

    def joint(self, j: int, mask: np.ndarray | None = None):
        """(τ̂, q̇, Δq) of joint j (1-D arrays), the samples of `mask` only."""
        mask = slice(None) if mask is None else mask
        return self.tau[mask, j], self.v[mask, j], self.delta_q[mask, j]


def noncausal_torques(
    log: RobotLog,
    columns: Sequence[int],
    estimator: FloatingBaseTorqueEstimator,
    window: int,
    samples: np.ndarray,
    offsets: np.ndarray | None = None,
) -> tuple[list, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The estimator's `TorqueEstimate` at each of `samples` (indices), from centred
    Savitzky-Golay estimates of the log's encoders (`columns`: the estimator's joints,
    order 2), IMU (if the estimator has one) and F/T sensors (order 1); also
    (q, q̇, q̈) at those samples. `offsets` (k, 6): the F/T sensors' biases,
    subtracted from their compensated readings (as the online calibration does).

    Raises:
        ValueError: the log is shorter than the window, or lacks a signal the
            estimator needs.
    """
    t = log.t
    if len(t) < window:
        raise ValueError(
            f"the log has {len(t)} samples, fewer than the window {window}"
        )
    config = estimator.config()
    imu = bool(config.imu_frame)
    signals = ["imu_linear_acceleration", "imu_angular_velocity"] if imu else []
    signals += [f"wrench_{name}" for name in config.sensors]
    absent = [s for s in signals if s not in log.sensors]
    if absent:
        raise ValueError(f"the log lacks {absent}, which the estimator needs")
    dt = float(np.median(np.diff(t)))
    q, v, vdot = savgol_filter_offline(log.q_measured[:, columns], dt, window, 2)
    if imu:  # else a fixed base: the estimator knows its motion (none) and gravity
        sensors = log.sensors
        acc = savgol_filter_offline(sensors["imu_linear_acceleration"], dt, window, 1)[
            0
        ]
        gyro, alpha, _ = savgol_filter_offline(
            sensors["imu_angular_velocity"], dt, window, 1
        )
    wrenches = np.zeros((len(t), len(config.sensors), 6))
    for s, name in enumerate(config.sensors):
        wrenches[:, s] = savgol_filter_offline(
            log.sensors[f"wrench_{name}"], dt, window, 1
        )[0]
    estimates = [
        estimator.estimate(
            q[k],
            v[k],
            vdot[k],
            *((acc[k], gyro[k], alpha[k]) if imu else (None, None, None)),
            wrenches[k],
            offsets,
        )
        for k in samples
    ]
    return estimates, (q[samples], v[samples], vdot[samples])


def noncausal_estimates(
    log: RobotLog,
    estimator: FloatingBaseTorqueEstimator,
    window: int = 81,
    stride: int = 5,
) -> IdentificationData:
    """Filters a log with centred Savitzky-Golay windows and estimates τ̂ per sample.

    Args:
        log: an identification log (`logs.read_robot_log`, `RobotLog.from_arrays`):
            its sensors must include those of the estimator; its joints, the
            estimator's.
        estimator: the floating-base estimator (its config names joints and sensors).
        window: Savitzky-Golay window N, odd (centred windows need a middle sample; the
            paper's 80 becomes 81). Encoders and Δq: order 2; IMU and F/T: order 1.
        stride: keep every stride-th sample (neighbouring samples at 1 kHz add little).

    Raises:
        ValueError: the log lacks a signal or is shorter than the window.
        KeyError: an estimator joint is not in the log.
    """
    t = log.t
    cols = log_columns(log.joint_names, estimator.config().joints)
    keep = np.arange(0, len(t), stride)
    estimates, (q, v, vdot) = noncausal_torques(log, cols, estimator, window, keep)
    tau = np.array([e.tau for e in estimates]).reshape(len(keep), len(cols))
    dt = float(np.median(np.diff(t)))
    delta_q = savgol_filter_offline(
        log.q_cmd[:, cols] - log.q_measured[:, cols], dt, window, 2
    )[0]
    tau_true = None if log.tau_true is None else log.tau_true[keep][:, cols]
    # Unlabelled logs (e.g. from a real robot): phase and excited joint -1.
    labels = [
        np.full(len(keep), -1) if label is None else label[keep]
        for label in (log.phase, log.excited_joint)
    ]
    return IdentificationData(
        t[keep],
        q,
        v,
        vdot,
        tau,
        delta_q[keep],
        *labels,
        tau_true,
    )


def estimate_logs(
    logs: Sequence[RobotLog],
    estimator: FloatingBaseTorqueEstimator,
    window: float,
    stride: float,
    saturation_error: Callable[[float | None], float] = lambda gain: math.inf,
    saturation_margin: float = 1.0,
) -> IdentificationData:
    """`noncausal_estimates` of each log, concatenated, with the masks a fit needs.

    Args:
        window, stride: in seconds: the odd number of samples nearest to `window`
            at each log's own period, one sample every `stride` seconds.
        saturation_error: |q_cmd − q| (rad) at which the servo's output saturates at a
            gain (inf: never); a sample is `saturated` where any raw sample of its
            window exceeds `saturation_margin` times it.

    Raises:
        ValueError: naming the log: a log shorter than the window, and
            `noncausal_estimates`' errors.
    """
    parts = []
    joints = estimator.config().joints
    for k, log in enumerate(logs):
        period = log.period
        n_window = window_samples(window, period, f"{log.source}: window")
        n_stride = max(1, int(round(stride / period)))
        try:
            data = noncausal_estimates(log, estimator, n_window, n_stride)
        except ValueError as error:
            raise ValueError(f"{log.source}: {error}") from None
        keep = np.arange(0, len(log.t), n_stride)
        cols = log_columns(log.joint_names, joints)
        margin = n_window * period  # the filters' edges: fitted, not centred
        inside = (data.t > data.t[0] + margin) & (data.t < data.t[-1] - margin)
        error = np.abs(log.q_cmd[:, cols] - log.q_measured[:, cols])
        limit = saturation_margin * saturation_error(log.gain)
        data.segment = np.full(len(keep), k)
        data.gain = np.full(len(keep), math.nan if log.gain is None else log.gain)
        data.usable = inside & ~_within_window(~log.valid, n_window)[keep]
        data.saturated = _within_window(error >= limit, n_window)[keep]
        parts.append(data)
    return _concatenate(parts)


def check_logs(logs: Sequence[RobotLog], window: float, what: str) -> None:
    """Raises ValueError naming the log that cannot join an identification with the
    filter window `window` (s, the config key `what`): one that states no servo gain
    among logs that do (pooling needs each gain), one sampled too slowly for the
    window (`logs.check_window_rate`), one with a gap between samples longer than the
    window, one whose period puts fewer than 3 samples in the window."""
    gains = [log.gain for log in logs]
    if len(set(gains)) > 1 and None in gains:
        missing = logs[gains.index(None)].source
        raise ValueError(
            f"{missing}: states no servo gain (the robot description's logs.gain), "
            "but pooling it with logs of other gains needs each log's gain"
        )
    for log in logs:
        check_window_rate(log, window, what)
        gap, where = log.longest_gap
        if gap > window:
            raise ValueError(
                f"{log.source}: a gap of {gap:.3g} s between samples at t = "
                f"{where:.3f} s, longer than the filter window {window:g} s "
                f"({what}): split the log there or widen the window"
            )
        window_samples(window, log.period, f"{log.source}: {what}")


def _within_window(mask: np.ndarray, window: int) -> np.ndarray:
    """True where any sample of the centred window of `window` samples is in `mask`
    ((m,) or (m, n), per column)."""
    kernel = np.ones(window)
    columns = mask.reshape(len(mask), -1).astype(float)
    spread = np.column_stack(
        [np.convolve(c, kernel, mode="same") > 0.5 for c in columns.T]
    )
    return spread.reshape(mask.shape)


def _concatenate(parts: Sequence[IdentificationData]) -> IdentificationData:
    """One IdentificationData of several logs' (their samples one after another)."""
    if len(parts) == 1:
        return parts[0]
    names = [f.name for f in dataclasses.fields(IdentificationData)]
    joined = {}
    for name in names:
        values = [getattr(p, name) for p in parts]
        missing = any(v is None for v in values)
        joined[name] = None if missing else np.concatenate(values)
    return IdentificationData(**joined)


def split_blocks(
    t: np.ndarray, block: float = 1.0, held_out_every: int = 3
) -> np.ndarray:
    """Boolean mask of held-out samples: every `held_out_every`-th block of `block`
    seconds (contiguous blocks, so held-out samples are not neighbours of training
    ones)."""
    blocks = np.floor((t - t[0]) / block).astype(int)
    return blocks % held_out_every == held_out_every - 1
