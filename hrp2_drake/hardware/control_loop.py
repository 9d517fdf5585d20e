"""The controller's real-time loop, one for every robot link.

`ControlLoop` (the controller, `hrp2-drake control`): each period, the link
(`hardware.link.RobotLink`) writes the period's samples into the fused controller's
buffers (their rows: `FusedController.layout`), one tick of the `FusedController`
runs, and the link sends the command at once. Over LCM (`hardware.lcm_link.LcmLink`)
the robot's encoder message is the clock; on a servo bus (`hardware.bus_link.BusLink`,
Dynamixel or Feetech) the loop's own clock, one sync read and one sync write per
period. No Simulator paces it, and Python's garbage collector does not run
inside the loop (`hardware.real_time.garbage_collector_frozen`). It refuses to start
before the fused controller's kernels are compiled (`FusedController.warm_up`), and
nothing compiles while it runs (`hrp2_drake.kernels.freeze`: a kernel called with a
new signature raises, which ends the run in a ramp).

It fails safe. Whatever ends a run (its duration, a malformed or stale message, a
silent robot or servo, a servo's hardware error, an exception, SIGTERM/SIGINT), the
command ramps from the last one sent to the measured pose over `ramp_time`
(position control holding the robot), the report is written with the fault and its
time, and the process ends with one line. Where the link itself is gone nothing can
be sent: the loop ends cleanly and the robot's own watchdog (or its servos' position
loop) holds the pose.

The robot's side is elsewhere: the simulated robot over LCM in
`hardware.robot_bridge`, and the in-process runs the loops are tested against in
`hardware.in_process`.
"""

import math
import signal
import time
from dataclasses import dataclass, field

import numpy as np

from hrp2_drake import kernels
from hrp2_drake.control.balance import BALANCE_FAULTS
from hrp2_drake.control.fused import FusedController
from hrp2_drake.control.safety import describe_faults
from hrp2_drake.control.torque_chain import EventKind
from hrp2_drake.control.torque_controller import FALLBACK_REASONS
from hrp2_drake.hardware.link import LinkClosed, LoopFault, RobotLink
from hrp2_drake.hardware.real_time import (
    RealTimeConfig,
    check_time,
    garbage_collector_frozen,
    request_real_time,
)


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
        """Raises ValueError naming `where`.<field>: each time finite and > 0,
        silence_timeout at least two control periods (`period`, s; 0: unknown), and a
        CPU and priority the machine can grant (`RealTimeConfig.validate`)."""
        self.real_time.validate(f"{where}.real_time")
        for name in ("wait_timeout", "silence_timeout", "ramp_time"):
            check_time(getattr(self, name), f"{where}.{name}")
        if self.silence_timeout < 2 * period:
            raise ValueError(
                f"{where}.silence_timeout: {self.silence_timeout} s is shorter than "
                f"two periods ({2 * period} s)"
            )


