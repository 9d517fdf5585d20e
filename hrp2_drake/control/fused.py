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
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.framework import (
    BasicVector,
    Context,
    DiscreteValues,
    ValueProducer,
)

from hrp2_drake.control.balance import BalanceConfig, BalanceStep
from hrp2_drake.control.disturbance_observer import (
    DisturbanceObserverConfig,
    DisturbanceObserverStep,
)
from hrp2_drake.control.inverse_dynamics import (
    TORQUE_COMPONENTS,
    InverseDynamicsConfig,
    InverseDynamicsStep,
)
from hrp2_drake.control.predictor import DelayPredictorConfig, DelayPredictorStep
from hrp2_drake.control.safety import SafetyConfig, SafetySupervisorStep
from hrp2_drake.control.torque_controller import (
    DELTA_Q_COMPONENTS,
    DeltaQTorqueStep,
    TorqueControllerConfig,
)
from hrp2_drake.description import RobotDescription
from hrp2_drake.description.contacts import ContactsDescription
from hrp2_drake.estimation.base_kinematics import BaseFromSolesStep
from hrp2_drake.estimation.estimator_config import TorqueEstimatorConfig, filter_windows
from hrp2_drake.estimation.estimator_step import TorqueEstimatorStep
from hrp2_drake.estimation.savitzky_golay import SavitzkyGolayStep
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.simulation import WitnessFreeLeafSystem
from hrp2_drake.step import Step, new_sample, sampling_offset

#: The balance QP's signals among the fused controller's (`balance_<name>`), as
#: `build_balance_control` exports them.
BALANCE_SIGNALS = ("com", "sole_wrenches", "contact_forces", "fault", "fault_count")


class EventKind(IntEnum):
    """What the fused controller records of a tick's events (`FusedController.events`,
    column 1); the code in column 2 is a `FallbackReason`, the supervisor's fault
    bits (`control.safety.describe_faults`) or a `control.balance.BalanceFault`.
    Each is recorded when it starts (a balance fault also when its kind changes),
    not at every tick it lasts."""

    CONTROLLER_FALLBACK = 1
    SUPERVISOR_FAULT = 2
    BALANCE_FAULT = 3


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


@dataclass(frozen=True)
class ObserverParts:
    """The disturbance observer's model (the controller's, without Coulomb friction)
    and config."""

    model: MotorModel
    config: DisturbanceObserverConfig


@dataclass(frozen=True)
class SupervisorParts:
    """The safety supervisor's monitored sensors ({station port: kind}), config, and
    the number of sensor stamps it checks (`sensor_time`, one per signal)."""

    monitored: dict[str, str]
    config: SafetyConfig
    num_stamps: int


@dataclass(frozen=True)
class BalanceParts:
    """The balance front end of the chain (issue 29): the floating base's state from
    the soles' kinematics (`BaseFromSolesStep`) and the whole-body QP with contacts
    (`BalanceStep`), in the inverse dynamics' place.

    Args:
        plant: the robot alone with its floating base (the QP's and the base
            estimate's model; both steps share it, each with its own context).
        config: the QP; its joints are every joint of the robot, in its order.
        contacts: the soles' rectangles and the ground's friction (the
            description's `contacts`).
        sole_poses: each sole frame's pose in the world where it stands (X_WS): the
            anchors of the base's estimate.
    """

    plant: MultibodyPlant
    config: BalanceConfig
    contacts: ContactsDescription
    sole_poses: dict[str, RigidTransform]


