"""The fused torque controller: every step of the torque-control chain in one update.

The chain of paper Sec. 2 and 4 (Savitzky-Golay filters, floating-base torque
estimator, inverse dynamics, Δq torque controller, and this project's disturbance
observer, delay predictor and safety supervisor) runs in simulation as separate
LeafSystems. Each of them is a shell around a plain step (`hrp2_drake.step`); this
module runs the same step objects in sequence:

- `FusedController`: no Drake at all; `tick(t, ...)` is one control period. It is
  what the hardware loop (`hrp2_drake.hardware.control_loop`) calls when the robot's
  encoder message arrives.
- `FusedTorqueController`: the same as one LeafSystem (one discrete update per period,
  one state vector), `build_torque_control(..., fused=True)`.

With a balance front end (`BalanceParts`, issue 29: `build_balance_control(...,
fused=True)`), the base from the soles' kinematics and the whole-body QP with
contacts take the inverse dynamics' place: the QP's τ* of the controlled joints feeds
the Δq controller, and a QP fault is a controller fallback for the supervisor.

Timing: one tick from sample to command, as the authors' graph computes every entity
in the tick its samples arrive. A tick runs the steps in the chain's order, each
reading what its upstream steps computed in this tick (`FusedController.tick`); the
delays left are the filters' own (their window) and one sample between the command
and the servo. Two loops close through the Δq controller: the disturbance observer
and the delay predictor read this tick's Δq, and the controller reads their output of
the previous tick. The Diagram's systems do the same (`hrp2_drake.step.StepSystem`:
outputs computed from the current inputs, committed at the sampling instants); the
two shells give the same signals to 1e-12 (tests/test_fused.py).

.. code-block:: text

    q_measured ─► SG order 2 ─► q̂, q̂̇, q̂̈ ──────────────┐
    imu, wrenches ─► SG order 1 ─► values, gyro rate ──► estimator ─► τ̂, f̂
    q_ref, v_ref, vdot_ref, f_ref ─► inverse dynamics (eq. 12) ─► τ_d ─┐
      or, with balance: q_measured, q̂̇ ─► base from the soles ─► [q; v] ─┐  │
                        q_ref, com_ref ─► balance QP ─► τ* (controlled) ─┴──┤
                        τ̂ (or predicted), q̂̇ ─► Δq controller (eq. 10-11) ─► q_cmd
                              observer d̂ ─┘           │       (QP fault ─┐)
                                supervisor (faults, ramps) ◄──┘◄─────────┘ ─► q_cmd
"""

import time
from dataclasses import dataclass

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import (
    BasicVector,
    Context,
    DiscreteValues,
    ValueProducer,
)

from hrp2_drake.chain import FusedChain, Take
from hrp2_drake.control.torque_chain import (
    EventKind,
    TorqueChainParts,
    torque_chain,
)
from hrp2_drake.description import RobotDescription
from hrp2_drake.simulation import WitnessFreeLeafSystem
from hrp2_drake.step import new_sample, sampling_offset


