"""FloatingBaseTorqueEstimator: joint torques of a floating-base robot from encoders,
one IMU and 6-axis F/T sensors (paper Sec. 2), and `add_estimator`, which wires the
whole estimation chain (Savitzky-Golay filters + estimator) to a robot diagram.

The method (paper Sec. 2.2-2.4), on a private floating-base model of the robot:

1. Base motion from the IMU (Sec. 2.3 and its footnote 1). Joint torques depend on
   neither the pose of the base nor its linear velocity, and a uniform gravity field is
   equivalent to an upward acceleration of the whole system. So the internal model has
   no gravity, its base sits at the identity pose with zero linear velocity, and every
   acceleration is a *proper* acceleration (acceleration minus gravity, what an
   accelerometer reads). The base angular velocity comes from the gyro through the
   kinematics of the chain from the base to the IMU (ω_B = R_WI ω_I − J_ω,joints q̇),
   and the base spatial acceleration [α_B; a_Bo] from the 6x6 system
   J_I,base A_B = A_I − J_I,joints q̈ − J̇_I v, where A_I = [α_I; a_I] holds the measured
   angular acceleration (filtered gyro derivative, or zero) and the accelerometer's proper
   acceleration, both rotated into the base frame.
2. F/T compensation (Sec. 2.2). Each sensor reads S, the wrench that the subtree below
   it exerts on the body above it. Newton-Euler on that subtree (with proper
   accelerations, so gravity is included) gives the external wrench on it,
   F_ext = S − offset + Σ_b Ḣ_b, where Ḣ_b is the rate of change of momentum of each
   body b below the sensor, about the sensor origin (see "Offset calibration" for the
   offset). Σ_b Ḣ_b is the base-row part of one inverse dynamics of the model in which
   only the bodies below that sensor have mass (a private context per sensor), shifted
   from the base origin to the sensor origin: exact, also with moving links below the
   sensor (HRP-2's grippers).
3. Joint torques (Sec. 2.3, eq. 2): one inverse dynamics (RNEA) of the internal model with
   the external wrenches applied to the bodies right below the sensors gives
   G = M v̇ + h − J_mᵀ f_m (n + 6 generalized forces).
4. Unknown wrench (Sec. 2.4). The n + 6 equations G = [J_uᵀ Sᵀ] [f_u; τ] are solved for
   the unknown wrench f_u on one link u (the base by default, or a chosen link such as the
   torso) and τ. A = [J_uᵀ Sᵀ] is square; it is checked to have full column rank at
   construction (it always has for a tree: its base rows hold the invertible 6x6
   J_u,baseᵀ), so the least-squares solution is exact:
   f_u = J_u,base⁻ᵀ G_base, τ = G_joints − J_u,jointsᵀ f_u. For u = base, f_u = G_base
   and τ = S G (eq. 2).

Reflected rotor inertia: the model's actuators may carry a rotor inertia I_r and a gear
ratio ρ (Drake adds ρ² I_r to the joint's diagonal of the mass matrix). With
`include_rotor_inertia` (default) τ̂ includes it, which is the torque the actuator
applies on the joint when the plant's mass matrix includes it (as in our simulated
HRP-2); without, ρ² I_r q̈ is removed from each joint's torque.

Only rigid-body dynamics enter the internal model: its force elements (joint damping,
springs) and gravity are not used, τ̂ is the torque the actuators transmit.
"""

import copy
import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from pydrake.math import RigidTransform
from pydrake.multibody.math import SpatialForce
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import (
    BodyIndex,
    JacobianWrtVariable,
    MultibodyForces,
    RigidBody,
    SpatialInertia,
)
from pydrake.systems.framework import (
    Context,
    DiagramBuilder,
    DiscreteValues,
    LeafSystem,
    System,
)
from pydrake.systems.primitives import Demultiplexer, Multiplexer

from hrp2_drake.estimation.savitzky_golay import EVALUATION_POINTS, SavitzkyGolayFilter
from hrp2_drake.multibody import check_vector, get_frame, joint_indexing

ANGULAR_ACCELERATION_MODES = ("gyro_derivative", "neglected")
_WHERE = "FloatingBaseTorqueEstimator"


@dataclass
class ForceTorqueSensorConfig:
    """One 6-axis F/T sensor.

    Args:
        frame: name of the sensor frame (any frame or body of the plant). Readings and
            external wrenches are [torque; force] (N·m, N), about its origin, expressed
            in it.
        body: name of the body right below the sensor, on the side away from the base
            (for HRP-2 the foot or hand). The sensor carries this body and all the
            bodies beyond it (e.g. a gripper link), whose weight and inertia it
            compensates; the external wrench is assumed to act on this body. Empty: the
            body of `frame`. `frame` must be rigidly attached to it.
    """

    frame: str = ""
    body: str = ""


