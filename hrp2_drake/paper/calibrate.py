"""`hrp2-drake calibrate`: the emulated servo fitted to what was measured on the real
HRP-2.

The emulated servo (hrp2_drake.robot.servo) stands for the real robot, so its hidden
parameters come from the real robot's measurements, never from our own controllers'
results. This module builds models/hrp2/servo.yaml from three kinds of evidence:

1. **The paper's Table 1** fixes the linear part: Kτ = 1/(K1 K4) and Kv (the value an
   identification measures, latency included) on the right and left legs, as the
   `ideal` preset (servo_ideal.yaml) already has it.
2. **The authors' own measurements** fix the non-linear part, before any fit:
   the piecewise-linear fits of Δq(τ) of Sec. 3.2 on HRP-2 (andreadelprete/
   sot-torque-control, python/hrp2_motors_parameters_pwl.py, LGPL-3.0) give per joint
   the width of the steep central segment (the dead zone, in Δq) and the separation
   of the two velocity-sign branches (twice the Coulomb friction). See `PWL_FITS`.
3. **The position-control column of the paper's Tables 2 and 3** (the servo alone
   tracking the climbing swing on the hanging robot) is fitted by a real optimizer
   (scipy.optimize.least_squares, trust-region reflective) over the one mechanism
   that nothing else measures: the motor's voltage limit, i.e. the joint-side no-load
   speed ω0 of each moving right-leg joint, within physical bounds (the joint's rated
   speed, 3 rad/s in hrp2.rob, to 40 rad/s). Each evaluation simulates the whole
   hanging robot on the whole swing.

What it must not use, and does not: the torque-control columns of Tables 2 and 3,
Figure 5 and Sec. 5.2 (they stay out-of-sample predictions).

Table 2's "average" is N⁻¹ sqrt(Σ e²), which depends on the number of samples N the
paper does not give: `motion.derive_sample_count` derives it from the paper's own
numbers.
"""

import io
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from hrp2_drake import console
from hrp2_drake.assembly.builders import build_position_control, simulated_station
from hrp2_drake.paper import hrp2
from hrp2_drake.paper.claims import MOVING_JOINTS, MOVING_LABELS
from hrp2_drake.paper.motion import (
    PAPER_TABLE2,
    PAPER_TABLE3,
    MotionConfig,
    motion_reference,
    paper_sample_count,
    run_controller,
)
from hrp2_drake.report import legend_beside, markdown_table, pyplot, save_figure
from hrp2_drake.robot.servo import (
    ServoJointParams,
    ServoParams,
    effective_motor_parameters,
    load_servo_params,
    save_servo_params,
)
from hrp2_drake.robot.station import StationConfig

#: The position-control column of the paper's Table 2 (N⁻¹ sqrt(Σ e²), rad) and
#: Table 3 (maximum error, rad): hip roll, hip pitch, knee, ankle pitch, ankle roll.
PAPER_POSITION_AVERAGE = PAPER_TABLE2[:, 0] * 1e-3
PAPER_POSITION_MAX = PAPER_TABLE3[:, 0] * 1e-3

#: Piecewise-linear fits Δq = f±(τ) of HRP-2's legs by the paper's authors (Sec. 3.2,
#: Fig. 1): andreadelprete/sot-torque-control, python/hrp2_motors_parameters_pwl.py
#: (LGPL-3.0; numbers only). Per joint and branch (+: q̇ > 0, -: q̇ < 0): the slope
#: k2 (rad/(N·m)) of the central segment and its ends τ1, τ2 (N·m). The central
#: segment is where Δq moves with almost no torque: its width k2 (τ2 - τ1) is the
#: dead zone in Δq; the shift of its centre (τ1 + τ2)/2 between the branches is
#: twice the Coulomb friction. A slope of 8.33e-4 is the authors' bound on k2, so
#: those widths are lower bounds. The left hip yaw's + branch did not converge
#: (k2 = 100) and is not used.
PWL_FITS: dict[str, dict[str, tuple[float, float, float]]] = {
    "RLEG_JOINT0": {
        "+": (0.002431, 4.647462, 7.053441),
        "-": (0.002916, -5.447130, -3.455461),
    },
    "RLEG_JOINT1": {
        "+": (0.000833, 4.680849, 5.434831),
        "-": (0.000833, -3.987784, -3.202386),
    },
    "RLEG_JOINT2": {
        "+": (0.000833, 2.508688, 4.164688),
        "-": (0.000833, -11.694394, -8.598394),
    },
    "RLEG_JOINT3": {
        "+": (0.002415, 2.521347, 2.827010),
        "-": (0.000833, -8.327572, -7.158899),
    },
    "RLEG_JOINT4": {
        "+": (0.001963, 1.895690, 3.193865),
        "-": (0.005242, -4.124708, -3.671868),
    },
    "RLEG_JOINT5": {
        "+": (0.002760, 2.010004, 2.647346),
        "-": (0.001577, -3.188489, -1.953347),
    },
    "LLEG_JOINT0": {"-": (0.001836, -7.161778, -3.908519)},
    "LLEG_JOINT1": {
        "+": (0.000864, 1.502178, 2.350674),
        "-": (0.000833, -4.133966, -3.254320),
    },
    "LLEG_JOINT2": {
        "+": (0.000833, 12.411460, 15.594460),
        "-": (0.000833, 1.935234, 4.742034),
    },
    "LLEG_JOINT3": {
        "+": (0.000833, 7.420875, 8.740275),
        "-": (0.000833, -1.278539, -0.185339),
    },
    "LLEG_JOINT4": {
        "+": (0.001507, 3.311642, 4.748123),
        "-": (0.002136, -2.312898, -1.234218),
    },
    "LLEG_JOINT5": {
        "+": (0.003025, 1.358952, 1.961382),
        "-": (0.002221, -2.207792, -1.330901),
    },
}


