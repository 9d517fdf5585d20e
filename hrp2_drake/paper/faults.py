"""`hrp2-drake experiment faults`: a fault campaign on the motion and force experiments.

Each fault (sensor NaN, freeze, zero, bias, glitch; extra command latency; a wrong
model in the controllers) is injected into the calibrated station during torque
control (K6 = 1 on the climbing swing's fastest part; the paper's force experiment),
with the SafetySupervisor in the loop. Per fault and experiment it reports whether the
fault was detected and when, when the robot went back to position control, whether
torque control resumed, the largest tracking error against the same experiment without
fault and against position control, the largest step of q_cmd beyond the reference's
own motion, and whether anything raised or diverged.
"""

import functools
import io
import json
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from hrp2_drake import console
from hrp2_drake.assembly.builders import (
    build_position_control,
    build_torque_control,
    simulated_station,
)
from hrp2_drake.assembly.torque_control import (
    ControllerSettings,
    EstimatorSettings,
    TorqueControlConfig,
)
from hrp2_drake.config import check_finite, replace_fields
from hrp2_drake.control.safety import describe_faults
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.paper import hrp2
from hrp2_drake.paper.force import ForceConfig, run_force
from hrp2_drake.paper.motion import MotionConfig, motion_reference, run_controller
from hrp2_drake.report import markdown_table, pyplot, save_figure
from hrp2_drake.robot.faults import SensorFault
from hrp2_drake.robot.station import StationConfig

#: Tracking during a fault may exceed position control's by at most this (rad), and a
#: mode switch may step q_cmd by at most this beyond the reference's motion (rad).
TRACKING_MARGIN = 0.005
STEP_BOUND = 0.002
#: Position control at the motion's first pose before it starts (s).
SETTLE = 0.7


@dataclass
class FaultCase:
    """One fault of the campaign: sensor faults (their start is relative to the
    experiment's fault time), and/or a command latency or a model error."""

    name: str = ""
    sensor_faults: list[SensorFault] = field(default_factory=list)
    extra_command_latency: float = 0.0
    model_error: float = 0.0


def default_cases() -> list[FaultCase]:
    knee = hrp2.JOINT_NAMES.index("RLEG_JOINT3")
    return [
        FaultCase(
            "F/T NaN burst (5 ms)",
            [SensorFault("wrench_right_foot", "nan", 0.0, 0.005)],
        ),
        FaultCase(
            "F/T frozen (200 ms)",
            [SensorFault("wrench_right_foot", "freeze", 0.0, 0.2)],
        ),
        FaultCase(
            "F/T zeroed (200 ms)", [SensorFault("wrench_right_foot", "zero", 0.0, 0.2)]
        ),
        FaultCase(
            "IMU bias step (0.5 m/s²)",
            [SensorFault("imu_linear_acceleration", "bias", 0.0, np.inf, [0], [0.5])],
        ),
        FaultCase(
            "encoder glitch (knee, 10 mrad, one sample)",
            [SensorFault("q_measured", "glitch", 0.0, 0.001, [knee], [0.01])],
        ),
        FaultCase(
            "encoder frozen (knee, 200 ms)",
            [SensorFault("q_measured", "freeze", 0.0, 0.2, [knee])],
        ),
        FaultCase(
            "encoder NaN (knee, 5 ms)",
            [SensorFault("q_measured", "nan", 0.0, 0.005, [knee])],
        ),
        FaultCase("extra command latency (2 ms)", extra_command_latency=0.002),
        FaultCase("model error (masses, COMs ±20%)", model_error=0.2),
    ]


