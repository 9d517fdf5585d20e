"""The simulated robot over LCM (`hrp2-drake sim-robot`): `RobotBridge`, the
reference for a real robot's LCM bridge. Every period it publishes the sensors (F/T and
IMU first, the encoders last, stamped with the robot's clock; one message per channel
of `control.fused.ControllerLayout.channels`), applies the latest command, and guards
itself: after `watchdog_periods` without a new command it holds the measured pose
until commands come again. Channels and messages: `hardware.lcm_station`,
`hardware.messages`.
"""

import math
import signal
import time
from dataclasses import dataclass

import numpy as np

from hrp2_drake.control.fused import ControllerLayout
from hrp2_drake.hardware.lcm_station import LcmChannels
from hrp2_drake.hardware.messages import SignalCodec
from hrp2_drake.hardware.real_time import check_time, garbage_collector_frozen
from hrp2_drake.hardware.transport import Transport, TransportClosed


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
        check_time(self.lockstep_timeout, "BridgeConfig.lockstep_timeout")


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
        port = self.station.GetOutputPort
        self._messages = [
            ([port(signal) for signal in channel.signals], name, codec)
            for channel, name, codec in zip(
                layout.channels(),
                channels.sensors(robot),
                channels.codecs(robot),
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
        lockstep_timeout (the controller ticks on it); holding its pose (the watchdog
        tripped) it waits for nothing. False if `stopped()` says so meanwhile."""
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
            self.fault = (
                f"the transport is gone at t = {self._context.get_time():.3f} s "
                f"({error})"
            )
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
