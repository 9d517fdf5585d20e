"""DeltaQTorqueController: joint-torque control through a position servo (paper Sec.
4.1.1-4.1.2, eq. 10-11); the gain mapping of Sec. 4.2 between the user's gains
{K_p, K_s, K_d, K_f} and the position-servo-like gains {K6, K7, K8, K9}; and the
wiring helpers that put a torque-controlled joint subset into a whole-robot command.

The control law (per joint, all gains diagonal):

    τ* = τ_d + K_p e_τ + K_i ∫ e_τ dt,   e_τ = τ_d − τ̂                 (eq. 11)
         [− d̂, a DisturbanceObserver's estimate, with disturbance_compensation]
    Δq = K_τ τ* + K_v q̂̇                                               (eq. 10)
    q_cmd = q_measured + Δq                                           (eq. 6: Δq is the
                                                                       servo's input error)

K_τ and K_v come from the identified MotorModel (eq. 6); the paper's controller has
no Coulomb term, an option adds K_c tanh(q̂̇ / v_s).

Sec. 4.2: with τ_d from eq. 12 and τ̂ = M_j q̂̈ + ĥ_j − J_jᵀ f̂, Δq is

    Δq = K_τ (M_j q̈_d + ĥ_j − J_jᵀ f_d) + K_v q̂̇                        (eq. 13)
         + K6 e_q + K7 ė_q + K8 ë_q + K9 e_f                          (eq. 14)

    K6 = K_τ (I + K_p) K_s        K7 = K_τ (I + K_p) K_d
    K8 = K_τ K_p M_j              K9 = −K_τ (K_p J_jᵀ (I + K_f) + J_jᵀ K_f)

`gains_from_user` and `user_from_gains` map one set to the other.
"""

import logging
import math
from dataclasses import dataclass, field
from typing import NamedTuple, Sequence

import numpy as np
from pydrake.systems.framework import (
    Context,
    DiagramBuilder,
    DiscreteValues,
    InputPort,
)
from pydrake.systems.primitives import MatrixGain, Selector, SelectorParams

from hrp2_drake.control.inverse_dynamics import (
    TORQUE_COMPONENTS,
    InverseDynamicsController,
    gain_vector,
)
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.multibody import check_joint_names, eval_finite
from hrp2_drake.step import Step, StepSystem

_WHERE = "DeltaQTorqueController"
_logger = logging.getLogger(__name__)

#: The components of Δq (paper Sec. 5.5, plus the integral term, zero when K_i = 0,
#: and the disturbance compensation, zero without it), in the order of their output
#: ports.
DELTA_Q_COMPONENTS: tuple[str, ...] = (
    "feedforward_torque",
    "feedforward_friction",
    "feedback_position",
    "feedback_velocity",
    "feedback_acceleration",
    "feedback_force",
    "feedback_torque_integral",
    "feedback_disturbance",
)

#: Why the controller fell back to position control (`fallback_reason`), by code.
FALLBACK_REASONS: dict[int, str] = {
    0: "",
    1: "tau_estimated is not finite",
    2: "|tau_estimated| exceeds tau_limit",
    3: "tau_desired, v, tau_disturbance or a torque component of the inverse dynamics "
    "is not finite",
    4: "|delta_q| before saturation exceeds delta_q_fallback_limit",
    5: "q_measured is not finite",
    6: "sensor_fault: the estimation filters hold a NaN or infinite sample",
}


# yaml_load_typed reads the field types at run time: this module must not use
# `from __future__ import annotations`.
@dataclass
class TorqueControllerConfig:
    """Configuration of DeltaQTorqueController (eq. 10-11 and its safety layer).

    Every per-joint value is a list of one value (the same for every joint) or of
    one value per joint (config.joints order); in Python a plain number is accepted
    too.

    Args:
        joints: names of the n controlled joints, in the order of every joint vector
            of the controller; the motor model must have them all.
        kp: torque-feedback proportional gain K_p (dimensionless), eq. 11; the paper
            uses 2 on every joint (Sec. 5.1).
        ki: torque-feedback integral gain K_i (1/s), eq. 11; 0 in the paper.
        integral_limit: bound on |∫ e_τ dt| (N·m·s), the anti-windup of the K_i term.
        delta_q_limit: saturation of Δq (rad): the command sent is
            q_measured + clip(Δq, ±delta_q_limit).
        delta_q_fallback_limit: a |Δq| before saturation above this (rad) latches
            the fallback (must be >= delta_q_limit).
        tau_limit: a |τ̂| above this (N·m) latches the fallback.
        coulomb_compensation: add the motor model's K_c tanh(q̂̇ / coulomb_velocity)
            to the friction feedforward (not in the paper's eq. 10).
        coulomb_velocity: velocity scale of that smooth sign (rad/s).
        start_time: torque control starts at this time (s); before, the controller
            holds the position (see the class docstring), e.g. while the estimator's
            filters fill their window.
        period: the update period (s).
        latch_fallback: the fallback latches until `reset_fallback` (default, the
            controller alone); False: it lasts while its reason does, for a
            SafetySupervisor that decides when torque control resumes and ramps.
        disturbance_compensation: declare the input `tau_disturbance` (n), the
            torque d̂ the motor model misses (a DisturbanceObserver's), and subtract
            it from τ* (the paper's future work: a disturbance observer).
    """

    joints: list[str] = field(default_factory=list)
    kp: list[float] = field(default_factory=lambda: [2.0])
    ki: list[float] = field(default_factory=lambda: [0.0])
    integral_limit: list[float] = field(default_factory=lambda: [math.inf])
    delta_q_limit: list[float] = field(default_factory=lambda: [0.1])
    delta_q_fallback_limit: list[float] = field(default_factory=lambda: [0.2])
    tau_limit: list[float] = field(default_factory=lambda: [500.0])
    coulomb_compensation: bool = False
    coulomb_velocity: float = 0.05
    start_time: float = 0.0
    period: float = 0.001
    latch_fallback: bool = True
    disturbance_compensation: bool = False

    def validate(self) -> None:
        """Raises ValueError naming the bad field (yaml_load_typed does not call it)."""
        where = "TorqueControllerConfig"
        check_joint_names(self.joints, where)
        gains = self.vectors()  # checks sizes, finiteness and signs
        for name in ("integral_limit", "delta_q_limit", "tau_limit"):
            if not np.all(gains[name] > 0):
                raise ValueError(
                    f"{where}.{name} must be > 0, got {getattr(self, name)}"
                )
        if np.any(gains["delta_q_fallback_limit"] < gains["delta_q_limit"]):
            raise ValueError(
                f"{where}.delta_q_fallback_limit={self.delta_q_fallback_limit} must be "
                f">= delta_q_limit={self.delta_q_limit}"
            )
        if not (math.isfinite(self.coulomb_velocity) and self.coulomb_velocity > 0):
            raise ValueError(
                f"{where}.coulomb_velocity={self.coulomb_velocity} must be > 0 (rad/s)"
            )
        if not math.isfinite(self.start_time):
            raise ValueError(f"{where}.start_time={self.start_time} must be finite (s)")
        if not (math.isfinite(self.period) and self.period > 0):
            raise ValueError(f"{where}.period={self.period} must be > 0 (s)")

    def vectors(self) -> dict[str, np.ndarray]:
        """Every per-joint field as an array of n values (raises like validate)."""
        where, n = "TorqueControllerConfig", len(self.joints)
        out = {}
        for name in ("kp", "ki"):
            out[name] = gain_vector(name, getattr(self, name), n, where)
        # Bounds may be +inf (never binds).
        for name in (
            "integral_limit",
            "delta_q_limit",
            "delta_q_fallback_limit",
            "tau_limit",
        ):
            out[name] = gain_vector(name, getattr(self, name), n, where, allow_inf=True)
        return out


