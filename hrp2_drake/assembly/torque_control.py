"""The torque control's settings (paper Sec. 4), stated at 1 kHz (`at_period`): what
`build_torque_control` reads with the control period.

`TorqueControlConfig` holds the wiring decisions (which joints, when torque control
starts, whether a supervisor guards it) and one settings class per concern, each with
its own `validate()`: `estimator`, `controller`, `observer`, `supervisor` (a
`SafetyConfig`) and `faults`. A file of the flat layout (before issue 19: `k6: 0.1` at
the top) is refused with one line naming each key's new place (`moved_keys`).

Code that varies settings by name (the motion experiment's improvements, `hrp2-drake
tune`'s search space) names them by path ("controller.k6"):
`hrp2_drake.config.field_at`, `set_field_at`, `replace_fields`, `field_type`.
"""

import dataclasses
import math
from dataclasses import dataclass, field

from hrp2_drake.config import check_finite, moved_keys
from hrp2_drake.control.safety import SafetyConfig
from hrp2_drake.description import RobotDescription
from hrp2_drake.estimation.estimator_config import (
    TorqueEstimatorConfig,
    check_offset,
    estimation_delay,
)
from hrp2_drake.estimation.savitzky_golay import check_evaluation

_WHERE = "TorqueControlConfig"


@dataclass
class EstimatorSettings:
    """The torque estimator of the torque control (paper Sec. 2, `add_estimator`).

    Args:
        window: Savitzky-Golay window of the estimator (paper: 80 samples).
        windows: per-joint (and per-sensor: an F/T sensor's name, or "imu") windows
            instead of `window` (TorqueEstimatorConfig.windows): every window centred
            on the longest one's centre, which sets the estimates' delay; each of
            its parity. Short windows do not work with the paper's K_p = 2: the
            tuned windows (4-16 samples) alone on the paper's K6 = 0.1 controller
            track up to 9x worse than its 80-sample window (the motion experiment's
            "per-signal windows only" row: ankle roll 7x the average and 9x the
            maximum error, hips and ankle pitch 3-4x). A short window smooths τ̂
            less, and the torque loop with K_p = 2 oscillates: Δq at 43 Hz on the
            ankle roll and 200 Hz on the hip yaw, all of its power above 5 Hz
            against a quarter of it with the 80-sample window (3.0-3.5 s of the
            climbing motion). K_p ≤ 1 keeps the short-window loop stable: with K_p
            = 1 the same windows track as well as the paper's controller (3-4 s of
            the climbing motion, maximum errors 15/38/53/31/15 mrad against
            16/40/53/39/17), which is why `hrp2-drake tune` bounds K_p to 1.
        evaluation: where the filters evaluate their fit: "centre" (the paper's, delay
            (N − 1)/2 samples) or "end" (causal, no delay, noisier).
        offset_calibration_time: F/T offset calibration at start-up (s, from 0.2 s;
            0 = none): only when nothing touches the feet and hands then (the robot
            hanging); must end before the torque control's start_time.
        offsets: the F/T sensors' offsets found before the run, by sensor name:
            [torque; force] (N·m, N, sensor frame), what the estimator starts with
            (e.g. `hrp2-drake balance`'s calibration, the robot lifted, then put
            down); a sensor not named: zero.
        imu_offset: the IMU's offsets found before the run, [accelerometer (3,
            m/s²); gyroscope (3, rad/s)] in the IMU frame, subtracted from its
            readings; empty: none.
    """

    window: int = 80
    windows: dict[str, int] = field(default_factory=dict)
    evaluation: str = "centre"
    offset_calibration_time: float = 0.0
    offsets: dict[str, list[float]] = field(default_factory=dict)
    imu_offset: list[float] = field(default_factory=list)

    def validate(self) -> None:
        """Raises ValueError naming the bad field (the windows' names and parities are
        checked against the robot when the estimator is built)."""
        where = f"{_WHERE}.estimator"
        check_window(self.window, f"{where}.window")
        for name, window in self.windows.items():
            check_window(window, f"{where}.windows['{name}']")
        check_evaluation(self.evaluation, f"{where}.evaluation")
        check_finite(
            self.offset_calibration_time, f"{where}.offset_calibration_time", 0.0, False
        )
        check_offset(self.imu_offset, f"{where}.imu_offset", "accelerometer; gyroscope")
        for name, offset in self.offsets.items():
            check_offset(
                offset, f"{where}.offsets['{name}']", "torque; force", optional=False
            )

    def delay(self, period: float) -> float:
        """Seconds between the robot state the estimates of the chain these settings
        build at `period` (s; the robot's sensor period) describe and the sample they
        are computed from: `estimator_config.estimation_delay` of its filters (19.5
        ms for a 40-sample window at 1 kHz)."""
        filters = TorqueEstimatorConfig(
            window=self.window,
            windows=dict(self.windows),
            evaluation=self.evaluation,
            period=period,
        )
        return estimation_delay(filters)


