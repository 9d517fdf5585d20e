"""Diagram builders for the control experiments (paper Sec. 5): the robot's own
position control (the baseline) and the paper's torque control.

.. code-block:: text

    build_position_control:
        reference ──► q_cmd ──► station

    build_torque_control:
        reference ─┬──────────────────────────────────────────► q_ref (other joints)
                   └─► InverseDynamicsController ─► DeltaQTorqueController ─► merger ─► station
                             ▲  q̂, q̂̇ (or encoders)      ▲ τ̂, q̂̇, encoders            │
                             └──────── add_estimator (SG filters + RNEA) ◄──────────────┘

Both return a `ControlDiagram`: the diagram, which exports every signal an experiment
logs as a named output port (`LOGGED`), and its station.
"""

import functools
import weakref
from dataclasses import dataclass, replace

import numpy as np
from pydrake.systems.framework import Diagram, DiagramBuilder, OutputPort, PortDataType
from pydrake.systems.primitives import MatrixGain, TrajectorySource
from pydrake.trajectories import (
    FunctionHandleTrajectory,
    PiecewisePolynomial,
    Trajectory,
)

from hrp2_drake.control.inverse_dynamics import (
    InverseDynamicsConfig,
    InverseDynamicsController,
    make_fixed_base_plant,
)
from hrp2_drake.control.disturbance_observer import (
    DisturbanceObserver,
    DisturbanceObserverConfig,
)
from hrp2_drake.control.fused import FusedTorqueController, TorqueChainParts
from hrp2_drake.control.predictor import DelayPredictor, DelayPredictorConfig
from hrp2_drake.control.safety import SafetySupervisor, supervisor_sensors
from hrp2_drake.control.torque_controller import (
    DELTA_Q_COMPONENTS,
    DeltaQTorqueController,
    JointCommandMerger,
    TorqueControllerConfig,
    connect_inverse_dynamics,
    inverse_dynamics_gains_for_k6,
    make_joint_selector,
)
from hrp2_drake.description import RobotDescription
from hrp2_drake.estimation.torque_estimator import add_estimator
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.multibody import joint_indexing
from hrp2_drake.robot.station import StationConfig, make_station, sensor_sizes
from hrp2_drake.assembly.torque_control import TorqueControlConfig, check_control_period

#: The six components of Δq of paper Sec. 5.5 (the controller's seventh, the torque
#: integral, is zero with the paper's K_i = 0).
COMPONENTS = DELTA_Q_COMPONENTS[:6]


#: Segments per piece of `first_order_hold`.
HOLD_PIECE = 1000


def first_order_hold(
    breaks: np.ndarray,
    samples: np.ndarray,
    shift: float = 0.0,
    after: PiecewisePolynomial | None = None,
) -> PiecewisePolynomial:
    """`PiecewisePolynomial.FirstOrderHold(breaks, samples)` (samples: one column a
    break) shifted right by `shift` (s) and appended to `after` if given (then
    returned), built `HOLD_PIECE` segments at a time.

    The same polynomials at the same breaks as FirstOrderHold, shiftRight and
    ConcatenateInTime of the whole (a segment depends on its two samples alone, and
    the pieces meet exactly), without their copies: FirstOrderHold takes twice the
    memory of its result while it builds it, ConcatenateInTime copies its argument,
    and a 1 kHz reference is large (the climbing motion, 16 001 segments x 90 rows,
    is a 210 MB PiecewisePolynomial: 440 MB while FirstOrderHold builds it whole).
    """
    trajectory = after
    for k in range(0, max(len(breaks) - 1, 1), HOLD_PIECE):
        piece = PiecewisePolynomial.FirstOrderHold(
            breaks[k : k + HOLD_PIECE + 1], samples[:, k : k + HOLD_PIECE + 1]
        )
        piece.shiftRight(shift)
        if trajectory is None:
            trajectory = piece
        else:
            trajectory.ConcatenateInTime(piece)
    return trajectory


