"""`hrp2-drake control --lcm URL` and `hrp2-drake sim-robot --lcm URL`: the torque
controller against a robot over LCM, in real time, and the simulated robot that
stands in for the real one behind the same channels (hrp2_drake/hardware).

`control` runs the fused controller (`control/fused.py`, the same steps as the
simulation's systems) in the message-driven loop (`hardware/control_loop.py`): the
robot's encoder message is the clock; decode, one tick, publish. It times every tick
from receive to publish and writes control.md (with a latency histogram),
control.json and control.npz. `sim-robot` is `RobotBridge`: the simulated station
behind the channels, in real time, with a command watchdog; on exit it writes its
ground truth for evaluation. Start-up order: the robot (or `sim-robot`) first, then
`control`, which waits for the robot's first messages.
"""

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from hrp2_drake.config import check_finite, moved_keys
from hrp2_drake.console import say
from hrp2_drake.control.fused import FusedController
from hrp2_drake.control.safety import SafetyConfig
from hrp2_drake.assembly.builders import (
    JointReference,
    TorqueControlConfig,
    check_control_period,
    torque_chain_parts,
)
from hrp2_drake.assembly.torque_control import EstimatorSettings
from hrp2_drake.description import RobotDescription, load_robot_description
from hrp2_drake.tools.track import TrackConfig, check_sinusoid, sinusoid_reference
from hrp2_drake.hardware.control_loop import (
    BridgeConfig,
    ControlLoop,
    LoopConfig,
    LoopSettings,
    RobotBridge,
)
from hrp2_drake.hardware.lcm_station import LcmChannels
from hrp2_drake.hardware.transport import open_transport
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.report import legend_beside, markdown_table, pyplot, save_figure
from hrp2_drake.robot.station import StationConfig


@moved_keys(
    station="robot",
    wait_timeout="loop.wait_timeout",
    silence_timeout="loop.silence_timeout",
    ramp_time="loop.ramp_time",
    real_time="loop.real_time",
)
@dataclass
class LcmControlConfig:
    """Configuration of `hrp2-drake control`.

    Args:
        robot: the robot's description: a robot.yaml path, or the name of a robot in
            models/ ("hrp2", "iiwa14"); empty: HRP-2. It gives the control period
            (its sensors.period) and the home pose the reference starts from (its
            initial_positions, or its trajectory's first sample).
        torque_control: the controller (its supervisor included; staleness limits
            widened for a transport's jitter).
        duration: how long to run (s of robot time).
        motion: "sinusoid" (every controlled joint around the home pose, `track`'s
            reference) or "hold" (the home pose).
        amplitude, frequency, settle: the sinusoids (rad, Hz) after `settle` s.
        loop: the message-driven loop's own settings: how long to wait for the
            robot's first messages, when the robot is silent (the loop then ramps to
            position control and stops), the ramp that ends every run, real time.
        channels: the LCM channels.
    """

    robot: str = ""
    torque_control: TorqueControlConfig = field(default_factory=lambda: TorqueControlConfig(
        start_time=0.5, estimator=EstimatorSettings(window=41),
        # A sample may come a few ms late over a network (and two real-time processes
        # share 2 cores here): stale after 10 ms or 12 repeated samples, not 2.5 / 5.
        supervisor=SafetyConfig(stale_time=0.010, stale_samples=12),
    ))
    duration: float = 5.0
    motion: str = "sinusoid"
    amplitude: float = 0.2
    frequency: float = 0.4
    settle: float = 0.5
    loop: LoopSettings = field(default_factory=LoopSettings)
    channels: LcmChannels = field(default_factory=LcmChannels)

    def description(self) -> RobotDescription:
        """The robot's description (checked against its model; cached)."""
        return load_robot_description(self.robot or None)

    def period(self) -> float:
        """The control period: the robot's sensor period (s)."""
        return self.description().sensors.period

    def home(self) -> np.ndarray:
        """The home pose (rad, the description's joint order)."""
        return self.description().home_positions()

    def validate(self) -> None:
        """Raises ValueError naming the bad field: the robot, the controller (its gains,
        its supervisor's period against the robot's), the motion against the joints'
        limits, the loop's timing."""
        robot = self.description()
        self.torque_control.validate()
        where = "LcmControlConfig"
        check_control_period(self.torque_control, self.period(), f"{where}.torque_control")
        if self.motion not in ("sinusoid", "hold"):
            raise ValueError(
                f"{where}.motion: '{self.motion}', expected sinusoid or hold"
            )
        check_sinusoid(robot, self.home(), self.amplitude, self.frequency, self.settle, where)
        check_finite(self.duration, f"{where}.duration", 0.0)
        self.loop.validate(self.period(), f"{where}.loop")

    def loop_config(self) -> LoopConfig:
        """The loop's settings for this run: `loop`, `duration` and the robot's period."""
        return LoopConfig(duration=self.duration, period=self.period(), settings=self.loop)