def pwl_priors(joint: str) -> tuple[float, float | None]:
    """(dead zone half-width in Δq (rad), Coulomb friction (N·m) or None) of a leg
    joint from the authors' piecewise-linear fits (`PWL_FITS`)."""
    fit = PWL_FITS[joint]
    widths = [k2 * (t2 - t1) for k2, t1, t2 in fit.values()]
    half_width = 0.5 * float(np.mean(widths))
    if "+" in fit and "-" in fit:
        centre = {b: 0.5 * (t1 + t2) for b, (_, t1, t2) in fit.items()}
        coulomb = 0.5 * (centre["+"] - centre["-"])
    else:
        coulomb = None
    return half_width, coulomb


@dataclass
class CalibrationConfig:
    """Configuration of `hrp2-drake calibrate`.

    Args:
        latency: command transport latency, controller to servo board (s). HRP-2's
            controller runs at 1 kHz and its commands reach the motor boards through
            the robot's I/O one cycle later: 1 ms. Not measured by the paper; the
            identified Kv of Table 1 includes it (Δq is computed with the command as
            sent), so the servo's own damping is Kv - latency.
        hysteresis_width: joint travel over which the direction-dependent gain and the
            Coulomb friction switch after a reversal (rad): the lost motion of a
            harmonic drive, about 1 arcmin (2.9e-4 rad).
        stall_current: supply voltage / winding resistance (A) of the leg motors: a
            150 W-class 48 V DC motor stalls at about 40 A, HRP-2's driver limit here.
        no_load_speed_bounds: [min, max] of each calibrated joint-side no-load speed
            (rad/s): the rated joint speed of hrp2.rob (3 rad/s) to 40 rad/s.
        motor_no_load_speed: motor-side no-load speed of the leg motors (rad/s), the
            prior of every joint's ω0 = this / gear ratio, and the optimizer's start:
            a 150 W-class 48 V DC motor turns at about 7,600 rpm (794 rad/s) unloaded.
        prior_weight: weight of the residual log(ω0 / prior) of each joint, which keeps
            a joint whose errors do not depend on its voltage limit (it never gets near
            its no-load speed in the swing) at the prior instead of anywhere.
        average_weight: weight of Table 2's residuals relative to Table 3's.
        max_iterations: the optimizer's iterations (each: two simulations in parallel).
        settle: time holding the first pose before the swing (s).
        end: where the climbing motion is cut (s); < 0: its end (19.07 s). Shorter
            runs are for tests: Table 2's N is the whole motion's.
        jobs: parallel simulations (1 or 2).
    """

    latency: float = 0.001
    hysteresis_width: float = 2.9e-4
    stall_current: float = 40.0
    no_load_speed_bounds: list[float] = field(default_factory=lambda: [3.0, 40.0])
    motor_no_load_speed: float = 794.0
    prior_weight: float = 0.05
    average_weight: float = 0.5
    max_iterations: int = 12
    settle: float = 1.0
    end: float = -1.0
    jobs: int = 2

    def validate(self) -> None:
        lo, hi = self.no_load_speed_bounds
        if not 0 < lo < hi:
            raise ValueError(
                "CalibrationConfig.no_load_speed_bounds: need 0 < min < max, got "
                f"{lo}, {hi}"
            )
        if not self.motor_no_load_speed > 0 or self.prior_weight < 0:
            raise ValueError(
                "CalibrationConfig: motor_no_load_speed must be > 0, prior_weight >= 0"
            )
        if self.latency < 0 or self.hysteresis_width < 0 or self.stall_current <= 0:
            raise ValueError(
                "CalibrationConfig: latency and hysteresis_width must be >= 0, "
                "stall_current > 0"
            )
        if self.jobs not in (1, 2) or self.max_iterations < 1:
            raise ValueError(
                "CalibrationConfig: jobs must be 1 or 2, max_iterations >= 1"
            )


