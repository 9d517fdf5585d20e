"""Message-driven real-time loops over LCM: the controller's and the robot's.

`ControlLoop` (the controller, `hrp2-drake control`): the robot's encoder message is
the clock. Each new `<P>_Q_MEASURED` message is decoded into preallocated buffers, one
tick of the `FusedController` runs, and `<P>_Q_CMD` is published at once. The IMU and
F/T messages only update the latest values (and their stamps) when they arrive; the
robot sends them before the encoders of the same period. No Simulator paces it, no
LCM system takes extra steps, and Python's garbage collector does not run inside the
loop (`gc.freeze()` after start-up, then `gc.disable()` until the loop ends).

It fails safe. Whatever ends a run (its duration, a malformed or stale message, a
silent robot, an exception, SIGTERM/SIGINT), the command ramps from the last one sent
to the measured pose over `ramp_time` (position control holding the robot), the report
is written with the fault and its time, and the process ends with one line. Where the
transport itself is gone nothing can be sent: the loop ends cleanly and the robot's
own watchdog holds the pose.

`RobotBridge` (the robot, `hrp2-drake sim-robot`): the reference for a real robot's
bridge. Every period it publishes the sensors (F/T and IMU first, the encoders last,
stamped with the robot's clock), applies the latest command, and guards itself: after
`watchdog_periods` without a new command it holds the measured pose until commands
come again.
"""

import gc
import math
import os
import signal
import time
from dataclasses import dataclass, field

import numpy as np

from hrp2_drake.control.fused import (
    EVENT_CONTROLLER_FALLBACK,
    EVENT_SUPERVISOR_FAULT,
    FusedController,
)
from hrp2_drake.control.safety import describe_faults
from hrp2_drake.control.torque_controller import FALLBACK_REASONS
from hrp2_drake.description import RobotDescription
from hrp2_drake.hardware.lcm_station import IMU_COORDS, LcmChannels
from hrp2_drake.hardware.messages import SignalCodec, WrenchCodec
from hrp2_drake.hardware.transport import Transport, TransportClosed


class LoopFault(RuntimeError):
    """What ended a loop early (the message names it)."""