def control_reference(config: LcmControlConfig) -> JointReference:
    robot = config.description()
    q0 = config.home()
    if config.motion == "hold":
        return JointReference.hold(q0, config.duration + 1.0)
    track = TrackConfig(
        settle=config.settle, amplitude=config.amplitude,
        frequency=config.frequency, duration=config.duration + 1.0 - config.settle,
    )
    return sinusoid_reference(robot, q0, track)


def run_control(
    config: LcmControlConfig, motor_model: MotorModel, lcm_url: str, out: Path
) -> dict:
    """The whole `hrp2-drake control`: build the fused controller, wait for the robot,
    run the message-driven loop, report (control.md with a latency histogram,
    control.json, control.npz). The summary says why the run ended ("fault")."""
    config.validate()
    robot = config.description()
    reference = control_reference(config)
    controller = FusedController(
        torque_chain_parts(robot, reference, motor_model, config.torque_control)
    )
    transport = open_transport(lcm_url, timeout=min(config.loop.wait_timeout, 2.0))
    try:
        loop = ControlLoop(controller, robot, transport, config.channels, reference,
                           config=config.loop_config())
        say(f"waiting for {robot.name} on {lcm_url} ...")
        loop.wait_for_robot()
        say(f"running {config.duration} s")
        summary = loop.run()
    finally:
        transport.close()
    signals = loop.signals()
    cols = [robot.joints.index(j) for j in config.torque_control.controlled_joints(robot)]
    after = signals["t"] >= config.torque_control.start_time + 0.1
    error = signals["q_ref"][after][:, cols] - signals["q_measured"][after][:, cols]
    summary |= {
        "robot": robot.name,
        "lcm": lcm_url,
        "duration": config.duration,
        "max_error_mrad": (np.abs(error).max(axis=0) * 1e3).tolist() if len(error) else [],
        "rms_error_mrad": (np.sqrt(np.mean(error**2, axis=0)) * 1e3).tolist() if len(error) else [],
    }
    out.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out / "control.npz", **signals)
    (out / "control.json").write_text(json.dumps(summary, indent=2))
    _latency_histogram(signals["latency_us"], config.period(), out / "latency.png")
    (out / "control.md").write_text(_markdown(robot, config, summary))
    return summary


def _latency_histogram(latency_us: np.ndarray, period: float, path: Path) -> None:
    fig, ax = pyplot().subplots(figsize=(7, 3.5))
    if len(latency_us):
        bins = np.logspace(np.log10(max(latency_us.min(), 1.0)), np.log10(latency_us.max() + 1), 60)
        ax.hist(latency_us, bins=bins, color="tab:blue")
        ax.set_xscale("log")
        ax.set_yscale("log")
    ax.axvline(period * 1e6, color="tab:red", linestyle="--", label=f"period {period * 1e6:.0f} µs")
    ax.set_xlabel("receive → publish latency (µs)")
    ax.set_ylabel("ticks")
    legend_beside(ax, fontsize=None)
    ax.set_title("Controller ticks over LCM")
    save_figure(fig, path, tight=True)