LEGS = hrp2.JOINT_NAMES[:12]


def _mirror(joint: str) -> str:
    return joint.replace("LLEG", "RLEG") if joint.startswith("LLEG") else joint


def build_servo(
    config: CalibrationConfig,
    no_load_speeds: dict[str, float],
    prior: ServoParams | None = None,
) -> ServoParams:
    """The servo: the `ideal` preset's linear part (Table 1) plus the mechanisms, with
    the given no-load speeds on the right-leg joints (mirrored on the left leg)."""
    prior = prior or load_servo_params("ideal")
    out = ServoParams()
    for name, ideal in prior.joints.items():
        p = ServoJointParams(**asdict(ideal))
        if name in LEGS:
            eff = effective_motor_parameters(prior, [name])
            k_tau, k_v = float(eff["k_tau"][0]), float(eff["k_v"][0])
            half_width, coulomb = pwl_priors(name)
            p.i_deadzone = half_width * p.k4
            if coulomb is None:
                coulomb = pwl_priors(_mirror(name))[1]
            p.k3 = coulomb
            p.hysteresis_width = config.hysteresis_width
            # The identified Kv (Table 1) includes the latency: keep it, split the
            # rest as the prior does (its share of real viscous friction K2).
            p.latency = config.latency
            damping = (k_v - config.latency) / k_tau
            share = ideal.k2 / (ideal.k1 * ideal.k5 + ideal.k2)
            p.k2 = share * damping
            p.k5 = (1 - share) * damping / p.k1
            speed = no_load_speeds.get(_mirror(name))
            if speed is not None:  # no data, no voltage limit (both .inf)
                p.stall_current = config.stall_current
                p.no_load_speed = float(speed)
        out.joints[name] = p
    return out


def position_control_errors(
    servo_file: str,
    settle: float = 1.0,
    servo_off: tuple[str, ...] = (),
    log: bool = False,
    end: float = -1.0,
) -> dict:
    """The hanging robot's own position servo on the whole climbing swing: the
    tracking error of the five moving right-leg joints after `settle`.

    Returns:
        dict with "max" (rad), "sum_squares" (Σ e², rad², at 1 kHz) and "rms" (rad)
        per moving joint, and "peak_speed" (rad/s); with `log`, "signals".
    """
    station = StationConfig(
        scenario="hanging", servo_file=servo_file, servo_off=list(servo_off)
    )
    config = MotionConfig(station=station, settle=settle, end=end)
    reference = motion_reference(config)
    robot, simulated, _ = simulated_station(station)
    control = build_position_control(robot, simulated, reference)
    signals = run_controller(
        control, reference.end_time(), "position control", stream=io.StringIO()
    )
    t = signals["t"]
    after = t >= settle
    columns = [hrp2.JOINT_NAMES.index(j) for j in MOVING_JOINTS]
    error = (signals["q_ref"] - signals["q_measured"])[after][:, columns]
    out = {
        "max": np.abs(error).max(axis=0),
        "sum_squares": np.sum(error**2, axis=0),
        "rms": np.sqrt(np.mean(error**2, axis=0)),
    }
    if log:
        out["signals"] = signals
    return out


def _evaluate(args: tuple) -> dict:
    """Process-pool worker: writes the servo for `speeds` and runs position control."""
    config, speeds, path, off = args
    save_servo_params(
        build_servo(config, speeds), Path(path), ["calibration candidate"]
    )
    result = position_control_errors(path, config.settle, off, end=config.end)
    return {k: v.tolist() for k, v in result.items()}


@dataclass
class Evaluation:
    """One simulation of the optimizer: the no-load speeds and what they gave."""

    speeds: list[float]  # rad/s, moving joints
    max_error: list[float]  # rad
    average_error: list[float]  # rad, Table 2's formula with the derived N
    cost: float
    kind: str  # "iterate" (the optimizer's point) or "finite difference"


