"""`hrp2-drake identify [--robot FILE]`: motor identification of a robot's controlled
joints (paper Sec. 3, 5.2; HRP-2's right leg by default).

Collects (or loads) an identification log, estimates q̇, q̈, τ̂ non-causally, runs every
fit of the paper per joint on training blocks, validates on held-out blocks, and writes
the Table 1 analogue, the validation table and Figures 1 and 3.
"""

import json
import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hrp2_drake.estimation.torque_estimator import FloatingBaseTorqueEstimator
from hrp2_drake.config import check_finite
from hrp2_drake.identification.dataset import (
    IdentificationData,
    check_log,
    noncausal_estimates,
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
from hrp2_drake.description import RobotDescription
from hrp2_drake.experiments.ground_truth import true_motor_model
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.robot import model
from hrp2_drake.robot.station import StationConfig, initial_joint_positions, make_station

_logger = logging.getLogger(__name__)

#: The paper's Table 1 (10³ Kτ, 10³ Kv), right leg.
PAPER_TABLE1 = {
    "RLEG_JOINT0": (0.212, 13.0),
    "RLEG_JOINT1": (0.030, 6.332),
    "RLEG_JOINT2": (0.12, 7.0),
    "RLEG_JOINT3": (0.051, 6.561),
    "RLEG_JOINT4": (0.177, 7.698),
    "RLEG_JOINT5": (0.240, 6.0),
}
LINEAR_METHODS = ("asymmetric", "least_squares", "two_stage")
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
        window: Savitzky-Golay window of the non-causal estimates (odd).
        stride: keep every stride-th sample of the log.
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
    window: int = 81
    stride: int = 5
    w: float = 1000.0
    w_sweep: list[float] = field(default_factory=lambda: [1.0, 10.0, 100.0, 1000.0, 10000.0])
    zero_velocity_threshold: float = 0.05
    held_out_block: float = 1.0
    held_out_every: int = 3

    def validate(self) -> None:
        """Raises ValueError naming the bad field (yaml_load_typed does not call it)."""
        self.station.validate()
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
        if self.window % 2 == 0 or self.window < 3:
            raise ValueError(
                f"IdentifyConfig.window must be odd and >= 3, got {self.window}"
            )
        if self.stride < 1:
            raise ValueError(f"IdentifyConfig.stride must be >= 1, got {self.stride}")
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


@dataclass
class IdentificationResult:
    joints: list[JointResult]
    data: IdentificationData
    held_out: np.ndarray
    train: np.ndarray
    config: IdentifyConfig
    identified: MotorModel  # the asymmetric fit: what the controller reads
    estimation_rms: np.ndarray | None = None  # τ̂ vs truth (N·m), if the log has truth
    estimation_peak: np.ndarray | None = None


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
    """Non-causal estimation, then every fit per joint, validated on held-out blocks."""
    config.validate()
    robot = config.station.description()
    estimator = FloatingBaseTorqueEstimator(robot.make_plant(), robot.estimator_config())
    data = noncausal_estimates(log, log_joint_names, estimator, config.window, config.stride)
    log_period = float(np.median(np.diff(log["t"])))
    margin = config.window * log_period  # the filters' edges: fitted, not centred
    inside = (data.t > data.t[0] + margin) & (data.t < data.t[-1] - margin)
    usable = inside & (data.phase != PHASE_TRANSITION)
    held = split_blocks(data.t, config.held_out_block, config.held_out_every)
    train, test = usable & ~held, usable & held
    columns = {name: i for i, name in enumerate(estimator.config().joints)}
    labelled = bool(np.any(data.phase >= 0))
    results = []
    for name in config.identified_joints():
        j = columns[name]
        tau, dq, dlt = data.joint(j, train)
        models = {
            "least_squares": fit_least_squares(tau, dq, dlt, joint_name=name),
            "asymmetric": fit_asymmetric(tau, dq, dlt, config.w, joint_name=name),
        }
        # Refuse data that identify no motor (noise, too little excitation): the
        # two models written to files must be positive and explain the data.
        check_identified(models["least_squares"], tau, dq, dlt)
        check_identified(models["asymmetric"], tau, dq, dlt, min_explained=None)
        models["two_stage"] = fit_two_stage(
            tau, dq, dlt, config.zero_velocity_threshold, config.w, joint_name=name
        )
        # The piecewise-linear model of Sec. 3.2 has no velocity term: the paper fitted
        # it to the static high-torque data (Fig. 1), and so do we (an unlabelled log:
        # its near-zero-velocity samples).
        static = np.abs(data.dq[:, j]) < config.zero_velocity_threshold
        pushes = train & (data.phase == PHASE_HIGH_TORQUE if labelled else static)
        piecewise = _fit_piecewise(data.joint(j, pushes), name)
        tau_h, dq_h, dlt_h = data.joint(j, test)
        validation = {}
        static_h = test & (data.phase == PHASE_HIGH_TORQUE if labelled else static)
        for method, fitted in list(models.items()) + [("piecewise_linear", piecewise)]:
            if fitted is None:
                continue
            samples = (tau_h, dq_h, dlt_h)
            if method == "piecewise_linear":
                samples = data.joint(j, static_h)
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
                "rms": float(np.sqrt(np.mean((fitted.predict(tau_h, dq_h) - dlt_h) ** 2))),
                "overestimation": overestimation_share(fitted, tau_h, dq_h, dlt_h),
            }
        samples = {"train": int(train.sum()), "held_out": int(test.sum())}
        results.append(JointResult(name, models, piecewise, validation, samples, sweep))
    identified = MotorModel.from_joints({r.joint: r.models["asymmetric"] for r in results})
    rms = peak = None
    if data.tau_true is not None:
        err = data.tau[inside] - data.tau_true[inside]
        rms = np.sqrt(np.mean(err**2, axis=0))
        peak = np.abs(data.tau_true[inside]).max(axis=0)
    return IdentificationResult(results, data, held, train, config, identified, rms, peak)