class DeltaQTorqueStep(Step):
    """Eq. 10-11 for one sample, with the Δq components of Sec. 5.5, the saturation
    and the fallback to position control, outside Drake's systems framework: the
    per-tick arithmetic of DeltaQTorqueController (its docstring has the law, the
    components and the safety rules), written once for it and for a fused
    controller.

    State (n = len(config.joints), config.joints order):
        q_cmd (n, rad), delta_q (n, rad), delta_q_unsaturated (n, rad),
        tau_commanded (n, N·m), one array of n (rad) per DELTA_Q_COMPONENTS name,
        fallback_active (1: 1.0 in fallback, else 0.0): the controller's outputs;
        fallback_reason (1): the FALLBACK_REASONS code of the last fallback (0 if
        none);
        tau_error_integral (n, N·m·s): ∫ e_τ dt of eq. 11.
    All zero at construction; `initialize` sets the first command.

    `step` reads `q_cmd` (the command it holds), `fallback_active` and
    `tau_error_integral` and keeps `fallback_reason` between fallbacks: `carried`,
    what a shell must load before a tick. It rewrites the others every tick, except
    `unused`: feedback_torque_integral without K_i, feedback_disturbance without
    config.disturbance_compensation, zero for ever (a shell need neither load nor
    store them). A tick allocates nothing but numpy scalars.
    """

    #: The state arrays that `step` reads or keeps between ticks.
    carried: tuple[str, ...] = (
        "q_cmd",
        "fallback_active",
        "fallback_reason",
        "tau_error_integral",
    )

    #: The state arrays that reset_fallback sets (to zero).
    RESET_STATE: tuple[str, ...] = (
        "fallback_active",
        "fallback_reason",
        "tau_error_integral",
    )

    def __init__(self, motor_model: MotorModel, config: TorqueControllerConfig):
        """
        Args:
            motor_model, config: as DeltaQTorqueController's (validated here).

        Raises:
            ValueError: a bad config, or K_τ <= 0 for a joint.
            KeyError: a joint of config.joints that the motor model does not have.
        """
        super().__init__()
        config.validate()
        self._config = config
        self._motor = motor_model.subset(list(config.joints))  # KeyError if missing
        if not np.all(self._motor.k_tau > 0):
            bad = [j for j, k in zip(config.joints, self._motor.k_tau) if not k > 0]
            raise ValueError(f"{_WHERE}: the motor model's k_tau is <= 0 for {bad}")
        n = self._n = len(config.joints)
        self._make_gains()
        self._make_work_arrays()
        for name in ("q_cmd", "delta_q", "delta_q_unsaturated", "tau_commanded"):
            self._declare(name, np.zeros(n))
        for name in DELTA_Q_COMPONENTS:
            self._declare(name, np.zeros(n))
        self._declare("fallback_active", np.zeros(1))
        self._declare("fallback_reason", np.zeros(1))
        self._declare("tau_error_integral", np.zeros(n))
        self._finalize()
        #: The state arrays that stay zero under this config.
        self.unused: tuple[str, ...] = ()
        if not self._integrates:
            self.unused += ("feedback_torque_integral",)
        if not config.disturbance_compensation:
            self.unused += ("feedback_disturbance",)

    def _make_gains(self) -> None:
        """The gains, bounds and their products, formed once."""
        config, n = self._config, self._n
        vectors = config.vectors()
        self._kp = vectors["kp"]
        self._ki = vectors["ki"]
        self._integral_limit = vectors["integral_limit"]
        self._delta_q_limit = vectors["delta_q_limit"]
        self._fallback_limit = vectors["delta_q_fallback_limit"]
        self._tau_limit = vectors["tau_limit"]
        self._k_tau = self._motor.k_tau
        self._minus_k_tau = -self._k_tau
        self._k_v = self._motor.k_v
        self._k_c = self._motor.k_c if config.coulomb_compensation else np.zeros(n)
        self._coulomb = config.coulomb_compensation
        self._coulomb_velocity = config.coulomb_velocity
        self._period_n = np.full(n, config.period)  # an array: faster than a float
        self._half_period = 0.5 * config.period
        self._start_time = config.start_time
        self._latch_fallback = config.latch_fallback
        self._compensates = config.disturbance_compensation
        k_tau_one_plus_kp = self._k_tau * (1.0 + self._kp)
        self._k_tau_kp = self._k_tau * self._kp
        self._k_tau_ki = self._k_tau * self._ki
        # The gains of τ_ff, τ_Ks, τ_Kd, τ_Kf, τ_ef in the components of Δq.
        self._term_gains = np.stack(
            [self._k_tau] + [k_tau_one_plus_kp] * 3 + [self._k_tau_kp]
        )
        self._integrates = bool(np.any(self._ki != 0.0))  # else ∫ e_τ dt is unused
        self._clips_integral = bool(np.any(np.isfinite(self._integral_limit)))
        self._minus_integral_limit = -self._integral_limit
        self._minus_delta_q_limit = -self._delta_q_limit

    def _make_work_arrays(self) -> None:
        n, k = self._n, len(TORQUE_COMPONENTS)
        self._ones_n = np.ones(n)
        # The terms without the inverse dynamics's: τ_ff = τ_d (row 0), zeros.
        self._no_terms = np.zeros((k, n))
        self._no_terms_ff = self._no_terms[0]
        # K_τ τ_ff, K_τ (1 + K_p) τ_Ks, ... (one product per tick into these rows).
        self._scaled = np.zeros((k, n))
        self._scaled_rows = tuple(self._scaled)
        self._scaled_pv = self._scaled[1:3]  # K_τ (1 + K_p) [τ_Ks; τ_Kd]
        self._scaled_flat = self._scaled.reshape(-1)  # a view
        self._ones_scaled = np.ones(self._scaled.size)
        self._e_tau = np.zeros(n)
        self._integral = np.zeros(n)  # the next ∫ e_τ dt, kept if no fallback
        self._work = np.zeros(n)
        self._exceeds = np.zeros(n, dtype=bool)

    def _views_changed(self) -> None:
        # delta_q_unsaturated .. the last component: contiguous rows of the state,
        # zero outside torque control.
        first = self.rows("delta_q_unsaturated").start
        self._zero_outside_torque_control = self.state[
            first : self.rows(DELTA_Q_COMPONENTS[-1]).stop
        ]
        # feedback_position, feedback_velocity: contiguous, one (2, n) copy.
        rows = self.rows("feedback_position").start, self.rows("feedback_velocity").stop
        self._feedback_pv = self.state[rows[0] : rows[1]].reshape(2, self._n)

    # ----------------------------------------------------------------- accessors

    def config(self) -> TorqueControllerConfig:
        return self._config

    def motor_model(self) -> MotorModel:
        """The motor model of the controlled joints (config.joints order)."""
        return self._motor

    def joint_names(self) -> tuple[str, ...]:
        return tuple(self._config.joints)

    def reset_fallback(self) -> None:
        """Leaves the fallback: torque control resumes at the next tick (with a zero
        torque-error integral)."""
        for name in self.RESET_STATE:
            getattr(self, name).fill(0.0)

    # ----------------------------------------------------------------- per tick

    def initialize(
        self, t: float, q_measured: np.ndarray, q_ref: np.ndarray | None = None
    ) -> None:
        """The first command, before the first tick: q_cmd = q_ref if given, else
        q_measured (Δq = 0), so that the servo holds the robot from the start.

        Args:
            t: the time (s), for the error message.
            q_measured: the encoders (rad), n.
            q_ref: the position reference (rad), n, or None.

        Raises:
            ValueError: q_measured or q_ref is not finite.
        """
        _check_finite("q_measured", q_measured, t)
        self._hold(t, q_measured, q_measured if q_ref is None else q_ref, False)

    def step(
        self,
        t: float,
        tau_desired: np.ndarray,
        tau_estimated: np.ndarray,
        v: np.ndarray,
        q_measured: np.ndarray,
        q_ref: np.ndarray | None = None,
        sensor_fault: np.ndarray | None = None,
        terms: np.ndarray | None = None,
        tau_disturbance: np.ndarray | None = None,
    ) -> int:
        """One tick: eq. 10-11 and the components of Δq, or position control
        (DeltaQTorqueController's docstring, "Safety").

        Args:
            t: the time (s) (config.start_time starts torque control).
            tau_desired: τ_d (N·m), n.
            tau_estimated: τ̂ (N·m), n.
            v: q̂̇ (rad/s), n.
            q_measured: the encoders (rad), n.
            q_ref: the position reference of the fallback (rad), n; None: hold the
                last q_cmd.
            sensor_fault: a 1-array, > 0 while the estimation filters hold a bad
                sample (then fallback, reason 6); None: no fault.
            terms: (5, n), the rows τ_ff, τ_Ks, τ_Kd, τ_Kf, τ_ef of the inverse
                dynamics (TORQUE_COMPONENTS order, e.g. InverseDynamicsStep.terms),
                N·m; None: τ_ff = τ_d and zeros.
            tau_disturbance: d̂ (N·m), n, with config.disturbance_compensation
                (required then; ignored otherwise).

        Returns:
            The FALLBACK_REASONS code of a fallback that starts at this tick (the
            previous tick was not in fallback), else 0: what the controller logs
            once, and what a fused controller counts.

        Raises:
            ValueError: q_ref, when it is used (position control), is not finite;
                tau_disturbance is None with config.disturbance_compensation.
        """
        if not math.isfinite(q_measured.dot(self._ones_n)):
            # No torque command is safe without the encoders: hand back to the servo.
            return self._latch(t, q_measured, q_ref, 5)
        if t + self._half_period < self._start_time:
            self._hold(t, q_measured, q_ref, False)
            return 0
        fallback = self.fallback_active[0]
        if fallback and self._latch_fallback:
            self._hold(t, q_measured, q_ref, True)
            return 0
        if terms is None:
            self._no_terms_ff[:] = tau_desired
            terms = self._no_terms
        # K_τ τ_ff, K_τ (1 + K_p) τ_Ks, K_τ (1 + K_p) τ_Kd, K_τ (1 + K_p) τ_Kf,
        # K_τ K_p τ_ef: one product, finite exactly when the terms are (finite,
        # non-negative gains).
        np.multiply(self._term_gains, terms, self._scaled)
        reason = self._input_fault(tau_desired, tau_estimated, v, sensor_fault)
        if not reason:
            reason = self._eq10_11(tau_desired, tau_estimated, v, tau_disturbance)
        if reason:
            return self._latch(t, q_measured, q_ref, reason)
        self._torque_control(tau_estimated, q_measured, terms, tau_disturbance)
        if fallback:  # not latched: torque control resumes
            self.fallback_active[0] = 0.0
        return 0

    def _input_fault(self, tau_desired, tau_estimated, v, sensor_fault) -> int:
        """The FALLBACK_REASONS code of a bad input (0, 1, 2, 3 or 6); the terms
        are checked through their products in `_scaled`."""
        if sensor_fault is not None and sensor_fault[0] > 0:
            return 6
        ones = self._ones_n
        if not math.isfinite(tau_estimated.dot(ones)):
            return 1
        magnitude = np.abs(tau_estimated, self._work)
        if np.count_nonzero(np.greater(magnitude, self._tau_limit, self._exceeds)):
            return 2
        scaled = self._scaled_flat.dot(self._ones_scaled)
        if not math.isfinite(tau_desired.dot(ones) + v.dot(ones) + scaled):
            return 3
        return 0

    def _eq10_11(self, tau_desired, tau_estimated, v, tau_disturbance) -> int:
        """Eq. 11 into tau_commanded (and the next integral), eq. 10 into
        delta_q_unsaturated, the friction feedforward into feedforward_friction;
        returns the FALLBACK_REASONS code this finds (0, 3: d̂ not finite, 4: Δq
        beyond delta_q_fallback_limit)."""
        e_tau = np.subtract(tau_desired, tau_estimated, self._e_tau)
        integral = np.multiply(e_tau, self._period_n, self._integral)
        np.add(self.tau_error_integral, integral, integral)
        if self._clips_integral:  # anti-windup: |∫ e_τ dt| <= integral_limit
            np.maximum(integral, self._minus_integral_limit, out=integral)
            np.minimum(integral, self._integral_limit, out=integral)
        # Eq. 11: τ* = τ_d + K_p e_τ + K_i ∫ e_τ dt [− d̂].
        tau_star = np.multiply(self._kp, e_tau, self.tau_commanded)
        np.add(tau_desired, tau_star, tau_star)
        work = self._work
        if self._integrates:
            np.add(tau_star, np.multiply(self._ki, integral, work), tau_star)
        if self._compensates:
            if tau_disturbance is None:
                raise ValueError(f"{_WHERE}: disturbance_compensation needs d̂")
            if not math.isfinite(tau_disturbance.dot(self._ones_n)):
                return 3
            np.subtract(tau_star, tau_disturbance, tau_star)
        friction = np.multiply(self._k_v, v, self.feedforward_friction)
        if self._coulomb:  # + K_c tanh(q̂̇ / v_s)
            np.tanh(np.divide(v, self._coulomb_velocity, work), work)
            np.add(friction, np.multiply(self._k_c, work, work), friction)
        # Eq. 10: Δq = K_τ τ* + K_v q̂̇.
        delta_q = np.multiply(self._k_tau, tau_star, self.delta_q_unsaturated)
        np.add(delta_q, friction, delta_q)
        too_large = np.greater(
            np.abs(delta_q, work), self._fallback_limit, self._exceeds
        )
        return 4 if np.count_nonzero(too_large) else 0

    def _torque_control(self, tau_estimated, q_measured, terms, tau_disturbance):
        """After `_eq10_11` without a fallback: the saturated Δq, q_cmd, the
        components of Δq and the integral."""
        saturated = np.maximum(
            self.delta_q_unsaturated, self._minus_delta_q_limit, out=self.delta_q
        )
        np.minimum(saturated, self._delta_q_limit, out=saturated)
        np.add(q_measured, saturated, self.q_cmd)
        # The components of Δq (DeltaQTorqueController's docstring; Sec. 4.2 eqs.
        # 13-14, Sec. 5.5), from the products in `_scaled` (`step`).
        feedforward, _, _, force, error = self._scaled_rows
        self.feedforward_torque[:] = feedforward
        self._feedback_pv[:] = self._scaled_pv  # K6 e_q, K7 ė_q
        np.add(force, error, self.feedback_force)  # K9 e_f
        # K_τ K_p (τ_ff − τ̂) − K_τ K_p τ_ef
        acceleration = np.subtract(terms[0], tau_estimated, self.feedback_acceleration)
        np.multiply(self._k_tau_kp, acceleration, acceleration)
        np.subtract(acceleration, error, acceleration)
        if self._integrates:  # (else feedback_torque_integral stays zero)
            np.multiply(self._k_tau_ki, self._integral, self.feedback_torque_integral)
        if self._compensates:
            np.multiply(self._minus_k_tau, tau_disturbance, self.feedback_disturbance)
        self.tau_error_integral[:] = self._integral

    def _hold(self, t, q_measured, q_ref, fallback: bool) -> None:
        """Position control: q_cmd = q_ref (None: the q_cmd held), Δq = q_cmd −
        q_measured (0 where not finite), the torque-control arrays zero, and
        fallback_active."""
        if q_ref is not None:
            _check_finite("q_ref", q_ref, t)
            self.q_cmd[:] = q_ref
        delta_q = np.subtract(self.q_cmd, q_measured, self.delta_q)
        if not math.isfinite(delta_q.dot(self._ones_n)):
            delta_q[~np.isfinite(delta_q)] = 0.0
        self._zero_outside_torque_control.fill(0.0)
        self.fallback_active[0] = 1.0 if fallback else 0.0

    def _latch(self, t, q_measured, q_ref, reason: int) -> int:
        """Fallback to position control for `reason`; returns `reason` if the
        fallback starts now, else 0."""
        new = 0 if self.fallback_active[0] else reason
        self._hold(t, q_measured, q_ref, True)
        self.fallback_reason[0] = reason
        return new