@dataclass(frozen=True)
class ControllerLayout:
    """The rows of the fused controller's sensor buffer
    (`FusedController.sensor_buffer`), named once for every shell that fills it: the
    LeafSystem's ports, the LCM link's messages, the bus link's reads, the in-process
    runs and the robot's bridge.

    The buffer is what the station outputs, in its order (`robot.station.sensor_sizes`):
    [q_measured (N); imu_linear_acceleration (3); imu_angular_velocity (3) (with an
    IMU); wrench_<s> (6 each); sensor_time (one stamp per signal, if stamped)].

    Args:
        num_joints: N, the robot's joints.
        has_imu: whether the robot has an IMU.
        sensor_names: the F/T sensors, in the robot's order.
        num_stamps: the size of `sensor_time`: one per signal (the safety supervisor
            checks them), or 0 (not stamped: no supervisor).
    """

    num_joints: int
    has_imu: bool
    sensor_names: tuple[str, ...]
    num_stamps: int

    def __post_init__(self):
        if self.num_stamps not in (0, len(self.signals())):
            raise ValueError(
                f"ControllerLayout: {self.num_stamps} sensor stamps for "
                f"{len(self.signals())} signals (one per signal, or 0)"
            )

    @property
    def num_values(self) -> int:
        """The other sensors' values (IMU, F/T) after q_measured."""
        return (6 if self.has_imu else 0) + 6 * len(self.sensor_names)

    @property
    def size(self) -> int:
        return self.num_joints + self.num_values + self.num_stamps

    @property
    def q_measured(self) -> slice:
        return slice(0, self.num_joints)

    @property
    def values(self) -> slice:
        """The IMU's and the F/T sensors' values (what the sensor filter smooths)."""
        return slice(self.num_joints, self.num_joints + self.num_values)

    @property
    def stamps(self) -> slice:
        """`sensor_time`: the time of each signal's latest sample (s)."""
        start = self.num_joints + self.num_values
        return slice(start, start + self.num_stamps)

    @property
    def q_measured_stamp(self) -> slice:
        """The encoders' row of `sensor_time` (empty if not stamped)."""
        start = self.stamps.start
        return slice(start, start + 1) if self.num_stamps else slice(start, start)

    def signals(self) -> dict[str, slice]:
        """The station's sensor ports (their names) and their rows, in its order."""
        N = self.num_joints
        rows = {"q_measured": slice(0, N)}
        if self.has_imu:
            rows["imu_linear_acceleration"] = slice(N, N + 3)
            rows["imu_angular_velocity"] = slice(N + 3, N + 6)
        start = N + (6 if self.has_imu else 0)
        for k, name in enumerate(self.sensor_names):
            rows[f"wrench_{name}"] = slice(start + 6 * k, start + 6 * k + 6)
        return rows

    def channels(self) -> list["SensorChannel"]:
        """The robot's sensor messages, one per channel (the order of
        `hardware.lcm_station.LcmChannels.sensors`): the encoders, the IMU (its two
        signals in one message), each F/T sensor."""
        signals = self.signals()
        groups = [("q_measured",)]
        if self.has_imu:
            groups.append(("imu_linear_acceleration", "imu_angular_velocity"))
        groups += [(f"wrench_{name}",) for name in self.sensor_names]
        out, stamp = [], 0
        for group in groups:
            first, last = signals[group[0]], signals[group[-1]]
            stamps = self.stamps.start + stamp
            stamp_rows = slice(stamps, stamps + (len(group) if self.num_stamps else 0))
            out.append(SensorChannel(group, slice(first.start, last.stop), stamp_rows))
            stamp += len(group)
        return out

    @classmethod
    def of_robot(cls, robot: RobotDescription, stamped: bool) -> "ControllerLayout":
        """The layout of `robot`'s station, with a stamp per signal if `stamped`."""
        imu, names = robot.has_imu(), tuple(robot.sensor_names())
        num_stamps = 1 + (2 if imu else 0) + len(names) if stamped else 0
        return cls(len(robot.joints), imu, names, num_stamps)

    def in_values(self, rows: slice) -> slice:
        """`rows` of the buffer as rows of `values` (the sensor filter's rows)."""
        start = self.values.start
        return slice(rows.start - start, rows.stop - start)


@dataclass(frozen=True)
class SensorChannel:
    """One sensor message of the robot (`ControllerLayout.channels`).

    Args:
        signals: the station's ports it carries (one, or the IMU's two).
        rows: their rows of the sensor buffer.
        stamp_rows: their stamps' rows of the sensor buffer (within its `stamps`;
            empty if not stamped).
    """

    signals: tuple[str, ...]
    rows: slice
    stamp_rows: slice