@dataclass
class CalibrationResult:
    speeds: dict[str, float]
    sample_count: dict
    history: list[Evaluation]
    final: dict  # "max", "average", "rms" of the calibrated servo (rad)
    ideal: dict  # the same for the `ideal` preset
    ablation: dict[str, dict]  # mechanism switched off -> "max", "average"
    optimizer: dict
    wall_time: float


def _average(result: dict, n: float) -> np.ndarray:
    """Table 2's N⁻¹ sqrt(Σ e²) of a run's errors with the paper's N (rad)."""
    return np.sqrt(np.asarray(result["sum_squares"])) / n


def _residuals(result: dict, n: float, weight: float) -> np.ndarray:
    """Log ratios simulation / paper: Table 3 (max), then Table 2 (average)."""
    max_error = np.asarray(result["max"])
    average = _average(result, n)
    return np.concatenate(
        [
            np.log(max_error / PAPER_POSITION_MAX),
            weight * np.log(average / PAPER_POSITION_AVERAGE),
        ]
    )


def gear_ratios(joints) -> np.ndarray:
    """The gear ratio of each joint's actuator in the HRP-2 model (drake:gear_ratio)."""
    from pydrake.multibody.plant import MultibodyPlant

    plant = MultibodyPlant(0.0)
    hrp2.add_hrp2(plant)
    plant.Finalize()
    ratios = {}
    for index in plant.GetJointActuatorIndices():
        actuator = plant.get_joint_actuator(index)
        ratios[actuator.joint().name()] = actuator.default_gear_ratio()
    return np.array([ratios[j] for j in joints])


class _Fit:
    """The least squares of `run_calibration` over log(ω0) of the moving joints: its
    simulations (in `pool`, a point and its finite-difference neighbour at a time),
    their cache and history, the residuals and their (diagonal) Jacobian."""

    STEP = 0.04  # finite-difference step of log(ω0)

    def __init__(
        self, config: CalibrationConfig, work: Path, n: float, wall0: float, stream
    ):
        self.config, self.work, self.n = config, work, n
        self.wall0, self.stream = wall0, stream
        self.lo, self.hi = np.log(config.no_load_speed_bounds)
        self.prior = np.clip(
            np.log(config.motor_no_load_speed / gear_ratios(MOVING_JOINTS)),
            self.lo,
            self.hi,
        )
        self.history: list[Evaluation] = []
        self.cache: dict[tuple, dict] = {}
        self.pool = ProcessPoolExecutor(
            max_workers=config.jobs,
            mp_context=get_context("spawn"),
            initializer=console.start_worker,
            initargs=(console.program(), ""),
        )
        self.counter = iter(range(10**6))

    def submit(self, x: np.ndarray):
        speeds = dict(zip(MOVING_JOINTS, np.exp(x).tolist()))
        path = self.work / f"candidate_{next(self.counter)}.yaml"
        return self.pool.submit(_evaluate, (self.config, speeds, str(path), ()))

    def residuals(self, x: np.ndarray, result: dict) -> np.ndarray:
        r = _residuals(result, self.n, self.config.average_weight)
        return np.concatenate([r, self.config.prior_weight * (x - self.prior)])

    def record(self, x: np.ndarray, result: dict, kind: str = "iterate") -> np.ndarray:
        """The residuals of one simulation, added to the history and said."""
        r = self.residuals(x, result)
        self.history.append(
            Evaluation(
                np.exp(x).tolist(),
                list(result["max"]),
                _average(result, self.n).tolist(),
                float(0.5 * r @ r),
                kind,
            )
        )
        ratios = np.asarray(result["max"]) / PAPER_POSITION_MAX
        console.say(
            f"simulation {len(self.history):2d} "
            f"({time.perf_counter() - self.wall0:5.0f} s): ω0 "
            f"{np.array2string(np.exp(x), precision=2)} rad/s -> max error / paper "
            f"{np.array2string(ratios, precision=2)}, cost {0.5 * r @ r:.4f}",
            self.stream,
        )
        return r

    def perturbed(self, x: np.ndarray) -> np.ndarray:
        # Step into the bounds, away from the nearer one.
        return np.where(x + self.STEP <= self.hi, x + self.STEP, x - self.STEP)

    def fun(self, x: np.ndarray) -> np.ndarray:
        key = tuple(np.round(x, 12))
        if key not in self.cache:
            # The point and its finite-difference neighbour, in parallel: the
            # Jacobian is (nearly) diagonal, one joint's no-load speed moves its own
            # errors, so one extra simulation gives all of it.
            here, there = self.submit(x), self.submit(self.perturbed(x))
            self.cache[key] = {"here": here.result(), "there": there}
        return self.record(x, self.cache[key]["here"])

    def jac(self, x: np.ndarray) -> np.ndarray:
        key = tuple(np.round(x, 12))
        if key not in self.cache:
            self.fun(x)
        entry = self.cache[key]
        if "r_there" not in entry:
            entry["r_there"] = self.record(
                self.perturbed(x), entry["there"].result(), "finite difference"
            )
        r0 = self.residuals(x, entry["here"])
        dx = self.perturbed(x) - x
        m = len(MOVING_JOINTS)
        jacobian = np.zeros((3 * m, m))
        for j in range(m):
            for row in (j, m + j):
                jacobian[row, j] = (entry["r_there"][row] - r0[row]) / dx[j]
            jacobian[2 * m + j, j] = self.config.prior_weight
        return jacobian

    def solve(self):
        """scipy's least_squares from the prior (its OptimizeResult)."""
        from scipy.optimize import least_squares

        x0 = self.prior.copy()
        return least_squares(
            self.fun,
            x0,
            jac=self.jac,
            bounds=(np.full_like(x0, self.lo), np.full_like(x0, self.hi)),
            method="trf",
            x_scale=1.0,
            max_nfev=self.config.max_iterations,
            xtol=1e-3,
            ftol=1e-4,
        )


