"""Sensor fault injection for the simulated station (`StationConfig.faults`).

A `FaultInjector` sits between a sensor's sampler and the station's exported port and,
while a fault is active (start <= t < start + duration), changes what the port reads:

    "nan"     the entries read NaN (a dropped or corrupt sample)
    "zero"    the entries read 0 (a sensor that lost power or its offset compensation)
    "freeze"  the entries hold the last value sampled before the fault (a stale driver)
    "bias"    the entries read magnitude more (an IMU bias step, a shifted F/T offset)
    "glitch"  the entries read magnitude more for one sensor period (an encoder glitch)

Only the signals named in the config get an injector; without faults the station is
exactly as before. Ground truth (`joint_torque_true`, `state_true`) is never altered.
"""

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from pydrake.systems.framework import BasicVector, Context, DiscreteValues

from hrp2_drake.simulation import WitnessFreeLeafSystem

FAULT_KINDS = ("nan", "zero", "freeze", "bias", "glitch")


@dataclass
class SensorFault:
    """One fault on one of the station's sensor ports.

    Args:
        signal: the station output port ("q_measured", "imu_linear_acceleration",
            "imu_angular_velocity", "wrench_<sensor>").
        kind: one of FAULT_KINDS.
        start: when it starts (s).
        duration: how long it lasts (s; "glitch" lasts one sensor period whatever this
            is; .inf: to the end).
        indices: the entries it affects (empty: all).
        magnitude: "bias" and "glitch": the offset, one value for every affected entry
            or one per entry (the signal's unit).
    """

    signal: str = ""
    kind: str = "nan"
    start: float = 0.0
    duration: float = 0.005
    indices: list[int] = field(default_factory=list)
    magnitude: list[float] = field(default_factory=lambda: [0.0])

    def validate(self, where: str, sizes: dict[str, int]) -> None:
        if self.signal not in sizes:
            raise ValueError(
                f"{where}.signal: unknown signal '{self.signal}', expected one of "
                f"{sorted(sizes)}"
            )
        if self.kind not in FAULT_KINDS:
            raise ValueError(
                f"{where}.kind: '{self.kind}', expected one of {FAULT_KINDS}"
            )
        if not (math.isfinite(self.start) and self.start >= 0):
            raise ValueError(
                f"{where}.start: must be finite and >= 0, got {self.start}"
            )
        if not self.duration > 0:
            raise ValueError(f"{where}.duration: must be > 0, got {self.duration}")
        size = sizes[self.signal]
        bad = [i for i in self.indices if not 0 <= i < size]
        if bad:
            raise ValueError(
                f"{where}.indices: {bad} out of range for '{self.signal}' ({size})"
            )
        count = len(self.indices) or size
        if len(self.magnitude) not in (1, count) or not np.all(
            np.isfinite(self.magnitude)
        ):
            raise ValueError(
                f"{where}.magnitude: 1 or {count} finite values, got {self.magnitude}"
            )


class FaultInjector(WitnessFreeLeafSystem):
    """Applies `SensorFault`s to one sensor signal.

    .. code-block:: text

                    ┌───────────────┐
        signal ────►│ FaultInjector ├──► signal
                    └───────────────┘

    The output is the input (direct feedthrough, no delay) except where a fault is
    active. For "freeze" a discrete state keeps the last input sampled before the
    fault, updated every `period`.
    """

    def __init__(self, size: int, faults: Sequence[SensorFault], period: float):
        super().__init__()
        self._size = size
        self._period = period
        self._faults = []
        for fault in faults:
            rows = np.array(fault.indices or range(size), dtype=int)
            magnitude = np.broadcast_to(
                np.asarray(fault.magnitude, float), rows.shape
            ).copy()
            end = fault.start + (period if fault.kind == "glitch" else fault.duration)
            self._faults.append((fault.kind, fault.start, end, rows, magnitude))
        self._input = self.DeclareVectorInputPort("signal", size)
        self._held = self.DeclareDiscreteState(size)
        if any(f.kind == "freeze" for f in faults):
            self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._hold)
        self.DeclareVectorOutputPort("signal", size, self._calc)

    def _hold(self, context: Context, state: DiscreteValues) -> None:
        t = context.get_time()
        if not any(
            k == "freeze" and start <= t < end for k, start, end, *_ in self._faults
        ):
            state.set_value(self._held, self._input.Eval(context))

    def _calc(self, context: Context, output: BasicVector) -> None:
        value = self._input.Eval(context).copy()
        # Tolerance: a fault starting at a sample time covers that sample.
        t = context.get_time() + 1e-9
        for kind, start, end, rows, magnitude in self._faults:
            if not start <= t < end:
                continue
            if kind == "nan":
                value[rows] = np.nan
            elif kind == "zero":
                value[rows] = 0.0
            elif kind == "freeze":
                value[rows] = context.get_discrete_state(self._held).get_value()[rows]
            else:  # bias, glitch
                value[rows] += magnitude
        output.set_value(value)


def freeze_windows(
    signals: Sequence[str], faults: Sequence[SensorFault]
) -> list[tuple[int, float, float]]:
    """(signal index, start, end) of every "freeze" fault on one of `signals`."""
    return [
        (signals.index(f.signal), f.start, f.start + f.duration)
        for f in faults
        if f.kind == "freeze"
    ]


def update_stamps(
    stamps: np.ndarray, t: float, freezes: Sequence[tuple[int, float, float]]
) -> None:
    """Sets, in place, the stamp of every signal to t but those a freeze holds at t
    (`freeze_windows`; a stale driver sends nothing new)."""
    if not freezes:
        stamps[:] = t
        return
    frozen = {k for k, start, end in freezes if start <= t + 1e-9 < end}
    for k in range(len(stamps)):
        if k not in frozen:
            stamps[k] = t


class SensorClock(WitnessFreeLeafSystem):
    """The time stamp of each sensor's latest sample, as a real driver reports it
    (a message time, a sequence counter): updated every `period`, except while a
    "freeze" fault holds that sensor (a stale driver sends nothing new).

    .. code-block:: text

        ┌─────────────┐
        │ SensorClock ├──► sensor_time (one stamp per signal, s)
        └─────────────┘

    (The simulated station's `SensorSampler` keeps the same stamps itself.)
    """

    def __init__(
        self, signals: Sequence[str], faults: Sequence[SensorFault], period: float
    ):
        super().__init__()
        self._freezes = freeze_windows(list(signals), faults)
        self._stamps = self.DeclareDiscreteState(len(signals))
        self._stamps_group = int(self._stamps)
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._update)
        self.DeclareStateOutputPort("sensor_time", self._stamps)

    def _update(self, context: Context, state: DiscreteValues) -> None:
        # In place on `state`, which holds the current stamps on entry.
        stamps = state.get_mutable_value(self._stamps_group)
        update_stamps(stamps, context.get_time(), self._freezes)
