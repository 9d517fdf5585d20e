"""Force-tracking experiment (paper Sec. 5.4, Figure 5).

HRP-2 stands on both feet, the right foot on a rigid block (the paper's Fig. 2a, our
"standing_on_block" scenario). The six right-leg joints are torque controlled with
the inverse dynamics of eq. 12 and a force task on the right foot; every other joint
stays in position control. The reference joint angles are the standing pose, the
position gains are 10% of the servo's (K6 = 0.1), the force gain is K_f = 1 and the
force reference is a sinusoid on the vertical force of the right foot.

.. code-block:: text

    t = 0 ─── settle ─────────┬── hold ──┬── periods / frequency ───────────►
      position control        │ torque   │ torque control,
      (estimator's window     │ control, │ f_ref,z = f0,z + A sin(2π f (t − t1))
      fills; f0 = the mean of │ f_ref =  │ (other axes: held at f0, or zero)
      f̂ over its last         │ f0       │
      static_average s)       │          │

Wrench conventions (as InverseDynamicsController's force task): f = [torque; force]
(N·m, N) that the environment exerts on the right foot, about the origin of the F/T
sensor frame "RLEG_FOOT", expressed in it; standing flat, f_z is the vertical load of
the right foot (about half the robot's weight, 260 N here). The controller's f̂ is the
estimator's external_wrench_right_foot (the F/T reading compensated for the foot's
weight and inertia, delayed by the Savitzky-Golay window, 39.5 ms for N = 80).

What "zero on the other axes" means here. The paper keeps "the force on the other
axes to zero". A foot standing on a block carries a static wrench on every axis
(here about 10 N laterally and 1-3 N·m of moments, set by the stance), so a literal
zero would ask the robot to change its stance. The default (`other_axes = "hold"`)
reads it as a zero *change*: every axis but f_z keeps its static value f0 and the
coupling is measured as the deviation from it; `other_axes = "zero"` ramps those
axes to zero during the hold phase (the literal reading, an ablation).

Evaluation (each against the reference in its own terms, f0 of the same signal):
  - "estimate": f̂, what the controller feeds back (the paper's Fig. 5 can only show
    an estimate: HRP-2 has no other force measurement);
  - "F/T reading": the raw sensor wrench (1 ms, noise 0.5 N, bias), smoothed by a
    zero-phase moving average of `smoothing` s: the force the foot really applies,
    up to the sensor's constant bias and the foot's weight, which cancel in the
    deviation from the static value.
Metrics on f_z over the sinusoid: overshoot at the apexes, (|peak − f0| − A) / A
(max over apexes; negative = the apexes are not reached), the amplitude ratio and
phase of a least-squares sinusoid at the reference frequency, the delay by
cross-correlation (positive: the measurement lags), the RMS error; on f_x the
coupling max |f_x − f0,x| / A (paper: about 10%).

The two-pass structure: a first simulation of the settle phase alone measures f0 (the
run is deterministic, the sensors' noise a pure function of the seed, so the second
simulation repeats it sample for sample), a second one runs the whole experiment with
the reference built on f0. On the robot one would latch f̂ when torque control
starts; the result is the same.
"""

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from pydrake.trajectories import PiecewisePolynomial

from hrp2_drake.assembly.builders import (
    JointReference,
    build_torque_control,
    simulated_station,
)
from hrp2_drake.assembly.torque_control import ControllerSettings, TorqueControlConfig
from hrp2_drake.config import field_at, replace_fields
from hrp2_drake.control.torque_chain import COMPONENTS
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.paper import hrp2
from hrp2_drake.paper.claims import PAPER_COUPLING_X, PAPER_OVERSHOOT, force_verdict
from hrp2_drake.paper.motion import (
    IMPROVED_FILE,
    IMPROVEMENTS,
    improvement_alone,
    load_improved,
    run_controller,
)
from hrp2_drake.report import legend_beside, markdown_table, pyplot, save_figure
from hrp2_drake.robot.station import StationConfig, initial_joint_positions

#: The axes of a wrench, in the order of the wrench vectors.
WRENCH_AXES = ("tau_x", "tau_y", "tau_z", "f_x", "f_y", "f_z")
FZ, FX = 5, 3
#: The force task's frame: the right foot's F/T sensor frame.
FORCE_FRAME = hrp2.FT_SENSOR_BODIES["right_foot"]
SIGNALS = {"estimate": "external_wrench_right_foot", "ft_reading": "wrench_right_foot"}


def _default_torque_control() -> TorqueControlConfig:
    return TorqueControlConfig(
        controller=ControllerSettings(k6=0.1, kf=[1.0], force_frame=FORCE_FRAME)
    )


