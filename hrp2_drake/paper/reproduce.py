"""`hrp2-drake reproduce`: identification and every experiment of the paper, with the
paper's settings, into one report with the paper's numbers beside ours.

    DIR/report.md        a verdict per claim of the paper and per goal of this project
                         (apart, each with its threshold), every table beside the
                         paper's, every figure
    DIR/results.json     every number
    DIR/<step>/          each step's own report, figures, logs (and Meshcat replays)

Identification runs first (every control experiment uses its motor model); the other
steps run in parallel processes (`jobs`), then the control-component analysis reads
the motion and force logs. `quick` shortens everything to a CI-sized smoke run. The
console shows the progress; each repeated warning once, its count at the end
(`hrp2_drake.console`).
"""

import json
import logging
import time
import traceback
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from hrp2_drake import console
from hrp2_drake.paper.claims import (
    PAPER_COUPLING_X,
    PAPER_OVERSHOOT,
    push_outcome,
    verdict_tables,
)
from hrp2_drake.report import markdown_table

STEPS = (
    "identify",
    "estimation",
    "motion",
    "force",
    "stability",
    "faults",
    "components",
)


@dataclass
class ReproduceConfig:
    """Configuration of `hrp2-drake reproduce`.

    Args:
        jobs: parallel processes for the experiments after identification.
        quick: CI-sized durations (minutes become seconds); the numbers are then
            only indicative.
        replays: record Meshcat HTML replays of the motion and force experiments.
        steps: the steps to run (default: all).
    """

    jobs: int = 2
    quick: bool = False
    replays: bool = True
    steps: tuple[str, ...] = STEPS


_logger = logging.getLogger(__name__)


def _log(message: str) -> None:
    _logger.info(message)


def _save_signals(path: Path, signals: dict[str, dict[str, np.ndarray]]) -> None:
    flat = {
        f"{label}::{name}": value
        for label, logged in signals.items()
        for name, value in logged.items()
    }
    np.savez_compressed(path, **flat)


def load_signals(path: Path) -> dict[str, dict[str, np.ndarray]]:
    out: dict[str, dict[str, np.ndarray]] = {}
    with np.load(path) as data:
        for key in data.files:
            label, name = key.split("::", 1)
            out.setdefault(label, {})[name] = data[key]
    return out


# --------------------------------------------------------------------------- steps
# Each step runs in its own process: (out_dir, model_path, quick, replays) -> summary.


def step_identify(out: Path, quick: bool) -> dict:
    from hrp2_drake.assembly.identification import IdentifyConfig, identify_collection

    config = IdentifyConfig(duration_scale=0.5 if quick else 1.0)
    return identify_collection(config, out)


def step_motion(out: Path, model_path: Path, quick: bool, replays: bool) -> dict:
    from dataclasses import replace

    from hrp2_drake.identification.motor_model import MotorModel
    from hrp2_drake.paper.motion import (
        FIGURE4_RUNS,
        MotionConfig,
        run_motion,
        write_motion_report,
    )

    config = MotionConfig(end=16.0)
    if quick:
        config = replace(config, start=3.0, end=4.0, settle=0.7)

    def kept(label: str) -> bool:
        """The runs the report plots and the components step reads: their signals
        (of the others, their errors alone; about 40 MB of signals a run)."""
        return label in FIGURE4_RUNS or label in _component_runs([label])

    result = run_motion(config, MotorModel.load(model_path), keep_signals=kept)
    summary = write_motion_report(result, out)
    keep = _component_runs(result.signals)
    _save_signals(out / "motion_signals.npz", {k: result.signals[k] for k in keep})
    if replays:
        _motion_replay(config, MotorModel.load(model_path), out / "motion_replay.html")
        summary["replay"] = "motion_replay.html"
    return summary


