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
(`EstimationChain.delay()`, 41.5 ms for the paper's 80 samples), so Δq is taken
`delay` seconds old from a buffer of what was sent: every term refers to the same
instant. The raw d is low-passed (first order, `bandwidth`), so that the observer
passes the slow disturbance and not the estimate's noise:

    d̂[k+1] = d̂[k] + α (d[k] − d̂[k]),    α = 1 − exp(−bandwidth · period).

The Δq controller can subtract d̂ from its torque command (τ* = τ_d − d̂). The
observer only estimates; wiring and tuning belong to the experiments.
"""

import math
from dataclasses import dataclass, field

import numpy as np
from pydrake.systems.framework import Context, DiscreteValues

from hrp2_drake.identification.motor_model import MotorModel
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
        delay: the age of τ̂ and q̂̇ when they arrive (s): the estimation chain's
            delay. Δq is delayed by it (rounded to whole periods) to meet them.
        limit: |d̂| is clipped to this (N·m), one value for every joint or one per
            joint; .inf: no clip.
        period: the update period (s).
    """

    joints: list[str] = field(default_factory=list)
    bandwidth: float = 10.0
    delay: float = 0.0415
    limit: list[float] = field(default_factory=lambda: [math.inf])
    period: float = 0.001

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


class DisturbanceObserverStep(Step):
    """The observer's per-tick arithmetic (module docstring), without Drake.

    Args:
        motor_model: the identified motor model (K_τ, K_v, K_c); it must have every
            joint of config.joints.
        config: the DisturbanceObserverConfig.

    State (`Step`): `disturbance` (n, d̂, N·m), `ring` (max(D, 1), n): the Δq
    (rad) sent over the last D = delay_periods() periods, and `counters` (2):
    [next ring slot, periods seen].
    """

    def __init__(self, motor_model: MotorModel, config: DisturbanceObserverConfig):
        super().__init__()
        config.validate()
        self._config = config
        model = motor_model.subset(config.joints)
        n = len(config.joints)
        self._k_tau, self._k_v, self._k_c = model.k_tau, model.k_v, model.k_c
        self._alpha = 1.0 - math.exp(-config.bandwidth * config.period)
        self._delay = round(config.delay / config.period)
        self._limit = np.broadcast_to(np.asarray(config.limit, float), (n,)).copy()
        self._lower = -self._limit
        self._clips = bool(np.any(np.isfinite(self._limit)))  # else no clip at all
        self._coulomb = bool(np.any(self._k_c != 0.0))  # else K_c sign(q̇) = 0
        self._ones = np.ones(n)
        self._declare("disturbance", np.zeros(n))
        self._declare("ring", np.zeros((max(self._delay, 1), n)))
        self._declare("counters", np.zeros(2))
        # Per-tick work: the raw d, K_c sign(q̂̇).
        self._raw = np.zeros(n)
        self._friction = np.zeros(n)
        self._finalize()

    def _views_changed(self) -> None:
        self._slots = list(self.ring)  # a view per ring row

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

        Into `out` ((n,), not an input) when given, with no allocation (the per-tick
        use); a new array otherwise."""
        if out is None:
            out = np.empty(np.broadcast(delta_q, v, tau, self._k_tau).shape)
            friction = np.empty_like(out)
        else:
            friction = self._friction
        # (Positional outputs: about twice as fast as `out=` on small arrays.)
        np.multiply(self._k_v, v, out)
        np.subtract(delta_q, out, out)
        if self._coulomb:  # (K_c = 0: nothing to subtract)
            np.sign(v, friction)
            np.multiply(friction, self._k_c, friction)  # K_c sign(q̇)
            np.subtract(out, friction, out)
        np.divide(out, self._k_tau, out)
        np.subtract(tau, out, out)
        return out

    def step(
        self, t: float, delta_q: np.ndarray, v: np.ndarray, tau_estimated: np.ndarray
    ) -> None:
        """One period (t in s, unused): Δq sent now (n, rad) enters the ring; with q̂̇
        (n, rad/s) and τ̂ (n, N·m), as old as `delay`, d̂ moves towards the raw d of
        the Δq sent `delay` ago (held on a non-finite input or before the ring
        covers `delay`)."""
        counters, ones = self.counters, self._ones
        slot, count = int(counters[0]), int(counters[1])
        delta_q_sum = delta_q.dot(ones)
        finite = math.isfinite(delta_q_sum + v.dot(ones) + tau_estimated.dot(ones))
        old = self._slots[slot] if self._delay else delta_q  # sent `delay` ago
        raw = None  # hold d̂ on a bad sample, or while no Δq is that old yet
        if finite and count >= self._delay:
            raw = self.raw_disturbance(old, v, tau_estimated, out=self._raw)
        if self._delay:
            old[:] = delta_q if math.isfinite(delta_q_sum) else 0.0  # its slot, reused
            counters[0] = (slot + 1) % self._delay
        counters[1] = count + 1
        if raw is None:
            return
        estimate = self.disturbance
        np.subtract(raw, estimate, raw)
        np.multiply(raw, self._alpha, raw)
        np.add(estimate, raw, estimate)
        if self._clips:  # clipped to ±limit
            np.maximum(estimate, self._lower, out=estimate)
            np.minimum(estimate, self._limit, out=estimate)


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
        disturbance (n): d̂ (N·m), discrete state; zero until the Δq buffer covers
        `delay` (the first delay seconds).

    A non-finite input holds d̂ (the sample is skipped, Δq still enters the buffer as
    zero): bad sensor data do not reach the estimate.
    """

    def __init__(self, motor_model: MotorModel, config: DisturbanceObserverConfig):
        super().__init__()
        step = DisturbanceObserverStep(motor_model, config)
        n = len(config.joints)
        self._delta_q = self.DeclareVectorInputPort("delta_q", n)
        self._v = self.DeclareVectorInputPort("v", n)
        self._tau = self.DeclareVectorInputPort("tau_estimated", n)
        self._declare_step_state(step)
        self._declare_step_output("disturbance")
        self.DeclarePeriodicDiscreteUpdateEvent(config.period, 0.0, self._update)

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

    def _update(self, context: Context, discrete_state: DiscreteValues) -> None:
        # (discrete_state holds the current discrete state on entry.)
        self._load(discrete_state)
        self._step.step(
            context.get_time(),
            self._delta_q.Eval(context),
            self._v.Eval(context),
            self._tau.Eval(context),
        )
        self._store(discrete_state)