@dataclass
class TorqueChainParts:
    """Everything the torque-control chain is made of, as data: the models and configs
    that the separate LeafSystems and the fused controller are both built from
    (`hrp2_drake.assembly.builders.torque_chain_parts` makes it).

    Args:
        all_joints: the robot's joints (every joint vector of the station).
        joints: the torque-controlled joints (a subset, any order).
        estimator_plant, estimator_config: the floating-base estimator's model.
        id_plant, id_config: the inverse dynamics' fixed-base model and gains.
        controller_model, controller_config: the Δq controller (eq. 10-11).
        observer: the disturbance observer's model and config, or None.
        predictor: the delay predictor's config (model: controller_model), or None.
        supervisor: the safety supervisor's parts, or None: the Δq controller's
            latched fallback alone.
        position_source: "encoders" or "estimate" (q of eq. 12).
        feedback_velocity, friction_velocity: "estimate" or "reference".
        force_sensor: the F/T sensor whose f̂ feeds the force task ("" = none).
        period: the control period (s).
        balance: the balance front end, or None: the inverse dynamics (id_plant,
            id_config) gives τ_d. With it, the QP's τ* of `joints` does, and
            id_plant, id_config, position_source, feedback_velocity and
            force_sensor are unused.
        sample_lead: the station samples its sensors this long (s, less than a
            period) before each multiple of the period (a bus: its read-to-write
            delay); the Diagram shells commit each tick at the sampling instants.
    """

    all_joints: list[str]
    joints: list[str]
    estimator_plant: MultibodyPlant
    estimator_config: TorqueEstimatorConfig
    id_plant: MultibodyPlant
    id_config: InverseDynamicsConfig
    controller_model: MotorModel
    controller_config: TorqueControllerConfig
    observer: ObserverParts | None = None
    predictor: DelayPredictorConfig | None = None
    supervisor: SupervisorParts | None = None
    position_source: str = "encoders"
    feedback_velocity: str = "reference"
    friction_velocity: str = "reference"
    force_sensor: str = ""
    period: float = field(default=0.001)
    balance: BalanceParts | None = None
    sample_lead: float = 0.0