@dataclass
class FaultCampaignConfig:
    """Configuration of the fault campaign.

    Args:
        experiments: "motion" and/or "force".
        motion_start, motion_end: the part of the climbing motion (s): the fastest
            swing of the knee by default.
        motion_fault_time: when the faults start in the motion run (s of simulation;
            the motion starts after a 0.7 s settle).
        force_fault_time: when the faults start in the force run (s).
        k6: the torque controller's position gain in the motion runs.
        jobs: parallel simulations.
        quick: CI-sized: three faults, shorter runs.
    """

    experiments: list[str] = field(default_factory=lambda: ["motion", "force"])
    motion_start: float = 3.0
    motion_end: float = 4.6
    motion_fault_time: float = 1.05
    force_fault_time: float = 3.0
    k6: float = 1.0
    jobs: int = 2
    quick: bool = False

    def validate(self) -> None:
        unknown = set(self.experiments) - {"motion", "force"}
        if unknown or not self.experiments:
            raise ValueError(
                f"FaultCampaignConfig.experiments: {self.experiments}, expected motion "
                "and/or force"
            )
        if not self.motion_start < self.motion_end:
            raise ValueError(
                "FaultCampaignConfig: motion_end must be after motion_start"
            )
        check_finite(self.k6, "FaultCampaignConfig.k6", 0.0)
        if self.jobs < 1:
            raise ValueError(
                f"FaultCampaignConfig.jobs: {self.jobs}, expected 1 or more"
            )
        # Faults start once torque control runs, and before the run ends.
        torque_start = TorqueControlConfig().start_time
        motion = MotionConfig(
            start=self.motion_start, end=self.motion_end, settle=SETTLE
        )
        try:  # the part of the climbing motion: within it
            motion.validate()
        except ValueError as error:
            raise ValueError(
                f"FaultCampaignConfig.motion_start, motion_end: {error}"
            ) from None
        runs = {
            "motion_fault_time": (
                self.motion_fault_time,
                torque_start,
                SETTLE + self.motion_end - self.motion_start,
            ),
            "force_fault_time": (
                self.force_fault_time,
                ForceConfig().settle,
                ForceConfig().duration,
            ),
        }
        for name, (value, start, end) in runs.items():
            check_finite(value, f"FaultCampaignConfig.{name}")
            if not start <= value < end:
                raise ValueError(
                    f"FaultCampaignConfig.{name}: {value:g} s, expected from "
                    f"{start:g} s (torque control starts) to before {end:g} s (the "
                    "run ends)"
                )


def _shifted(case: FaultCase, t0: float) -> list[SensorFault]:
    return [replace(f, start=f.start + t0) for f in case.sensor_faults]


def _motion_run(
    config: FaultCampaignConfig,
    case: FaultCase | None,
    motor_path: str,
    position_control: bool = False,
) -> dict:
    t_fault = config.motion_fault_time
    station = StationConfig(scenario="hanging")
    torque = TorqueControlConfig(
        controller=ControllerSettings(k6=config.k6),
        estimator=EstimatorSettings(offset_calibration_time=0.25),
    )
    if case is not None:
        station = replace(
            station,
            faults=_shifted(case, t_fault),
            extra_command_latency=case.extra_command_latency,
        )
        torque = replace_fields(torque, {"faults.model_error": case.model_error})
    motion = MotionConfig(
        station=station, start=config.motion_start, end=config.motion_end, settle=SETTLE
    )
    reference = motion_reference(motion)
    robot, simulated, period = simulated_station(station)
    if position_control:
        control = build_position_control(robot, simulated, reference)
    else:
        control = build_torque_control(
            robot,
            simulated,
            reference,
            MotorModel.load(motor_path),
            torque,
            control_period=period,
        )
    signals = run_controller(
        control, reference.end_time(), "faults", stream=io.StringIO()
    )
    return _summarize(signals, t_fault, "motion")


def _force_run(
    config: FaultCampaignConfig, case: FaultCase | None, motor_path: str
) -> dict:
    t_fault = config.force_fault_time
    force = ForceConfig()
    force.ablations = []
    if config.quick:
        force = replace(force, settle=0.6, static_average=0.2, hold=0.3, periods=1.0)
        t_fault = force.settle + 0.8
    if case is not None:
        station = replace(
            force.station,
            faults=_shifted(case, t_fault),
            extra_command_latency=case.extra_command_latency,
        )
        force = replace(
            force,
            station=station,
            torque_control=replace_fields(
                force.torque_control, {"faults.model_error": case.model_error}
            ),
        )
    run = run_force(force, MotorModel.load(motor_path))
    out = _summarize(run.signals, t_fault, "force")
    out["force_rms_error"] = float(run.metrics["ft_reading"]["rms_error"])
    return out


