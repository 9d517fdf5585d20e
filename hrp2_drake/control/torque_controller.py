"""DeltaQTorqueController: joint-torque control through a position servo (paper Sec.
4.1.1-4.1.2, eq. 10-11), its per-tick step (`DeltaQTorqueControllerStep`) and its
kernels. Beside it: K_s, K_d for a position gain K6 (gains.py).

The control law (per joint, all gains diagonal):

    τ* = τ_d + K_p e_τ + K_i ∫ e_τ dt,   e_τ = τ_d − τ̂                 (eq. 11)
         [− d̂, a DisturbanceObserver's estimate, with disturbance_compensation]
    Δq = K_τ τ* + K_v q̂̇                                               (eq. 10)
    q_cmd = q_measured + Δq                                           (eq. 6: Δq is
                                                        the servo's input error)

K_τ and K_v come from the identified MotorModel (eq. 6); the paper's controller has
no Coulomb term, an option adds K_c tanh(q̂̇ / v_s).
"""

import logging
import math
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np
from pydrake.systems.framework import Context, DiscreteValues, InputPort

from hrp2_drake.control.inverse_dynamics import TORQUE_COMPONENTS, gain_vector
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.kernels import kernel
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


class FallbackReason(IntEnum):
    """Why the controller fell back to position control (`fallback_reason`): the
    codes the step's kernel returns (`_delta_q_step`)."""

    NONE = 0
    TAU_ESTIMATED_NOT_FINITE = 1
    TAU_LIMIT = 2
    INPUT_NOT_FINITE = 3
    DELTA_Q_FALLBACK_LIMIT = 4
    Q_MEASURED_NOT_FINITE = 5
    SENSOR_FAULT = 6