class FusedController:
    """The whole torque-control chain as one plain object (module docstring).

    Inputs of a tick (arrays, SI units, the robot description's joint order), written
    into its buffers before `tick`: `sensor_buffer` = [q_measured (N);
    imu_linear_acceleration (3); imu_angular_velocity (3); wrench_<s> (6 each);
    sensor_time (the time of each signal's latest sample, if supervised)] as the
    station outputs them, its rows named by `layout` (views: `q_measured`,
    `sensor_values`, `sensor_time`, `q_measured_time`); the reference `q_ref`, `v_ref`,
    `vdot_ref` (N each) at t, `f_ref` (6) with a force task, and `com_ref` (9: the
    CoM's position, velocity and acceleration in the world, m, m/s, m/s²) with a
    balance front end.

    After a tick, `command(q_ref, out)` is the position command for the servo, and the
    steps' state arrays hold every signal the diagram logs (`signals()`).
    """

    def __init__(self, parts: TorqueChainParts):
        self.parts = parts
        self._period = parts.period
        all_joints, joints = parts.all_joints, parts.joints
        self._N = len(all_joints)
        self._index = np.array([all_joints.index(j) for j in joints])
        #: The table the controller runs (`control.torque_chain`).
        self.chain = torque_chain(parts)
        econfig = parts.estimator_config
        #: The rows of `sensor_buffer`, for every shell that fills it.
        self.layout = layout = ControllerLayout(
            num_joints=self._N,
            has_imu=bool(econfig.imu_frame),
            sensor_names=tuple(econfig.sensors),
            num_stamps=parts.supervisor.num_stamps if parts.supervisor else 0,
        )
        station = [
            (f"station/{name}", rows.stop - rows.start)
            for name, rows in layout.signals().items()
        ]
        if layout.num_stamps:
            station.append(("station/sensor_time", layout.num_stamps))
        references = [
            (f"reference/{n}", size) for n, size in self.chain.references.items()
        ]
        # Events: (t, kind, code) rows, a ring of the latest ones, and counts.
        self.events = np.zeros((256, 3))
        self.num_events = 0
        self.event_counts = {kind: 0 for kind in EventKind}
        self._chain = FusedChain(self.chain, station + references, self._record)
        #: Each row's step by name, and as an attribute (None: a step the chain
        #: does not have).
        self.steps = self._chain.steps
        for name in _STEP_NAMES:
            setattr(self, name, self.steps.get(name))
        self.state = self._chain.state
        self._initial_state = self.state.copy()
        sources = self._chain.sources
        start = self.state.size
        self.sensor_buffer = sources[start : start + layout.size]
        self.q_measured = self.sensor_buffer[layout.q_measured]
        self.sensor_values = self.sensor_buffer[layout.values]
        self.sensor_time = self.sensor_buffer[layout.stamps]
        self.q_measured_time = self.sensor_buffer[layout.q_measured_stamp]
        start += layout.size
        #: The whole reference in one view: [q_ref; v_ref; vdot_ref (; f_ref with a
        #: force task; com_ref with balance)].
        self.reference = sources[start : start + sum(n for _, n in references)]
        view = self._chain.view
        self.q_ref, self.v_ref, self.vdot_ref = (
            view(f"reference/{name}") for name in ("q_ref", "v_ref", "vdot_ref")
        )
        refs = self.chain.references
        self.f_ref = view("reference/f_ref") if "f_ref" in refs else np.zeros(6)
        self.com_ref = view("reference/com_ref") if "com_ref" in refs else np.zeros(0)
        self._merged = np.zeros(self._N)
        #: The supervisor's controller fallback as `command` reads it.
        self._fallback = (
            self._chain.argument("supervisor", "controller_fallback")
            if self.supervisor is not None
            else None
        )
        self.warmed_up = False  # (`warm_up`)

    # ------------------------------------------------------------------ ticks

    def warm_up(self) -> float:
        """Compiles, or loads from numba's cache, every kernel of the chain's steps
        (`Step.warm_up`: each called on arrays of a real tick's types, no state
        changed), before a loop starts; the wall time it took (s). A real-time loop
        refuses to start before it (`warmed_up`) and forbids compiling while it runs
        (`hrp2_drake.kernels.freeze`)."""
        start = time.perf_counter()
        for step in self.steps.values():
            step.warm_up()
        self.warmed_up = True
        return time.perf_counter() - start

    def reset(self) -> None:
        """Every step back to its initial state (before `initialize`)."""
        self.state[:] = self._initial_state
        self.num_events = 0
        for kind in self.event_counts:
            self.event_counts[kind] = 0

    def initialize(self, t: float) -> None:
        """The initialization events of the chain's systems, from the current
        `sensor_buffer` and reference (the station's first sample)."""
        self._chain.initialize(t)

    def tick(self, t: float) -> None:
        """One control period at time t (s) from the current `sensor_buffer` and
        reference buffers (q_ref, v_ref, vdot_ref, f_ref; com_ref with balance).

        One tick from sample to command: the rows of the chain's table run in order
        and each reads what the rows above it computed in this tick; the observer and
        the predictor close loops through the Δq controller, which reads their output
        of the previous tick (`hrp2_drake.chain`)."""
        self._chain.tick(t)

    def command(self, q_ref: np.ndarray, out: np.ndarray) -> np.ndarray:
        """The position command for the servo (all joints) after a tick, with the
        reference q_ref of the moment it is sent (the diagram's q_cmd output)."""
        merged = self._merged
        merged[:] = q_ref
        merged[self._index] = self.torque.q_cmd
        if self.supervisor is None:
            out[:] = merged
            return out
        # The supervisor's controller fallback, from the state now (with balance,
        # the sum of the Δq controller's and the QP's).
        fallback, update = self._fallback
        if update is not None:
            update()
        self.supervisor.q_cmd(merged, q_ref, fallback, out)
        return out

    def _record(self, t: float, kind: int, code: int) -> None:
        row = self.events[self.num_events % len(self.events)]
        row[0], row[1], row[2] = t, kind, code
        self.num_events += 1
        self.event_counts[kind] += 1

    def recorded_events(self) -> list[tuple[float, int, int]]:
        """The latest events (t, kind, code), oldest first (at most 256)."""
        count = min(self.num_events, len(self.events))
        start = self.num_events - count
        rows = [self.events[(start + i) % len(self.events)] for i in range(count)]
        return [(float(r[0]), int(r[1]), int(r[2])) for r in rows]

    # ------------------------------------------------------------------ signals

    def torque_active(self) -> float:
        """How much torque control drives the robot now: the supervisor's ramp α in
        [0, 1], or 1/0 for the controller alone (its fallback)."""
        if self.supervisor is not None:
            return float(self.supervisor.mode[0])
        return 0.0 if self.torque.fallback_active[0] else 1.0

    def signals(self) -> dict[str, np.ndarray]:
        """The logged signals that are rows of the state (views on it): the chain's
        logged signals (`Chain.logged`) but the command and the sums."""
        out = {}
        for name, source in self.chain.logged().items():
            if name == "q_cmd" or not isinstance(source, Take):
                continue
            rows = self._chain.logged_rows(source)
            if isinstance(rows, list):
                out[name] = self.state[rows[0]]
        return out

    def logged_rows(self, name: str) -> list[slice] | np.ndarray:
        """The rows of `state` of a logged signal (`FusedChain.logged_rows`)."""
        return self._chain.logged_rows(self.chain.logged()[name])


