"""The controller's real-time loop, one for every robot link, and the simulated robot
over LCM.

`ControlLoop` (the controller, `hrp2-drake control`): each period, the link
(`hardware.link.RobotLink`) writes the period's samples into the fused controller's
buffers, one tick of the `FusedController` runs, and the link sends the command at
once. Over LCM (`hardware.lcm_link.LcmLink`) the robot's encoder message is the
clock; on a Dynamixel bus (`hardware.dynamixel.DynamixelLink`) the loop's own clock,
one sync read and one sync write per period. No Simulator paces it, and Python's
garbage collector does not run inside the loop (`gc.freeze()` after start-up, then
`gc.disable()` until the loop ends). It refuses to start before the fused controller's
kernels are compiled (`FusedController.warm_up`), and nothing compiles while it runs
(`hrp2_drake.kernels.freeze`: a kernel called with a new signature raises, which ends
the run in a ramp).

It fails safe. Whatever ends a run (its duration, a malformed or stale message, a
silent robot or servo, a servo's hardware error, an exception, SIGTERM/SIGINT), the
command ramps from the last one sent to the measured pose over `ramp_time`
(position control holding the robot), the report is written with the fault and its
time, and the process ends with one line. Where the link itself is gone nothing can
be sent: the loop ends cleanly and the robot's own watchdog (or its servos' position
loop) holds the pose.

`RobotBridge` (the robot, `hrp2-drake sim-robot`): the reference for a real robot's
LCM bridge. Every period it publishes the sensors (F/T and IMU first, the encoders
last, stamped with the robot's clock), applies the latest command, and guards itself:
after `watchdog_periods` without a new command it holds the measured pose until
commands come again.

`run_in_process` and `run_on_bus_in_process`: the fused controller on the simulated
robot in one process with the LCM loop's and the bus loop's timing, what the loops
are tested against.
"""

import contextlib
import gc
import math
import os
import signal
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from hrp2_drake import kernels
from hrp2_drake.control.fused import ControllerLayout, EventKind, FusedController
from hrp2_drake.control.safety import describe_faults
from hrp2_drake.control.torque_controller import FALLBACK_REASONS
from hrp2_drake.hardware.lcm_station import LcmChannels
from hrp2_drake.hardware.link import LinkClosed, LoopFault, RobotLink
from hrp2_drake.hardware.messages import SignalCodec
from hrp2_drake.hardware.transport import Transport, TransportClosed


@dataclass
class RealTimeConfig:
    """How the loop asks the operating system for real time.

    Args:
        cpu: pin the process to this CPU (-1: leave it).
        priority: ask for SCHED_FIFO at this priority (0: the normal scheduler).
        freeze_gc: collect and freeze the garbage collector's objects after start-up
            and disable it while the loop runs.
    """

    cpu: int = -1
    priority: int = 0
    freeze_gc: bool = True


def request_real_time(config: RealTimeConfig) -> dict:
    """Pins the CPU and asks for SCHED_FIFO as configured; what was granted."""
    granted = {"cpu": None, "scheduler": "SCHED_OTHER", "error": ""}
    if config.cpu >= 0:
        try:
            os.sched_setaffinity(0, {config.cpu})
            granted["cpu"] = config.cpu
        except OSError as error:
            granted["error"] += f"cpu {config.cpu}: {error.strerror}; "
    if config.priority > 0:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(config.priority))
            granted["scheduler"] = f"SCHED_FIFO {config.priority}"
        except (OSError, AttributeError) as error:
            granted["error"] += f"SCHED_FIFO: {getattr(error, 'strerror', error)}; "
    return granted


@contextlib.contextmanager
def garbage_collector_frozen(freeze: bool = True) -> Iterator[None]:
    """Within it, Python's garbage collector does not run (the objects of start-up
    collected and frozen first): a collection of a process that imported Drake takes
    tens of ms, more than a period. Everything the same without `freeze`."""
    if freeze:
        gc.collect()
        gc.freeze()
        gc.disable()
    try:
        yield
    finally:
        if freeze:
            gc.enable()
            gc.unfreeze()


def _check_time(value, name: str) -> None:
    """Raises ValueError naming `name` unless `value` is a time: finite, > 0 (s)."""
    if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
        raise ValueError(f"{name}: {value!r} must be a finite number > 0 (s)")