def _component_runs(labels) -> list[str]:
    """The motion runs among `labels` whose signals the components step reads
    (motion_signals.npz): the paper's torque control at K6 = 1 and 0.1, and
    position control."""
    from hrp2_drake.paper.motion import is_beyond_paper

    paper = [label for label in labels if not is_beyond_paper(label)]
    keep = [label for label in paper if "K6=1" in label and "," not in label]
    keep += [
        label for label in paper if "K6=0.1" in label or label == "position control"
    ]
    return keep


def _motion_replay(config, motor_model, path: Path) -> None:
    """A Meshcat recording of torque control K6 = 1 on the climbing motion."""
    from pydrake.geometry import Meshcat
    from pydrake.systems.analysis import Simulator

    from hrp2_drake.assembly.builders import build_torque_control, simulated_station
    from hrp2_drake.config import replace_fields
    from hrp2_drake.paper.motion import motion_reference

    meshcat = Meshcat()
    reference = motion_reference(config)
    robot, station, period = simulated_station(config.station, meshcat)
    k6_1 = replace_fields(config.torque_control, {"controller.k6": 1.0})
    control = build_torque_control(
        robot,
        station,
        reference,
        motor_model,
        k6_1,
        control_period=period,
    )
    simulator = Simulator(control.diagram)
    meshcat.StartRecording(frames_per_second=30.0)
    simulator.AdvanceTo(reference.end_time())
    meshcat.StopRecording()
    meshcat.PublishRecording()
    path.write_text(meshcat.StaticHtml())


def step_force(out: Path, model_path: Path, quick: bool, replays: bool) -> dict:
    from dataclasses import replace

    from pydrake.geometry import Meshcat

    from hrp2_drake.identification.motor_model import MotorModel
    from hrp2_drake.paper.force import (
        ForceConfig,
        run_force,
        run_force_all,
        write_force_report,
    )

    config = ForceConfig()
    if quick:
        config = replace(config, settle=0.6, static_average=0.2, hold=0.3, periods=1.0)
        config.ablations = []
    motor_model = MotorModel.load(model_path)
    result = run_force_all(config, motor_model)
    summary = write_force_report(result, out)
    if replays:
        meshcat = Meshcat()
        meshcat.StartRecording(frames_per_second=30.0)
        base = result.baseline
        run_force(
            config,
            motor_model,
            static=(base.static_wrench, base.static_reading),
            gain=base.posture_gain,
            meshcat=meshcat,
        )
        meshcat.StopRecording()
        meshcat.PublishRecording()
        (out / "force_replay.html").write_text(meshcat.StaticHtml())
        summary["replay"] = "force_replay.html"
    return summary


def step_stability(out: Path, model_path: Path, quick: bool, replays: bool) -> dict:
    from dataclasses import replace

    from hrp2_drake.identification.motor_model import MotorModel
    from hrp2_drake.paper.stability import StabilityConfig, run_stability_experiment

    config = StabilityConfig()
    if quick:
        config = replace(config, push_velocities=[0.5, 2.0])
    models = {
        "asymmetric": MotorModel.load(model_path),
        "least_squares": MotorModel.load(
            model_path.with_name("motor_model_least_squares.yaml")
        ),
    }
    return run_stability_experiment(config, models, out)


def step_components(out: Path, motion_dir: Path, force_dir: Path) -> dict:
    from hrp2_drake.paper.components import analyse_components
    from hrp2_drake.paper.force import load_signals as load_force_signals

    return analyse_components(
        load_signals(motion_dir / "motion_signals.npz"),
        load_force_signals(force_dir / "force_signals.npz"),
        out,
    )


def step_estimation(out: Path, model_path: Path, quick: bool, replays: bool) -> dict:
    from hrp2_drake.paper.estimation import (
        EstimationConfig,
        run_estimation_experiment,
    )

    config = EstimationConfig()
    if quick:
        config.duration_scale = 0.35
        config.windows = [40, 80]
    return run_estimation_experiment(config, out)


