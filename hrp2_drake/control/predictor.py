"""DelayPredictor: carries the delayed estimates q̂̇, τ̂, f̂ forward to the present with
the identified motor model (the paper's future work, Sec. 6: "The state estimation
algorithm could also exploit [the identified model] to predict the future state and
so nullify estimation delays").

The estimation chain (Savitzky-Golay filters + RNEA) outputs q̂̇, q̂̈, τ̂ and f̂ that
describe the robot `delay` seconds ago (39.5 ms for the paper's 80-sample window at
1 kHz, `EstimationChain.delay()`, and one period more when the predictor's output is
read, `loop_delay`), but the Δq the controller sent since then is known.
Per joint, the motor model (eq. 6, without its Coulomb term)

    Δq = K_τ τ + K_v q̇,            τ = m q̈ + τ_rest

(m the joint-space inertia diagonal, τ_rest gravity, coupling, external torque) is a
first-order system in q̇, time constant T = K_τ m / K_v, driven by Δq:

    K_τ m q̈ + K_v q̇ = Δq − K_τ τ_rest.

The predictor uses it incrementally, anchored at the delayed estimates: over the
horizon H it takes the motor-model disturbance d = τ̂ − (Δq − K_v q̂̇) / K_τ (what the
DisturbanceObserver estimates) as constant, and so only the *change* of q̈ is
predicted by the model,

    q̈(t) = q̂̈ + [(Δq(t) − Δq_0) − K_v (q̇(t) − q̂̇)] / (K_τ m),              (1)

with Δq_0 the Δq acting at the delayed instant. With an exact model (d = 0) this is
the same as holding τ_rest = τ̂ − m q̂̈ constant; with a model error (a K_τ off by
20 %) the error scales with the change over the horizon, not with the torque itself
(holding τ_rest and trusting the model's absolute torque would bias a joint that
carries 50 N·m of gravity by 8 N·m). Δq is held over each control period, so (1)
has an exact discretization: per step of length h, with x = q̇ − q̂̇,

    x⁺ = Φ x + Γ (q̂̈ + (Δq_j − Δq_0) / (K_τ m)),   Φ = e^(−h/T),  Γ = T (1 − Φ),

a linear recurrence whose end value over the horizon is one weighted sum of the
buffered Δq (the weights are precomputed; one pass of O(M n) per tick):

    q̇_pred = q̂̇ + x_end
    τ_pred = τ̂ + m (q̈_end − q̂̈) = τ̂ + [(Δq_end − Δq_0) − K_v x_end] / K_τ
    f_pred = f̂ + H ḟ̂                                    (first-order extrapolation)

Alignment (all times on the controller's clock, ticks t_k = k · period):
  - the estimates read at tick k describe the robot at t_k − delay (`delay` may be a
    fraction of a period: the paper's 40.5 ms is 40.5 periods, and the first step of
    the recurrence is then the fraction). In the torque chain the predictor steps
    after the Δq controller of its tick and the controller reads it at the next
    (the loop's one tick): its inputs of tick k serve tick k + 1, which is this
    alignment with `delay` = `estimator_config.loop_delay` (the estimation delay
    plus that period);
  - the Δq read at tick k was computed by the controller at tick k − 1 and acts on
    the joint over [t_{k−1} + λ, t_k + λ), λ = `command_latency` (whole periods). In
    a Drake diagram with a discrete plant stepping at the control period λ = one
    period: the plant's step at t_k reads the Δq that the controller computed at
    t_{k−1} (the default); on a robot that applies a command as soon as it is sent,
    λ = 0; a servo's transport latency adds to it;
  - the prediction is for t_k + λ, the end of the newest known Δq: the horizon is
    H = delay + λ, covering M = ceil(H / period) buffered Δq. The outputs are discrete
    state, read by a consumer at t_{k+1}: with λ = one period, exactly when they
    describe the robot; τ_pred is the torque just before that instant (under the Δq
    read at tick k, before the next one takes over);
  - until M Δq have been read the outputs pass the delayed estimates through (and f̂
    is extrapolated); before the first tick they are zero.

Assumptions and their limits:
  - d (equivalently τ_rest, for an exact model) is constant over H: a change of
    gravity torque with the posture, of coupling with the other joints' motion or of
    an external force within the 40 ms is not predicted (f̂ only by extrapolation);
  - the inertia is diagonal and constant (m is taken at construction, e.g. at the
    start pose): the coupling through the off-diagonal terms of M(q) is in d;
  - the servo obeys eq. 6 exactly: its dead zone, current saturation, direction-
    dependent friction and any latency not set in `command_latency` are
    unmodelled. A Coulomb term K_c sign(q̇) of constant sign cancels in (1); a
    joint that reverses within H gets it wrong by up to 2 K_c / K_τ in τ_pred;
  - q̂̈ is the noisiest input (a second derivative), and it enters the predicted
    velocity with a weight of about min(H, T): the predictor trades delay for
    noise. `max_velocity_correction` and `max_torque_correction` bound what the
    prediction may add to the delayed estimate.
"""

