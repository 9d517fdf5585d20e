"""`hrp2-drake identify [--robot FILE]`: motor identification of a robot's controlled
joints (paper Sec. 3, 5.2; HRP-2's right leg by default).

Collects (or loads) an identification log, estimates q̇, q̈, τ̂ non-causally, runs every
fit of the paper per joint on training blocks, validates on held-out blocks, and writes
the Table 1 analogue, the validation table and Figures 1 and 3.
"""

import dataclasses
import functools
import json
import logging
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from hrp2_drake.estimation.estimator_config import estimator_config
from hrp2_drake.estimation.torque_estimator import FloatingBaseTorqueEstimator
from hrp2_drake.config import check_finite
from hrp2_drake.identification.dataset import (
    IdentificationData,
    LogSegment,
    check_log,
    estimate_segments,
    split_blocks,
)
from hrp2_drake.identification.excitation import (
    PHASE_HIGH_TORQUE,
    PHASE_TRANSITION,
    CollectionConfig,
    collect,
    load_log,
    make_plan,
    save_log,
)
from hrp2_drake.identification.fitting import (
    check_identified,
    fit_asymmetric,
    fit_least_squares,
    fit_piecewise_linear,
    fit_two_stage,
    overestimation_share,
)
from hrp2_drake.description import RobotDescription, load_robot_description
from hrp2_drake.tools.ground_truth import true_motor_model
from hrp2_drake.identification.logs import describe, read_robot_log
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.report import markdown_table, pyplot, save_figure
from hrp2_drake.robot.station import StationConfig, initial_joint_positions, make_station

_logger = logging.getLogger(__name__)

LINEAR_METHODS = ("asymmetric", "least_squares", "two_stage")
#: The fits `IdentifyConfig.fit` may pick for motor_model.yaml, and what each is for.
FITS = ("asymmetric", "least_squares", "coulomb", "two_stage")
FIT_PURPOSE = {
    "asymmetric": "conservative (rarely over-estimates |Δq|): for the torque controller's "
    "feedforward, as the paper uses it",
    "least_squares": "the smallest prediction error: for prediction, rollouts and simulation",
    "coulomb": "least squares with a Coulomb term Kc sign(q̇): prediction where dry "
    "friction shows",
    "two_stage": "Kτ from near-zero-velocity samples, then Kv (Sec. 3.3.1)",
}
#: Longest filter window or stride (s): a longer one is a sample count in an old config.
MAX_WINDOW = 2.0
#: Initial breakpoints (N·m) of the piecewise-linear fit: the paper's, then wider ones
#: (Sec. 3.2.3: "it requires the user to provide an initial guess").
PIECEWISE_INITIAL_BREAKPOINTS = ((-0.5, 0.5), (-2.0, 2.0), (-5.0, 5.0))