@dataclass
class JointReference:
    """A joint-space reference for all n joints of a robot: positions, velocities,
    accelerations as one trajectory of 3n rows [q; q̇; q̈] (rad, rad/s, rad/s²)."""

    trajectory: PiecewisePolynomial

    @staticmethod
    def from_samples(t: np.ndarray, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> "JointReference":
        """Linear interpolation between dense samples (e.g. 1 kHz), by
        `first_order_hold`."""
        return JointReference(first_order_hold(t, np.hstack([q, v, a]).T))

    @staticmethod
    def hold(q: np.ndarray, duration: float) -> "JointReference":
        n = len(q)
        values = np.concatenate([q, np.zeros(2 * n)])
        return JointReference(
            PiecewisePolynomial.ZeroOrderHold([0.0, duration], np.column_stack([values, values]))
        )

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x = self.trajectory.value(t).ravel()
        n = len(x) // 3
        return x[:n], x[n : 2 * n], x[2 * n :]

    def end_time(self) -> float:
        return self.trajectory.end_time()


def borrowed(trajectory: Trajectory) -> FunctionHandleTrajectory:
    """`trajectory` for a `TrajectorySource`, neither copied nor kept alive by it:
    the source evaluates `trajectory` itself (the same values) as long as the
    caller keeps it alive (a `ControlDiagram` keeps its own).

    Why: TrajectorySource keeps a copy of its trajectory, a 1 kHz reference is large
    (the climbing motion, a PiecewisePolynomial of 16 001 segments x 90 rows, takes
    210 MB), and pydrake 1.51.1 on Python 3.11 never frees a Diagram holding a
    Python LeafSystem (every control diagram here: such a system's tp_traverse
    visits its __dict__ twice, so the garbage collector takes the cycles through it
    for reachable). A copy per diagram stayed for the life of the process.
    """
    owner = weakref.ref(trajectory)

    def value(t: float) -> np.ndarray:
        alive = owner()
        if alive is None:
            raise RuntimeError(
                "the trajectory of this TrajectorySource was freed: keep its "
                "ControlDiagram while simulating the diagram"
            )
        return alive.value(t)

    return FunctionHandleTrajectory(
        value,
        trajectory.rows(),
        trajectory.cols(),
        trajectory.start_time(),
        trajectory.end_time(),
    )


@dataclass
class ControlDiagram:
    """A built control experiment: the diagram (its output ports are the logged
    signals), its station, and the trajectories its diagram reads (kept alive here,
    not by the diagram: `borrowed`)."""

    diagram: Diagram
    station: Diagram
    reference: JointReference
    force_reference: PiecewisePolynomial | None = None

    def output_names(self) -> list[str]:
        """The logged signals: every vector output (not `contact_results`)."""
        return [
            port.get_name()
            for port in map(self.diagram.get_output_port, range(self.diagram.num_output_ports()))
            if port.get_data_type() == PortDataType.kVectorValued
        ]


def _build(
    builder: DiagramBuilder,
    station: Diagram,
    ports: dict[str, OutputPort],
    reference: JointReference,
    force_reference: PiecewisePolynomial | None = None,
) -> ControlDiagram:
    if station.HasOutputPort("contact_results"):
        ports = ports | {"contact_results": station.GetOutputPort("contact_results")}
    for name, port in ports.items():
        builder.ExportOutput(port, name)
    return ControlDiagram(builder.Build(), station, reference, force_reference)


def _add_reference(builder: DiagramBuilder, reference: JointReference, n: int):
    if reference.trajectory.rows() != 3 * n:
        raise ValueError(
            f"the joint reference has {reference.trajectory.rows()} rows, expected "
            f"3 x {n} joints"
        )
    source = builder.AddNamedSystem(
        "reference", TrajectorySource(borrowed(reference.trajectory))
    )
    blocks = {}
    for k, name in enumerate(("q_ref", "v_ref", "vdot_ref")):
        select = np.zeros((n, 3 * n))
        select[:, k * n : (k + 1) * n] = np.eye(n)
        gain = builder.AddNamedSystem(f"{name}_all", MatrixGain(select))
        builder.Connect(source.get_output_port(), gain.get_input_port())
        blocks[name] = gain.get_output_port()
    return blocks


def _station_ports(station: Diagram, robot: RobotDescription) -> dict[str, OutputPort]:
    """The station's logged ports (ground truth only if it has it: a simulation)."""
    names = ["q_measured", "joint_torque_true", "state_true"]
    if robot.force_sensor:
        names.append(f"wrench_{robot.force_sensor}")
    return {name: station.GetOutputPort(name) for name in names if station.HasOutputPort(name)}


def _add_station(builder: DiagramBuilder, station_config: StationConfig, meshcat, station):
    """The given station (e.g. `hardware.make_lcm_station`), or the simulated one."""
    if station is None:
        station = make_station(station_config, meshcat)
    return builder.AddNamedSystem("station", station)


def build_position_control(
    station_config: StationConfig, reference: JointReference, meshcat=None, station=None
) -> ControlDiagram:
    """The baseline: the robot's own position servo tracking the reference (q_cmd =
    q_ref). `station`: a station Diagram to use instead of simulating
    `station_config` (e.g. the LCM hardware station; the config still names the
    robot)."""
    robot = station_config.description()
    builder = DiagramBuilder()
    station = _add_station(builder, station_config, meshcat, station)
    blocks = _add_reference(builder, reference, len(robot.joints))
    builder.Connect(blocks["q_ref"], station.GetInputPort("q_cmd"))
    ports = _station_ports(station, robot) | {
        "q_ref": blocks["q_ref"],
        "q_cmd": blocks["q_ref"],
    }
    return _build(builder, station, ports, reference)


def _joint_inertia(plant, all_joints: list[str], joints: list[str], q: np.ndarray) -> np.ndarray:
    """Diagonal of the mass matrix (kg·m², reflected rotor inertia included) of
    `joints` at the joint angles q (all_joints order): what sets K_d for a damping
    ratio."""
    if not np.all(np.isfinite(q)):
        raise ValueError(f"the reference's joint angles at t = 0 are not finite: {q}")
    indexing = joint_indexing(plant, all_joints)
    context = plant.CreateDefaultContext()
    x = plant.GetPositions(context)
    x[indexing.q] = q
    plant.SetPositions(context, x)
    rows = indexing.subset(joints).v
    return np.diag(plant.CalcMassMatrix(context))[rows]


def torque_chain_parts(
    robot: RobotDescription,
    reference: JointReference,
    motor_model: MotorModel,
    config: TorqueControlConfig,
) -> TorqueChainParts:
    """The models and configs of the torque-control chain of `config` on `robot`: what
    both the separate systems and the fused controller are built from."""
    config.validate()
    joints = config.controlled_joints(robot)
    unknown = [j for j in joints if j not in robot.joints]
    if unknown:
        raise ValueError(
            f"TorqueControlConfig.joints: {unknown} are not joints of robot '{robot.name}'"
        )
    if len(config.kp) not in (1, len(joints)):
        raise ValueError(
            f"TorqueControlConfig.kp: {len(config.kp)} values for {len(joints)} "
            "joints (give one, or one per joint)"
        )
    all_joints = list(robot.joints)
    # The controllers' model of the robot (with errors, if asked: a fault).
    errors = dict(model_error=config.model_error, seed=config.model_error_seed)
    estimator_config = robot.estimator_config(
        config.window,
        windows=dict(config.windows),
        evaluation=config.evaluation,
        offset_calibration_time=config.offset_calibration_time,
        offset_calibration_start=0.2,
    )
    # Inverse dynamics on the fixed-base model (paper footnote 3): a floating robot's
    # base welded upright at the origin, a fixed robot as it is mounted.
    if robot.base == "fixed":
        fixed = robot.make_plant(weld_base=True, **errors)
    else:
        fixed = make_fixed_base_plant(
            functools.partial(robot.add_model, weld_base=False, **errors), robot.base_body
        )
    controller_model = motor_model.subset(joints)
    inertia = _joint_inertia(fixed, all_joints, joints, reference.at(0.0)[0])
    ks, kd = inverse_dynamics_gains_for_k6(
        controller_model.k_tau, config.k6, inertia, config.kp, config.damping_ratio
    )
    id_config = InverseDynamicsConfig(
        joints=joints,
        ks=ks.tolist(),
        kd=kd.tolist(),
        force_frame=config.force_frame,
        kf=list(config.kf) if config.force_frame else [0.0],
    )
    controller_config = TorqueControllerConfig(
        joints=joints,
        kp=list(config.kp),
        delta_q_limit=[config.delta_q_limit],
        start_time=config.start_time,
        latch_fallback=not config.supervised,
        disturbance_compensation=config.disturbance_observer > 0,
    )
    delay = (estimator_config.delay_samples() + 2) * estimator_config.period
    observer = None
    if config.disturbance_observer > 0:
        # The observer inverts the controller's own model: no Coulomb term (the
        # controller sends none), so what friction the model misses is d̂'s.
        observer = (
            MotorModel(
                joints, controller_model.k_tau, controller_model.k_v, np.zeros(len(joints))
            ),
            DisturbanceObserverConfig(
                joints=joints, bandwidth=config.disturbance_observer, delay=delay
            ),
        )
    predictor = None
    if config.predictor:
        predictor = DelayPredictorConfig(
            joints=joints, delay=delay, inertia=inertia.tolist()
        )
    supervisor = None
    if config.supervised:
        supervisor = (
            supervisor_sensors(robot.sensor_names(), imu=robot.has_imu()),
            replace(config.safety, start_time=config.start_time),
            len(sensor_sizes(robot)),
        )
    return TorqueChainParts(
        all_joints=all_joints,
        joints=joints,
        estimator_plant=robot.make_plant(**errors),
        estimator_config=estimator_config,
        id_plant=fixed,
        id_config=id_config,
        controller_model=controller_model,
        controller_config=controller_config,
        observer=observer,
        predictor=predictor,
        supervisor=supervisor,
        position_source=config.position_source,
        feedback_velocity=config.feedback_velocity,
        friction_velocity=config.friction_velocity,
        force_sensor=robot.sensor_of_body(config.force_frame) if config.force_frame else "",
        period=estimator_config.period,
    )


def build_torque_control(
    station_config: StationConfig,
    reference: JointReference,
    motor_model: MotorModel,
    config: TorqueControlConfig,
    meshcat=None,
    force_reference: PiecewisePolynomial | None = None,
    station: Diagram | None = None,
    fused: bool = False,
) -> ControlDiagram:
    """Station + estimation chain + inverse dynamics + Δq torque controller (paper Sec.
    4) on `config.joints`, the other joints in position control on the reference.
    `station`: a station Diagram with the simulated station's ports to use instead of
    simulating `station_config` (e.g. `hardware.make_lcm_station`: the same
    controller on hardware; the config still names the robot).
    `fused`: the whole chain as one `FusedTorqueController` (the real-time path; the
    same signals to 1e-12) instead of its separate systems."""
    robot = station_config.description()
    check_control_period(config, station_config)
    parts = torque_chain_parts(robot, reference, motor_model, config)
    builder = DiagramBuilder()
    station = _add_station(builder, station_config, meshcat, station)
    blocks = _add_reference(builder, reference, len(parts.all_joints))
    f_ref = None
    if config.force_frame:
        f_ref = builder.AddNamedSystem(
            "force_reference", TrajectorySource(borrowed(force_reference))
        ).get_output_port()
    build = _add_fused_chain if fused else _add_separate_chain
    ports = build(builder, station, robot, parts, blocks, f_ref)
    builder.Connect(ports["q_cmd"], station.GetInputPort("q_cmd"))
    ports = _station_ports(station, robot) | ports | {"q_ref": blocks["q_ref"]}
    return _build(builder, station, ports, reference, force_reference)


def _add_fused_chain(builder, station, robot, parts, blocks, f_ref) -> dict[str, OutputPort]:
    fused = builder.AddNamedSystem("fused_controller", FusedTorqueController(parts))
    for k in range(fused.num_input_ports()):
        port = fused.get_input_port(k)
        name = port.get_name()
        if name in blocks:
            builder.Connect(blocks[name], port)
        elif name == "f_ref":
            builder.Connect(f_ref, port)
        else:
            builder.Connect(station.GetOutputPort(name), port)
    names = ["q_cmd", "tau_estimated", "tau_desired", "delta_q", "fallback_active",
             "sensor_fault", *COMPONENTS]
    if parts.supervisor is not None:
        names += [f"supervisor_{name}" for name in ("mode", "fault", "transition")]
    if robot.force_sensor:
        names.append(f"external_wrench_{robot.force_sensor}")
    return {name: fused.GetOutputPort(name) for name in names}


def _add_separate_chain(builder, station, robot, parts, blocks, f_ref) -> dict[str, OutputPort]:
    """The chain as its separate LeafSystems (the design card's diagram)."""
    all_joints, joints = parts.all_joints, parts.joints
    chain = add_estimator(builder, station, parts.estimator_plant, parts.estimator_config)

    def select(name: str):
        """A selector of the controlled joints from a vector of all joints."""
        return builder.AddNamedSystem(name, make_joint_selector(all_joints, joints))

    inverse_dynamics = builder.AddNamedSystem(
        "inverse_dynamics", InverseDynamicsController(parts.id_plant, parts.id_config)
    )
    selected = {}
    for name in ("q_ref", "v_ref", "vdot_ref"):
        selected[name] = sel = select(f"{name}_controlled")
        builder.Connect(blocks[name], sel.get_input_port())
        builder.Connect(sel.get_output_port(), inverse_dynamics.GetInputPort(name))
    q_enc = select("q_measured_controlled")
    builder.Connect(station.GetOutputPort("q_measured"), q_enc.get_input_port())
    q_hat = select("q_estimate_controlled")
    builder.Connect(chain.encoder_filter.GetOutputPort("value"), q_hat.get_input_port())
    v_hat = select("v_estimate_controlled")
    builder.Connect(chain.encoder_filter.GetOutputPort("derivative"), v_hat.get_input_port())
    tau_hat = select("tau_estimate_controlled")
    builder.Connect(chain.estimator.GetOutputPort("tau"), tau_hat.get_input_port())
    position = q_enc if parts.position_source == "encoders" else q_hat
    velocity = {
        "estimate": v_hat.get_output_port(),
        "reference": selected["v_ref"].get_output_port(),
    }
    torque_estimate = tau_hat.get_output_port()
    predictor = None
    if parts.predictor is not None:
        # τ̂ and q̂̇ carried from the chain's delay to the present (the Δq input is
        # connected below, once the controller exists).
        predictor = builder.AddNamedSystem(
            "delay_predictor", DelayPredictor(parts.controller_model, parts.predictor)
        )
        vdot_hat = select("vdot_estimate_controlled")
        builder.Connect(
            chain.encoder_filter.GetOutputPort("second_derivative"),
            vdot_hat.get_input_port(),
        )
        for source, target in (
            (v_hat, "v_estimated"),
            (vdot_hat, "vdot_estimated"),
            (tau_hat, "tau_estimated"),
        ):
            builder.Connect(source.get_output_port(), predictor.GetInputPort(target))
        velocity["estimate"] = predictor.GetOutputPort("v_predicted")
        torque_estimate = predictor.GetOutputPort("tau_predicted")
    builder.Connect(position.get_output_port(), inverse_dynamics.GetInputPort("q"))
    builder.Connect(velocity[parts.feedback_velocity], inverse_dynamics.GetInputPort("v"))
    if parts.force_sensor:
        builder.Connect(f_ref, inverse_dynamics.GetInputPort("f_ref"))
        builder.Connect(
            chain.estimator.GetOutputPort(f"external_wrench_{parts.force_sensor}"),
            inverse_dynamics.GetInputPort("f"),
        )

    torque = builder.AddNamedSystem(
        "torque_controller",
        DeltaQTorqueController(parts.controller_model, parts.controller_config),
    )
    connect_inverse_dynamics(builder, inverse_dynamics, torque)
    builder.Connect(torque_estimate, torque.GetInputPort("tau_estimated"))
    builder.Connect(velocity[parts.friction_velocity], torque.GetInputPort("v"))
    if predictor is not None:
        builder.Connect(torque.GetOutputPort("delta_q"), predictor.GetInputPort("delta_q"))
    builder.Connect(q_enc.get_output_port(), torque.GetInputPort("q_measured"))
    builder.Connect(selected["q_ref"].get_output_port(), torque.GetInputPort("q_ref"))
    builder.Connect(chain.input_fault, torque.GetInputPort("sensor_fault"))
    if parts.observer is not None:
        observer = builder.AddNamedSystem(
            "disturbance_observer", DisturbanceObserver(*parts.observer)
        )
        builder.Connect(torque.GetOutputPort("delta_q"), observer.GetInputPort("delta_q"))
        builder.Connect(v_hat.get_output_port(), observer.GetInputPort("v"))
        builder.Connect(tau_hat.get_output_port(), observer.GetInputPort("tau_estimated"))
        builder.Connect(observer.get_output_port(), torque.GetInputPort("tau_disturbance"))

    merger = builder.AddNamedSystem("merger", JointCommandMerger(all_joints, joints))
    builder.Connect(blocks["q_ref"], merger.GetInputPort("q_ref"))
    builder.Connect(torque.GetOutputPort("q_cmd"), merger.GetInputPort("q_controlled"))
    q_cmd = merger.get_output_port()
    supervisor_ports = {}
    if parts.supervisor is not None:
        monitored, safety, num_stamps = parts.supervisor
        supervisor = builder.AddNamedSystem(
            "safety_supervisor",
            SafetySupervisor(len(all_joints), monitored, safety, num_sensor_stamps=num_stamps),
        )
        builder.Connect(q_cmd, supervisor.GetInputPort("q_torque"))
        builder.Connect(blocks["q_ref"], supervisor.GetInputPort("q_position"))
        for name in ("q_measured", *monitored):
            builder.Connect(station.GetOutputPort(name), supervisor.GetInputPort(name))
        builder.Connect(
            torque.GetOutputPort("fallback_active"),
            supervisor.GetInputPort("controller_fallback"),
        )
        builder.Connect(
            station.GetOutputPort("sensor_time"), supervisor.GetInputPort("sensor_time")
        )
        q_cmd = supervisor.GetOutputPort("q_cmd")
        supervisor_ports = {
            f"supervisor_{name}": supervisor.GetOutputPort(name)
            for name in ("mode", "fault", "transition")
        }
    ports = supervisor_ports | {
        "q_cmd": q_cmd,
        "tau_estimated": chain.estimator.GetOutputPort("tau"),
        "tau_desired": inverse_dynamics.GetOutputPort("tau_desired"),
        "delta_q": torque.GetOutputPort("delta_q"),
        "fallback_active": torque.GetOutputPort("fallback_active"),
        "sensor_fault": chain.input_fault,
    }
    if robot.force_sensor:
        name = f"external_wrench_{robot.force_sensor}"
        ports[name] = chain.estimator.GetOutputPort(name)
    return ports | {name: torque.GetOutputPort(name) for name in COMPONENTS}