import math
from dataclasses import dataclass, field

import numpy as np
from pydrake.systems.framework import Context

from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.kernels import kernel
from hrp2_drake.multibody import check_joint_names
from hrp2_drake.step import Step, StepSystem

_WHERE = "DelayPredictor"
# The bookkeeping state: newest ring row, Δq read so far (capped at M), consecutive
# bad ticks, total bad ticks.
_NEWEST_ROW, _NUM_SAMPLES, _CONSECUTIVE_BAD, _TOTAL_BAD = range(4)
# Horizons within this many periods of a whole number are whole (float rounding).
_WHOLE_TOLERANCE = 1e-9


# yaml_load_typed reads the field types at run time: this module must not use
# `from __future__ import annotations`.
@dataclass
class DelayPredictorConfig:
    """Configuration of the DelayPredictor.

    Args:
        joints: the predicted joints (the torque-controlled ones), in the order of
            every joint vector of the predictor; the motor model must have them all.
        delay: the age of q̂̇, q̂̈, τ̂ (and f̂, ḟ̂) when the predictor reads them (s):
            in the torque chain `estimator_config.loop_delay` (the Alignment in
            the module docstring); need not be whole periods.
        inertia: the joint-space inertia diagonal m, one value > 0 per joint (kg·m²),
            e.g. of the mass matrix at the start pose (rotor inertia included).
        command_latency: from the controller's update that computes a Δq to the
            start of the interval over which it acts on the joint (s, rounded to
            whole periods): one period for a Drake discrete plant stepping at the
            control period, 0 on a robot that applies a command when it is sent,
            plus a servo's transport latency. The prediction is for this long after
            the tick.
        wrench_size: k, the number of wrench entries (6 per F/T sensor) to
            extrapolate; 0: no wrench ports.
        max_velocity_correction: bound on |q̇_pred − q̂̇| (rad/s), one value for every
            joint or one per joint; .inf: no bound.
        max_torque_correction: bound on |τ_pred − τ̂| (N·m), one value or one per
            joint; .inf: no bound.
        period: the control period (s; a keyword, no default), the controller's.
    """

    joints: list[str] = field(default_factory=list)
    delay: float = 0.0405
    inertia: list[float] = field(default_factory=list)
    command_latency: float = 0.001
    wrench_size: int = 0
    max_velocity_correction: list[float] = field(default_factory=lambda: [math.inf])
    max_torque_correction: list[float] = field(default_factory=lambda: [math.inf])
    period: float = field(kw_only=True)

    def validate(self) -> None:
        """Raises ValueError naming the bad field (yaml_load_typed does not call it)."""
        where = "DelayPredictorConfig"
        check_joint_names(self.joints, where)
        n = len(self.joints)
        if not (math.isfinite(self.period) and self.period > 0):
            raise ValueError(f"{where}.period={self.period} must be > 0 (s)")
        if not (math.isfinite(self.delay) and self.delay >= 0):
            raise ValueError(f"{where}.delay={self.delay} must be >= 0 (s)")
        if not (math.isfinite(self.command_latency) and self.command_latency >= 0):
            raise ValueError(
                f"{where}.command_latency={self.command_latency} must be >= 0 (s)"
            )
        inertia = np.asarray(self.inertia, dtype=float)
        if inertia.shape != (n,) or not np.all(np.isfinite(inertia) & (inertia > 0)):
            raise ValueError(
                f"{where}.inertia: {n} finite values > 0 (kg·m², one per joint of "
                f"{self.joints}), got {self.inertia}"
            )
        if isinstance(self.wrench_size, bool) or not (
            isinstance(self.wrench_size, (int, np.integer)) and self.wrench_size >= 0
        ):
            raise ValueError(
                f"{where}.wrench_size={self.wrench_size!r} must be an integer >= 0"
            )
        for name in ("max_velocity_correction", "max_torque_correction"):
            values = getattr(self, name)
            if len(values) not in (1, n) or any(not v > 0 for v in values):
                raise ValueError(f"{where}.{name}: 1 or {n} values > 0, got {values}")