@functools.cache
def _joint_positions() -> np.ndarray:
    """Where the 30 joint angles are in the floating-base station's state."""
    return hrp2.hrp2_joint_indexing(hrp2.estimator_plant()).q


def _summarize(signals: dict, t_fault: float, experiment: str) -> dict:
    """What the campaign reports of one run (see the module docstring)."""
    t = signals["t"]
    leg = [hrp2.JOINT_NAMES.index(j) for j in hrp2.RIGHT_LEG]
    after = t >= t_fault
    # Tracking against the true joint angles (ground truth, for evaluation): a faulty
    # encoder is what the controllers see, not where the leg is.
    q_true = signals["state_true"][:, _joint_positions()]
    error = signals["q_ref"][:, leg] - q_true[:, leg]
    finite = np.all(np.isfinite(error), axis=1)
    out = {
        "experiment": experiment,
        "max_error_after": float(np.abs(error[after & finite]).max()),
        "max_error": float(np.abs(error[finite]).max()),
        "finite": bool(np.all(np.isfinite(signals["q_cmd"]))),
    }
    # How much farther q_cmd moves in one period than the reference does (rad).
    excess = np.maximum(
        np.abs(np.diff(signals["q_cmd"][:, leg], axis=0))
        - np.abs(np.diff(signals["q_ref"][:, leg], axis=0)),
        0.0,
    )
    out["max_command_step"] = float(excess.max())
    knee = hrp2.JOINT_NAMES.index("RLEG_JOINT3")
    out["trace"] = {
        "t": (t[::5] - t_fault).tolist(),
        "knee_error": np.nan_to_num(error[::5, leg.index(knee)]).tolist(),
    }
    if "supervisor_fault" in signals:
        bits = signals["supervisor_fault"][:, 0]
        mode = signals["supervisor_mode"][:, 0]
        hit = after & (bits > 0)
        out["detected"] = bool(hit.any())
        out["detection_delay"] = (
            float(t[np.argmax(hit)] - t_fault) if hit.any() else None
        )
        out["fault_bits"] = (
            int(np.bitwise_or.reduce(bits[after].astype(int))) if after.any() else 0
        )
        out["faults"] = describe_faults(out["fault_bits"])
        down = after & (mode < 1.0)
        out["position_control_at"] = (
            float(t[np.argmax(down)] - t_fault) if down.any() else None
        )
        out["resumed"] = bool(mode[-1] == 1.0)
        switching = (mode > 0) & (mode < 1)
        window = np.convolve(switching, np.ones(3), mode="same")[1:] > 0
        out["max_switch_step"] = float(excess[window].max()) if window.any() else 0.0
        out["trace"]["mode"] = mode[::5].tolist()
    return out


def _job(args: tuple) -> dict:
    kind, config, case, motor_path, position = args
    start = time.perf_counter()
    try:
        if kind == "motion":
            result = _motion_run(config, case, motor_path, position)
        else:
            result = _force_run(config, case, motor_path)
        result["raised"] = None
    except Exception as error:  # the campaign reports it: nothing may raise
        result = {"experiment": kind, "raised": f"{type(error).__name__}: {error}"}
    result["case"] = (
        case.name if case else ("position control" if position else "no fault")
    )
    result["seconds"] = time.perf_counter() - start
    return result