@dataclass
class IdentifyConfig:
    """Configuration of `hrp2-drake identify`.

    Args:
        station: the robot during data collection (the paper's: hanging).
        collection: pushes and sinusoids; empty sinusoids and push body: the robot
            description's `identification` (HRP-2: pushes on the right foot, one
            sinusoid per right-leg joint).
        duration_scale: shortens the default collection (1 = about 90 s of data).
        joints: the joints to identify; empty: the robot's controlled joints.
        window: Savitzky-Golay window of the non-causal estimates (s): the odd
            number of samples nearest to it at the log's rate (81 at 1 kHz).
        stride: keep one sample per `stride` seconds of the log.
        fit: the fit `motor_model.yaml` holds (`FITS`): "asymmetric" (eq. 8: rarely
            over-estimates |Δq|, conservative, what the paper's controller uses),
            "least_squares" (eq. 7: the smallest error, for prediction and
            simulation), "coulomb" (least squares with the Coulomb term), "two_stage"
            (Sec. 3.3.1).
        saturation_margin: a sample is left out of the fits where the servo's
            documented output (robot description's `position_loop`) exceeds this
            share of its limit anywhere in its filter window: in saturation Δq no
            longer sets the torque, and the driver's effective voltage already
            drops near full output.
        w: weight of over-estimation in the asymmetric penalty. The paper used 100;
            on our emulated servo (direction-dependent gain, dead zone) 100 leaves
            up to ~10% of held-out samples over-estimated by a hair (tenths of a
            mrad), 1000 keeps it under 5% at the same accuracy: the report's w sweep
            shows both.
        w_sweep: the weights of the sweep table (asymmetric fit only).
        zero_velocity_threshold: |q̇| below which a sample is static (rad/s),
            two-stage fit and Figure 1.
        held_out_block: length of the validation blocks (s).
        held_out_every: one block in `held_out_every` is held out for validation.
    """

    station: StationConfig = field(default_factory=lambda: StationConfig(scenario="hanging"))
    collection: CollectionConfig = field(default_factory=CollectionConfig)
    duration_scale: float = 1.0
    joints: list[str] = field(default_factory=list)
    window: float = 0.081
    stride: float = 0.005
    fit: str = "asymmetric"
    saturation_margin: float = 0.9
    w: float = 1000.0
    w_sweep: list[float] = field(default_factory=lambda: [1.0, 10.0, 100.0, 1000.0, 10000.0])
    zero_velocity_threshold: float = 0.05
    held_out_block: float = 1.0
    held_out_every: int = 3

    def validate(self) -> None:
        """Raises ValueError naming the bad field (yaml_load_typed does not call it)."""
        self.station.validate()
        self.collection.validate()
        robot = self.station.description()
        joints = self.identified_joints()
        if not joints:
            raise ValueError("IdentifyConfig.joints: no joint to identify")
        unknown = [j for j in joints if j not in robot.joints]
        if unknown:
            raise ValueError(f"IdentifyConfig.joints: unknown joints {unknown}")
        if len(set(self.joints)) != len(self.joints):
            raise ValueError(
                f"IdentifyConfig.joints: duplicated joints in {self.joints}"
            )
        for name, longest in (("window", MAX_WINDOW), ("stride", MAX_WINDOW)):
            value = getattr(self, name)
            check_finite(value, f"IdentifyConfig.{name}", 0.0)
            if value > longest:
                raise ValueError(
                    f"IdentifyConfig.{name}: {value:g} s, longer than {longest:g} s: "
                    f"{name}s are in seconds (81 samples at 1 kHz: 0.081)"
                )
        if self.fit not in FITS:
            raise ValueError(f"IdentifyConfig.fit: '{self.fit}', expected one of {FITS}")
        check_finite(self.saturation_margin, "IdentifyConfig.saturation_margin", 0.0)
        if self.held_out_every < 2:
            raise ValueError(
                f"IdentifyConfig.held_out_every must be >= 2, got {self.held_out_every}"
            )
        for name in ("duration_scale", "zero_velocity_threshold", "held_out_block"):
            check_finite(getattr(self, name), f"IdentifyConfig.{name}", 0.0)
        check_finite(self.w, "IdentifyConfig.w", 1.0, strict=False)
        if not self.w_sweep:
            raise ValueError(
                "IdentifyConfig.w_sweep: empty, expected some weights >= 1"
            )
        for k, w in enumerate(self.w_sweep):
            check_finite(w, f"IdentifyConfig.w_sweep[{k}]", 1.0, strict=False)

    def identified_joints(self) -> list[str]:
        """`joints`, or the robot's controlled joints if empty."""
        return list(self.joints or self.station.description().controlled_joints)

    def collection_or_default(self) -> CollectionConfig:
        if self.collection.sinusoids or self.collection.pushes.body:
            return self.collection
        return self.station.description().identification.scaled(
            self.duration_scale, self.station.sensors_config().seed
        )


@dataclass
class JointResult:
    """Identification of one joint: every fit, validated on held-out samples."""

    joint: str
    models: dict[str, MotorModel]
    piecewise: object | None
    validation: dict[str, dict[str, float]]  # method -> {"rms", "overestimation"}
    samples: dict[str, int]
    w_sweep: dict[float, dict[str, float]]  # w -> k_tau, k_v, rms, overestimation
    #: per gain (logs of several gains): method -> {"k_tau", "k_v", "k_c"} times gain
    per_gain: dict[float, dict[str, dict[str, float]]] = field(default_factory=dict)
    piecewise_note: str = ""  # how the piecewise-linear fit went (report)


@dataclass
class IdentificationResult:
    joints: list[JointResult]
    data: IdentificationData
    held_out: np.ndarray
    train: np.ndarray
    config: IdentifyConfig
    identified: MotorModel  # the fit of config.fit: what motor_model.yaml holds
    estimation_rms: np.ndarray | None = None  # τ̂ vs truth (N·m), if the log has truth
    estimation_peak: np.ndarray | None = None
    #: the servo gain the models hold at (logs that state one), else 0
    gain: float = 0.0
    #: samples left out: servo off or filter edges, output saturated
    excluded: dict[str, int] = field(default_factory=dict)
    logs: list[dict] = field(default_factory=list)  # one row per log (real logs)


def collect_log(config: IdentifyConfig, progress: bool = True) -> tuple[dict, list[str]]:
    """Runs the data collection on the simulated robot."""
    robot = config.station.description()
    station = make_station(config.station)
    plant = station.GetSubsystemByName("plant")
    collection = config.collection_or_default()
    if collection.is_empty():
        raise ValueError(
            f"IdentifyConfig.collection: empty, and robot '{robot.name}' describes no "
            "identification excitation"
        )
    plan = make_plan(collection, robot.joints, initial_joint_positions(config.station))
    body = plant.GetBodyByName(collection.pushes.body).index() if collection.pushes.body else None
    log = collect(station, plan, body, collection.pushes.point, progress=progress)
    return log, list(robot.joints)


