"""The closed loop of any robot as one Diagram: the robot's own position control
(the baseline) and the paper's torque control (Sec. 4).

.. code-block:: text

    build_position_control:
        reference ──► q_cmd ──► station

    build_torque_control:
        reference ─┬──────────────────────────────────────────► q_ref (other joints)
                   ▼
        InverseDynamicsController ─► DeltaQTorqueController ─► merger ─► station
              ▲  q̂, q̂̇ (or encoders)      ▲ τ̂, q̂̇, encoders            │
              └──────── add_estimator (SG filters + RNEA) ◄──────────────┘

Both take the robot as data (its `RobotDescription`) and its station as a Diagram: a
simulated one (`simulated_station(StationConfig)`, which also gives the control
period), or any Diagram with its ports (a real robot runs the same chain without a
Diagram: `hardware.control_loop.ControlLoop`). Both return a
`ControlDiagram`: the diagram, which exports every signal an experiment logs as a
named output port (`ControlDiagram.output_names`), and its station.
"""

import functools
import weakref
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
from pydrake.geometry import Meshcat
from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.framework import Diagram, DiagramBuilder, OutputPort, PortDataType
from pydrake.systems.primitives import (
    Demultiplexer,
    Multiplexer,
    TrajectorySource,
    ZeroOrderHold,
)
from pydrake.trajectories import (
    FunctionHandleTrajectory,
    PiecewisePolynomial,
    Trajectory,
)

from hrp2_drake.assembly.torque_control import (
    TorqueControlConfig,
    delta_q_limit,
)
from hrp2_drake.chain import Chain, add_chain
from hrp2_drake.control.disturbance_observer import DisturbanceObserverConfig
from hrp2_drake.control.fused import FusedTorqueController
from hrp2_drake.control.gains import (
    inverse_dynamics_gains,
    inverse_dynamics_gains_for_k6,
)
from hrp2_drake.control.inverse_dynamics import (
    InverseDynamicsConfig,
    make_fixed_base_plant,
)
from hrp2_drake.control.predictor import DelayPredictorConfig
from hrp2_drake.control.safety import supervisor_sensors, with_sensor_ranges
from hrp2_drake.control.torque_chain import (
    ObserverParts,
    SupervisorParts,
    TorqueChainParts,
    torque_chain,
)
from hrp2_drake.control.torque_controller import TorqueControllerConfig
from hrp2_drake.description import RobotDescription
from hrp2_drake.estimation import estimator_config as estimation_config
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.multibody import joint_indexing
from hrp2_drake.robot.sensors import SensorSampler
from hrp2_drake.robot.station import StationConfig, make_station, sensor_sizes
from hrp2_drake.simulation import SampleHold
from hrp2_drake.step import sampling_offset

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
    and a 1 kHz reference is large (16 s of 30 joints, 16 001 segments x 90 rows, is
    a 210 MB PiecewisePolynomial: 440 MB while FirstOrderHold builds it whole).
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


class SmoothMove:
    """A move from `start` to `goal` (rad, every joint): a quintic with zero velocity
    and acceleration at both ends, no joint faster than `speed` rad/s (a quintic peaks
    at 15/8 of the mean speed), at least 0.2 s; none (`duration` 0) if `start` is
    within `tolerance` (rad) of `goal` on every joint (the position servo takes that
    step). The move that starts a run on a robot, from its measured pose."""

    def __init__(
        self, start: np.ndarray, goal: np.ndarray, speed: float, tolerance: float = 1e-3
    ):
        self.start = np.asarray(start, float)
        self.step = np.asarray(goal, float) - self.start
        distance = float(np.max(np.abs(self.step)))
        self.duration = (
            max(0.2, 1.875 * distance / speed) if distance > tolerance else 0.0
        )

    def at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """q, q̇, q̈ at the times t (s, 1-D, within the move): (len(t), n) each."""
        s = np.asarray(t, float) / self.duration
        e = s**3 * (10 - 15 * s + 6 * s**2)
        de = 30 * s**2 * (1 - s) ** 2 / self.duration
        dde = 60 * s * (1 - s) * (1 - 2 * s) / self.duration**2
        step = self.step
        return self.start + np.outer(e, step), np.outer(de, step), np.outer(dde, step)