def run_calibration(
    config: CalibrationConfig, work: Path, stream=None
) -> CalibrationResult:
    """Fits the no-load speeds of the moving joints to the position-control column of
    Tables 2 and 3 (module docstring), then measures the calibrated servo, the `ideal`
    preset and each mechanism switched off on the same swing."""
    stream = stream or sys.stderr
    config.validate()
    work.mkdir(parents=True, exist_ok=True)
    wall0 = time.perf_counter()
    sample_count = paper_sample_count()
    n = sample_count["n"]
    console.say(
        f"Table 2's N = {n:.0f} samples (a {sample_count['log_duration']:.1f} s log "
        "at 1 kHz), derived from the paper's own tables",
        stream,
    )
    fit = _Fit(config, work, n, wall0, stream)
    try:
        solution = fit.solve()
        speeds = dict(zip(MOVING_JOINTS, np.exp(solution.x).tolist()))
        optimizer = {
            "method": "scipy.optimize.least_squares (trf, bounds, diagonal "
            "finite-difference Jacobian)",
            "status": int(solution.status),
            "message": str(solution.message),
            "function_evaluations": int(solution.nfev),
            "cost": float(solution.cost),
        }
        console.say(solution.message, stream)
        measured = _measure_all(config, speeds, work, fit.pool, stream)
    finally:
        fit.pool.shutdown()
    for path in work.glob("candidate_*.yaml"):
        path.unlink()
    final, ideal = measured["calibrated"], measured["ideal"]
    return CalibrationResult(
        speeds=speeds,
        sample_count=sample_count,
        history=fit.history,
        final=_errors(final, n) | {"signals": final.get("signals")},
        ideal=_errors(ideal, n) | {"signals": ideal.get("signals")},
        ablation={k: _errors(v, n) for k, v in measured.items() if k.endswith(" off")},
        optimizer=optimizer,
        wall_time=time.perf_counter() - wall0,
    )


def _measure_all(
    config: CalibrationConfig, speeds: dict[str, float], work: Path, pool, stream
) -> dict[str, dict]:
    """The calibrated servo (`speeds`, written to work/servo.yaml), the ideal preset
    and each mechanism off, in parallel in `pool`: `_measure` of each, by label."""
    from hrp2_drake.robot.servo import SERVO_MECHANISMS

    final_path = work / "servo.yaml"
    save_servo_params(build_servo(config, speeds), final_path, ["calibrated"])
    runs = {"calibrated": (str(final_path), ()), "ideal": ("ideal", ())}
    runs |= {f"{m} off": (str(final_path), (m,)) for m in SERVO_MECHANISMS}
    futures = {
        label: pool.submit(_measure, path, config.settle, off, config.end)
        for label, (path, off) in runs.items()
    }
    measured = {}
    for label, future in futures.items():
        measured[label] = future.result()
        console.say(f"measured {label}", stream)
    return measured


