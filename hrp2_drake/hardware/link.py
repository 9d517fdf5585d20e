"""What a control loop needs of a robot: a link (`RobotLink`) through which a period's
samples come in and its command goes out. The controller's loop
(`hardware.control_loop.ControlLoop`) is one loop for every link: over LCM
(`hardware.lcm_link.LcmLink`: the robot's encoder message is the clock) and on a
servo bus (`hardware.bus_link.BusLink`, Dynamixel or Feetech: the loop's own clock,
one sync read and one sync write per period).

A link raises `LoopFault` for what makes the loop hand the robot back to its servos
(a malformed or stale message, a silent or faulting servo) and `LinkClosed` when
nothing can reach the robot any more (the transport or the port is gone).
"""

import numpy as np


class LoopFault(RuntimeError):
    """What ended a loop early (the message names it); `t`: the time of the period it
    happened in (s), if not the last tick's."""

    def __init__(self, message: str, t: float | None = None):
        super().__init__(message)
        self.t = t


class LinkClosed(ConnectionError):
    """The robot cannot be reached any more: nothing can be sent (the robot's own
    watchdog, or its servos' position loop, holds it)."""


class RobotLink:
    """The robot as a control loop sees it (module docstring). A link writes each
    period's samples into the fused controller's buffers (`sensor_buffer`, its rows
    named by `FusedController.layout`: q_measured, the other sensors' values, their
    stamps) and sends its command.

    Attributes:
        name: where the robot is, for reports ("lcm tcpq://...", "/dev/ttyUSB0").
        lockstep: True if the robot's clock is the link's traffic (a lock-step
            simulation): the loop then never waits for the wall clock.
        started_ns, received_ns: `time.perf_counter_ns` when the latest period's
            exchange began and when its samples were all in (the loop times its tick
            from `received_ns` and the whole period from `started_ns`).
    """

    name: str = ""
    lockstep: bool = False
    started_ns: int = 0
    received_ns: int = 0

    def connect(self, controller) -> np.ndarray:
        """Waits for the robot, checks it and readies it; its present pose (rad,
        joint order). A ValueError or TimeoutError with one line if it cannot."""
        raise NotImplementedError

    def receive(self, controller, timeout: float) -> float | None:
        """The next period's samples, written into the controller's buffers; their
        time (s from the first period), or None if none came within `timeout` s."""
        raise NotImplementedError

    def send(self, q_cmd: np.ndarray, t: float) -> None:
        """The position command for the period at t (s)."""
        raise NotImplementedError

    def silence(self, timeout: float) -> str:
        """Why no period came within `timeout` s, in words (the loop's fault)."""
        return f"the robot went silent: no new sample for {timeout * 1e3:.0f} ms"

    def gone(self, error: LinkClosed) -> str:
        """The fault when the link is gone (`LinkClosed`), in words."""
        return f"the link is gone: {error}"

    def counters(self) -> dict:
        """What the link counted during the run (refused samples, bus faults...)."""
        return {}

    def ending(self, ramped: bool) -> str:
        """What the robot is left with at the end of a run, in words."""
        if ramped:
            return "the command then ramped to the measured pose (position control)"
        return "nothing could be sent any more: the robot's own watchdog holds its pose"

    def close(self) -> None:
        pass