def identify(
    config: IdentifyConfig, log: dict, log_joint_names: list[str]
) -> IdentificationResult:
    """`identify_segments` of one log."""
    return identify_segments(config, [LogSegment(log, list(log_joint_names))])


def identify_segments(
    config: IdentifyConfig, segments: Sequence[LogSegment]
) -> IdentificationResult:
    """Non-causal estimation of each log, then every fit per joint on the pooled
    training samples, validated on held-out blocks of every log.

    Logs that state the servo's gain pool into one gain-aware model: each sample's Δq
    is brought to the reference gain (the smallest of the logs) by Δq · gain /
    reference (a P-controlled servo's output is gain · Δq), and the models hold at that
    gain (`MotorModel.gain`). Samples where the servo is off, or its output near its
    documented limit, are left out.
    """
    config.validate()
    check_segments(config, segments)
    _logger.info("estimating and fitting ...")
    robot = config.station.description()
    gains = [s.gain for s in segments]
    reference = min(gains) if gains[0] is not None else 0.0
    estimator = FloatingBaseTorqueEstimator(robot.make_plant(), estimator_config(robot))
    data = estimate_segments(
        segments, estimator, config.window, config.stride,
        robot.position_loop.saturation_error, config.saturation_margin,
    )
    if reference:
        data.delta_q = data.delta_q * (data.gain / reference)[:, None]
    held = np.zeros(len(data.t), bool)
    for k in range(len(segments)):
        rows = data.segment == k
        held[rows] = split_blocks(data.t[rows], config.held_out_block, config.held_out_every)
    usable = data.usable & (data.phase != PHASE_TRANSITION)
    columns = {name: i for i, name in enumerate(estimator.config().joints)}
    results = [
        _identify_joint(config, data, usable & ~data.saturated[:, columns[name]], held,
                        columns[name], name, reference)
        for name in config.identified_joints()
    ]
    chosen = MotorModel.from_joints({r.joint: r.models[config.fit] for r in results})
    rms = peak = None
    if data.tau_true is not None:
        err = data.tau[data.usable] - data.tau_true[data.usable]
        rms = np.sqrt(np.mean(err**2, axis=0))
        peak = np.abs(data.tau_true[data.usable]).max(axis=0)
    excluded = {
        "servo off or filter edges": int(np.count_nonzero(~data.usable)),
        "output saturated": int(np.count_nonzero(data.usable & data.saturated.any(axis=1))),
    }
    train = usable & ~held & ~data.saturated.any(axis=1)  # of every joint
    return IdentificationResult(
        results, data, held, train, config, chosen, rms, peak, reference, excluded
    )


def check_segments(config: IdentifyConfig, segments: Sequence[LogSegment]) -> None:
    """Raises ValueError naming the log that cannot join the identification: one that
    states no servo gain among logs that do (pooling needs each gain), or one with a
    gap between samples longer than the filter window."""
    gains = [s.gain for s in segments]
    if len(set(gains)) > 1 and None in gains:
        missing = segments[gains.index(None)].source
        raise ValueError(
            f"{missing}: states no servo gain (the robot description's logs.gain), "
            "but pooling it with logs of other gains needs each log's gain"
        )
    for segment in segments:
        gap, where = segment.longest_gap
        if gap > config.window:
            raise ValueError(
                f"{segment.source}: a gap of {gap:.3g} s between samples at t = "
                f"{where:.3f} s, longer than the filter window {config.window:g} s "
                "(IdentifyConfig.window): split the log there or widen the window"
            )