@dataclass
class LoopSettings:
    """The controller loop's own settings (what a run does not set itself).

    Args:
        wait_timeout: how long to wait for the first message of every channel (s).
        silence_timeout: the robot is silent after this long without a new encoder
            sample (s): the loop ramps out.
        ramp_time: the ramp from the last command to the measured pose that ends
            every run (s).
        real_time: CPU pinning, SCHED_FIFO priority, garbage collector.
    """

    wait_timeout: float = 10.0
    silence_timeout: float = 0.05
    ramp_time: float = 0.2
    real_time: RealTimeConfig = field(default_factory=RealTimeConfig)

    def validate(self, period: float = 0.0, where: str = "LoopSettings") -> None:
        """Raises ValueError naming `where`.<field>: each time finite and > 0, and
        silence_timeout at least two control periods (`period`, s; 0: unknown)."""
        for name in ("wait_timeout", "silence_timeout", "ramp_time"):
            _check_time(getattr(self, name), f"{where}.{name}")
        if self.silence_timeout < 2 * period:
            raise ValueError(
                f"{where}.silence_timeout: {self.silence_timeout} s is shorter than "
                f"two periods ({2 * period} s)"
            )


@dataclass
class LoopConfig:
    """The controller loop's settings for one run.

    Args:
        duration: seconds of robot time to run (from the first encoder message).
        period: the robot's sensor period (s): the tick's budget.
        settings: the loop's own settings (timeouts, ramp, real time).
    """

    duration: float = 5.0
    period: float = 0.001
    settings: LoopSettings = field(default_factory=LoopSettings)

    def validate(self) -> None:
        for name in ("duration", "period"):
            _check_time(getattr(self, name), f"LoopConfig.{name}")
        self.settings.validate(self.period, "LoopConfig.settings")