@dataclass
class _SensorChannel:
    """An IMU or F/T channel of the controller: its codec, the rows of the fused
    controller's sensor values and stamps it writes, the stamp's unit (s), and the
    latest stamp (-1: none yet)."""

    codec: object
    values: np.ndarray
    stamp_rows: np.ndarray
    unit: float
    last_stamp: int = -1


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
    """The controller's message-driven loop (module docstring).

    Args:
        controller: the fused controller (built for `robot`).
        robot: the robot description (joint names, IMU, F/T sensors).
        transport: the LCM transport (`transport.open_transport`).
        channels: the channel names.
        reference: a `JointReference` (q, v, vdot of every joint over time).
        force_reference: f_ref(t) (6) of a force task, or None.
        config: the loop's settings.
    """

    def __init__(self, controller: FusedController, robot: RobotDescription,
                 transport: Transport, channels: LcmChannels, reference,
                 force_reference=None, config: LoopConfig | None = None):
        self.controller = controller
        self.robot = robot
        self.transport = transport
        self.channels = channels = channels.resolved(robot)
        self.reference = reference
        self.force_reference = force_reference
        self.config = config = config or LoopConfig()
        config.validate()
        N = len(robot.joints)
        self._N = N
        self._q_codec = SignalCodec(robot.joints, channels.q_measured)
        self._cmd_codec = SignalCodec(robot.joints, channels.q_cmd)
        # The other sensor channels, each writing into the controller's buffers.
        values = controller.sensor_values
        stamps = controller.sensor_time
        self._others: list[_SensorChannel] = []
        row, stamp_row = 0, 1
        if robot.has_imu():
            codec = SignalCodec(IMU_COORDS, channels.imu)
            # The IMU's one message stamps its two signals (accelerometer, gyro).
            self._others.append(_SensorChannel(codec, values[0:6], stamps[1:3], 1e-6))
            row, stamp_row = 6, 3
        for name in robot.sensor_names():
            codec = WrenchCodec(channels.wrench(name))
            self._others.append(_SensorChannel(
                codec, values[row : row + 6], stamps[stamp_row : stamp_row + 1], 1e-3
            ))
            row, stamp_row = row + 6, stamp_row + 1
        self._q_cmd = np.zeros(N)
        self._last_stamp = -1
        self._first_stamp = -1
        self.t = 0.0
        self.ticks = 0
        self.refused = 0
        self.fault: LoopFault | None = None
        self.fault_time = math.nan
        capacity = int(config.duration / config.period * 1.2) + 1000
        self.latency_ns = np.zeros(capacity, dtype=np.int64)
        self.receive_gap_ns = np.zeros(capacity, dtype=np.int64)
        self.log_t = np.zeros(capacity)
        self.log = {name: np.zeros((capacity, N)) for name in ("q_ref", "q_measured", "q_cmd")}
        self.log_mode = np.zeros(capacity)
        self._last_receive = 0
        self._stop = False
        self._armed = False  # ticks only once every channel has spoken
        self.ramped = False
        self._seen: set[str] = set()
        transport.subscribe(channels.q_measured, self._on_q_measured)
        for other in self._others:
            transport.subscribe(
                other.codec.channel, lambda data, c=other: self._on_sensor(c, data)
            )

    # ---------------------------------------------------------------- messages

    def _on_sensor(self, channel: "_SensorChannel", data: bytes) -> None:
        self._seen.add(channel.codec.channel)
        stamp = channel.codec.timestamp(data)
        if stamp <= channel.last_stamp:
            self.refused += 1
            return
        try:
            channel.values[:] = channel.codec.values(data)
        except ValueError as error:
            raise LoopFault(str(error)) from None
        channel.last_stamp = stamp
        if self._first_stamp >= 0:
            channel.stamp_rows[:] = stamp * channel.unit - self._first_stamp * 1e-6

    def _on_q_measured(self, data: bytes) -> None:
        received = time.perf_counter_ns()
        if not self._armed:
            self._seen.add(self.channels.q_measured)
            return
        stamp = SignalCodec.timestamp(data)
        if stamp <= self._last_stamp:
            self.refused += 1  # an old or repeated sample: not a new period
            return
        controller = self.controller
        try:
            controller.q_measured[:] = self._q_codec.values(data)
        except ValueError as error:
            raise LoopFault(str(error)) from None
        first = self._first_stamp < 0
        if first:
            self._first_stamp = stamp
            for other in self._others:
                other.stamp_rows[:] = other.last_stamp * other.unit - stamp * 1e-6
        self._last_stamp = stamp
        t = self.t = (stamp - self._first_stamp) * 1e-6
        controller.sensor_time[0] = t
        self._set_reference(t)
        if first:
            controller.initialize(t)
        controller.tick(t)
        q_cmd = controller.command(controller.q_ref, self._q_cmd)
        self.transport.publish(self.channels.q_cmd, self._cmd_codec.encode(q_cmd, t))
        done = time.perf_counter_ns()
        k = self.ticks
        if k < len(self.latency_ns):
            self.latency_ns[k] = done - received
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
        controller, N = self.controller, self._N
        x = self.reference.trajectory.value(t)[:, 0]
        controller.q_ref[:] = x[:N]
        controller.v_ref[:] = x[N : 2 * N]
        controller.vdot_ref[:] = x[2 * N :]
        if self.force_reference is not None:
            controller.f_ref[:] = self.force_reference.value(t)[:, 0]

    # ---------------------------------------------------------------- running

    def wait_for_robot(self) -> None:
        """Waits up to wait_timeout for a message on every sensor channel (without
        ticking); a TimeoutError naming the silent ones otherwise."""
        channels = [self.channels.q_measured] + [c.codec.channel for c in self._others]
        deadline = time.monotonic() + self.config.settings.wait_timeout
        try:
            while len(self._seen) < len(channels) and time.monotonic() < deadline:
                self.transport.handle(max(min(0.05, deadline - time.monotonic()), 0.0))
        except LoopFault as error:
            raise ValueError(f"the robot's first messages: {error}") from None
        silent = [channel for channel in channels if channel not in self._seen]
        if silent:
            raise TimeoutError(
                f"no message from the robot on {', '.join(silent)} within "
                f"{self.config.settings.wait_timeout:g} s on {self.transport.url}: start the "
                "robot's bridge (or `hrp2-drake sim-robot`) first, with the same URL "
                "and robot"
            )
        self._armed = True

    def run(self) -> dict:
        """Runs until the duration (robot time), a fault, or a signal; ramps out; the
        run's summary (see `summary`)."""
        config = self.config.settings
        granted = request_real_time(config.real_time)
        previous = {
            sig: signal.signal(sig, self._on_signal) for sig in (signal.SIGTERM, signal.SIGINT)
        }
        if config.real_time.freeze_gc:
            gc.collect()
            gc.freeze()
            gc.disable()
        silence_ns = int(config.silence_timeout * 1e9)
        try:
            last_tick, ticks = time.perf_counter_ns(), self.ticks
            while not self._stop:
                self.transport.handle(config.silence_timeout / 4)
                now = time.perf_counter_ns()
                if self.ticks != ticks:
                    last_tick, ticks = now, self.ticks
                elif now - last_tick > silence_ns:
                    raise LoopFault(
                        f"the robot went silent: no new {self.channels.q_measured} "
                        f"sample for {config.silence_timeout * 1e3:.0f} ms"
                    )
        except TransportClosed as error:
            self._set_fault(LoopFault(f"the transport is gone: {error}"))
        except LoopFault as error:
            self._set_fault(error)
            self._ramp_out()
        except Exception as error:  # a bug must not leave the robot in torque mode
            self._set_fault(LoopFault(f"{type(error).__name__}: {error}"))
            self._ramp_out()
        else:
            self._ramp_out()
        finally:
            if config.real_time.freeze_gc:
                gc.enable()
                gc.unfreeze()
            for sig, handler in previous.items():
                signal.signal(sig, handler)
        return self.summary(granted)

    def _on_signal(self, signum, frame) -> None:
        self._set_fault(LoopFault(f"stopped by {signal.Signals(signum).name}"))
        self._stop = True

    def _set_fault(self, fault: LoopFault) -> None:
        if self.fault is None:
            self.fault, self.fault_time = fault, self.t

    def _ramp_out(self) -> None:
        """From the last command to the measured pose over ramp_time, one command per
        period on the wall clock (the robot may have gone silent)."""
        q_from = self._q_cmd.copy()
        q_hold = self.controller.q_measured.copy()
        if not np.all(np.isfinite(q_hold)):
            q_hold = q_from
        steps = max(1, int(round(self.config.settings.ramp_time / self.config.period)))
        start = time.perf_counter()
        try:
            for k in range(1, steps + 1):
                s = k / steps
                command = (1.0 - s) * q_from + s * q_hold
                self.transport.publish(
                    self.channels.q_cmd, self._cmd_codec.encode(command, self.t + k * self.config.period)
                )
                delay = start + k * self.config.period - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
        except TransportClosed as error:
            self._set_fault(LoopFault(f"the transport is gone during the ramp: {error}"))
            return
        self.ramped = True

    # ---------------------------------------------------------------- report

    def summary(self, granted: dict | None = None) -> dict:
        """Ticks, latency (receive to publish), overruns, torque share, events."""
        k = min(self.ticks, len(self.latency_ns))
        latency = self.latency_ns[:k] * 1e-3
        period_us = self.config.period * 1e6
        controller = self.controller
        # Start-up: position control until start_time, then the supervisor's ramp.
        start = controller.parts.controller_config.start_time
        if controller.parts.supervisor is not None:
            start += controller.parts.supervisor[1].ramp_time
        after = self.log_t[:k] >= start
        share = float(np.mean(self.log_mode[:k][after] >= 1.0)) if np.any(after) else 0.0
        events = []
        for t, kind, code in controller.recorded_events():
            if kind == EVENT_CONTROLLER_FALLBACK:
                events.append({"t": t, "what": "controller fallback",
                               "reason": FALLBACK_REASONS.get(code, str(code))})
            elif kind == EVENT_SUPERVISOR_FAULT:
                events.append({"t": t, "what": "supervisor fault",
                               "reason": describe_faults(code)})
        overruns = np.flatnonzero(latency > period_us)
        # Each overrun alone (a stall), or in runs (a tick that cannot keep up)?
        longest_run = 0
        if len(overruns):
            breaks = np.flatnonzero(np.diff(overruns) > 1)
            starts = np.concatenate([[0], breaks + 1])
            ends = np.concatenate([breaks, [len(overruns) - 1]])
            longest_run = int((ends - starts).max() + 1)
        fault_times = np.array([t for t, kind, _ in controller.recorded_events()])
        followed = sum(
            bool(np.any((fault_times >= self.log_t[i]) & (fault_times < self.log_t[i] + 0.05)))
            for i in overruns
        ) if len(fault_times) else 0
        gave_up = False
        if controller.supervisor is not None:
            cfg = controller.parts.supervisor[1]
            gave_up = controller.event_counts[EVENT_SUPERVISOR_FAULT] > cfg.max_reentries
        percentile = (lambda p: float(np.percentile(latency, p))) if k else (lambda p: math.nan)
        return {
            "ticks": int(self.ticks),
            "refused_samples": int(self.refused),
            "latency_us": {
                "p50": percentile(50), "p99": percentile(99), "p99.9": percentile(99.9),
                "max": float(latency.max()) if k else math.nan,
            },
            "overruns": int(len(overruns)),
            "overrun_times": [float(self.log_t[i]) for i in overruns[:50]],
            "longest_overrun_run": longest_run,
            "overruns_followed_by_a_fallback": int(followed),
            "torque_share": share,
            "events": events,
            "event_counts": {"controller_fallback": controller.event_counts[EVENT_CONTROLLER_FALLBACK],
                             "supervisor_fault": controller.event_counts[EVENT_SUPERVISOR_FAULT]},
            "gave_up": bool(gave_up),
            "fault": str(self.fault) if self.fault else "",
            "fault_time": None if math.isnan(self.fault_time) else float(self.fault_time),
            "ramped": bool(self.ramped),
            "real_time": granted or {},
        }

    def signals(self) -> dict[str, np.ndarray]:
        k = min(self.ticks, len(self.latency_ns))
        out = {"t": self.log_t[:k].copy(), "latency_us": self.latency_ns[:k] * 1e-3,
               "receive_gap_us": self.receive_gap_ns[:k] * 1e-3,
               "torque_active": self.log_mode[:k].copy()}
        return out | {name: log[:k].copy() for name, log in self.log.items()}