def step_faults(out: Path, model_path: Path, quick: bool, replays: bool) -> dict:
    from hrp2_drake.paper.faults import FaultCampaignConfig, run_fault_campaign

    return run_fault_campaign(FaultCampaignConfig(quick=quick, jobs=1), model_path, out)


STEP_FUNCTIONS: dict[str, Callable] = {
    "estimation": step_estimation,
    "motion": step_motion,
    "force": step_force,
    "stability": step_stability,
    "faults": step_faults,
}


def _run_step(
    name: str,
    out: Path,
    model_path: Path,
    quick: bool,
    replays: bool,
    program: str = "",
) -> dict:
    """Runs one step in a worker process; failures become a summary with the error.
    Its console lines name the step; each repeated warning is printed once and its
    count returned in the summary ("repeated_warnings", printed by the parent at the
    end of the run)."""
    start = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    with console.session(program, context=name, summary=False) as session:
        try:
            summary = STEP_FUNCTIONS[name](out, model_path, quick, replays)
            summary["ok"] = True
        except Exception as error:  # reported, and the other steps go on
            summary = {
                "ok": False,
                "error": f"{type(error).__name__}: {error}",
                "traceback": traceback.format_exc(),
            }
        summary["repeated_warnings"] = session.repeats()
    summary["seconds"] = time.perf_counter() - start
    return summary


def run_reproduce(config: ReproduceConfig, out: Path) -> dict:
    """Runs every step and writes report.md and results.json; returns the results."""
    out.mkdir(parents=True, exist_ok=True)
    wall = time.perf_counter()
    results: dict[str, dict] = {}
    _log("identification (every control experiment uses its motor model)")
    start = time.perf_counter()
    results["identify"] = step_identify(out / "identify", config.quick)
    results["identify"]["seconds"] = time.perf_counter() - start
    model_path = out / "identify" / "motor_model.yaml"

    parallel = [s for s in config.steps if s in STEP_FUNCTIONS]
    _log(f"running {', '.join(parallel)} in {config.jobs} process(es)")
    with ProcessPoolExecutor(
        max_workers=max(1, config.jobs), mp_context=get_context("spawn")
    ) as pool:
        futures = {
            name: pool.submit(
                _run_step,
                name,
                out / name,
                model_path,
                config.quick,
                config.replays,
                console.program(),
            )
            for name in parallel
        }
        session = console.current()
        for name, future in futures.items():
            results[name] = future.result()
            status = (
                "done" if results[name]["ok"] else f"FAILED: {results[name]['error']}"
            )
            _log(f"{name}: {status} in {results[name]['seconds']:.0f} s")
            repeats = results[name].get("repeated_warnings", {})
            if session is not None:  # printed with the run's own, at its end
                session.add_repeats(repeats, name)
            else:
                console.print_repeats(repeats, name)
    if "components" in config.steps:
        if results.get("motion", {}).get("ok") and results.get("force", {}).get("ok"):
            _log("control components (motion and force logs)")
            start = time.perf_counter()
            try:
                results["components"] = step_components(
                    out / "components", out / "motion", out / "force"
                )
                results["components"]["ok"] = True
            except Exception as error:
                results["components"] = {
                    "ok": False,
                    "error": f"{type(error).__name__}: {error}",
                }
            results["components"]["seconds"] = time.perf_counter() - start
        else:
            results["components"] = {
                "ok": False,
                "error": "needs the motion and force steps",
            }
    results["total_seconds"] = time.perf_counter() - wall
    results["quick"] = config.quick
    (out / "results.json").write_text(json.dumps(results, indent=2, default=float))
    (out / "report.md").write_text(write_report(results, out))
    _log(f"report: {out / 'report.md'} ({results['total_seconds']:.0f} s)")
    return results