class ControlLoop:
    """The controller's loop over any robot link (module docstring).

    Args:
        controller: the fused controller (built for the link's robot).
        link: the robot (`RobotLink`), connected (`RobotLink.connect`).
        reference: a `JointReference` (q, v, vdot of every joint over time).
        force_reference: f_ref(t) (6) of a force task, or None.
        config: the loop's settings.
    """

    def __init__(
        self,
        controller: FusedController,
        link: RobotLink,
        reference,
        force_reference=None,
        config: LoopConfig | None = None,
    ):
        self.controller = controller
        self.link = link
        self.reference = reference
        self.force_reference = force_reference
        self.config = config = config or LoopConfig()
        config.validate()
        N = len(controller.q_measured)
        self._q_cmd = np.zeros(N)
        self.t = 0.0
        self.ticks = 0
        self.fault: LoopFault | None = None
        self.fault_time = math.nan
        capacity = int(config.duration / config.period * 1.2) + 1000
        self.latency_ns = np.zeros(capacity, dtype=np.int64)
        self.cycle_ns = np.zeros(capacity, dtype=np.int64)
        self.receive_gap_ns = np.zeros(capacity, dtype=np.int64)
        self.log_t = np.zeros(capacity)
        self.log = {
            name: np.zeros((capacity, N)) for name in ("q_ref", "q_measured", "q_cmd")
        }
        self.log_mode = np.zeros(capacity)
        self._last_receive = 0
        self._stop = False
        self.ramped = False

    @property
    def refused(self) -> int:
        """Samples the link refused (an old or repeated timestamp)."""
        return self.link.counters().get("refused_samples", 0)

    # ---------------------------------------------------------------- periods

    def step(self, timeout: float = 0.0) -> bool:
        """One period if the link has one within `timeout` s (receive, tick, send);
        whether it had. What `run` repeats; a lock-step test calls it alone."""
        t = self.link.receive(self.controller, timeout)
        if t is None:
            return False
        self._tick(t)
        return True

    def _tick(self, t: float) -> None:
        controller, link = self.controller, self.link
        first = self.ticks == 0
        self.t = t
        self._set_reference(t)
        if first:
            controller.initialize(t)
        controller.tick(t)
        q_cmd = controller.command(controller.q_ref, self._q_cmd)
        link.send(q_cmd, t)
        done = time.perf_counter_ns()
        received = link.received_ns
        k = self.ticks
        if k < len(self.latency_ns):
            self.latency_ns[k] = done - received
            self.cycle_ns[k] = done - link.started_ns
            self.receive_gap_ns[k] = received - self._last_receive if k else 0
            self.log_t[k] = t
            self.log["q_ref"][k] = controller.q_ref
            self.log["q_measured"][k] = controller.q_measured
            self.log["q_cmd"][k] = q_cmd
            self.log_mode[k] = controller.torque_active()
        self._last_receive = received
        self.ticks = k + 1
        if t >= self.config.duration:
            self._stop = True

    def _set_reference(self, t: float) -> None:
        controller = self.controller
        controller.q_ref[:], controller.v_ref[:], controller.vdot_ref[:] = (
            self.reference.at(t)
        )
        if self.force_reference is not None:
            controller.f_ref[:] = self.force_reference.value(t)[:, 0]

    # ---------------------------------------------------------------- running

    def run(self) -> dict:
        """Runs until the duration (robot time), a fault, or a signal; ramps out; the
        run's summary (see `summary`)."""
        if not self.controller.warmed_up:
            raise RuntimeError(
                "the control loop refuses to start: its fused controller's kernels are "
                "not compiled (call FusedController.warm_up() before the loop)"
            )
        config = self.config.settings
        granted = request_real_time(config.real_time)
        previous = {
            sig: signal.signal(sig, self._on_signal)
            for sig in (signal.SIGTERM, signal.SIGINT)
        }
        try:
            with garbage_collector_frozen(config.real_time.freeze_gc), kernels.compile_disabled():
                self._loop(config.silence_timeout)
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
        return self.summary(granted)

    def _loop(self, silence: float) -> None:
        """Periods until the end, then the ramp out; a fault recorded on the way."""
        try:
            while not self._stop:
                if not self.step(silence):
                    raise LoopFault(self.link.silence(silence))
        except LinkClosed as error:
            self._set_fault(LoopFault(self.link.gone(error)))
            return
        except LoopFault as error:
            self._set_fault(error)
        except Exception as error:  # a bug must not leave the robot in torque mode
            self._set_fault(LoopFault(f"{type(error).__name__}: {error}"))
        self._ramp_out()

    def _on_signal(self, signum, frame) -> None:
        self._set_fault(LoopFault(f"stopped by {signal.Signals(signum).name}"))
        self._stop = True

    def _set_fault(self, fault: LoopFault) -> None:
        if self.fault is None:
            self.fault = fault
            self.fault_time = self.t if fault.t is None else fault.t

    def _ramp_out(self) -> None:
        """From the last command to the measured pose over ramp_time, one command per
        period: each after the period's samples where they still come (a lock-step
        robot's clock is its traffic), on the wall clock where they do not (the robot
        may have gone silent)."""
        period = self.config.period
        q_from = self._q_cmd.copy()
        q_hold = self.controller.q_measured.copy()
        if not np.all(np.isfinite(q_hold)):
            q_hold = q_from
        steps = max(1, int(round(self.config.settings.ramp_time / period)))
        start = time.perf_counter()
        try:
            for k in range(1, steps + 1):
                try:
                    self.link.receive(self.controller, period)
                except LoopFault:
                    pass  # a faulty sample does not stop the ramp
                s = k / steps
                self.link.send((1.0 - s) * q_from + s * q_hold, self.t + k * period)
                delay = start + k * period - time.perf_counter()
                if delay > 0 and not self.link.lockstep:
                    time.sleep(delay)
        except LinkClosed as error:
            self._set_fault(LoopFault(f"{self.link.gone(error)} (during the ramp)"))
            return
        self.ramped = True

    # ---------------------------------------------------------------- report

    def summary(self, granted: dict | None = None) -> dict:
        """Ticks, latency (samples in to command out), the period's cycle (the
        exchange's start to the command out), overruns, torque share, events, what
        the link counted."""
        k = min(self.ticks, len(self.latency_ns))
        latency = self.latency_ns[:k] * 1e-3
        cycle = self.cycle_ns[:k] * 1e-3
        period_us = self.config.period * 1e6
        controller = self.controller
        # Start-up: position control until start_time, then the supervisor's ramp.
        supervisor = controller.parts.supervisor
        start = controller.parts.controller_config.start_time
        if supervisor is not None:
            start += supervisor.config.ramp_time
        after = self.log_t[:k] >= start
        share = (
            float(np.mean(self.log_mode[:k][after] >= 1.0)) if np.any(after) else 0.0
        )
        overruns = np.flatnonzero(cycle > period_us)
        percentile = (
            (lambda x, p: float(np.percentile(x, p))) if k else (lambda x, p: math.nan)
        )
        faults = controller.event_counts[EventKind.SUPERVISOR_FAULT]
        gave_up = supervisor is not None and faults > supervisor.config.max_reentries
        return {
            "ticks": int(self.ticks),
            "refused_samples": int(self.refused),
            "latency_us": {
                "p50": percentile(latency, 50),
                "p99": percentile(latency, 99),
                "p99.9": percentile(latency, 99.9),
                "max": float(latency.max()) if k else math.nan,
            },
            "cycle_us": {
                "p50": percentile(cycle, 50),
                "p99": percentile(cycle, 99),
                "max": float(cycle.max()) if k else math.nan,
            },
            "overruns": int(len(overruns)),
            "overrun_times": [float(self.log_t[i]) for i in overruns[:50]],
            "longest_overrun_run": _longest_run(overruns),
            "overruns_followed_by_a_fallback": self._followed_by_a_fallback(overruns),
            "torque_share": share,
            "events": self._events(),
            "event_counts": {
                kind.name.lower(): count
                for kind, count in controller.event_counts.items()
            },
            "gave_up": bool(gave_up),
            "fault": str(self.fault) if self.fault else "",
            "fault_time": (
                None if math.isnan(self.fault_time) else float(self.fault_time)
            ),
            "ramped": bool(self.ramped),
            "ending": self.link.ending(self.ramped),
            "link": {"name": self.link.name, **self.link.counters()},
            "real_time": granted or {},
        }

    def _events(self) -> list[dict]:
        events = []
        for t, kind, code in self.controller.recorded_events():
            if kind == EventKind.CONTROLLER_FALLBACK:
                events.append(
                    {
                        "t": t,
                        "what": "controller fallback",
                        "reason": FALLBACK_REASONS.get(code, str(code)),
                    }
                )
            elif kind == EventKind.SUPERVISOR_FAULT:
                events.append(
                    {
                        "t": t,
                        "what": "supervisor fault",
                        "reason": describe_faults(code),
                    }
                )
        return events

    def _followed_by_a_fallback(self, overruns: np.ndarray) -> int:
        """Overruns followed by a fallback or a supervisor fault within 50 ms."""
        fault_times = np.array([t for t, _, _ in self.controller.recorded_events()])
        if not len(fault_times):
            return 0
        return sum(
            bool(
                np.any(
                    (fault_times >= self.log_t[i])
                    & (fault_times < self.log_t[i] + 0.05)
                )
            )
            for i in overruns
        )

    def signals(self) -> dict[str, np.ndarray]:
        k = min(self.ticks, len(self.latency_ns))
        out = {
            "t": self.log_t[:k].copy(),
            "latency_us": self.latency_ns[:k] * 1e-3,
            "cycle_us": self.cycle_ns[:k] * 1e-3,
            "receive_gap_us": self.receive_gap_ns[:k] * 1e-3,
            "torque_active": self.log_mode[:k].copy(),
        }
        return out | {name: log[:k].copy() for name, log in self.log.items()}