def _identify_joint(
    config: IdentifyConfig,
    data: IdentificationData,
    usable: np.ndarray,
    held: np.ndarray,
    j: int,
    name: str,
    gain: float,
) -> JointResult:
    """Every fit of one joint on its training samples, validated on held-out ones."""
    train, test = usable & ~held, usable & held
    if not np.any(train):
        raise ValueError(
            f"joint {name!r}: no sample to identify from: every sample has the servo "
            "off, its output saturated, or lies within a filter window of a log's edge"
        )
    tau, dq, dlt = data.joint(j, train)
    models = _fits(config, tau, dq, dlt, name, gain)
    # Refuse data that identify no motor (noise, too little excitation): the
    # two models the controller and a prediction read must be positive and explain
    # the data.
    check_identified(models["least_squares"], tau, dq, dlt)
    check_identified(models["asymmetric"], tau, dq, dlt, min_explained=None)
    # The piecewise-linear model of Sec. 3.2 has no velocity term: the paper fitted
    # it to the static high-torque data (Fig. 1), and so do we (an unlabelled log:
    # its near-zero-velocity samples).
    labelled = bool(np.any(data.phase >= 0))
    static = np.abs(data.dq[:, j]) < config.zero_velocity_threshold
    pushes = train & (data.phase == PHASE_HIGH_TORQUE if labelled else static)
    piecewise, piecewise_note = _fit_piecewise(data.joint(j, pushes), name)
    tau_h, dq_h, dlt_h = data.joint(j, test)
    validation = {}
    static_h = test & (data.phase == PHASE_HIGH_TORQUE if labelled else static)
    for method, fitted in list(models.items()) + [("piecewise_linear", piecewise)]:
        samples = data.joint(j, static_h) if method == "piecewise_linear" else (tau_h, dq_h, dlt_h)
        if fitted is None or samples[0].size == 0:
            continue
        residual = fitted.predict(*samples[:2]) - samples[2]
        validation[method] = {
            "rms": float(np.sqrt(np.mean(residual**2))),
            "overestimation": overestimation_share(fitted, *samples),
        }
    sweep = {}
    for w in config.w_sweep:
        fitted = fit_asymmetric(tau, dq, dlt, w, joint_name=name)
        sweep[w] = {
            "k_tau": float(fitted.k_tau[0]),
            "k_v": float(fitted.k_v[0]),
            "rms": _rms(fitted, tau_h, dq_h, dlt_h),
            "overestimation": overestimation_share(fitted, tau_h, dq_h, dlt_h),
        }
    per_gain = {}
    log_gains = np.unique(data.gain[train]) if gain else []
    for g in log_gains if len(log_gains) > 1 else []:
        rows = train & (data.gain == g)
        tau_g, dq_g, dlt_g = data.joint(j, rows)
        fitted = _fits(config, tau_g, dq_g, dlt_g * gain / g, name, g)
        per_gain[float(g)] = {
            m: {p: float(getattr(f, p)[0] * g) for p in ("k_tau", "k_v", "k_c")}
            for m, f in fitted.items()
        }
    samples = {"train": int(train.sum()), "held_out": int(test.sum())}
    return JointResult(
        name, models, piecewise, validation, samples, sweep, per_gain, piecewise_note
    )


def _fits(config, tau, dq, dlt, name: str, gain: float) -> dict[str, MotorModel]:
    """Every linear fit of `FITS`, each model holding at `gain` and naming its fit."""
    models = {
        "least_squares": fit_least_squares(tau, dq, dlt, joint_name=name),
        "asymmetric": fit_asymmetric(tau, dq, dlt, config.w, joint_name=name),
        "coulomb": fit_least_squares(tau, dq, dlt, coulomb=True, joint_name=name),
        "two_stage": fit_two_stage(
            tau, dq, dlt, config.zero_velocity_threshold, config.w, joint_name=name
        ),
    }
    return {
        method: dataclasses.replace(model, gain=float(gain), fit=method)
        for method, model in models.items()
    }


def _rms(model: MotorModel, tau, dq, dlt) -> float:
    return float(np.sqrt(np.mean((model.predict(tau, dq) - dlt) ** 2))) if tau.size else math.nan


def _fit_piecewise(samples, name: str):
    """The piecewise-linear fit from the first initial guess that works, and a note
    for the report (why there is none, or which guesses failed first).

    The piecewise-linear model is the one the paper tried and abandoned (Sec. 3.2),
    fitted for comparison only; its algorithm needs a good initial guess (the
    paper's words): the paper's breakpoints in N·m, then ones at 10% and 30% of the
    joint's peak static torque (a small servo). A guess that fails is expected, not an
    error: the report says so, the console only in debug."""
    tau = samples[0]
    peak = float(np.percentile(np.abs(tau), 95)) if tau.size else 0.0
    guesses = PIECEWISE_INITIAL_BREAKPOINTS + tuple(
        (-f * peak, f * peak) for f in (0.1, 0.3) if f * peak < PIECEWISE_INITIAL_BREAKPOINTS[0][1]
    )
    failed = []
    for guess in guesses:
        try:
            fitted = fit_piecewise_linear(*samples, initial_breakpoints=guess, joint_name=name)
        except ValueError as error:
            failed.append((guess, _reason(error)))
            continue
        note = f"from {_breakpoints(guess)} N·m" + (f"; {_failures(failed)}" if failed else "")
        _logger.debug("%s: piecewise-linear model (for comparison only) %s", name, note)
        return fitted, note
    note = f"not fitted: {_failures(failed)}"
    _logger.debug("%s: piecewise-linear model (for comparison only) %s", name, note)
    return None, note


def _reason(error: ValueError) -> str:
    """Why a piecewise-linear fit failed, short: "the lines no longer intersect in
    order" (no joint, branch, breakpoints, iteration nor advice)."""
    text = str(error).split(";")[0].rsplit(": ", 1)[-1]
    return re.sub(r" \(breakpoints \[[^\]]*\] at iteration \d+\)", "", text)


