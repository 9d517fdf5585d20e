"""Drake's `lcmt_drake_signal` and `lcmt_force_torque` on the wire, encoded and decoded
with numpy: the codecs read and write the few fields we use directly, the same
messages on the wire, readable by any LCM tool (`lcm-spy` decodes them as Drake's
types).
"""

import struct
from collections.abc import Sequence

import numpy as np
from drake import lcmt_drake_signal, lcmt_force_torque


class SignalCodec:
    """`lcmt_drake_signal` with a fixed list of coordinate names (joint names, IMU
    axes): values (float64), names, timestamp (µs)."""

    FINGERPRINT = lcmt_drake_signal._get_packed_fingerprint()

    def __init__(self, names: Sequence[str], channel: str):
        self.names = list(names)
        self.channel = channel
        n = len(self.names)
        self._head = self.FINGERPRINT + struct.pack(">i", n)
        self._tail = b"".join(
            struct.pack(">I", len(name.encode()) + 1) + name.encode() + b"\0"
            for name in self.names
        )
        self._size = len(self._head) + 8 * n + len(self._tail) + 8
        self._checked: bytes | None = None

    def encode(self, values: np.ndarray, time: float) -> bytes:
        return b"".join(
            (
                self._head,
                np.asarray(values, ">f8").tobytes(),
                self._tail,
                struct.pack(">q", self.stamp_of(time)),
            )
        )

    @staticmethod
    def stamp_of(time: float) -> int:
        """The timestamp (µs) a message of the time `time` (s) carries."""
        return int(round(time * 1e6))

    @staticmethod
    def elapsed(stamp: int, first: int) -> float:
        """The time (s) from the timestamp `first` to `stamp` (µs): a tick's time
        over LCM, its encoder message's stamp since the run's first."""
        return (stamp - first) * 1e-6

    def values(self, data: bytes) -> np.ndarray:
        """The values (a read-only view on `data`); a ValueError naming the channel if
        the message is not this signal (type, size or names)."""
        if data is not self._checked:
            self._check(data)
        return np.frombuffer(data, ">f8", len(self.names), 12)

    @staticmethod
    def timestamp(data: bytes) -> int:
        return struct.unpack_from(">q", data, len(data) - 8)[0] if data else -1

    def _check(self, data: bytes) -> None:
        if (
            len(data) == self._size
            and data[: len(self._head)] == self._head
            and (data[self._size - 8 - len(self._tail) : self._size - 8] == self._tail)
        ):
            self._checked = data
            return
        if data[:8] != self.FINGERPRINT:
            raise ValueError(f"channel {self.channel}: not an lcmt_drake_signal")
        message = lcmt_drake_signal.decode(data)
        raise ValueError(
            f"channel {self.channel}: coordinates {list(message.coord)[:4]}... "
            f"({message.dim}), expected {self.names[:4]}... ({len(self.names)})"
        )


class WrenchCodec:
    """`lcmt_force_torque`: [τ; f] (the station's order) and a timestamp (ms, as Drake
    documents the type)."""

    FINGERPRINT = lcmt_force_torque._get_packed_fingerprint()
    _FORMAT = struct.Struct(">qdddddd")
    _ORDER = np.array([3, 4, 5, 0, 1, 2])  # fx fy fz tx ty tz -> tx ty tz fx fy fz

    def __init__(self, channel: str):
        self.channel = channel

    def encode(self, wrench: np.ndarray, time: float) -> bytes:
        tx, ty, tz, fx, fy, fz = (float(v) for v in wrench)
        return self.FINGERPRINT + self._FORMAT.pack(
            int(round(time * 1e3)), fx, fy, fz, tx, ty, tz
        )

    def values(self, data: bytes) -> np.ndarray:
        if len(data) != 64 or data[:8] != self.FINGERPRINT:
            raise ValueError(f"channel {self.channel}: not an lcmt_force_torque")
        return np.frombuffer(data, ">f8", 6, 16)[self._ORDER]

    @staticmethod
    def timestamp(data: bytes) -> int:
        return struct.unpack_from(">q", data, 8)[0] if data else -1