def check_window(window: int, where: str) -> None:
    """Raises ValueError naming `where` (the key in the user's file) unless `window`
    is a Savitzky-Golay window of 3 samples or more (the encoders' parabola), stated
    at 1 kHz (`at_period`): the message gives the samples and the time."""
    if isinstance(window, bool) or not isinstance(window, int):
        raise ValueError(f"{where}: {window!r}, expected a number of samples (integer)")
    if window < 3:
        raise ValueError(
            f"{where}: {window} sample{'' if window == 1 else 's'} "
            f"({window * REFERENCE_PERIOD * 1e3:g} ms at 1 kHz), expected 3 or more "
            "(the encoders' filter fits a parabola)"
        )


@dataclass
class ControllerSettings:
    """The inverse dynamics and the Δq torque controller (paper Sec. 4, eq. 12-13).

    Args:
        k6: position-feedback gain relative to the position servo (Sec. 4.2): 1 = the
            servo's own stiffness, 0.1 = 10% of it. Unused when `stiffness` is
            given.
        stiffness: the joint stiffness the arm holds its reference with against a
            push (N·m/rad), one value or one per torque-controlled joint; empty
            (default): K6's (K6 = K_τ × stiffness, K_τ identified). It is the
            stiffness against a force the torque estimate does not see (a hand on
            an arm without F/T sensors): K_s = stiffness / (1 + K_p), since the
            torque feedback adds K_p K_s e_q (`inverse_dynamics_gains`).
        kp: torque-feedback gain K_p (paper: 2), one value or one per joint.
        ki: torque-feedback integral gain K_i (1/s, eq. 11; the paper's 0), one value
            or one per joint.
        integral_limit: the K_i term's anti-windup, a bound on |∫ e_τ dt| (N·m·s).
        damping_ratio: sets K_d from K_s and the joint inertia (see
            `inverse_dynamics_gains_for_k6`).
        position_source: "encoders" (e_q from the raw encoders, no delay; default) or
            "estimate" (e_q from the filtered q̂, delayed by the window: the paper's).
        feedback_velocity: the q̇ of ė_q in eq. 12: "estimate" (q̂̇, the paper's) or
            "reference" (q̇_d, default: no velocity feedback in τ_d, see below).
        friction_velocity: the q̇ of the friction feedforward K_v q̇ (eq. 10, 13):
            "estimate" (q̂̇, the paper's) or "reference" (q̇_d, default).
        force_frame: frame of the force task ("" = motion control only); its wrench
            is the estimate of the F/T sensor whose body it is (or the
            description's force_sensor).
        kf: force-feedback gain K_f (one value or 6).
        delta_q_limit: saturation of Δq (rad); twice it latches the controller's
            fallback. 0: the robot's own (`delta_q_limit`): where its description
            documents its position loop, the error at which the loop's output
            saturates at its gain (beyond it a larger Δq adds no torque: a Dynamixel
            XL330 at kp 400, 0.87 rad); else 0.1 rad (HRP-2's leg: hundreds of N·m).

    Why the defaults differ from the paper's eq. 13 (measured in the motion
    experiment, its "K6 = 1 with the estimates" table): the servo turns Δq = K_τ τ* +
    K_v q̇_x into τ = τ* + (K_v/K_τ)(q̇_x − q̇). With q̇_x = q̂̇, delayed d = 40 ms by
    the centred window, the last term is about −(K_v/K_τ) d q̈: the friction
    feedforward arrives late and acts as an added inertia (passive: the real part of
    (K_v/K_τ)(e^{−sd} − 1) is never positive) of 5 kg·m² on the knee and 2.3 on the
    hip pitch, so the leg lags its reference (the authors' code, which fed q̂̇ there:
    hip pitch maximum error 53 mrad against 6 with q̇_d, on the calibrated servo). With
    q̇_x = q̇_d the same term is the servo's own damping on the velocity error,
    (K_v/K_τ)(q̇_d − q̇), so K_d of eq. 12 is not needed. e_q from the 40 ms-old q̂ is
    what makes the paper's eq. 12-13 as written unstable: with K6 = 1 it is the servo's
    whole stiffness acting on a 40 ms-old position (it diverges on the `ideal` servo,
    and, unsupervised, oscillates at 76-137 mrad on the calibrated one, bounded only by
    the voltage limit); the raw encoders avoid it, as the authors' code did. Causal
    ("end") filters remove the delay but their derivatives are too noisy for K_p = 2.
    """

    k6: float = 1.0
    stiffness: list[float] = field(default_factory=list)
    kp: list[float] = field(default_factory=lambda: [2.0])
    ki: list[float] = field(default_factory=lambda: [0.0])
    integral_limit: float = math.inf
    damping_ratio: float = 1.0
    position_source: str = "encoders"
    feedback_velocity: str = "reference"
    friction_velocity: str = "reference"
    force_frame: str = ""
    kf: list[float] = field(default_factory=lambda: [0.0])
    delta_q_limit: float = 0.0

    def __post_init__(self):
        """A plain number for `kp` or `kf` (from Python code: YAML gives lists)
        becomes a list of one, when the settings are made, not when validated."""
        if isinstance(self.kp, (int, float)):
            self.kp = [float(self.kp)]
        if isinstance(self.ki, (int, float)):
            self.ki = [float(self.ki)]
        if isinstance(self.kf, (int, float)):
            self.kf = [float(self.kf)]
        if isinstance(self.stiffness, (int, float)):
            self.stiffness = [float(self.stiffness)]

    def validate(self) -> None:
        """Raises ValueError naming the bad field: the signals' sources, and gains that
        are finite and of a sign a controller can use. It changes nothing."""
        where = f"{_WHERE}.controller"
        if self.position_source not in ("encoders", "estimate"):
            raise ValueError(f"{where}.position_source: '{self.position_source}'")
        for name in ("feedback_velocity", "friction_velocity"):
            if getattr(self, name) not in ("estimate", "reference"):
                raise ValueError(f"{where}.{name}: '{getattr(self, name)}'")
        for name in ("kp", "ki", "kf", "stiffness"):
            if not isinstance(getattr(self, name), list):
                raise ValueError(
                    f"{where}.{name}: {getattr(self, name)!r}, expected a list (one "
                    "value, or one per joint / axis)"
                )
        if not self.kp or not all(math.isfinite(k) and k >= 0 for k in self.kp):
            raise ValueError(
                f"{where}.kp: {self.kp}: one value or one per joint, each finite and "
                ">= 0"
            )
        if not self.ki or not all(math.isfinite(k) and k >= 0 for k in self.ki):
            raise ValueError(
                f"{where}.ki: {self.ki}: one value or one per joint, each finite and "
                ">= 0"
            )
        if not self.integral_limit > 0:
            raise ValueError(
                f"{where}.integral_limit: must be > 0 (N·m·s), got "
                f"{self.integral_limit}"
            )
        check_finite(self.k6, f"{where}.k6", 0.0, strict=False)
        if not all(
            isinstance(k, (int, float)) and math.isfinite(k) and k >= 0
            for k in self.stiffness
        ):
            raise ValueError(
                f"{where}.stiffness: {self.stiffness}: one value or one per joint, "
                "each finite and >= 0 (N·m/rad)"
            )
        check_finite(self.damping_ratio, f"{where}.damping_ratio", 0.0, strict=False)
        check_finite(self.delta_q_limit, f"{where}.delta_q_limit", 0.0, strict=False)
        if len(self.kf) not in (1, 6):
            raise ValueError(
                f"{where}.kf: {len(self.kf)} values, expected one or 6 (one per axis "
                "of the wrench)"
            )
        for k, gain in enumerate(self.kf):
            check_finite(gain, f"{where}.kf[{k}]", 0.0, strict=False)