def _start_in(array: np.ndarray, view: np.ndarray) -> int:
    """The index in the 1-D `array` of the first entry of `view`, a contiguous view on
    it."""
    offset = view.__array_interface__["data"][0] - array.__array_interface__["data"][0]
    return offset // array.itemsize


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
        self._n = len(joints)
        self._index = np.array([all_joints.index(j) for j in joints])
        econfig = parts.estimator_config
        if list(econfig.joints) != list(all_joints):
            raise ValueError(
                "FusedController: the estimator's joints must be the robot's joints, "
                "in its order"
            )
        balance = parts.balance
        if balance is not None and list(balance.config.joints) != list(all_joints):
            raise ValueError(
                "FusedController: the balance QP's joints must be the robot's joints, "
                "in its order"
            )
        if balance is not None and parts.force_sensor:
            raise ValueError(
                "FusedController: a force task and a balance QP (it has its own "
                "contact forces)"
            )
        #: The rows of `sensor_buffer`, for every shell that fills it.
        self.layout = ControllerLayout(
            num_joints=self._N,
            has_imu=bool(econfig.imu_frame),
            sensor_names=tuple(econfig.sensors),
            num_stamps=parts.supervisor.num_stamps if parts.supervisor else 0,
        )
        self._make_steps()
        self._make_state()
        self._make_buffers()
        self._wire()
        self._make_gathers()
        # Events: (t, kind, code) rows, a ring of the latest ones, and counts.
        self.events = np.zeros((256, 3))
        self.num_events = 0
        self.event_counts = {kind: 0 for kind in EventKind}
        self.warmed_up = False  # (`warm_up`)

    # ------------------------------------------------------------------ wiring

    def _make_steps(self) -> None:
        """The steps of the chain, from `parts` (None for a step it does not have)."""
        parts, N = self.parts, self._N
        econfig = parts.estimator_config
        encoder_windows, sensor_windows = filter_windows(econfig)
        self.encoder_filter = SavitzkyGolayStep(
            N,
            encoder_windows,
            2,
            econfig.period,
            econfig.evaluation,
            span=econfig.span(),
        )
        num_values = self.layout.num_values
        self.sensor_filter = (
            SavitzkyGolayStep(
                num_values,
                sensor_windows,
                1,
                econfig.period,
                econfig.evaluation,
                span=econfig.span(),
            )
            if num_values
            else None
        )
        self.estimator = TorqueEstimatorStep(parts.estimator_plant, econfig)
        balance = parts.balance
        # τ_d: the inverse dynamics, or the base from the soles and the balance QP.
        self.inverse_dynamics = self.base = self.balance = None
        if balance is None:
            self.inverse_dynamics = InverseDynamicsStep(parts.id_plant, parts.id_config)
        else:
            self.base = BaseFromSolesStep(
                balance.plant, list(parts.all_joints), balance.sole_poses
            )
            self.balance = BalanceStep(balance.plant, balance.config, balance.contacts)
        self.torque = DeltaQTorqueStep(parts.controller_model, parts.controller_config)
        observer = parts.observer
        self.observer = (
            DisturbanceObserverStep(observer.model, observer.config)
            if observer
            else None
        )
        self.predictor = (
            DelayPredictorStep(parts.controller_model, parts.predictor)
            if parts.predictor
            else None
        )
        supervisor = parts.supervisor
        self.supervisor = (
            SafetySupervisorStep(
                N, supervisor.monitored, supervisor.config, supervisor.num_stamps
            )
            if supervisor
            else None
        )

    def _make_state(self) -> None:
        """One state vector for all steps, each step bound to its rows (moved into
        `_sources` by `_make_buffers`)."""
        steps = [
            ("encoder_filter", self.encoder_filter),
            ("sensor_filter", self.sensor_filter),
            ("estimator", self.estimator),
            ("inverse_dynamics", self.inverse_dynamics),
            ("base", self.base),
            ("balance", self.balance),
            ("torque", self.torque),
            ("observer", self.observer),
            ("predictor", self.predictor),
            ("supervisor", self.supervisor),
        ]
        self._steps: dict[str, Step] = {name: s for name, s in steps if s is not None}
        self._offsets: dict[str, int] = {}
        size = 0
        for name, step in self._steps.items():
            self._offsets[name] = size
            size += step.state_size
        self.state = np.zeros(size)
        for name, step in self._steps.items():
            start = self._offsets[name]
            step.bind(self.state[start : start + step.state_size])
        self._initial_state = self.state.copy()

    def _make_buffers(self) -> None:
        N, n = self._N, self._n
        layout = self.layout
        # Everything a tick reads, in one buffer (`_sources`): the steps' state
        # (`state`, moved here: what each step computed so far in the tick), the
        # station's signals (`sensor_buffer`, rows: `layout`), q_ref, v_ref,
        # vdot_ref, f_ref, com_ref (with balance), and six zeros (no force reading),
        # so that `take`s with precomputed rows select the controlled joints' inputs
        # (`_make_gathers`).
        com_ref = 9 if self.balance is not None else 0
        sizes = [self.state.size, layout.size, N, N, N, 6, com_ref, 6]
        self._sources = np.zeros(sum(sizes))
        ends = np.cumsum(sizes)
        (
            state,
            self.sensor_buffer,
            self.q_ref,
            self.v_ref,
            self.vdot_ref,
            self.f_ref,
            self.com_ref,
            self._no_force,
        ) = (self._sources[end - size : end] for size, end in zip(sizes, ends))
        for name, step in self._steps.items():
            start = self._offsets[name]
            step.bind(state[start : start + step.state_size])
        self.state = state
        #: The whole reference in one view: [q_ref; v_ref; vdot_ref; f_ref; com_ref].
        start = ends[1]
        self.reference = self._sources[start : start + 3 * N + 6 + com_ref]
        self.q_measured = self.sensor_buffer[layout.q_measured]
        self.sensor_values = self.sensor_buffer[layout.values]
        self.sensor_time = self.sensor_buffer[layout.stamps]
        self.q_measured_time = self.sensor_buffer[layout.q_measured_stamp]
        # Selections of the controlled joints, previous and now (`_make_gathers`);
        # with balance, also the reference's and the QP's τ* (no inverse dynamics'
        # inputs to take them from).
        names = ("q_measured", "q_hat", "v_hat", "vdot_hat", "tau_hat")
        if self.balance is not None:
            names += ("q_ref", "v_ref", "tau_star")
        self._gathered = np.zeros(len(names) * n)
        self._selected = {
            name: self._gathered[i * n : (i + 1) * n] for i, name in enumerate(names)
        }
        self._merged = np.zeros(N)
        self._fault = np.zeros(1)
        # The supervisor's controller fallback with balance: the Δq controller's plus
        # the QP's fault code (`_balance_fallback`).
        self._controller_fallback = np.zeros(1)
        self._no_fault = np.zeros(1)  # the sensor filter's fault without one

    def _state_view(self, step_name: str, array_name: str) -> np.ndarray:
        """The named array of a step: what it computed last (this tick's once it
        stepped in the tick, the previous tick's before)."""
        step = self._steps[step_name]
        rows = step.rows(array_name)
        start = self._offsets[step_name]
        return self.state[start + rows.start : start + rows.stop]

    def _wire(self) -> None:
        s = self._state_view
        self._s_q_hat = s("encoder_filter", "value")
        self._s_v_hat = s("encoder_filter", "derivative")
        self._s_vdot_hat = s("encoder_filter", "second_derivative")
        self._s_encoder_fault = s("encoder_filter", "input_fault")
        self._s_sensor_fault = self._no_fault
        if self.sensor_filter is not None:
            values = s("sensor_filter", "value")
            rates = s("sensor_filter", "derivative")
            self._s_sensor_fault = s("sensor_filter", "input_fault")
            layout = self.layout
            rows = {
                name: layout.in_values(signal)
                for name, signal in layout.signals().items()
                if name != "q_measured"
            }
            imu = layout.has_imu
            acc, gyro = "imu_linear_acceleration", "imu_angular_velocity"
            self._s_acc = values[rows[acc]] if imu else None
            self._s_gyro = values[rows[gyro]] if imu else None
            self._s_alpha = rates[rows[gyro]] if imu else None
            names = layout.sensor_names
            self._s_wrenches = (
                values[rows[f"wrench_{names[0]}"].start :].reshape(len(names), 6)
                if names
                else None
            )
        else:
            self._s_acc = self._s_gyro = self._s_alpha = self._s_wrenches = None
        self._s_tau = s("estimator", "tau")
        self._s_force = (
            s("estimator", f"external_wrench_{self.parts.force_sensor}")
            if self.parts.force_sensor
            else None
        )
        self._s_q_cmd_controlled = s("torque", "q_cmd")
        self._s_delta_q = s("torque", "delta_q")
        self._s_fallback = s("torque", "fallback_active")
        self._s_disturbance = s("observer", "disturbance") if self.observer else None
        if self.predictor is not None:
            self._s_v_predicted = s("predictor", "v_predicted")
            self._s_tau_predicted = s("predictor", "tau_predicted")
        if self.balance is None:
            self._wire_inverse_dynamics()
        else:
            self._wire_balance()

    def _wire_inverse_dynamics(self) -> None:
        """τ_d and its terms (the Δq controller's inputs): the inverse dynamics'."""
        self._s_tau_desired = self._state_view("inverse_dynamics", "tau_desired")
        rows = [self.inverse_dynamics.rows(name) for name in TORQUE_COMPONENTS]
        start = self._offsets["inverse_dynamics"]
        contiguous = all(a.stop == b.start for a, b in zip(rows, rows[1:]))
        if not contiguous:
            raise ValueError("InverseDynamicsStep: the torque terms must be contiguous")
        self._s_terms = self.state[
            start + rows[0].start : start + rows[-1].stop
        ].reshape(len(TORQUE_COMPONENTS), self._n)
        self._supervisor_fallback = self._s_fallback

    def _wire_balance(self) -> None:
        """The balance front end's inputs: the base's state, the QP's τ* (all
        joints; `_make_gathers` selects the controlled ones) and fault code. The Δq
        controller gets τ* alone (no terms: τ_ff = τ*, as in the separate diagram),
        the supervisor the sum of the two fallbacks (the separate diagram's
        Adder)."""
        s = self._state_view
        self._s_robot_state = s("base", "robot_state")
        self._s_balance_tau = s("balance", "tau_desired")
        self._s_balance_fault = s("balance", "fault")
        self._s_terms = None
        self._supervisor_fallback = self._controller_fallback

    def _source_rows(self, view: np.ndarray) -> np.ndarray:
        """The rows of `_sources` that a view on it covers."""
        start = _start_in(self._sources, view)
        return np.arange(start, start + view.size)

    def _make_gathers(self) -> None:
        """The selections of a tick, as row indices into `_sources`: the inverse
        dynamics' inputs, straight into its `inputs` ([q_ref; v_ref; vdot_ref;
        position; velocity (; f_ref; f̂)], controlled joints), and `_gathered`
        ([q_measured; q̂; q̂̇; q̂̈; τ̂ (; q_ref; v_ref; τ*)], controlled joints); and
        the views the steps read them from."""
        rows, index, sel = self._source_rows, self._index, self._selected
        gathered = [
            self.q_measured,
            self._s_q_hat,
            self._s_v_hat,
            self._s_vdot_hat,
            self._s_tau,
        ]
        if self.predictor is not None:
            v_estimate, tau_estimate = self._s_v_predicted, self._s_tau_predicted
        else:
            v_estimate, tau_estimate = sel["v_hat"], sel["tau_hat"]
        self._tau_estimate = tau_estimate
        if self.balance is None:
            q_ref, v_ref = self._gather_inverse_dynamics()
        else:
            gathered += [self.q_ref, self.v_ref, self._s_balance_tau]
            q_ref, v_ref = sel["q_ref"], sel["v_ref"]
            self._tau_desired = sel["tau_star"]
        # In the order of `_gathered`'s names (`_make_buffers`).
        self._gather = np.concatenate([rows(view)[index] for view in gathered])
        # What the Δq controller reads besides: q_ref, τ̂ and the friction's q̂̇.
        self._q_ref_controlled = q_ref
        friction = {"estimate": v_estimate, "reference": v_ref}
        self._v_friction = friction[self.parts.friction_velocity]

    def _gather_inverse_dynamics(self) -> tuple[np.ndarray, np.ndarray]:
        """The inverse dynamics' inputs as rows of `_sources` (`_make_gathers`);
        returns the views of q_ref and v_ref (controlled joints) among them."""
        rows, index = self._source_rows, self._index
        parts = self.parts
        if self.predictor is not None:
            v_estimate_rows = rows(self._s_v_predicted)
        else:
            v_estimate_rows = rows(self._s_v_hat)[index]
        velocity = {"estimate": v_estimate_rows, "reference": rows(self.v_ref)[index]}
        encoders = parts.position_source == "encoders"
        position = self.q_measured if encoders else self._s_q_hat
        id_rows = [
            rows(self.q_ref)[index],
            rows(self.v_ref)[index],
            rows(self.vdot_ref)[index],
            rows(position)[index],
            velocity[parts.feedback_velocity],
        ]
        if self.inverse_dynamics.has_force_task():  # f_d and f̂, or zeros
            if self._s_force is not None:
                id_rows += [rows(self.f_ref), rows(self._s_force)]
            else:
                id_rows += [rows(self._no_force)] * 2
        self._id_gather = np.concatenate(id_rows)
        self._id_inputs = self.inverse_dynamics.inputs
        self._id_rows = self.inverse_dynamics.input_rows
        self._tau_desired = self._s_tau_desired
        return self._id_rows[0], self._id_rows[1]

    # ------------------------------------------------------------------ ticks

    def warm_up(self) -> float:
        """Compiles, or loads from numba's cache, every kernel of the chain's steps
        (`Step.warm_up`: each called on arrays of a real tick's types, no state
        changed), before a loop starts; the wall time it took (s). A real-time loop
        refuses to start before it (`warmed_up`) and forbids compiling while it runs
        (`hrp2_drake.kernels.freeze`)."""
        start = time.perf_counter()
        for step in self._steps.values():
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
        q_measured, q_ref = self._selected["q_measured"], self._q_ref_controlled
        self.q_measured.take(self._index, out=q_measured, mode="clip")
        self.q_ref.take(self._index, out=q_ref, mode="clip")
        self.encoder_filter.initialize(t, self.q_measured)
        if self.sensor_filter is not None:
            self.sensor_filter.initialize(t, self.sensor_values)
        self.torque.initialize(t, q_measured, q_ref)
        if self.supervisor is not None:
            self.supervisor.initialize(self.q_measured, self.q_ref, self.sensor_values)

    def tick(self, t: float) -> None:
        """One control period at time t (s) from the current `sensor_buffer` and
        reference buffers (q_ref, v_ref, vdot_ref, f_ref; com_ref with balance).

        One tick from sample to command: the steps run in the chain's order and each
        reads what its upstream steps computed in this tick; the observer and the
        predictor close loops through the Δq controller, which reads their output of
        the previous tick (module docstring)."""
        sources = self._sources
        # Filters and estimator (paper Sec. 2), on this tick's samples.
        self.encoder_filter.step(t, self.q_measured)
        if self.sensor_filter is not None:
            self.sensor_filter.step(t, self.sensor_values)
        self.estimator.step(
            t,
            self._s_q_hat,
            self._s_v_hat,
            self._s_vdot_hat,
            self._s_acc,
            self._s_gyro,
            self._s_alpha,
            self._s_wrenches,
        )
        if self.balance is None:
            # Eq. 12 from its input rows, filled in place by the take.
            sources.take(self._id_gather, 0, self._id_inputs, "clip")
            self.inverse_dynamics.step(t, *self._id_rows)
        else:
            self._balance_tick(t)
        # Every selection of the controlled joints the Δq controller and the loops
        # read: one take.
        sources.take(self._gather, 0, self._gathered, "clip")
        sel = self._selected
        q_measured, v_hat, tau_hat = sel["q_measured"], sel["v_hat"], sel["tau_hat"]
        fault = self._fault
        fault[0] = self._s_encoder_fault[0] + self._s_sensor_fault[0]
        reason = self.torque.step(
            t,
            self._tau_desired,
            self._tau_estimate,
            self._v_friction,
            q_measured,
            self._q_ref_controlled,
            fault,
            self._s_terms,
            self._s_disturbance,
        )
        if reason:
            self._record(t, EventKind.CONTROLLER_FALLBACK, reason)
        if self.balance is not None:  # the supervisor's controller fallback
            self._balance_fallback()
        if self.observer is not None:
            self.observer.step(t, self._s_delta_q, v_hat, tau_hat)
        if self.predictor is not None:
            self.predictor.step(t, v_hat, sel["vdot_hat"], tau_hat, self._s_delta_q)
        if self.supervisor is not None:
            merged = self._merged
            merged[:] = self.q_ref
            merged[self._index] = self._s_q_cmd_controlled
            bits = self.supervisor.step(
                t,
                merged,
                self.q_ref,
                self.q_measured,
                self.sensor_values,
                None,
                self._supervisor_fallback,
                self.sensor_time,
            )
            if bits:
                self._record(t, EventKind.SUPERVISOR_FAULT, bits)

    def _balance_tick(self, t: float) -> None:
        """The balance front end's part of a tick: the base from the soles (the
        encoders and q̂̇ of this tick), then the QP (the base's state of this tick,
        q_ref and com_ref)."""
        self.base.step(t, self.q_measured, self._s_v_hat)
        previous = self._s_balance_fault[0]
        code = self.balance.step(t, self._s_robot_state, self.q_ref, self.com_ref)
        if code and code != previous:
            self._record(t, EventKind.BALANCE_FAULT, code)

    def command(self, q_ref: np.ndarray, out: np.ndarray) -> np.ndarray:
        """The position command for the servo (all joints) after a tick, with the
        reference q_ref of the moment it is sent (the diagram's q_cmd output)."""
        merged = self._merged
        merged[:] = q_ref
        merged[self._index] = self.torque.q_cmd
        if self.supervisor is None:
            out[:] = merged
            return out
        fallback = self.torque.fallback_active
        if self.balance is not None:
            fallback = self._balance_fallback()
        self.supervisor.q_cmd(merged, q_ref, fallback, out)
        return out

    def _balance_fallback(self) -> np.ndarray:
        """The supervisor's controller fallback with balance, of the tick in the
        state: the Δq controller's plus the QP's fault code (the separate diagram's
        Adder)."""
        fallback = self._controller_fallback
        fallback[0] = self.torque.fallback_active[0] + self.balance.fault[0]
        return fallback

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
        """The logged signals (views on the state): the names of
        `build_torque_control`'s output ports (with balance, `build_balance_control`'s:
        tau_desired is the QP's, of every joint; base_state, balance_com,
        balance_sole_wrenches, balance_contact_forces, balance_fault,
        balance_fault_count)."""
        balance = self.balance
        tau_desired = self.inverse_dynamics if balance is None else balance
        out = {
            "tau_estimated": self.estimator.tau,
            "tau_desired": tau_desired.tau_desired,
            "delta_q": self.torque.delta_q,
            "fallback_active": self.torque.fallback_active,
        }
        if balance is not None:
            out["base_state"] = self.base.robot_state
            for name in BALANCE_SIGNALS:
                out[f"balance_{name}"] = getattr(balance, name)
        for name in self.layout.sensor_names:
            wrench = f"external_wrench_{name}"
            out[wrench] = getattr(self.estimator, wrench)
        for name in DELTA_Q_COMPONENTS[:6]:
            out[name] = getattr(self.torque, name)
        if self.supervisor is not None:
            for name in ("mode", "fault", "transition"):
                out[f"supervisor_{name}"] = getattr(self.supervisor, name)
        return out