def _check_finite(name: str, value: np.ndarray, t: float) -> None:
    if not math.isfinite(np.sum(value)):
        bad = np.flatnonzero(~np.isfinite(value))
        raise ValueError(
            f"{_WHERE}: input port '{name}' is not finite at t = {t:.6g} s, at "
            f"indices {bad.tolist()}"
        )


class DeltaQTorqueController(StepSystem):
    """Joint-torque control by position-servo corrections Δq (paper eq. 10-11), with
    Δq split into the components of Sec. 5.5, saturation and a latching fallback to
    position control.

    .. code-block:: text

                                 ┌────────────────────────┐
        tau_desired ────────────►│                        ├──► q_cmd
        tau_estimated ──────────►│                        ├──► delta_q
        v ──────────────────────►│                        ├──► delta_q_unsaturated
        q_measured ─────────────►│                        ├──► tau_commanded
        q_ref (optional) ───────►│ DeltaQTorqueController ├──► feedforward_torque
        tau_feedforward ────────►│                        ├──► feedforward_friction
        tau_position_feedback ──►│  (the five tau_* are   ├──► feedback_position
        tau_velocity_feedback ──►│   optional, all or     ├──► feedback_velocity
        tau_force_feedback ─────►│   none, from an        ├──► feedback_acceleration
        tau_force_error ────────►│   InverseDynamics-     ├──► feedback_force
                                 │   Controller)          ├──► feedback_torque_integral
                                 │                        ├──► fallback_active
                                 └────────────────────────┘

    Inputs (n = len(config.joints), every joint vector in config.joints order):
        tau_desired (n): τ_d (N·m), e.g. InverseDynamicsController's.
        tau_estimated (n): τ̂ (N·m), e.g. FloatingBaseTorqueEstimator's tau.
        v (n): the estimated joint velocities q̂̇ (rad/s).
        q_measured (n): the encoders (rad), from which q_cmd = q_measured + Δq.
        q_ref (n, optional): the position reference of the fallback (rad).
        sensor_fault (1, optional): > 0 while the estimation filters hold a bad
            sample (`EstimationChain.input_fault`): the estimates rest on held data.
        tau_disturbance (n, only with config.disturbance_compensation): d̂ (N·m),
            subtracted from τ*; not finite: fallback (reason 3).
        tau_feedforward, tau_position_feedback, tau_velocity_feedback,
        tau_force_feedback, tau_force_error (n each, optional: connect all or none,
            e.g. with `connect_inverse_dynamics`): the terms of τ_d of the
            InverseDynamicsController (see its docstring), used only to split Δq into
            its components.

    Outputs (discrete state, updated every config.period):
        q_cmd (n): the position command for the servo (rad).
        delta_q (n): q_cmd − q_measured, what the servo receives (rad): the
            saturated Δq in torque control, the servo error of the position command
            in fallback.
        delta_q_unsaturated (n): Δq of eq. 10 before saturation (rad); zero outside
            torque control.
        tau_commanded (n): τ* of eq. 11 (N·m); zero outside torque control.
        feedforward_torque, feedforward_friction, feedback_position,
        feedback_velocity, feedback_acceleration, feedback_force,
        feedback_torque_integral (n each, rad): the components of Δq (below);
            zero outside torque control.
        fallback_active (1): 1 once the fallback latched, else 0.

    The components. With the inverse-dynamics terms τ_ff = M_j q̈_d + ĥ_j − J_jᵀ f_d,
    τ_Ks = K_s e_q, τ_Kd = K_d ė_q, τ_Kf = −J_jᵀ K_f e_f (τ_d = τ_ff + τ_Ks + τ_Kd +
    τ_Kf) and τ_ef = −J_jᵀ e_f:

        feedforward_torque       = K_τ τ_ff                        (eq. 13, 1st term)
        feedforward_friction     = K_v q̂̇ [+ K_c tanh(q̂̇ / v_s)]    (eq. 13, 2nd term)
        feedback_position        = K_τ (1 + K_p) τ_Ks              = K6 e_q
        feedback_velocity        = K_τ (1 + K_p) τ_Kd              = K7 ė_q
        feedback_force           = K_τ ((1 + K_p) τ_Kf + K_p τ_ef) = K9 e_f
        feedback_acceleration    = K_τ K_p (τ_ff − τ_ef − τ̂)
                                 = K_τ K_p (M_j q̈_d + ĥ_j − J_jᵀ f̂ − τ̂)
        feedback_torque_integral = K_τ K_i ∫ e_τ dt
        feedback_disturbance     = −K_τ d̂                          (with
                                                                    tau_disturbance)

    Identity: they sum to Δq of eq. 10 (delta_q_unsaturated) for any τ̂, because
    K_τ τ* = K_τ ((1 + K_p) τ_d − K_p τ̂ + K_i ∫ e_τ) expands into exactly these
    terms (up to floating-point rounding). When τ̂ = M_j q̂̈ + ĥ_j − J_jᵀ f̂ with the
    controller's own ĥ_j (the assumption of Sec. 4.2), feedback_acceleration is
    K_τ K_p M_j (q̈_d − q̂̈) = K8 ë_q, so the components are eqs. 13-14 term by term;
    with a real estimator it also carries the mismatch between the estimator's and
    the controller's models (and the one-period lag of τ_d behind τ̂), which is part
    of the torque feedback. Without the tau_* inputs, τ_ff = τ_d and the other terms
    are zero: feedforward_torque = K_τ τ_d and feedback_acceleration =
    K_τ K_p (τ_d − τ̂), the whole proportional torque feedback.

    Safety (what a deployment needs):
      - Saturation: Δq is clipped to ±config.delta_q_limit (0.1 rad) per joint.
      - Fallback to position control, latched (it stays until `reset_fallback`):
        when τ̂ is NaN or infinite, |τ̂| > config.tau_limit, τ_d, q̂̇ or a tau_* input
        is not finite, |Δq| before saturation > config.delta_q_fallback_limit,
        q_measured is not finite, or sensor_fault > 0,
        the controller commands q_cmd = q_ref if q_ref is connected, else holds the
        last q_cmd it sent (the last safe one), with Δq = q_cmd − q_measured, and
        sets fallback_active; a warning is logged with the reason
        (`fallback_reason`). The integral stops.
      - Before config.start_time it commands the same position (q_ref, else the
        q_cmd held since initialization) without latching anything.
      - A NaN or infinite q_measured latches the fallback too (without encoders no
        torque command is safe; the servo holds q_ref), with Δq reported 0 where it is
        not finite. A NaN q_ref (our own reference) raises ValueError.
      - An initialization event sets q_cmd = q_ref if connected, else q_measured
        (Δq = 0), so the servo holds the robot from the first step.

    The arithmetic is `DeltaQTorqueStep`'s (this system is its shell: ports, state
    groups, events, the fallback's log line, and the check that the tau_* inputs are
    connected all or none).

    Stability of the torque loop (a property of eq. 10-11, not of this code): the
    servo turns Δq into torque within one period, so if τ̂ followed the applied
    torque immediately (an ideal joint-torque sensor, or the simulator's ground
    truth) the loop τ_{k+d} = (1 + K_p) τ_d − K_p τ_k would have its poles at
    |z| = K_p^(1/d): unstable for K_p > 1 whatever the delay d. With τ̂ estimated
    from the motion through Savitzky-Golay filters (Sec. 2, 5.1) the loop gain at
    high frequency is much lower, and K_p = 2 (the paper's) runs stably on the
    simulated HRP-2.
    """

    def __init__(self, motor_model: MotorModel, config: TorqueControllerConfig):
        """
        Args:
            motor_model: the identified K_τ (rad/(N·m)), K_v (s), K_c (rad) (eq. 6);
                it must have every joint of config.joints, with K_τ > 0.
            config: joints, gains, limits (validated here).
        """
        super().__init__()
        step = DeltaQTorqueStep(motor_model, config)
        n = len(config.joints)

        # Ports.
        self._tau_desired = self.DeclareVectorInputPort("tau_desired", n)
        self._tau_estimated = self.DeclareVectorInputPort("tau_estimated", n)
        self._v = self.DeclareVectorInputPort("v", n)
        self._q_measured = self.DeclareVectorInputPort("q_measured", n)
        self._q_ref = self.DeclareVectorInputPort("q_ref", n)
        self._sensor_fault = self.DeclareVectorInputPort("sensor_fault", 1)
        self._tau_terms = [
            self.DeclareVectorInputPort(name, n) for name in TORQUE_COMPONENTS
        ]
        self._tau_disturbance = (
            self.DeclareVectorInputPort("tau_disturbance", n)
            if config.disturbance_compensation
            else None
        )
        self._declare_step_state(step)
        for name in (
            "q_cmd",
            "delta_q",
            "delta_q_unsaturated",
            "tau_commanded",
            *DELTA_Q_COMPONENTS,
            "fallback_active",
        ):
            self._declare_step_output(name)
        self.DeclareInitializationDiscreteUpdateEvent(self._initialize)
        self.DeclarePeriodicDiscreteUpdateEvent(config.period, 0.0, self._update)

        # Per tick: the step's state arrays that it reads or keeps are the only ones
        # loaded from the context, those it may change the only ones stored (the
        # context's discrete update starts from the current state); the tau_* inputs
        # land in the rows of one work array.
        views = {name: step.state[rows] for name, rows in step.layout()}
        self._carried = [(self.step_group(name), views[name]) for name in step.carried]
        self._written = [
            (self.step_group(name), view)
            for name, view in views.items()
            if name not in step.unused
        ]
        self._terms = np.zeros((len(TORQUE_COMPONENTS), n))
        self._term_rows = list(zip(self._terms, self._tau_terms))

    # ----------------------------------------------------------------- accessors

    def config(self) -> TorqueControllerConfig:
        return self._step.config()

    def motor_model(self) -> MotorModel:
        """The motor model of the controlled joints (config.joints order)."""
        return self._step.motor_model()

    def joint_names(self) -> tuple[str, ...]:
        return self._step.joint_names()

    def _value(self, context: Context, name: str) -> np.ndarray:
        return context.get_discrete_state(self.step_group(name)).get_value()

    def fallback_active(self, context: Context) -> bool:
        return bool(self._value(context, "fallback_active")[0])

    def fallback_reason(self, context: Context) -> str:
        """Why the fallback latched ("" when it did not), see FALLBACK_REASONS."""
        return FALLBACK_REASONS[int(self._value(context, "fallback_reason")[0])]

    def tau_error_integral(self, context: Context) -> np.ndarray:
        """∫ e_τ dt (N·m·s) of eq. 11."""
        return self._value(context, "tau_error_integral").copy()

    def reset_fallback(self, context: Context) -> None:
        """Leaves the fallback: torque control resumes at the next update (with a
        zero torque-error integral)."""
        step = self._step
        step.reset_fallback()
        for name in step.RESET_STATE:
            context.get_mutable_discrete_state(self.step_group(name)).set_value(
                getattr(step, name)
            )

    # ----------------------------------------------------------------- computation

    def _read_finite(self, port: InputPort, context: Context) -> np.ndarray:
        return eval_finite(port, context, f"{_WHERE} {self.GetSystemPathname()}")

    def _read_terms(self, context: Context) -> np.ndarray | None:
        """The rows τ_ff, τ_Ks, τ_Kd, τ_Kf, τ_ef from the tau_* inputs in the work
        array it returns, or None if they are not connected."""
        terms = self._tau_terms
        if terms[0].HasValue(context):  # then all of them, or Eval raises
            try:
                for row, port in self._term_rows:
                    row[:] = port.Eval(context)
                return self._terms
            except RuntimeError:
                if all(port.HasValue(context) for port in terms):
                    raise  # not a missing connection
        if any(port.HasValue(context) for port in terms):
            missing = [p.get_name() for p in terms if not p.HasValue(context)]
            raise RuntimeError(
                f"{_WHERE} {self.GetSystemPathname()}: connect all of "
                f"{list(TORQUE_COMPONENTS)} or none; unconnected: {missing}"
            )
        return None

    def _initialize(self, context: Context, discrete_state: DiscreteValues) -> None:
        self._load(discrete_state)
        q_measured = self._read_finite(self._q_measured, context)
        q_ref = None
        if self._q_ref.HasValue(context):
            q_ref = self._read_finite(self._q_ref, context)
        self._step.initialize(context.get_time(), q_measured, q_ref)
        self._store(discrete_state)

    def _update(self, context: Context, discrete_state: DiscreteValues) -> None:
        # The hot path of every control period: one Eval per input, the step, one
        # set_value per state group (scripts/bench.py --only tick).
        for group, view in self._carried:
            view[:] = discrete_state.get_value(group)
        q_ref = sensor_fault = disturbance = None
        if self._q_ref.HasValue(context):
            q_ref = self._q_ref.Eval(context)
        if self._sensor_fault.HasValue(context):
            sensor_fault = self._sensor_fault.Eval(context)
        if self._tau_disturbance is not None:
            disturbance = self._tau_disturbance.Eval(context)
        reason = self._step.step(
            context.get_time(),
            self._tau_desired.Eval(context),
            self._tau_estimated.Eval(context),
            self._v.Eval(context),
            self._q_measured.Eval(context),
            q_ref,
            sensor_fault,
            self._read_terms(context),
            disturbance,
        )
        if reason:
            _logger.warning(
                "%s %s: falling back to position control at t = %.6g s: %s",
                _WHERE,
                self.GetSystemPathname(),
                context.get_time(),
                FALLBACK_REASONS[reason],
            )
        for group, view in self._written:
            discrete_state.set_value(group, view)