def _longest_run(indices: np.ndarray) -> int:
    """The longest run of consecutive integers in the sorted `indices` (0 if none):
    each overrun alone (a stall), or in runs (a tick that cannot keep up)?"""
    if not len(indices):
        return 0
    breaks = np.flatnonzero(np.diff(indices) > 1)
    starts = np.concatenate([[0], breaks + 1])
    ends = np.concatenate([breaks, [len(indices) - 1]])
    return int((ends - starts).max() + 1)


# ------------------------------------------------------------------ the robot's side


@dataclass
class BridgeConfig:
    """The simulated robot's bridge (`RobotBridge`).

    Args:
        duration: seconds of robot time (inf: until SIGTERM or SIGINT).
        rate: the real-time rate (1 on a robot; < 1 slows the robot's clock).
        watchdog_periods: hold the measured pose after this many of its own periods
            without a new command (once commands have come).
        lockstep: the robot advances a period only once the command for the last
            one has come, or after `lockstep_timeout` s without one: a clock that
            does not depend on the machine, for tests (a real robot never waits).
        lockstep_timeout: how long a lock-step robot waits for a command (s of wall
            time): before the first command, and when the controller is gone.
    """

    duration: float = math.inf
    rate: float = 1.0
    watchdog_periods: int = 5
    lockstep: bool = False
    lockstep_timeout: float = 0.2

    def validate(self) -> None:
        if not (self.duration > 0):
            raise ValueError(f"BridgeConfig.duration: {self.duration} must be > 0 (s)")
        if not (math.isfinite(self.rate) and self.rate > 0):
            raise ValueError(
                f"BridgeConfig.rate: {self.rate} must be a finite number > 0"
            )
        if not (isinstance(self.watchdog_periods, int) and self.watchdog_periods >= 1):
            raise ValueError(
                f"BridgeConfig.watchdog_periods: {self.watchdog_periods!r} must be an "
                "integer >= 1"
            )
        _check_time(self.lockstep_timeout, "BridgeConfig.lockstep_timeout")