#: Each FallbackReason in words.
FALLBACK_REASONS: dict[int, str] = {
    FallbackReason.NONE: "",
    FallbackReason.TAU_ESTIMATED_NOT_FINITE: "tau_estimated is not finite",
    FallbackReason.TAU_LIMIT: "|tau_estimated| exceeds tau_limit",
    FallbackReason.INPUT_NOT_FINITE: "tau_desired, v, tau_disturbance or a torque "
    "component of the inverse dynamics is not finite",
    FallbackReason.DELTA_Q_FALLBACK_LIMIT: "|delta_q| before saturation exceeds "
    "delta_q_fallback_limit",
    FallbackReason.Q_MEASURED_NOT_FINITE: "q_measured is not finite",
    FallbackReason.SENSOR_FAULT: "sensor_fault: the estimation filters hold a NaN or "
    "infinite sample",
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
        period: the control period (s; a keyword, no default).
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
    period: float = field(kw_only=True)
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


# The state of DeltaQTorqueControllerStep, as the kernels index it: the start of each
# named array in units of n (the order of its `_declare` calls, checked at
# construction), then fallback_active, fallback_reason, tau_error_integral at 12 n,
# 12 n + 1, 12 n + 2.
_Q_CMD, _DELTA_Q, _DELTA_Q_UNSATURATED, _TAU_COMMANDED = 0, 1, 2, 3
_FF_TORQUE, _FF_FRICTION, _FB_POSITION, _FB_VELOCITY = 4, 5, 6, 7
_FB_ACCELERATION, _FB_FORCE, _FB_INTEGRAL, _FB_DISTURBANCE = 8, 9, 10, 11
_FALLBACK = 12  # fallback_active at 12 n, fallback_reason and the integral after it
_STATE_ROWS = 13  # the state has 13 n + 2 entries
# Its constants (`DeltaQTorqueControllerStep._constants`, packed once): rows of n, then
# the scalars at _C_ROWS n.
(
    _C_KP,
    _C_KI,
    _C_INTEGRAL_LIMIT,
    _C_DELTA_Q_LIMIT,
    _C_FALLBACK_LIMIT,
    _C_TAU_LIMIT,
    _C_K_TAU,
    _C_K_V,
    _C_K_C,
    _C_K_TAU_ONE_PLUS_KP,
    _C_K_TAU_KP,
    _C_K_TAU_KI,
) = range(12)
_C_ROWS = 12
_S_PERIOD, _S_COULOMB_VELOCITY, _S_INTEGRATES, _S_COMPENSATES, _S_COULOMB, _S_LATCH = (
    range(6)
)
_S_COUNT = 6
# What the kernels return besides a FALLBACK_REASONS code: the step raises.
_Q_REF_NOT_FINITE, _NO_DISTURBANCE, _BAD_SIZE = -1, -2, -3


@kernel
def _delta_q_hold(q_measured, q_ref, has_q_ref, fallback, state):
    """Position control on DeltaQTorqueControllerStep's `state`: q_cmd = q_ref
    (has_q_ref False: the q_cmd held), Δq = q_cmd − q_measured (0 where not finite), the
    torque-control arrays zero, fallback_active = fallback. Returns 0, or
    _Q_REF_NOT_FINITE (nothing changed) or _BAD_SIZE."""
    n = (state.shape[0] - 2) // _STATE_ROWS
    if q_measured.shape[0] != n or (has_q_ref and q_ref.shape[0] != n):
        return _BAD_SIZE
    if has_q_ref:
        total = 0.0
        for i in range(n):
            total += q_ref[i]
        if not math.isfinite(total):
            return _Q_REF_NOT_FINITE
        for i in range(n):
            state[_Q_CMD * n + i] = q_ref[i]
    for i in range(n):
        delta = state[_Q_CMD * n + i] - q_measured[i]
        state[_DELTA_Q * n + i] = delta if math.isfinite(delta) else 0.0
    # delta_q_unsaturated .. feedback_disturbance: zero outside torque control.
    for j in range(_DELTA_Q_UNSATURATED * n, (_FB_DISTURBANCE + 1) * n):
        state[j] = 0.0
    state[_FALLBACK * n] = 1.0 if fallback else 0.0
    return 0


# Whole: one compiled pass on the tick's arrays; a split costs calls (scripts/bench.py)
@kernel
def _delta_q_step(
    before_start,
    tau_desired,
    tau_estimated,
    v,
    q_measured,
    q_ref,
    has_q_ref,
    sensor_fault,
    terms,
    has_terms,
    tau_disturbance,
    has_disturbance,
    state,
    constants,
):
    """One tick of DeltaQTorqueControllerStep on its `state` with its packed `constants`
    (`DeltaQTorqueControllerStep.step`: the arguments are its inputs, a flag for each
    optional one, whose array is then a stand-in). Returns the FALLBACK_REASONS code of
    a fallback that starts now (else 0), or a negative code on which the step raises.

    Elementwise, in numpy's order of operations (the numbers of the numpy version
    bit for bit), except K_c tanh(q̂̇ / v_s), libm's tanh where numpy's own SIMD one
    differs by at most one unit in the last place; the sums only test finiteness.
    """
    n = (state.shape[0] - 2) // _STATE_ROWS
    c = constants
    if (
        tau_desired.shape[0] != n
        or tau_estimated.shape[0] != n
        or v.shape[0] != n
        or q_measured.shape[0] != n
        or (has_q_ref and q_ref.shape[0] != n)
        or sensor_fault.shape[0] < 1
        or (has_terms and (terms.shape[0] != 5 or terms.shape[1] != n))
        or (has_disturbance and tau_disturbance.shape[0] != n)
        or c.shape[0] != _C_ROWS * n + _S_COUNT
    ):
        return _BAD_SIZE
    scalars = _C_ROWS * n
    period = c[scalars + _S_PERIOD]
    integrates = c[scalars + _S_INTEGRATES] != 0.0
    compensates = c[scalars + _S_COMPENSATES] != 0.0
    active = _FALLBACK * n  # fallback_active; fallback_reason, tau_error_integral
    integral_row = active + 2
    total = 0.0
    for i in range(n):
        total += q_measured[i]
    fallback = False
    reason = 0
    if not math.isfinite(total):
        # No torque command is safe without the encoders: hand back to the servo.
        reason = 5
    else:
        if before_start:
            return _delta_q_hold(q_measured, q_ref, has_q_ref, False, state)
        fallback = state[active] != 0.0
        if fallback and c[scalars + _S_LATCH] != 0.0:
            return _delta_q_hold(q_measured, q_ref, has_q_ref, True, state)
        # A bad input (codes 6, 1, 2, 3); the terms through their products with
        # the gains, finite exactly when the terms are (finite, non-negative gains).
        if sensor_fault[0] > 0:
            reason = 6
        else:
            total = 0.0
            for i in range(n):
                total += tau_estimated[i]
            if not math.isfinite(total):
                reason = 1
            else:
                for i in range(n):
                    if abs(tau_estimated[i]) > c[_C_TAU_LIMIT * n + i]:
                        reason = 2
                        break
            if reason == 0:
                desired = 0.0
                velocity = 0.0
                scaled = 0.0
                for i in range(n):
                    desired += tau_desired[i]
                    velocity += v[i]
                    k_tau_one_plus_kp = c[_C_K_TAU_ONE_PLUS_KP * n + i]
                    if has_terms:
                        scaled += (
                            c[_C_K_TAU * n + i] * terms[0, i]
                            + k_tau_one_plus_kp * terms[1, i]
                            + k_tau_one_plus_kp * terms[2, i]
                            + k_tau_one_plus_kp * terms[3, i]
                            + c[_C_K_TAU_KP * n + i] * terms[4, i]
                        )
                    else:
                        scaled += c[_C_K_TAU * n + i] * tau_desired[i]
                if not math.isfinite(desired + velocity + scaled):
                    reason = 3
        if reason == 0 and compensates:
            if not has_disturbance:
                return _NO_DISTURBANCE
            total = 0.0
            for i in range(n):
                total += tau_disturbance[i]
            if not math.isfinite(total):
                reason = 3
        if reason == 0:
            # Eq. 11 into tau_commanded, eq. 10 into delta_q_unsaturated, the
            # friction feedforward; |Δq| beyond delta_q_fallback_limit: code 4.
            coulomb = c[scalars + _S_COULOMB] != 0.0
            coulomb_velocity = c[scalars + _S_COULOMB_VELOCITY]
            for i in range(n):
                e_tau = tau_desired[i] - tau_estimated[i]
                integral = _clipped_integral(
                    state[integral_row + i], e_tau, period, c[_C_INTEGRAL_LIMIT * n + i]
                )
                # τ* = τ_d + K_p e_τ + K_i ∫ e_τ dt [− d̂].
                tau_star = tau_desired[i] + c[_C_KP * n + i] * e_tau
                if integrates:
                    tau_star = tau_star + c[_C_KI * n + i] * integral
                if compensates:
                    tau_star = tau_star - tau_disturbance[i]
                state[_TAU_COMMANDED * n + i] = tau_star
                friction = c[_C_K_V * n + i] * v[i]
                if coulomb:  # + K_c tanh(q̂̇ / v_s)
                    friction = friction + c[_C_K_C * n + i] * math.tanh(
                        v[i] / coulomb_velocity
                    )
                state[_FF_FRICTION * n + i] = friction
                # Eq. 10: Δq = K_τ τ* + K_v q̂̇.
                delta_q = c[_C_K_TAU * n + i] * tau_star + friction
                state[_DELTA_Q_UNSATURATED * n + i] = delta_q
                if abs(delta_q) > c[_C_FALLBACK_LIMIT * n + i]:
                    reason = 4
        if reason == 0:
            # Torque control: the saturated Δq, q_cmd, the components of Δq
            # (DeltaQTorqueController's docstring; Sec. 4.2 eqs. 13-14, Sec. 5.5),
            # the integral.
            for i in range(n):
                limit = c[_C_DELTA_Q_LIMIT * n + i]
                delta_q = state[_DELTA_Q_UNSATURATED * n + i]
                delta_q = min(max(delta_q, -limit), limit)  # (np.maximum, np.minimum)
                state[_DELTA_Q * n + i] = delta_q
                state[_Q_CMD * n + i] = q_measured[i] + delta_q
                k_tau = c[_C_K_TAU * n + i]
                k_tau_one_plus_kp = c[_C_K_TAU_ONE_PLUS_KP * n + i]
                k_tau_kp = c[_C_K_TAU_KP * n + i]
                if has_terms:
                    feedforward = terms[0, i]
                    position, velocity, force, error = (
                        terms[1, i],
                        terms[2, i],
                        terms[3, i],
                        terms[4, i],
                    )
                else:  # τ_ff = τ_d, the others zero
                    feedforward = tau_desired[i]
                    position = velocity = force = error = 0.0
                state[_FF_TORQUE * n + i] = k_tau * feedforward  # K_τ τ_ff
                state[_FB_POSITION * n + i] = k_tau_one_plus_kp * position  # K6 e_q
                state[_FB_VELOCITY * n + i] = k_tau_one_plus_kp * velocity  # K7 ė_q
                error = k_tau_kp * error  # K_τ K_p τ_ef
                state[_FB_FORCE * n + i] = k_tau_one_plus_kp * force + error  # K9 e_f
                # K_τ K_p (τ_ff − τ̂) − K_τ K_p τ_ef
                state[_FB_ACCELERATION * n + i] = (
                    k_tau_kp * (feedforward - tau_estimated[i]) - error
                )
                e_tau = tau_desired[i] - tau_estimated[i]
                integral = _clipped_integral(
                    state[integral_row + i], e_tau, period, c[_C_INTEGRAL_LIMIT * n + i]
                )
                if integrates:  # (else feedback_torque_integral stays zero)
                    state[_FB_INTEGRAL * n + i] = c[_C_K_TAU_KI * n + i] * integral
                if compensates:
                    state[_FB_DISTURBANCE * n + i] = -k_tau * tau_disturbance[i]
                state[integral_row + i] = integral
            if fallback:  # not latched: torque control resumes
                state[active] = 0.0
            return 0
    # The fallback to position control for `reason`: its code if it starts now.
    new = 0 if state[active] != 0.0 else reason
    code = _delta_q_hold(q_measured, q_ref, has_q_ref, True, state)
    if code:
        return code
    state[active + 1] = reason
    return new


@kernel
def _clipped_integral(integral, e_tau, period, limit):
    """The next ∫ e_τ dt (forward Euler), clipped to ±limit (anti-windup)."""
    integral = integral + e_tau * period
    # As np.maximum then np.minimum: a NaN stays NaN (the first argument).
    return min(max(integral, -limit), limit)


class DeltaQTorqueControllerStep(Step):
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
    store them).

    A tick is one numba kernel (`_delta_q_step`) on the state and the gains, packed
    once into one array (`hrp2_drake.kernels`); it allocates nothing.
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
        for name in ("q_cmd", "delta_q", "delta_q_unsaturated", "tau_commanded"):
            self._declare(name, np.zeros(n))
        for name in DELTA_Q_COMPONENTS:
            self._declare(name, np.zeros(n))
        self._declare("fallback_active", np.zeros(1))
        self._declare("fallback_reason", np.zeros(1))
        self._declare("tau_error_integral", np.zeros(n))
        self._finalize()
        self._check_layout()
        # Stand-ins for the optional inputs (the kernel's flags say they are absent).
        self._no_fault = np.zeros(1)
        self._no_terms = np.zeros((len(TORQUE_COMPONENTS), n))
        self._no_disturbance = np.zeros(n)
        #: The state arrays that stay zero under this config.
        self.unused: tuple[str, ...] = ()
        if not self._integrates:
            self.unused += ("feedback_torque_integral",)
        if not config.disturbance_compensation:
            self.unused += ("feedback_disturbance",)

    def _make_gains(self) -> None:
        """The gains, bounds and their products, formed once and packed into one
        array for the kernel (`_constants`: the rows _C_*, then the scalars _S_*)."""
        config, n = self._config, self._n
        vectors = config.vectors()
        kp, ki = vectors["kp"], vectors["ki"]
        k_tau = self._motor.k_tau
        k_c = self._motor.k_c if config.coulomb_compensation else np.zeros(n)
        self._integrates = bool(np.any(ki != 0.0))  # else ∫ e_τ dt is unused
        rows = {
            _C_KP: kp,
            _C_KI: ki,
            _C_INTEGRAL_LIMIT: vectors["integral_limit"],
            _C_DELTA_Q_LIMIT: vectors["delta_q_limit"],
            _C_FALLBACK_LIMIT: vectors["delta_q_fallback_limit"],
            _C_TAU_LIMIT: vectors["tau_limit"],
            _C_K_TAU: k_tau,
            _C_K_V: self._motor.k_v,
            _C_K_C: k_c,
            # The gains of τ_Ks, τ_Kd, τ_Kf and of τ_ef in the components of Δq.
            _C_K_TAU_ONE_PLUS_KP: k_tau * (1.0 + kp),
            _C_K_TAU_KP: k_tau * kp,
            _C_K_TAU_KI: k_tau * ki,
        }
        scalars = np.zeros(_S_COUNT)
        scalars[_S_PERIOD] = config.period
        scalars[_S_COULOMB_VELOCITY] = config.coulomb_velocity
        scalars[_S_INTEGRATES] = self._integrates
        scalars[_S_COMPENSATES] = config.disturbance_compensation
        scalars[_S_COULOMB] = config.coulomb_compensation
        scalars[_S_LATCH] = config.latch_fallback
        self._constants = np.concatenate(
            [np.asarray(rows[r], dtype=float) for r in range(_C_ROWS)] + [scalars]
        )
        self._half_period = 0.5 * config.period
        self._start_time = config.start_time

    def _check_layout(self) -> None:
        """The kernels index the state by the _Q_CMD .. _FB_DISTURBANCE rows."""
        n = self._n
        names = ("q_cmd", "delta_q", "delta_q_unsaturated", "tau_commanded")
        expected = {name: k * n for k, name in enumerate(names + DELTA_Q_COMPONENTS)}
        active = _FALLBACK * n
        expected |= {
            "fallback_active": active,
            "fallback_reason": active + 1,
            "tau_error_integral": active + 2,
        }
        actual = {name: rows.start for name, rows in self.layout()}
        if actual != expected or self.state_size != _STATE_ROWS * n + 2:
            raise AssertionError(f"{_WHERE}: the state layout is not the kernels'")

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
        q_ref = q_measured if q_ref is None else q_ref
        code = _delta_q_hold(q_measured, q_ref, True, False, self.state)
        if code:
            self._raise(code, t, q_ref)

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
                dynamics (TORQUE_COMPONENTS order, e.g.
                InverseDynamicsControllerStep.terms), N·m; None: τ_ff = τ_d and zeros.
            tau_disturbance: d̂ (N·m), n, with config.disturbance_compensation
                (required then; ignored otherwise).

        Every array is float64 (the kernel is compiled for float64 arrays,
        `warm_up`).

        Returns:
            The FALLBACK_REASONS code of a fallback that starts at this tick (the
            previous tick was not in fallback), else 0: what the controller logs
            once, and what a fused controller counts.

        Raises:
            ValueError: q_ref, when it is used (position control), is not finite;
                tau_disturbance is None with config.disturbance_compensation; an
                input of the wrong size.
        """
        code = _delta_q_step(
            t + self._half_period < self._start_time,
            tau_desired,
            tau_estimated,
            v,
            q_measured,
            q_measured if q_ref is None else q_ref,
            q_ref is not None,
            self._no_fault if sensor_fault is None else sensor_fault,
            self._no_terms if terms is None else terms,
            terms is not None,
            self._no_disturbance if tau_disturbance is None else tau_disturbance,
            tau_disturbance is not None,
            self.state,
            self._constants,
        )
        if code < 0:
            self._raise(code, t, q_ref)
        return code

    def _raise(self, code: int, t: float, q_ref: np.ndarray | None) -> None:
        """The error of a kernel's negative code."""
        if code == _Q_REF_NOT_FINITE:
            _check_finite("q_ref", q_ref, t)
            raise ValueError(
                f"{_WHERE}: input port 'q_ref' is not finite at t = {t:.6g} s"
            )
        if code == _NO_DISTURBANCE:
            raise ValueError(f"{_WHERE}: disturbance_compensation needs d̂")
        n = self._n
        raise ValueError(
            f"{_WHERE}: at t = {t:.6g} s, an input of the wrong size: every joint "
            f"vector has {n} entries, terms ({len(TORQUE_COMPONENTS)}, {n}), "
            "sensor_fault 1"
        )

    def warm_up(self) -> None:
        """Compiles (or loads from numba's cache) `_delta_q_step` and `_delta_q_hold`
        for the arrays of a tick (C-contiguous float64; terms (5, n)), on copies:
        the state is left as it was; and `_clipped_integral` for its float64
        arguments (a kernel that `freeze` disables needs a signature of its own)."""
        n = self._n
        state = self.state.copy()
        zeros = np.zeros(n)
        _clipped_integral(0.0, 0.0, 0.0, 1.0)
        _delta_q_hold(zeros, zeros, True, False, state)
        _delta_q_step(
            False,
            zeros,
            zeros,
            zeros,
            zeros,
            zeros,
            True,
            self._no_fault,
            self._no_terms,
            True,
            zeros,
            True,
            state,
            self._constants,
        )


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

    Outputs (the tick of the inputs held now, direct feedthrough; committed every
    config.period, `hrp2_drake.step.StepSystem`):
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

    The arithmetic is `DeltaQTorqueControllerStep`'s (this system is its shell: ports,
    state groups, events, the fallback's log line, and the check that the tau_* inputs
    are connected all or none).

    Stability of the torque loop (a property of eq. 10-11, not of this code): the
    servo turns Δq into torque within one period, so if τ̂ followed the applied
    torque immediately (an ideal joint-torque sensor, or the simulator's ground
    truth) the loop τ_{k+d} = (1 + K_p) τ_d − K_p τ_k would have its poles at
    |z| = K_p^(1/d): unstable for K_p > 1 whatever the delay d. With τ̂ estimated
    from the motion through Savitzky-Golay filters (Sec. 2, 5.1) the loop gain at
    high frequency is much lower, and K_p = 2 (the paper's) runs stably on the
    simulated HRP-2.
    """

    def __init__(
        self,
        motor_model: MotorModel,
        config: TorqueControllerConfig,
        lead: float = 0.0,
    ):
        """
        Args:
            motor_model: the identified K_τ (rad/(N·m)), K_v (s), K_c (rad) (eq. 6);
                it must have every joint of config.joints, with K_τ > 0.
            config: joints, gains, limits (validated here).
            lead: the samples arrive this long (s) before each multiple of the
                period (`StepSystem`: the commits follow the sampler).
        """
        super().__init__()
        step = DeltaQTorqueControllerStep(motor_model, config)
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
        self._declare_commit(config.period, lead)

        # Per tick: the step's state arrays that it reads or keeps are the only ones
        # loaded from the context; the tau_* inputs land in the rows of one work
        # array.
        views = {name: step.state[rows] for name, rows in step.layout()}
        self._tick_loads = [
            (self.step_group(name), views[name]) for name in step.carried
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
        """Leaves the fallback: torque control resumes in the tick of the sample now
        held (with a zero torque-error integral)."""
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

    def _tick(self, context: Context, t: float) -> None:
        # The hot path of every control period: one Eval per input and the step
        # (scripts/bench.py --only tick).
        q_ref = sensor_fault = disturbance = None
        if self._q_ref.HasValue(context):
            q_ref = self._q_ref.Eval(context)
        if self._sensor_fault.HasValue(context):
            sensor_fault = self._sensor_fault.Eval(context)
        if self._tau_disturbance is not None:
            disturbance = self._tau_disturbance.Eval(context)
        reason = self._step.step(
            t,
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
                t,
                FALLBACK_REASONS[reason],
            )