# --------------------------------------------------------------------- wiring


class JointCommandMerger(Selector):
    """The whole-robot position command: a full reference with the entries of the
    torque-controlled joints replaced by the torque controller's q_cmd.

    .. code-block:: text

                       ┌────────────────────┐
        q_ref ────────►│                    │
                       │ JointCommandMerger ├──► q_cmd
        q_controlled ─►│                    │
                       └────────────────────┘

    Inputs:
        q_ref (N): the position reference of every joint (rad), all_joint_names
            order: the joints not in joint_names stay position controlled.
        q_controlled (n): DeltaQTorqueController's q_cmd (rad), joint_names order.

    Output:
        q_cmd (N): q_ref with the joint_names entries replaced by q_controlled
            (direct feedthrough, no state: it is wiring).

    A Drake Selector (C++, entries copied): wiring that runs at every plant step needs
    no Python.
    """

    def __init__(self, all_joint_names: Sequence[str], joint_names: Sequence[str]):
        """
        Args:
            all_joint_names: the N joints of the command (e.g. HRP-2's JOINT_NAMES).
            joint_names: the n torque-controlled joints, each among all_joint_names.

        Raises:
            KeyError: a joint of joint_names is not in all_joint_names.
            ValueError: duplicated names.
        """
        rows = _selection_rows(all_joint_names, joint_names, "JointCommandMerger")
        N, n = len(all_joint_names), len(joint_names)
        # Entry i of q_cmd: q_ref[i], or q_controlled[k] if joint i is controlled
        # joint k.
        source = {i: (0, i) for i in range(N)} | {
            int(row): (1, k) for k, row in enumerate(rows)
        }
        Params = SelectorParams
        super().__init__(
            Params(
                inputs=[
                    Params.InputPortParams(name="q_ref", size=N),
                    Params.InputPortParams(name="q_controlled", size=n),
                ],
                outputs=[
                    Params.OutputPortParams(
                        name="q_cmd",
                        selections=[
                            Params.OutputSelection(
                                input_port_index=port, input_offset=k
                            )
                            for port, k in (source[i] for i in range(N))
                        ],
                    )
                ],
            )
        )


