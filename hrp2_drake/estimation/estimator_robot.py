"""The robot as the torque estimator finds it on its plant (`EstimatorRobot`): the
base (floating, or welded to the world), the joints, the IMU, the F/T sensors and
their nesting, the actuators' reflected inertias and the unknown-wrench link, each
found by name and checked, with one error naming what is wrong
(`FloatingBaseTorqueEstimator`'s docstring, "Errors")."""

import numpy as np
from pydrake.math import RigidTransform
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import BodyIndex, JacobianWrtVariable, RigidBody
from pydrake.systems.framework import Context

from hrp2_drake.estimation.estimator_config import (
    ForceTorqueSensorConfig,
    TorqueEstimatorConfig,
)
from hrp2_drake.estimation.internal_model import WHERE, ModelSensor
from hrp2_drake.multibody import floating_base, get_frame, joint_indexing, tree_parents


class EstimatorRobot:
    """The robot of a `TorqueEstimatorConfig` on its plant, found and checked at
    construction.

    Attributes:
        base: the base body (of the plant): the floating base, or a body welded to the
            world (`fixed_base`).
        fixed_base: True if the base is welded to the world (directly or through
            welds).
        indexing: config.joints' positions and velocities in the plant.
        n: the number of joints.
        parent: {body index: its parent's} of the robot's tree, rooted at the base.
        imu: the IMU frame, or None without IMU (only for a fixed base).
        sensors: the F/T sensors, config.sensors order (their internal-model fields
            empty until `internal_model` fills them).
        nesting: (outer, inner) sensor indices of every sensor directly below another.
        reflected_inertia: ρ² I_r of each joint (kg·m²), config.joints order.
        unknown_frame: the unknown-wrench link's body frame, None for the base.
    """

    def __init__(
        self,
        plant: MultibodyPlant,
        plant_context: Context,
        config: TorqueEstimatorConfig,
    ):
        """Finds and checks the base, the joints, the IMU, the sensors (their nesting)
        and the unknown-wrench link; a floating base is put at the identity pose in
        `plant_context` (the pose the sensors' frames are measured at).

        Raises:
            ValueError, KeyError: see FloatingBaseTorqueEstimator.
        """
        self._config = config
        self.base, self.fixed_base = self._find_base(plant, config)
        self.indexing = joint_indexing(plant, config.joints)
        self.n = self.indexing.size
        self.parent = tree_parents(plant, self.base.index())
        self._check_dofs(plant)
        if not self.fixed_base:
            plant.SetFreeBodyPose(plant_context, self.base, RigidTransform())
        self._check_base_jacobian(plant, plant_context)
        self.imu = self._find_imu(plant, config)
        self.sensors = [
            self._make_sensor(plant, plant_context, name, sensor)
            for name, sensor in config.sensors.items()
        ]
        self.nesting = self._nest_sensors()
        self.reflected_inertia = self._reflected_inertias(plant, plant_context)
        self.unknown_frame = self._find_unknown_wrench_frame(plant, config)
        below = [b for s in self.sensors for b in s.bodies]
        if self.imu is not None and int(self.imu.body().index()) in below:
            raise ValueError(
                f"{WHERE}: IMU frame '{config.imu_frame}' is below an F/T sensor"
            )

    @staticmethod
    def _find_base(
        plant: MultibodyPlant, config: TorqueEstimatorConfig
    ) -> tuple[RigidBody, bool]:
        """(base body, fixed): the floating base, or a body welded to the world."""
        world = plant.world_body()
        welded = {int(b.index()) for b in plant.GetBodiesWeldedTo(world)}
        welded.discard(int(world.index()))
        if config.base_body:
            if not plant.HasBodyNamed(config.base_body):
                raise KeyError(f"{WHERE}: base body '{config.base_body}' is not a body")
            base = plant.GetBodyByName(config.base_body)
            if base.is_floating_base_body():
                return base, False
            if int(base.index()) in welded:
                return base, True
            raise ValueError(
                f"{WHERE}: base body '{config.base_body}' is not a floating base, nor "
                "welded to the world"
            )
        advice = (
            "give a model of the robot alone, or name its base in "
            "TorqueEstimatorConfig.base_body"
        )
        if plant.GetFloatingBaseBodies():
            return floating_base(plant, WHERE, advice=advice), False
        # Bodies welded directly to the world (not through other welded bodies).
        direct = set()
        for j in plant.GetJointIndices():
            joint = plant.get_joint(j)
            ends = {int(joint.parent_body().index()), int(joint.child_body().index())}
            if joint.num_velocities() == 0 and int(world.index()) in ends:
                direct |= ends - {int(world.index())}
        if len(direct) == 1:
            return plant.get_body(BodyIndex(direct.pop())), True
        names = [plant.get_body(BodyIndex(b)).name() for b in sorted(direct)]
        raise ValueError(
            f"{WHERE}: the plant must have exactly one floating base body, or none "
            "and exactly one body welded to the world; it has no floating base and "
            f"the bodies welded to the world {names}: {advice}"
        )

    def _base_dofs(self) -> int:
        return 0 if self.fixed_base else 6

    def _check_dofs(self, plant: MultibodyPlant) -> None:
        """The base's and config.joints' velocities are all of the plant's, and every
        joint with degrees of freedom but the floating base's is in the robot's tree."""
        for j in plant.GetJointIndices():
            joint = plant.get_joint(j)
            if joint.num_velocities() == 0:
                continue
            child = int(joint.child_body().index())
            if not self.fixed_base and child == int(self.base.index()):
                if joint.parent_body().index() == plant.world_body().index():
                    continue  # the floating base's joint
            parent = int(joint.parent_body().index())
            if parent not in self.parent or child not in self.parent:
                raise ValueError(
                    f"{WHERE}: joint '{joint.name()}' (between '"
                    f"{joint.parent_body().name()}' and '{joint.child_body().name()}') "
                    f"is not in the tree of the base '{self.base.name()}': only the "
                    "base may be attached to the world; give a model of the robot alone"
                )
        expected = self._base_dofs() + self.n
        if plant.num_velocities() != expected:
            covered = set(self.indexing.v.tolist())
            if not self.fixed_base:
                start = self.base.floating_velocities_start_in_v()
                covered |= set(range(start, start + 6))
            missing = [
                plant.get_joint(j).name()
                for j in plant.GetJointIndices()
                if plant.get_joint(j).num_velocities() > 0
                and plant.get_joint(j).velocity_start() not in covered
            ]
            what = "the fixed base and" if self.fixed_base else "the floating base and"
            raise ValueError(
                f"{WHERE}: the plant has {plant.num_velocities()} velocities, but "
                f"{what} the {self.n} joints of the config cover {expected}; joints "
                f"not in the config: {missing}"
            )

    def _check_base_jacobian(self, plant: MultibodyPlant, context: Context) -> None:
        """A floating base's velocities must be [ω_WB; v_WBo]; a fixed base has none
        (welded to the world, its motion is the IMU's or none)."""
        if self.fixed_base:
            return
        J = plant.CalcJacobianSpatialVelocity(
            context,
            JacobianWrtVariable.kV,
            self.base.body_frame(),
            np.zeros(3),
            plant.world_frame(),
            plant.world_frame(),
        )
        start = self.base.floating_velocities_start_in_v()
        if not np.allclose(J[:, start : start + 6], np.eye(6), atol=1e-12):
            raise ValueError(
                f"{WHERE}: the floating joint of '{self.base.name()}' does not have "
                "velocities [ω_WB; v_WBo] (e.g. a quaternion or rpy floating joint)"
            )

    def _find_imu(self, plant: MultibodyPlant, config: TorqueEstimatorConfig):
        """The IMU frame, or None without IMU (only for a fixed base)."""
        if not config.imu_frame:
            if not self.fixed_base:
                raise ValueError(
                    f"{WHERE}: TorqueEstimatorConfig.imu_frame is empty, but the base "
                    f"'{self.base.name()}' is floating: its motion comes from the IMU "
                    "(only a robot welded to the world may go without IMU)"
                )
            return None
        imu = get_frame(plant, config.imu_frame, "IMU frame")
        if imu.body().index() == plant.world_body().index():
            raise ValueError(f"{WHERE}: IMU frame '{config.imu_frame}' is on the world")
        if int(imu.body().index()) not in self.parent:
            raise ValueError(
                f"{WHERE}: IMU frame '{config.imu_frame}' is on body "
                f"'{imu.body().name()}', which is not in the robot's tree"
            )
        return imu

    def _subtree(self, body: int) -> list[int]:
        children: dict[int, list[int]] = {}
        for child, parent in self.parent.items():
            children.setdefault(parent, []).append(child)
        out, stack = [], [body]
        while stack:
            b = stack.pop()
            out.append(b)
            stack.extend(children.get(b, []))
        return sorted(out)

    def _make_sensor(
        self,
        plant: MultibodyPlant,
        context: Context,
        name: str,
        cfg: ForceTorqueSensorConfig,
    ):
        frame = get_frame(plant, cfg.frame, f"F/T sensor '{name}' frame")
        if cfg.body:
            if not plant.HasBodyNamed(cfg.body):
                raise KeyError(
                    f"{WHERE}: F/T sensor '{name}' body '{cfg.body}' is not a body of "
                    "the plant"
                )
            body = plant.GetBodyByName(cfg.body)
        else:
            body = frame.body()
        index = int(body.index())
        if index not in self.parent:
            raise ValueError(
                f"{WHERE}: F/T sensor '{name}': body '{body.name()}' is not part of "
                "the robot's tree"
            )
        if index == int(self.base.index()):
            raise ValueError(
                f"{WHERE}: F/T sensor '{name}': body '{body.name()}' is the base; give "
                "the body right below the sensor"
            )
        welded = {int(b.index()) for b in plant.GetBodiesWeldedTo(body)} | {index}
        on = int(frame.body().index())
        if on not in welded:
            raise ValueError(
                f"{WHERE}: F/T sensor '{name}': frame '{cfg.frame}' is not rigidly "
                f"attached to body '{body.name()}'"
            )
        bodies = self._subtree(index)
        if on != index and on in bodies:
            # E.g. the ankle link above an F/T weld whose frame is on the foot: the
            # sensor would wrongly carry the ankle link.
            raise ValueError(
                f"{WHERE}: F/T sensor '{name}': body '{body.name()}' is above its "
                f"frame '{cfg.frame}' (on body '{frame.body().name()}'): give the body "
                "right below the sensor"
            )
        X_BS = frame.CalcPose(context, body.body_frame())
        return ModelSensor(name, frame, body, X_BS, bodies)

    def _nest_sensors(self) -> list[tuple[int, int]]:
        """(outer, inner) sensor indices for every sensor directly below another (the
        innermost sensor whose subtree holds its body). Raises ValueError for two
        sensors on one body."""
        owner: dict[int, str] = {}
        for sensor in self.sensors:
            b = int(sensor.body.index())
            if b in owner:
                raise ValueError(
                    f"{WHERE}: F/T sensors '{owner[b]}' and '{sensor.name}' have "
                    f"the same body '{sensor.body.name()}': give each sensor the body "
                    "right below it"
                )
            owner[b] = sensor.name
        subtrees = [set(sensor.bodies) for sensor in self.sensors]
        pairs = []
        for inner, sensor in enumerate(self.sensors):
            outers = [
                a
                for a, bodies in enumerate(subtrees)
                if a != inner and int(sensor.body.index()) in bodies
            ]
            if outers:  # nested subtrees: the smallest is the innermost
                pairs.append((min(outers, key=lambda a: len(subtrees[a])), inner))
        return pairs

    def _reflected_inertias(
        self, plant: MultibodyPlant, context: Context
    ) -> np.ndarray:
        by_joint = {}
        for index in plant.GetJointActuatorIndices():
            actuator = plant.get_joint_actuator(index)
            by_joint[int(actuator.joint().index())] = (
                actuator.rotor_inertia(context) * actuator.gear_ratio(context) ** 2
            )
        return np.array(
            [
                by_joint.get(int(plant.GetJointByName(j).index()), 0.0)
                for j in self._config.joints
            ]
        )

    def _find_unknown_wrench_frame(self, plant: MultibodyPlant, config):
        name = config.unknown_wrench_body
        if not name or name == self.base.name():
            return None
        if not plant.HasBodyNamed(name):
            raise KeyError(
                f"{WHERE}: unknown-wrench body '{name}' is not a body of the plant"
            )
        body = plant.GetBodyByName(name)
        if int(body.index()) not in self.parent:
            raise ValueError(
                f"{WHERE}: unknown-wrench body '{name}' is not in the robot"
            )
        return body.body_frame()
