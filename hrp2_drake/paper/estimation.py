"""Torque-estimation accuracy in closed loop (paper Sec. 2 and 5.1).

The station runs with noisy default sensors (encoder quantization, IMU and F/T noise and
biases) while the position servo tracks sinusoids; one estimation chain per window
(Savitzky-Golay filters + FloatingBaseTorqueEstimator, `add_estimator`) reads the same
sensors in the same diagram. Each τ̂ is compared with the ground truth
`joint_torque_true` shifted by the chain's delay (`EstimationChain.delay()`, checked by
searching the shift that minimises the error), per joint: RMS error, peak |τ|, RMS/peak
(`estimation.accuracy.errors`, the balance experiment's definition too).

Motions (documented in `default_motions`):
- "hanging" (paper Fig. 2b): the six right-leg joints track sinusoids of different
  frequencies around half-sitting; the rest holds half-sitting.
- "standing": both legs squat in phase (hip pitch and ankle pitch move by minus half
  the knee, so the feet stay flat and the torso upright above them), the chest yaws
  (a moment about the vertical that loads the hip-yaw joints), the pelvis sways
  sideways and the torso leans, the arms swing: the robot stays standing (the report
  gives the waist's tilt), and every right-leg joint carries a changing torque.

F/T offsets: the hanging run calibrates them at start-up (nothing touches the feet and
hands); the standing run cannot (the feet are on the ground from t = 0), so it uses
offsets calibrated in a short hanging run with the same sensors, as one calibrates a
real robot lifted before putting it down.
"""

import dataclasses
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import TrajectorySource

from hrp2_drake import console
from hrp2_drake.assembly.torque_control import check_window
from hrp2_drake.description.sensors import SensorsConfig
from hrp2_drake.estimation.accuracy import errors, shifted
from hrp2_drake.estimation.estimation_chain import add_estimator
from hrp2_drake.paper import hrp2
from hrp2_drake.paper.claims import GOAL_RMS_OVER_PEAK
from hrp2_drake.report import markdown_table, pyplot, save_figure
from hrp2_drake.robot.station import (
    StationConfig,
    initial_joint_positions,
    make_station,
)
from hrp2_drake.simulation import (
    add_loggers,
    joint_reference,
    logs_to_arrays,
    run_with_progress,
)

SCENARIOS = ("hanging", "standing")
PAPER_WINDOW = 80  # samples (paper Sec. 5.1)
PLOT_JOINT = "RLEG_JOINT3"  # the right knee
REVERSAL_MARGIN = 0.03  # s, see analyse


@dataclass
class JointSinusoid:
    """q_cmd = q0 + envelope(t)
    · (offset + amplitude · sin(2π f (t − t_start) + phase)).

    Args:
        joint: joint name (HRP-2).
        amplitude: rad (signed: joints moved together share a phase and a frequency).
        frequency: Hz.
        offset: rad, a shift of the centre, brought in by the envelope.
        phase: rad.
    """

    joint: str = ""
    amplitude: float = 0.0
    frequency: float = 0.5
    offset: float = 0.0
    phase: float = 0.0


def _squat(leg: str, knee: float, frequency: float) -> list[JointSinusoid]:
    """Hip pitch, knee, ankle pitch of `leg` ("RLEG" or "LLEG") in phase, hip and ankle
    by −knee/2: equal thigh and shank (0.3 m each) keep the hip above the ankle and the
    foot parallel to the torso (flat on the ground with the torso upright)."""
    return [
        JointSinusoid(f"{leg}_JOINT2", -knee / 2, frequency),
        JointSinusoid(f"{leg}_JOINT3", knee, frequency),
        JointSinusoid(f"{leg}_JOINT4", -knee / 2, frequency),
    ]