@dataclass
class ObserverSettings:
    """What the torque control adds to the paper's to correct its delayed estimates
    (the paper's future work).

    Args:
        disturbance_observer: bandwidth (rad/s) of a DisturbanceObserver whose d̂, the
            torque the motor model misses, is subtracted from τ*; 0: none (the
            paper's controller).
        predictor: a DelayPredictor carries the estimator's τ̂ (and q̂̇ where the
            controller reads the estimate) from the chain's delay to the present
            with the motor model, the joint inertia at the start pose and the Δq
            already sent. The disturbance observer keeps the delayed, aligned
            estimates. (f̂ of a force task is not predicted.)
            It does not work on HRP-2 with K_p near 1 or above: on the calibrated
            servo the controller falls back to position control within 0.1 s of
            the start of torque control (measured on the climbing motion: 13 ms
            after it with the paper's K6 = 0.1, K_p = 2; 0.19 s with K_p = 1; 0.08 s
            with the tuned controller, K_p 0.13-0.98), so the motion experiment's
            "predictor only" and "all (tuned) + predictor" rows are position
            control's. The reason, measured: it inverts the motor model, so each
            change ΔΔq of the Δq sent within its horizon adds ΔΔq/K_τ to the
            predicted τ̂ at once (K_τ = 0.03-0.24 mrad/(N·m) on the leg: 4-33 N·m
            per mrad of Δq), without the estimator's smoothing; the Δq controller
            answers two ticks later with −K_p ΔΔq, so the loop through the
            predictor oscillates with a 4 ms period
            and grows by √K_p per tick for K_p > 1 (the hip pitch's Δq reached ±98 mrad
            within 12 ms) until |τ̂| passes tau_limit (500 N·m, fallback reason
            "|tau_estimated| exceeds tau_limit"). The servo does not produce those
            torques (the estimator's τ̂ stays smooth), and it is not the cause: the
            `ideal` servo, without latency or voltage limit, falls back after the
            same 11-13 ms. With K_p = 0.5 the 0.6 s measured ran without a fallback.
    """

    disturbance_observer: float = 0.0
    predictor: bool = False

    def validate(self) -> None:
        """Raises ValueError unless the observer's bandwidth is finite and >= 0."""
        if not (
            math.isfinite(self.disturbance_observer) and self.disturbance_observer >= 0
        ):
            raise ValueError(
                f"{_WHERE}.observer.disturbance_observer: {self.disturbance_observer} "
                "must be a bandwidth >= 0 (rad/s; 0 = none)"
            )