def _selection_rows(
    all_joint_names: Sequence[str], joint_names: Sequence[str], where: str
) -> np.ndarray:
    all_joint_names, joint_names = list(all_joint_names), list(joint_names)
    for names, what in (
        (all_joint_names, "all_joint_names"),
        (joint_names, "joint_names"),
    ):
        duplicates = sorted({j for j in names if names.count(j) > 1})
        if duplicates:
            raise ValueError(f"{where}: duplicated joints {duplicates} in {what}")
    missing = [j for j in joint_names if j not in all_joint_names]
    if missing:
        raise KeyError(f"{where}: joints {missing} are not among all_joint_names")
    return np.array([all_joint_names.index(j) for j in joint_names], dtype=int)


def make_joint_selector(
    all_joint_names: Sequence[str], joint_names: Sequence[str]
) -> MatrixGain:
    """A MatrixGain (ports u0 → y0) that selects the joint_names entries of an
    all_joint_names vector, e.g. the right leg's q_measured from the station's."""
    rows = _selection_rows(all_joint_names, joint_names, "make_joint_selector")
    select = np.zeros((len(rows), len(all_joint_names)))
    select[np.arange(len(rows)), rows] = 1.0
    return MatrixGain(select)


def connect_inverse_dynamics(
    builder: DiagramBuilder,
    inverse_dynamics: InverseDynamicsController,
    torque_controller: DeltaQTorqueController,
) -> None:
    """Connects tau_desired and the five tau_* terms of `inverse_dynamics` to
    `torque_controller` (both already in `builder`, for the same joints)."""
    if tuple(inverse_dynamics.joint_names()) != tuple(torque_controller.joint_names()):
        raise ValueError(
            "connect_inverse_dynamics: the controllers' joints differ: "
            f"{inverse_dynamics.joint_names()} vs {torque_controller.joint_names()}"
        )
    for name in ("tau_desired", *TORQUE_COMPONENTS):
        builder.Connect(
            inverse_dynamics.GetOutputPort(name), torque_controller.GetInputPort(name)
        )