def _breakpoints(guess: tuple[float, float]) -> str:
    return f"({guess[0]:g}, {guess[1]:g})"


def _failures(failed: list[tuple[tuple[float, float], str]]) -> str:
    """"from (-0.5, 0.5) and (-2, 2) it did not converge (<reasons>)"."""
    guesses = " and ".join(_breakpoints(g) for g, _ in failed)
    reasons = "; ".join(dict.fromkeys(why for _, why in failed))
    return f"from {guesses} it did not converge ({reasons})"


# ------------------------------------------------------------------------- report
def write_report(result: IdentificationResult, out: Path, log_is_simulated: bool) -> dict:
    """Writes identification.md, identification.json, motor_model.yaml (the fit of
    `IdentifyConfig.fit`), motor_model_<fit>.yaml for every fit, and the figures;
    returns the results as a dict."""
    out.mkdir(parents=True, exist_ok=True)
    robot = result.config.station.description()
    joints = result.config.identified_joints()
    truth = (
        true_motor_model(robot, joints, servo_file=result.config.station.servo_file)
        if log_is_simulated
        else None
    )
    rows = {}
    for k, r in enumerate(result.joints):
        row = {m: {"k_tau": float(r.models[m].k_tau[0]), "k_v": float(r.models[m].k_v[0]),
                   "k_c": float(r.models[m].k_c[0])}
               for m in FITS}
        row["validation"] = r.validation
        row["samples"] = r.samples
        row["w_sweep"] = {f"{w:g}": v for w, v in r.w_sweep.items()}
        if r.per_gain:
            row["per_gain"] = {f"{g:g}": v for g, v in r.per_gain.items()}
        if r.joint in robot.published_motor_model:  # [10³ Kτ, 10³ Kv]
            k_tau, k_v = robot.published_motor_model[r.joint]
            row["paper"] = {"k_tau": k_tau * 1e-3, "k_v": k_v * 1e-3}
        if truth is not None:
            row["emulator"] = {"k_tau": float(truth.k_tau[k]), "k_v": float(truth.k_v[k])}
            row["relative_error_asymmetric"] = {
                p: row["asymmetric"][p] / row["emulator"][p] - 1 for p in ("k_tau", "k_v")
            }
        rows[r.joint] = row
    summary = {"joints": rows, "fit": result.config.fit, "gain": result.gain,
               "excluded_samples": result.excluded}
    if result.logs:
        summary["logs"] = result.logs
    if result.estimation_rms is not None:
        cols = [robot.joints.index(j) for j in joints]
        summary["torque_estimation"] = {
            j: {"rms": float(result.estimation_rms[c]), "peak": float(result.estimation_peak[c])}
            for j, c in zip(joints, cols)
        }
    (out / "identification.json").write_text(json.dumps(summary, indent=2))
    result.identified.save(out / "motor_model.yaml")
    for method in FITS:
        MotorModel.from_joints(
            {r.joint: r.models[method] for r in result.joints}
        ).save(out / f"motor_model_{method}.yaml")
    figures = plot_figures(result, out)
    (out / "identification.md").write_text(_markdown(result, summary, figures))
    return summary


def _label(joint: str, robot: RobotDescription | None = None) -> str:
    robot = robot or load_robot_description()
    if joint in robot.controlled_joints:
        return robot.labels()[robot.controlled_joints.index(joint)]
    return joint