def run_fault_campaign(
    config: FaultCampaignConfig, motor_model_path: Path, out: Path, stream=None
) -> dict:
    """Runs every fault on every experiment (and the references without fault and in
    position control), in `config.jobs` processes; writes faults.md, faults.json and
    the figure in `out`."""
    import sys

    stream = stream or sys.stderr
    config.validate()
    out.mkdir(parents=True, exist_ok=True)
    cases = default_cases()
    if config.quick:
        cases = [cases[0], cases[4], cases[7]]
    jobs = []
    for kind in config.experiments:
        jobs.append((kind, config, None, str(motor_model_path), False))
        if kind == "motion":
            jobs.append((kind, config, None, str(motor_model_path), True))
        jobs += [(kind, config, case, str(motor_model_path), False) for case in cases]
    wall = time.perf_counter()
    results = []

    def collect(done) -> None:
        for result in done:
            results.append(result)
            console.say(
                f"fault run {len(results)}/{len(jobs)}: {result['experiment']}: "
                f"{result['case']} ({result['seconds']:.0f} s)",
                stream,
            )

    if config.jobs == 1:  # in this process (e.g. inside reproduce's own workers)
        collect(_job(job) for job in jobs)
    else:
        with ProcessPoolExecutor(
            config.jobs,
            mp_context=get_context("spawn"),
            initializer=console.start_worker,
            initargs=(console.program(), "faults"),
        ) as pool:  # the workers' lines in the console's format, repeats counted
            collect(pool.map(_job, jobs))
    summary = {
        "results": results,
        "config": asdict(config),
        "tracking_margin": TRACKING_MARGIN,
        "step_bound": STEP_BOUND,
        "wall_time": time.perf_counter() - wall,
    }
    summary["verdict"] = _verdict(results)
    figure = _plot(results, out)
    for result in results:  # plotted; the summary keeps the numbers
        result.pop("trace", None)
    (out / "faults.json").write_text(json.dumps(summary, indent=2, default=float))
    (out / "faults.md").write_text(_report(summary, out) + f"\n![{figure}]({figure})\n")
    return summary