def _markdown(robot, config: LcmControlConfig, summary: dict) -> str:
    labels = robot.labels()
    lat = summary["latency_us"]
    lines = [
        f"# Torque control of {robot.name} over LCM ({summary['lcm']})",
        "",
        f"{config.duration} s, message-driven (the robot's encoder message clocks each "
        f"tick); motion: {config.motion}.",
        "",
        f"**How the run ended:** {_ending(summary)}",
        "",
        f"**Torque control active:** {summary['torque_share'] * 100:.1f}% of the ticks after "
        "start-up (start_time + the supervisor's ramp).",
        f"**Gave up for good** (more faults than the supervisor's max_reentries): "
        f"{'yes' if summary['gave_up'] else 'no'}.",
        "",
    ]
    if summary["max_error_mrad"]:
        lines += [
            "Errors as the encoders see them (q_ref − q_measured, mrad), after torque "
            "control started:",
            "",
            *markdown_table(
                [None, *labels],
                [
                    [name, *(f"{v:.2f}" for v in summary[key])]
                    for name, key in (("maximum", "max_error_mrad"), ("RMS", "rms_error_mrad"))
                ],
            ),
            "",
        ]
    rt = summary.get("real_time", {})
    lines += [
        "## Ticks",
        "",
        f"{summary['ticks']} ticks; receive → publish latency: p50 {lat['p50']:.0f} µs, "
        f"p99 {lat['p99']:.0f} µs, p99.9 {lat['p99.9']:.0f} µs, max {lat['max']:.0f} µs; "
        f"{summary['overruns']} ticks over the period (the longest run of consecutive "
        f"ones: {summary['longest_overrun_run']}; followed by a fallback within 50 ms: "
        f"{summary['overruns_followed_by_a_fallback']}); {summary['refused_samples']} "
        "samples refused (timestamp not advancing).",
        f"Operating system: CPU {rt.get('cpu')}, scheduler {rt.get('scheduler')}"
        + (f" ({rt['error'].strip('; ')})" if rt.get("error") else "") + "; garbage "
        "collector frozen and disabled in the loop"
        + ("" if config.loop.real_time.freeze_gc else " (not: freeze_gc is off)") + ".",
        "",
        "![latency](latency.png)",
        "",
        "## Fallbacks",
        "",
    ]
    if summary["events"]:
        lines += markdown_table(
            ["t (s)", "what", "reason"],
            [[f"{e['t']:.3f}", f"{e['what']}", f"{e['reason']}"] for e in summary["events"]],
            align="rll",
        )
    else:
        lines.append("None.")
    if summary["overrun_times"]:
        lines += ["", "Overruns at t = " + ", ".join(f"{x:.3f}" for x in summary["overrun_times"]) + " s."]
    return "\n".join(lines) + "\n"


def _ending(summary: dict) -> str:
    """Why the run ended and what the robot was left with, in one sentence."""
    what = summary["fault"] or "its duration"
    when = f" at t = {summary['fault_time']:.3f} s" if summary["fault"] else ""
    if summary.get("ramped"):
        after = "the command then ramped to the measured pose (position control)"
    else:
        after = ("nothing could be sent any more: the robot's own watchdog holds its "
                 "pose")
    return f"{what}{when}; {after}."


def run_sim_robot(config: StationConfig, lcm_url: str, duration: float, out: Path | None,
                  channels: LcmChannels | None = None, rate: float = 1.0,
                  watchdog_periods: int = 5) -> dict:
    """The whole `hrp2-drake sim-robot`: `RobotBridge` in real time (or at `rate` times
    it) for `duration` s (inf: until SIGTERM or Ctrl-C); writes its ground truth
    (sim_robot.npz: t, state_true, q_measured, q_cmd, holding) to `out` on exit."""
    config.validate()
    bridge_config = BridgeConfig(duration=duration, rate=rate, watchdog_periods=watchdog_periods)
    bridge_config.validate()
    transport = open_transport(lcm_url)
    try:
        bridge = RobotBridge(config, transport, channels, bridge_config)
        say(f"{bridge.robot.name} on {lcm_url}")
        summary = bridge.run()
    finally:
        transport.close()
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(out / "sim_robot.npz", joint_names=np.array(bridge.robot.joints),
                            **bridge.signals())
        (out / "sim_robot.json").write_text(json.dumps(summary, indent=2))
    return summary
