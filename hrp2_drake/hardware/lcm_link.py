"""A robot over LCM as the control loop's link (`LcmLink`): the robot's encoder
message is the clock.

The IMU and F/T messages only update the latest values (and their stamps); the robot
sends them before the encoders of the same period, so each encoder message takes with
it the other channels' latest messages at its arrival. Each new
`<P>_Q_MEASURED` message (a timestamp newer than the last) is one period: it is
decoded into the fused controller's buffers and `receive` returns its time; an old or
repeated one is refused (counted). A loop that falls behind takes every period in
order. `send` publishes `<P>_Q_CMD` at once. Channels
and messages: `hardware.lcm_station` (module docstring), `hardware.messages`.
"""

import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from hrp2_drake.description import RobotDescription
from hrp2_drake.hardware.lcm_station import LcmChannels
from hrp2_drake.hardware.link import LoopFault, RobotLink
from hrp2_drake.hardware.messages import SignalCodec
from hrp2_drake.hardware.transport import Transport


@dataclass
class _SensorChannel:
    """An IMU or F/T channel of the controller: its codec, the rows of the fused
    controller's sensor buffer it writes (its values and its stamps:
    `ControllerLayout.channels`), the stamp's unit (s), its latest message and its
    stamp (-1: none yet), and the message its values hold now."""

    codec: object
    values: np.ndarray
    stamp_rows: np.ndarray
    unit: float
    latest: bytes = b""
    last_stamp: int = -1
    applied: bytes = b""