def _markdown(result: IdentificationResult, summary: dict, figures: list[str]) -> str:
    config = result.config
    robot = config.station.description()
    label = functools.partial(_label, robot=robot)
    joints = summary["joints"]
    at_gain = f" at servo gain {result.gain:g}" if result.gain else ""
    lines = [
        f"# Motor identification of {robot.name} (paper Sec. 3, Table 1, Figures 1 and 3)",
        "",
        f"Samples: {int(result.train.sum())} training, "
        f"{int((~result.train & result.held_out).sum())} held out "
        f"(one {config.held_out_block:g} s block in {config.held_out_every}), window "
        f"{config.window * 1e3:g} ms, w = {config.w:g}. Left out: "
        + ", ".join(f"{n} {what}" for what, n in result.excluded.items()) + ".",
        "",
        f"`motor_model.yaml` holds the **{config.fit.replace('_', ' ')}** fit{at_gain}; "
        "every fit is also written as `motor_model_<fit>.yaml`. What each is for:",
        "",
        *(f"- {m.replace('_', ' ')}: {FIT_PURPOSE[m]}." for m in FITS),
    ]
    if result.logs:
        lines += ["", "## Logs", "", *markdown_table(
            ["log", "raw rate (Hz)", "duration (s)", "gain", "servo on", "longest gap (ms)"],
            [[r["log"], f"{r['raw_rate_hz']:g}", f"{r['duration_s']:g}",
              "–" if r["gain"] is None else f"{r['gain']:g}",
              f"{r['valid_share'] * 100:.0f}%", f"{r['longest_gap_s'] * 1e3:.1f}"]
             for r in result.logs])]
    lines += _parameter_table(result, joints, label)
    lines += _gain_table(result, joints, label)
    lines += [
        "",
        "## Validation on held-out samples",
        "",
        "RMS of Δq̂ − Δq (mrad) / share of samples where |Δq| is over-estimated.",
        "",
    ]
    methods = FITS + ("piecewise_linear",)
    header = ["joint", *(m.replace("_", " ") for m in methods[:-1]),
              "piecewise-linear (static samples only)"]
    lines += markdown_table(
        header,
        [[label(joint)] + [
            f"{v['rms'] * 1e3:.3f} / {v['overestimation'] * 100:.1f}%" if v else "not fitted"
            for v in (row["validation"].get(m) for m in methods)
        ] for joint, row in joints.items()],
        align="l" * len(header),
    )
    notes = [f"- {label(r.joint)}: {r.piecewise_note}" for r in result.joints if r.piecewise_note]
    if notes:
        lines += ["", "The piecewise-linear model (Sec. 3.2, abandoned by the paper; for "
                  "comparison only) needs an initial guess of its breakpoints:", "", *notes]
    lines += _sweep_table(result, joints, label)
    if "torque_estimation" in summary:
        lines += ["", "## Non-causal torque estimate vs ground truth", "", *markdown_table(
            ["joint", "RMS error (N·m)", "peak |τ| (N·m)", "RMS / peak"],
            [[label(j), f"{v['rms']:.3f}", f"{v['peak']:.1f}", f"{v['rms'] / v['peak'] * 100:.2f}%"]
             for j, v in summary["torque_estimation"].items()])]
    lines += ["", "## Figures", ""] + [f"![{f}]({f})" for f in figures]
    return "\n".join(lines) + "\n"


def _parameter_table(result, joints: dict, label) -> list[str]:
    """Table 1: every fit's parameters; the emulator's and the paper's columns only
    where there is something to compare."""
    truth = truth_in({"joints": joints})
    paper = any("paper" in row for row in joints.values())
    scale = f" (servo gain {result.gain:g})" if result.gain else ""
    header = ["joint"]
    for m in FITS:
        header += [f"{m.replace('_', ' ')} Kτ", "Kv"] + (["Kc"] if m == "coulomb" else [])
    header += ["emulator Kτ", "Kv", "error Kτ, Kv (asym.)"] if truth else []
    header += ["paper Kτ", "Kv"] if paper else []
    rows = []
    for joint, row in joints.items():
        cells = [label(joint)]
        for m in FITS:
            cells += [f"{row[m]['k_tau'] * 1e3:.4f}", f"{row[m]['k_v'] * 1e3:.3f}"]
            cells += [f"{row[m]['k_c'] * 1e3:.3f}"] if m == "coulomb" else []
        if truth:
            e = row.get("relative_error_asymmetric")
            cells += [f"{row['emulator']['k_tau'] * 1e3:.4f}", f"{row['emulator']['k_v'] * 1e3:.3f}",
                      f"{e['k_tau'] * 100:+.1f}%, {e['k_v'] * 100:+.1f}%"] if e else ["–"] * 3
        if paper:
            p = row.get("paper")
            cells += [f"{p['k_tau'] * 1e3:.3f}", f"{p['k_v'] * 1e3:.3f}"] if p else ["–", "–"]
        rows.append(cells)
    return ["", f"## Table 1: identified motor parameters{scale} (10³ Kτ in rad/(N·m), "
            "10³ Kv in s, 10³ Kc in rad)", "", *markdown_table(header, rows)]


def _gain_table(result, joints: dict, label) -> list[str]:
    """Gain consistency: each fit's Kτ·gain and Kv·gain fitted on each gain's logs
    alone, and their spread (max / min; 1 for a servo whose output is gain · Δq)."""
    if not any("per_gain" in row for row in joints.values()):
        return []
    lines = ["", "## Gain consistency", "",
             "Each fit on the logs of one servo gain at a time: Kτ·gain (rad/(N·m) · gain) "
             "and Kv·gain (s · gain), and their spread (max/min) across the gains. A "
             "P-controlled servo's output is gain · Δq, so a spread of 1 means the model "
             "transfers from one gain to another; the pooled model above assumes it.", ""]
    for joint, row in joints.items():
        gains = list(row.get("per_gain", {}))
        if not gains:
            continue
        body = []
        for m in FITS:
            per = [row["per_gain"][g][m] for g in gains]
            cells = [m.replace("_", " ")]
            for p in ("k_tau", "k_v"):
                values = [v[p] for v in per]
                cells += [f"{v:.4g}" for v in values]
                cells.append(f"{max(values) / min(values):.3f}" if min(values) > 0 else "–")
            body.append(cells)
        header = (["fit (" + label(joint) + ")"] + [f"Kτ·gain at {g}" for g in gains]
                  + ["Kτ spread"] + [f"Kv·gain at {g}" for g in gains] + ["Kv spread"])
        lines += markdown_table(header, body) + [""]
    return lines[:-1]


