"""Identification of the motor model from logged data (paper Sec. 3).

Every fit takes plain 1-D arrays of one joint, τ (N·m), q̇ (rad/s) and Δq (rad), and
returns a one-joint model named `joint_name`; combine joints with
`MotorModel.from_joints` or `fit_joints`.

- `fit_least_squares`: eq. 7.
- `fit_asymmetric`: eq. 8, by Newton's method ("newton") or as the QP of eq. 9 ("qp").
- `fit_two_stage`: Sec. 3.3.1, k_tau from zero-velocity samples, then k_v.
- `fit_piecewise_linear`: Sec. 3.2.1-3.2.2, the model the paper abandoned.
- `check_identified`: refuses a fitted model the data do not identify (k_tau or
  k_v not positive, or too little of Δq explained).

Data that cannot identify the model raise ValueError naming the joint and the problem.
All linear fits work on a regressor whose columns are scaled to unit RMS and a Δq scaled
to unit RMS, so that solver tolerances and the rank test do not depend on units.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import scipy.sparse
from pydrake.solvers import ClarabelSolver, MathematicalProgram, QuadraticCost

from hrp2_drake.identification.motor_model import (
    FitReport,
    MotorModel,
    PiecewiseLinearBranch,
    PiecewiseLinearMotorModel,
)

MIN_TORQUE = 1e-3  # N·m; data with max |τ| below this contain no torque.
MIN_VELOCITY = 1e-3  # rad/s; data with max |q̇| below this contain no motion.
MIN_SAMPLES = 10  # fewest samples of any fit (or stage, or piecewise segment).
MAX_CONDITION = 1e6  # largest condition number of the unit-RMS-column regressor.
MAX_NEWTON_ITERATIONS = 100
#: Least share of Δq's mean square that the least-squares fit of eq. 6 must explain
#: (1 - Σ(Δq̂ - Δq)² / ΣΔq²) for the data to identify a model. Noise-only Δq gives
#: ~0.03 on a short log; HRP-2's emulated right leg 0.54 (knee, whose error the
#: voltage limit shapes) to 0.98.
MIN_EXPLAINED = 0.2


def fit_least_squares(
    tau: np.ndarray,
    v: np.ndarray,
    delta_q: np.ndarray,
    coulomb: bool = False,
    joint_name: str = "joint",
) -> MotorModel:
    """Fits Δq = k_tau τ + k_v q̇ (+ k_c sign(q̇)) in the least-squares sense (eq. 7).

    Args:
        tau: Joint torques, N·m, shape (m,).
        v: Joint velocities, rad/s, shape (m,).
        delta_q: Position errors q_cmd - q, rad, shape (m,).
        coulomb: Also fit the Coulomb term k_c (the paper drops it).
        joint_name: Name of the joint in the returned model.
    """
    where = f"joint {joint_name!r}"
    tau, v, delta_q = _check_data(tau, v, delta_q, where)
    A = _regressor(tau, v, coulomb, where)
    A_hat, b_hat, scale = _scaled_problem(A, delta_q, where)
    x_hat = np.linalg.lstsq(A_hat, b_hat, rcond=None)[0]  # eq. 7
    return _linear_model(joint_name, x_hat * scale, "least_squares", 0, tau, v, delta_q)


def fit_asymmetric(
    tau: np.ndarray,
    v: np.ndarray,
    delta_q: np.ndarray,
    w: float = 100.0,
    method: str = "newton",
    coulomb: bool = False,
    joint_name: str = "joint",
) -> MotorModel:
    """Fits eq. 6 with the asymmetric penalty of eq. 8.

    Over-estimating |Δq| costs w times more than under-estimating it: the samples are
    split by the sign of Δq (Δq >= 0: residual z = a x - b; Δq < 0: z = -(a x - b)) and
    the fit minimises Σ Φ(z) with Φ(z) = w z² if z > 0 else z².

    Args:
        tau, v, delta_q, coulomb, joint_name: As in `fit_least_squares`.
        w: Weight of over-estimation, >= 1 (the paper uses 100; w = 1 is least squares).
        method: "newton": Newton's method on the convex eq. 8, each step a weighted
            least-squares solve of 2 (3) unknowns with numpy; fast for 10^6 samples.
            "qp": the QP of eq. 9 (2m slack variables, sparse) solved by Clarabel
            through Drake's MathematicalProgram; same optimum, slow beyond 10^5.
    """
    where = f"joint {joint_name!r}"
    tau, v, delta_q = _check_data(tau, v, delta_q, where)
    A = _regressor(tau, v, coulomb, where)
    x, iterations = _solve_asymmetric(
        A, delta_q, _overestimation_sign(delta_q), w, method, where
    )
    return _linear_model(
        joint_name, x, f"asymmetric {method}", iterations, tau, v, delta_q
    )


def fit_two_stage(
    tau: np.ndarray,
    v: np.ndarray,
    delta_q: np.ndarray,
    zero_velocity_threshold: float,
    w: float = 100.0,
    method: str = "newton",
    coulomb: bool = False,
    joint_name: str = "joint",
) -> MotorModel:
    """Two-stage asymmetric fit (Sec. 3.3.1).

    Stage 1 fits Δq = k_tau τ on the samples with |q̇| < zero_velocity_threshold;
    stage 2 fits Δq - k_tau τ = k_v q̇ (+ k_c sign(q̇)) on the others, k_tau fixed.
    Both stages use the asymmetric penalty of eq. 8, split by the sign of Δq, so that
    "over-estimation" keeps meaning |k_tau τ + k_v q̇| > |Δq| in stage 2.

    Args:
        tau, v, delta_q, w, method, coulomb, joint_name: As in `fit_asymmetric`.
        zero_velocity_threshold: |q̇| below which a sample is static, rad/s.
    """
    where = f"joint {joint_name!r}"
    tau, v, delta_q = _check_data(tau, v, delta_q, where)
    if not zero_velocity_threshold > 0:
        raise ValueError(
            f"{where}: zero_velocity_threshold must be > 0 rad/s, "
            f"got {zero_velocity_threshold}"
        )
    static = np.abs(v) < zero_velocity_threshold
    sign = _overestimation_sign(delta_q)

    threshold = f"{zero_velocity_threshold} rad/s"
    stage = f"{where}, stage 1 ({np.count_nonzero(static)} samples |v| < {threshold})"
    _check_data(tau[static], v[static], delta_q[static], stage)
    A1 = _regressor(tau[static], None, False, stage)
    (k_tau,), iterations_1 = _solve_asymmetric(
        A1, delta_q[static], sign[static], w, method, stage
    )

    moving = ~static
    stage = f"{where}, stage 2 ({np.count_nonzero(moving)} samples |v| >= {threshold})"
    _check_data(tau[moving], v[moving], delta_q[moving], stage)
    A2 = _regressor(None, v[moving], coulomb, stage)
    b2 = delta_q[moving] - k_tau * tau[moving]
    x2, iterations_2 = _solve_asymmetric(A2, b2, sign[moving], w, method, stage)

    x = np.concatenate([[k_tau], x2])
    return _linear_model(
        joint_name,
        x,
        f"two_stage {method}",
        iterations_1 + iterations_2,
        tau,
        v,
        delta_q,
    )


def fit_piecewise_linear(
    tau: np.ndarray,
    v: np.ndarray,
    delta_q: np.ndarray,
    initial_breakpoints: tuple[float, float] = (-0.5, 0.5),
    max_iterations: int = 10,
    central_slope_bounds: tuple[float, float] = (0.0, 0.1),
    tolerance: float = 1e-6,
    joint_name: str = "joint",
) -> PiecewiseLinearMotorModel:
    """Fits the piecewise-linear model of Sec. 3.2.1 with the algorithm of Sec. 3.2.2.

    Per branch (q̇ > 0 and q̇ < 0; samples with q̇ = 0 are unused), starting from the
    breakpoints (τ1, τ2), it repeats: fit one line by least squares to each of the three
    torque segments, set τ1 to the intersection of lines 1 and 2 and τ2 to that of lines
    2 and 3; until the breakpoints move by at most `tolerance` or after
    `max_iterations`. The result is continuous by construction. A segment with fewer
    than MIN_SAMPLES samples (or a single torque value) keeps its line of the previous
    iteration; at the first iteration that raises, as do crossing or parallel lines:
    the paper notes the algorithm needs a good initial guess.

    Args:
        tau, v, delta_q, joint_name: As in `fit_least_squares`.
        initial_breakpoints: Initial (τ1, τ2), N·m; the paper's (-0.5, 0.5) (legs).
        max_iterations: The paper's 10.
        central_slope_bounds: Bounds of the central slope k_τ2, rad/(N·m). The central
            segment spans the dead zone of the current control where Δq changes a lot
            for little τ, so the slope is positive and large (HRP-2's outer slopes are
            ~1e-4); the default upper bound 0.1 only excludes near-vertical lines whose
            intersections are ill-conditioned.
        tolerance: Breakpoint change below which the fit has converged, N·m.
    """
    where = f"joint {joint_name!r}"
    tau, v, delta_q = _check_data(tau, v, delta_q, where)
    if not initial_breakpoints[0] < initial_breakpoints[1]:
        raise ValueError(f"{where}: initial breakpoints must satisfy τ1 < τ2")
    if not central_slope_bounds[0] <= central_slope_bounds[1]:
        raise ValueError(f"{where}: central_slope_bounds must be (low, high)")
    if max_iterations < 1:
        raise ValueError(f"{where}: max_iterations must be >= 1")
    masks = {"positive": v > 0, "negative": v < 0}
    fits = {
        name: _fit_branch(
            tau[mask],
            delta_q[mask],
            np.array(initial_breakpoints, dtype=float),
            max_iterations,
            central_slope_bounds,
            tolerance,
            f"{where}, branch v {'>' if name == 'positive' else '<'} 0",
        )
        for name, mask in masks.items()
    }
    model = PiecewiseLinearMotorModel(
        joint_name, positive=fits["positive"][0], negative=fits["negative"][0]
    )
    for name, mask in masks.items():
        _, iterations, converged = fits[name]
        model.reports[name] = _report(
            model,
            f"piecewise_linear {name}",
            iterations,
            tau[mask],
            v[mask],
            delta_q[mask],
            converged,
        )
    return model


def overestimation_share(
    model,
    tau: np.ndarray,
    v: np.ndarray,
    delta_q: np.ndarray,
    tolerance: float = 1e-12,
):
    """Fraction of samples where the model over-estimates |Δq|.

    A sample is over-estimated when the prediction lies beyond the data in the direction
    of the data's sign, sign(Δq) (Δq̂ - Δq) > tolerance, with Δq = 0 counted as positive
    as in the split of eq. 8. The tolerance (rad) only absorbs round-off on exact data.
    Works for any model with `predict(tau, v)`.

    Returns:
        A float for 1-D data; a (n,) array, one share per joint, for (m, n) data.
    """
    delta_q = np.asarray(delta_q, dtype=float)
    predicted = model.predict(tau, v)
    if predicted.shape != delta_q.shape:
        raise ValueError(
            f"overestimation_share: delta_q {delta_q.shape} does not match the "
            f"prediction {predicted.shape}"
        )
    over = _overestimation_sign(delta_q) * (predicted - delta_q) > tolerance
    share = np.mean(over, axis=0)
    return float(share) if over.ndim == 1 else share


def explained_share(
    model, tau: np.ndarray, v: np.ndarray, delta_q: np.ndarray
) -> float:
    """1 - Σ(Δq̂ - Δq)² / ΣΔq²: the share of Δq's mean square (about zero: eq. 6 has
    no intercept) that a one-joint model explains; 0 or less for no better than
    Δq̂ = 0."""
    delta_q = np.asarray(delta_q, dtype=float)
    residual = model.predict(tau, v) - delta_q
    total = float(np.sum(delta_q**2))
    return 1.0 - float(np.sum(residual**2)) / total if total > 0 else 0.0


def check_identified(
    model: MotorModel,
    tau: np.ndarray,
    v: np.ndarray,
    delta_q: np.ndarray,
    min_explained: float | None = MIN_EXPLAINED,
) -> None:
    """Refuses a one-joint linear model that the data did not identify.

    A servo's Δq grows with the torque it delivers and with the velocity it follows
    (eq. 6): k_tau <= 0 or k_v <= 0 is noise, not a motor. And a fit that explains
    less than `min_explained` of Δq's mean square (`explained_share`; None: not
    tested) found no law in the data: too little excitation, or Δq is noise.

    Raises:
        ValueError: naming the joint, the fit and what is wrong.
    """
    name = model.joint_names[0]
    method = model.reports[name].method if name in model.reports else "fit"
    where = f"joint {name!r} ({method.replace('_', ' ')})"
    problems = [
        f"{symbol} = {value:.3g} {unit} is not > 0"
        for symbol, value, unit in (
            ("k_tau", model.k_tau[0], "rad/(N·m)"),
            ("k_v", model.k_v[0], "s"),
        )
        if not value > 0
    ]
    if min_explained is not None:
        share = explained_share(model, tau, v, delta_q)
        if share < min_explained:
            problems.append(
                f"the model explains {share:.1%} of delta_q's mean square "
                f"(< {min_explained:.0%})"
            )
    if problems:
        raise ValueError(
            f"{where}: the data do not identify a motor model: {'; '.join(problems)} "
            "(too little excitation, or delta_q is noise)"
        )


def fit_joints(
    fit: Callable[..., MotorModel],
    tau: np.ndarray,
    v: np.ndarray,
    delta_q: np.ndarray,
    joint_names: Sequence[str],
    **kwargs,
) -> MotorModel:
    """Applies a one-joint fit to every column of (m, n) arrays; returns one model."""
    tau, v, delta_q = (np.asarray(a, dtype=float) for a in (tau, v, delta_q))
    for name, value in (("tau", tau), ("v", v), ("delta_q", delta_q)):
        if value.ndim != 2 or value.shape[1] != len(joint_names):
            raise ValueError(
                f"fit_joints: {name} must have shape (m, {len(joint_names)}), "
                f"got {value.shape}"
            )
    return MotorModel.from_joints(
        {
            name: fit(tau[:, j], v[:, j], delta_q[:, j], joint_name=name, **kwargs)
            for j, name in enumerate(joint_names)
        }
    )


# --- data checks and the regressor of eq. 7 ---


def _check_data(tau, v, delta_q, where: str):
    """Returns float arrays; raises unless 1-D, equally long, finite, with some Δq."""
    arrays = {"tau": tau, "v": v, "delta_q": delta_q}
    arrays = {name: np.asarray(value, dtype=float) for name, value in arrays.items()}
    for name, value in arrays.items():
        if value.ndim != 1:
            raise ValueError(
                f"{where}: {name} must be a 1-D array (one joint), "
                f"got shape {value.shape}"
            )
    sizes = {name: value.size for name, value in arrays.items()}
    if len(set(sizes.values())) > 1:
        raise ValueError(f"{where}: mismatched lengths {sizes}")
    if sizes["tau"] < MIN_SAMPLES:
        raise ValueError(f"{where}: too few samples ({sizes['tau']} < {MIN_SAMPLES})")
    for name, value in arrays.items():
        bad = np.count_nonzero(~np.isfinite(value))
        if bad:
            raise ValueError(f"{where}: {name} has {bad} NaN or inf samples")
    if not np.any(arrays["delta_q"]):
        raise ValueError(
            f"{where}: delta_q is zero everywhere, no position error to fit"
        )
    return arrays["tau"], arrays["v"], arrays["delta_q"]


def _regressor(tau, v, coulomb: bool, where: str) -> np.ndarray:
    """The matrix A of eq. 7: columns τ, q̇, sign(q̇) (those given, k_c if coulomb)."""
    columns = []
    if tau is not None:
        _check_excited(tau, "no torque", "tau", "N·m", MIN_TORQUE, "k_tau", where)
        columns.append(tau)
    if v is not None:
        _check_excited(v, "no motion", "v", "rad/s", MIN_VELOCITY, "k_v", where)
        columns.append(v)
        if coulomb:
            columns.append(np.sign(v))
    return np.column_stack(columns)


def _check_excited(
    values: np.ndarray,
    lack: str,
    name: str,
    unit: str,
    minimum: float,
    parameter: str,
    where: str,
) -> None:
    """Raises ValueError if max |values| (`name`, in `unit`) is below `minimum`: the
    data do not excite `parameter` (`lack` says what is missing)."""
    peak = np.max(np.abs(values))
    if peak < minimum:
        raise ValueError(
            f"{where}: {lack} (max |{name}| = {peak:.3g} {unit} < {minimum}), "
            f"cannot identify {parameter}"
        )


def _scaled_problem(A: np.ndarray, b: np.ndarray, where: str):
    """Returns Â = A / d and b̂ = b / s, with unit-RMS columns and b̂, and the factor
    s / d that maps a solution x̂ of Â x̂ ≈ b̂ back to x; raises if Â is rank-deficient.
    """
    column_rms = np.sqrt(np.mean(A**2, axis=0))
    b_rms = np.sqrt(np.mean(b**2))
    if b_rms == 0:
        raise ValueError(f"{where}: the fitted position error is zero everywhere")
    A_hat = A / column_rms
    eigenvalues = np.linalg.eigvalsh(A_hat.T @ A_hat)
    condition = np.sqrt(eigenvalues[-1] / max(eigenvalues[0], 1e-300))
    if condition > MAX_CONDITION:
        raise ValueError(
            f"{where}: rank-deficient regressor (condition number {condition:.3g} > "
            f"{MAX_CONDITION:.0g}): tau, v (and sign(v)) are not independent"
        )
    return A_hat, b / b_rms, b_rms / column_rms


def _overestimation_sign(delta_q: np.ndarray) -> np.ndarray:
    """+1 where Δq >= 0, -1 where Δq < 0: the split of eq. 8."""
    return np.where(delta_q >= 0, 1.0, -1.0)


# --- eq. 8 by Newton's method, eq. 9 as a sparse QP ---


def _solve_asymmetric(A, b, sign, w: float, method: str, where: str):
    """Minimises Σ Φ(sign_i (a_i x - b_i)) (eq. 8); returns x and the iterations."""
    if not (np.isfinite(w) and w >= 1):
        raise ValueError(f"{where}: w must be a finite number >= 1, got {w}")
    A_hat, b_hat, scale = _scaled_problem(A, b, where)
    if method == "newton":
        x_hat, iterations = _asymmetric_newton(A_hat, b_hat, sign, w, where)
    elif method == "qp":
        x_hat, iterations = _asymmetric_qp(A_hat, b_hat, sign, w, where), 0
    else:
        raise ValueError(f"{where}: method must be 'newton' or 'qp', got {method!r}")
    return x_hat * scale, iterations


def _asymmetric_newton(A, b, sign, w: float, where: str):
    """Newton's method on eq. 8, started at the least-squares solution.

    The cost Σ ω_i (a_i x - b_i)², ω_i = w if sign_i (a_i x - b_i) > 0 else 1, is
    convex, piecewise quadratic and C¹; a Newton step minimises the quadratic of the
    current over-estimated set (a weighted least-squares solve of 2 or 3 unknowns).
    When the set at the new point is the same, that point is the exact optimum.
    Otherwise a backtracking line search guarantees descent.
    """

    def cost(x):
        r = A @ x - b
        over = np.flatnonzero(sign * r > 0)
        return r @ r + (w - 1) * (r[over] @ r[over]), over, r

    # The weighted sums split as Σ_all + (w - 1) Σ_over, so each step only touches the
    # over-estimated rows beyond the fixed Gram matrix.
    gram = A.T @ A
    x = np.linalg.solve(gram, A.T @ b)  # least squares (eq. 7)
    f, over, r = cost(x)
    for iteration in range(1, MAX_NEWTON_ITERATIONS + 1):
        A_over = A[over]
        hessian = gram + (w - 1) * (A_over.T @ A_over)  # half the Hessian of the cost
        gradient = A.T @ r + (w - 1) * (A_over.T @ r[over])  # half the gradient
        step = -np.linalg.solve(hessian, gradient)
        f_new, over_new, r_new = cost(x + step)
        if np.array_equal(over_new, over) or np.linalg.norm(step) <= 1e-13 * (
            1 + np.linalg.norm(x)
        ):
            return x + step, iteration
        t = 1.0
        while f_new > f + 1e-4 * t * 2 * gradient @ step and t > 1e-10:
            t /= 2
            f_new, over_new, r_new = cost(x + t * step)
        x, f, over, r = x + t * step, f_new, over_new, r_new
    raise RuntimeError(
        f"{where}: Newton's method on eq. 8 did not converge in "
        f"{MAX_NEWTON_ITERATIONS} iterations"
    )


def _asymmetric_qp(A, b, sign, w: float, where: str) -> np.ndarray:
    """Solves the QP of eq. 9 with Clarabel; returns x.

    min w ‖y^p‖² + ‖y^n‖²  s.t.  y^p >= S (A x - b),  y^n >= -S (A x - b),  y >= 0,
    with S = diag(sign): the paper's stacked [A^pos; -A^neg] rows, in data order.
    """
    m, p = A.shape
    prog = MathematicalProgram()
    x = prog.NewContinuousVariables(p, "x")
    y_p = prog.NewContinuousVariables(m, "y_p")
    y_n = prog.NewContinuousVariables(m, "y_n")
    # One 1x1 cost per slack, sharing two cost objects: Drake aggregates them into a
    # diagonal sparse Hessian, where one dense 2m x 2m Q would not fit in memory.
    cost_p = QuadraticCost(np.array([[2.0 * w]]), np.zeros(1), 0.0, True)
    cost_n = QuadraticCost(np.array([[2.0]]), np.zeros(1), 0.0, True)
    for i in range(m):
        prog.AddCost(cost_p, y_p[i : i + 1])
        prog.AddCost(cost_n, y_n[i : i + 1])
    # S A x - y^p <= S b  and  -S A x - y^n <= -S b, as one sparse constraint.
    SA = scipy.sparse.csr_matrix(sign[:, np.newaxis] * A)
    I = scipy.sparse.identity(m, format="csr")
    constraint = scipy.sparse.bmat([[SA, -I, None], [-SA, None, -I]], format="csc")
    prog.AddLinearConstraint(
        constraint,
        np.full(2 * m, -np.inf),
        np.concatenate([sign * b, -sign * b]),
        np.concatenate([x, y_p, y_n]),
    )
    prog.AddBoundingBoxConstraint(0.0, np.inf, y_p)
    prog.AddBoundingBoxConstraint(0.0, np.inf, y_n)
    # Clarabel's default tolerances (1e-8) on these unit-scaled data reproduce the
    # Newton optimum to ~1e-10 relative.
    result = ClarabelSolver().Solve(prog)
    if not result.is_success():
        raise RuntimeError(
            f"{where}: the QP of eq. 9 failed in Clarabel: "
            f"{result.get_solution_result()}"
        )
    return result.GetSolution(x)


# --- piecewise-linear fit (Sec. 3.2.2) ---


def _fit_branch(
    tau, delta_q, breakpoints, max_iterations, central_slope_bounds, tolerance, where
):
    """Alternating fit of one branch; returns (branch, iterations, converged)."""
    if tau.size < 3 * MIN_SAMPLES:
        raise ValueError(
            f"{where}: too few samples ({tau.size} < {3 * MIN_SAMPLES}) for three lines"
        )
    lines = [None, None, None]
    converged = False
    for iteration in range(1, max_iterations + 1):
        segment = np.searchsorted(breakpoints, tau)  # 0: τ <= τ1, 1: τ1 < τ <= τ2, 2
        for i in range(3):
            selected = segment == i
            if np.count_nonzero(selected) >= MIN_SAMPLES and np.ptp(tau[selected]) > 0:
                bounds = central_slope_bounds if i == 1 else (-np.inf, np.inf)
                lines[i] = _fit_line(tau[selected], delta_q[selected], bounds)
            elif lines[i] is None:
                raise ValueError(
                    f"{where}: segment {i + 1} of initial breakpoints {breakpoints} "
                    f"has {np.count_nonzero(selected)} samples (or a single torque), "
                    f"needs {MIN_SAMPLES}; choose other initial breakpoints"
                )
        (k1, q1), (k2, q2), (k3, q3) = lines
        with np.errstate(divide="ignore", invalid="ignore"):
            new_breakpoints = np.array([(q2 - q1) / (k1 - k2), (q3 - q2) / (k2 - k3)])
        if not (
            np.all(np.isfinite(new_breakpoints))
            and np.all(np.diff(new_breakpoints) > 0)
        ):
            raise ValueError(
                f"{where}: the lines no longer intersect in order (breakpoints "
                f"{new_breakpoints} at iteration {iteration}); choose other initial "
                "breakpoints or central_slope_bounds"
            )
        converged = np.max(np.abs(new_breakpoints - breakpoints)) <= tolerance
        breakpoints = new_breakpoints
        if converged:
            break
    (k1, q1), (k2, q2), (k3, q3) = lines
    return (
        PiecewiseLinearBranch([k1, k2, k3], [q1, q2, q3], breakpoints),
        iteration,
        converged,
    )


def _fit_line(tau, delta_q, slope_bounds) -> tuple[float, float]:
    """Least-squares line Δq = k τ + q with k in slope_bounds.

    For fixed k the best q is mean(Δq - k τ) and the reduced cost is a convex parabola
    in k, so clipping the unconstrained slope gives the bounded optimum.
    """
    tau_mean, delta_q_mean = np.mean(tau), np.mean(delta_q)
    tau_centered = tau - tau_mean
    k = np.dot(tau_centered, delta_q - delta_q_mean) / np.dot(
        tau_centered, tau_centered
    )
    k = float(np.clip(k, *slope_bounds))
    return k, float(delta_q_mean - k * tau_mean)


# --- the returned model and its report ---


def _linear_model(joint_name, x, method, iterations, tau, v, delta_q) -> MotorModel:
    """One-joint MotorModel from x = (k_tau, k_v[, k_c]), with its FitReport."""
    k_c = x[2] if len(x) > 2 else 0.0
    model = MotorModel([joint_name], [x[0]], [x[1]], [k_c])
    model.reports[joint_name] = _report(model, method, iterations, tau, v, delta_q)
    return model


def _report(model, method, iterations, tau, v, delta_q, converged=True) -> FitReport:
    residual = model.predict(tau, v) - delta_q
    return FitReport(
        method=method,
        samples=int(tau.size),
        residual_rms=float(np.sqrt(np.mean(residual**2))),
        overestimation_share=overestimation_share(model, tau, v, delta_q),
        iterations=int(iterations),
        converged=bool(converged),
    )