class LcmLink(RobotLink):
    """The robot behind its LCM channels (module docstring).

    Args:
        robot: the robot description (joint names, IMU, F/T sensors).
        transport: the LCM transport (`transport.open_transport`).
        channels: the channel names.
        controller: the fused controller whose buffers the messages fill.
        wait_timeout: how long `connect` waits for the first message of every
            channel (s).
    """

    def __init__(
        self,
        robot: RobotDescription,
        transport: Transport,
        channels: LcmChannels,
        controller,
        wait_timeout: float = 10.0,
    ):
        self.robot = robot
        self.transport = transport
        self.channels = channels = channels.resolved(robot)
        self.name = f"lcm {transport.url}"
        self.wait_timeout = wait_timeout
        self._controller = controller
        self._q_codec = SignalCodec(robot.joints, channels.q_measured)
        self._cmd_codec = SignalCodec(robot.joints, channels.q_cmd)
        # The other sensor channels, each writing its rows of the controller's
        # sensor buffer (the IMU's one message stamps its two signals).
        buffer = controller.sensor_buffer
        encoders, *others = controller.layout.channels()
        self._q_stamp = buffer[encoders.stamp_rows]
        self._others: list[_SensorChannel] = [
            _SensorChannel(
                codec,
                buffer[channel.rows],
                buffer[channel.stamp_rows],
                1e-6 if isinstance(codec, SignalCodec) else 1e-3,  # µs or ms
            )
            for channel, codec in zip(others, channels.codecs(robot)[1:], strict=True)
        ]
        # New encoder messages not yet taken, oldest first, with their arrival and the
        # other channels' latest messages then: every one is a period, in order, with
        # its own sensors, even when the loop falls behind.
        self._pending: deque[tuple[bytes, int, tuple[bytes, ...]]] = deque()
        self._last_stamp = -1
        self._first_stamp = -1
        self.refused = 0
        self._seen: set[str] = set()
        transport.subscribe(channels.q_measured, self._on_q_measured)
        for other in self._others:
            transport.subscribe(
                other.codec.channel, lambda data, c=other: self._on_sensor(c, data)
            )

    # ---------------------------------------------------------------- messages

    def _on_sensor(self, channel: _SensorChannel, data: bytes) -> None:
        self._seen.add(channel.codec.channel)
        stamp = channel.codec.timestamp(data)
        if stamp <= channel.last_stamp:
            self.refused += 1
            return
        channel.latest, channel.last_stamp = data, stamp

    def _on_q_measured(self, data: bytes) -> None:
        self._seen.add(self.channels.q_measured)
        newest = (
            SignalCodec.timestamp(self._pending[-1][0])
            if self._pending
            else self._last_stamp
        )
        if SignalCodec.timestamp(data) <= newest:
            self.refused += 1  # an old or repeated sample: not a new period
            return
        # The period's other sensors: their latest messages now (sent before it).
        others = tuple(other.latest for other in self._others)
        self._pending.append((data, time.perf_counter_ns(), others))

    def _apply(self, others: tuple[bytes, ...]) -> None:
        """The other channels' messages of a period into the controller's buffers."""
        for channel, data in zip(self._others, others):
            if data is channel.applied:
                continue
            try:
                channel.values[:] = channel.codec.values(data)
            except ValueError as error:
                raise LoopFault(str(error)) from None
            channel.applied = data
            stamp = channel.codec.timestamp(data)
            channel.stamp_rows[:] = stamp * channel.unit - self._first_stamp * 1e-6

    # ---------------------------------------------------------------- the link

    def connect(self, controller) -> np.ndarray:
        """Waits up to wait_timeout for a message on every sensor channel; the pose of
        the latest encoder message. A TimeoutError names the silent channels."""
        channels = [self.channels.q_measured] + [c.codec.channel for c in self._others]
        deadline = time.monotonic() + self.wait_timeout
        try:
            while len(self._seen) < len(channels) and time.monotonic() < deadline:
                self.transport.handle(max(min(0.05, deadline - time.monotonic()), 0.0))
            q = self._q_codec.values(self._pending[-1][0]) if self._pending else None
            for other in self._others:
                if other.latest:
                    other.codec.values(other.latest)
        except (LoopFault, ValueError) as error:
            raise ValueError(f"the robot's first messages: {error}") from None
        silent = [channel for channel in channels if channel not in self._seen]
        if silent:
            raise TimeoutError(
                f"no message from the robot on {', '.join(silent)} within "
                f"{self.wait_timeout:g} s on {self.transport.url}: start the "
                "robot's bridge (or `hrp2-drake sim-robot`) first, with the same URL "
                "and robot"
            )
        # The latest sample is the run's first period (a lock-step robot waits on
        # it for the first command); the older ones are not periods of the run.
        while len(self._pending) > 1:
            self._pending.popleft()
        self.refused = 0  # (a robot may send its first sample again while it waits)
        return np.array(q, dtype=float)

    def receive(self, controller, timeout: float) -> float | None:
        deadline = time.perf_counter() + timeout
        while not self._pending:
            remaining = deadline - time.perf_counter()
            self.transport.handle(max(remaining, 0.0))  # at least once
            if not self._pending and remaining <= 0:
                return None
        data, self.received_ns, others = self._pending.popleft()
        self.started_ns = self.received_ns
        try:
            controller.q_measured[:] = self._q_codec.values(data)
        except ValueError as error:
            raise LoopFault(str(error)) from None
        stamp = SignalCodec.timestamp(data)
        if self._first_stamp < 0:
            self._first_stamp = stamp
        self._apply(others)
        self._last_stamp = stamp
        t = SignalCodec.elapsed(stamp, self._first_stamp)
        self._q_stamp[:] = t
        return t

    def send(self, q_cmd: np.ndarray, t: float) -> None:
        self.transport.publish(self.channels.q_cmd, self._cmd_codec.encode(q_cmd, t))

    def silence(self, timeout: float) -> str:
        return (
            f"the robot went silent: no new {self.channels.q_measured} sample for "
            f"{timeout * 1e3:.0f} ms"
        )

    def gone(self, error) -> str:
        return f"the transport is gone: {error}"

    def counters(self) -> dict:
        return {"refused_samples": int(self.refused)}

    def close(self) -> None:
        """Closes the transport (the link's, from `open_transport`)."""
        self.transport.close()