def _errors(result: dict, n: float) -> dict:
    """A measured run's maximum, Table 2 average (with the paper's N) and RMS errors
    (rad, per moving joint)."""
    return {
        "max": list(result["max"]),
        "average": _average(result, n).tolist(),
        "rms": list(result["rms"]),
    }


def _measure(path: str, settle: float, off: tuple, end: float) -> dict:
    """Process-pool worker: position-control errors plus the knee's error over time
    (for the report's plot)."""
    result = position_control_errors(path, settle, off, log=True, end=end)
    signals = result.pop("signals")
    j = hrp2.JOINT_NAMES.index("RLEG_JOINT3")
    out = {k: v.tolist() for k, v in result.items()}
    out["signals"] = {
        "t": signals["t"][::5].tolist(),
        "knee_error": (
            signals["q_ref"][::5, j] - signals["q_measured"][::5, j]
        ).tolist(),
    }
    return out


def _ratio_cell(sim: float, paper: float, scale: float, digits: int) -> str:
    return f"{sim * scale:.{digits}f} ({paper * scale:g}, {sim / paper:.2f}x)"


def write_calibration_report(
    result: CalibrationResult, config: CalibrationConfig, out: Path
) -> dict:
    """calibration.md, calibration.json and the plots, in `out`."""
    out.mkdir(parents=True, exist_ok=True)
    final_max = np.asarray(result.final["max"])
    final_avg = np.asarray(result.final["average"])
    within_max = np.abs(final_max / PAPER_POSITION_MAX - 1) <= 0.20
    within_avg = np.abs(final_avg / PAPER_POSITION_AVERAGE - 1) <= 0.30
    lines = _introduction(result, config)
    lines += [
        "## Fit per joint (position control, rad·10³: simulation (paper, ratio))",
        "",
    ]
    rows = [
        [
            label,
            _ratio_cell(final_max[j], PAPER_POSITION_MAX[j], 1e3, 2),
            "yes" if within_max[j] else "no",
            _ratio_cell(final_avg[j], PAPER_POSITION_AVERAGE[j], 1e3, 3),
            "yes" if within_avg[j] else "no",
            f"{result.speeds[MOVING_JOINTS[j]]:.2f}",
        ]
        for j, label in enumerate(MOVING_LABELS)
    ]
    header = [
        "joint",
        "max error (Table 3)",
        "within ±20%",
        "average error (Table 2, N above)",
        "within ±30%",
        "ω0 (rad/s)",
    ]
    lines += markdown_table(header, rows, align="lrcrcr")
    lines += ["", "## The calibrated servo, right leg", ""]
    lines += _servo_table(build_servo(config, result.speeds))
    lines += [
        "",
        "## What each mechanism changes (maximum error, rad·10³; paper in the header)",
        "",
    ]
    rows = [("calibrated", result.final), ("ideal preset (before)", result.ideal)]
    rows += list(result.ablation.items())
    lines += markdown_table(
        [
            "servo",
            *(f"{l} ({v * 1e3:g})" for l, v in zip(MOVING_LABELS, PAPER_POSITION_MAX)),
        ],
        [[label, *(f"{v * 1e3:.2f}" for v in values["max"])] for label, values in rows],
    )
    figures = plot_calibration(result, out)
    lines += ["", "## Figures", ""] + [f"![{f}]({f})" for f in figures] + [""]
    (out / "calibration.md").write_text("\n".join(lines))
    summary = {
        "no_load_speeds": result.speeds,
        "sample_count": result.sample_count,
        "max_error": result.final["max"],
        "average_error": result.final["average"],
        "paper_max_error": PAPER_POSITION_MAX.tolist(),
        "paper_average_error": PAPER_POSITION_AVERAGE.tolist(),
        "within_max_20": within_max.tolist(),
        "within_average_30": within_avg.tolist(),
        "ideal": {k: result.ideal[k] for k in ("max", "average")},
        "ablation": result.ablation,
        "optimizer": result.optimizer,
        "history": [asdict(e) for e in result.history],
        "wall_time": result.wall_time,
    }
    (out / "calibration.json").write_text(json.dumps(summary, indent=2))
    return summary