def _plot(results: list[dict], out: Path) -> str:
    """Per experiment: the supervisor's mode and the knee's tracking error around the
    fault, one line per fault, each case in a style of its own (up to 11 curves a
    panel); one legend below the panels, off the data."""
    plt = pyplot()
    kinds = sorted({r["experiment"] for r in results})
    cases = list(dict.fromkeys(r["case"] for r in results))
    colours = [
        f"C{k}" for k in range(10) if k != 7
    ]  # C7 is the grey of position control
    styles, k = {}, 0
    for case in cases:
        if case == "no fault":
            styles[case] = dict(lw=1.6, color="k")
        elif case == "position control":
            styles[case] = dict(lw=1.2, color="0.5", ls="--")
        else:
            styles[case] = dict(
                lw=0.9, color=colours[k % 9], ls=("-", "-.", ":")[k // 9 % 3]
            )
            k += 1
    fig, axes = plt.subplots(
        2, len(kinds), figsize=(7 * len(kinds), 8), squeeze=False, layout="constrained"
    )
    for col, kind in enumerate(kinds):
        for r in results:
            trace = r.get("trace")
            if r["experiment"] != kind or not trace:
                continue
            style = styles[r["case"]]
            if "mode" in trace:
                axes[0, col].plot(trace["t"], trace["mode"], label=r["case"], **style)
            axes[1, col].plot(
                trace["t"],
                np.asarray(trace["knee_error"]) * 1e3,
                label=r["case"],
                **style,
            )
        axes[0, col].set_title(f"{kind}: supervisor mode (1 = torque control)")
        axes[1, col].set_title(f"{kind}: knee tracking error (mrad)")
        for ax in axes[:, col]:
            ax.axvline(0.0, color="r", lw=0.8)
            ax.set_xlabel("time from the fault (s)")
            ax.grid(True, alpha=0.3)
    handles = {}
    for ax in axes.ravel():
        for handle, label in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(label, handle)
    fig.legend(
        handles.values(), handles.keys(), loc="outside lower center", ncol=4, fontsize=8
    )
    name = "faults.png"
    save_figure(fig, out / name, dpi=100)
    return name


def _verdict(results: list[dict]) -> dict:
    faulty = [r for r in results if r["case"] not in ("no fault", "position control")]
    raised = [r["case"] for r in results if r.get("raised")]
    sensor = [r for r in faulty if r.get("raised") is None and r.get("fault_bits", 0)]
    slow = [
        r["case"]
        for r in sensor
        if r["detection_delay"] is None or r["detection_delay"] > 0.010
    ]
    position = {r["experiment"]: r for r in results if r["case"] == "position control"}
    worse = []
    for r in faulty:
        ref = position.get(r["experiment"])
        judged = ref and not ref.get("raised") and not r.get("raised")
        if judged:
            if r["max_error_after"] > ref["max_error"] + TRACKING_MARGIN:
                worse.append(f"{r['experiment']}: {r['case']}")
    steps = [
        f"{r['experiment']}: {r['case']}"
        for r in results
        if r.get("max_switch_step", 0.0) > STEP_BOUND
    ]
    # A run that raised was not judged: no check can hold for it.
    unjudged = [
        f"{r['experiment']}: {r['case']} (raised, not judged)"
        for r in results
        if r.get("raised")
    ]
    slow, steps, worse = slow + unjudged, steps + unjudged, worse + unjudged
    return {
        "nothing_raised": not raised,
        "raised": raised,
        "detected_within_10_ms": not slow,
        "detected_late": slow,
        "no_step_above_bound": not steps,
        "steps_above_bound": steps,
        "tracking_within_margin": not worse,
        "tracking_worse": worse,
    }


def _report(summary: dict, out: Path) -> str:
    results = summary["results"]
    v = summary["verdict"]
    lines = [
        "# Fault campaign: the supervised torque control under faults",
        "",
        "Calibrated robot, SafetySupervisor in the loop. Motion: the hanging robot on "
        "the climbing swing's fastest part (K6 = 1), faults from the knee's fast "
        "phase; force: the paper's experiment (K6 = 0.1), faults during the sinusoid. "
        "Errors in mrad on the right leg, against the true joint angles (what a faulty "
        "encoder reads is not where the leg is); `step` is how much farther q_cmd "
        "moved in one period than the reference did, at most, during mode switches.",
        "",
        _check("nothing raised, nothing diverged", v, "nothing_raised", "raised"),
        _check(
            "every NaN, freeze or staleness detected within 10 ms",
            v,
            "detected_within_10_ms",
            "detected_late",
        ),
        _check(
            f"no q_cmd step above {STEP_BOUND * 1e3:g} mrad at a mode switch",
            v,
            "no_step_above_bound",
            "steps_above_bound",
        ),
        _check(
            f"tracking no worse than position control + {TRACKING_MARGIN * 1e3:g} mrad",
            v,
            "tracking_within_margin",
            "tracking_worse",
        ),
        "",
        *_run_table(results),
    ]
    lines += [
        "",
        "A fault the supervisor cannot see (a bias step, an extra latency, a wrong "
        "model) is judged by its tracking; the IMU only enters the estimate of the "
        "base, which the fixed-base controller does not use.",
        "",
    ]
    return "\n".join(lines)


def _check(text: str, verdict: dict, key: str, misses: str) -> str:
    """One criterion of `_verdict`, met ("yes") or not (and where not)."""
    met = "yes" if verdict[key] else "no: " + ", ".join(verdict[misses])
    return f"- {text}: **{met}**"


def _run_table(results: list[dict]) -> list[str]:
    """One row per run: its detection, fallback, resumption, error and step."""
    rows = []
    for r in results:
        if r.get("raised"):
            rows.append(
                [r["experiment"], r["case"], *["-"] * 6, f"raised: {r['raised']}"]
            )
            continue
        detected = "-"
        if "detected" in r:
            detected = (
                f"yes ({r['detection_delay'] * 1e3:.0f} ms)" if r["detected"] else "no"
            )
        down = r.get("position_control_at")
        rows.append(
            [
                r["experiment"],
                r["case"],
                detected,
                f"{r.get('faults', '-')}",
                "-" if down is None else f"{down * 1e3:.0f} ms",
                "-" if "resumed" not in r else ("yes" if r["resumed"] else "no"),
                f"{r['max_error_after'] * 1e3:.1f}",
                f"{r.get('max_switch_step', 0.0) * 1e3:.2f}",
                "ran" if r["finite"] else "not finite",
            ]
        )
    header = [
        "experiment",
        "fault",
        "detected (delay)",
        "faults seen",
        "position control after",
        "resumed",
        "max error after (mrad)",
        "step (mrad)",
        "outcome",
    ]
    return markdown_table(header, rows, align="llllrlrrl")