def _fit_piecewise(samples, name: str):
    """The piecewise-linear fit from the first initial guess that works, or None.

    The piecewise-linear model is the one the paper tried and abandoned (Sec. 3.2),
    fitted for comparison only; its algorithm needs a good initial guess (the
    paper's words), so a guess that fails is expected, not an error: one
    information line per joint says which guesses failed and what came of it."""
    failed = []
    for guess in PIECEWISE_INITIAL_BREAKPOINTS:
        try:
            fitted = fit_piecewise_linear(*samples, initial_breakpoints=guess, joint_name=name)
        except ValueError as error:
            failed.append((guess, _reason(error)))
            continue
        if failed:
            _logger.info(
                "%s: piecewise-linear model (Sec. 3.2, abandoned by the paper; for "
                "comparison only) fitted from the initial breakpoints %s N·m; %s",
                name, _breakpoints(guess), _failures(failed),
            )
        return fitted
    _logger.info(
        "%s: no piecewise-linear model (Sec. 3.2, abandoned by the paper; for comparison "
        "only; its column of the report says 'failed'): %s", name, _failures(failed),
    )
    return None


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
    """Writes report.md, results.json, motor_model.yaml and the figures; returns the
    results as a dict."""
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
        row = {m: {"k_tau": float(r.models[m].k_tau[0]), "k_v": float(r.models[m].k_v[0])}
               for m in LINEAR_METHODS}
        row["validation"] = r.validation
        row["samples"] = r.samples
        row["w_sweep"] = {f"{w:g}": v for w, v in r.w_sweep.items()}
        if r.joint in PAPER_TABLE1:
            row["paper"] = {"k_tau": PAPER_TABLE1[r.joint][0] * 1e-3,
                            "k_v": PAPER_TABLE1[r.joint][1] * 1e-3}
        if truth is not None:
            row["emulator"] = {"k_tau": float(truth.k_tau[k]), "k_v": float(truth.k_v[k])}
            row["relative_error_asymmetric"] = {
                p: row["asymmetric"][p] / row["emulator"][p] - 1 for p in ("k_tau", "k_v")
            }
        rows[r.joint] = row
    summary = {"joints": rows}
    if result.estimation_rms is not None:
        cols = [robot.joints.index(j) for j in joints]
        summary["torque_estimation"] = {
            j: {"rms": float(result.estimation_rms[c]), "peak": float(result.estimation_peak[c])}
            for j, c in zip(joints, cols)
        }
    (out / "identification.json").write_text(json.dumps(summary, indent=2))
    result.identified.save(out / "motor_model.yaml")
    # The symmetric fit too: the open-loop stability experiment contrasts the two.
    MotorModel.from_joints(
        {r.joint: r.models["least_squares"] for r in result.joints}
    ).save(out / "motor_model_least_squares.yaml")
    figures = plot_figures(result, out)
    (out / "identification.md").write_text(_markdown(result, summary, figures))
    return summary