class RobotBridge:
    """The simulated robot behind the LCM channels (module docstring).

    Each period k: the station advances to t_k (its discrete updates at t_{k−1} used
    the command in force), its sensors at t_k are published (F/T, IMU, then the
    encoders, stamped t_k), and every command that arrives before the next period is
    applied at once. The ground truth is logged for evaluation only.
    """

    def __init__(
        self,
        station_config,
        transport: Transport,
        channels: LcmChannels | None = None,
        config: BridgeConfig | None = None,
    ):
        from pydrake.systems.analysis import Simulator

        from hrp2_drake.robot.station import initial_joint_positions, make_station

        self.config = config = config or BridgeConfig()
        config.validate()
        robot = self.robot = station_config.description()
        self.channels = channels = (channels or LcmChannels()).resolved(robot)
        self.transport = transport
        self.period = station_config.sensors_config().period
        self.station = make_station(station_config)
        self.simulator = Simulator(self.station)
        self._context = self.simulator.get_mutable_context()
        self._q_cmd_port = self.station.GetInputPort("q_cmd")
        self._home = initial_joint_positions(station_config)
        self._command = self._home.copy()
        self._q_cmd_port.FixValue(self._context, self._command)
        # One message per channel, of its station ports (the IMU's two in one).
        layout = ControllerLayout.of_robot(robot, stamped=False)
        self._messages = [
            ([self.station.GetOutputPort(port) for port in channel.signals], name, codec)
            for channel, name, codec in zip(
                layout.channels(), channels.sensors(robot), channels.codecs(robot),
                strict=True,
            )
        ]
        self._cmd_codec = SignalCodec(robot.joints, channels.q_cmd)
        self.k = 0
        self._last_command_k = -1
        self._last_command_stamp = -1
        self.watchdog_trips = 0
        self.late_periods = 0  # periods that started over a period behind real time
        self.holding = False
        self.malformed_commands = 0
        self.refused_commands = 0
        self.fault = ""
        self._log: list[tuple] = []
        transport.subscribe(channels.q_cmd, self._on_command)

    def _on_command(self, data: bytes) -> None:
        stamp = SignalCodec.timestamp(data)
        if stamp <= self._last_command_stamp and self._last_command_stamp >= 0:
            self.refused_commands += 1
            return
        try:
            values = self._cmd_codec.values(data)
        except ValueError:
            self.malformed_commands += 1
            return
        if not np.all(np.isfinite(values)):
            self.malformed_commands += 1
            return
        self._last_command_stamp = stamp
        self._last_command_k = self.k
        self.holding = False
        self._command[:] = values
        self._q_cmd_port.FixValue(self._context, self._command)

    def _watchdog(self) -> None:
        """Holds the measured pose once no new command has come for watchdog_periods
        of the robot's own periods (once commands have come): a robot that runs
        late counts its periods all the same."""
        if self._last_command_k < 0 or self.holding:
            return
        if self.k - self._last_command_k > self.config.watchdog_periods:
            self.hold()
            self.watchdog_trips += 1

    def _wait_for_command(self, stopped) -> bool:
        """Lock step: handles messages until a command newer than the last period's
        has come, or, once commands have come, lockstep_timeout s of wall time (the
        controller gone: the watchdog counts these periods). Before the first
        command it waits as long as it takes, sending its first sample again every
        lockstep_timeout (the controller ticks on it); holding its pose (the watchdog tripped) it
        waits for nothing. False if `stopped()` says so meanwhile."""
        timeout = self.config.lockstep_timeout
        deadline = time.perf_counter() + timeout
        self.transport.handle(0.0)  # at least once: a command that came meanwhile
        if self.holding:
            return True  # nothing to wait for: on at full speed until commands come
        while self._last_command_k < self.k:
            if stopped():
                return False
            if self._last_command_k < 0:
                # Nobody has answered yet: the sample again, for a controller that
                # subscribed after it went out (the same stamps: not a new period).
                self.transport.handle(timeout)
                if self._last_command_k < 0:
                    self.publish_sensors()
                continue
            remaining = deadline - time.perf_counter()
            if remaining <= 0:
                break
            self.transport.handle(remaining)
        return True

    def hold(self) -> None:
        """Holds the measured pose (the servo in position control)."""
        q = self.station.GetOutputPort("q_measured").Eval(self._context)
        self._command[:] = q
        self._q_cmd_port.FixValue(self._context, self._command)
        self.holding = True

    def publish_sensors(self) -> None:
        """The sensors at the current time: F/T and IMU first, the encoders last."""
        t = self._context.get_time()
        context = self._context
        messages = []
        for ports, channel, codec in self._messages:
            values = (
                np.concatenate([port.Eval(context) for port in ports])
                if len(ports) > 1
                else ports[0].Eval(context)
            )
            messages.append((channel, codec.encode(values, t)))
        self.transport.publish_many(messages[1:] + messages[:1])

    def step(self) -> None:
        """One period: advance to the next sample time, publish (`run` adds the
        watchdog and the real-time pacing; a lock-step test calls this alone)."""
        if self.k == 0:
            self.simulator.Initialize()
        else:
            self.simulator.AdvanceTo(self.k * self.period)
        self.publish_sensors()
        self._record()
        self.k += 1

    def _record(self) -> None:
        context = self._context
        self._log.append(
            (
                context.get_time(),
                self.station.GetOutputPort("state_true").Eval(context).copy(),
                self.station.GetOutputPort("q_measured").Eval(context).copy(),
                self._command.copy(),
                self.holding,
                self._last_command_k == self.k,  # a new command since the last period
            )
        )

    def run(self) -> dict:
        """Real time until the duration, a signal, or the transport's end."""
        stop = {"now": False}

        def terminate(signum, frame):
            stop["now"] = True

        previous = {
            s: signal.signal(s, terminate) for s in (signal.SIGTERM, signal.SIGINT)
        }
        wall_period = self.period / self.config.rate
        if self.k == 0:
            self.step()  # initialization: not timed against the clock
        start = time.perf_counter() - self.k * wall_period
        try:
            with garbage_collector_frozen():
                while not stop["now"] and self.k * self.period <= self.config.duration:
                    if self.config.lockstep:
                        if not self._wait_for_command(lambda: stop["now"]):
                            break
                        self._watchdog()
                        self.step()
                        continue
                    self.step()
                    deadline = start + self.k * wall_period
                    self.transport.handle(0.0)  # at least once: behind schedule too
                    while True:
                        remaining = deadline - time.perf_counter()
                        if remaining <= 0:
                            self.late_periods += remaining < -wall_period
                            break
                        self.transport.handle(remaining)
                    self._watchdog()
        except TransportClosed as error:
            self.fault = f"the transport is gone at t = {self._context.get_time():.3f} s ({error})"
            self.hold()
        finally:
            for s, handler in previous.items():
                signal.signal(s, handler)
        return self.summary()

    def summary(self) -> dict:
        return {
            "robot": self.robot.name,
            "simulated": float(self._context.get_time()),
            "watchdog_trips": int(self.watchdog_trips),
            "late_periods": int(self.late_periods),
            "holding": bool(self.holding),
            "malformed_commands": int(self.malformed_commands),
            "refused_commands": int(self.refused_commands),
            "fault": self.fault,
        }

    def signals(self) -> dict[str, np.ndarray]:
        """t, state_true, q_measured, q_cmd (applied), holding, commanded (a new
        command came since the last period): one row per period."""
        if not self._log:
            return {}
        columns = list(zip(*self._log))
        names = ("t", "state_true", "q_measured", "q_cmd", "holding", "commanded")
        return {
            name: np.array(column, dtype=float) for name, column in zip(names, columns)
        }


