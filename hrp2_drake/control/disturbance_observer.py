"""DisturbanceObserver: the torque the identified motor model does not explain, per
joint (the paper's future work: "We also plan to experiment with Disturbance
Observers"; its reference [7] uses one on series elastic actuators).

The Δq controller (eq. 10-11) relies on the identified model Δq = K_τ τ + K_v q̇ +
K_c sign(q̇) (eq. 6). Whatever the model misses (dead zone, direction-dependent
friction, a model error, an external torque that τ̂ sees but the model cannot) shows
as a torque disturbance

    d = τ̂ − τ_model,    τ_model = (Δq − K_v q̂̇ − K_c sign(q̂̇)) / K_τ,

the joint torque the estimator measures minus the one the model predicts for the Δq
the controller sent. τ̂ and q̂̇ come from the estimation chain, delayed by its window
(`EstimationChain.delay()`, 39.5 ms for the paper's 80 samples), and a Δq acts one
period after it is sent, so Δq is taken `delay` seconds old (the two together:
`estimator_config.loop_delay`, 40.5 ms) from a buffer of what was sent: every term
refers to the same instant. The raw d is low-passed (first order, `bandwidth`), so
that the observer passes the slow disturbance and not the estimate's noise:

    d̂[k+1] = d̂[k] + α (d[k] − d̂[k]),    α = 1 − exp(−bandwidth · period).

The Δq controller can subtract d̂ from its torque command (τ* = τ_d − d̂). The
observer only estimates; wiring and tuning belong to the experiments.
"""

import math
from dataclasses import dataclass, field

import numpy as np
from pydrake.systems.framework import Context

from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.kernels import kernel
from hrp2_drake.multibody import check_joint_names
from hrp2_drake.step import Step, StepSystem

_WHERE = "DisturbanceObserver"


@dataclass
class DisturbanceObserverConfig:
    """Configuration of the DisturbanceObserver.

    Args:
        joints: the observed joints (the torque-controlled ones), in the order of
            every vector of the observer.
        bandwidth: of the first-order low-pass on the raw disturbance (rad/s); its
            time constant is 1 / bandwidth.
        delay: how long before the Δq sent now the Δq that acted at the instant
            τ̂ and q̂̇ describe was sent (s): the estimation chain's delay plus the
            period before a Δq acts (`estimator_config.loop_delay`). Δq is delayed
            by it (rounded to whole periods) to meet them.
        limit: |d̂| is clipped to this (N·m), one value for every joint or one per
            joint; .inf: no clip.
        period: the control period (s; a keyword, no default).
    """

    joints: list[str] = field(default_factory=list)
    bandwidth: float = 10.0
    delay: float = 0.0405
    limit: list[float] = field(default_factory=lambda: [math.inf])
    period: float = field(kw_only=True)

    def validate(self) -> None:
        """Raises ValueError naming the bad field."""
        where = "DisturbanceObserverConfig"
        check_joint_names(self.joints, where)
        if not (math.isfinite(self.bandwidth) and self.bandwidth > 0):
            raise ValueError(f"{where}.bandwidth={self.bandwidth} must be > 0 (rad/s)")
        if not (math.isfinite(self.delay) and self.delay >= 0):
            raise ValueError(f"{where}.delay={self.delay} must be >= 0 (s)")
        if not (math.isfinite(self.period) and self.period > 0):
            raise ValueError(f"{where}.period={self.period} must be > 0 (s)")
        n = len(self.joints)
        if len(self.limit) not in (1, n) or any(not v > 0 for v in self.limit):
            raise ValueError(
                f"{where}.limit: 1 or {len(self.joints)} values > 0, got {self.limit}"
            )


# The constants of DisturbanceObserverStep (`_constants`, packed once): K_τ, K_v,
# K_c, the limit (rows of n), then the scalars α, D (the delay in periods), whether
# |d̂| is clipped, whether K_c is used.
_C_K_TAU, _C_K_V, _C_K_C, _C_LIMIT = range(4)
_C_ROWS = 4
_S_ALPHA, _S_DELAY, _S_CLIPS, _S_COULOMB = range(4)
_S_COUNT = 4
# What `_observer_step` returns on inputs of the wrong size (the step raises).
_BAD_SIZE = -1


@kernel
def _raw_disturbance(delta_q, v, tau, k_tau, k_v, k_c, coulomb):
    """d = τ̂ − (Δq − K_v q̇ − K_c sign(q̇)) / K_τ for one joint (numpy's order of
    operations, and its sign: 0 at ±0); coulomb False: no K_c term."""
    out = delta_q - k_v * v
    if coulomb:  # (K_c = 0: nothing to subtract)
        sign = 1.0 if v > 0.0 else (-1.0 if v < 0.0 else 0.0)
        out = out - sign * k_c
    return tau - out / k_tau