# ------------------------------------------------------------------ the robot's side


@dataclass
class BridgeConfig:
    """The simulated robot's bridge (`RobotBridge`).

    Args:
        duration: seconds of robot time (inf: until SIGTERM or SIGINT).
        rate: the real-time rate (1 on a robot; < 1 slows the robot's clock).
        watchdog_periods: hold the measured pose after this many periods without a
            new command (once commands have come).
    """

    duration: float = math.inf
    rate: float = 1.0
    watchdog_periods: int = 5

    def validate(self) -> None:
        if not (self.duration > 0):
            raise ValueError(f"BridgeConfig.duration: {self.duration} must be > 0 (s)")
        if not (math.isfinite(self.rate) and self.rate > 0):
            raise ValueError(f"BridgeConfig.rate: {self.rate} must be a finite number > 0")
        if not (isinstance(self.watchdog_periods, int) and self.watchdog_periods >= 1):
            raise ValueError(
                f"BridgeConfig.watchdog_periods: {self.watchdog_periods!r} must be an "
                "integer >= 1"
            )


class RobotBridge:
    """The simulated robot behind the LCM channels (module docstring).

    Each period k: the station advances to t_k (its discrete updates at t_{k−1} used
    the command in force), its sensors at t_k are published (F/T, IMU, then the
    encoders, stamped t_k), and every command that arrives before the next period is
    applied at once. The ground truth is logged for evaluation only.
    """

    def __init__(self, station_config, transport: Transport,
                 channels: LcmChannels | None = None, config: BridgeConfig | None = None):
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
        self._codecs = list(zip(channels.sensors(robot), channels.codecs(robot)))
        ports = ["q_measured"]
        if robot.has_imu():
            ports.append(("imu_linear_acceleration", "imu_angular_velocity"))
        ports += [f"wrench_{name}" for name in robot.sensor_names()]
        self._ports = ports
        self._cmd_codec = SignalCodec(robot.joints, channels.q_cmd)
        self.k = 0
        self._last_command_k = -1
        self._last_command_stamp = -1
        self._last_command_wall = 0.0
        self._watch_from = 0.0
        self._watchdog_time = config.watchdog_periods * self.period / config.rate
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
        self._last_command_wall = time.perf_counter()
        self.holding = False
        self._command[:] = values
        self._q_cmd_port.FixValue(self._context, self._command)

    def _watchdog(self, now: float, late: bool) -> None:
        """Holds the measured pose once no new command has come for watchdog_periods
        periods of wall time (at the bridge's rate). While the robot itself is behind
        its clock (a stall of its own, catching up), that time does not run."""
        if late:
            self._watch_from = now
        if self._last_command_k < 0 or self.holding:
            return
        if now - max(self._last_command_wall, self._watch_from) > self._watchdog_time:
            self.hold()
            self.watchdog_trips += 1

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
        for port, (channel, codec) in zip(self._ports, self._codecs):
            if isinstance(port, tuple):
                values = np.concatenate(
                    [self.station.GetOutputPort(p).Eval(context) for p in port]
                )
            else:
                values = self.station.GetOutputPort(port).Eval(context)
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
        self._log.append((
            context.get_time(),
            self.station.GetOutputPort("state_true").Eval(context).copy(),
            self.station.GetOutputPort("q_measured").Eval(context).copy(),
            self._command.copy(),
            self.holding,
        ))

    def run(self) -> dict:
        """Real time until the duration, a signal, or the transport's end."""
        stop = {"now": False}

        def terminate(signum, frame):
            stop["now"] = True

        previous = {s: signal.signal(s, terminate) for s in (signal.SIGTERM, signal.SIGINT)}
        wall_period = self.period / self.config.rate
        if self.k == 0:
            self.step()  # initialization: not timed against the clock
        start = time.perf_counter() - self.k * wall_period
        try:
            gc.collect()
            gc.freeze()
            gc.disable()
            while not stop["now"] and self.k * self.period <= self.config.duration:
                self.step()
                deadline = start + self.k * wall_period
                self.transport.handle(0.0)  # at least once: behind schedule too
                late = False
                while True:
                    remaining = deadline - time.perf_counter()
                    if remaining <= 0:
                        late = remaining < -wall_period
                        self.late_periods += late
                        break
                    self.transport.handle(remaining)
                self._watchdog(time.perf_counter(), late)
        except TransportClosed as error:
            self.fault = f"the transport is gone at t = {self._context.get_time():.3f} s ({error})"
            self.hold()
        finally:
            gc.enable()
            gc.unfreeze()
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
        """t, state_true, q_measured, q_cmd (applied), holding: one row per period."""
        if not self._log:
            return {}
        columns = list(zip(*self._log))
        names = ("t", "state_true", "q_measured", "q_cmd", "holding")
        return {name: np.array(column, dtype=float) for name, column in zip(names, columns)}