def run_in_process(
    station_config, controller: FusedController, reference, ticks: int, on_tick=None
) -> list[tuple[np.ndarray, np.ndarray]]:
    """The fused controller on the simulated station in one process, without messages,
    with the LCM loop's timing: the station's sample k (k >= 0; 0 at initialization,
    as the robot's bridge sends it) is the controller's tick at t = k period, and the
    command is applied at once. What the message-driven loop is tested against
    (tests/test_fused.py, tests/test_lcm.py with a lock-step robot), and the bench's
    closed-loop tick (`on_tick(tick)` wraps each tick: a timer). Returns (q_cmd, τ̂)
    per tick."""
    from pydrake.systems.analysis import Simulator

    from hrp2_drake.robot.station import initial_joint_positions, make_station

    robot = station_config.description()
    period = station_config.sensors_config().period
    station = make_station(station_config)
    simulator = Simulator(station)
    context = simulator.get_mutable_context()
    layout = controller.layout
    buffer = controller.sensor_buffer
    # The station's sensor ports (and its stamps, if the controller takes them),
    # each with its rows of the controller's sensor buffer.
    sensors = [
        (station.GetOutputPort(name), buffer[rows])
        for name, rows in layout.signals().items()
    ]
    if layout.num_stamps:
        sensors.append((station.GetOutputPort("sensor_time"), controller.sensor_time))
    q_cmd_port = station.GetInputPort("q_cmd")
    q_cmd_port.FixValue(context, initial_joint_positions(station_config))
    command = np.zeros(len(robot.joints))
    simulator.Initialize()
    out = []
    for k in range(ticks):
        if k:
            simulator.AdvanceTo(k * period)
        for port, rows in sensors:
            rows[:] = port.Eval(context)
        _tick_in_process(controller, reference, k * period, k == 0, on_tick, command)
        q_cmd_port.FixValue(context, command)
        out.append((command.copy(), controller.estimator.tau.copy()))
    return out