def _sweep_table(result, joints: dict, label) -> list[str]:
    config = result.config
    lines = [
        "",
        "## The asymmetric penalty's weight w",
        "",
        "Held-out share of over-estimated |Δq|"
        + (" / error of Kτ, Kv against the emulator" if truth_in({"joints": joints}) else "")
        + " (the paper used w = 100).",
        "",
    ]
    rows = []
    for joint, row in joints.items():
        cells = [label(joint)]
        for v in row["w_sweep"].values():
            cell = f"{v['overestimation'] * 100:.1f}%"
            if "emulator" in row:
                e = row["emulator"]
                cell += f" / {(v['k_tau'] / e['k_tau'] - 1) * 100:+.1f}%, {(v['k_v'] / e['k_v'] - 1) * 100:+.1f}%"
            cells.append(cell)
        rows.append(cells)
    header = ["joint"] + [f"w = {w:g}" for w in config.w_sweep]
    return lines + markdown_table(header, rows, align="l" * len(header))


def truth_in(summary: dict) -> bool:
    return any("emulator" in row for row in summary["joints"].values())


#: The joints of the paper's Figures 1 (knee, hip pitch) and 3 (ankle pitch, hip roll).
FIGURE1_JOINTS = ("RLEG_JOINT3", "RLEG_JOINT2")
FIGURE3_JOINTS = ("RLEG_JOINT4", "RLEG_JOINT1")


def _figure_joints(identified: Sequence[str], paper: Sequence[str]) -> list[str]:
    """The paper's joints of a figure if they were identified, else the robot's first
    two identified joints."""
    return [j for j in paper if j in identified] or list(identified)[:2]


def plot_figures(result: IdentificationResult, out: Path) -> list[str]:
    """Figure 1 (τ vs Δq at near-zero velocity with the fits; HRP-2: knee and hip
    pitch) and Figure 3 (friction part vs q̇, symmetric vs asymmetric; HRP-2: ankle
    pitch and hip roll); another robot: its first two identified joints."""
    by_joint = {r.joint: r for r in result.joints}
    robot = result.config.station.description()
    names = []
    for name, paper_joints, plot in (
        ("figure1_torque_vs_delta_q.png", FIGURE1_JOINTS, _plot_figure1),
        ("figure3_friction_fit.png", FIGURE3_JOINTS, _plot_figure3),
    ):
        joints = _figure_joints(by_joint, paper_joints)
        if joints:
            save_figure(plot(result, joints, robot), out / name, tight=True)
            names.append(name)
    return names


def _plot_figure1(result: IdentificationResult, joints: list[str], robot: RobotDescription):
    """Figure 1 of `joints`: τ̂ vs Δq at near-zero velocity, the data and the fits."""
    data, cfg = result.data, result.config
    by_joint = {r.joint: r for r in result.joints}
    column = {name: i for i, name in enumerate(robot.joints)}
    fig, axes = pyplot().subplots(1, len(joints), figsize=(6 * len(joints), 4.5), squeeze=False)
    for ax, joint in zip(axes[0], joints):
        r, j = by_joint[joint], column[joint]
        static = result.train & (np.abs(data.dq[:, j]) < cfg.zero_velocity_threshold)
        tau, dq, dlt = data.joint(j, static)
        ax.scatter(tau[dq > 0], dlt[dq > 0] * 1e3, s=2, alpha=0.4, label="data, q̇ > 0")
        ax.scatter(tau[dq < 0], dlt[dq < 0] * 1e3, s=2, alpha=0.4, label="data, q̇ < 0")
        grid = np.linspace(tau.min(), tau.max(), 200)
        for method, style in (("least_squares", "k--"), ("asymmetric", "b-")):
            k = r.models[method].k_tau[0]
            ax.plot(grid, k * grid * 1e3, style, label=f"{method.replace('_', ' ')}: Δq = Kτ τ")
        if r.piecewise is not None:
            ax.plot(grid, r.piecewise.positive(grid) * 1e3, "g:", label="piecewise, q̇ > 0")
            ax.plot(grid, r.piecewise.negative(grid) * 1e3, "m:", label="piecewise, q̇ < 0")
        ax.set_xlabel("τ̂ (N·m)")
        ax.set_ylabel("Δq (mrad)")
        ax.set_title(f"{_label(joint, robot)}, |q̇| < {cfg.zero_velocity_threshold} rad/s")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle("Figure 1: torque vs position error at near-zero velocity")
    return fig