def _label(joint: str, robot: RobotDescription | None = None) -> str:
    robot = robot or model.description()
    if joint in robot.controlled_joints:
        return robot.labels()[robot.controlled_joints.index(joint)]
    return joint


def _markdown(result: IdentificationResult, summary: dict, figures: list[str]) -> str:
    lines = [
        "# Motor identification (paper Sec. 3, Table 1, Figures 1 and 3)",
        "",
        f"Samples: {int(result.train.sum())} training, "
        f"{int((~result.train & result.held_out).sum())} held out "
        f"(one {result.config.held_out_block:g} s block in "
        f"{result.config.held_out_every}), window "
        f"{result.config.window}, w = {result.config.w:g}.",
        "",
        "## Table 1: identified motor parameters (10³ Kτ in rad/(N·m), 10³ Kv in s)",
        "",
        "| joint | asymmetric Kτ | Kv | least squares Kτ | Kv | two-stage Kτ | Kv "  # LINEAR_METHODS
        "| emulator Kτ | Kv | error Kτ, Kv (asym.) | paper Kτ | Kv |",
        "| --- |" + " ---: |" * 11,
    ]
    for joint, row in summary["joints"].items():
        cells = []
        for m in LINEAR_METHODS:
            cells += [f"{row[m]['k_tau'] * 1e3:.4f}", f"{row[m]['k_v'] * 1e3:.3f}"]
        if "emulator" in row:
            e = row["relative_error_asymmetric"]
            cells += [f"{row['emulator']['k_tau'] * 1e3:.4f}", f"{row['emulator']['k_v'] * 1e3:.3f}",
                      f"{e['k_tau'] * 100:+.1f}%, {e['k_v'] * 100:+.1f}%"]
        else:
            cells += ["–", "–", "–"]
        paper = row.get("paper")
        cells += [f"{paper['k_tau'] * 1e3:.3f}", f"{paper['k_v'] * 1e3:.3f}"] if paper else ["–", "–"]
        lines.append(f"| {_label(joint, result.config.station.description())} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "## Validation on held-out samples",
        "",
        "RMS of Δq̂ − Δq (mrad) / share of samples where |Δq| is over-estimated.",
        "",
        "| joint | asymmetric | least squares | two-stage | piecewise-linear (pushes only) |",
        "| --- | --- | --- | --- | --- |",
    ]
    for joint, row in summary["joints"].items():
        cells = []
        for m in LINEAR_METHODS + ("piecewise_linear",):
            v = row["validation"].get(m)
            cells.append(f"{v['rms'] * 1e3:.3f} / {v['overestimation'] * 100:.1f}%" if v else "failed")
        lines.append(f"| {_label(joint, result.config.station.description())} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "## The asymmetric penalty's weight w",
        "",
        "Held-out share of over-estimated |Δq|"
        + (" / error of Kτ, Kv against the emulator" if truth_in(summary) else "")
        + " (the paper used w = 100).",
        "",
        "| joint | " + " | ".join(f"w = {w:g}" for w in result.config.w_sweep) + " |",
        "| --- |" + " --- |" * len(result.config.w_sweep),
    ]
    for joint, row in summary["joints"].items():
        cells = []
        for w, v in row["w_sweep"].items():
            cell = f"{v['overestimation'] * 100:.1f}%"
            if "emulator" in row:
                e = row["emulator"]
                cell += f" / {(v['k_tau'] / e['k_tau'] - 1) * 100:+.1f}%, {(v['k_v'] / e['k_v'] - 1) * 100:+.1f}%"
            cells.append(cell)
        lines.append(f"| {_label(joint, result.config.station.description())} | " + " | ".join(cells) + " |")
    if "torque_estimation" in summary:
        lines += ["", "## Non-causal torque estimate vs ground truth", "",
                  "| joint | RMS error (N·m) | peak |τ| (N·m) | RMS / peak |", "| --- | ---: | ---: | ---: |"]
        for joint, v in summary["torque_estimation"].items():
            lines.append(f"| {_label(joint, result.config.station.description())} | {v['rms']:.3f} | {v['peak']:.1f} | {v['rms'] / v['peak'] * 100:.2f}% |")
    lines += ["", "## Figures", ""] + [f"![{f}]({f})" for f in figures]
    return "\n".join(lines) + "\n"