# --------------------------------------------------------------------- Sec. 4.2


class TorqueControlGains(NamedTuple):
    """The gains of eq. 14: K6, K7, K8 (n, n) and K9 (n, k), None without a force
    task. K6 is in rad/rad, K7 in s, K8 in s², K9 in rad/N (rad/(N·m) for torque
    rows of the wrench)."""

    k6: np.ndarray
    k7: np.ndarray
    k8: np.ndarray
    k9: np.ndarray | None


class UserGains(NamedTuple):
    """The user's gains: K_p (n, n), K_s (n, n, N·m/rad), K_d (n, n, N·m·s/rad),
    K_f (k, k), None without a force task."""

    kp: np.ndarray
    ks: np.ndarray
    kd: np.ndarray
    kf: np.ndarray | None


def _as_matrix(name: str, value, size: int) -> np.ndarray:
    """A number, a vector (a diagonal) or a (size, size) matrix as a matrix."""
    array = np.asarray(value, dtype=float)
    if array.ndim == 0 or (array.ndim == 1 and array.size == 1):
        matrix = float(array.reshape(-1)[0]) * np.eye(size)
    elif array.shape == (size,):
        matrix = np.diag(array)
    elif array.shape == (size, size):
        matrix = array.copy()
    else:
        raise ValueError(
            f"gain mapping: '{name}' has shape {array.shape}, expected a number, "
            f"({size},) or ({size}, {size})"
        )
    if not np.all(np.isfinite(matrix)):
        raise ValueError(f"gain mapping: '{name}' is not finite")
    return matrix