@dataclass
class JointReference:
    """A joint-space reference for all n joints of a robot: positions, velocities,
    accelerations as one trajectory of 3n rows [q; q̇; q̈] (rad, rad/s, rad/s²);
    `approach_time`: the move from the robot's pose it starts with (s;
    `after_approach`)."""

    trajectory: PiecewisePolynomial
    approach_time: float = 0.0

    @staticmethod
    def from_samples(
        t: np.ndarray, q: np.ndarray, v: np.ndarray, a: np.ndarray
    ) -> "JointReference":
        """Linear interpolation between dense samples (e.g. 1 kHz), by
        `first_order_hold`."""
        return JointReference(first_order_hold(t, np.hstack([q, v, a]).T))

    @staticmethod
    def hold(q: np.ndarray, duration: float) -> "JointReference":
        n = len(q)
        values = np.concatenate([q, np.zeros(2 * n)])
        return JointReference(
            PiecewisePolynomial.ZeroOrderHold(
                [0.0, duration], np.column_stack([values, values])
            )
        )

    def after_approach(
        self, start: np.ndarray, speed: float = 0.5, tolerance: float = 1e-3
    ) -> "JointReference":
        """This reference (piecewise linear between its breaks, as `from_samples` and
        `hold` make it) delayed by a smooth move to its first pose from `start` (rad,
        every joint; the robot's measured pose): `SmoothMove`, its duration in
        `approach_time`; this reference itself if the move is none (`start` within
        `tolerance` of the first pose)."""
        move = SmoothMove(start, self.at(0.0)[0], speed, tolerance)
        if not move.duration:
            return self
        t = np.arange(0.0, move.duration, 0.001)
        later = self.trajectory.get_segment_times()
        samples = np.array([self.trajectory.value(x).ravel() for x in later])
        times = np.concatenate([t, move.duration + np.asarray(later)])
        values = np.vstack([np.hstack(move.at(t)), samples])
        return JointReference(
            first_order_hold(times, values.T), approach_time=move.duration
        )

    @staticmethod
    def split(
        values: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """q, q̇, q̈ (views) of reference values [q; q̇; q̈]: 3n entries along the last
        axis (one sample, or one row per sample). The one place the layout is read."""
        n = values.shape[-1] // 3
        return values[..., :n], values[..., n : 2 * n], values[..., 2 * n :]

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """q, q̇, q̈ at the time t (s), n each."""
        return JointReference.split(self.trajectory.value(t).ravel())

    def end_time(self) -> float:
        return self.trajectory.end_time()


def borrowed(trajectory: Trajectory, shift: float = 0.0) -> FunctionHandleTrajectory:
    """`trajectory` for a `TrajectorySource`, neither copied nor kept alive by it:
    the source evaluates `trajectory` itself (the same values) as long as the
    caller keeps it alive (a `ControlDiagram` keeps its own).

    Why: TrajectorySource keeps a copy of its trajectory, a 1 kHz reference is large
    (16 s of 30 joints, a PiecewisePolynomial of 16 001 segments x 90 rows, takes
    210 MB), and pydrake 1.51.1 on Python 3.11 never frees a Diagram holding a
    Python LeafSystem (every control diagram here: such a system's tp_traverse
    visits its __dict__ twice, so the garbage collector takes the cycles through it
    for reachable). A copy per diagram stayed for the life of the process.

    `shift` (s): the source gives the trajectory `shift` ahead, its value at t +
    shift (`ChainClock`).
    """
    owner = weakref.ref(trajectory)

    def value(t: float) -> np.ndarray:
        alive = owner()
        if alive is None:
            raise RuntimeError(
                "the trajectory of this TrajectorySource was freed: keep its "
                "ControlDiagram while simulating the diagram"
            )
        return alive.value(t + shift)

    return FunctionHandleTrajectory(
        value,
        trajectory.rows(),
        trajectory.cols(),
        trajectory.start_time() - shift,
        trajectory.end_time() - shift,
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
    #: Other trajectories its diagram reads that the builder made (e.g. a CoM
    #: reference moved by an offset), kept alive here.
    kept: tuple = ()

    def output_names(self) -> list[str]:
        """The logged signals: every vector output (not `contact_results`)."""
        return [
            port.get_name()
            for port in map(
                self.diagram.get_output_port, range(self.diagram.num_output_ports())
            )
            if port.get_data_type() == PortDataType.kVectorValued
        ]


def build_control_diagram(
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
    if station.HasInputPort("applied_spatial_force"):  # pushes, from outside
        builder.ExportInput(
            station.GetInputPort("applied_spatial_force"), "applied_spatial_force"
        )
    return ControlDiagram(builder.Build(), station, reference, force_reference)


def add_reference(
    builder: DiagramBuilder,
    reference: JointReference,
    n: int,
    chain: "ChainClock | None" = None,
) -> dict[str, OutputPort]:
    """q_ref, v_ref, vdot_ref of every joint from `reference`, as it is (a function
    of time: what position control follows and what is logged), and with `chain`
    also "chain_q_ref", "chain_v_ref", "chain_vdot_ref": what the torque chain
    reads (`ChainClock`); "reference" and "chain_reference": the three in one."""
    if reference.trajectory.rows() != 3 * n:
        raise ValueError(
            f"the joint reference has {reference.trajectory.rows()} rows, expected "
            f"3 x {n} joints"
        )
    sources = {
        "": builder.AddNamedSystem(
            "reference", TrajectorySource(borrowed(reference.trajectory))
        ).get_output_port()
    }
    if chain is not None:
        sources["chain_"] = chain.source(
            builder, "chain_reference", reference.trajectory
        )
    blocks = {f"{prefix}reference": port for prefix, port in sources.items()}
    for prefix, port in sources.items():
        # [q; v; v̇] into its three blocks (entries copied, in C++).
        split = builder.AddNamedSystem(
            f"{prefix}reference_split", Demultiplexer([n, n, n])
        )
        builder.Connect(port, split.get_input_port())
        for k, name in enumerate(("q_ref", "v_ref", "vdot_ref")):
            blocks[f"{prefix}{name}"] = split.get_output_port(k)
    return blocks


@dataclass(frozen=True)
class ChainClock:
    """How the torque chain of a diagram reads its references (joints, force, CoM).

    A discrete MultibodyPlant takes its step before the samplers of the same
    instant latch its state: the sample latched at t is the state of t + its time
    step (`shift`; a ZeroOrderHold on its state port logs the plant's own state at
    every instant). So the chain reads each reference `shift` ahead, at the time of
    the state its samples hold. The separate systems (`sampled`) read it held from
    each of the station's sampling instants to the next (a `SampleHold`, so that a
    tick's inputs hold still between two samples); the fused controller latches it
    itself.

    Args:
        parts: the chain's parts (its period and the station's sample lead).
        sampled: hold the references (the separate systems).
        shift: the station plant's time step (s; 0 for a continuous plant).
    """

    parts: TorqueChainParts
    sampled: bool
    shift: float

    def source(self, builder: DiagramBuilder, name: str, trajectory: Trajectory):
        """`trajectory` as the chain reads it: a `TrajectorySource` "name" `shift`
        ahead, held if `sampled`."""
        source = builder.AddNamedSystem(
            name, TrajectorySource(borrowed(trajectory, self.shift))
        ).get_output_port()
        if not self.sampled:
            return source
        period, lead = self.parts.period, self.parts.sample_lead
        hold = builder.AddNamedSystem(
            f"{name}_sampled",
            SampleHold(
                source.size(),
                period,
                sampling_offset(period, lead, name),
                self.first(trajectory),  # what the initialization events read
            ),
        )
        builder.Connect(source, hold.get_input_port())
        return hold.get_output_port()

    def first(self, trajectory: Trajectory) -> np.ndarray:
        """The value the chain reads of `trajectory` first (at its start, `shift`
        ahead)."""
        return trajectory.value(trajectory.start_time() + self.shift).ravel()

    def initial_command(self, reference: JointReference) -> np.ndarray:
        """The servo's command before the first multiple of the period: the pose of
        the reference the chain reads first."""
        return self.first(reference.trajectory)[: reference.trajectory.rows() // 3]


def chain_clock(station: Diagram, parts: TorqueChainParts, fused: bool) -> ChainClock:
    """The `ChainClock` of a chain on `station`: the plant's time step from the
    station's MultibodyPlant."""
    shift = 0.0
    for system in station.GetSystems():
        if isinstance(system, MultibodyPlant):
            shift = system.time_step()
    return ChainClock(parts, sampled=not fused, shift=shift)


def connect_command(
    builder: DiagramBuilder,
    station: Diagram,
    q_cmd: OutputPort,
    parts,
    initial: np.ndarray,
) -> None:
    """The chain's q_cmd to the station's servo, which takes it at each multiple of
    the period and holds it to the next (`SampleHold` "goal_hold"): the one sample
    between a command and the servo of a real robot. (A discrete plant's state port
    shows, when the samplers latch it, the state its next step starts from: a
    command of the tick's own sample, read by the plant as it is, would act in that
    very step, with no delay at all.) On a bus, whose sensors sample `sample_lead`
    before each multiple, the goal computed from them is written at the multiple.
    `initial`: the command before the first multiple (the reference's first pose:
    the servo holds it)."""
    hold = builder.AddNamedSystem(
        "goal_hold",
        SampleHold(q_cmd.size(), parts.period, 0.0, initial),
    )
    builder.Connect(q_cmd, hold.get_input_port())
    builder.Connect(hold.get_output_port(), station.GetInputPort("q_cmd"))


def sample_lead(station: Diagram) -> float:
    """How long (s) before each multiple of its period the station samples its
    sensors (its `SensorSampler`'s lead; 0 for a station without one)."""
    for system in station.GetSystems():
        if isinstance(system, SensorSampler):
            return system.lead()
    return 0.0


def station_ports(station: Diagram, robot: RobotDescription) -> dict[str, OutputPort]:
    """The station's logged ports (ground truth only if it has it: a simulation)."""
    names = ["q_measured", "joint_torque_true", "state_true"]
    if robot.force_sensor:
        names.append(f"wrench_{robot.force_sensor}")
    return {
        name: station.GetOutputPort(name)
        for name in names
        if station.HasOutputPort(name)
    }


class SimulatedStation(NamedTuple):
    """What the builders take, for a simulated robot (`simulated_station`)."""

    #: The robot the station simulates.
    robot: RobotDescription
    #: `make_station`'s Diagram: one per built diagram (a Diagram joins one builder).
    station: Diagram
    #: The control period (s): the station's sensor period.
    control_period: float


def simulated_station(
    config: StationConfig, meshcat: Meshcat | None = None
) -> SimulatedStation:
    """The simulated station of `config` (`make_station(config, meshcat)`), its robot
    and its control period (`config.sensors_config().period`, s): the common case of
    `build_position_control` and `build_torque_control`, e.g.

        robot, station, period = simulated_station(config)
        build_torque_control(robot, station, ..., control_period=period)
    """
    return SimulatedStation(
        config.description(),
        make_station(config, meshcat),
        config.sensors_config().period,
    )


def add_station(
    builder: DiagramBuilder, robot: RobotDescription, station: Diagram
) -> Diagram:
    """Adds `station` (a simulated or a hardware station) to `builder` as "station",
    once its q_cmd input is checked to command every joint of `robot`."""
    if not station.HasInputPort("q_cmd"):
        raise ValueError(f"station '{station.get_name()}': no q_cmd input port")
    size = station.GetInputPort("q_cmd").size()
    if size != len(robot.joints):
        raise ValueError(
            f"station '{station.get_name()}': q_cmd has {size} rows, expected one per "
            f"joint of robot '{robot.name}' ({len(robot.joints)})"
        )
    return builder.AddNamedSystem("station", station)


def build_position_control(
    robot: RobotDescription,
    station: Diagram,
    reference: JointReference,
    command_period: float = 0.0,
) -> ControlDiagram:
    """The baseline: the robot's own position servo tracking the reference (q_cmd =
    q_ref).

    Args:
        robot: the robot of `station`.
        station: a station Diagram with `make_station`'s ports (a simulated one:
            `simulated_station`).
        reference: the joint reference of every joint of `robot`.
        command_period: the period at which the servo gets its goal (s; a bus
            writes it once per period: q_ref held from each multiple of it); 0: the
            reference as it is.
    """
    builder = DiagramBuilder()
    station = add_station(builder, robot, station)
    blocks = add_reference(builder, reference, len(robot.joints))
    q_cmd = blocks["q_ref"]
    if command_period > 0:
        hold = builder.AddNamedSystem(
            "goal_hold", ZeroOrderHold(command_period, len(robot.joints))
        )
        builder.Connect(q_cmd, hold.get_input_port())
        q_cmd = hold.get_output_port()
    builder.Connect(q_cmd, station.GetInputPort("q_cmd"))
    ports = station_ports(station, robot) | {"q_ref": blocks["q_ref"], "q_cmd": q_cmd}
    return build_control_diagram(builder, station, ports, reference)


def _joint_inertia(
    plant, all_joints: list[str], joints: list[str], q: np.ndarray
) -> np.ndarray:
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


def _check_controlled_joints(
    robot: RobotDescription, config: TorqueControlConfig, joints: list[str]
) -> None:
    """Raises ValueError unless `joints` are joints of `robot` and
    `config.controller.kp` gives one gain or one per joint."""
    unknown = [j for j in joints if j not in robot.joints]
    if unknown:
        raise ValueError(
            f"TorqueControlConfig.joints: {unknown} are not joints of robot "
            f"'{robot.name}'"
        )
    for name in ("kp", "ki"):
        gains = getattr(config.controller, name)
        if len(gains) not in (1, len(joints)):
            raise ValueError(
                f"TorqueControlConfig.controller.{name}: {len(gains)} values for "
                f"{len(joints)} joints (give one, or one per joint)"
            )


def _inverse_dynamics_plant(robot: RobotDescription, errors: dict):
    """The inverse dynamics' model, on the fixed-base model (paper footnote 3): a
    floating robot's base welded upright at the origin, a fixed robot as it is
    mounted; with the model `errors` of `robot.make_plant`."""
    if robot.base == "fixed":
        return robot.make_plant(weld_base=True, **errors)
    return make_fixed_base_plant(
        functools.partial(robot.add_model, weld_base=False, **errors), robot.base_body
    )


def _inverse_dynamics_config(
    config: TorqueControlConfig,
    joints: list[str],
    ks: np.ndarray,
    kd: np.ndarray,
    period: float,
) -> InverseDynamicsConfig:
    """The inverse dynamics of `joints` with the gains K_s, K_d (one per joint), updated
    every `period` s."""
    return InverseDynamicsConfig(
        joints=joints,
        period=period,
        ks=ks.tolist(),
        kd=kd.tolist(),
        force_frame=config.controller.force_frame,
        kf=list(config.controller.kf) if config.controller.force_frame else [0.0],
    )


def _torque_controller_config(
    robot: RobotDescription,
    config: TorqueControlConfig,
    joints: list[str],
    period: float,
) -> TorqueControllerConfig:
    """The Δq torque controller of `joints`, updated every `period` s: Δq saturated at
    `delta_q_limit`, the fallback latched at twice it."""
    limit = delta_q_limit(robot, config)
    return TorqueControllerConfig(
        joints=joints,
        period=period,
        kp=list(config.controller.kp),
        ki=list(config.controller.ki),
        integral_limit=[config.controller.integral_limit],
        delta_q_limit=[limit],
        delta_q_fallback_limit=[2 * limit],
        start_time=config.start_time,
        latch_fallback=not config.supervised,
        disturbance_compensation=config.observer.disturbance_observer > 0,
    )


def _observer_parts(
    config: TorqueControlConfig,
    joints: list[str],
    controller_model: MotorModel,
    delay: float,
    period: float,
) -> ObserverParts | None:
    """The disturbance observer's model and config (None without one); `delay`: the
    estimation chain's (s); `period`: the control period (s)."""
    bandwidth = config.observer.disturbance_observer
    if not bandwidth > 0:
        return None
    # The observer inverts the controller's own model: no Coulomb term (the
    # controller sends none), so what friction the model misses is d̂'s.
    return ObserverParts(
        model=MotorModel(
            joints, controller_model.k_tau, controller_model.k_v, np.zeros(len(joints))
        ),
        config=DisturbanceObserverConfig(
            joints=joints, bandwidth=bandwidth, delay=delay, period=period
        ),
    )


def _supervisor_parts(
    robot: RobotDescription, config: TorqueControlConfig
) -> SupervisorParts | None:
    """The safety supervisor's monitored sensors, config (its ranges left 0 the
    robot's: its description's `sensor_ranges`) and number of sensor stamps (one per
    station signal), None if `config` is not supervised."""
    if not config.supervised:
        return None
    monitored = supervisor_sensors(robot.sensor_names(), imu=robot.has_imu())
    supervisor = replace(config.supervisor, start_time=config.start_time)
    return SupervisorParts(
        monitored=monitored,
        config=with_sensor_ranges(
            supervisor, monitored, robot.sensor_ranges, where=robot.source_file
        ),
        num_stamps=len(sensor_sizes(robot)),
    )


def torque_chain_parts(
    robot: RobotDescription,
    reference: JointReference,
    motor_model: MotorModel,
    config: TorqueControlConfig,
    *,
    period: float,
    sample_lead: float = 0.0,
) -> TorqueChainParts:
    """The models and configs of the torque-control chain of `config` on `robot`: what
    both the separate systems and the fused controller are built from.

    `period`: the control period (s), the robot's sensor period (on a bus, the bus's):
    every step of the chain updates once per period, and the Savitzky-Golay filters
    differentiate with it (`config` stated for it: `at_period`). `sample_lead`: the
    station samples this long (s) before each multiple of it (`sample_lead`)."""
    config.validate()
    joints = config.controlled_joints(robot)
    _check_controlled_joints(robot, config, joints)
    all_joints = list(robot.joints)
    # The controllers' model of the robot (with errors, if asked: a fault).
    errors = dict(
        model_error=config.faults.model_error, seed=config.faults.model_error_seed
    )
    estimator = config.estimator
    estimator_config = estimation_config.estimator_config(
        robot,
        estimator.window,
        windows=dict(estimator.windows),
        evaluation=estimator.evaluation,
        offset_calibration_time=estimator.offset_calibration_time,
        offset_calibration_start=0.2,
        offsets=dict(estimator.offsets),
        imu_offset=list(estimator.imu_offset),
        period=period,
    )
    fixed = _inverse_dynamics_plant(robot, errors)
    controller_model = motor_model.subset(joints)
    inertia = _joint_inertia(fixed, all_joints, joints, reference.at(0.0)[0])
    gains = config.controller
    if gains.stiffness:  # K_s chosen in N·m/rad
        ks, kd = inverse_dynamics_gains(
            gains.stiffness, inertia, gains.kp, gains.damping_ratio
        )
    else:
        ks, kd = inverse_dynamics_gains_for_k6(
            controller_model.k_tau, gains.k6, inertia, gains.kp, gains.damping_ratio
        )
    delay = estimation_config.loop_delay(estimator_config)
    predictor = None
    if config.observer.predictor:
        predictor = DelayPredictorConfig(
            joints=joints, delay=delay, inertia=inertia.tolist(), period=period
        )
    return TorqueChainParts(
        all_joints=all_joints,
        joints=joints,
        estimator_plant=robot.make_plant(**errors),
        estimator_config=estimator_config,
        id_plant=fixed,
        id_config=_inverse_dynamics_config(config, joints, ks, kd, period),
        controller_model=controller_model,
        controller_config=_torque_controller_config(robot, config, joints, period),
        observer=_observer_parts(config, joints, controller_model, delay, period),
        predictor=predictor,
        supervisor=_supervisor_parts(robot, config),
        position_source=gains.position_source,
        feedback_velocity=gains.feedback_velocity,
        friction_velocity=gains.friction_velocity,
        force_sensor=robot.sensor_of_body(gains.force_frame)
        if gains.force_frame
        else "",
        period=estimator_config.period,
        sample_lead=sample_lead,
    )


def build_torque_control(
    robot: RobotDescription,
    station: Diagram,
    reference: JointReference,
    motor_model: MotorModel,
    config: TorqueControlConfig,
    *,
    control_period: float,
    force_reference: PiecewisePolynomial | None = None,
    fused: bool = False,
) -> ControlDiagram:
    """Station + estimation chain + inverse dynamics + Δq torque controller (paper Sec.
    4) on `config.joints`, the other joints in position control on the reference.

    Args:
        robot: the robot of `station`.
        station: a station Diagram with `make_station`'s ports (a simulated one:
            `simulated_station`); on hardware the same chain runs as the fused
            controller in `hardware.control_loop.ControlLoop`.
        reference: the joint reference of every joint of `robot`.
        motor_model: the controller's model of the actuators.
        config: the torque control (stated for `control_period`: `at_period`).
        control_period: the robot's sensor period (s; on a bus, the bus's): every
            step of the chain updates once a period.
        force_reference: the wrench reference (6 rows), needed when `config` has a
            force frame (a force task).
        fused: the whole chain as one `FusedTorqueController` (the real-time path;
            the same signals to 1e-12) instead of its separate systems.
    """
    parts = torque_chain_parts(
        robot,
        reference,
        motor_model,
        config,
        period=control_period,
        sample_lead=sample_lead(station),
    )
    builder = DiagramBuilder()
    station = add_station(builder, robot, station)
    clock = chain_clock(station, parts, fused)
    blocks = add_reference(builder, reference, len(parts.all_joints), clock)
    references = chain_references(blocks)
    if parts.force_sensor:  # a force frame: a force task
        if force_reference is None:
            raise ValueError(
                f"build_torque_control: no force_reference for the force task at F/T "
                f"sensor '{parts.force_sensor}' (TorqueControlConfig's force frame)"
            )
        references["f_ref"] = clock.source(builder, "force_reference", force_reference)
    ports = add_torque_chain(
        builder, station, parts, references, fused, logged_wrench=robot.force_sensor
    )
    if not fused:
        initial = clock.initial_command(reference)
        connect_command(builder, station, ports["q_cmd"], parts, initial)
    ports = station_ports(station, robot) | ports | {"q_ref": blocks["q_ref"]}
    return build_control_diagram(builder, station, ports, reference, force_reference)


def add_torque_chain(
    builder: DiagramBuilder,
    station: Diagram,
    parts: TorqueChainParts,
    references: dict[str, OutputPort],
    fused: bool,
    logged_wrench: str = "",
) -> dict[str, OutputPort]:
    """Adds the torque-control chain of `parts` (its table, `torque_chain`) between
    `station` and the references it reads (`references`: q_ref, v_ref, vdot_ref, and
    f_ref or com_ref where the chain has them, by name): as one
    `FusedTorqueController`, or as the table's separate LeafSystems. Returns the
    logged signals' ports by name (`chain_signals`); the command to the servo is the
    caller's to connect for the separate systems (`connect_command`), the fused
    controller's own (its servo_command)."""
    chain = torque_chain(parts)
    names = chain_signals(chain, logged_wrench)
    if fused:
        system = add_fused_controller(builder, station, parts, references)
        return {name: system.GetOutputPort(name) for name in names}
    signals = {
        f"station/{station.get_output_port(k).get_name()}": station.get_output_port(k)
        for k in range(station.num_output_ports())
    }
    signals |= {f"reference/{name}": port for name, port in references.items()}
    added = add_chain(builder, chain, signals)
    return {name: added.logged[name] for name in names}


def add_fused_controller(
    builder, station, parts, sources: dict[str, OutputPort]
) -> FusedTorqueController:
    """Adds the `FusedTorqueController` of `parts` as "fused_controller": its
    `sensors` the station's sensor signals multiplexed in its layout's order
    ("sensors", a Multiplexer), every other input connected to the source of its
    name in `sources` (the reference's blocks, f_ref, com_ref), or else to the
    station's output of its name."""
    fused = builder.AddNamedSystem("fused_controller", FusedTorqueController(parts))
    signals = fused.layout().signals()
    mux = builder.AddNamedSystem(
        "sensors", Multiplexer([rows.stop - rows.start for rows in signals.values()])
    )
    for k, name in enumerate(signals):
        builder.Connect(station.GetOutputPort(name), mux.get_input_port(k))
    sources = sources | {"sensors": mux.get_output_port()}
    for k in range(fused.num_input_ports()):
        port = fused.get_input_port(k)
        name = port.get_name()
        source = sources.get(name)
        builder.Connect(
            source if source is not None else station.GetOutputPort(name), port
        )
    # The servo's command: the one the fused controller holds from each multiple of
    # the period (`connect_command` for the separate systems).
    builder.Connect(fused.GetOutputPort("servo_command"), station.GetInputPort("q_cmd"))
    return fused


def chain_signals(chain: Chain, logged_wrench: str = "") -> list[str]:
    """The chain's logged signals, by name, in order (`Chain.logged`): the output
    ports that `build_torque_control` and `build_balance_control` export from the
    chain, fused or separate. Of the F/T sensors' compensated external wrenches, only
    `logged_wrench`'s ("" for none)."""
    wrench = f"external_wrench_{logged_wrench}"
    return [
        name
        for name in chain.logged()
        if not name.startswith("external_wrench_") or name == wrench
    ]


def chain_references(blocks: dict[str, OutputPort]) -> dict[str, OutputPort]:
    """The reference a chain reads, by name (q_ref, v_ref, vdot_ref, and the three
    in one, joint_reference: what the fused controller reads): the chain's blocks of
    `add_reference` (`ChainClock`)."""
    names = ("q_ref", "v_ref", "vdot_ref")
    return {name: blocks[f"chain_{name}"] for name in names} | {
        "joint_reference": blocks["chain_reference"]
    }