class FusedTorqueController(WitnessFreeLeafSystem):
    """The fused controller as one LeafSystem (`build_torque_control(..., fused=True)`,
    `build_balance_control(..., fused=True)`).

    .. code-block:: text

                                 ┌───────────────────────┐
        q_measured ─────────────►│                       ├──► q_cmd, servo_command
        imu_linear_acceleration ►│                       ├──► tau_estimated, tau_desired
        imu_angular_velocity ───►│                       ├──► delta_q, fallback_active
        wrench_<s> (each) ──────►│ FusedTorqueController ├──► sensor_fault
        sensor_time ────────────►│                       ├──► external_wrench_<s>
        q_ref, v_ref, vdot_ref ─►│                       ├──► the six Δq components
        f_ref (force task) ─────►│                       ├──► supervisor_mode, _fault,
        com_ref (balance) ──────►│                       │    _transition (supervised)
                                 │                       ├──► base_state, balance_com,
                                 │                       │    _sole_wrenches,
                                 │                       │    _contact_forces, _fault,
                                 └───────────────────────┘    _fault_count (balance)

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
        # The station's sensor ports, each with its rows of the sensor buffer.
        self._sensor_ports = [
            (
                self.DeclareVectorInputPort(name, rows.stop - rows.start),
                fused.sensor_buffer[rows],
            )
            for name, rows in layout.signals().items()
        ]
        self._stamp_port = (
            self.DeclareVectorInputPort("sensor_time", layout.num_stamps)
            if layout.num_stamps
            else None
        )
        # The reference ports, each with its rows of `FusedController.reference`.
        self._reference_ports = [
            (self.DeclareVectorInputPort(name, N), getattr(fused, name))
            for name in ("q_ref", "v_ref", "vdot_ref")
        ]
        if parts.force_sensor:
            self._reference_ports.append(
                (self.DeclareVectorInputPort("f_ref", 6), fused.f_ref)
            )
        if parts.balance:
            self._reference_ports.append(
                (self.DeclareVectorInputPort("com_ref", 9), fused.com_ref)
            )
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
        sensors = [port.ticket() for port, _ in self._sensor_ports]
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
        for name, view in fused.signals().items():
            rows = self._rows_of(view)
            self.DeclareVectorOutputPort(
                name,
                len(view),
                lambda context, output, rows=rows: output.SetFromVector(
                    self._ticked.Eval(context)[rows]
                ),
                prerequisites_of_calc=ticked,
            )
        fault_rows = [self._rows_of(fused.encoder_filter.input_fault)]
        if fused.sensor_filter is not None:
            fault_rows.append(self._rows_of(fused.sensor_filter.input_fault))
        self.DeclareVectorOutputPort(
            "sensor_fault",
            1,
            lambda context, output: output.SetFromVector(
                [sum(self._ticked.Eval(context)[r][0] for r in fault_rows)]
            ),
            prerequisites_of_calc=ticked,
        )
        # The cache value whose contents `fused.state` holds (None: unknown).
        self._holds = None

    def _rows_of(self, view: np.ndarray) -> slice:
        """The rows of the fused state that a state view covers."""
        start = _start_in(self._fused.state, view)
        return slice(start, start + view.size)

    def _read_sensors(self, context: Context) -> None:
        for port, rows in self._sensor_ports:
            rows[:] = port.Eval(context)
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