def truth_in(summary: dict) -> bool:
    return any("emulator" in row for row in summary["joints"].values())


def plot_figures(result: IdentificationResult, out: Path) -> list[str]:
    """Figure 1 (τ vs Δq at near-zero velocity, knee and hip pitch, with the fits) and
    Figure 3 (friction part vs q̇, symmetric vs asymmetric, ankle pitch and hip roll)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    data, cfg = result.data, result.config
    by_joint = {r.joint: r for r in result.joints}
    column = {name: i for i, name in enumerate(cfg.station.description().joints)}
    names = []

    fig1 = [j for j in ("RLEG_JOINT3", "RLEG_JOINT2") if j in by_joint]
    if fig1:
        fig, axes = plt.subplots(1, len(fig1), figsize=(6 * len(fig1), 4.5), squeeze=False)
        for ax, joint in zip(axes[0], fig1):
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
            ax.set_title(f"right {_label(joint, cfg.station.description())}, |q̇| < {cfg.zero_velocity_threshold} rad/s")
            ax.grid(True, alpha=0.3)
            ax.legend(fontsize=7)
        fig.suptitle("Figure 1: torque vs position error at near-zero velocity")
        fig.tight_layout()
        fig.savefig(out / "figure1_torque_vs_delta_q.png", dpi=110)
        plt.close(fig)
        names.append("figure1_torque_vs_delta_q.png")

    fig3 = [j for j in ("RLEG_JOINT4", "RLEG_JOINT1") if j in by_joint]
    if fig3:
        fig, axes = plt.subplots(len(fig3), 2, figsize=(11, 4 * len(fig3)), squeeze=False)
        for row, joint in zip(axes, fig3):
            r, j = by_joint[joint], column[joint]
            tau, dq, dlt = data.joint(j, result.train)
            for ax, method in zip(row, ("least_squares", "asymmetric")):
                fitted = r.models[method]
                friction = dlt - fitted.k_tau[0] * tau
                ax.scatter(dq, friction * 1e3, s=2, alpha=0.3, color="tab:red", label="data")
                grid = np.linspace(dq.min(), dq.max(), 100)
                ax.plot(grid, fitted.k_v[0] * grid * 1e3, "b-", label=f"Kv q̇, Kv = {fitted.k_v[0] * 1e3:.2f}e-3")
                share = overestimation_share(fitted, tau, dq, dlt)
                kind = "symmetric, eq. 7" if method == "least_squares" else f"asymmetric, w={cfg.w:g}"
                ax.set_title(
                    f"right {_label(joint, cfg.station.description())}, {kind}: over-estimates {share * 100:.1f}%",
                    fontsize=10,
                )
                ax.set_xlabel("q̇ (rad/s)")
                ax.set_ylabel("Δq − Kτ τ̂ (mrad)")
                ax.grid(True, alpha=0.3)
                ax.legend(fontsize=8)
        fig.suptitle("Figure 3: friction part of the model vs velocity")
        fig.tight_layout()
        fig.savefig(out / "figure3_friction_fit.png", dpi=110)
        plt.close(fig)
        names.append("figure3_friction_fit.png")
    return names


def run_identify(config: IdentifyConfig, out: Path, log_path: Path | None = None) -> dict:
    """The whole `hrp2-drake identify`: collect (or load), identify, report."""
    config.validate()
    out.mkdir(parents=True, exist_ok=True)
    if log_path is None:
        log, names = collect_log(config)
        save_log(out / "identification_log.npz", log, names)
        simulated = True
    else:
        log, names = read_log(log_path, config.station.description())
        simulated = "joint_torque_true" in log
    _logger.info("estimating and fitting ...")
    try:
        result = identify(config, log, names)
    except (ValueError, KeyError) as error:
        if log_path is None:
            raise
        message = error.args[0] if isinstance(error, KeyError) and error.args else error
        raise ValueError(f"{log_path}: {message}; no motor model written") from error
    return write_report(result, out, simulated)


def read_log(
    path: str | Path, robot: RobotDescription | None = None
) -> tuple[dict, list[str]]:
    """`load_log` with every problem of the file as one error naming it (missing, a
    folder, not a readable .npz archive: `dataset.read_npz`; a missing or misshapen
    array), then `check_log`: text or NaN in an array, time not increasing on a
    constant grid, arrays of the wrong width, no column for a joint of the estimator."""
    log, names = load_log(path)
    check_log(log, names, str(path), (robot or model.description()).joints)
    return log, names