@dataclass
class FaultSettings:
    """Faults of the controllers' own model of the robot (the fault campaign).

    Args:
        model_error: the estimator's and inverse dynamics' model of the robot has
            every link's mass and COM off by a random factor within ±model_error
            (a fault: `RobotDescription.add_model`); 0: the exact model.
        model_error_seed: the seed of those factors.
    """

    model_error: float = 0.0
    model_error_seed: int = 0

    def validate(self) -> None:
        """Raises ValueError unless model_error is in [0, 1)."""
        if not 0 <= self.model_error < 1:
            raise ValueError(
                f"{_WHERE}.faults.model_error: {self.model_error} must be in [0, 1)"
            )


@moved_keys(
    k6="controller.k6",
    kp="controller.kp",
    damping_ratio="controller.damping_ratio",
    position_source="controller.position_source",
    feedback_velocity="controller.feedback_velocity",
    friction_velocity="controller.friction_velocity",
    force_frame="controller.force_frame",
    kf="controller.kf",
    delta_q_limit="controller.delta_q_limit",
    window="estimator.window",
    windows="estimator.windows",
    evaluation="estimator.evaluation",
    offset_calibration_time="estimator.offset_calibration_time",
    disturbance_observer="observer.disturbance_observer",
    predictor="observer.predictor",
    safety="supervisor",
    model_error="faults.model_error",
    model_error_seed="faults.model_error_seed",
)
@dataclass
class TorqueControlConfig:
    """The paper's torque control of a set of joints (e.g. HRP-2's right leg), Sec. 4.

    Args:
        joints: the torque-controlled joints; every other joint stays in position
            control on its reference. Empty: the robot description's
            controlled_joints.
        start_time: position control until then (the filters fill), s.
        supervised: a SafetySupervisor between the controllers and the robot
            (default): faults hand the robot back to its servo with a ramp, torque
            control starts with a ramp and resumes once faults have cleared; the Δq
            controller's own fallback then does not latch. False: the controller's
            latched fallback alone.
        estimator: the torque estimator (its windows, the F/T offset calibration).
        controller: the inverse dynamics' and the Δq controller's gains and signals.
        observer: the disturbance observer and the delay predictor (default: none).
        supervisor: the supervisor's settings (its start_time is start_time).
        faults: errors of the controllers' model of the robot (default: none).
    """

    joints: list[str] = field(default_factory=list)
    start_time: float = 0.5
    supervised: bool = True
    estimator: EstimatorSettings = field(default_factory=EstimatorSettings)
    controller: ControllerSettings = field(default_factory=ControllerSettings)
    observer: ObserverSettings = field(default_factory=ObserverSettings)
    supervisor: SafetyConfig = field(default_factory=SafetyConfig)
    faults: FaultSettings = field(default_factory=FaultSettings)

    def controlled_joints(self, robot: RobotDescription) -> list[str]:
        """`joints`, or the robot's controlled joints if empty."""
        return list(self.joints or robot.controlled_joints)

    def validate(self) -> None:
        """Raises ValueError naming the bad field: each part's own checks, then those
        across parts (the offset calibration ends before start_time)."""
        self.supervisor.validate()
        self.faults.validate()
        self.estimator.validate()
        self.controller.validate()
        self.observer.validate()
        check_finite(self.start_time, f"{_WHERE}.start_time", 0.0, False)
        calibration = self.estimator.offset_calibration_time
        if calibration > 0 and 0.2 + calibration > self.start_time:
            raise ValueError(
                f"{_WHERE}.estimator.offset_calibration_time: the calibration "
                f"(0.2 s + {calibration} s) must end before start_time = "
                f"{self.start_time} s"
            )