@dataclass
class TorqueEstimatorConfig:
    """Configuration of FloatingBaseTorqueEstimator and of add_estimator's filters.

    Args:
        joints: names of the n one-dof joints, in the order of every joint vector (q,
            v, vdot, tau); together with the floating base they must cover every degree
            of freedom of the model.
        imu_frame: name of the IMU frame (gyro and accelerometer axes and origin).
        sensors: F/T sensors by name (the name makes the ports wrench_<name> and
            external_wrench_<name>).
        base_body: name of the floating base body; empty for the model's unique
            floating base.
        angular_acceleration: "gyro_derivative" (the IMU body's angular acceleration
            is the imu_angular_acceleration input, the filtered derivative of the gyro)
            or "neglected" (it is taken as zero and that input is not read; paper
            Sec. 2.3).
        include_rotor_inertia: include the actuators' reflected rotor inertia ρ² I_r
            in τ̂.
        unknown_wrench_body: the link u that carries the unknown wrench (Sec. 2.4);
            empty for the floating base (then τ̂ is eq. 2).
        offset_calibration_time: length (s) of the start-up F/T offset calibration, 0
            for none (see the estimator's docstring).
        offset_calibration_start: time (s) the calibration starts, to skip the
            filters' start-up (their windows fill with the sensors' first samples;
            the default leaves 2.5 windows of 80 ms).
        period: the update period (s) of the estimator and of the filters.
        window: number of samples N of every Savitzky-Golay filter of add_estimator
            (one window for all, so all estimates refer to the same time).
        evaluation: Savitzky-Golay evaluation point, "centre" (delay (N - 1) / 2
            samples, the paper's choice) or "end".
    """

    joints: list[str] = field(default_factory=list)
    imu_frame: str = ""
    sensors: dict[str, ForceTorqueSensorConfig] = field(default_factory=dict)
    base_body: str = ""
    angular_acceleration: str = "gyro_derivative"
    include_rotor_inertia: bool = True
    unknown_wrench_body: str = ""
    offset_calibration_time: float = 0.0
    offset_calibration_start: float = 0.2
    period: float = 0.001
    window: int = 80
    evaluation: str = "centre"

    def validate(self) -> None:
        """Raises ValueError naming the bad field (yaml_load_typed does not call it)."""
        where = "TorqueEstimatorConfig"
        if not self.joints:
            raise ValueError(f"{where}.joints is empty")
        duplicates = sorted({j for j in self.joints if self.joints.count(j) > 1})
        if duplicates:
            raise ValueError(f"{where}.joints: duplicated joints {duplicates}")
        if not self.imu_frame:
            raise ValueError(f"{where}.imu_frame is empty")
        for name, sensor in self.sensors.items():
            if not (name and name.replace("_", "a").isalnum() and name.isascii()):
                raise ValueError(
                    f"{where}.sensors: sensor name '{name}' must be a non-empty "
                    "snake_case identifier (it names ports)"
                )
            if not isinstance(sensor, ForceTorqueSensorConfig):
                raise ValueError(
                    f"{where}.sensors['{name}'] must be a ForceTorqueSensorConfig, "
                    f"got {type(sensor).__name__}"
                )
            if not sensor.frame:
                raise ValueError(f"{where}.sensors['{name}'].frame is empty")
        if self.angular_acceleration not in ANGULAR_ACCELERATION_MODES:
            raise ValueError(
                f"{where}.angular_acceleration='{self.angular_acceleration}' must be "
                f"one of {ANGULAR_ACCELERATION_MODES}"
            )
        for name in ("offset_calibration_time", "offset_calibration_start"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(
                    f"{where}.{name}={value} must be a finite number >= 0 (s)"
                )
        if not (math.isfinite(self.period) and self.period > 0):
            raise ValueError(f"{where}.period={self.period} must be > 0 (s)")
        if (
            isinstance(self.window, bool)
            or not isinstance(self.window, int)
            or (self.window < 3)
        ):
            raise ValueError(
                f"{where}.window={self.window!r} must be an integer >= 3 (the encoder "
                "filter fits a parabola)"
            )
        if self.evaluation not in EVALUATION_POINTS:
            raise ValueError(
                f"{where}.evaluation='{self.evaluation}' must be one of "
                f"{EVALUATION_POINTS}"
            )


class TorqueEstimate(NamedTuple):
    """What the estimator computes for one sample (see `estimate`).

    Attributes:
        tau: joint torques (N·m, n, config.joints order).
        unknown_wrench: [torque; force] on the unknown-wrench link, about its origin,
            expressed in its frame (N·m, N).
        external_wrenches: (k, 6) compensated external wrench of each sensor, in
            config.sensors order: [torque; force] exerted by the environment on the
            bodies below the sensor, about the sensor origin, in the sensor frame.
    """

    tau: np.ndarray
    unknown_wrench: np.ndarray
    external_wrenches: np.ndarray


@dataclass
class _Sensor:
    name: str
    frame: object  # the sensor Frame S
    body: RigidBody  # the body right below the sensor, B
    R_BS: np.ndarray
    p_BoSo_B: np.ndarray
    bodies: list[int]  # BodyIndex of every body below the sensor (B's subtree)
    context: Context  # the plant with mass only below the sensor (compensation)
    port: object = None


class FloatingBaseTorqueEstimator(LeafSystem):
    """Joint torques, external wrenches and the unknown wrench of a floating-base robot
    from encoders, one IMU and k 6-axis F/T sensors (paper Sec. 2; method in the module
    docstring).

    .. code-block:: text

                                   ┌─────────────────────────────┐
        q ────────────────────────►│                             ├──► tau
        v ────────────────────────►│                             ├──► unknown_wrench
        vdot ─────────────────────►│ FloatingBaseTorqueEstimator ├──► external_wrench_<s>
        imu_linear_acceleration ──►│                             │    (one per sensor s)
        imu_angular_velocity ─────►│                             │
        imu_angular_acceleration ─►│                             │
        wrench_<s> ───────────────►│ (one per sensor s)          │
                                   └─────────────────────────────┘

    Inputs:
        q, v, vdot (n each): joint positions (rad), velocities (rad/s), accelerations
            (rad/s²), config.joints order (e.g. Savitzky-Golay estimates from encoders).
        imu_linear_acceleration (3): proper acceleration (acceleration minus gravity,
            m/s²) of the IMU frame origin, in the IMU frame: at rest it reads +g upward.
        imu_angular_velocity (3): angular velocity of the IMU body (rad/s), IMU frame.
        imu_angular_acceleration (3): its angular acceleration (rad/s², IMU frame, the
            time derivative of imu_angular_velocity). Not read when
            config.angular_acceleration is "neglected" (it may stay unconnected).
        wrench_<sensor> (6): the sensor reading [torque; force] (N·m, N): the wrench
            the bodies below the sensor exert on the body above it, about the sensor
            origin, in the sensor frame.

    Outputs (discrete state, updated every config.period; zero before the first update):
        tau (n): estimated joint torques τ̂ (N·m), config.joints order.
        unknown_wrench (6): the unknown wrench f_u [torque; force] (N·m, N) on the
            unknown-wrench link u (config.unknown_wrench_body, default the base), about
            u's origin, expressed in u's frame; gravity excluded (it is the wrench of
            the environment, e.g. a push or a string). Close to zero when every
            contact is measured (monitoring, paper Sec. 2.4).
        external_wrench_<sensor> (6): the compensated external wrench [torque; force]
            the environment exerts on the bodies below that sensor, about the sensor
            origin, in the sensor frame (standing still, a foot's is +z ground
            reaction).

    Offset calibration (config.offset_calibration_time = T > 0, starting at
    t0 = config.offset_calibration_start): F/T sensors drift, so their offsets are
    measured at start-up. Procedure: start the robot (or the simulation) with nothing
    touching the bodies below the sensors (robot hanging, or held with its feet and
    hands free; it may move, slow motions are compensated); wait t0 for the filters'
    windows to fill (default 0.2 s, 2.5 windows of 80 ms), then keep contact-free for
    T more seconds (e.g. 0.5 s). At every update with t0 <= t < t0 + T the estimator
    averages the compensated wrench S + ΣḢ of each sensor, which is the offset when
    nothing touches, and uses the running average as the offset (so the external
    wrenches read ≈ 0 while calibrating); afterwards the average is frozen and
    subtracted from every reading. Before t0 the offsets are zero. The offsets and the
    number of samples averaged are discrete state (`offsets(context)`,
    `num_calibration_samples(context)`); with T = 0 the offsets stay zero.

    Errors: a NaN or infinite input raises ValueError naming the port; an unknown
    frame, body or joint name raises KeyError naming it; a model whose degrees of
    freedom are not the floating base plus config.joints raises ValueError.

    Allocated once at construction: one private context of `plant` for the robot, one
    per F/T sensor in which only the bodies below that sensor have mass (its inverse
    dynamics gives the compensation ΣḢ), and the MultibodyForces; nothing per update
    but small numpy temporaries. `plant`'s default parameters (masses, inertias, rotor
    inertias, gear ratios) are read at construction. `plant` must be a finalized
    model of the robot alone: floating base, no welds to the world; its gravity and
    force elements are ignored.
    """

    def __init__(self, plant: MultibodyPlant, config: TorqueEstimatorConfig):
        """
        Args:
            plant: a finalized MultibodyPlant holding only the robot, with a floating
                base (for HRP-2: MultibodyPlant(0.0), add_hrp2, Finalize). It must
                outlive the estimator; it is never modified.
            config: joint, frame and sensor names and options (validated here).
        """
        super().__init__()
        config.validate()
        if not plant.is_finalized():
            raise ValueError(f"{_WHERE}: the plant must be finalized")
        self._plant = plant
        self._config = copy.deepcopy(config)
        self._context = plant.CreateDefaultContext()
        self._forces = MultibodyForces(plant)
        self._world = plant.world_frame()
        self._zero3 = np.zeros(3)

        self._base = self._find_base(plant, config)
        self._indexing = joint_indexing(plant, config.joints)
        n = self._n = self._indexing.size
        # Index arrays, or slices when contiguous (cheaper per tick).
        self._jq = _as_slice(self._indexing.q)
        self._jv = _as_slice(self._indexing.v)
        self._check_dofs(plant)
        start = self._base.floating_velocities_start_in_v()
        self._base_v = slice(start, start + 6)  # [ω_WB; v_WBo]
        self._base_w = slice(start, start + 3)
        self._base_a = slice(start + 3, start + 6)

        # The base at the identity pose, with zero linear velocity, for ever.
        plant.SetFreeBodyPose(self._context, self._base, RigidTransform())
        plant.SetVelocities(self._context, np.zeros(plant.num_velocities()))
        self._q_full = plant.GetPositions(self._context).copy()
        self._v_full = np.zeros(plant.num_velocities())
        self._nq = plant.num_positions()
        self._x_full = np.concatenate([self._q_full, self._v_full])
        self._no_forces = MultibodyForces(plant)  # stays zero
        self._vdot_full = np.zeros(plant.num_velocities())
        self._check_base_jacobian(plant)

        self._imu = get_frame(plant, config.imu_frame, "IMU frame")
        if self._imu.body().index() == plant.world_body().index():
            raise ValueError(
                f"{_WHERE}: IMU frame '{config.imu_frame}' is on the world"
            )
        self._parent = self._tree_parents(plant)
        self._sensors = [
            self._make_sensor(plant, name, sensor)
            for name, sensor in config.sensors.items()
        ]
        self._check_disjoint_subtrees()
        self._reflected_inertia = self._reflected_inertias(plant)
        self._unknown_frame = self._find_unknown_wrench_frame(plant, config)
        self._check_rank(plant)

        # Ports.
        self._q_port = self.DeclareVectorInputPort("q", n)
        self._v_port = self.DeclareVectorInputPort("v", n)
        self._vdot_port = self.DeclareVectorInputPort("vdot", n)
        self._acc_port = self.DeclareVectorInputPort("imu_linear_acceleration", 3)
        self._gyro_port = self.DeclareVectorInputPort("imu_angular_velocity", 3)
        self._alpha_port = self.DeclareVectorInputPort("imu_angular_acceleration", 3)
        for sensor in self._sensors:
            sensor.port = self.DeclareVectorInputPort(f"wrench_{sensor.name}", 6)

        k = len(self._sensors)
        self._tau_state = self.DeclareDiscreteState(n)
        self._unknown_state = self.DeclareDiscreteState(6)
        self._external_states = [self.DeclareDiscreteState(6) for _ in range(k)]
        # F/T offsets (6 per sensor) then the number of calibration samples.
        self._calibration_state = self.DeclareDiscreteState(6 * k + 1)
        self.DeclareStateOutputPort("tau", self._tau_state)
        self.DeclareStateOutputPort("unknown_wrench", self._unknown_state)
        for sensor, state in zip(self._sensors, self._external_states):
            self.DeclareStateOutputPort(f"external_wrench_{sensor.name}", state)
        self.DeclarePeriodicDiscreteUpdateEvent(config.period, 0.0, self._update)

        # Work arrays of the update.
        self._raw = np.zeros((k, 6))
        self._compensated = np.zeros((k, 6))
        self._external = np.zeros((k, 6))
        self._A_I = np.zeros(6)
        self._neglect_alpha = config.angular_acceleration == "neglected"
        # Calibrate at the updates with start <= t < start + time (half-period margins).
        self._calibration_begin = config.offset_calibration_start - 0.5 * config.period
        self._calibration_end = (
            config.offset_calibration_start
            + config.offset_calibration_time
            - 0.5 * config.period
        )
        self._period = config.period

    # ----------------------------------------------------------------- construction

    @staticmethod
    def _find_base(plant: MultibodyPlant, config: TorqueEstimatorConfig) -> RigidBody:
        if config.base_body:
            if not plant.HasBodyNamed(config.base_body):
                raise KeyError(
                    f"{_WHERE}: base body '{config.base_body}' is not a body"
                )
            base = plant.GetBodyByName(config.base_body)
            if not base.is_floating_base_body():
                raise ValueError(
                    f"{_WHERE}: base body '{config.base_body}' is not a floating base"
                )
            return base
        bases = sorted(int(b) for b in plant.GetFloatingBaseBodies())
        if len(bases) != 1:
            found = [plant.get_body(BodyIndex(b)).name() for b in bases]
            raise ValueError(
                f"{_WHERE}: the plant must have exactly one floating base body, it has "
                f"{found}: give a model of the robot alone, welded to nothing"
            )
        return plant.get_body(BodyIndex(bases[0]))

    def _check_dofs(self, plant: MultibodyPlant) -> None:
        if plant.num_velocities() != 6 + self._n:
            start = self._base.floating_velocities_start_in_v()
            covered = set(self._indexing.v.tolist()) | set(range(start, start + 6))
            missing = [
                plant.get_joint(j).name()
                for j in plant.GetJointIndices()
                if plant.get_joint(j).num_velocities() > 0
                and plant.get_joint(j).velocity_start() not in covered
            ]
            raise ValueError(
                f"{_WHERE}: the plant has {plant.num_velocities()} velocities, but the "
                f"floating base and the {self._n} joints of the config cover "
                f"{6 + self._n}; joints not in the config: {missing}"
            )

    def _check_base_jacobian(self, plant: MultibodyPlant) -> None:
        J = plant.CalcJacobianSpatialVelocity(
            self._context,
            JacobianWrtVariable.kV,
            self._base.body_frame(),
            self._zero3,
            self._world,
            self._world,
        )
        if not np.allclose(J[:, self._base_v], np.eye(6), atol=1e-12):
            raise ValueError(
                f"{_WHERE}: the floating joint of '{self._base.name()}' does not have "
                "velocities [ω_WB; v_WBo] (e.g. a quaternion or rpy floating joint)"
            )

    def _tree_parents(self, plant: MultibodyPlant) -> dict[int, int]:
        """Parent body index of every body of the tree rooted at the base."""
        world = int(plant.world_body().index())
        neighbours: dict[int, list[int]] = {}
        for j in plant.GetJointIndices():
            joint = plant.get_joint(j)
            a, b = int(joint.parent_body().index()), int(joint.child_body().index())
            if world in (a, b):
                continue
            neighbours.setdefault(a, []).append(b)
            neighbours.setdefault(b, []).append(a)
        base = int(self._base.index())
        parent = {base: -1}
        stack = [base]
        while stack:
            a = stack.pop()
            for b in neighbours.get(a, []):
                if b not in parent:
                    parent[b] = a
                    stack.append(b)
        return parent

    def _subtree(self, body: int) -> list[int]:
        children: dict[int, list[int]] = {}
        for child, parent in self._parent.items():
            children.setdefault(parent, []).append(child)
        out, stack = [], [body]
        while stack:
            b = stack.pop()
            out.append(b)
            stack.extend(children.get(b, []))
        return sorted(out)

    def _make_sensor(
        self, plant: MultibodyPlant, name: str, cfg: ForceTorqueSensorConfig
    ):
        frame = get_frame(plant, cfg.frame, f"F/T sensor '{name}' frame")
        if cfg.body:
            if not plant.HasBodyNamed(cfg.body):
                raise KeyError(
                    f"{_WHERE}: F/T sensor '{name}' body '{cfg.body}' is not a body of "
                    "the plant"
                )
            body = plant.GetBodyByName(cfg.body)
        else:
            body = frame.body()
        index = int(body.index())
        if index not in self._parent:
            raise ValueError(
                f"{_WHERE}: F/T sensor '{name}': body '{body.name()}' is not part of the "
                "robot's tree"
            )
        if index == int(self._base.index()):
            raise ValueError(
                f"{_WHERE}: F/T sensor '{name}': body '{body.name()}' is the base; give "
                "the body right below the sensor"
            )
        welded = {int(b.index()) for b in plant.GetBodiesWeldedTo(body)} | {index}
        if int(frame.body().index()) not in welded:
            raise ValueError(
                f"{_WHERE}: F/T sensor '{name}': frame '{cfg.frame}' is not rigidly "
                f"attached to body '{body.name()}'"
            )
        X_BS = frame.CalcPose(self._context, body.body_frame())
        below = self._subtree(index)
        # The plant with every body above the sensor massless: its inverse dynamics
        # gives the momentum rate of the bodies below (see _compensate).
        context = plant.CreateDefaultContext()
        plant.SetFreeBodyPose(context, self._base, RigidTransform())
        for i in range(plant.num_bodies()):
            if i not in below and i != int(plant.world_body().index()):
                plant.get_body(BodyIndex(i)).SetSpatialInertiaInBodyFrame(
                    context, SpatialInertia.Zero()
                )
        return _Sensor(
            name,
            frame,
            body,
            X_BS.rotation().matrix(),
            X_BS.translation(),
            below,
            context,
        )

    def _check_disjoint_subtrees(self) -> None:
        owner: dict[int, str] = {}
        for sensor in self._sensors:
            for b in sensor.bodies:
                if b in owner:
                    raise ValueError(
                        f"{_WHERE}: F/T sensors '{owner[b]}' and '{sensor.name}' carry "
                        "the same bodies (nested sensors are not supported)"
                    )
                owner[b] = sensor.name

    def _reflected_inertias(self, plant: MultibodyPlant) -> np.ndarray:
        by_joint = {}
        for index in plant.GetJointActuatorIndices():
            actuator = plant.get_joint_actuator(index)
            by_joint[int(actuator.joint().index())] = (
                actuator.rotor_inertia(self._context)
                * actuator.gear_ratio(self._context) ** 2
            )
        return np.array(
            [
                by_joint.get(int(plant.GetJointByName(j).index()), 0.0)
                for j in self._config.joints
            ]
        )

    def _find_unknown_wrench_frame(self, plant: MultibodyPlant, config):
        name = config.unknown_wrench_body
        if not name or name == self._base.name():
            return None
        if not plant.HasBodyNamed(name):
            raise KeyError(
                f"{_WHERE}: unknown-wrench body '{name}' is not a body of the plant"
            )
        body = plant.GetBodyByName(name)
        if int(body.index()) not in self._parent:
            raise ValueError(
                f"{_WHERE}: unknown-wrench body '{name}' is not in the robot"
            )
        return body.body_frame()

    def _check_rank(self, plant: MultibodyPlant) -> None:
        """A = [J_uᵀ Sᵀ] must have full column rank (Sec. 2.4)."""
        nv = plant.num_velocities()
        frame = self._unknown_frame or self._base.body_frame()
        J_u = plant.CalcJacobianSpatialVelocity(
            self._context,
            JacobianWrtVariable.kV,
            frame,
            self._zero3,
            self._world,
            frame,
        )
        S = np.zeros((self._n, nv))
        S[np.arange(self._n), self._indexing.v] = 1.0
        A = np.hstack([J_u.T, S.T])
        rank = np.linalg.matrix_rank(A)
        if rank < A.shape[1]:
            raise ValueError(
                f"{_WHERE}: A = [J_uᵀ Sᵀ] has rank {rank} < {A.shape[1]}: the unknown "
                f"wrench on '{frame.body().name()}' and the torques are not identifiable"
            )

    # ----------------------------------------------------------------- accessors

    def plant(self) -> MultibodyPlant:
        return self._plant

    def config(self) -> TorqueEstimatorConfig:
        return self._config

    def sensor_names(self) -> list[str]:
        return [s.name for s in self._sensors]

    def reflected_inertia(self) -> np.ndarray:
        """ρ² I_r of each joint (kg·m²), config.joints order (0 without actuator)."""
        return self._reflected_inertia.copy()

    def offsets(self, context: Context) -> np.ndarray:
        """(k, 6) F/T offsets in use (sensor frame, N·m and N), config.sensors order."""
        value = context.get_discrete_state(self._calibration_state).get_value()
        return value[:-1].reshape(-1, 6).copy()

    def num_calibration_samples(self, context: Context) -> int:
        return int(context.get_discrete_state(self._calibration_state).get_value()[-1])

    # ----------------------------------------------------------------- computation

    def estimate(
        self,
        q: np.ndarray,
        v: np.ndarray,
        vdot: np.ndarray,
        imu_linear_acceleration: np.ndarray,
        imu_angular_velocity: np.ndarray,
        imu_angular_acceleration: np.ndarray,
        wrenches: np.ndarray,
        offsets: np.ndarray | None = None,
    ) -> TorqueEstimate:
        """The estimate of one sample, without a Context (e.g. on logged data with
        non-causal filters, paper Sec. 3.4.3). Same units and frames as the ports;
        `wrenches` and `offsets` are (k, 6) in config.sensors order (offsets default
        to zero). imu_angular_acceleration is ignored in "neglected" mode.

        Raises:
            ValueError: a wrong size or a non-finite value, naming the argument.
        """
        n, k = self._n, len(self._sensors)
        q = check_vector("q", q, n, _WHERE)
        v = check_vector("v", v, n, _WHERE)
        vdot = check_vector("vdot", vdot, n, _WHERE)
        acc = check_vector(
            "imu_linear_acceleration", imu_linear_acceleration, 3, _WHERE
        )
        gyro = check_vector("imu_angular_velocity", imu_angular_velocity, 3, _WHERE)
        alpha = (
            self._zero3
            if self._neglect_alpha
            else check_vector(
                "imu_angular_acceleration", imu_angular_acceleration, 3, _WHERE
            )
        )
        raw = check_vector("wrenches", np.ravel(wrenches), 6 * k, _WHERE).reshape(k, 6)
        off = (
            np.zeros((k, 6))
            if offsets is None
            else check_vector("offsets", np.ravel(offsets), 6 * k, _WHERE).reshape(k, 6)
        )
        self._set_kinematics(q, v, vdot, acc, gyro, alpha)
        compensated = np.zeros((k, 6))
        self._compensate(raw, compensated)
        external = compensated - off
        tau, unknown = self._dynamics(external, vdot)
        return TorqueEstimate(tau.copy(), unknown.copy(), external)

    def _set_kinematics(self, q, v, vdot, acc, gyro, alpha) -> None:
        """Sets the private context and self._vdot_full from the measurements (step 1)."""
        plant, context, imu, W = self._plant, self._context, self._imu, self._world
        self._q_full[self._jq] = q
        plant.SetPositions(context, self._q_full)
        J_I = plant.CalcJacobianSpatialVelocity(
            context, JacobianWrtVariable.kV, imu, self._zero3, W, W
        )
        R_WI = imu.CalcRotationMatrixInWorld(context).matrix()
        J_Ij = J_I[:, self._jv]
        # ω_WI = ω_WB + J_ω,joints q̇ (the base at the identity pose: W = B).
        self._v_full[self._base_w] = R_WI @ gyro - J_Ij[:3] @ v
        self._v_full[self._jv] = v
        plant.SetVelocities(context, self._v_full)
        self._x_full[: self._nq] = self._q_full
        self._x_full[self._nq :] = self._v_full
        bias = plant.CalcBiasSpatialAcceleration(
            context, JacobianWrtVariable.kV, imu, self._zero3, W, W
        ).get_coeffs()
        A_I = self._A_I
        A_I[:3] = R_WI @ alpha
        A_I[3:] = R_WI @ acc
        rhs = A_I - J_Ij @ vdot - bias
        # J_I,base = [I 0; −[p_BoIo]× I] (checked at construction for the base frame):
        # solve the 6x6 system J_I,base A_B = rhs by blocks.
        alpha_B = rhs[:3]
        self._vdot_full[self._base_w] = alpha_B
        self._vdot_full[self._base_a] = rhs[3:] - J_I[3:, self._base_w] @ alpha_B
        self._vdot_full[self._jv] = vdot

    def _compensate(self, raw: np.ndarray, out: np.ndarray) -> None:
        """out[s] = S_s + Σ_b Ḣ_b (about So, in S): step 2 without the offsets.

        Σ_b Ḣ_b comes from Drake's inverse dynamics on the sensor's own context, where
        only the bodies below the sensor have mass: the base rows of M v̇ + h are then
        the momentum rate of those bodies, about the base origin, in the base frame.
        """
        plant, x = self._plant, self._x_full
        for s, sensor in enumerate(self._sensors):
            plant.SetPositionsAndVelocities(sensor.context, x)
            G = plant.CalcInverseDynamics(
                sensor.context, self._vdot_full, self._no_forces
            )
            torque_Bo, force = G[self._base_w], G[self._base_a]
            X_WS = sensor.frame.CalcPoseInWorld(self._context)
            p = X_WS.translation()
            # Shift from the base origin Bo (= Wo) to So: τ_So = τ_Bo + p_SoBo × f.
            torque_So = torque_Bo - np.array(
                (
                    p[1] * force[2] - p[2] * force[1],
                    p[2] * force[0] - p[0] * force[2],
                    p[0] * force[1] - p[1] * force[0],
                )
            )
            R_SW = X_WS.rotation().matrix().T
            out[s, :3] = raw[s, :3] + R_SW @ torque_So
            out[s, 3:] = raw[s, 3:] + R_SW @ force

    def _dynamics(self, external: np.ndarray, vdot: np.ndarray):
        """Steps 3 and 4: (tau, unknown wrench) from the external wrenches."""
        plant, context, forces = self._plant, self._context, self._forces
        forces.SetZero()
        for s, sensor in enumerate(self._sensors):
            R_BS = sensor.R_BS
            F_B = SpatialForce(R_BS @ external[s, :3], R_BS @ external[s, 3:])
            sensor.body.AddInForce(
                context, sensor.p_BoSo_B, F_B, sensor.body.body_frame(), forces
            )
        # G = M v̇ + h − J_mᵀ f_m, without gravity (proper accelerations carry it).
        G = plant.CalcInverseDynamics(context, self._vdot_full, forces)
        tau = G[self._jv]
        if self._unknown_frame is None:
            unknown = G[self._base_v]  # J_u = [I 0] for the base at the identity pose
        else:
            frame = self._unknown_frame
            J_u = plant.CalcJacobianSpatialVelocity(
                context, JacobianWrtVariable.kV, frame, self._zero3, self._world, frame
            )
            # [J_uᵀ Sᵀ] [f_u; τ] = G (Sec. 2.4): base rows first.
            unknown = np.linalg.solve(J_u[:, self._base_v].T, G[self._base_v])
            tau -= J_u[:, self._jv].T @ unknown
        if not self._config.include_rotor_inertia:
            tau -= self._reflected_inertia * vdot
        return tau, unknown

    def _read(self, port, context: Context) -> np.ndarray:
        value = port.Eval(context)
        if not math.isfinite(value.sum()):
            bad = np.flatnonzero(~np.isfinite(value))
            raise ValueError(
                f"{_WHERE} {self.GetSystemPathname()}: input port '{port.get_name()}' is "
                f"not finite at t = {context.get_time():.6g} s, at indices {bad.tolist()}"
            )
        return value

    def _update(self, context: Context, discrete_state: DiscreteValues) -> None:
        q = self._read(self._q_port, context)
        v = self._read(self._v_port, context)
        vdot = self._read(self._vdot_port, context)
        acc = self._read(self._acc_port, context)
        gyro = self._read(self._gyro_port, context)
        alpha = (
            self._zero3
            if self._neglect_alpha
            else self._read(self._alpha_port, context)
        )
        raw = self._raw
        for s, sensor in enumerate(self._sensors):
            raw[s] = self._read(sensor.port, context)

        self._set_kinematics(q, v, vdot, acc, gyro, alpha)
        self._compensate(raw, self._compensated)

        calibration = discrete_state.get_mutable_vector(
            self._calibration_state
        ).get_mutable_value()
        offsets = calibration[:-1].reshape(-1, 6)  # a view on the state
        if self._calibration_begin <= context.get_time() < self._calibration_end:
            count = calibration[-1] + 1.0
            offsets += (self._compensated - offsets) / count  # running mean
            calibration[-1] = count
        np.subtract(self._compensated, offsets, out=self._external)

        tau, unknown = self._dynamics(self._external, vdot)
        discrete_state.get_mutable_vector(self._tau_state).set_value(tau)
        discrete_state.get_mutable_vector(self._unknown_state).set_value(unknown)
        for s, state in enumerate(self._external_states):
            discrete_state.get_mutable_vector(state).set_value(self._external[s])


def _as_slice(indices: np.ndarray):
    """`indices` as a slice if they are consecutive, else unchanged."""
    if len(indices) and np.array_equal(
        indices, np.arange(indices[0], indices[0] + len(indices))
    ):
        return slice(int(indices[0]), int(indices[0]) + len(indices))
    return indices


# --------------------------------------------------------------------- the chain


@dataclass
class EstimationChain:
    """The systems add_estimator adds.

    Attributes:
        estimator: the FloatingBaseTorqueEstimator.
        encoder_filter: Savitzky-Golay filter of the encoders (order 2): q, v, vdot.
        sensor_filter: one Savitzky-Golay filter (order 1) of [accelerometer (3); gyro
            (3); F/T sensors (6 each, config.sensors order)]: values, and the gyro's
            derivative as the angular acceleration.
    """

    estimator: FloatingBaseTorqueEstimator
    encoder_filter: SavitzkyGolayFilter
    sensor_filter: SavitzkyGolayFilter

    def delay(self) -> float:
        """Seconds between the robot state an output of the estimator describes and the
        time it is output: the filters' delay plus two periods (a sensor sample taken
        at t enters the filters at t + period, the estimator reads the filters' update
        at t + 2 periods). For the paper's N = 80 at 1 kHz: 41.5 ms."""
        return self.encoder_filter.delay() + 2 * self.encoder_filter.period()


def add_estimator(
    builder: DiagramBuilder,
    station: System,
    plant: MultibodyPlant,
    config: TorqueEstimatorConfig,
    *,
    encoders: str = "q_measured",
    accelerometer: str = "imu_linear_acceleration",
    gyroscope: str = "imu_angular_velocity",
    wrench_prefix: str = "wrench_",
    name: str = "torque_estimator",
) -> EstimationChain:
    """Adds the whole estimation chain of paper Sec. 2 to `builder` and connects it to
    the output ports of `station` (a robot diagram, simulated or real, already added to
    `builder`), with the paper's filters (Sec. 5.1): Savitzky-Golay of order 2 on the
    encoders (q, v, vdot), of order 1 on the IMU and the F/T sensors (values; the gyro's
    derivative is the angular acceleration), one window for all (config.window, same
    delay everywhere).

    .. code-block:: text

        q_measured ──────────► SG order 2 ─► value, derivative, second_derivative
                                             = q, v, vdot ──────────────────┐
        imu_linear_acceleration ─┐                                          ▼
        imu_angular_velocity ────┼─► Mux ─► SG order 1 ─► value ─► Demux ─► estimator
        wrench_<s> (each) ───────┘                    └─► derivative ─► Demux ─┘
                                     (the gyro's derivative: imu_angular_acceleration)

    Args:
        builder: the builder that holds `station`.
        station: the system whose outputs are the robot's sensors.
        plant: the estimator's floating-base model of the robot (see
            FloatingBaseTorqueEstimator; not the station's plant, which may be welded or
            carry contact and strings).
        config: names and options; config.joints must be the order of the encoder port.
        encoders, accelerometer, gyroscope: names of the station's output ports.
        wrench_prefix: the F/T port of sensor s is wrench_prefix + s.
        name: name of the estimator; the other systems' names start with it (give
            another to add a second chain to the same builder).

    Returns:
        The added systems (their outputs are the estimator's ports).

    Raises:
        KeyError: a port the station lacks (named), an unknown frame/joint.
    """
    config.validate()
    names = list(config.sensors)
    ports = [encoders, accelerometer, gyroscope] + [wrench_prefix + n for n in names]
    missing = [p for p in ports if not station.HasOutputPort(p)]
    if missing:
        raise KeyError(
            f"add_estimator: station '{station.get_name()}' has no output ports {missing}"
        )
    n = len(config.joints)
    if station.GetOutputPort(encoders).size() != n:
        raise ValueError(
            f"add_estimator: port '{encoders}' has "
            f"{station.GetOutputPort(encoders).size()} entries, config.joints has {n}"
        )
    estimator = builder.AddNamedSystem(name, FloatingBaseTorqueEstimator(plant, config))
    encoder_filter = builder.AddNamedSystem(
        f"{name}_encoder_filter",
        SavitzkyGolayFilter(n, config.window, 2, config.period, config.evaluation),
    )
    builder.Connect(station.GetOutputPort(encoders), encoder_filter.get_input_port())
    for source, target in (
        ("value", "q"),
        ("derivative", "v"),
        ("second_derivative", "vdot"),
    ):
        builder.Connect(
            encoder_filter.GetOutputPort(source), estimator.GetInputPort(target)
        )

    sizes = [3, 3] + [6] * len(names)
    mux = builder.AddNamedSystem(f"{name}_sensor_mux", Multiplexer(sizes))
    for k, port in enumerate(ports[1:]):
        builder.Connect(station.GetOutputPort(port), mux.get_input_port(k))
    sensor_filter = builder.AddNamedSystem(
        f"{name}_sensor_filter",
        SavitzkyGolayFilter(
            sum(sizes), config.window, 1, config.period, config.evaluation
        ),
    )
    builder.Connect(mux.get_output_port(), sensor_filter.get_input_port())
    values = builder.AddNamedSystem(f"{name}_sensor_values", Demultiplexer(sizes))
    builder.Connect(sensor_filter.GetOutputPort("value"), values.get_input_port())
    targets = ["imu_linear_acceleration", "imu_angular_velocity"] + [
        f"wrench_{n}" for n in names
    ]
    for k, target in enumerate(targets):
        builder.Connect(values.get_output_port(k), estimator.GetInputPort(target))
    rates = builder.AddNamedSystem(f"{name}_sensor_derivatives", Demultiplexer(sizes))
    builder.Connect(sensor_filter.GetOutputPort("derivative"), rates.get_input_port())
    builder.Connect(
        rates.get_output_port(1), estimator.GetInputPort("imu_angular_acceleration")
    )
    return EstimationChain(estimator, encoder_filter, sensor_filter)