def _joint_count(*values) -> int:
    """n from the first of `values` that is a vector or a matrix (1 if none)."""
    for value in values:
        if value is not None and np.ndim(value) >= 1 and np.size(value) > 1:
            return int(np.shape(value)[0])
    return 1


def _check_shape(name: str, value, shape: tuple[int, ...]) -> np.ndarray:
    array = np.asarray(value, dtype=float)
    if array.shape != shape:
        raise ValueError(
            f"gain mapping: '{name}' has shape {array.shape}, expected {shape}"
        )
    if not np.all(np.isfinite(array)):
        raise ValueError(f"gain mapping: '{name}' is not finite")
    return array


def _check_jacobian(jacobian, n: int) -> np.ndarray:
    """J_j as a finite (k, n) float array (raises ValueError otherwise)."""
    J = np.asarray(jacobian, dtype=float)
    if J.ndim != 2 or J.shape[1] != n:
        raise ValueError(
            f"gain mapping: 'jacobian' has shape {J.shape}, expected (k, {n})"
        )
    return _check_shape("jacobian", J, J.shape)


def gains_from_user(
    k_tau,
    kp,
    ks,
    kd,
    kf,
    mass_matrix: np.ndarray,
    jacobian: np.ndarray | None,
) -> TorqueControlGains:
    """{K_p, K_s, K_d, K_f} → {K6, K7, K8, K9} given K_τ, M_j, J_j (paper Sec. 4.2).

    Args:
        k_tau: K_τ (rad/(N·m)): a number, an (n,) diagonal or an (n, n) matrix.
        kp, ks, kd: K_p, K_s (N·m/rad), K_d (N·m·s/rad): the same forms.
        kf: K_f: a number, a (k,) diagonal or a (k, k) matrix; ignored without a
            force task.
        mass_matrix: M_j (n, n), e.g. InverseDynamicsController.joint_space_model.
        jacobian: J_j (k, n), the force task's Jacobian in the frame of f; None
            without a force task (then K9 is None).
    """
    M = np.asarray(mass_matrix, dtype=float)
    if M.ndim != 2 or M.shape[0] != M.shape[1]:
        raise ValueError(
            f"gain mapping: 'mass_matrix' has shape {M.shape}, expected (n, n)"
        )
    n = M.shape[0]
    M = _check_shape("mass_matrix", M, (n, n))
    K_tau = _as_matrix("k_tau", k_tau, n)
    Kp = _as_matrix("kp", kp, n)
    I = np.eye(n)
    k6 = K_tau @ (I + Kp) @ _as_matrix("ks", ks, n)  # K6 = K_τ (I + K_p) K_s
    k7 = K_tau @ (I + Kp) @ _as_matrix("kd", kd, n)  # K7 = K_τ (I + K_p) K_d
    k8 = K_tau @ Kp @ M  # K8 = K_τ K_p M_j
    k9 = None
    if jacobian is not None:
        J = _check_jacobian(jacobian, n)
        Kf = _as_matrix("kf", kf, J.shape[0])
        # K9 = −K_τ (K_p J_jᵀ (I + K_f) + J_jᵀ K_f)
        k9 = -K_tau @ (Kp @ J.T @ (np.eye(J.shape[0]) + Kf) + J.T @ Kf)
    return TorqueControlGains(k6, k7, k8, k9)