# ------------------------------------------------------------------------- report
def _section(out: Path, step: str, filename: str) -> list[str]:
    """A step's own markdown, its headings demoted and its figure paths prefixed."""
    path = out / step / filename
    if not path.is_file():
        return [f"*{step}: no report ({path.name} missing)*"]
    lines = []
    for line in path.read_text().splitlines():
        if line.startswith("#"):
            line = "#" + line
        line = line.replace("](", f"]({step}/") if line.startswith("![") else line
        lines.append(line)
    return lines


def _predictions(results: dict) -> list[str]:
    """Figure 5 and Sec. 5.2 as predictions beside the paper, with ratios where the
    paper gives a number (Tables 2 and 3: in the motion section)."""
    lines = [
        "## Predictions beside the paper",
        "",
        "The servo is calibrated to Table 1 and the position-control column of Tables "
        "2 and 3 only (`hrp2-drake calibrate`): everything below, and the "
        "torque-control columns of Tables 2 and 3 (motion section, simulation/paper "
        "per cell), is a prediction.",
        "",
    ]
    rows = []
    force = results.get("force", {})
    if force.get("ok") and "baseline" in force:
        m = force["baseline"]["metrics"]["ft_reading"]
        rows += [
            [
                "Fig. 5",
                "overshoot at the apex ≤ 10%",
                f"{m['overshoot'] * 100:+.1f}%",
                f"{m['overshoot'] / PAPER_OVERSHOOT:.2f}",
            ],
            [
                "Fig. 5",
                "coupling on X: the same 10%",
                f"{m['coupling_x'] * 100:.1f}%",
                f"{m['coupling_x'] / PAPER_COUPLING_X:.2f}",
            ],
            ["Fig. 5", "no significant delay", f"{m['lag_ms']:+.0f} ms", "-"],
            [
                "Fig. 5",
                "(amplitude of the z force)",
                f"ratio {m['amplitude_ratio']:.2f}",
                "-",
            ],
        ]
    for delay, v in results.get("stability", {}).get("verdicts", {}).items():
        label = "as it is" if delay == "0 ms" else f"with δc = {delay} compensated"
        rows += [
            [
                "Sec. 5.2",
                f"least squares: unstable once a speed is reached (controller {label})",
                push_outcome(v["least_squares"]),
                "-",
            ],
            [
                "Sec. 5.2",
                f"asymmetric fit: stable (controller {label})",
                push_outcome(v["asymmetric"]),
                "-",
            ],
        ]
    header = ["paper", "what it reports", "simulation", "simulation/paper"]
    return lines + markdown_table(header, rows, align="lllr")


def write_report(results: dict, out: Path) -> str:
    lines = [
        "# Reproduction of Del Prete et al. 2015 on a simulated HRP-2",
        "",
        f"Generated by `hrp2-drake reproduce` in {results['total_seconds'] / 60:.1f} "
        "min"
        + (
            " (quick: CI-sized durations, numbers only indicative)"
            if results.get("quick")
            else ""
        )
        + ". Every number below is measured in this run; the paper's values are in "
        "parentheses or in their own columns.",
        "",
        "## Verdicts",
        "",
    ]
    lines += verdict_tables(results)
    failed = [s for s in STEPS if s in results and not results[s].get("ok", True)]
    if failed:
        lines += ["", "Steps that failed (their claims and goals are not judged):", ""]
        lines += [f"- {step}: {results[step]['error']}" for step in failed]
    lines += [""] + _predictions(results) + [""]
    for step, filename in (
        ("identify", "identification.md"),
        ("estimation", "estimation.md"),
        ("motion", "motion.md"),
        ("force", "force.md"),
        ("components", "components.md"),
        ("stability", "stability.md"),
        ("faults", "faults.md"),
    ):
        if step in results:
            lines += _section(out, step, filename) + [""]
    lines += ["## Timing", ""]
    lines += [
        f"- {step}: {results[step].get('seconds', 0):.0f} s"
        for step in STEPS
        if step in results
    ]
    return "\n".join(lines) + "\n"