def _introduction(result: CalibrationResult, config: CalibrationConfig) -> list[str]:
    """The report's title, what was fitted to what, and Table 2's N."""
    n = result.sample_count["n"]
    return [
        "# Calibration of the emulated servo to the real HRP-2",
        "",
        "The servo's linear part is the paper's Table 1; its dead zone and Coulomb "
        "friction come from the authors' piecewise-linear fits on the real robot; the "
        "voltage limit (no-load speed ω0 of each moving joint) is fitted to the "
        "position-control column of Tables 2 and 3 (the hanging robot's own servo on "
        "the climbing swing). The torque-control columns, Figure 5 and Sec. 5.2 are "
        "not used: they stay predictions.",
        "",
        f"Optimizer: {result.optimizer['method']}; {result.optimizer['message']} "
        f"({len(result.history)} simulations of the 20 s swing, "
        f"{result.wall_time / 60:.1f} min with {config.jobs} processes).",
        "",
        "## Table 2's N",
        "",
        "Table 2 divides sqrt(Σ e²) by N, the number of samples of the paper's log, "
        "which the paper does not give. Where the error is velocity-proportional (Kv "
        "q̇, the joints below their speed limit) max|e| / sqrt(Σ e²) = max|q̇| / "
        "sqrt(Σ q̇²), so the paper's own ratio of Table 3 to Table 2 fixes N: "
        + ", ".join(
            f"{label} {v:.0f}"
            for label, v in zip(MOVING_LABELS, result.sample_count["per_joint"])
        )
        + f". The mean over {', '.join(result.sample_count['used'])} (the knee is at "
        f"its speed limit, its error is not velocity-proportional): **N = {n:.0f}**, a "
        f"{result.sample_count['log_duration']:.1f} s log at 1 kHz, about the moving "
        "part of the 19 s motion (1.1-14.9 s).",
        "",
    ]


def _servo_table(servo: ServoParams) -> list[str]:
    """The right leg's servo parameters, effective (identified) where it matters."""
    eff = effective_motor_parameters(servo, hrp2.RIGHT_LEG)
    p = servo.vectors(hrp2.RIGHT_LEG)
    rows = [
        [
            label,
            f"{eff['k_tau'][j] * 1e3:.3f}",
            f"{eff['k_v'][j] * 1e3:.3f}",
            f"{p['latency'][j] * 1e3:.0f}",
            f"{eff['deadzone'][j] * 1e3:.3f}",
            f"{p['k3'][j]:.2f}",
            f"{p['hysteresis_width'][j] * 1e3:.2f}",
            f"{p['stall_current'][j]:.0f}",
            f"{p['no_load_speed'][j]:.2f}",
        ]
        for j, label in enumerate(hrp2.RIGHT_LEG_LABELS)
    ]
    header = [
        "joint",
        "10³Kτ",
        "10³Kv (identified, incl. latency)",
        "latency (ms)",
        "dead zone (mrad, half)",
        "Coulomb (N·m)",
        "hysteresis (mrad)",
        "stall current (A)",
        "ω0 (rad/s)",
    ]
    return markdown_table(header, rows)


def plot_calibration(result: CalibrationResult, out: Path) -> list[str]:
    """Three figures in `out`: the fit's convergence, simulation against the paper
    before (the ideal preset) and after, the knee's error over time; their names."""
    names = [
        "calibration_history.png",
        "calibration_fit.png",
        "calibration_knee_error.png",
    ]
    for plot, name in zip((_plot_history, _plot_fit, _plot_knee_error), names):
        save_figure(plot(result), out / name, tight=True)
    return names


def _plot_history(result: CalibrationResult):
    """Convergence: each simulation's max-error ratios and cost."""
    fig, axes = pyplot().subplots(1, 2, figsize=(15, 4))
    ratios = np.array(
        [np.asarray(e.max_error) / PAPER_POSITION_MAX for e in result.history]
    )
    costs = np.array([e.cost for e in result.history])
    iterate = np.array([e.kind == "iterate" for e in result.history])
    index = np.arange(len(result.history))
    for j, label in enumerate(MOVING_LABELS):
        line = axes[0].plot(
            index[iterate], ratios[iterate, j], "o-", label=label, ms=3
        )[0]
        axes[0].plot(
            index[~iterate], ratios[~iterate, j], "x", color=line.get_color(), alpha=0.5
        )
    axes[0].axhspan(0.8, 1.2, color="g", alpha=0.1, label="±20%")
    axes[0].set_xlabel(
        "simulation (o: the optimizer's points, x: finite-difference steps)"
    )
    axes[0].set_ylabel("max error / paper (Table 3)")
    axes[0].set_yscale("log")
    legend_beside(axes[0])
    axes[1].semilogy(
        index[iterate], costs[iterate], "ko-", ms=3, label="optimizer's points"
    )
    axes[1].semilogy(
        index[~iterate],
        costs[~iterate],
        "kx",
        alpha=0.5,
        label="finite-difference steps",
    )
    legend_beside(axes[1])
    axes[1].set_xlabel("simulation")
    axes[1].set_ylabel("cost ½‖r‖² (log ratios)")
    for ax in axes:
        ax.grid(True, alpha=0.3)
    fig.suptitle("Calibration: least squares over the no-load speeds")
    return fig


