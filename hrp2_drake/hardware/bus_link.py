"""The control loop's link over a robot's servo bus (`BusLink`, Dynamixel or
Feetech) and the bus of a robot's description (`servo_bus`, `bus.kind`); the bus
itself is `hardware.servo_bus.ServoBus`."""

import time

import numpy as np

from hrp2_drake.description import RobotDescription
from hrp2_drake.hardware.dynamixel import DynamixelBus
from hrp2_drake.hardware.feetech import FeetechBus
from hrp2_drake.hardware.link import LoopFault, RobotLink
from hrp2_drake.hardware.servo_bus import (
    STARTUP_WAIT,
    STATUS_CORRUPT,
    STATUS_OK,
    STATUS_SILENT,
    BusRead,
    ServoBus,
)


def servo_bus(robot: RobotDescription, port: str) -> ServoBus:
    """The robot's bus at `port`, through its kind's SDK (`bus.kind`)."""
    kind = robot.bus.kind
    if kind == "feetech":
        return FeetechBus(robot, port)
    if kind == "dynamixel":
        return DynamixelBus(robot, port)
    raise ValueError(f"robot '{robot.name}': its description has no bus (bus.kind)")


class BusLink(RobotLink):
    """A robot on its servo bus (Dynamixel or Feetech) as the control loop's link
    (`hardware.link`).

    The loop's own clock: period k starts at k·T on the wall clock from the first
    `receive` (T: the description's `sensors.period`, the bus's) with one sync read,
    and its command is one sync write. A period that starts late runs at once (it is
    counted; a loop more than the loop's silence timeout behind is a fault), or, with
    `skip_late`, skips to the period of now. With `lockstep` (a lock-step simulation
    behind the port: its clock is the bus traffic) nothing waits for the wall clock.
    The samples of period k have time k·T; their stamp moves only when every servo
    answered.

    Bus faults are counted per servo: no status, a corrupt status (CRC, length), a
    hardware alert. A servo with a hardware alert, or without a valid status for
    `bus.silent_periods` periods in a row, is a `LoopFault` naming it: the loop ramps
    to position control where the bus still works.

    Args:
        robot: the robot description (its `bus`).
        port: the serial port.
        lockstep: the robot's clock is the bus traffic.
        gain: the position P gain to set (None: the description's).
        skip_late: a period that starts more than a period late skips to the period
            of now (counted), rather than running late: a recording, whose log takes
            the host's clock (a controller runs every period).
    """

    def __init__(
        self,
        robot: RobotDescription,
        port: str,
        lockstep: bool = False,
        gain: float | None = None,
        skip_late: bool = False,
    ):
        self.robot = robot
        self.gain = gain
        self.skip_late = skip_late
        self.skipped = 0
        self.bus = servo_bus(robot, port)
        self.name = port
        self.lockstep = lockstep
        self.period = robot.sensors.period
        n = len(robot.joints)
        self._k = 0
        self._t0 = 0.0
        self._failures = np.zeros(n, dtype=int)  # consecutive, per servo
        self.silent = np.zeros(n, dtype=int)
        self.corrupt = np.zeros(n, dtype=int)
        self.alerts = np.zeros(n, dtype=int)
        self.incomplete = 0
        self.late = 0
        self.max_lag = 0.0
        self.reading: BusRead | None = None  # the latest sync read

    def connect(self, controller) -> np.ndarray:
        q = self.bus.start(self.gain)
        if self.lockstep:
            # Nothing waits for the wall clock: the wait only tells an absent
            # status from a late one (a loaded host or emulator), as at start-up.
            self.bus.set_status_wait(STARTUP_WAIT)
        controller.q_measured[:] = q
        return q

    def receive(self, controller, timeout: float) -> float | None:
        if self._k == 0:
            self._t0 = time.perf_counter()  # the clock starts with the first period
        t = self._k * self.period
        if not self.lockstep:
            lag = time.perf_counter() - (self._t0 + t)
            if lag < 0:
                time.sleep(-lag)
            elif lag > self.period:
                self.late += 1
                self.max_lag = max(self.max_lag, lag)
                if self.skip_late:  # on to the period of now
                    skipped = int(lag / self.period)
                    self.skipped += skipped
                    self._k += skipped
                    t = self._k * self.period
                elif lag > timeout:
                    raise LoopFault(
                        f"{self.name}: the loop is {lag * 1e3:.0f} ms behind the bus "
                        f"period ({self.period * 1e3:g} ms)",
                        t,
                    )
        self.started_ns = time.perf_counter_ns()
        self.reading = reading = self.bus.read()
        self.received_ns = time.perf_counter_ns()
        self._tally(reading, t)
        controller.q_measured[:] = reading.position
        if reading.complete:
            controller.q_measured_time[:] = t
        else:
            self.incomplete += 1
        self._k += 1
        return t

    def _tally(self, reading: BusRead, t: float) -> None:
        """Counts the period's bus faults (the period at t, s); a LoopFault for a
        servo's hardware alert or a servo without a valid status for
        `silent_periods` periods."""
        ok = reading.status == STATUS_OK
        self.silent += reading.status == STATUS_SILENT
        self.corrupt += reading.status == STATUS_CORRUPT
        self._failures = np.where(ok, 0, self._failures + 1)
        alert = ok & reading.alert
        self.alerts += alert
        for k in np.flatnonzero(alert):
            raise LoopFault(
                f"{self.bus.name(k)}: hardware error: {self.bus.hardware_error(k)}", t
            )
        limit = self.robot.bus.silent_periods
        for k in np.flatnonzero(self._failures >= limit):
            what = (
                "no status"
                if reading.status[k] == STATUS_SILENT
                else "a corrupt status"
            )
            raise LoopFault(
                f"{self.bus.name(k)}: {what} in {self._failures[k]} periods in a row "
                f"(silent_periods: {limit})",
                t,
            )

    def send(self, q_cmd: np.ndarray, t: float) -> None:
        self.bus.write(q_cmd)

    def gone(self, error) -> str:
        return f"the bus is gone: {error}"

    def ending(self, ramped: bool) -> str:
        if ramped:
            return (
                "the goal then ramped to the measured pose: the servos' own position "
                "loop holds the robot"
            )
        return (
            "nothing could be sent any more: the servos hold their last goal "
            "position (their own position loop)"
        )

    def counters(self) -> dict:
        per_servo = {
            str(servo): {
                "no_status": int(self.silent[k]),
                "corrupt": int(self.corrupt[k]),
                "hardware_alerts": int(self.alerts[k]),
            }
            for k, servo in enumerate(self.bus.ids)
        }
        return {
            "servos": per_servo,
            "incomplete_periods": int(self.incomplete),
            "late_periods": int(self.late),
            "skipped_periods": int(self.skipped),
            "max_lag_ms": self.max_lag * 1e3,
            "stale_bytes": int(self.bus.stale_bytes),
        }

    def close(self) -> None:
        self.bus.close()
