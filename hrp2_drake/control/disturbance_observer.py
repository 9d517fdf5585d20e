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
from pydrake.systems.framework import Context, DiscreteValues, LeafSystem

from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.multibody import check_joint_names

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
        if len(self.limit) not in (1, len(self.joints)) or any(not v > 0 for v in self.limit):
            raise ValueError(
                f"{where}.limit: 1 or {len(self.joints)} values > 0, got {self.limit}"
            )


class DisturbanceObserver(LeafSystem):
    """The torque disturbance d̂ the motor model misses (module docstring).

    .. code-block:: text

                          ┌─────────────────────┐
        delta_q ─────────►│                     │
        v ───────────────►│ DisturbanceObserver ├──► disturbance
        tau_estimated ───►│                     │
                          └─────────────────────┘

    Inputs (n each, config.joints order):
        delta_q: the Δq the controller sends now (rad), e.g. DeltaQTorqueController's
            `delta_q`.
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
        config.validate()
        self._config = config
        model = motor_model.subset(config.joints)
        n = len(config.joints)
        self._k_tau, self._k_v, self._k_c = model.k_tau, model.k_v, model.k_c
        self._alpha = 1.0 - math.exp(-config.bandwidth * config.period)
        self._delay = round(config.delay / config.period)
        self._limit = np.broadcast_to(np.asarray(config.limit, float), (n,)).copy()
        self._delta_q = self.DeclareVectorInputPort("delta_q", n)
        self._v = self.DeclareVectorInputPort("v", n)
        self._tau = self.DeclareVectorInputPort("tau_estimated", n)
        estimate = self.DeclareDiscreteState(n)
        self._estimate = int(estimate)
        # The Δq sent over the last `delay` periods (a ring), and [next slot, samples].
        self._ring = int(self.DeclareDiscreteState(max(self._delay, 1) * n))
        self._counters = int(self.DeclareDiscreteState(2))
        self.DeclareStateOutputPort("disturbance", estimate)
        self.DeclarePeriodicDiscreteUpdateEvent(config.period, 0.0, self._update)

    def config(self) -> DisturbanceObserverConfig:
        return self._config

    def delay_periods(self) -> int:
        """The Δq delay in whole periods."""
        return self._delay

    def raw_disturbance(self, delta_q: np.ndarray, v: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """d = τ̂ − (Δq − K_v q̇ − K_c sign(q̇)) / K_τ for aligned samples (N·m)."""
        return tau - (delta_q - self._k_v * v - self._k_c * np.sign(v)) / self._k_tau

    def _update(self, context: Context, discrete_state: DiscreteValues) -> None:
        delta_q = self._delta_q.Eval(context)
        v = self._v.Eval(context)
        tau = self._tau.Eval(context)
        n = len(delta_q)
        counters = discrete_state.get_mutable_value(self._counters)
        slot, count = int(counters[0]), int(counters[1])
        finite = math.isfinite(delta_q.sum() + v.sum() + tau.sum())
        if self._delay == 0:
            old = delta_q
        else:
            ring = discrete_state.get_mutable_value(self._ring)
            old = ring[slot * n : (slot + 1) * n].copy()  # sent `delay` periods ago
            ring[slot * n : (slot + 1) * n] = delta_q if math.isfinite(delta_q.sum()) else 0.0
            counters[0] = (slot + 1) % self._delay
        counters[1] = count + 1
        if not finite or count < self._delay:
            return  # hold d̂: a bad sample, or no Δq that old yet
        estimate = discrete_state.get_mutable_value(self._estimate)
        estimate += self._alpha * (self.raw_disturbance(old, v, tau) - estimate)
        np.clip(estimate, -self._limit, self._limit, out=estimate)