@kernel
def _observer_step(delta_q, v, tau_estimated, state, constants):
    """One period of DisturbanceObserverStep on its `state` ([d̂; ring; counters])
    with its packed `constants` (`DisturbanceObserverStep.step`); returns 0, or
    _BAD_SIZE (nothing changed). Elementwise, in numpy's order of operations (bit
    for bit); the sums only test finiteness."""
    c = constants
    n = (c.shape[0] - _S_COUNT) // _C_ROWS
    scalars = _C_ROWS * n
    delay = int(c[scalars + _S_DELAY])
    ring = n  # the ring's first entry; counters after it
    counters = ring + max(delay, 1) * n
    if (
        delta_q.shape[0] != n
        or v.shape[0] != n
        or tau_estimated.shape[0] != n
        or state.shape[0] != counters + 2
    ):
        return _BAD_SIZE
    slot, count = int(state[counters]), int(state[counters + 1])
    delta_q_sum = 0.0
    total = 0.0
    for i in range(n):
        delta_q_sum += delta_q[i]
        total += v[i]
    for i in range(n):
        total += tau_estimated[i]
    delta_q_finite = math.isfinite(delta_q_sum)
    # d̂ moves towards the raw d of the Δq sent `delay` ago; held on a non-finite
    # input or while no Δq is that old yet.
    update = math.isfinite(delta_q_sum + total) and count >= delay
    alpha = c[scalars + _S_ALPHA]
    clips = c[scalars + _S_CLIPS] != 0.0
    coulomb = c[scalars + _S_COULOMB] != 0.0
    old = ring + slot * n  # the Δq sent `delay` ago (delay > 0)
    for i in range(n):
        if update:
            raw = _raw_disturbance(
                state[old + i] if delay else delta_q[i],
                v[i],
                tau_estimated[i],
                c[_C_K_TAU * n + i],
                c[_C_K_V * n + i],
                c[_C_K_C * n + i],
                coulomb,
            )
            estimate = state[i]
            estimate = estimate + (raw - estimate) * alpha
            if clips:  # clipped to ±limit
                limit = c[_C_LIMIT * n + i]
                estimate = min(max(estimate, -limit), limit)
            state[i] = estimate
        if delay:  # Δq sent now, in its slot (zero if not finite)
            state[old + i] = delta_q[i] if delta_q_finite else 0.0
    if delay:
        state[counters] = (slot + 1) % delay
    state[counters + 1] = count + 1
    return 0


@kernel
def _raw_disturbance_rows(delta_q, v, tau, constants, out):
    """`_raw_disturbance` of each entry of (m, n) arrays, joint i in column i."""
    c = constants
    n = (c.shape[0] - _S_COUNT) // _C_ROWS
    coulomb = c[_C_ROWS * n + _S_COULOMB] != 0.0
    for row in range(out.shape[0]):
        for i in range(n):
            out[row, i] = _raw_disturbance(
                delta_q[row, i],
                v[row, i],
                tau[row, i],
                c[_C_K_TAU * n + i],
                c[_C_K_V * n + i],
                c[_C_K_C * n + i],
                coulomb,
            )


