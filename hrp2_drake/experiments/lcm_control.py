"""`hrp2-drake control --lcm URL` and `hrp2-drake sim-robot --lcm URL`: the torque
controller against a robot over LCM, in real time, and the simulated robot that
stands in for the real one behind the same channels (hrp2_drake/hardware).

`control` builds `build_torque_control` on `make_lcm_station` (the same diagram as in
simulation, the station swapped), paces it with Drake's Simulator at a target
real-time rate of 1, and times every tick. `sim-robot` runs the simulated station
behind the channels, in real time, and on exit writes its ground truth for evaluation.
Start-up order: the robot (or `sim-robot`) first, then `control`, which waits for the
robot's first messages.
"""

import json
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydrake.lcm import DrakeLcm
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, EventStatus, LeafSystem

from hrp2_drake.control.safety import SafetyConfig
from hrp2_drake.experiments.builders import JointReference, TorqueControlConfig, build_torque_control
from hrp2_drake.experiments.track import TrackConfig, sinusoid_reference
from hrp2_drake.hardware.lcm_station import LcmChannels, make_lcm_station, make_sim_robot
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.robot.station import StationConfig, initial_joint_positions
from hrp2_drake.simulation import add_loggers, logs_to_arrays


@dataclass
class LcmControlConfig:
    """Configuration of `hrp2-drake control`.

    Args:
        station: names the robot (`station.robot`) and its home pose (the scenario's
            initial pose: what the reference starts from; use the robot's scenario).
        torque_control: the controller (its supervisor included; staleness limits
            widened for a transport's jitter).
        duration: how long to run (s of robot time).
        motion: "sinusoid" (every controlled joint around the home pose, `track`'s
            reference) or "hold" (the home pose).
        amplitude, frequency, settle: the sinusoids (rad, Hz) after `settle` s.
        realtime_rate: the Simulator's target real-time rate (1 on a robot).
        wait_timeout: how long to wait for the robot's first messages (s).
        channels: the LCM channels.
    """

    station: StationConfig = field(default_factory=StationConfig)
    torque_control: TorqueControlConfig = field(default_factory=lambda: TorqueControlConfig(
        start_time=0.5, window=41,
        # A sample may come a few ms late over a network (and two real-time processes
        # share 2 cores here): stale after 10 ms or 12 repeated samples, not 2.5 / 5.
        safety=SafetyConfig(stale_time=0.010, stale_samples=12),
    ))
    duration: float = 5.0
    motion: str = "sinusoid"
    amplitude: float = 0.2
    frequency: float = 0.4
    settle: float = 0.5
    realtime_rate: float = 1.0
    wait_timeout: float = 10.0
    channels: LcmChannels = field(default_factory=LcmChannels)

    def validate(self) -> None:
        self.station.validate()
        self.torque_control.validate()
        if self.motion not in ("sinusoid", "hold"):
            raise ValueError(f"LcmControlConfig.motion: '{self.motion}', expected sinusoid or hold")
        for name in ("duration", "realtime_rate", "wait_timeout"):
            if not getattr(self, name) > 0:
                raise ValueError(f"LcmControlConfig.{name} must be > 0, got {getattr(self, name)}")


def control_reference(config: LcmControlConfig) -> JointReference:
    robot = config.station.description()
    q0 = initial_joint_positions(config.station)
    if config.motion == "hold":
        return JointReference.hold(q0, config.duration + 1.0)
    track = TrackConfig(
        station=config.station, settle=config.settle, amplitude=config.amplitude,
        frequency=config.frequency, duration=config.duration + 1.0 - config.settle,
    )
    return sinusoid_reference(robot, q0, track)


class TickProbe(LeafSystem):
    """Records the wall-clock time at which each tick's processing starts: a periodic
    unrestricted update, which a Simulator step runs first, right after its real-time
    pause (instrumentation: the callback only appends to a list)."""

    def __init__(self, period: float):
        super().__init__()
        self.starts: list[float] = []
        self.DeclarePeriodicUnrestrictedUpdateEvent(period, 0.0, self._stamp)

    def _stamp(self, context, state) -> None:
        self.starts.append(time.perf_counter())