def run_in_process(station_config, controller: FusedController, reference, ticks: int,
                   on_tick=None) -> list[tuple[np.ndarray, np.ndarray]]:
    """The fused controller on the simulated station in one process, without messages,
    with the LCM loop's timing: the station's sample k (k >= 1) is the controller's tick
    at t = (k − 1) period (over LCM the robot's first sample is consumed while the
    controller waits for every channel), and the command is applied at once. What the
    message-driven loop is tested against (tests/test_fused.py), and the bench's
    closed-loop tick (`on_tick(tick)` wraps each tick: a timer). Returns (q_cmd, τ̂)
    per tick."""
    from pydrake.systems.analysis import Simulator

    from hrp2_drake.robot.station import initial_joint_positions, make_station, sensor_sizes

    robot = station_config.description()
    period = station_config.sensors_config().period
    station = make_station(station_config)
    simulator = Simulator(station)
    context = simulator.get_mutable_context()
    sizes = sensor_sizes(robot)
    rows = np.cumsum([0] + list(sizes.values()))
    sensor_ports = [station.GetOutputPort(name) for name in sizes]
    stamp_port = station.GetOutputPort("sensor_time")
    q_cmd_port = station.GetInputPort("q_cmd")
    q_cmd_port.FixValue(context, initial_joint_positions(station_config))
    command = np.zeros(len(robot.joints))
    N = len(robot.joints)
    tick = on_tick or (lambda step: step())
    simulator.Initialize()
    out = []
    for k in range(1, ticks + 1):
        simulator.AdvanceTo(k * period)
        for port, a, b in zip(sensor_ports, rows[:-1], rows[1:]):
            controller.sensor_buffer[a:b] = port.Eval(context)
        t = (k - 1) * period
        controller.sensor_time[:] = stamp_port.Eval(context) - period
        x = reference.trajectory.value(t)[:, 0]
        controller.q_ref[:], controller.v_ref[:] = x[:N], x[N : 2 * N]
        controller.vdot_ref[:] = x[2 * N :]
        if k == 1:
            controller.initialize(t)

        def step(t=t):
            controller.tick(t)
            controller.command(controller.q_ref, command)

        tick(step)
        q_cmd_port.FixValue(context, command)
        out.append((command.copy(), controller.estimator.tau.copy()))
    return out