def default_motions() -> dict[str, list[JointSinusoid]]:
    """The motion of each scenario (module docstring).

    Hanging: the six right-leg joints, amplitudes within the identification
    excitation's range, frequencies 0.4-1 Hz (peak velocities 0.5-1.3 rad/s); the hip
    roll is centred 0.1 rad outward so that the feet never touch.

    Standing, every right-leg joint loaded by a changing torque while the feet stay
    flat and the robot balanced: both legs squat (knee ±0.25 rad at 0.5 Hz, hip and
    ankle pitch by minus half), sway sideways (hip roll ±0.06 rad and ankle roll ∓0.06
    rad at 0.35 Hz, both legs: the pelvis translates ±4 cm, moving the weight from foot
    to foot), lean the torso (hip pitch ±0.1 rad at 0.3 Hz, both legs), the chest yaws
    (±0.35 rad at 0.6 Hz: a moment about the vertical that loads the hip-yaw joints)
    and the arms swing (shoulder pitch ±0.3 rad at 0.7 Hz, in antiphase).
    """
    standing = _squat("RLEG", 0.25, 0.5) + _squat("LLEG", 0.25, 0.5)
    for leg in ("RLEG", "LLEG"):
        standing += [
            JointSinusoid(f"{leg}_JOINT1", 0.06, 0.35),
            JointSinusoid(f"{leg}_JOINT5", -0.06, 0.35),
            JointSinusoid(f"{leg}_JOINT2", -0.1, 0.3, phase=1.0),
        ]
    standing += [
        JointSinusoid("CHEST_JOINT0", 0.35, 0.6),
        JointSinusoid("RARM_JOINT0", 0.3, 0.7),
        JointSinusoid("LARM_JOINT0", -0.3, 0.7),
    ]
    return {
        "hanging": [
            JointSinusoid("RLEG_JOINT0", 0.3, 0.6),
            JointSinusoid("RLEG_JOINT1", 0.1, 0.5, offset=-0.1),
            JointSinusoid("RLEG_JOINT2", 0.4, 0.4),
            JointSinusoid("RLEG_JOINT3", 0.5, 0.7, phase=0.5 * math.pi),
            JointSinusoid("RLEG_JOINT4", 0.3, 0.9),
            JointSinusoid("RLEG_JOINT5", 0.15, 1.0),
        ],
        "standing": standing,
    }


#: The key of the per-signal-window chain (beside the uniform windows' ints).
PER_SIGNAL = "per_signal"


