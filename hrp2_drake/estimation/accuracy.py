"""How an estimate is judged against the ground truth: the one definition of τ̂'s error.

The paper's estimator is noncausal (Sec. 2): "at time t we do not estimate q̇(t) but
q̇(t − t_d), where t_d is the estimation delay. The same applies for q, v̇ and the
force/torque measurements". So τ̂'s sample i describes the robot t_d earlier, and its
error is τ̂(t_i) − τ(t_i − t_d): the truth delayed by the chain's delay
(`estimator_config.estimation_delay`), in samples of the log. The estimation
experiment (`paper/estimation.py`) and the balance experiment both judge τ̂ so.

    delay = estimation_delay(estimator) / log_period  # samples, maybe fractional
    e = errors(t, tau_estimated, joint_torque_true, delay, start)
    e["ratio"] < GOAL_RMS_OVER_PEAK
"""

import math

import numpy as np


def shifted(signal: np.ndarray, samples: float) -> np.ndarray:
    """signal (rows: samples) delayed by a fractional number of samples >= 0, linear
    interpolation: out[i] = signal(i − samples); rows before the start are NaN."""
    if not samples >= 0:
        raise ValueError(f"shifted: a delay of {samples} samples, expected >= 0")
    whole = math.floor(samples)
    frac = samples - whole
    out = np.full(signal.shape, np.nan)
    hi = np.arange(len(signal)) - whole  # signal(i − whole)
    lo = hi - 1  # signal(i − whole − 1)
    ok = (hi >= 0) & (hi < len(signal)) & ((lo >= 0) | (frac == 0.0))
    out[ok] = (1.0 - frac) * signal[hi[ok]] + frac * signal[np.maximum(lo[ok], 0)]
    return out


def errors(
    t: np.ndarray,
    estimate: np.ndarray,
    true: np.ndarray,
    delay_samples: float,
    start: float,
) -> dict:
    """An estimate against the truth delayed by `delay_samples` (`shifted`), on the
    samples t >= start where the delayed truth exists.

    Args:
        t: (samples,) the log's times (s), uniform.
        estimate: (samples, signals), e.g. τ̂ (N·m).
        true: (samples, signals), the ground truth in the same units, sampled at t.
        delay_samples: the estimate's delay in samples of t (the chain's delay over
            the log's period); 0 compares with the truth of the same instant.
        start: the first time (s) counted.

    Returns:
        {"rms": per signal RMS error, "peak": per signal peak |truth| (of the delayed
        truth, on the same samples), "ratio": rms / peak}, numpy arrays.
    """
    reference = shifted(true, delay_samples)
    rows = (t >= start) & np.all(np.isfinite(reference), axis=1)
    if not rows.any():
        raise ValueError(
            f"errors: no sample from t = {start:g} s with the truth delayed by "
            f"{delay_samples:g} samples ({len(t)} samples in the log)"
        )
    error = estimate[rows] - reference[rows]
    rms = np.sqrt(np.mean(error**2, axis=0))
    peak = np.max(np.abs(reference[rows]), axis=0)
    return {"rms": rms, "peak": peak, "ratio": rms / np.maximum(peak, 1e-12)}