def check_for_robot(
    config: TorqueControlConfig, robot: RobotDescription, where: str
) -> None:
    """Raises ValueError naming `where`.<field> (the path of `config` in the user's
    file, e.g. "ControlConfig.torque_control") unless `config` fits `robot`: its
    joints are the robot's, each once; `controller.kp` has one value or one per
    torque-controlled joint; the estimator's per-signal windows name a joint, an F/T
    sensor or "imu" of the robot; `controller.force_frame` is a frame of its model."""
    unknown = [name for name in config.joints if name not in robot.joints]
    if unknown:
        raise ValueError(
            f"{where}.joints: {unknown} not joints of robot '{robot.name}' (e.g. "
            f"{robot.joints[:3]})"
        )
    repeated = sorted({name for name in config.joints if config.joints.count(name) > 1})
    if repeated:
        raise ValueError(f"{where}.joints: {repeated} given more than once")
    n = len(config.controlled_joints(robot))
    for name in ("kp", "stiffness"):
        gains = getattr(config.controller, name)
        if isinstance(gains, list) and len(gains) not in (
            (0, 1, n) if name == "stiffness" else (1, n)
        ):
            raise ValueError(
                f"{where}.controller.{name}: {len(gains)} values, expected one or {n} "
                "(one per torque-controlled joint)"
            )
    signals = [*robot.joints, *robot.force_torque_sensors]
    signals += ["imu"] if robot.has_imu() else []
    unknown = [
        name for name in config.estimator.offsets if name not in robot.sensor_names()
    ]
    if unknown:
        raise ValueError(
            f"{where}.estimator.offsets: {unknown} not F/T sensors of robot "
            f"'{robot.name}' ({robot.sensor_names()})"
        )
    unknown = [name for name in config.estimator.windows if name not in signals]
    if unknown:
        raise ValueError(
            f"{where}.estimator.windows: {unknown} not a joint, an F/T sensor or 'imu' "
            f"of robot '{robot.name}' (e.g. {signals[:2] + signals[-2:]})"
        )
    frame = config.controller.force_frame
    if frame and not robot.make_plant().HasFrameNamed(frame):
        raise ValueError(
            f"{where}.controller.force_frame: no frame '{frame}' in robot "
            f"'{robot.name}''s model"
        )