def _tick_in_process(controller: FusedController, reference, t: float, first: bool,
                     on_tick, command: np.ndarray) -> None:
    """One tick of an in-process run at t (s): the reference at t, the chain's
    initialization on the `first`, the tick and its command into `command`, wrapped
    by `on_tick(step)` if given (a timer)."""
    controller.q_ref[:], controller.v_ref[:], controller.vdot_ref[:] = reference.at(t)
    if first:
        controller.initialize(t)

    def step():
        controller.tick(t)
        controller.command(controller.q_ref, command)

    (on_tick or (lambda tick: tick()))(step)


def run_on_bus_in_process(
    station_config, controller: FusedController, reference, ticks: int, on_tick=None
) -> list[tuple[np.ndarray, np.ndarray]]:
    """The fused controller on the simulated robot's servos (`SimulatedServos`) in one
    process, without a wire, with the bus loop's timing: what `DynamixelLink` and a
    lock-step emulator (`hardware.sim_servo`) do, call for call.

    Start-up at robot time 0, as `DynamixelBus.start`: the P gain set
    (`position_loop.gain`), the present pose read (through the goal register's
    pulses) and made the goal, torque on. Then period k: the servos sample at k·T,
    one tick at t = k·T, and the command, in pulses, reaches them at k·T + d (d: the
    bus's `read_to_write`). `on_tick(step)` wraps each tick (a timer). Returns
    (q_cmd, τ̂) per tick.
    """
    from hrp2_drake.robot.bus_servos import SimulatedServos

    servos = SimulatedServos(station_config)
    robot = servos.robot
    bus = robot.bus
    period = station_config.sensors_config().period
    delay = bus.timing().read_to_write
    servos.set_gain(robot.position_loop.gain)
    servos.set_goal(bus.quantized(servos.present().position))
    servos.set_enabled(np.ones(len(robot.joints)))
    command = np.zeros(len(robot.joints))
    out = []
    for k in range(ticks):
        t = k * period
        servos.advance_to(t)
        controller.q_measured[:] = bus.quantized(servos.present().position)
        controller.q_measured_time[:] = t
        _tick_in_process(controller, reference, t, k == 0, on_tick, command)
        servos.advance_to(t + delay)
        servos.set_goal(bus.quantized(command))
        out.append((command.copy(), controller.estimator.tau.copy()))
    return out