# The constants of DelayPredictorStep (`_constants`, packed once): the scalars n, M,
# k, H, whether each correction is bounded; then the weights W (2, M, n) and C
# (2, n) of `_linear_prediction`, and the bounds (lower, upper) of the velocity and
# of the torque correction (4, n; ±inf where unbounded).
_S_N, _S_M, _S_K, _S_HORIZON, _S_BOUND_V, _S_BOUND_TAU = range(6)
_S_COUNT = 6
# What `_predictor_step` returns on inputs of the wrong size (the step raises).
_BAD_SIZE = -1


# Whole: one compiled pass on the tick's arrays; a split costs calls (scripts/bench.py)
@kernel
def _predictor_step(v, vdot, tau, delta_q, wrench, rate, state, constants):
    """One period of DelayPredictorStep on its `state` with its packed `constants`
    (`DelayPredictorStep.step`; `wrench` and `rate` of size k, empty when k = 0).
    Returns 0, or _BAD_SIZE (nothing changed).

    Elementwise in the order of operations of the numpy version it replaced (bit
    for bit), and the weighted sum over the M buffered Δq accumulated oldest first
    from 0, which is np.einsum's order for n >= 2 (bit for bit); for n = 1 einsum
    sums in another order (measured: up to 3e-13 of τ_pred's magnitude on random
    Δq, 0 for n >= 2). The other sums only test finiteness.
    """
    c = constants
    n, M, k = int(c[_S_N]), int(c[_S_M]), int(c[_S_K])
    # The state: v_predicted, tau_predicted, wrench_predicted (k), input_fault,
    # counters (4), ring (2M, n).
    fault = 2 * n + k
    counters = fault + 1
    ring = counters + 4
    if (
        v.shape[0] != n
        or vdot.shape[0] != n
        or tau.shape[0] != n
        or delta_q.shape[0] != n
        or wrench.shape[0] != k
        or rate.shape[0] != k
        or state.shape[0] != ring + 2 * M * n
    ):
        return _BAD_SIZE
    bad = False
    ready = True
    row = 0
    total = 0.0
    for i in range(n):
        total += delta_q[i]
    delta_q_finite = math.isfinite(total)
    if not delta_q_finite:
        bad = True  # (also counted without a horizon)
    if M:
        # Δq read now into rows r and r + M of the ring (a non-finite entry: that
        # joint's previous Δq, 0 before any).
        row = int(state[counters])
        samples = int(state[counters + 1])
        newest = (row + 1) % M
        for i in range(n):
            value = delta_q[i]
            if not delta_q_finite and not math.isfinite(value):
                value = state[ring + row * n + i] if samples else 0.0
            state[ring + newest * n + i] = value
            state[ring + (newest + M) * n + i] = value
        row = newest
        state[counters] = row
        samples = min(samples + 1, M)
        state[counters + 1] = samples
        ready = samples >= M
    velocity, acceleration, torque = 0.0, 0.0, 0.0
    for i in range(n):
        velocity += v[i]
        acceleration += vdot[i]
        torque += tau[i]
    if not math.isfinite(velocity + acceleration + torque):
        bad = True  # hold v_predicted and tau_predicted
    elif ready and M:
        # [q̇_pred − q̂̇, τ_pred − τ̂] = Σ_j W_j ⊙ Δq_j + C ⊙ q̂̈ over the window of
        # Δq, oldest first (rows r + 1 .. r + M), bounded; eq. (1) of the module
        # docstring over the horizon.
        weights = _S_COUNT
        vdot_weights = weights + 2 * M * n
        bounds = vdot_weights + 2 * n
        window = ring + (row + 1) * n
        for output in range(2):
            bounded = c[_S_BOUND_V + output] != 0.0
            for i in range(n):
                correction = 0.0
                w = weights + output * M * n + i
                for j in range(M):
                    correction += c[w + j * n] * state[window + j * n + i]
                correction = correction + c[vdot_weights + output * n + i] * vdot[i]
                if bounded:
                    lower = c[bounds + 2 * output * n + i]
                    upper = c[bounds + (2 * output + 1) * n + i]
                    correction = min(max(correction, lower), upper)
                if output == 0:
                    state[i] = v[i] + correction
                else:
                    state[n + i] = tau[i] + correction
    else:  # the delayed estimates pass through
        for i in range(n):
            state[i] = v[i]
            state[n + i] = tau[i]
    if k:
        total = 0.0
        for i in range(k):
            total += wrench[i]
        for i in range(k):
            total += rate[i]
        if math.isfinite(total):
            horizon = c[_S_HORIZON]
            for i in range(k):
                state[2 * n + i] = rate[i] * horizon + wrench[i]  # f̂ + H ḟ̂
        else:
            bad = True  # hold wrench_predicted
    consecutive = state[counters + 2]
    if bad or consecutive != 0.0:
        # Count a bad tick, or clear the consecutive count on the first good one.
        consecutive = (consecutive + 1.0) * (1.0 if bad else 0.0)
        state[counters + 2] = consecutive
        state[counters + 3] += 1.0 if bad else 0.0
        state[fault] = consecutive
    return 0