def _plot_fit(result: CalibrationResult):
    """Simulation vs paper, before (the ideal preset) and after (calibrated)."""
    fig, axes = pyplot().subplots(1, 2, figsize=(12, 4))
    x = np.arange(len(MOVING_LABELS))
    for ax, key, paper, title in (
        (axes[0], "max", PAPER_POSITION_MAX, "Table 3: maximum error"),
        (axes[1], "average", PAPER_POSITION_AVERAGE, "Table 2: N⁻¹ sqrt(Σe²)"),
    ):
        ax.bar(x - 0.27, paper * 1e3, 0.27, label="paper (real HRP-2)", color="k")
        ax.bar(
            x,
            np.asarray(result.ideal[key]) * 1e3,
            0.27,
            label="ideal preset",
            color="0.6",
        )
        ax.bar(
            x + 0.27,
            np.asarray(result.final[key]) * 1e3,
            0.27,
            label="calibrated",
            color="C0",
        )
        ax.set_xticks(x, MOVING_LABELS)
        ax.set_ylabel("rad·10³")
        ax.set_title(title)
        ax.grid(True, axis="y", alpha=0.3)
    legend_beside(axes[1])
    fig.suptitle("Position control on the climbing swing")
    return fig


def _plot_knee_error(result: CalibrationResult):
    """The knee's error over time, the ideal preset and the calibrated servo."""
    fig, ax = pyplot().subplots(figsize=(12, 3.5))
    for label, run in (("ideal preset", result.ideal), ("calibrated", result.final)):
        s = run.get("signals")
        if s:
            ax.plot(s["t"], np.asarray(s["knee_error"]) * 1e3, lw=0.8, label=label)
    ax.axhline(
        PAPER_POSITION_MAX[2] * 1e3, color="k", ls="--", lw=0.8, label="paper's maximum"
    )
    ax.axhline(-PAPER_POSITION_MAX[2] * 1e3, color="k", ls="--", lw=0.8)
    ax.set_xlabel("t (s)")
    ax.set_ylabel("knee tracking error (mrad)")
    legend_beside(ax)
    ax.grid(True, alpha=0.3)
    return fig


def calibrate(
    config: CalibrationConfig, out: Path, install: bool = False, stream=None
) -> dict:
    """Runs the calibration, writes out/servo.yaml and the report; with `install`,
    also models/hrp2/servo.yaml (the simulated robot's servo)."""
    from hrp2_drake.paper.hrp2 import SERVO_FILE, models_dir

    stream = stream or sys.stderr
    result = run_calibration(config, out, stream)
    header = [
        (
            "Hidden parameters of the emulated HRP-2 position servo "
            "(docs/architecture.md), calibrated to"
        ),
        "the real robot by `hrp2-drake calibrate` (hrp2_drake/paper/calibrate.py):",
        (
            "Table 1 (linear part), the authors' piecewise-linear fits (dead zone, "
            "Coulomb),"
        ),
        "the position-control column of Tables 2 and 3 (no-load speeds). Sources and",
        "report: models/hrp2/README.md. Only hrp2_drake/robot/ reads this file.",
        "Units: k1 N m/A, k2 N m s/rad, k3 N m, k4 A/rad, k5 A s/rad, i_* and",
        "stall_current A, v_coulomb and no_load_speed rad/s, encoder_resolution and",
        "hysteresis_width rad, latency s.",
        "no_load_speed (rad/s) of the moving right-leg joints: "
        + ", ".join(f"{k} {v:.4g}" for k, v in result.speeds.items()),
    ]
    servo = build_servo(config, result.speeds)
    save_servo_params(servo, out / "servo.yaml", header)
    if install:
        save_servo_params(servo, models_dir() / SERVO_FILE, header)
        console.say(f"wrote {models_dir() / SERVO_FILE}", stream)
    summary = write_calibration_report(result, config, out)
    console.say(
        f"wrote {out / 'calibration.md'} ({result.wall_time / 60:.1f} min)", stream
    )
    return summary