class ControlLoop:
    """The controller's loop over any robot link (module docstring).

    Args:
        controller: the fused controller (built for the link's robot).
        link: the robot (`RobotLink`), connected (`RobotLink.connect`).
        reference: a `JointReference` (q, v, vdot of every joint over time).
        force_reference: f_ref(t) (6) of a force task, or None.
        settings: the loop's own settings, validated where they were loaded
            (`LoopSettings.validate`); None: the defaults.
        duration: seconds of robot time to run (from the first period).
        com_reference: the CoM reference (9 rows: position, velocity,
            acceleration, m, m/s, m/s², world: what the balance QP tracks), a
            trajectory evaluated at each tick as the joint reference is: given if
            and only if the controller's chain has a balance front end.
        start_check: (time, check): `check()` is called once, at the first
            period at or after `time` (s: before torque control starts, the
            supervisor's start_time), with that period's samples in the
            controller's buffers and before its tick; a sentence (not empty) is a
            fault: the loop ramps out, and the robot never gets a torque-control
            command (e.g. a balance controller on a robot whose soles carry no
            weight).

    The period (the tick's budget, s) is the controller's (`parts.period`: the
    robot's sensor period).
    """

    def __init__(
        self,
        controller: FusedController,
        link: RobotLink,
        reference,
        force_reference=None,
        settings: LoopSettings | None = None,
        duration: float = 5.0,
        com_reference=None,
        start_check=None,
    ):
        balance = controller.com_ref.size > 0
        if balance != (com_reference is not None):
            raise ValueError(
                "ControlLoop: a balance chain needs a CoM reference (com_reference), "
                "and only a balance chain takes one"
            )
        if balance and com_reference.rows() != controller.com_ref.size:
            raise ValueError(
                f"ControlLoop: com_reference has {com_reference.rows()} rows, "
                f"expected {controller.com_ref.size} (position, velocity, "
                "acceleration)"
            )
        self.controller = controller
        self.link = link
        self.reference = reference
        self.force_reference = force_reference
        self.com_reference = com_reference
        self._start_check = start_check
        self.settings = settings or LoopSettings()
        self.duration = duration
        self.period = controller.parts.period
        N = len(controller.q_measured)
        self._q_cmd = np.zeros(N)
        self.t = 0.0
        self.ticks = 0
        self.fault: LoopFault | None = None
        self.fault_time = math.nan
        capacity = int(duration / self.period * 1.2) + 1000
        self.latency_ns = np.zeros(capacity, dtype=np.int64)
        self.cycle_ns = np.zeros(capacity, dtype=np.int64)
        self.receive_gap_ns = np.zeros(capacity, dtype=np.int64)
        self.log_t = np.zeros(capacity)
        self.log = {
            name: np.zeros((capacity, N)) for name in ("q_ref", "q_measured", "q_cmd")
        }
        if balance:  # the CoM's reference and the QP's CoM (the model's, estimated)
            self.log["com_ref"] = np.zeros((capacity, controller.com_ref.size))
            self.log["balance_com"] = np.zeros((capacity, 3))
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
        if self._start_check is not None and t >= self._start_check[0]:
            check, self._start_check = self._start_check[1], None
            refused = check()
            if refused:
                raise LoopFault(refused)
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
            if self.com_reference is not None:
                self.log["com_ref"][k] = controller.com_ref
                self.log["balance_com"][k] = controller.balance.com
            self.log_mode[k] = controller.torque_active()
        self._last_receive = received
        self.ticks = k + 1
        if t >= self.duration:
            self._stop = True

    def _set_reference(self, t: float) -> None:
        controller = self.controller
        controller.q_ref[:], controller.v_ref[:], controller.vdot_ref[:] = (
            self.reference.at(t)
        )
        if self.force_reference is not None:
            controller.f_ref[:] = self.force_reference.value(t)[:, 0]
        if self.com_reference is not None:
            controller.com_ref[:] = self.com_reference.value(t)[:, 0]

    # ---------------------------------------------------------------- running

    def run(self) -> dict:
        """Runs until the duration (robot time), a fault, or a signal; ramps out; the
        run's summary (see `summary`)."""
        if not self.controller.warmed_up:
            raise RuntimeError(
                "the control loop refuses to start: its fused controller's kernels are "
                "not compiled (call FusedController.warm_up() before the loop)"
            )
        settings = self.settings
        granted = request_real_time(settings.real_time)
        previous = {
            sig: signal.signal(sig, self._on_signal)
            for sig in (signal.SIGTERM, signal.SIGINT)
        }
        try:
            with (
                garbage_collector_frozen(settings.real_time.freeze_gc),
                kernels.compile_disabled(),
            ):
                self._loop(settings.silence_timeout)
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
        period = self.period
        q_from = self._q_cmd.copy()
        q_hold = self.controller.q_measured.copy()
        if not np.all(np.isfinite(q_hold)):
            q_hold = q_from
        if not self.ticks:  # nothing sent yet: hold the measured pose from the start
            q_from = q_hold
        steps = max(1, int(round(self.settings.ramp_time / period)))
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
        period_us = self.period * 1e6
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
            elif kind == EventKind.BALANCE_FAULT:
                events.append(
                    {
                        "t": t,
                        "what": "balance QP fault",
                        "reason": BALANCE_FAULTS.get(code, str(code)),
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