class DelayPredictorStep(Step):
    """The predictor's per-tick arithmetic (module docstring), without Drake.

    Args:
        motor_model: the identified motor model (K_τ, K_v; its Coulomb term is not
            used); it must have every joint of config.joints.
        config: the DelayPredictorConfig.

    State (`Step`; n = len(config.joints), k = config.wrench_size, M =
    num_buffered()): `v_predicted` (n, rad/s), `tau_predicted` (n, N·m),
    `wrench_predicted` (k, N and N·m; only if k > 0), `input_fault` (1: consecutive
    ticks with a non-finite input), `counters` (4: newest ring row, Δq read so far
    (at most M), consecutive bad ticks, total bad ticks), and `ring` ((2M, n), rad;
    only if M > 0): the last M Δq read, each written twice (rows r and r + M) so
    that the window, oldest first, is the contiguous rows r + 1 .. r + M.

    A tick is one numba kernel (`_predictor_step`) on the state and the weights,
    packed once into one array (`hrp2_drake.kernels`); it allocates nothing.
    """

    def __init__(self, motor_model: MotorModel, config: DelayPredictorConfig):
        super().__init__()
        config.validate()
        self._config = config
        try:
            model = motor_model.subset(config.joints)
        except KeyError as error:
            raise KeyError(f"{_WHERE}: {error.args[0]}") from None
        errors = model.sign_errors()
        if errors:
            raise ValueError(f"{_WHERE}: motor model {errors[0]}")
        n = self._n = len(config.joints)
        k = self._k = int(config.wrench_size)
        period = config.period
        self._k_tau, self._k_v = model.k_tau, model.k_v
        self._inertia = np.asarray(config.inertia, dtype=float)
        self._latency_periods = round(config.command_latency / period)
        horizon_periods = config.delay / period + self._latency_periods
        whole = math.floor(horizon_periods + _WHOLE_TOLERANCE)
        fraction = horizon_periods - whole
        if fraction < _WHOLE_TOLERANCE:
            fraction = 0.0
        self._horizon = horizon_periods * period
        # M buffered Δq; the oldest acts over a fraction of a period when the horizon
        # is not whole.
        self._steps = M = whole + (fraction > 0.0)
        steps = np.full(M, period)
        if fraction > 0.0:
            steps[0] = fraction * period
        self._prediction_weights, self._vdot_weights = self._linear_prediction(steps)
        self._declare("v_predicted", np.zeros(n))
        self._declare("tau_predicted", np.zeros(n))
        if k:
            self._declare("wrench_predicted", np.zeros(k))
        self._declare("input_fault", 0.0)
        self._declare("counters", np.zeros(4))
        if M:
            self._declare("ring", np.zeros((2 * M, n)))
        # The constants of the kernel, packed once (_S_* scalars, W, C, bounds).
        bounds = [
            _bounds(config.max_velocity_correction, n),
            _bounds(config.max_torque_correction, n),
        ]
        scalars = np.zeros(_S_COUNT)
        scalars[[_S_N, _S_M, _S_K, _S_HORIZON]] = n, M, k, self._horizon
        scalars[[_S_BOUND_V, _S_BOUND_TAU]] = [bound is not None for bound in bounds]
        unbounded = (np.full(n, -np.inf), np.full(n, np.inf))
        self._constants = np.concatenate(
            [scalars, self._prediction_weights.reshape(-1)]
            + [self._vdot_weights.reshape(-1)]
            + [side for bound in bounds for side in (bound or unbounded)]
        )
        self._no_wrench = np.zeros(0)
        self._finalize()
        self._check_layout()

    def _check_layout(self) -> None:
        """The kernel indexes the state as v_predicted, tau_predicted,
        wrench_predicted, input_fault, counters, ring."""
        n, k, M = self._n, self._k, self._steps
        starts = {
            "v_predicted": 0,
            "tau_predicted": n,
            "input_fault": 2 * n + k,
            "counters": 2 * n + k + 1,
        }
        if k:
            starts["wrench_predicted"] = 2 * n
        if M:
            starts["ring"] = 2 * n + k + 5
        actual = {name: rows.start for name, rows in self.layout()}
        if actual != starts or self.state_size != 2 * n + k + 5 + 2 * M * n:
            raise AssertionError(f"{_WHERE}: the state layout is not the kernel's")

    def _linear_prediction(self, steps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The prediction as weights on the buffered Δq and on q̂̈.

        The recurrence x⁺ = Φ_j x + Γ_j g_j from x = 0 (steps of length h_j, Φ =
        e^(−a h), Γ = (1 − Φ) / a, = h for a = K_v / (K_τ m) = 0) ends at x_end =
        Σ_j B_j g_j, B_j = Γ_j Π_{l > j} Φ_l; with g_j = q̂̈ + (Δq_j − Δq_0) / (K_τ m)
        (eq. (1) of the module docstring) and Δτ = (Δq_end − Δq_0 − K_v x_end) / K_τ,

            [x_end, Δτ] = Σ_j W_j ⊙ Δq_j + C ⊙ q̂̈

        with W (2, M, n) and C (2, n) returned here: one weighted sum per tick.
        """
        a = self._k_v / (self._k_tau * self._inertia)  # 1 / T, (n,)
        z = -np.outer(steps, a)  # −a h_j, (M, n)
        safe = np.where(z == 0.0, 1.0, z)
        phi = np.exp(z)
        gamma = steps[:, None] * np.where(z == 0.0, 1.0, np.expm1(z) / safe)
        b = np.empty_like(gamma)
        later = np.ones_like(a)  # Π_{l > j} Φ_l
        for j in range(len(steps) - 1, -1, -1):
            b[j] = later * gamma[j]
            later = later * phi[j]
        weights = np.zeros((2, *b.shape))
        if len(steps):
            weights[0] = b / (self._k_tau * self._inertia)
            weights[0, 0] -= b.sum(axis=0) / (self._k_tau * self._inertia)  # −Δq_0
            weights[1] = -self._k_v / self._k_tau * weights[0]
            weights[1, -1] += 1.0 / self._k_tau  # Δq_end
            weights[1, 0] -= 1.0 / self._k_tau  # −Δq_0
        total = b.sum(axis=0)
        vdot_weights = np.stack([total, -self._k_v / self._k_tau * total])
        return weights, vdot_weights

    def config(self) -> DelayPredictorConfig:
        return self._config

    def horizon(self) -> float:
        """H = delay + command_latency (s, the latency in whole periods): how far the
        estimates are carried forward."""
        return self._horizon

    def num_buffered(self) -> int:
        """M, the number of Δq the horizon covers (the buffer's length)."""
        return self._steps

    def time_constants(self) -> np.ndarray:
        """T = K_τ m / K_v per joint (s; inf where K_v = 0)."""
        with np.errstate(divide="ignore"):
            return self._k_tau * self._inertia / self._k_v

    def is_ready(self) -> bool:
        """True once M Δq have been read (before, the outputs pass the estimates)."""
        return bool(self.counters[_NUM_SAMPLES] >= self._steps)

    def bad_input_count(self) -> int:
        """How many ticks had a NaN or infinite input."""
        return int(self.counters[_TOTAL_BAD])

    def step(
        self,
        t: float,
        v_estimated: np.ndarray,
        vdot_estimated: np.ndarray,
        tau_estimated: np.ndarray,
        delta_q: np.ndarray,
        wrench_estimated: np.ndarray | None = None,
        wrench_rate: np.ndarray | None = None,
    ) -> None:
        """One period (t in s, unused): q̂̇ (n, rad/s), q̂̈ (n, rad/s²), τ̂ (n, N·m)
        from `delay` ago, the Δq just sent (n, rad), and with wrench_size k > 0 f̂
        (k, N and N·m) and ḟ̂ (k, N/s and N·m/s) as old, carried to the present in
        place on the state (DelayPredictor's docstring: what bad input does)."""
        code = _predictor_step(
            v_estimated,
            vdot_estimated,
            tau_estimated,
            delta_q,
            self._no_wrench if wrench_estimated is None else wrench_estimated,
            self._no_wrench if wrench_rate is None else wrench_rate,
            self.state,
            self._constants,
        )
        if code:
            n, k = self._n, self._k
            raise ValueError(
                f"{_WHERE}: v_estimated, vdot_estimated, tau_estimated and delta_q "
                f"must have {n} entries"
                + (f", wrench_estimated and wrench_rate {k}" if k else "")
            )

    def warm_up(self) -> None:
        """Compiles (or loads from numba's cache) `_predictor_step` for the arrays
        of a tick (C-contiguous float64 vectors), on a copy of the state: the state
        is left as it was."""
        zeros, wrench = np.zeros(self._n), np.zeros(self._k)
        state, constants = self.state.copy(), self._constants
        _predictor_step(zeros, zeros, zeros, zeros, wrench, wrench, state, constants)


def _bounds(values: list[float], n: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(lower, upper) bounds on a correction (n each), None when all infinite."""
    upper = np.broadcast_to(np.asarray(values, float), (n,)).copy()
    return (-upper, upper) if np.isfinite(upper).any() else None


class DelayPredictor(StepSystem):
    """q̂̇, τ̂, f̂ carried from `delay` ago to the present by the motor model (module
    docstring): the LeafSystem shell of a `DelayPredictorStep`.

    .. code-block:: text

                             ┌────────────────┐
        v_estimated ────────►│                ├──► v_predicted
        vdot_estimated ─────►│                ├──► tau_predicted
        tau_estimated ──────►│ DelayPredictor ├──► wrench_predicted (optional)
        delta_q ────────────►│                ├──► input_fault
        wrench_estimated ───►│                │
        wrench_rate ────────►│                │
                             └────────────────┘

    Inputs (n = len(config.joints), config.joints order; k = config.wrench_size):
        v_estimated (n): q̂̇ (rad/s), describing the robot `delay` ago.
        vdot_estimated (n): q̂̈ (rad/s²), as old (the encoder filter's
            second_derivative).
        tau_estimated (n): τ̂ (N·m), as old.
        delta_q (n): the Δq the controller sent (rad), after saturation, e.g.
            DeltaQTorqueController's `delta_q`: current.
        wrench_estimated (k, only if k > 0): f̂, the F/T wrenches (N, N·m), as old.
        wrench_rate (k, only if k > 0): ḟ̂ (N/s, N·m/s), the F/T filter's derivative.

    Outputs (held: the committed state of the previous tick, no direct feedthrough:
    the system closes a loop through the Δq controller without an algebraic loop):
        v_predicted (n): q̇ at t + command_latency (rad/s).
        tau_predicted (n): τ at t + command_latency (N·m).
        wrench_predicted (k, only if k > 0): f̂ + H ḟ̂.
        input_fault (1): consecutive ticks with a NaN or infinite input (0 when
            the last was good).

    Bad input never takes the diagram down: a non-finite q̂̇, q̂̈ or τ̂ holds
    v_predicted and tau_predicted (a non-finite f̂ or ḟ̂ holds wrench_predicted);
    a non-finite Δq entry enters the buffer as the previous Δq of that joint (0
    before any), the prediction goes on with it. Every such tick counts
    (`bad_input_count`, `input_fault`); the first good one predicts afresh.
    """

    def __init__(
        self,
        motor_model: MotorModel,
        config: DelayPredictorConfig,
        lead: float = 0.0,
    ):
        """`lead`: the samples arrive this long (s) before each multiple of the
        period (`StepSystem`: the commits follow the sampler)."""
        super().__init__()
        step = DelayPredictorStep(motor_model, config)
        n, k = len(config.joints), int(config.wrench_size)
        self._v = self.DeclareVectorInputPort("v_estimated", n)
        self._vdot = self.DeclareVectorInputPort("vdot_estimated", n)
        self._tau = self.DeclareVectorInputPort("tau_estimated", n)
        self._delta_q = self.DeclareVectorInputPort("delta_q", n)
        self._wrench = self._wrench_rate = None
        if k:
            self._wrench = self.DeclareVectorInputPort("wrench_estimated", k)
            self._wrench_rate = self.DeclareVectorInputPort("wrench_rate", k)
        self._declare_step_state(step)
        outputs = ("v_predicted", "tau_predicted", "wrench_predicted", "input_fault")
        for name in outputs:
            if k or name != "wrench_predicted":
                # Held: in a loop with the Δq controller, whose Δq it reads
                # this tick.
                self._declare_step_output(name, held=True)
        self._counters = self.step_group("counters")
        self._declare_commit(config.period, lead)

    def config(self) -> DelayPredictorConfig:
        return self._step.config()

    def horizon(self) -> float:
        """H = delay + command_latency (s, the latency in whole periods): how far the
        estimates are carried forward."""
        return self._step.horizon()

    def num_buffered(self) -> int:
        """M, the number of Δq the horizon covers (the buffer's length)."""
        return self._step.num_buffered()

    def time_constants(self) -> np.ndarray:
        """T = K_τ m / K_v per joint (s; inf where K_v = 0)."""
        return self._step.time_constants()

    def is_ready(self, context: Context) -> bool:
        """True once M Δq have been read (before, the outputs pass the estimates)."""
        counters = context.get_discrete_state(self._counters).get_value()
        return counters[_NUM_SAMPLES] >= self._step.num_buffered()

    def bad_input_count(self, context: Context) -> int:
        """How many ticks had a NaN or infinite input (see the class docstring)."""
        counters = context.get_discrete_state(self._counters).get_value()
        return int(counters[_TOTAL_BAD])

    def _tick(self, context: Context, t: float) -> None:
        # Never raises on bad data (class docstring).
        wrench = rate = None
        if self._wrench is not None:
            wrench = self._wrench.Eval(context)
            rate = self._wrench_rate.Eval(context)
        self._step.step(
            t,
            self._v.Eval(context),
            self._vdot.Eval(context),
            self._tau.Eval(context),
            self._delta_q.Eval(context),
            wrench,
            rate,
        )