class DisturbanceObserverStep(Step):
    """The observer's per-tick arithmetic (module docstring), without Drake.

    Args:
        motor_model: the identified motor model (K_τ, K_v, K_c); it must have every
            joint of config.joints.
        config: the DisturbanceObserverConfig.

    State (`Step`): `disturbance` (n, d̂, N·m), `ring` (max(D, 1), n): the Δq
    (rad) sent over the last D = delay_periods() periods, and `counters` (2):
    [next ring slot, periods seen].

    A tick is one numba kernel (`_observer_step`) on the state and the model,
    packed once into one array (`hrp2_drake.kernels`); it allocates nothing.
    """

    def __init__(self, motor_model: MotorModel, config: DisturbanceObserverConfig):
        super().__init__()
        config.validate()
        self._config = config
        model = motor_model.subset(config.joints)
        n = self._n = len(config.joints)
        self._delay = round(config.delay / config.period)
        limit = np.broadcast_to(np.asarray(config.limit, float), (n,))
        scalars = np.zeros(_S_COUNT)
        scalars[_S_ALPHA] = 1.0 - math.exp(-config.bandwidth * config.period)
        scalars[_S_DELAY] = self._delay
        scalars[_S_CLIPS] = np.any(np.isfinite(limit))  # else no clip at all
        scalars[_S_COULOMB] = np.any(model.k_c != 0.0)  # else K_c sign(q̂̇) = 0
        self._constants = np.concatenate(
            [np.asarray(row, dtype=float) for row in (model.k_tau, model.k_v)]
            + [np.asarray(model.k_c, dtype=float), limit, scalars]
        )
        self._declare("disturbance", np.zeros(n))
        self._declare("ring", np.zeros((max(self._delay, 1), n)))
        self._declare("counters", np.zeros(2))
        self._finalize()

    def config(self) -> DisturbanceObserverConfig:
        return self._config

    def delay_periods(self) -> int:
        """The Δq delay in whole periods."""
        return self._delay

    def raw_disturbance(
        self,
        delta_q: np.ndarray,
        v: np.ndarray,
        tau: np.ndarray,
        out: np.ndarray | None = None,
    ) -> np.ndarray:
        """d = τ̂ − (Δq − K_v q̇ − K_c sign(q̇)) / K_τ for aligned samples (N·m; Δq in
        rad, q̇ in rad/s, τ̂ in N·m; any shapes that broadcast with (n,)).

        Into `out` (C-contiguous float64 of the broadcast shape, not an input) when
        given; a new array otherwise."""
        n = self._n
        shape = np.broadcast_shapes(np.shape(delta_q), np.shape(v), np.shape(tau), (n,))
        if out is None:
            out = np.empty(shape)
        elif (
            out.shape != shape or out.dtype != np.float64 or not out.flags.c_contiguous
        ):
            raise ValueError(
                f"{_WHERE}.raw_disturbance: out must be a C-contiguous float64 array "
                f"of shape {shape}, got {out.dtype} {out.shape}"
            )
        rows = [
            np.ascontiguousarray(
                np.broadcast_to(np.asarray(x, dtype=float), shape)
            ).reshape(-1, n)
            for x in (delta_q, v, tau)
        ]
        _raw_disturbance_rows(*rows, self._constants, out.reshape(-1, n))
        return out

    def step(
        self, t: float, delta_q: np.ndarray, v: np.ndarray, tau_estimated: np.ndarray
    ) -> None:
        """One period (t in s, unused): Δq sent now (n, rad) enters the ring; with q̂̇
        (n, rad/s) and τ̂ (n, N·m), as old as `delay`, d̂ moves towards the raw d of
        the Δq sent `delay` ago (held on a non-finite input or before the ring
        covers `delay`). Float64 arrays (`warm_up`)."""
        if _observer_step(delta_q, v, tau_estimated, self.state, self._constants):
            raise ValueError(
                f"{_WHERE}: delta_q, v and tau_estimated must have {self._n} entries"
            )

    def warm_up(self) -> None:
        """Compiles (or loads from numba's cache) the kernels for the arrays of a
        tick (C-contiguous float64 vectors), on copies: the state is left as it
        was; and `_raw_disturbance` for its scalar arguments (a kernel that `freeze`
        disables needs a signature of its own)."""
        zeros = np.zeros(self._n)
        _raw_disturbance(0.0, 0.0, 0.0, 1.0, 0.0, 0.0, False)
        _observer_step(zeros, zeros, zeros, self.state.copy(), self._constants)
        self.raw_disturbance(zeros, zeros, zeros, out=np.zeros(self._n))


class DisturbanceObserver(StepSystem):
    """The torque disturbance d̂ the motor model misses (module docstring): the
    LeafSystem shell of a `DisturbanceObserverStep`.

    .. code-block:: text

                          ┌─────────────────────┐
        delta_q ─────────►│                     │
        v ───────────────►│ DisturbanceObserver ├──► disturbance
        tau_estimated ───►│                     │
                          └─────────────────────┘

    Inputs (n each, config.joints order):
        delta_q: the Δq the controller sends now (rad), e.g.
            DeltaQTorqueController's `delta_q`.
        v: the estimated joint velocities q̂̇ (rad/s), as old as tau_estimated.
        tau_estimated: the estimated joint torques τ̂ (N·m).

    Output:
        disturbance (n): d̂ (N·m) of the previous tick (held: the loop's one tick,
        `StepSystem`); zero until the Δq buffer covers `delay` (the first delay
        seconds).

    A non-finite input holds d̂ (the sample is skipped, Δq still enters the buffer as
    zero): bad sensor data do not reach the estimate.
    """

    def __init__(
        self,
        motor_model: MotorModel,
        config: DisturbanceObserverConfig,
        lead: float = 0.0,
    ):
        """`lead`: the samples arrive this long (s) before each multiple of the
        period (`StepSystem`: the commits follow the sampler)."""
        super().__init__()
        step = DisturbanceObserverStep(motor_model, config)
        n = len(config.joints)
        self._delta_q = self.DeclareVectorInputPort("delta_q", n)
        self._v = self.DeclareVectorInputPort("v", n)
        self._tau = self.DeclareVectorInputPort("tau_estimated", n)
        self._declare_step_state(step)
        # Held: in a loop with the Δq controller, whose Δq it reads this tick.
        self._declare_step_output("disturbance", held=True)
        self._declare_commit(config.period, lead)

    def config(self) -> DisturbanceObserverConfig:
        return self._step.config()

    def delay_periods(self) -> int:
        """The Δq delay in whole periods."""
        return self._step.delay_periods()

    def raw_disturbance(
        self, delta_q: np.ndarray, v: np.ndarray, tau: np.ndarray
    ) -> np.ndarray:
        """d = τ̂ − (Δq − K_v q̇ − K_c sign(q̇)) / K_τ for aligned samples (N·m), a new
        array (`DisturbanceObserverStep.raw_disturbance`)."""
        return self._step.raw_disturbance(delta_q, v, tau)

    def _tick(self, context: Context, t: float) -> None:
        self._step.step(
            t,
            self._delta_q.Eval(context),
            self._v.Eval(context),
            self._tau.Eval(context),
        )