def user_from_gains(
    k_tau,
    k6,
    k7,
    k9=None,
    jacobian: np.ndarray | None = None,
    *,
    kp=2.0,
    k8=None,
    mass_matrix: np.ndarray | None = None,
) -> UserGains:
    """{K6, K7, K9} (and K_p, or K8 with M_j) → {K_p, K_s, K_d, K_f}, the inverse of
    `gains_from_user` (paper Sec. 4.2).

    The set {K6, K7, K8, K9} over-determines the user's gains: K8 = K_τ K_p M_j fixes
    K_p by itself, so either K_p is given (default 2, the paper's) or it is computed
    from K8 and M_j (pass kp=None, k8 and mass_matrix): K_p = K_τ⁻¹ K8 M_j⁻¹.
    Then K_s = (K_τ (I + K_p))⁻¹ K6, K_d = (K_τ (I + K_p))⁻¹ K7, and K_f solves
    J_jᵀ K_f = (I + K_p)⁻¹ (−K_τ⁻¹ K9 − K_p J_jᵀ) (exactly when J_j has full row
    rank k, as the right leg's 6 x 6 Jacobian away from singularities).

    Args:
        k_tau: K_τ (rad/(N·m)): a number, an (n,) diagonal or an (n, n) matrix.
        k6, k7: K6, K7, same forms.
        k9: K9 (n, k); None without a force task (then K_f is None).
        jacobian: J_j (k, n), needed with k9.
        kp: K_p (same forms as k_tau), or None to compute it from k8 and mass_matrix.
        k8, mass_matrix: K8 and M_j (n, n), only with kp=None.

    Raises:
        ValueError: wrong shapes, singular K_τ (I + K_p) or M_j, a rank-deficient
            J_j, or a K9 that no K_f produces for these K_p, K_τ, J_j.
    """
    n = _joint_count(k_tau, k6, k7, kp, k8, mass_matrix)
    K_tau = _as_matrix("k_tau", k_tau, n)
    K6 = _as_matrix("k6", k6, n)
    K7 = _as_matrix("k7", k7, n)
    Kp = _user_kp(K_tau, kp, k8, mass_matrix, n)
    I = np.eye(n)
    A = K_tau @ (I + Kp)
    if np.linalg.cond(A) > 1e12:
        raise ValueError("user_from_gains: K_τ (I + K_p) is singular")
    ks = np.linalg.solve(A, K6)
    kd = np.linalg.solve(A, K7)
    kf = None
    if k9 is not None:
        if jacobian is None:
            raise ValueError("user_from_gains: k9 needs the jacobian")
        kf = _user_kf(K_tau, Kp, k9, _check_jacobian(jacobian, n))
    return UserGains(Kp, ks, kd, kf)


def _user_kp(K_tau: np.ndarray, kp, k8, mass_matrix, n: int) -> np.ndarray:
    """K_p of `user_from_gains`: `kp` as a matrix, or K_τ⁻¹ K8 M_j⁻¹ with kp=None."""
    if kp is None:
        if k8 is None or mass_matrix is None:
            raise ValueError("user_from_gains: with kp=None, give k8 and mass_matrix")
        K8 = _check_shape("k8", k8, (n, n))
        M = _check_shape("mass_matrix", mass_matrix, (n, n))
        # K8 = K_τ K_p M_j  →  K_p = K_τ⁻¹ K8 M_j⁻¹
        return np.linalg.solve(M.T, np.linalg.solve(K_tau, K8).T).T
    if k8 is not None or mass_matrix is not None:
        raise ValueError("user_from_gains: give kp, or k8 and mass_matrix, not both")
    return _as_matrix("kp", kp, n)


def _user_kf(K_tau: np.ndarray, Kp: np.ndarray, k9, J: np.ndarray) -> np.ndarray:
    """K_f of `user_from_gains`: the solution of J_jᵀ K_f = (I + K_p)⁻¹ (−K_τ⁻¹ K9 −
    K_p J_jᵀ), for a checked J_j (k, n) of full row rank and a K9 it can produce."""
    n, k = J.shape[1], J.shape[0]
    K9 = _check_shape("k9", k9, (n, k))
    if np.linalg.matrix_rank(J) < k:
        raise ValueError(
            f"user_from_gains: J_j has rank {np.linalg.matrix_rank(J)} < {k}: K_f "
            "is not determined by K9"
        )
    # K9 = −K_τ (K_p J_jᵀ + (I + K_p) J_jᵀ K_f)
    B = np.linalg.solve(np.eye(n) + Kp, -np.linalg.solve(K_tau, K9) - Kp @ J.T)
    kf, *_ = np.linalg.lstsq(J.T, B, rcond=None)
    residual = np.linalg.norm(J.T @ kf - B)
    if residual > 1e-8 * max(np.linalg.norm(B), 1e-300):
        raise ValueError(
            "user_from_gains: no K_f gives this K9 for these K_p, K_τ and J_j "
            f"(relative residual {residual / np.linalg.norm(B):.3g})"
        )
    return kf


def inverse_dynamics_gains_for_k6(
    k_tau,
    k6,
    joint_inertia,
    kp=2.0,
    damping_ratio: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """K_s and K_d of eq. 12 for a position-feedback gain K6 (the paper's tuning knob,
    Sec. 4.2 and 5.3: K6 = 1 is the native position servo's position gain).

    K_s = K6 / (K_τ (1 + K_p)) per joint (inverse of K6 = K_τ (1 + K_p) K_s), and
    K_d = 2 ζ sqrt(K_s M_jj): if the torque loop tracks τ_d, each joint's error obeys
    M_jj ë + K_d ė + K_s e = 0, a second-order system of damping ratio ζ (the
    coupling of M_j's off-diagonal terms neglected; on HRP-2 M_jj is dominated by
    the reflected rotor inertia ρ² I_r, so it barely changes with the posture). Then
    K7 = K_τ (1 + K_p) K_d = 2 ζ sqrt(K6 K_τ (1 + K_p) M_jj).

    Args:
        k_tau: K_τ per joint (rad/(N·m)), a number or (n,).
        k6: K6 per joint (rad/rad), a number or (n,).
        joint_inertia: M_jj per joint (kg·m²), (n,) or a number, e.g. the diagonal
            of InverseDynamicsController.joint_space_model(q).mass_matrix.
        kp: K_p per joint, a number or (n,).
        damping_ratio: ζ (dimensionless, >= 0).

    Returns:
        (ks, kd): (n,) arrays in N·m/rad and N·m·s/rad.
    """
    sizes = [np.size(x) for x in (k_tau, k6, joint_inertia, kp)]
    n = max(sizes)
    where = "inverse_dynamics_gains_for_k6"
    k_tau = gain_vector("k_tau", k_tau, n, where)
    k6 = gain_vector("k6", k6, n, where)
    inertia = gain_vector("joint_inertia", joint_inertia, n, where)
    kp = gain_vector("kp", kp, n, where)
    if not np.all(k_tau > 0):
        raise ValueError(f"{where}: k_tau must be > 0, got {k_tau}")
    if not (math.isfinite(damping_ratio) and damping_ratio >= 0):
        raise ValueError(f"{where}: damping_ratio={damping_ratio} must be >= 0")
    ks = k6 / (k_tau * (1.0 + kp))
    kd = 2.0 * damping_ratio * np.sqrt(ks * inertia)
    return ks, kd