#: Δq's saturation where a robot documents none (rad): `delta_q_limit`.
DEFAULT_DELTA_Q_LIMIT = 0.1


def delta_q_limit(robot: RobotDescription, config: TorqueControlConfig) -> float:
    """The saturation of Δq (rad) of `config` on `robot`: its controller's
    delta_q_limit, or for 0 the error at which the robot's documented position loop
    saturates at its gain (`PositionLoopDescription.saturation_error`), else
    `DEFAULT_DELTA_Q_LIMIT`."""
    if config.controller.delta_q_limit > 0:
        return config.controller.delta_q_limit
    saturation = robot.position_loop.saturation_error(None)
    return saturation if math.isfinite(saturation) else DEFAULT_DELTA_Q_LIMIT


#: The rate every setting of this module is stated at: 1 kHz, HRP-2's (s).
REFERENCE_PERIOD = 0.001


def at_period(config: TorqueControlConfig, period: float) -> TorqueControlConfig:
    """`config`, stated for the reference period (1 ms: `REFERENCE_PERIOD`), for a
    robot sampled every `period` s (a robot on a servo bus runs at the bus's rate):
    the same spans of time. The estimator's windows keep their length in seconds
    (rounded to whole samples, at least 5; per-signal windows of the longest one's
    parity); the supervisor's stale_time scales with the period; counts of periods
    (stale_samples, encoder_stale_samples) and times in seconds stay. At 1 ms,
    `config` itself."""
    if math.isclose(period, REFERENCE_PERIOD, rel_tol=1e-9):
        return config
    scale = period / REFERENCE_PERIOD

    def samples(window: int) -> int:
        return max(5, round(window / scale))

    window = samples(config.estimator.window)
    windows = {name: samples(w) for name, w in config.estimator.windows.items()}
    longest = max([window, *windows.values()])
    # Every window centred on the longest one's centre: each of its parity.
    windows = {name: w + (w - longest) % 2 for name, w in windows.items()}
    window += (window - longest) % 2
    estimator = dataclasses.replace(config.estimator, window=window, windows=windows)
    supervisor = dataclasses.replace(
        config.supervisor, stale_time=config.supervisor.stale_time * scale
    )
    return dataclasses.replace(config, estimator=estimator, supervisor=supervisor)
