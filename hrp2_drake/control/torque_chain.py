"""The torque-control chain declared once: `torque_chain(parts)`, the table of rows
(`hrp2_drake.chain`) from which both shells are built, the separate LeafSystems
(`assembly.builders`) and the fused controller (`control.fused`).

The rows, in the order a tick runs them (one tick from sample to command,
`hrp2_drake.step`): the estimation chain's (`estimation_rows`: the encoders' and the
other sensors' Savitzky-Golay filters, the estimator); τ_d from the inverse dynamics
(eq. 12), or with a balance front end from the base's state (the soles' kinematics)
and the whole-body QP; the Δq controller (eq. 10-11); the disturbance observer and
the delay predictor, which read this tick's Δq and which the rows above read one
tick late (held); the safety supervisor, whose q_cmd is the command (without it, the
controlled joints' q_cmd merged into the reference). Each row names its inputs: a
station signal, a reference, or another row's output, the controlled joints' entries
of one where a row works on them (`controlled`).

Adding a step is its module, one row here and its config field (`TorqueChainParts`).
"""

from dataclasses import dataclass, field
from enum import IntEnum

from pydrake.math import RigidTransform
from pydrake.multibody.plant import MultibodyPlant

from hrp2_drake.chain import (
    Arg,
    Chain,
    Row,
    Source,
    Sum,
    args,
    concatenated,
    entries,
    merged,
    whole,
)
from hrp2_drake.control.balance import (
    BalanceConfig,
    WholeBodyBalanceController,
    WholeBodyBalanceControllerStep,
)
from hrp2_drake.control.disturbance_observer import (
    DisturbanceObserver,
    DisturbanceObserverConfig,
    DisturbanceObserverStep,
)
from hrp2_drake.control.inverse_dynamics import (
    TORQUE_COMPONENTS,
    InverseDynamicsConfig,
    InverseDynamicsController,
    InverseDynamicsControllerStep,
)
from hrp2_drake.control.predictor import (
    DelayPredictor,
    DelayPredictorConfig,
    DelayPredictorStep,
)
from hrp2_drake.control.safety import (
    SafetyConfig,
    SafetySupervisor,
    SafetySupervisorStep,
)
from hrp2_drake.control.torque_controller import (
    DELTA_Q_COMPONENTS,
    DeltaQTorqueController,
    DeltaQTorqueControllerStep,
    TorqueControllerConfig,
)
from hrp2_drake.description.contacts import ContactsDescription
from hrp2_drake.estimation.base_kinematics import (
    FloatingBaseFromSoles,
    FloatingBaseFromSolesStep,
    ImuFusion,
)
from hrp2_drake.estimation.estimation_chain import estimation_rows
from hrp2_drake.estimation.estimator_config import TorqueEstimatorConfig
from hrp2_drake.estimation.savitzky_golay import (
    SavitzkyGolayFilter,
    SavitzkyGolayFilterStep,
)
from hrp2_drake.identification.motor_model import MotorModel

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
    the soles' kinematics (`FloatingBaseFromSolesStep`) and the whole-body QP with
    contacts (`WholeBodyBalanceControllerStep`), in the inverse dynamics' place.

    Args:
        plant: the robot alone with its floating base (the QP's and the base
            estimate's model; both steps share it, each with its own context).
        config: the QP; its joints are every joint of the robot, in its order.
        contacts: the soles' rectangles and the ground's friction (the
            description's `contacts`).
        sole_poses: each sole frame's pose in the world where it stands (X_WS): the
            anchors of the base's estimate.
        velocity_window: the samples of the base estimate's own Savitzky-Golay
            filter (order 2, centred) of the encoders (and the gyro): the joint
            velocities the base's state and the QP read, shorter than the torque
            estimator's window (its delay, (N − 1) / 2 periods, is the QP's
            damping's).
        imu: the gyro in the base's orientation (`ImuFusion`), None: the soles'
            kinematics alone.
    """

    plant: MultibodyPlant
    config: BalanceConfig
    contacts: ContactsDescription
    sole_poses: dict[str, RigidTransform]
    velocity_window: int
    imu: ImuFusion | None = None


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
        period: the control period (s; a keyword, no default).
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
    period: float = field(kw_only=True)
    balance: BalanceParts | None = None
    sample_lead: float = 0.0

    def check(self) -> None:
        """A ValueError unless the parts make one chain: the estimator's and the
        balance QP's joints are the robot's, in its order; no force task beside a
        balance QP (it has its own contact forces)."""
        if list(self.estimator_config.joints) != list(self.all_joints):
            raise ValueError(
                "torque chain: the estimator's joints must be the robot's joints, "
                "in its order"
            )
        balance = self.balance
        if balance is not None and list(balance.config.joints) != list(self.all_joints):
            raise ValueError(
                "torque chain: the balance QP's joints must be the robot's joints, "
                "in its order"
            )
        if balance is not None and self.force_sensor:
            raise ValueError(
                "torque chain: a force task and a balance QP (it has its own contact "
                "forces)"
            )


#: The six components of Δq of paper Sec. 5.5 that the chain logs (the controller's
#: seventh, the torque integral, is zero with the paper's K_i = 0).
COMPONENTS = DELTA_Q_COMPONENTS[:6]


def torque_chain(parts: TorqueChainParts) -> Chain:
    """The chain of `parts` as a table (module docstring)."""
    parts.check()
    rows = estimation_rows(
        parts.estimator_plant, parts.estimator_config, lead=parts.sample_lead
    )
    faults = tuple(f"{row.name}/input_fault" for row in rows[:-1])
    fault = Sum(faults, name="torque_estimator_input_fault")
    c = _Controlled(parts)
    if parts.balance is None:
        rows.append(_inverse_dynamics_row(parts, c))
        tau_desired = whole("inverse_dynamics/tau_desired")
    else:
        rows += _balance_rows(parts)
        tau_desired = c("balance/tau_desired")
    rows.append(_torque_row(parts, c, tau_desired, fault))
    if parts.observer is not None:
        rows.append(_observer_row(parts, c))
    if parts.predictor is not None:
        rows.append(_predictor_row(parts, c))
    N = len(parts.all_joints)
    merger = merged("reference/q_ref", N, "torque/q_cmd", c.index, name="merger")
    command: Source = merger
    if parts.supervisor is not None:
        rows.append(_supervisor_row(parts, merger))
        command = whole("supervisor/q_cmd")
    references = {"q_ref": N, "v_ref": N, "vdot_ref": N}
    if parts.force_sensor:
        references["f_ref"] = 6
    if parts.balance is not None:
        references["com_ref"] = 9
    return Chain(tuple(rows), command, references)


class _Controlled:
    """The controlled joints' entries of a signal of every joint (one Selector each
    in a Diagram, shared by its readers)."""

    def __init__(self, parts: TorqueChainParts):
        self.index = [parts.all_joints.index(j) for j in parts.joints]

    def __call__(self, signal: str):
        return entries(
            signal, self.index, name=f"{signal.replace('/', '_')}_controlled"
        )

    def velocity_estimate(self, parts: TorqueChainParts):
        """q̂̇ of the controlled joints: the delay predictor's (held), or the filter's."""
        if parts.predictor is not None:
            return whole("predictor/v_predicted")
        return self("encoder_filter/derivative")

    def velocity(self, parts: TorqueChainParts, source: str):
        return {
            "estimate": self.velocity_estimate(parts),
            "reference": self("reference/v_ref"),
        }[source]


def _inverse_dynamics_row(parts: TorqueChainParts, c: _Controlled) -> Row:
    """τ_d of eq. 12 and its terms: the reference, q (the encoders or q̂), the
    feedback velocity, and with a force task f_d and the sensor's f̂."""
    position = {"encoders": "station/q_measured", "estimate": "encoder_filter/value"}
    inputs = {
        "q_ref": c("reference/q_ref"),
        "v_ref": c("reference/v_ref"),
        "vdot_ref": c("reference/vdot_ref"),
        "q": c(position[parts.position_source]),
        "v": c.velocity(parts, parts.feedback_velocity),
    }
    if parts.force_sensor:
        inputs["f_ref"] = whole("reference/f_ref")
        inputs["f"] = whole(f"estimator/external_wrench_{parts.force_sensor}")
    plant, config, lead = parts.id_plant, parts.id_config, parts.sample_lead
    return Row(
        name="inverse_dynamics",
        system_name="inverse_dynamics",
        make_step=lambda: InverseDynamicsControllerStep(plant, config),
        make_system=lambda: InverseDynamicsController(plant, config, lead=lead),
        inputs=inputs,
        outputs=("tau_desired", *TORQUE_COMPONENTS),
        logged={"tau_desired": whole("inverse_dynamics/tau_desired")},
    )


def _balance_rows(parts: TorqueChainParts) -> list[Row]:
    """The balance front end: the base's own filter (`_base_filter_row`), the base's
    state from the soles (the encoders, that filter's velocities and, with an IMU,
    its gyro), then the whole-body QP (the base's state, q_ref, com_ref)."""
    balance, joints, lead = parts.balance, list(parts.all_joints), parts.sample_lead
    n = len(joints)
    base_inputs = {
        "q": whole("station/q_measured"),
        "v": entries("base_filter/derivative", range(n), name="base_velocities"),
    }
    if balance.imu is not None:
        base_inputs["gyro"] = entries(
            "base_filter/value", range(n, n + 3), name="base_gyro"
        )
    qp_inputs = {
        "state": whole("base/state"),
        "q_ref": whole("reference/q_ref"),
        "com_ref": whole("reference/com_ref"),
    }
    qp_outputs = ("tau_desired", *BALANCE_SIGNALS)
    return [
        _base_filter_row(parts),
        Row(
            name="base",
            system_name="base_from_soles",
            make_step=lambda: FloatingBaseFromSolesStep(
                balance.plant, joints, balance.sole_poses, balance.imu, parts.period
            ),
            make_system=lambda: FloatingBaseFromSoles(
                balance.plant,
                joints,
                balance.sole_poses,
                parts.period,
                lead=lead,
                imu=balance.imu,
            ),
            inputs=base_inputs,
            outputs={"state": "robot_state"},
            logged={"base_state": whole("base/state")},
        ),
        Row(
            name="balance",
            system_name="balance",
            make_step=lambda: WholeBodyBalanceControllerStep(
                balance.plant, balance.config, balance.contacts
            ),
            make_system=lambda: WholeBodyBalanceController(
                balance.plant, balance.config, balance.contacts, parts.period, lead=lead
            ),
            inputs=qp_inputs,
            outputs=qp_outputs,
            logged={"tau_desired": whole("balance/tau_desired")}
            | {f"balance_{s}": whole(f"balance/{s}") for s in BALANCE_SIGNALS},
            event=EventKind.BALANCE_FAULT,
            event_state="fault",
        ),
    ]


def _base_filter_row(parts: TorqueChainParts) -> Row:
    """The base estimate's own filter: the encoders (and the gyro, with an IMU) at
    `BalanceParts.velocity_window`, order 2, centred: the joint velocities, and the
    gyro's rate the base's orientation integrates, of one instant. Its input faults
    are the estimation's filters' too (the same signals), counted there."""
    balance, lead, period = parts.balance, parts.sample_lead, parts.period
    size = len(parts.all_joints) + (3 if balance.imu is not None else 0)
    window = balance.velocity_window
    signals = ["station/q_measured"]
    if balance.imu is not None:
        signals.append("station/imu_angular_velocity")
    return Row(
        name="base_filter",
        system_name="base_filter",
        inputs={"signal": concatenated(*signals, name="base_filter_signals")},
        arguments=args("signal"),
        outputs=("value", "derivative", "input_fault"),
        initialize=args("signal"),
        make_step=lambda: SavitzkyGolayFilterStep(size, window, 2, period, "centre"),
        make_system=lambda: SavitzkyGolayFilter(
            size, window, 2, period, "centre", lead=lead
        ),
    )


def _torque_row(parts, c: _Controlled, tau_desired: Source, fault: Sum) -> Row:
    """The Δq controller (eq. 10-11): τ_d (and the inverse dynamics' terms), τ̂ (the
    predictor's, held, or the filter's), the friction's velocity, the encoders, the
    reference, the filters' input fault and the observer's d̂ (held)."""
    tau_estimate = (
        whole("predictor/tau_predicted")
        if parts.predictor is not None
        else c("estimator/tau")
    )
    inputs = {
        "tau_desired": tau_desired,
        "tau_estimated": tau_estimate,
        "v": c.velocity(parts, parts.friction_velocity),
        "q_measured": c("station/q_measured"),
        "q_ref": c("reference/q_ref"),
        "sensor_fault": fault,
    }
    terms = Arg()
    if parts.balance is None:
        inputs |= {t: whole(f"inverse_dynamics/{t}") for t in TORQUE_COMPONENTS}
        terms = Arg(TORQUE_COMPONENTS, (len(TORQUE_COMPONENTS), len(parts.joints)))
    disturbance = Arg()
    if parts.observer is not None:
        inputs["tau_disturbance"] = whole("observer/disturbance")
        disturbance = Arg(("tau_disturbance",))
    model, config, lead = (
        parts.controller_model,
        parts.controller_config,
        parts.sample_lead,
    )
    logged = ("delta_q", "fallback_active", *COMPONENTS)
    return Row(
        name="torque",
        system_name="torque_controller",
        make_step=lambda: DeltaQTorqueControllerStep(model, config),
        make_system=lambda: DeltaQTorqueController(model, config, lead=lead),
        inputs=inputs,
        arguments=(
            *args(
                "tau_desired",
                "tau_estimated",
                "v",
                "q_measured",
                "q_ref",
                "sensor_fault",
            ),
            terms,
            disturbance,
        ),
        outputs=("q_cmd", *logged),
        logged={name: whole(f"torque/{name}") for name in logged},
        initialize=args("q_measured", "q_ref"),
        event=EventKind.CONTROLLER_FALLBACK,
    )


def _observer_row(parts: TorqueChainParts, c: _Controlled) -> Row:
    """d̂ from this tick's Δq, q̂̇ and τ̂; the Δq controller reads it one tick late."""
    observer, lead = parts.observer, parts.sample_lead
    inputs = {
        "delta_q": whole("torque/delta_q"),
        "v": c("encoder_filter/derivative"),
        "tau_estimated": c("estimator/tau"),
    }
    return Row(
        name="observer",
        system_name="disturbance_observer",
        make_step=lambda: DisturbanceObserverStep(observer.model, observer.config),
        make_system=lambda: DisturbanceObserver(
            observer.model, observer.config, lead=lead
        ),
        inputs=inputs,
        outputs=("disturbance",),
        held=frozenset({"disturbance"}),
    )


def _predictor_row(parts: TorqueChainParts, c: _Controlled) -> Row:
    """τ̂ and q̂̇ carried over the chain's delay with this tick's Δq; the rows above
    read them one tick late."""
    model, config, lead = parts.controller_model, parts.predictor, parts.sample_lead
    inputs = {
        "v_estimated": c("encoder_filter/derivative"),
        "vdot_estimated": c("encoder_filter/second_derivative"),
        "tau_estimated": c("estimator/tau"),
        "delta_q": whole("torque/delta_q"),
    }
    outputs = ("v_predicted", "tau_predicted")
    return Row(
        name="predictor",
        system_name="delay_predictor",
        make_step=lambda: DelayPredictorStep(model, config),
        make_system=lambda: DelayPredictor(model, config, lead=lead),
        inputs=inputs,
        outputs=outputs,
        held=frozenset(outputs),
    )


def _supervisor_row(parts: TorqueChainParts, merger: Source) -> Row:
    """The safety supervisor: the merged command, the reference, the encoders, the
    monitored sensors, the controller's fallback (with balance, plus the QP's fault
    code) and the sensors' stamps; its q_cmd is the chain's command."""
    supervisor, lead, N = parts.supervisor, parts.sample_lead, len(parts.all_joints)
    period = parts.period
    fallback: Source = whole("torque/fallback_active")
    if parts.balance is not None:
        fallback = Sum(("torque/fallback_active", "balance/fault"), name="fallback")
    monitored = tuple(supervisor.monitored)
    inputs = {
        "q_torque": merger,
        "q_position": whole("reference/q_ref"),
        "q_measured": whole("station/q_measured"),
        **{name: whole(f"station/{name}") for name in monitored},
        "controller_fallback": fallback,
    }
    stamps = Arg()
    if supervisor.num_stamps:
        inputs["sensor_time"] = whole("station/sensor_time")
        stamps = Arg(("sensor_time",))
    states = ("mode", "fault", "transition")
    return Row(
        name="supervisor",
        system_name="safety_supervisor",
        make_step=lambda: SafetySupervisorStep(
            N, supervisor.monitored, supervisor.config, period, supervisor.num_stamps
        ),
        make_system=lambda: SafetySupervisor(
            N,
            supervisor.monitored,
            supervisor.config,
            period,
            num_sensor_stamps=supervisor.num_stamps,
            lead=lead,
        ),
        inputs=inputs,
        arguments=(
            *args("q_torque", "q_position", "q_measured"),
            Arg(monitored, (-1,)),
            Arg(),  # no e-stop
            Arg(("controller_fallback",)),
            stamps,
        ),
        outputs={"q_cmd": None} | {s: s for s in states},
        logged={f"supervisor_{s}": whole(f"supervisor/{s}") for s in states},
        initialize=(*args("q_measured", "q_position"), Arg(monitored, (-1,))),
        timed_initialize=False,
        event=EventKind.SUPERVISOR_FAULT,
    )