def _plot_figure3(result: IdentificationResult, joints: list[str], robot: RobotDescription):
    """Figure 3 of `joints`: the friction part of the model vs q̇, symmetric (least
    squares) beside asymmetric."""
    data, cfg = result.data, result.config
    by_joint = {r.joint: r for r in result.joints}
    column = {name: i for i, name in enumerate(robot.joints)}
    fig, axes = pyplot().subplots(len(joints), 2, figsize=(11, 4 * len(joints)), squeeze=False)
    for row, joint in zip(axes, joints):
        r, j = by_joint[joint], column[joint]
        tau, dq, dlt = data.joint(j, result.train)
        for ax, method in zip(row, ("least_squares", "asymmetric")):
            fitted = r.models[method]
            friction = dlt - fitted.k_tau[0] * tau
            ax.scatter(dq, friction * 1e3, s=2, alpha=0.3, color="tab:red", label="data")
            grid = np.linspace(dq.min(), dq.max(), 100)
            kv = fitted.k_v[0]
            ax.plot(grid, kv * grid * 1e3, "b-", label=f"Kv q̇, Kv = {kv * 1e3:.2f}e-3")
            share = overestimation_share(fitted, tau, dq, dlt)
            kind = "symmetric, eq. 7" if method == "least_squares" else f"asymmetric, w={cfg.w:g}"
            ax.set_title(
                f"{_label(joint, robot)}, {kind}: over-estimates {share * 100:.1f}%",
                fontsize=10,
            )
            ax.set_xlabel("q̇ (rad/s)")
            ax.set_ylabel("Δq − Kτ τ̂ (mrad)")
            ax.grid(True, alpha=0.3)
            ax.legend(fontsize=8)
    fig.suptitle("Figure 3: friction part of the model vs velocity")
    return fig


def run_identify(
    config: IdentifyConfig, out: Path, log_paths: Sequence[Path] | Path | None = None
) -> dict:
    """The whole `hrp2-drake identify`: collect (or load the logs), identify, report."""
    config.validate()
    out.mkdir(parents=True, exist_ok=True)
    if isinstance(log_paths, (str, Path)):
        log_paths = [Path(log_paths)]
    if not log_paths:
        log, names = collect_log(config)
        save_log(out / "identification_log.npz", log, names)
        # The simulated servo ran at the station's gain: the model holds at it.
        gain = config.station.servo_gain_in_use()
        segments = [LogSegment(log, names, gain, source="the collected log")]
        simulated, rows = True, []
    else:
        segments, rows = read_segments(log_paths, config.station.description())
        simulated = all("joint_torque_true" in s.log for s in segments)
    try:
        result = identify_segments(config, segments)
    except (ValueError, KeyError) as error:
        if not log_paths:
            raise
        message = error.args[0] if isinstance(error, KeyError) and error.args else str(error)
        where = "" if any(message.startswith(str(p)) for p in log_paths) else f"{log_paths[0]}: "
        raise ValueError(f"{where}{message}; no motor model written") from error
    result.logs = rows
    return write_report(result, out, simulated)


def read_segments(
    paths: Sequence[Path], robot: RobotDescription
) -> tuple[list[LogSegment], list[dict]]:
    """Each log file as one segment: this project's .npz logs as they are (`read_log`),
    any other through the robot description's log format (`logs.read_robot_log`:
    resampled to its grid). Also one report row per log that was resampled."""
    segments, rows = [], []
    for path in paths:
        path = Path(path)
        if path.suffix.lower() == ".npz" or robot.logs.format == "npz":
            log, names = read_log(path, robot)
            gain = log.pop("gain", None)
            segments.append(LogSegment(
                log, names, float(np.ravel(gain)[0]) if gain is not None else None, str(path)
            ))
            continue
        robot_log = read_robot_log(path, robot.logs, robot.joints)
        segments.append(LogSegment(
            robot_log.arrays(), robot_log.joint_names, robot_log.gain, str(path),
            robot_log.longest_gap,
        ))
        rows += describe([robot_log])
    return segments, rows


def read_log(
    path: str | Path, robot: RobotDescription | None = None
) -> tuple[dict, list[str]]:
    """`load_log` with every problem of the file as one error naming it (missing, a
    folder, not a readable .npz archive: `dataset.read_npz`; a missing or misshapen
    array), then `check_log`: text or NaN in an array, time not increasing on a
    constant grid, arrays of the wrong width, no column for a joint of the estimator."""
    log, names = load_log(path)
    check_log(log, names, str(path), (robot or load_robot_description()).joints)
    return log, names