#: The rows a torque chain may have, by name (`FusedController`'s attributes).
_STEP_NAMES = (
    "encoder_filter",
    "sensor_filter",
    "estimator",
    "inverse_dynamics",
    "base",
    "balance",
    "torque",
    "observer",
    "predictor",
    "supervisor",
)


class FusedTorqueController(WitnessFreeLeafSystem):
    """The fused controller as one LeafSystem (`build_torque_control(..., fused=True)`,
    `build_balance_control(..., fused=True)`).

    .. code-block:: text

                                 ┌───────────────────────┐
        sensors ────────────────►│                       ├──► q_cmd, servo_command
                                 │                       ├──► tau_estimated, tau_desired
                                 │                       ├──► delta_q, fallback_active
                                 │ FusedTorqueController ├──► sensor_fault
        sensor_time ────────────►│                       ├──► external_wrench_<s>
        joint_reference ────────►│                       ├──► the six Δq components
        f_ref (force task) ─────►│                       ├──► supervisor_mode, _fault,
        com_ref (balance) ──────►│                       │    _transition (supervised)
                                 │                       ├──► base_state, balance_com,
                                 │                       │    _sole_wrenches,
                                 │                       │    _contact_forces, _fault,
                                 └───────────────────────┘    _fault_count (balance)

    `sensors` is the station's sensor signals one after the other, the rows of the
    sensor buffer but the stamps (`ControllerLayout`: q_measured, the IMU's two,
    wrench_<s> each): one port, read once a tick.

    The timing of the separate systems and of the samplers around them
    (`hrp2_drake.step.StepSystem`, `assembly.builders`), in one system. Its state:
    the committed `FusedController.state`, the time of the sample now shown, the
    reference held from its sampling instant (q_ref, v_ref, vdot_ref, f_ref,
    com_ref: the reference ports are read as they are, a function of time, and
    latched at each sampling instant) and the command the servo holds
    (`servo_command`, taken at each multiple of the period: the one sample between a
    command and the servo). A cache entry runs the tick on a copy of the committed
    state with the sensors as they are now and the held reference; the outputs are
    slices of it (direct feedthrough from the sensors), q_cmd its command. A periodic
    event at the station's sampling instants (`hrp2_drake.step.sampling_offset`)
    commits the tick and latches the reference (and, without a lead, the servo's
    command; on a bus, at each multiple).
    """

    def __init__(self, parts: TorqueChainParts):
        super().__init__()
        self._fused = fused = FusedController(parts)
        N = len(parts.all_joints)
        layout = fused.layout
        # The station's sensor signals in one port, the sensor buffer's rows but the
        # stamps (`ControllerLayout`: `add_fused_controller` multiplexes them).
        self._sensor_port = self.DeclareVectorInputPort(
            "sensors", layout.num_joints + layout.num_values
        )
        self._sensor_rows = fused.sensor_buffer[: layout.num_joints + layout.num_values]
        self._stamp_port = (
            self.DeclareVectorInputPort("sensor_time", layout.num_stamps)
            if layout.num_stamps
            else None
        )
        # The reference ports, each with its rows of `FusedController.reference`: the
        # joints' [q_ref; v_ref; vdot_ref] in one (`joint_reference`, one Eval a
        # tick), then f_ref and com_ref where the chain reads them.
        others = list(fused.chain.references.items())[3:]
        self._reference_ports = [
            (
                self.DeclareVectorInputPort("joint_reference", 3 * N),
                fused.reference[: 3 * N],
            ),
            *(
                (self.DeclareVectorInputPort(name, size), getattr(fused, name))
                for name, size in others
            ),
        ]
        self._group = int(self.DeclareDiscreteState(fused.state.copy()))
        self._sample_time = int(self.DeclareDiscreteState(1))
        self._reference = int(self.DeclareDiscreteState(fused.reference.copy()))
        self._command = self.DeclareDiscreteState(N)
        self._q_ref_rows = slice(0, N)  # of the held reference
        self.DeclareInitializationDiscreteUpdateEvent(self._initialize)
        self._lead = parts.sample_lead
        offset = sampling_offset(
            parts.period, parts.sample_lead, "FusedTorqueController"
        )
        self.DeclarePeriodicDiscreteUpdateEvent(parts.period, offset, self._commit)
        if self._lead > 0:  # the servo takes its command at the multiples
            self.DeclarePeriodicDiscreteUpdateEvent(parts.period, 0.0, self._send)
        model = AbstractValue.Make(np.zeros(fused.state.size))
        sensors = [self._sensor_port.ticket()]
        if self._stamp_port is not None:
            sensors.append(self._stamp_port.ticket())
        self._ticked = self.DeclareCacheEntry(
            "ticked",
            ValueProducer(allocate=model.Clone, calc=self._calc_ticked),
            {self.xd_ticket(), *sensors},
        )
        ticked = {self._ticked.ticket()}
        self._q_cmd_out = np.zeros(N)
        self.DeclareVectorOutputPort(
            "q_cmd",
            N,
            self._calc_q_cmd,
            prerequisites_of_calc=ticked | {self.xd_ticket()},
        )
        self.DeclareStateOutputPort("servo_command", self._command)
        self._command = int(self._command)
        # Every logged signal of the chain but the command: rows of the tick's state
        # (a sum of rows for the filters' input fault).
        for name in fused.chain.logged():
            if name == "q_cmd":
                continue
            rows = fused.logged_rows(name)
            size = rows[0].stop - rows[0].start if isinstance(rows, list) else rows.size
            self.DeclareVectorOutputPort(
                name,
                size,
                lambda context, output, rows=rows: output.SetFromVector(
                    _read_rows(self._ticked.Eval(context), rows)
                ),
                prerequisites_of_calc=ticked,
            )
        # The cache value whose contents `fused.state` holds (None: unknown).
        self._holds = None

    def layout(self) -> ControllerLayout:
        """The rows of its sensor buffer (`sensors`, then `sensor_time`)."""
        return self._fused.layout

    def _read_sensors(self, context: Context) -> None:
        self._sensor_rows[:] = self._sensor_port.Eval(context)
        if self._stamp_port is not None:
            self._fused.sensor_time[:] = self._stamp_port.Eval(context)

    def _read_reference(self, context: Context) -> None:
        """The reference ports as they are now, into `FusedController.reference`."""
        for port, buffer in self._reference_ports:
            buffer[:] = port.Eval(context)

    def _initialize(self, context: Context, state: DiscreteValues) -> None:
        fused = self._fused
        self._holds = None
        fused.state[:] = state.get_value(self._group)
        self._read_sensors(context)
        self._read_reference(context)
        fused.initialize(context.get_time())
        state.set_value(self._group, fused.state)
        state.get_mutable_value(self._sample_time)[0] = context.get_time()
        state.set_value(self._reference, fused.reference)
        # Before the first multiple the servo holds the reference's pose.
        state.set_value(self._command, fused.q_ref)

    def _calc_ticked(self, context: Context, value: AbstractValue) -> None:
        fused = self._fused
        fused.state[:] = context.get_discrete_state(self._group).get_value()
        self._read_sensors(context)
        fused.reference[:] = context.get_discrete_state(self._reference).get_value()
        fused.tick(context.get_discrete_state(self._sample_time).get_value()[0])
        ticked = value.get_mutable_value()
        ticked[:] = fused.state
        self._holds = ticked  # the cache value `fused.state` equals now

    def _command_now(self, context: Context) -> np.ndarray:
        """The command of the tick now shown (into a work array)."""
        fused = self._fused
        ticked = self._ticked.Eval(context)
        if ticked is not self._holds:  # another context's tick ran since
            fused.state[:] = ticked
            self._holds = ticked
        held = context.get_discrete_state(self._reference).get_value()
        return fused.command(held[self._q_ref_rows], self._q_cmd_out)

    def _commit(self, context: Context, state: DiscreteValues) -> None:
        if self._lead == 0:
            self._send(context, state)
        if new_sample(context, self._sample_time):
            state.set_value(self._group, self._ticked.Eval(context))
            state.get_mutable_value(self._sample_time)[0] = context.get_time()
        # (at the initialization's instant only the reference: the same)
        self._read_reference(context)
        state.set_value(self._reference, self._fused.reference)

    def _send(self, context: Context, state: DiscreteValues) -> None:
        """The servo takes the command of the tick now shown."""
        state.set_value(self._command, self._command_now(context))

    def _calc_q_cmd(self, context: Context, output: BasicVector) -> None:
        output.SetFromVector(self._command_now(context))


def _read_rows(state: np.ndarray, rows: list[slice] | np.ndarray) -> np.ndarray:
    """A logged signal from a state vector: its rows (one slice), the sum of several
    slices, or a take of indices."""
    if not isinstance(rows, list):
        return state[rows]
    if len(rows) == 1:
        return state[rows[0]]
    return sum(state[r] for r in rows)