class TickTimer:
    """Times a real-time Simulator's ticks: a tick starts when its processing starts
    (`TickProbe`, after the Simulator's real-time pause) and ends with the last step
    before the next tick (steps in between: LCM messages arriving). Its tick time is
    the diagram's computation and LCM work for that period; it overruns when longer
    than the period."""

    def __init__(self, simulator: Simulator, probe: TickProbe, period: float):
        self._simulator, self._probe, self._period = simulator, probe, period
        self._ends: list[float] = []
        simulator.set_monitor(self._monitor)

    def start(self) -> None:
        """Call right before running: restarts the Simulator's real-time pacing (its
        baseline would otherwise include the wait for the robot's first messages) and
        forgets the ticks of the initialization."""
        self._simulator.ResetStatistics()
        self._probe.starts.clear()
        self._ends.clear()

    def _monitor(self, context):
        self._ends.append(time.perf_counter())
        return EventStatus.Succeeded()

    def statistics(self) -> dict:
        starts, ends = np.array(self._probe.starts), np.array(self._ends)
        if len(starts) < 3:
            return {"ticks": int(len(starts))}
        # The end of tick k: the last step end before tick k + 1 starts.
        last = np.searchsorted(ends, starts[1:]) - 1
        tick = ends[last] - starts[:-1]
        over = tick > self._period
        return {
            "ticks": int(len(tick)),
            "tick_us": {
                "median": float(np.median(tick) * 1e6),
                "p99": float(np.percentile(tick, 99) * 1e6),
                "max": float(tick.max() * 1e6),
            },
            "overruns": int(np.count_nonzero(over)),
            "overrun_times": [float(k * self._period) for k in np.flatnonzero(over)[:20]],
            "late_start_over_a_period": int(
                np.count_nonzero(np.diff(starts) > 2 * self._period)
            ),
        }


def run_control(
    config: LcmControlConfig, motor_model: MotorModel, lcm_url: str, out: Path
) -> dict:
    """The whole `hrp2-drake control`: build, wait for the robot, run in real time,
    report the tracking seen by the encoders and the tick times."""
    config.validate()
    robot = config.station.description()
    lcm = DrakeLcm(lcm_url)
    station = make_lcm_station(robot, lcm, config.channels, wait_timeout=config.wait_timeout)
    reference = control_reference(config)
    control = build_torque_control(
        config.station, reference, motor_model, config.torque_control, station=station
    )
    builder = DiagramBuilder()
    diagram = builder.AddNamedSystem("control", control.diagram)
    period = config.station.sensors_config().period
    probe = builder.AddNamedSystem("tick_probe", TickProbe(period))
    names = ["q_ref", "q_measured", "q_cmd", "supervisor_mode", "tau_estimated"]
    loggers = add_loggers(
        builder, {n: diagram.GetOutputPort(n) for n in names if diagram.HasOutputPort(n)}, 0.001
    )
    simulator = Simulator(builder.Build())
    simulator.set_target_realtime_rate(config.realtime_rate)
    timer = TickTimer(simulator, probe, period)
    print(f"control: waiting for {robot.name} on {lcm_url} ...", file=sys.stderr, flush=True)
    try:
        simulator.Initialize()
    except RuntimeError as error:
        raise TimeoutError(
            f"no message from the robot within {config.wait_timeout} s on {lcm_url} "
            f"({' '.join(str(error).split())}): start the robot's bridge (or "
            "`hrp2-drake sim-robot`) first, with the same --lcm URL and robot"
        ) from None
    print(f"control: running {config.duration} s in real time", file=sys.stderr, flush=True)
    timer.start()
    simulator.AdvanceTo(config.duration)
    signals = logs_to_arrays(loggers, simulator.get_context())
    timing = timer.statistics()
    cols = [robot.joints.index(j) for j in config.torque_control.controlled_joints(robot)]
    after = signals["t"] >= config.torque_control.start_time + 0.1
    error = signals["q_ref"][after][:, cols] - signals["q_measured"][after][:, cols]
    summary = {
        "robot": robot.name,
        "lcm": lcm_url,
        "duration": config.duration,
        "timing": timing,
        "max_error_mrad": (np.abs(error).max(axis=0) * 1e3).tolist(),
        "rms_error_mrad": (np.sqrt(np.mean(error**2, axis=0)) * 1e3).tolist(),
        "supervisor_mode_final": float(signals["supervisor_mode"][-1, 0])
        if "supervisor_mode" in signals else None,
    }
    out.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out / "control.npz", **signals)
    (out / "control.json").write_text(json.dumps(summary, indent=2))
    (out / "control.md").write_text(_markdown(robot, config, summary))
    return summary