@dataclass
class EstimationConfig:
    """Configuration of the closed-loop estimation experiment.

    Args:
        scenarios: stations to run, among "hanging" and "standing".
        windows: Savitzky-Golay windows (samples) to compare; must include the paper's
            80. One estimation chain per window, all in the same diagram.
        per_signal_window, per_signal_windows: one more chain with per-signal
            windows (TorqueEstimatorConfig.window and .windows: the encoders' window
            and, by joint, F/T sensor or "imu", the others; every window centred on
            the longest's centre). The default, the encoders at 17 and the IMU at 41
            (delay 20 ms), was chosen on the hanging run; 0: no such chain.
        duration: simulated time per scenario (s), settle and ramp included.
        settle: time the initial pose is held before the motion starts (s); the
            errors are measured from then on (the filters are full by then).
        ramp: time over which the sinusoids' amplitude rises from 0 (s, smoothstep).
        duration_scale: multiplies duration, settle excepted (e.g. 0.3 for tests).
        motions: per scenario, the sinusoids the servo tracks; empty: default_motions().
        sensors: the station's sensors (none: the robot description's, HRP-2's noise
            and biases).
        seed: the sensors' noise seed (overrides sensors.seed).
        servo_file: the station's servo (`StationConfig.servo_file`; empty: calibrated).
        calibration_time: F/T offset calibration (s), while hanging, starting at
            calibration_start; 0 for none.
        calibration_start: start of the calibration (s), after the filters fill.
        plot_seconds: length of the τ plot (s), at the end of the run.
    """

    scenarios: list[str] = field(default_factory=lambda: list(SCENARIOS))
    windows: list[int] = field(default_factory=lambda: [20, 30, 40, 60, 80, 120, 160])
    per_signal_window: int = 17
    per_signal_windows: dict[str, int] = field(default_factory=lambda: {"imu": 41})
    duration: float = 10.0
    settle: float = 1.0
    ramp: float = 1.0
    duration_scale: float = 1.0
    motions: dict[str, list[JointSinusoid]] = field(default_factory=dict)
    sensors: SensorsConfig | None = None
    seed: int = 0
    servo_file: str = ""
    calibration_time: float = 0.5
    calibration_start: float = 0.2
    plot_seconds: float = 4.0

    def validate(self) -> None:
        """Raises ValueError naming the bad field (yaml_load_typed does not call it)."""
        where = "EstimationConfig"
        bad = [s for s in self.scenarios if s not in SCENARIOS]
        if bad or not self.scenarios:
            raise ValueError(f"{where}.scenarios: {self.scenarios}, use {SCENARIOS}")
        if PAPER_WINDOW not in self.windows:
            raise ValueError(f"{where}.windows must include the paper's {PAPER_WINDOW}")
        for k, window in enumerate(self.windows):
            check_window(window, f"{where}.windows[{k}]")
        if len(set(self.windows)) != len(self.windows):
            raise ValueError(f"{where}.windows: duplicates in {self.windows}")
        if self.per_signal_window:
            check_window(self.per_signal_window, f"{where}.per_signal_window")
            for name, window in self.per_signal_windows.items():
                check_window(window, f"{where}.per_signal_windows['{name}']")
            try:
                hrp2.estimator_config(
                    self.per_signal_window, windows=dict(self.per_signal_windows)
                ).validate()
            except ValueError as error:
                raise ValueError(f"{where}.per_signal_windows: {error}") from None
        for name in ("duration", "duration_scale"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{where}.{name} must be > 0")
        for name in ("settle", "ramp", "calibration_time", "calibration_start"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{where}.{name} must be >= 0")
        if self.run_duration() <= self.settle + 2 * max(self.windows) * 1e-3:
            raise ValueError(
                f"{where}: the run ({self.run_duration():.2f} s) leaves nothing to "
                f"measure after settle={self.settle} s"
            )
        if self.calibration_time > 0 and (
            self.calibration_start + self.calibration_time > self.settle
        ):
            raise ValueError(
                f"{where}: the calibration must end before the motion starts "
                f"(calibration_start + calibration_time <= settle)"
            )
        for scenario, motion in self.motions.items():
            if scenario not in SCENARIOS:
                raise ValueError(f"{where}.motions: unknown scenario '{scenario}'")
            for s in motion:
                if s.joint not in hrp2.JOINT_NAMES:
                    raise ValueError(f"{where}.motions.{scenario}: joint '{s.joint}'")

    def run_duration(self) -> float:
        return self.settle + (self.duration - self.settle) * self.duration_scale

    def motion(self, scenario: str) -> list[JointSinusoid]:
        return self.motions.get(scenario) or default_motions()[scenario]


def sinusoid_reference(
    q0: np.ndarray,
    motion: list[JointSinusoid],
    start: float,
    ramp: float,
    duration: float,
    dt: float = 0.005,
):
    """(times, positions (m, 30)) of the commanded joint angles: q0 until `start`,
    then the sinusoids (and their offsets) under a smoothstep envelope rising from 0
    to 1 over `ramp` (s)."""
    t = np.arange(0.0, duration + dt / 2, dt)
    q = np.tile(q0, (len(t), 1))
    s = np.clip((t - start) / ramp, 0.0, 1.0) if ramp > 0 else (t >= start) * 1.0
    envelope = s * s * (3.0 - 2.0 * s)
    for sinusoid in motion:
        j = hrp2.JOINT_NAMES.index(sinusoid.joint)
        wave = np.sin(2 * math.pi * sinusoid.frequency * (t - start) + sinusoid.phase)
        wave = np.where(t >= start, wave, math.sin(sinusoid.phase))
        q[:, j] += envelope * (sinusoid.offset + sinusoid.amplitude * wave)
    return t, q


def _station_config(config: EstimationConfig, scenario: str) -> StationConfig:
    base = (
        StationConfig().sensors_config() if config.sensors is None else config.sensors
    )
    sensors = dataclasses.replace(base, seed=config.seed)
    return StationConfig(
        scenario=scenario, sensors=sensors, servo_file=config.servo_file
    )


def _build(
    config: EstimationConfig,
    scenario: str,
    duration: float,
    calibrate: bool,
    motion: list[JointSinusoid] | None,
):
    """Station + q_cmd source + one chain per window + loggers of τ̂ and the truth."""
    station_config = _station_config(config, scenario)
    builder = DiagramBuilder()
    station = builder.AddNamedSystem("station", make_station(station_config))
    q0 = initial_joint_positions(station_config)
    t, q = sinusoid_reference(
        q0, motion or [], config.settle, config.ramp, duration + 0.1
    )
    source = builder.AddNamedSystem("q_cmd", TrajectorySource(joint_reference(t, q)))
    builder.Connect(source.get_output_port(), station.GetInputPort("q_cmd"))
    plant = hrp2.estimator_plant()
    options = {}
    if calibrate and config.calibration_time > 0:
        options = dict(
            offset_calibration_time=config.calibration_time,
            offset_calibration_start=config.calibration_start,
        )
    chains = {}
    for window in config.windows:
        chains[window] = add_estimator(
            builder,
            station,
            plant,
            hrp2.estimator_config(window, **options),
            name=f"estimator_w{window}",
        )
    if config.per_signal_window:
        chains[PER_SIGNAL] = add_estimator(
            builder,
            station,
            plant,
            hrp2.estimator_config(
                config.per_signal_window,
                windows=dict(config.per_signal_windows),
                **options,
            ),
            name=f"estimator_{PER_SIGNAL}",
        )
    ports = {
        "true": station.GetOutputPort("joint_torque_true"),
        "state": station.GetOutputPort("state_true"),
    }
    for window, chain in chains.items():
        ports[f"tau_w{window}"] = chain.estimator.GetOutputPort("tau")
    loggers = add_loggers(builder, ports, 1e-3)
    return builder.Build(), chains, loggers


def calibrate_offsets(config: EstimationConfig) -> dict[int, np.ndarray]:
    """F/T offsets (k, 6) per window, calibrated on the hanging station (robot still,
    nothing touching the sensors) with the same sensors."""
    end = config.calibration_start + config.calibration_time + 0.01
    diagram, chains, _ = _build(config, "hanging", end, True, None)
    simulator = Simulator(diagram)
    run_with_progress(simulator, end, "F/T offset calibration (hanging)", steps=2)
    context = simulator.get_context()
    return {
        window: chain.estimator.offsets(chain.estimator.GetMyContextFromRoot(context))
        for window, chain in chains.items()
    }


def run_scenario(
    config: EstimationConfig,
    scenario: str,
    offsets: dict[int, np.ndarray] | None = None,
) -> dict:
    """Simulates one scenario; returns {"t", "true", "tau": {window: τ̂}, "delay":
    {window: s}, "base" (waist pose: quaternion, position), "duration",
    "real_time_factor"}. The estimators start with `offsets` (per window) if given;
    otherwise, hanging, they calibrate at start-up (config.calibration_time)."""
    duration = config.run_duration()
    calibrate = offsets is None and scenario == "hanging"
    diagram, chains, loggers = _build(
        config, scenario, duration, calibrate, config.motion(scenario)
    )
    simulator = Simulator(diagram)
    context = simulator.get_context()
    if offsets is not None:
        for window, chain in chains.items():
            chain.estimator.set_offsets(
                chain.estimator.GetMyMutableContextFromRoot(context), offsets[window]
            )
    rtf = run_with_progress(simulator, duration, f"estimation {scenario}")
    logs = logs_to_arrays(loggers, simulator.get_context())
    return {
        "t": logs["t"],
        "true": logs["true"],
        "base": logs["state"][:, :7],  # the waist: quaternion (w, x, y, z), position
        "tau": {w: logs[f"tau_w{w}"] for w in chains},
        "delay": {w: chain.delay() for w, chain in chains.items()},
        "duration": duration,
        "real_time_factor": rtf,
    }


def best_shift(
    t: np.ndarray, tau: np.ndarray, true: np.ndarray, nominal: float, start: float
) -> float:
    """The delay (samples, in half samples within ±10 of `nominal`) that minimises the
    total squared error of the right leg: verifies the chain's delay."""
    leg = [hrp2.JOINT_NAMES.index(j) for j in hrp2.RIGHT_LEG]
    candidates = [round(nominal + 0.5 * k, 9) for k in range(-20, 21)]
    candidates = [c for c in candidates if c >= 0]
    cost = []
    for shift in candidates:
        e = errors(t, tau[:, leg], true[:, leg], shift, start)
        cost.append(float(np.sum(e["rms"] ** 2)))
    return candidates[int(np.argmin(cost))]


def near_reversals(t: np.ndarray, q: np.ndarray, margin: float) -> np.ndarray:
    """(samples, joints) mask: within `margin` (s) of a velocity reversal of that
    column of q (the commanded joint angles, sampled at t)."""
    v = np.diff(q, axis=0)
    near = np.zeros(q.shape, dtype=bool)
    for j in range(q.shape[1]):
        for k in np.flatnonzero(v[1:, j] * v[:-1, j] < 0) + 1:
            near[:, j] |= np.abs(t - t[k]) <= margin
    return near


def analyse(run: dict, config: EstimationConfig, scenario: str) -> dict:
    """Per window: errors against the truth delayed by the chain's delay, and at the
    shift that minimises them (the delay check); per right-leg joint, the share of its
    squared error within ±REVERSAL_MARGIN of its own commanded velocity reversals
    (where the servo's Coulomb friction and dead zone make the torque jump) and the
    share of the time that covers; the best window (smallest worst right-leg
    RMS/peak); the waist's motion (tilt from vertical, height range)."""
    t, true = run["t"], run["true"]
    period = t[1] - t[0]
    leg = [hrp2.JOINT_NAMES.index(j) for j in hrp2.RIGHT_LEG]
    q0 = initial_joint_positions(_station_config(config, scenario))
    _, q_cmd = sinusoid_reference(
        q0, config.motion(scenario), config.settle, config.ramp, t[-1], period
    )
    reversals = near_reversals(t, q_cmd[: len(t), leg], REVERSAL_MARGIN)
    windows = {}
    for window, tau in run[
        "tau"
    ].items():  # (and the per-signal chain, set apart below)
        nominal = round(run["delay"][window] / period, 9)
        e = errors(t, tau, true, nominal, config.settle)
        shift = best_shift(t, tau, true, nominal, config.settle)
        at_shift = errors(t, tau, true, shift, config.settle)
        # The error of τ̂'s sample i refers to the robot at t_i − delay.
        near = shifted(reversals.astype(float), nominal) > 0
        reference = shifted(true[:, leg], nominal)
        rows = (t >= config.settle) & np.all(np.isfinite(reference), axis=1)
        squared = (tau[rows][:, leg] - reference[rows]) ** 2
        near = near[rows]
        windows[window] = {
            "delay_s": run["delay"][window],
            "delay_samples": nominal,
            "best_shift_samples": shift,
            "rms": e["rms"].tolist(),
            "peak": e["peak"].tolist(),
            "ratio": e["ratio"].tolist(),
            "right_leg_worst_ratio": float(np.max(e["ratio"][leg])),
            "rms_at_best_shift": at_shift["rms"].tolist(),
            "right_leg_worst_ratio_at_best_shift": float(
                np.max(at_shift["ratio"][leg])
            ),
            "right_leg_error_share_near_reversals": (
                np.sum(squared * near, axis=0) / np.sum(squared, axis=0)
            ).tolist(),
            "right_leg_time_share_near_reversals": np.mean(near, axis=0).tolist(),
        }
    per_signal = windows.pop(PER_SIGNAL, None)
    best = min(windows, key=lambda w: windows[w]["right_leg_worst_ratio"])
    quaternion, position = run["base"][:, :4], run["base"][:, 4:]
    # The waist's z axis in the world: its z component is 1 − 2(x² + y²).
    up = 1.0 - 2.0 * (quaternion[:, 1] ** 2 + quaternion[:, 2] ** 2)
    return {
        "windows": windows,
        "best_window": best,
        "goal_met": windows[best]["right_leg_worst_ratio"] < GOAL_RMS_OVER_PEAK,
        "per_signal": per_signal,
        "per_signal_goal_met": per_signal is not None
        and per_signal["right_leg_worst_ratio"] < GOAL_RMS_OVER_PEAK,
        "duration_s": run["duration"],
        "real_time_factor": run["real_time_factor"],
        "base_max_tilt_rad": float(np.max(np.arccos(np.clip(up, -1.0, 1.0)))),
        "base_height_range_m": [
            float(position[:, 2].min()),
            float(position[:, 2].max()),
        ],
    }


def plot_torque(run: dict, analysis: dict, config: EstimationConfig, path: Path):
    """τ̂ (paper window and best window, each shifted back by its delay) and the true τ
    of PLOT_JOINT over the last config.plot_seconds, with the errors below."""
    plt = pyplot()
    t, true = run["t"], run["true"]
    j = hrp2.JOINT_NAMES.index(PLOT_JOINT)
    shown = t >= max(config.settle, t[-1] - config.plot_seconds)
    best = analysis["best_window"]
    fig, (top, bottom) = plt.subplots(
        2, 1, figsize=(9, 6.5), sharex=True, layout="constrained"
    )
    top.plot(t[shown], true[shown, j], "k", lw=1.0, label="true τ (joint_torque_true)")
    for window, style in ((PAPER_WINDOW, "C0"), (best, "C1--")):
        delay = run["delay"][window]
        label = f"τ̂, window {window}, shifted back {1e3 * delay:.1f} ms"
        if window == best:
            label += " (best)"
        top.plot(
            t[shown] - delay, run["tau"][window][shown, j], style, lw=1.2, label=label
        )
        error = run["tau"][window][:, j] - shifted(true, delay / (t[1] - t[0]))[:, j]
        bottom.plot(
            t[shown] - delay, error[shown], style, lw=1.0, label=f"window {window}"
        )
        if best == PAPER_WINDOW:
            break
    top.set_ylabel(f"{PLOT_JOINT} torque (N·m)")
    top.set_title(f"{PLOT_JOINT} (right knee), {path.stem.split('_')[-1]}")
    bottom.set_ylabel("τ̂ − delayed true τ (N·m)")
    bottom.set_xlabel("time the estimate refers to (s)")
    # One legend below the panels (off the data); the errors below share the styles.
    fig.legend(
        *top.get_legend_handles_labels(), loc="outside lower center", ncol=2, fontsize=8
    )
    save_figure(fig, path)


def _table(w: dict) -> list[str]:
    """The right-leg table of one chain's analysis."""
    rows = []
    for k, name in enumerate(hrp2.RIGHT_LEG):
        j = hrp2.JOINT_NAMES.index(name)
        time_share = w["right_leg_time_share_near_reversals"][k]
        share = (
            f"{100 * w['right_leg_error_share_near_reversals'][k]:.0f} % "
            f"({100 * time_share:.0f} %)"
            if time_share > 0
            else "(does not move)"
        )
        rows.append(
            [
                f"{name} ({hrp2.RIGHT_LEG_LABELS[k]})",
                f"{w['rms'][j]:.3f}",
                f"{w['peak'][j]:.2f}",
                f"{100 * w['ratio'][j]:.2f} %",
                share,
            ]
        )
    header = [
        "joint",
        "RMS error (N·m)",
        "peak abs(τ) (N·m)",
        "RMS / peak",
        "share of the squared error near its velocity reversals (share of the time)",
    ]
    return markdown_table(header, rows)


def _summary_all(w: dict, window) -> str:
    ratio, peak = np.array(w["ratio"]), np.array(w["peak"])
    loaded = peak >= 1.0
    worst = int(np.flatnonzero(loaded)[np.argmax(ratio[loaded])])
    return (
        f"All 30 joints, {window}: median RMS error "
        f"{np.median(w['rms']):.3f} N·m, max {np.max(w['rms']):.3f} N·m "
        f"({hrp2.JOINT_NAMES[int(np.argmax(w['rms']))]}); RMS/peak median "
        f"{100 * np.median(ratio[loaded]):.2f} %, worst {100 * ratio[worst]:.2f} % "
        f"({hrp2.JOINT_NAMES[worst]}, peak {peak[worst]:.2f} N·m) over the "
        f"{int(loaded.sum())} joints whose peak abs(τ) reaches 1 N·m (the others "
        "barely move)."
    )


def markdown(results: dict, config: EstimationConfig) -> str:
    lines = [
        "# Torque estimation in closed loop",
        "",
        "The station runs with noisy default sensors while the position servo tracks "
        "sinusoids (`hrp2_drake/paper/estimation.py`); one estimation chain per "
        "Savitzky-Golay window reads the same sensors. τ̂ is compared with "
        "`joint_torque_true` delayed by the chain's delay ((N − 1)/2 samples); "
        f"errors from t = {config.settle} s (motion start). Goal: RMS error < "
        f"{100 * GOAL_RMS_OVER_PEAK:.0f} % of peak abs(τ) on every right-leg joint at "
        "the best window. The last column of the joint tables is the share of the "
        f"joint's squared error within ±{1e3 * REVERSAL_MARGIN:.0f} ms of its own "
        "commanded velocity reversals, where the servo's Coulomb friction and dead "
        "zone make the torque jump faster than these filters follow (a real torque, "
        "not noise: with noiseless sensors the error is the same there).",
        "",
    ]
    for scenario, analysis in results.items():
        lines += _scenario_lines(scenario, analysis, config)
    return "\n".join(lines)


def _scenario_lines(
    scenario: str, analysis: dict, config: EstimationConfig
) -> list[str]:
    """One scenario's section: the run, every window, the joint tables of the paper's
    and the best window with the goal, of the per-signal windows if run, the plot."""
    best = analysis["best_window"]
    lines = [
        f"## {scenario}",
        "",
        f"{analysis['duration_s']:.1f} s simulated at "
        f"{analysis['real_time_factor']:.2f}x real time (station + "
        f"{len(analysis['windows'])} chains). Motion: "
        + ", ".join(
            f"{s.joint} {s.amplitude:+.2f} rad {s.frequency:g} Hz"
            for s in config.motion(scenario)
        )
        + ".",
        "",
        f"The waist tilted at most {math.degrees(analysis['base_max_tilt_rad']):.1f}° "
        f"from vertical, its height stayed in "
        f"[{analysis['base_height_range_m'][0]:.3f}, "
        f"{analysis['base_height_range_m'][1]:.3f}] m.",
        "",
        *_window_table(analysis["windows"]),
    ]
    lines += ["", f"### {scenario}, paper window ({PAPER_WINDOW})", ""]
    paper, best_w = analysis["windows"][PAPER_WINDOW], analysis["windows"][best]
    lines += _table(paper)
    lines += ["", _summary_all(paper, f"window {PAPER_WINDOW}"), ""]
    lines += [f"### {scenario}, best window ({best})", ""]
    lines += _table(best_w)
    lines += ["", _summary_all(best_w, f"window {best}"), ""]
    verdict = "met" if analysis["goal_met"] else "NOT met"
    lines += [
        f"Goal (RMS < {100 * GOAL_RMS_OVER_PEAK:.0f} % of peak on every right-leg "
        f"joint at the best window): **{verdict}** (worst "
        f"{100 * best_w['right_leg_worst_ratio']:.2f} %).",
        "",
    ]
    per_signal = analysis.get("per_signal")
    if per_signal is not None:
        label = _per_signal_label(config)
        verdict = "met" if analysis["per_signal_goal_met"] else "NOT met"
        lines += [f"### {scenario}, per-signal windows ({label})", ""]
        lines += _table(per_signal)
        lines += [
            "",
            _summary_all(per_signal, "per-signal windows"),
            "",
            f"Delay {1e3 * per_signal['delay_s']:.1f} ms (the longest window's "
            f"centre; best shift {per_signal['best_shift_samples']:.1f} samples). "
            f"Goal with per-signal windows: **{verdict}** (worst "
            f"{100 * per_signal['right_leg_worst_ratio']:.2f} %).",
            "",
        ]
    return lines + [f"![τ̂ and true τ, {PLOT_JOINT}](estimation_tau_{scenario}.png)", ""]


def _window_table(windows: dict[int, dict]) -> list[str]:
    """Per window: its delay, the shift that minimises the error, the worst
    right-leg RMS/peak at its delay and at that shift."""
    rows = [
        [
            f"{window}",
            f"{1e3 * w['delay_s']:.1f}",
            f"{w['best_shift_samples']:.1f} (delay: {w['delay_samples']:.1f})",
            f"{100 * w['right_leg_worst_ratio']:.2f} %",
            f"{100 * w['right_leg_worst_ratio_at_best_shift']:.2f} %",
        ]
        for window, w in sorted(windows.items())
    ]
    header = [
        "window",
        "delay (ms)",
        "shift minimising the error (samples)",
        "worst right-leg RMS/peak",
        "same, at that shift",
    ]
    return markdown_table(header, rows, align="rrrrr")


def _per_signal_label(config: EstimationConfig) -> str:
    others = ", ".join(f"{k} {v}" for k, v in config.per_signal_windows.items())
    return f"encoders {config.per_signal_window}" + (f", {others}" if others else "")


def run_estimation_experiment(config: EstimationConfig, out: Path) -> dict:
    """Runs every scenario of `config`, writes out/estimation.md, estimation.json and
    estimation_tau_<scenario>.png; returns the JSON summary."""
    config.validate()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    for scenario in config.scenarios:
        offsets = None
        if scenario != "hanging" and config.calibration_time > 0:
            offsets = calibrate_offsets(config)
        run = run_scenario(config, scenario, offsets)
        analysis = analyse(run, config, scenario)
        plot_torque(run, analysis, config, out / f"estimation_tau_{scenario}.png")
        results[scenario] = analysis
        best = analysis["best_window"]
        per_signal = analysis.get("per_signal")
        message = (
            f"{scenario}: best window {best}, worst right-leg RMS/peak "
            f"{100 * analysis['windows'][best]['right_leg_worst_ratio']:.2f} % "
            f"(window {PAPER_WINDOW}: "
            f"{100 * analysis['windows'][PAPER_WINDOW]['right_leg_worst_ratio']:.2f} %"
            + (
                "; per-signal windows: "
                f"{100 * per_signal['right_leg_worst_ratio']:.2f} %)"
                if per_signal
                else ")"
            )
        )
        console.say(message)
    summary = {
        "joints": list(hrp2.JOINT_NAMES),
        "right_leg": list(hrp2.RIGHT_LEG),
        "goal_rms_over_peak": GOAL_RMS_OVER_PEAK,
        "config": asdict(config),
        "scenarios": {
            s: {**a, "windows": {str(w): v for w, v in a["windows"].items()}}
            for s, a in results.items()
        },
    }
    (out / "estimation.json").write_text(json.dumps(summary, indent=2))
    (out / "estimation.md").write_text(markdown(results, config))
    return summary