@dataclass
class ForceConfig:
    """Configuration of the force-tracking experiment (paper Sec. 5.4).

    Args:
        station: the robot (the paper's: standing, right foot on a block).
        torque_control: the right leg's torque control (paper: K6 = 0.1, K_p = 2,
            K_f = 1, window 80); force_frame must be the right foot's sensor frame
            "RLEG_FOOT". Its start_time is replaced by `settle`.
        settle: position control before torque control starts (s): the estimator's
            window fills and the robot settles on its feet.
        static_average: f0 is the mean of f̂ over the last static_average s of the
            settle phase (s).
        hold: torque control with f_ref = f0 before the sinusoid starts (s).
        amplitude: A, the amplitude of the sinusoid on f_z (N); 50 N, about 20% of the
            static load (our choice: Fig. 5's numbers are not in the text we have).
        frequency: the sinusoid's frequency (Hz); 0.5 Hz, a slow oscillation (the
            paper does not give its frequency either).
        periods: the number of periods of the sinusoid.
        other_axes: "hold" (every axis but f_z keeps its static value) or "zero"
            (they ramp to zero during `hold`, the paper's words taken literally);
            see the module docstring.
        compatible_reference: make the right leg's reference joint angles follow the
            posture the force implies (the paper's setting: "the reference joint
            angles were set to be compatible with the force task"): q_ref = q0 +
            G (f_ref,z − f0,z), with G (rad/N) the regression of the joint angles on
            f_ref,z in a first run with a fixed reference (one more simulation).
            False: the standing pose throughout.
        smoothing: window of the zero-phase moving average applied to the F/T
            reading before its peaks are measured (s).
        max_lag: the largest delay the cross-correlation looks for (s).
        ablations: the variants `run_force_all` runs besides the paper's settings,
            for the report, among `ABLATIONS` (each one more simulation).
    """

    station: StationConfig = field(
        default_factory=lambda: StationConfig(scenario="standing_on_block")
    )
    torque_control: TorqueControlConfig = field(default_factory=_default_torque_control)
    settle: float = 1.0
    static_average: float = 0.3
    hold: float = 0.5
    amplitude: float = 50.0
    frequency: float = 0.5
    periods: float = 3.0
    other_axes: str = "hold"
    compatible_reference: bool = True
    smoothing: float = 0.02
    max_lag: float = 0.2
    ablations: list[str] = field(default_factory=lambda: list(ABLATIONS))

    def validate(self) -> None:
        """Raises ValueError naming the bad field (yaml_load_typed does not call it)."""
        where = "ForceConfig"
        self.station.validate()
        self.torque_control.validate()
        if self.station.scenario not in ("standing_on_block", "standing"):
            raise ValueError(
                f"{where}.station.scenario='{self.station.scenario}': the force task "
                "needs the right foot in contact ('standing_on_block' or 'standing')"
            )
        if self.torque_control.controller.force_frame != FORCE_FRAME:
            raise ValueError(
                f"{where}.torque_control.controller.force_frame="
                f"'{self.torque_control.controller.force_frame}': the force task is on "
                f"the right foot's sensor frame '{FORCE_FRAME}'"
            )
        for name in ("settle", "static_average", "amplitude", "frequency", "periods"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{where}.{name}={value} must be > 0")
        if self.static_average > self.settle:
            raise ValueError(
                f"{where}.static_average={self.static_average} exceeds settle="
                f"{self.settle} (s)"
            )
        if self.settle < 0.2:
            raise ValueError(
                f"{where}.settle={self.settle} s: the estimator needs about 0.1 s to "
                "fill its window before f0 can be measured"
            )
        for name in ("hold", "smoothing", "max_lag"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{where}.{name}={value} must be >= 0")
        if self.other_axes not in ("hold", "zero"):
            raise ValueError(
                f"{where}.other_axes='{self.other_axes}': 'hold' or 'zero'"
            )
        unknown = [a for a in self.ablations if a not in ABLATIONS]
        if unknown:
            raise ValueError(
                f"{where}.ablations: unknown {unknown}, expected among "
                f"{list(ABLATIONS)}"
            )

    @property
    def sinusoid_start(self) -> float:
        """t1, the time the sinusoid starts (s)."""
        return self.settle + self.hold

    @property
    def duration(self) -> float:
        """The whole experiment (s)."""
        return self.sinusoid_start + self.periods / self.frequency


#: The variants of the report: name -> (label, change of the config).
def _improved(config: ForceConfig, improvement: str = "") -> ForceConfig:
    """The force task with the improvements of the tuned K6 = 0.1 motion controller
    (`motion.IMPROVED_FILE`): all of them, or one alone (`motion.improvement_alone`);
    the force task's own settings (K_f, force frame) kept."""
    tuned = load_improved(IMPROVED_FILE, config.torque_control)
    if improvement:
        torque = improvement_alone(improvement, config.torque_control, tuned)
    else:
        fields = [f for name in IMPROVEMENTS for f in IMPROVEMENTS[name]]
        changes = {f: field_at(tuned, f) for f in fields}
        torque = replace_fields(config.torque_control, changes)
    return replace(config, torque_control=torque)


def _torque_changed(config: ForceConfig, changes: dict) -> ForceConfig:
    """`config` with `changes` to its torque control (values by field path,
    `torque_control.replace_fields`)."""
    return replace(
        config, torque_control=replace_fields(config.torque_control, changes)
    )


ABLATIONS: dict[str, tuple[str, Callable[[ForceConfig], ForceConfig]]] = {
    "k6_0": (
        "K6 = 0 (no position feedback)",
        lambda c: _torque_changed(c, {"controller.k6": 0.0}),
    ),
    "kf_2": (
        "K_f = 2",
        lambda c: _torque_changed(c, {"controller.kf": [2.0]}),
    ),
    "fixed_reference": (
        "reference posture fixed (the standing pose)",
        lambda c: replace(c, compatible_reference=False),
    ),
    "other_axes_zero": (
        "other axes' reference zero (literal)",
        lambda c: replace(c, other_axes="zero"),
    ),
    "paper_literal": (
        "paper-literal eq. 12-13 (q̂, q̂̇ estimates everywhere)",
        lambda c: _torque_changed(
            c,
            {
                "controller.position_source": "estimate",
                "controller.feedback_velocity": "estimate",
                "controller.friction_velocity": "estimate",
            },
        ),
    ),
    "window_40": (
        "estimator window 40 (20 ms delay)",
        lambda c: _torque_changed(c, {"estimator.window": 40}),
    ),
    # Beyond the paper: the motion-tuned K6 = 0.1 controller on a task it was not
    # tuned on (the over-fitting check), and its disturbance observer alone.
    "improved": (
        "improved (the motion-tuned K6 = 0.1 controller: observer, windows, gains)",
        _improved,
    ),
    "improved_observer_only": (
        "disturbance observer alone (the tuned bandwidth × delay)",
        lambda c: _improved(c, "disturbance observer"),
    ),
    # What the calibrated servo's static non-linearities cost (the plant changes: f0
    # and the posture gain are measured again).
    "servo_no_hysteresis": (
        "servo without direction hysteresis (Coulomb friction switching at sign(q̇))",
        lambda c: replace(
            c,
            station=replace(c.station, servo_off=[*c.station.servo_off, "hysteresis"]),
        ),
    ),
    "servo_no_deadzone": (
        "servo without dead zone",
        lambda c: replace(
            c, station=replace(c.station, servo_off=[*c.station.servo_off, "deadzone"])
        ),
    ),
}


# ----------------------------------------------------------------- references


def force_reference(
    config: ForceConfig, static_wrench: np.ndarray, dt: float = 0.001
) -> PiecewisePolynomial:
    """The 6-row force reference f_ref(t) (N·m, N; sensor frame, as f̂) for `config`
    around the static wrench f0: f0 until the sinusoid starts (and during the settle
    phase, where it is unused), then f0,z + A sin(2π f (t − t1)) on f_z; the other
    axes held at f0, or ramped to zero during the hold phase (other_axes = "zero")."""
    static_wrench = np.asarray(static_wrench, float).reshape(6)
    t = np.arange(0.0, config.duration + 0.5 + dt / 2, dt)
    values = np.tile(static_wrench[:, None], (1, len(t)))
    t1 = config.sinusoid_start
    phase = np.clip(t - t1, 0.0, None)
    values[FZ] += np.where(
        t >= t1, config.amplitude * np.sin(2 * np.pi * config.frequency * phase), 0.0
    )
    if config.other_axes == "zero":
        ramp = np.clip((t - config.settle) / max(config.hold, dt), 0.0, 1.0)
        others = [k for k in range(6) if k != FZ]
        values[others] *= 1.0 - ramp
    return PiecewisePolynomial.FirstOrderHold(t, values)


def joint_reference(
    config: ForceConfig,
    static_wrench: np.ndarray,
    posture_gain: np.ndarray | None = None,
    dt: float = 0.001,
) -> JointReference:
    """The joint reference: the standing pose held, or with `posture_gain` G (30,
    rad/N) the pose q0 + G (f_ref,z(t) − f0,z) with its velocity and acceleration (the
    reference "compatible with the force task")."""
    q0 = initial_joint_positions(config.station)
    duration = config.duration + 0.5
    if posture_gain is None:
        return JointReference.hold(q0, duration)
    t = np.arange(0.0, duration + dt / 2, dt)
    w = 2 * np.pi * config.frequency
    phase = np.clip(t - config.sinusoid_start, 0.0, None)
    on = t >= config.sinusoid_start
    a = config.amplitude
    dfz = np.where(on, a * np.sin(w * phase), 0.0)
    dfz_dot = np.where(on, a * w * np.cos(w * phase), 0.0)
    dfz_ddot = np.where(on, -a * w * w * np.sin(w * phase), 0.0)
    g = np.asarray(posture_gain, float).reshape(1, -1)
    return JointReference.from_samples(
        t, q0 + dfz[:, None] * g, dfz_dot[:, None] * g, dfz_ddot[:, None] * g
    )


# ----------------------------------------------------------------- metrics


def moving_average(x: np.ndarray, samples: int) -> np.ndarray:
    """Zero-phase (centred) moving average of `samples` samples along axis 0; the
    edges average over the part of the window inside the signal."""
    if samples <= 1:
        return np.asarray(x, float).copy()
    x = np.asarray(x, float)
    kernel = np.ones(samples)
    half = samples // 2
    shape = (len(x),) + x.shape[1:]
    flat = x.reshape(len(x), -1)
    out = np.empty_like(flat)
    count = np.convolve(np.ones(len(x)), kernel, "full")[half : half + len(x)]
    for k in range(flat.shape[1]):
        out[:, k] = (
            np.convolve(flat[:, k], kernel, "full")[half : half + len(x)] / count
        )
    return out.reshape(shape)


def sinusoid_fit(t: np.ndarray, y: np.ndarray, frequency: float, t1: float):
    """Least-squares y ≈ c + a sin(ω (t − t1) − φ): returns (a, φ / ω, c), the
    amplitude, the delay (s, positive: y lags a sine starting at t1) and the mean."""
    w = 2 * np.pi * frequency
    basis = np.column_stack(
        [np.sin(w * (t - t1)), np.cos(w * (t - t1)), np.ones(len(t))]
    )
    s, c, mean = np.linalg.lstsq(basis, y, rcond=None)[0]
    # a sin(x − φ) = a cos φ sin x − a sin φ cos x.
    return float(np.hypot(s, c)), float(math.atan2(-c, s) / w), float(mean)


def cross_correlation_lag(
    reference: np.ndarray,
    measured: np.ndarray,
    window: np.ndarray,
    dt: float,
    max_lag: float,
) -> float:
    """The lag (s) that maximizes the correlation coefficient between the measured
    samples in `window` and the reference shifted by that lag, refined by a parabola
    through the peak; positive: `measured` lags.

    The measured samples stay the same for every lag (the reference is known outside
    the window), so the estimate has none of the edge bias of a correlation of two
    finite windows, which matters for a slow sinusoid whose correlation is flat near
    its peak.

    Args:
        reference, measured: (samples,) on the same uniform time grid.
        window: boolean mask of the samples compared; the lags are limited so that
            the shifted reference stays inside the signal.
    """
    k_max = max(1, int(round(max_lag / dt)))
    index = np.flatnonzero(window)
    first, last = index[0], index[-1]
    k_max = min(k_max, first, len(reference) - 1 - last)
    if k_max < 1:
        raise ValueError("cross_correlation_lag: no room to shift the reference")
    lags = np.arange(-k_max, k_max + 1)
    m = measured[index] - measured[index].mean()
    c = np.empty(len(lags))
    for i, k in enumerate(lags):
        r = reference[index - k]
        r = r - r.mean()
        c[i] = np.dot(r, m) / max(np.linalg.norm(r) * np.linalg.norm(m), 1e-300)
    i = int(np.argmax(c))
    shift = 0.0
    if 0 < i < len(c) - 1:
        denominator = c[i - 1] - 2 * c[i] + c[i + 1]
        if denominator < 0:
            shift = 0.5 * (c[i - 1] - c[i + 1]) / denominator
    return float((lags[i] + shift) * dt)


def tracking_metrics(
    t: np.ndarray,
    reference: np.ndarray,
    measured: np.ndarray,
    static_measured: np.ndarray,
    config: ForceConfig,
) -> dict:
    """The metrics of one measured wrench signal against the reference.

    Args:
        t: log times (s), uniform.
        reference: f_ref at t (samples, 6), built on the controller's f0.
        measured: the wrench signal (samples, 6), already smoothed if noisy.
        static_measured: f0 of this signal (6): the reference is shifted by
            static_measured − f0 so that each signal is compared in its own terms.
        config: the experiment (amplitude, frequency, windows).

    Returns:
        dict: overshoot (max over apexes of (|peak − f0,z| − A) / A),
        overshoot_per_apex, amplitude_ratio, phase_delay_ms (sinusoid fit), lag_ms
        (cross-correlation), rms_error (N) and rms_error_ratio (/ A) on f_z;
        coupling_x (max |f_x − f0,x| / A), coupling_x_fit (fitted amplitude of f_x at
        the frequency / A) and the same for every axis in coupling_fit.
    """
    dt = float(t[1] - t[0])
    t1, a, f = config.sinusoid_start, config.amplitude, config.frequency
    window = (t >= t1) & (t <= config.duration + 1e-9)
    base = reference[np.argmax(t >= t1)]  # f_ref at t1: the static level per axis
    shift = static_measured - reference[np.argmax(t >= config.settle - 1e-9)]
    ref = reference + shift  # the reference in the signal's terms
    deviation = measured - (base + shift)
    apexes = t1 + (np.arange(int(round(2 * config.periods))) + 0.5) / (2 * f)
    per_apex = []
    for k, apex in enumerate(apexes):
        near = (t >= apex - 0.25 / f) & (t <= apex + 0.25 / f) & window
        if not near.any():
            continue
        sign = 1.0 if k % 2 == 0 else -1.0
        peak = np.max(sign * deviation[near, FZ])
        per_apex.append(float((peak - a) / a))
    amplitude, delay, _ = sinusoid_fit(t[window], measured[window, FZ], f, t1)
    inner = window & (t >= t1 + config.max_lag) & (t <= t[-1] - config.max_lag)
    lag = cross_correlation_lag(ref[:, FZ], measured[:, FZ], inner, dt, config.max_lag)
    error = measured[window, FZ] - ref[window, FZ]
    coupling_fit = {}
    for k, axis in enumerate(WRENCH_AXES):
        if k != FZ:
            coupling_fit[axis] = (
                sinusoid_fit(t[window], measured[window, k], f, t1)[0] / a
            )
    return {
        "overshoot": max(per_apex),
        "overshoot_per_apex": per_apex,
        "amplitude_ratio": amplitude / a,
        "phase_delay_ms": delay * 1e3,
        "lag_ms": lag * 1e3,
        "rms_error": float(np.sqrt(np.mean(error**2))),
        "rms_error_ratio": float(np.sqrt(np.mean(error**2)) / a),
        "coupling_x": float(np.abs(deviation[window, FX]).max() / a),
        "coupling_x_fit": coupling_fit["f_x"],
        "coupling_fit": coupling_fit,
    }


# ----------------------------------------------------------------- runs


@dataclass
class ForceRun:
    """One simulation of the experiment.

    Attributes:
        label: what was run.
        config: its configuration.
        signals: the logged ports ({"t", port: (samples, size)}), plus "f_ref".
        static_wrench: f0, the controller's f̂ at rest (6; N·m, N).
        static_reading: the F/T reading at rest, same window (6).
        metrics: tracking_metrics by signal ("estimate", "ft_reading").
        fallback_time: when the torque controller fell back to position control (s),
            or None.
        posture_gain: G (30, rad/N) of a compatible reference, or None.
        name: its key in ABLATIONS ("" for the paper's settings): what readers match
            on, never the label.
    """

    label: str
    config: ForceConfig
    signals: dict[str, np.ndarray]
    static_wrench: np.ndarray
    static_reading: np.ndarray
    metrics: dict[str, dict]
    fallback_time: float | None
    posture_gain: np.ndarray | None = None
    name: str = ""


@dataclass
class ForceResult:
    """The experiment: the paper's settings (`baseline`) and the ablations."""

    baseline: ForceRun
    variants: list[ForceRun]


def _torque_config(config: ForceConfig) -> TorqueControlConfig:
    return replace(config.torque_control, start_time=config.settle)


def measure_static_wrench(
    config: ForceConfig, motor_model: MotorModel
) -> tuple[np.ndarray, np.ndarray]:
    """f0: the settle phase alone (position control), then the means of f̂ and of the
    F/T reading over its last `static_average` s. Returns (f̂ mean, reading mean)."""
    placeholder = force_reference(config, np.zeros(6))
    robot, station, period = simulated_station(config.station)
    control = build_torque_control(
        robot,
        station,
        joint_reference(config, np.zeros(6)),
        motor_model,
        _torque_config(config),
        control_period=period,
        force_reference=placeholder,
    )
    logged = run_controller(control, config.settle, "force: settle")
    at_rest = logged["t"] >= config.settle - config.static_average - 1e-9
    return (
        logged[SIGNALS["estimate"]][at_rest].mean(axis=0),
        logged[SIGNALS["ft_reading"]][at_rest].mean(axis=0),
    )


def posture_gain(run: ForceRun) -> np.ndarray:
    """G (30, rad/N): the slope of a regression of each joint angle (encoders) on
    f_ref,z − f0,z over the sinusoid of `run` (zero outside the right leg). Samples
    with a non-finite encoder reading (a sensor fault) are left out."""
    s, c = run.signals, run.config
    on = (s["t"] >= c.sinusoid_start) & np.all(np.isfinite(s["q_measured"]), axis=1)
    x = s["f_ref"][on, FZ] - run.static_wrench[FZ]
    gain = np.zeros(hrp2.NUM_JOINTS)
    basis = np.column_stack([x, np.ones(len(x))])
    for j, name in enumerate(hrp2.JOINT_NAMES):
        if name in c.torque_control.controlled_joints(hrp2.description()):
            gain[j] = np.linalg.lstsq(basis, s["q_measured"][on, j], rcond=None)[0][0]
    return gain


def run_force(
    config: ForceConfig,
    motor_model: MotorModel,
    label: str = "K6 = 0.1, K_f = 1",
    static: tuple[np.ndarray, np.ndarray] | None = None,
    gain: np.ndarray | None = None,
    meshcat=None,
) -> ForceRun:
    """Runs the experiment once (after the settle-phase measurement of f0, unless
    `static` gives it). With config.compatible_reference and no `gain`, a first run
    with the held reference measures the posture gain G."""
    config.validate()
    if static is None:
        static = measure_static_wrench(config, motor_model)
    f0, reading0 = static
    if config.compatible_reference and gain is None:
        fixed = run_force(
            replace(config, compatible_reference=False), motor_model, label, static
        )
        gain = posture_gain(fixed)
    f_ref = force_reference(config, f0)
    reference = joint_reference(
        config, f0, gain if config.compatible_reference else None
    )
    robot, station, period = simulated_station(config.station, meshcat)
    control = build_torque_control(
        robot,
        station,
        reference,
        motor_model,
        _torque_config(config),
        control_period=period,
        force_reference=f_ref,
    )
    signals = run_controller(control, config.duration, f"force: {label}")
    t = signals["t"]
    signals["f_ref"] = np.array([f_ref.value(x).ravel() for x in t])
    smoothing = max(1, int(round(config.smoothing / (t[1] - t[0]))))
    measured = {
        "estimate": signals[SIGNALS["estimate"]],
        "ft_reading": moving_average(signals[SIGNALS["ft_reading"]], smoothing),
    }
    statics = {"estimate": f0, "ft_reading": reading0}
    metrics = {
        name: tracking_metrics(
            t, signals["f_ref"], measured[name], statics[name], config
        )
        for name in measured
    }
    fallback = None
    if signals["fallback_active"].max() > 0:
        fallback = float(t[np.argmax(signals["fallback_active"][:, 0] > 0)])
    return ForceRun(label, config, signals, f0, reading0, metrics, fallback, gain)


def run_force_all(config: ForceConfig, motor_model: MotorModel) -> ForceResult:
    """The paper's settings, then every ablation of config.ablations (sharing f0
    when the settle phase is the same)."""
    config.validate()
    static = measure_static_wrench(config, motor_model)
    baseline = run_force(config, motor_model, static=static)
    variants = []
    for name in config.ablations:
        label, change = ABLATIONS[name]
        variant = change(config)
        same_plant = variant.station == config.station
        gain = (
            baseline.posture_gain
            if variant.compatible_reference and same_plant
            else None
        )
        shared = static if same_plant else None
        run = run_force(variant, motor_model, label, shared, gain)
        run.name = name
        variants.append(run)
    return ForceResult(baseline, variants)


# ----------------------------------------------------------------- report


def summarize(result: ForceResult) -> dict:
    """The JSON summary of the experiment."""

    def run_summary(run: ForceRun) -> dict:
        c = run.config
        return {
            "label": run.label,
            "name": run.name,
            "k6": c.torque_control.controller.k6,
            "kf": list(c.torque_control.controller.kf),
            "kp": list(c.torque_control.controller.kp),
            "window": c.torque_control.estimator.window,
            "other_axes": c.other_axes,
            "compatible_reference": c.compatible_reference,
            "static_wrench": run.static_wrench.tolist(),
            "static_reading": run.static_reading.tolist(),
            "metrics": run.metrics,
            "fallback_time": run.fallback_time,
            "joint_motion_peak_to_peak": dict(
                zip(
                    c.torque_control.controlled_joints(hrp2.description()),
                    joint_motion(run).tolist(),
                )
            ),
            "verdict": {
                name: force_verdict(run.metrics[name], c.frequency)
                for name in run.metrics
            },
        }

    c = result.baseline.config
    return {
        "experiment": {
            "scenario": c.station.scenario,
            "block_height": c.station.block_height,
            "amplitude_N": c.amplitude,
            "frequency_Hz": c.frequency,
            "periods": c.periods,
            "settle_s": c.settle,
            "hold_s": c.hold,
            "other_axes": c.other_axes,
        },
        "paper": {"overshoot": PAPER_OVERSHOOT, "coupling_x": PAPER_COUPLING_X},
        "baseline": run_summary(result.baseline),
        "variants": [run_summary(v) for v in result.variants],
    }


def write_force_report(result: ForceResult, out: Path) -> dict:
    """force.md, force.json, figure5_force_tracking.png and force_signals.npz (the
    baseline's logged signals, for the components analysis) in `out`."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    summary = summarize(result)
    (out / "force.json").write_text(json.dumps(summary, indent=2))
    save_signals(result.baseline, out / "force_signals.npz")
    figure = plot_figure5(result, out)
    (out / "force.md").write_text(_markdown(result, summary, figure))
    return summary


def run_force_experiment(
    config: ForceConfig, motor_model: MotorModel, out: Path
) -> dict:
    """Runs the experiment (paper settings and config.ablations) and writes its report
    in `out`; returns the JSON summary (force.json)."""
    return write_force_report(run_force_all(config, motor_model), Path(out))


#: The logged ports save_signals keeps (the components analysis needs these).
SAVED_PORTS = (
    "q_ref",
    "q_measured",
    "tau_desired",
    "tau_estimated",
    "joint_torque_true",
    "delta_q",
    "fallback_active",
    "wrench_right_foot",
    "external_wrench_right_foot",
    "f_ref",
    *COMPONENTS,
)


def save_signals(run: ForceRun, path: Path) -> None:
    """The run's logged signals (SAVED_PORTS and "t") as a compressed npz, whole (30
    joints), so that `load_signals` returns what `run_controller` returned."""
    arrays = {"t": run.signals["t"]}
    arrays |= {name: run.signals[name] for name in SAVED_PORTS if name in run.signals}
    np.savez_compressed(path, **arrays)


def load_signals(path: Path) -> dict[str, np.ndarray]:
    """The signals `save_signals` wrote ({"t", port: array})."""
    with np.load(path) as data:
        return {name: data[name] for name in data.files}


def joint_motion(run: ForceRun) -> np.ndarray:
    """Peak-to-peak motion of the torque-controlled joints (encoders, rad) during the
    sinusoid, in the order of run.config.torque_control.joints."""
    on = run.signals["t"] >= run.config.sinusoid_start
    columns = [
        hrp2.JOINT_NAMES.index(j)
        for j in run.config.torque_control.controlled_joints(hrp2.description())
    ]
    q = run.signals["q_measured"][on][:, columns]
    return q.max(axis=0) - q.min(axis=0)


def _markdown(result: ForceResult, summary: dict, figure: str) -> str:
    base = result.baseline
    c, gains = base.config, base.config.torque_control.controller
    lines = [
        "# Force tracking (paper Sec. 5.4, Figure 5)",
        "",
        f"HRP-2 standing, right foot on a {c.station.block_height * 100:.0f} cm block; "
        f"right leg in torque control (K6 = {gains.k6:g}, K_p = "
        f"{', '.join(f'{k:g}' for k in gains.kp)}, K_f = {gains.kf[0]:g}, window "
        f"{c.torque_control.estimator.window}), the other joints in position control. "
        f"Reference: the standing pose; f_z = f0,z + {c.amplitude:g} "
        f"sin(2π·{c.frequency:g} Hz·t) for {c.periods:g} periods after {c.settle:g} s "
        f"of position control and {c.hold:g} s at f0; other axes "
        + ("held at their static values." if c.other_axes == "hold" else "zero.")
        + "",
        "",
        f"Static wrench of the right foot f0 (estimate, [τ; f] in N·m, N): "
        f"{np.array2string(base.static_wrench, precision=1, suppress_small=True)}.",
        "",
        "## Paper's Fig. 5 vs simulation (paper settings)",
        "",
        *_figure5_table(base.metrics),
        "",
        *_detail_lines(base),
    ]
    if result.variants:
        lines += _variant_lines([base] + result.variants)
    lines += [f"![{figure}]({figure})", ""]
    return "\n".join(lines)


def _figure5_table(metrics: dict[str, dict]) -> list[str]:
    """Fig. 5's numbers beside the paper's, from the estimate and the F/T reading."""
    e, r = metrics["estimate"], metrics["ft_reading"]
    rows = [
        ("overshoot at the apexes", "≈ 10%", "overshoot", "{:+.1%}"),
        (
            "amplitude ratio (sinusoid fit)",
            "≈ 1.1 (implied)",
            "amplitude_ratio",
            "{:.3f}",
        ),
        ("delay, cross-correlation (ms)", "none visible", "lag_ms", "{:+.1f}"),
        ("delay, sinusoid phase (ms)", "", "phase_delay_ms", "{:+.1f}"),
        ("RMS error of f_z (N)", "", "rms_error", "{:.2f}"),
        ("RMS error of f_z / A", "", "rms_error_ratio", "{:.1%}"),
        ("coupling on X, max abs(Δf_x) / A", "≈ 10%", "coupling_x", "{:.1%}"),
        ("coupling on X, fitted amplitude / A", "", "coupling_x_fit", "{:.1%}"),
    ]
    return markdown_table(
        ["metric", "paper", "estimate f̂", "F/T reading"],
        [
            [label, paper, fmt.format(e[key]), fmt.format(r[key])]
            for label, paper, key, fmt in rows
        ],
    )


def _detail_lines(base: ForceRun) -> list[str]:
    """The paper settings' run beyond Fig. 5: per apex, the coupling on the other
    axes, how far the leg moved, and its fallback if it fell back."""
    r = base.metrics["ft_reading"]
    lines = [
        "Per apex (F/T reading): "
        + ", ".join(f"{x:+.1%}" for x in r["overshoot_per_apex"])
        + ". Coupling on the other axes (fitted amplitude / A, F/T reading): "
        + ", ".join(f"{k} {v:.1%}" for k, v in r["coupling_fit"].items())
        + ".",
        "",
        "Right-leg motion during the sinusoid (peak-to-peak, mrad; the contact and "
        "the position-controlled left leg are compliant, so the leg moves with the "
        "force and K6 e_q resists it): "
        + ", ".join(
            f"{label} {value * 1e3:.1f}"
            for label, value in zip(hrp2.RIGHT_LEG_LABELS, joint_motion(base))
        )
        + ".",
        "",
    ]
    if base.fallback_time is not None:
        lines += [
            "The controller fell back to position control at "
            f"{base.fallback_time:.2f} s.",
            "",
        ]
    return lines


def _variant_lines(runs: list[ForceRun]) -> list[str]:
    """Each run's tracking (F/T reading, the estimate in parentheses)."""
    rows = []
    for run in runs:
        m, me = run.metrics["ft_reading"], run.metrics["estimate"]
        rows.append(
            [
                run.label,
                f"{m['overshoot']:+.1%} ({me['overshoot']:+.1%})",
                f"{m['amplitude_ratio']:.3f} ({me['amplitude_ratio']:.3f})",
                f"{m['lag_ms']:+.0f} ({me['lag_ms']:+.0f})",
                f"{m['rms_error']:.1f} ({me['rms_error']:.1f})",
                f"{m['coupling_x']:.1%}",
                f"{run.fallback_time:.2f} s" if run.fallback_time else "no",
            ]
        )
    header = [
        "variant",
        "overshoot",
        "amplitude ratio",
        "lag (ms)",
        "RMS error (N)",
        "coupling X",
        "fallback",
    ]
    return [
        "## Why: variants (F/T reading; estimate in parentheses)",
        "",
        *markdown_table(header, rows, align="lrrrrrl"),
        "",
    ]


#: Variants per panel of Fig. 5's variant panels: with the paper's settings and the
#: reference, at most 8 curves, each of its own colour.
VARIANTS_PER_PANEL = 6


def plot_figure5(result: ForceResult, out: Path) -> str:
    """The paper's Fig. 5: reference and measured f_z and f_x of the right foot
    (estimate and smoothed F/T reading, each shifted to the controller's f0), plus
    f_z of the variants, VARIANTS_PER_PANEL per panel beside the paper's settings
    (at most 8 curves a panel); every legend beside its panel, off the data."""
    plt = pyplot()
    groups = [
        result.variants[k : k + VARIANTS_PER_PANEL]
        for k in range(0, len(result.variants), VARIANTS_PER_PANEL)
    ]
    rows = 2 + len(groups)
    fig, axes = plt.subplots(
        rows, 1, figsize=(13, 3.2 * rows), sharex=True, layout="constrained"
    )
    _plot_paper_settings(axes[:2], result.baseline)
    for k, (ax, group) in enumerate(zip(axes[2:], groups)):
        first = k * VARIANTS_PER_PANEL + 1
        _plot_variants(
            ax,
            result.baseline,
            group,
            f"variants {first}-{first + len(group) - 1} of {len(result.variants)}",
        )
    for ax in axes:
        legend_beside(ax, fontsize=7)
    axes[-1].set_xlabel("t (s)")
    name = "figure5_force_tracking.png"
    save_figure(fig, out / name)
    return name


def _smoothing_samples(run: ForceRun) -> int:
    """The samples of the F/T reading's moving average in Fig. 5."""
    t = run.signals["t"]
    return max(1, int(round(run.config.smoothing / (t[1] - t[0]))))


def _plot_paper_settings(axes, base: ForceRun) -> None:
    """Fig. 5's two panels: f_z and f_x of the reference, the estimate and the F/T
    reading (smoothed, shifted to f0) with the paper settings' run."""
    c = base.config
    s = base.signals
    t = s["t"]
    keep = t >= c.settle - 0.2
    reading = moving_average(s[SIGNALS["ft_reading"]], _smoothing_samples(base))
    reading = reading - base.static_reading + base.static_wrench
    for ax, axis, name in ((axes[0], FZ, "f_z"), (axes[1], FX, "f_x")):
        ax.plot(t[keep], s["f_ref"][keep, axis], "k--", lw=1.2, label="reference")
        ax.plot(
            t[keep],
            s[SIGNALS["estimate"]][keep, axis],
            lw=1,
            label="estimate f̂ (fed back)",
        )
        ax.plot(
            t[keep],
            reading[keep, axis],
            lw=1,
            label="F/T reading (smoothed,\nshifted to f0)",
        )
        ax.set_ylabel(f"{name} (N)")
        ax.grid(True, alpha=0.3)
        ax.axvline(c.settle, color="grey", lw=0.8, ls=":")
    m = base.metrics["ft_reading"]
    axes[0].set_title(
        f"right foot, K6 = {c.torque_control.controller.k6:g}, "
        f"K_f = {c.torque_control.controller.kf[0]:g}: "
        f"overshoot {m['overshoot']:+.1%}, lag {m['lag_ms']:+.0f} ms, coupling X "
        f"{m['coupling_x']:.1%} (F/T reading)",
        fontsize=10,
    )


def _plot_variants(ax, base: ForceRun, group: list[ForceRun], which: str) -> None:
    """One variant panel of Fig. 5: f_z of the reference, of the paper settings' run
    and of the variants of `group` (F/T reading, smoothed, less f0); `which` names
    them in the title."""
    c = base.config
    t = base.signals["t"]
    keep = t >= c.settle - 0.2
    smoothing = _smoothing_samples(base)
    ax.plot(
        t[keep],
        base.signals["f_ref"][keep, FZ] - base.static_wrench[FZ],
        "k--",
        lw=1.2,
        label="reference",
    )
    for i, run in enumerate([base] + group):
        rt = run.signals["t"]
        keep_v = rt >= c.settle - 0.2
        smooth = moving_average(run.signals[SIGNALS["ft_reading"]], smoothing)
        ax.plot(
            rt[keep_v],
            smooth[keep_v, FZ] - run.static_reading[FZ],
            color="0.35" if run is base else f"C{i - 1}",
            lw=1.4 if run is base else 0.9,
            label="the paper's settings" if run is base else _wrapped(run.label),
        )
    ax.set_ylabel("f_z − f0,z (N), F/T")
    ax.set_title(f"{which} beside the paper's settings", fontsize=10)
    ax.grid(True, alpha=0.3)


def _wrapped(label: str, width: int = 42) -> str:
    """A legend label on lines of at most `width` characters."""
    import textwrap

    return "\n".join(textwrap.wrap(label, width))