def _markdown(robot, config: LcmControlConfig, summary: dict) -> str:
    t = summary["timing"]
    labels = robot.labels()
    lines = [
        f"# Torque control of {robot.name} over LCM ({summary['lcm']})",
        "",
        f"{config.duration} s paced at {config.realtime_rate}x real time; motion: "
        f"{config.motion}. Errors as the encoders see them (q_ref − q_measured, mrad), "
        "after torque control started.",
        "",
        "| | " + " | ".join(labels) + " |",
        "| --- |" + " ---: |" * len(labels),
        "| maximum | " + " | ".join(f"{v:.2f}" for v in summary["max_error_mrad"]) + " |",
        "| RMS | " + " | ".join(f"{v:.2f}" for v in summary["rms_error_mrad"]) + " |",
        "",
        "## Ticks",
        "",
        f"{t.get('ticks', 0)} ticks; tick time (from the start of a tick's processing, after "
        "the real-time pause, to its end: computation and LCM work): median "
        f"{t['tick_us']['median']:.0f} µs, p99 {t['tick_us']['p99']:.0f} µs, max "
        f"{t['tick_us']['max']:.0f} µs; {t['overruns']} ticks over the period; "
        f"{t['late_start_over_a_period']} ticks started more than a period late (the "
        "previous tick's overrun, or the scheduler).",
    ]
    if t["overrun_times"]:
        lines.append(f"Overruns at t = {', '.join(f'{x:.3f}' for x in t['overrun_times'])} s.")
    return "\n".join(lines) + "\n"


def run_sim_robot(config: StationConfig, lcm_url: str, duration: float, out: Path | None,
                  channels: LcmChannels | None = None, rate: float = 1.0) -> dict:
    """The whole `hrp2-drake sim-robot`: the simulated robot behind the LCM channels,
    in real time (or at `rate` times it), for `duration` s (inf: until SIGTERM or
    Ctrl-C); writes its ground
    truth (sim_robot.npz: t, state_true, q_measured, q_cmd) to `out` on exit."""
    config.validate()
    robot = config.description()
    lcm = DrakeLcm(lcm_url)
    robot_diagram = make_sim_robot(config, lcm, channels)
    builder = DiagramBuilder()
    diagram = builder.AddNamedSystem("robot", robot_diagram)
    loggers = add_loggers(
        builder, {n: diagram.GetOutputPort(n) for n in ("state_true", "q_measured", "q_cmd")}, 0.001
    )
    simulator = Simulator(builder.Build())
    simulator.set_target_realtime_rate(rate)
    simulator.Initialize()
    stop = {"now": False}

    def terminate(*_):
        stop["now"] = True

    previous = signal.signal(signal.SIGTERM, terminate)
    print(f"sim-robot: {robot.name} on {lcm_url}", file=sys.stderr, flush=True)
    try:
        t = 0.0
        while t < duration and not stop["now"]:
            t = min(duration, t + 0.1)
            simulator.AdvanceTo(t)
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGTERM, previous)
    signals = logs_to_arrays(loggers, simulator.get_context())
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(out / "sim_robot.npz", joint_names=np.array(robot.joints), **signals)
    return {"robot": robot.name, "simulated": float(simulator.get_context().get_time())}
