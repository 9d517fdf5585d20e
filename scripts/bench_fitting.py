"""Times the asymmetric-penalty fit (paper eq. 8-9) from 10^3 to 10^6 samples.

The paper's solvers (CVX, qpOASES) failed beyond 10^4 samples. Here "newton" solves
eq. 8 directly (goal: 10^6 samples under 0.3 s) and "qp" builds eq. 9 as a sparse
MathematicalProgram solved by Clarabel (run up to 10^5 samples). Least squares (eq. 7)
on the same data is the baseline for ratios.

    python scripts/bench_fitting.py
"""

import time

import numpy as np

from hrp2_drake.identification.fitting import fit_asymmetric, fit_least_squares

QP_MAX_SAMPLES = 10**5


def synthetic_log(m: int, seed: int = 0):
    """(τ, q̇, Δq) of one joint: half static high-torque pushes, half an
    increasing-amplitude sinusoid (Sec. 3.4), with a current dead zone and noise."""
    rng = np.random.default_rng(seed)
    m_static = m // 2
    t = np.linspace(0.0, 20.0, m - m_static)
    amplitude, omega = 0.05 + 0.03 * t, np.pi
    tau = np.concatenate(
        [
            80.0 * np.sin(2 * np.pi * rng.uniform(size=m_static)),
            -2.0 * amplitude * omega**2 * np.sin(omega * t),
        ]
    )
    dq = np.concatenate(
        [1e-3 * rng.standard_normal(m_static), amplitude * omega * np.cos(omega * t)]
    )
    delta_q = (
        0.177e-3 * tau
        + 7.698e-3 * dq
        + 2e-3 * np.sign(tau + 30.0 * dq)
        + 2e-4 * rng.standard_normal(m)
    )
    return tau, dq, delta_q


def _best_time(function, repeats: int) -> tuple[float, object]:
    best, result = np.inf, None
    for _ in range(repeats):
        start = time.perf_counter()
        result = function()
        best = min(best, time.perf_counter() - start)
    return best, result


def bench_fitting(sizes=(10**3, 10**4, 10**5, 10**6)) -> list[dict]:
    """Returns one row per (fit, size): {"name", "samples", "seconds"} (best of 3;
    a single run for QPs of 10^5 samples and more), plus "note" for skipped QPs and
    "relative_difference" of QP vs Newton (max over k_tau, k_v)."""
    rows = []
    for m in sizes:
        log = synthetic_log(m)
        seconds, _ = _best_time(lambda log=log: fit_least_squares(*log), 3)
        rows.append({"name": "fit_least_squares", "samples": m, "seconds": seconds})
        seconds, newton = _best_time(
            lambda log=log: fit_asymmetric(*log, method="newton"), 3
        )
        rows.append({"name": "fit_asymmetric newton", "samples": m, "seconds": seconds})
        row = {"name": "fit_asymmetric qp", "samples": m, "seconds": None}
        if m > QP_MAX_SAMPLES:
            row["note"] = f"skipped: the QP is run up to {QP_MAX_SAMPLES} samples"
        else:
            repeats = 3 if m < QP_MAX_SAMPLES else 1
            seconds, qp = _best_time(
                lambda log=log: fit_asymmetric(*log, method="qp"), repeats
            )
            row["seconds"] = seconds
            row["relative_difference"] = float(
                max(
                    abs(qp.k_tau[0] / newton.k_tau[0] - 1),
                    abs(qp.k_v[0] / newton.k_v[0] - 1),
                )
            )
        rows.append(row)
    return rows


if __name__ == "__main__":
    for row in bench_fitting():
        seconds = "-" if row["seconds"] is None else f"{row['seconds']:.4f} s"
        extra = row.get("note", "")
        if "relative_difference" in row:
            extra = f"QP vs Newton: {row['relative_difference']:.1e} relative"
        print(f"{row['name']:<24} {row['samples']:>8} samples  {seconds:>10}  {extra}")
