"""FloatingBaseTorqueEstimator on other robot layouts than HRP-2's: a fixed-base arm
(with and without IMU) and a leg with nested F/T sensors (iCub-like: one in the thigh,
one at the ankle; paper Sec. 2.2), floating or welded to the world.

The models are built here from URDF strings (non-trivial inertias and centres of mass,
revolute and prismatic joints, F/T sensors as weld joints). The reference values are
computed without the estimator's code, on a *continuous* plant with gravity: true
torques from the equations of motion M v̇ + h − τ_g − Σ Jᵀ f (CalcMassMatrix,
CalcBiasTerm, CalcGravityGeneralizedForces, Jacobians), confirmed by the plant's
forward dynamics; F/T readings and the mounting's wrench from its weld reaction forces;
IMU readings from CalcSpatialAccelerationsFromVdot; external wrenches by summing the
applied wrenches on each sensor's segment.
"""

import dataclasses

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.multibody.math import SpatialForce, SpatialVelocity
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import ExternallyAppliedSpatialForce, MultibodyPlant
from pydrake.multibody.tree import (
    BodyIndex,
    FixedOffsetFrame,
    JacobianWrtVariable,
    SpatialInertia,
)
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource
from ticks import commit

from hrp2_drake import kernels
from hrp2_drake.estimation.estimation_chain import add_estimator
from hrp2_drake.estimation.estimator_config import (
    ForceTorqueSensorConfig,
    TorqueEstimatorConfig,
)
from hrp2_drake.estimation.estimator_step import FloatingBaseTorqueEstimatorStep
from hrp2_drake.estimation.torque_estimator import FloatingBaseTorqueEstimator

kV = JacobianWrtVariable.kV
TOL = 1e-8
IMU_NAMES = (
    "imu_linear_acceleration",
    "imu_angular_velocity",
    "imu_angular_acceleration",
)


# ----------------------------------------------------------------------------- models


def _vec(x) -> str:
    return " ".join(f"{value:.17g}" for value in x)


def _link(name: str, rng: np.random.Generator) -> str:
    """A link with a random mass, centre of mass and rotated inertia (a solid box)."""
    mass = rng.uniform(0.5, 3.0)
    a, b, c = rng.uniform(0.05, 0.4, 3)
    moments = mass / 12 * np.array([b * b + c * c, a * a + c * c, a * a + b * b])
    return f"""
  <link name="{name}">
    <inertial>
      <origin xyz="{_vec(rng.normal(0, 0.05, 3))}" rpy="{_vec(rng.uniform(-3, 3, 3))}"/>
      <mass value="{mass:.17g}"/>
      <inertia ixx="{moments[0]:.17g}" iyy="{moments[1]:.17g}" izz="{moments[2]:.17g}"
               ixy="0" ixz="0" iyz="0"/>
    </inertial>
  </link>"""


def _joint(name: str, kind: str, parent: str, child: str, rng, axis=None) -> str:
    """A joint at a random pose on its parent; F/T welds are `fixed` joints."""
    origin = (
        f'<origin xyz="{_vec(rng.normal(0, 0.1, 3))}" '
        f'rpy="{_vec(rng.uniform(-0.6, 0.6, 3))}"/>'
    )
    extra = ""
    if kind != "fixed":
        axis = rng.normal(size=3) if axis is None else np.asarray(axis, float)
        # No <limit>: unbounded joints (a continuous plant would ignore limits).
        extra = f'<axis xyz="{_vec(axis / np.linalg.norm(axis))}"/>'
    return f"""
  <joint name="{name}" type="{kind}">
    <parent link="{parent}"/><child link="{child}"/>{origin}{extra}
  </joint>"""


#: The arm: 7 joints (two prismatic), a wrist F/T weld, a tool with a gripper finger
#: and a welded payload below it (the sensor carries all three).
ARM_CHAIN = [
    ("j1", "revolute", "base", "l1"),
    ("j2", "revolute", "l1", "l2"),
    ("j3", "prismatic", "l2", "l3"),
    ("j4", "revolute", "l3", "l4"),
    ("j5", "revolute", "l4", "l5"),
    ("j6", "prismatic", "l5", "l6"),
    ("j7", "revolute", "l6", "link7"),
    ("wrist_ft", "fixed", "link7", "tool"),
    ("finger", "revolute", "tool", "finger_link"),
    ("payload_mount", "fixed", "tool", "payload"),
]
ARM_JOINTS = [j for j, kind, _, _ in ARM_CHAIN if kind != "fixed"]
#: The bodies below the wrist sensor.
ARM_SEGMENTS = {"wrist": ["tool", "finger_link", "payload"]}
ARM_MOUNT = RigidTransform(RollPitchYaw(0.4, -0.3, 1.1), [0.2, -0.1, 0.7])


def _arm_urdf(world_joint: bool) -> str:
    """The arm, welded to the world by a tilted URDF joint, or free; an IMU on l2."""
    rng = np.random.default_rng(1)
    links = ["base"] + [child for _, _, _, child in ARM_CHAIN]
    text = "".join(_link(name, rng) for name in links)
    text += "".join(_joint(j, kind, p, c, rng) for j, kind, p, c in ARM_CHAIN)
    text += '\n  <link name="imu"/>' + _joint("imu_mount", "fixed", "l2", "imu", rng)
    if world_joint:
        rpy = RollPitchYaw(ARM_MOUNT.rotation()).vector()
        text += f"""
  <joint name="mount" type="fixed">
    <parent link="world"/><child link="base"/>
    <origin xyz="{_vec(ARM_MOUNT.translation())}" rpy="{_vec(rpy)}"/>
  </joint>"""
    return f'<?xml version="1.0"?>\n<robot name="arm">{text}\n</robot>'


def _arm_plant(welded: bool) -> MultibodyPlant:
    plant = MultibodyPlant(0.0)
    Parser(plant).AddModelsFromString(_arm_urdf(welded), "urdf")
    # Two actuators with reflected inertia (it enters M, and τ̂ includes it).
    for joint in ("j2", "j3"):
        actuator = plant.AddJointActuator(f"{joint}_motor", plant.GetJointByName(joint))
        actuator.set_default_rotor_inertia(2e-5)
        actuator.set_default_gear_ratio(120.0)
    plant.Finalize()
    return plant


#: The leg: a pelvis (base) with a torso carrying the IMU; hip, an F/T weld in the
#: thigh, knee, a prismatic shin, ankle, an F/T weld at the ankle, a foot with a toe.
LEG_CHAIN = [
    ("waist", "revolute", "pelvis", "torso"),
    ("imu_mount", "fixed", "torso", "imu"),
    ("hip_yaw", "revolute", "pelvis", "hip1"),
    ("hip_roll", "revolute", "hip1", "hip2"),
    ("hip_pitch", "revolute", "hip2", "thigh_upper"),
    ("thigh_ft", "fixed", "thigh_upper", "thigh_lower"),
    ("knee", "revolute", "thigh_lower", "shin"),
    ("shin_slide", "prismatic", "shin", "shin_lower"),
    ("ankle_pitch", "revolute", "shin_lower", "ankle1"),
    ("ankle_roll", "revolute", "ankle1", "ankle2"),
    ("ankle_ft", "fixed", "ankle2", "foot"),
    ("toe", "revolute", "foot", "toe_link"),
]
LEG_JOINTS = [j for j, kind, _, _ in LEG_CHAIN if kind != "fixed"]
#: Each sensor's segment: the bodies between it and the sensors nested below it.
LEG_SEGMENTS = {
    "thigh": ["thigh_lower", "shin", "shin_lower", "ankle1", "ankle2"],
    "ankle": ["foot", "toe_link"],
}
LEG_MOUNT = RigidTransform(RollPitchYaw(-0.5, 0.2, 0.3), [0.0, 0.3, 1.0])
#: The ankle sensor's frame, on the foot, away from the weld's frame.
X_FOOT_SENSOR = RigidTransform(RollPitchYaw(0.2, -0.4, 0.9), [0.01, -0.02, 0.03])


def _leg_urdf() -> str:
    rng = np.random.default_rng(2)
    text = "".join(
        _link(name, rng) if name != "imu" else '\n  <link name="imu"/>'
        for name in ["pelvis"] + [child for _, _, _, child in LEG_CHAIN]
    )
    text += "".join(_joint(j, kind, p, c, rng) for j, kind, p, c in LEG_CHAIN)
    return f'<?xml version="1.0"?>\n<robot name="leg">{text}\n</robot>'


def _leg_plant(welded: bool) -> MultibodyPlant:
    plant = MultibodyPlant(0.0)
    Parser(plant).AddModelsFromString(_leg_urdf(), "urdf")
    plant.AddFrame(
        FixedOffsetFrame(
            "ankle_ft_frame", plant.GetBodyByName("foot").body_frame(), X_FOOT_SENSOR
        )
    )
    if welded:
        plant.WeldFrames(
            plant.world_frame(), plant.GetBodyByName("pelvis").body_frame(), LEG_MOUNT
        )
    plant.Finalize()
    return plant


def _arm_config(imu: bool = False, **changes) -> TorqueEstimatorConfig:
    config = TorqueEstimatorConfig(
        joints=list(ARM_JOINTS),
        imu_frame="imu" if imu else "",
        # The weld's child frame is the sensor frame; the body defaults to its body.
        sensors={"wrist": ForceTorqueSensorConfig(frame="tool")},
    )
    return dataclasses.replace(config, **changes)


def _leg_config(imu: bool = True, **changes) -> TorqueEstimatorConfig:
    config = TorqueEstimatorConfig(
        joints=list(LEG_JOINTS),
        imu_frame="imu" if imu else "",
        sensors={
            # The weld's parent frame: on the body above, rigidly attached to the one
            # below (the sensor's body), at the same place.
            "thigh": ForceTorqueSensorConfig("thigh_ft_parent", "thigh_lower"),
            "ankle": ForceTorqueSensorConfig("ankle_ft_frame", "foot"),
        },
    )
    return dataclasses.replace(config, **changes)


# ------------------------------------------------------------------------------ truth


def _shift(F_F: np.ndarray, X_FG: RigidTransform) -> np.ndarray:
    """A wrench [torque about Fo; force] in F, about Go and in G."""
    R_GF = X_FG.rotation().inverse().matrix()
    torque = F_F[:3] - np.cross(X_FG.translation(), F_F[3:])
    return np.concatenate([R_GF @ torque, R_GF @ F_F[3:]])


class _Truth:
    """Consistent readings and true values from a continuous plant with gravity.

    Args:
        plant: the robot (floating, or welded to the world).
        joints: the joints' names (the order of q, v, vdot, tau).
        sensors: sensor name -> (F/T weld joint name, sensor frame name).
        segments: sensor name -> the bodies of its segment.
        imu: IMU frame name, or None.
    """

    def __init__(self, plant, joints, sensors, segments, imu=None):
        self.plant = plant
        self.context = plant.CreateDefaultContext()
        self.joints = [plant.GetJointByName(j) for j in joints]
        self.iq = np.array([j.position_start() for j in self.joints])
        self.iv = np.array([j.velocity_start() for j in self.joints])
        self.sensors = {
            name: (plant.GetJointByName(weld), plant.GetFrameByName(frame))
            for name, (weld, frame) in sensors.items()
        }
        self.segments = {
            name: {int(plant.GetBodyByName(b).index()) for b in bodies}
            for name, bodies in segments.items()
        }
        self.imu = plant.GetFrameByName(imu) if imu else None
        floating = sorted(int(b) for b in plant.GetFloatingBaseBodies())
        self.base = plant.get_body(BodyIndex(floating[0])) if floating else None
        # The weld that mounts a fixed base: the joint to the world without dofs.
        world = plant.world_body().index()
        self.mount = next(
            (
                plant.get_joint(j)
                for j in plant.GetJointIndices()
                if plant.get_joint(j).parent_body().index() == world
                and plant.get_joint(j).num_velocities() == 0
            ),
            None,
        )

    def _random_wrench(self, rng, scale: float = 1.0) -> np.ndarray:
        return scale * np.concatenate([rng.normal(0, 5, 3), rng.normal(0, 50, 3)])

    def sample(
        self,
        rng: np.random.Generator,
        wrenches_on: tuple[str, ...] = (),
        mount_wrench: bool = False,
        static: bool = False,
    ) -> dict:
        """Random q, v, v̇ (v = v̇ = 0 if static, fixed base only) and random wrenches
        on the bodies `wrenches_on` (at a random point of each); on a floating base
        with mount_wrench, a random unmeasured wrench on it (the mounting of a fixed
        base model), whose acceleration then follows from the equations of motion."""
        plant, context = self.plant, self.context
        W = plant.world_frame()
        q = plant.GetPositions(context)
        for joint, i in zip(self.joints, self.iq):
            q[i] = rng.uniform(-1, 1) * (
                0.05 if joint.type_name() == "prismatic" else 1
            )
        plant.SetPositions(context, q)
        v = np.zeros(plant.num_velocities())
        if not static:
            v[self.iv] = rng.normal(0, 1, len(self.iv))
        plant.SetVelocities(context, v)
        if self.base is not None:
            plant.SetFreeBodyPose(
                context,
                self.base,
                RigidTransform(RollPitchYaw(rng.uniform(-3, 3, 3)), rng.normal(size=3)),
            )
            plant.SetFreeBodySpatialVelocity(
                context,
                self.base,
                SpatialVelocity(rng.normal(size=3), rng.normal(size=3)),
            )
            v = plant.GetVelocities(context)

        applied, generalized = [], np.zeros(plant.num_velocities())
        external = {name: np.zeros(6) for name in self.sensors}
        unknown = np.zeros(6)
        bodies = [(plant.GetBodyByName(b), False) for b in wrenches_on]
        if mount_wrench:
            bodies.append((self.base, True))
        for body, is_mount in bodies:
            p_BoBq_B = np.zeros(3) if is_mount else rng.normal(0, 0.1, 3)
            X_WB = body.EvalPoseInWorld(context)
            p_WBq = X_WB @ p_BoBq_B
            F_W = self._random_wrench(rng, 2.0 if is_mount else 1.0)  # about Bq, in W
            J = plant.CalcJacobianSpatialVelocity(
                context, kV, body.body_frame(), p_BoBq_B, W, W
            )
            generalized += J.T @ F_W
            force = ExternallyAppliedSpatialForce()
            force.body_index = body.index()
            force.p_BoBq_B = p_BoBq_B
            force.F_Bq_W = SpatialForce(F_W[:3], F_W[3:])
            applied.append(force)
            if is_mount:  # about Bo (= Bq) in W to about Bo in B
                unknown = _shift(F_W, RigidTransform(X_WB.rotation(), np.zeros(3)))
            for name, (_, frame) in self.sensors.items():
                if int(body.index()) in self.segments[name]:
                    # About Bq in W to about So in S.
                    X_WS = frame.CalcPoseInWorld(context)
                    X_BqS = RigidTransform(X_WS.rotation(), X_WS.translation() - p_WBq)
                    external[name] += _shift(F_W, X_BqS)

        M = plant.CalcMassMatrix(context)
        h = plant.CalcBiasTerm(context) - plant.CalcGravityGeneralizedForces(context)
        vdot = np.zeros(plant.num_velocities())
        if not static:
            vdot[self.iv] = rng.normal(0, 3, len(self.iv))
        if self.base is not None:
            b = self.base.floating_velocities_start_in_v() + np.arange(6)
            rest = M @ vdot + h - generalized
            vdot[b] = np.linalg.solve(M[np.ix_(b, b)], -rest[b])
        residual = M @ vdot + h - generalized  # eq. (1): = Sᵀ τ
        tau = residual[self.iv]
        not_joints = np.setdiff1d(np.arange(plant.num_velocities()), self.iv)
        assert np.max(np.abs(residual[not_joints]), initial=0.0) < 1e-9

        # The forward dynamics with τ confirms v̇; then the welds' reactions.
        generalized_tau = np.zeros(plant.num_velocities())
        generalized_tau[self.iv] = tau
        plant.get_applied_generalized_force_input_port().FixValue(
            context, generalized_tau
        )
        plant.get_actuation_input_port().FixValue(
            context, np.zeros(plant.num_actuators())
        )
        plant.get_applied_spatial_force_input_port().FixValue(context, applied)
        vdot_fd = plant.get_generalized_acceleration_output_port().Eval(context)
        assert np.max(np.abs(vdot_fd - vdot)) < 1e-9 * (1 + np.max(np.abs(vdot)))
        reactions = plant.get_reaction_forces_output_port().Eval(context)
        readings = []
        for weld, frame in self.sensors.values():
            # The reaction: on the weld's child, about and in its child frame C.
            reading_C = -reactions[int(weld.index())].get_coeffs()
            X_CS = frame.CalcPose(context, weld.frame_on_child())
            readings.append(_shift(reading_C, X_CS))
        if self.base is None and self.mount is not None:
            # The mounting's wrench on the base, about its origin, in its frame.
            X_CB = (
                self.mount.child_body()
                .body_frame()
                .CalcPose(context, self.mount.frame_on_child())
            )
            unknown = _shift(reactions[int(self.mount.index())].get_coeffs(), X_CB)

        sample = dict(
            q=q[self.iq],
            v=v[self.iv],
            vdot=vdot[self.iv],
            readings=np.array(readings).reshape(-1, 6),
            tau=tau,
            external=np.array([external[name] for name in self.sensors]).reshape(-1, 6),
            unknown=unknown,
        )
        sample.update(dict.fromkeys(IMU_NAMES))
        if self.imu is not None:
            sample.update(self._imu(vdot))
        return sample

    def _imu(self, vdot: np.ndarray) -> dict:
        """Gyro, accelerometer (proper acceleration) and angular acceleration, in the
        IMU frame I."""
        plant, context, imu = self.plant, self.context, self.imu
        body = imu.body()
        A_WB = plant.CalcSpatialAccelerationsFromVdot(context, vdot)[int(body.index())]
        X_WB = body.EvalPoseInWorld(context)
        w_WB = body.EvalSpatialVelocityInWorld(context).rotational()
        p_BoIo_W = X_WB.rotation() @ imu.GetFixedPoseInBodyFrame().translation()
        A_WI = A_WB.Shift(p_BoIo_W, w_WB)
        R_IW = imu.CalcPoseInWorld(context).rotation().inverse().matrix()
        g_W = plant.gravity_field().gravity_vector()
        return dict(
            imu_linear_acceleration=R_IW @ (A_WI.translational() - g_W),
            imu_angular_velocity=R_IW @ w_WB,
            imu_angular_acceleration=R_IW @ A_WI.rotational(),
        )


@pytest.fixture(scope="module")
def arm():
    return _arm_plant(welded=True)


@pytest.fixture(scope="module")
def arm_truth(arm):
    return _Truth(arm, ARM_JOINTS, {"wrist": ("wrist_ft", "tool")}, ARM_SEGMENTS)


@pytest.fixture(scope="module")
def legs():
    return {"floating": _leg_plant(welded=False), "welded": _leg_plant(welded=True)}


def _leg_truth(plant, imu: bool) -> _Truth:
    sensors = {
        "thigh": ("thigh_ft", "thigh_ft_parent"),
        "ankle": ("ankle_ft", "ankle_ft_frame"),
    }
    return _Truth(plant, LEG_JOINTS, sensors, LEG_SEGMENTS, "imu" if imu else None)


def _estimate(estimator: FloatingBaseTorqueEstimator, sample: dict):
    return estimator.estimate(
        sample["q"],
        sample["v"],
        sample["vdot"],
        *(sample[name] for name in IMU_NAMES),
        sample["readings"],
    )


def _assert_matches(result, sample: dict) -> dict:
    """Asserts τ̂, the external and unknown wrenches to TOL; returns the errors."""
    errors = {
        "tau": np.max(np.abs(result.tau - sample["tau"])),
        "external": np.max(np.abs(result.external_wrenches - sample["external"])),
        "unknown": np.max(np.abs(result.unknown_wrench - sample["unknown"])),
    }
    np.testing.assert_allclose(result.tau, sample["tau"], rtol=0, atol=TOL)
    np.testing.assert_allclose(
        result.external_wrenches, sample["external"], rtol=0, atol=TOL
    )
    np.testing.assert_allclose(
        result.unknown_wrench, sample["unknown"], rtol=0, atol=TOL
    )
    return errors


# --------------------------------------------------------------------- fixed-base arm


@pytest.mark.parametrize("seed", range(3))
def test_fixed_base_arm_without_imu(arm, arm_truth, seed):
    """A tilted arm welded to the world, no IMU (gravity known): τ̂, the wrist's
    external wrench and the mounting's wrench on the base (unknown wrench) are exact,
    with a moving finger and a payload below the sensor."""
    estimator = FloatingBaseTorqueEstimator(arm, _arm_config())
    assert estimator.is_fixed_base() and not estimator.has_imu()
    assert estimator.base_body().name() == "base"
    # The payload is welded to the tool: its wrench is measured as the tool's.
    sample = arm_truth.sample(
        np.random.default_rng(seed), wrenches_on=("tool", "payload")
    )
    assert np.linalg.norm(sample["unknown"][3:]) > 10.0  # it holds the arm's weight
    _assert_matches(_estimate(estimator, sample), sample)


def test_fixed_base_arm_at_rest_holds_its_weight(arm, arm_truth):
    """At rest without contact the mounting's force is the weight, upward."""
    estimator = FloatingBaseTorqueEstimator(arm, _arm_config())
    sample = arm_truth.sample(np.random.default_rng(5), static=True)
    result = _estimate(estimator, sample)
    _assert_matches(result, sample)
    weight_W = arm.CalcTotalMass(arm.CreateDefaultContext()) * (
        arm.gravity_field().gravity_vector()
    )
    R_BW = ARM_MOUNT.rotation().inverse().matrix()
    np.testing.assert_allclose(
        result.unknown_wrench[3:], R_BW @ -weight_W, rtol=0, atol=TOL
    )


@pytest.mark.parametrize("seed", range(2))
def test_fixed_base_arm_with_imu_on_a_moving_platform(arm, seed):
    """A welded arm model with an IMU on a link (l2): the IMU gives the motion. Truth:
    the same arm on a free platform, moved by an unmeasured wrench on its base, which
    is the unknown wrench (the mounting's)."""
    truth = _Truth(
        _arm_plant(welded=False),
        ARM_JOINTS,
        {"wrist": ("wrist_ft", "tool")},
        ARM_SEGMENTS,
        imu="imu",
    )
    sample = truth.sample(
        np.random.default_rng(10 + seed), wrenches_on=("tool",), mount_wrench=True
    )
    estimator = FloatingBaseTorqueEstimator(arm, _arm_config(imu=True))
    assert estimator.is_fixed_base() and estimator.has_imu()
    _assert_matches(_estimate(estimator, sample), sample)


# --------------------------------------------------------------------- nested sensors


LEG_CASES = {
    # layout: (plant, IMU, truth plant, mounting wrench)
    "floating_with_imu": ("floating", True, "floating", False),
    "fixed_without_imu": ("welded", False, "welded", False),
    "fixed_with_imu": ("welded", True, "floating", True),
}


@pytest.mark.parametrize("case", list(LEG_CASES))
@pytest.mark.parametrize("seed", range(2))
def test_nested_sensors(legs, case, seed):
    """Thigh and ankle F/T sensors, wrenches on the bodies right below them: τ̂ is
    exact; the thigh's external wrench is its segment's (thigh to ankle), the ankle's
    that on the foot and toe."""
    plant_name, imu, truth_name, mount = LEG_CASES[case]
    estimator = FloatingBaseTorqueEstimator(legs[plant_name], _leg_config(imu=imu))
    assert estimator.nested_sensors() == {"ankle": "thigh"}
    truth = _leg_truth(legs[truth_name], imu)
    sample = truth.sample(
        np.random.default_rng(20 + seed),
        wrenches_on=("thigh_lower", "foot"),
        mount_wrench=mount,
    )
    # Both sensors carry a wrench; the thigh's is not its whole subtree's.
    assert np.all(np.linalg.norm(sample["external"], axis=1) > 1.0)
    _assert_matches(_estimate(estimator, sample), sample)


def test_nested_sensors_wrench_inside_a_segment(legs):
    """Wrenches on the shin (inside the thigh sensor's segment) and on the toe (below
    the ankle sensor's body): the segment wrenches and the base's (zero) are still
    exact, and so are the torques of the joints above the thigh sensor; the joints
    inside the segments see the wrench moved to the body right below the sensor."""
    estimator = FloatingBaseTorqueEstimator(legs["floating"], _leg_config())
    truth = _leg_truth(legs["floating"], imu=True)
    sample = truth.sample(np.random.default_rng(30), wrenches_on=("shin", "toe_link"))
    result = _estimate(estimator, sample)
    np.testing.assert_allclose(
        result.external_wrenches, sample["external"], rtol=0, atol=TOL
    )
    np.testing.assert_allclose(result.unknown_wrench, np.zeros(6), rtol=0, atol=TOL)
    above = [LEG_JOINTS.index(j) for j in ("waist", "hip_yaw", "hip_roll", "hip_pitch")]
    np.testing.assert_allclose(
        result.tau[above], sample["tau"][above], rtol=0, atol=TOL
    )
    inside = [LEG_JOINTS.index(j) for j in ("knee", "toe")]
    assert np.all(np.abs(result.tau[inside] - sample["tau"][inside]) > 1e-3)


def test_nested_offsets_stay_with_their_sensor(legs):
    """F/T offsets are per sensor reading: known offsets (estimate's `offsets`) give
    the unbiased estimate; the start-up calibration (robot moving, nothing touching)
    finds each sensor's own offset, nested or not."""
    plant = legs["floating"]
    truth = _leg_truth(plant, imu=True)
    rng = np.random.default_rng(40)
    bias = rng.normal(0, 2.0, (2, 6))
    sample = truth.sample(rng, wrenches_on=("thigh_lower", "foot"))
    estimator = FloatingBaseTorqueEstimator(plant, _leg_config())
    biased = dict(sample, readings=sample["readings"] + bias)
    result = estimator.estimate(
        *(biased[k] for k in ("q", "v", "vdot", *IMU_NAMES, "readings")), offsets=bias
    )
    _assert_matches(result, sample)

    config = _leg_config(offset_calibration_time=0.003, offset_calibration_start=0.0)
    estimator = FloatingBaseTorqueEstimator(plant, config)
    context = estimator.CreateDefaultContext()
    for k in range(3):  # moving, nothing touching
        free = truth.sample(rng)
        _fix(estimator, context, dict(free, readings=free["readings"] + bias))
        _step(estimator, context, 1e-3 * k)
    np.testing.assert_allclose(estimator.offsets(context), bias, rtol=0, atol=1e-8)
    _fix(estimator, context, biased)
    outputs = _step(estimator, context, 0.003)
    np.testing.assert_allclose(outputs["tau"], sample["tau"], rtol=0, atol=TOL)
    np.testing.assert_allclose(
        outputs["external"], sample["external"], rtol=0, atol=TOL
    )


# ------------------------------------------------------------------------- the system


def _fix(estimator, context, sample: dict) -> None:
    for name in ("q", "v", "vdot"):
        estimator.GetInputPort(name).FixValue(context, sample[name])
    for name in IMU_NAMES:
        if estimator.HasInputPort(name):
            estimator.GetInputPort(name).FixValue(context, sample[name])
    for name, reading in zip(estimator.sensor_names(), sample["readings"]):
        estimator.GetInputPort(f"wrench_{name}").FixValue(context, reading)


def _step(estimator, context, t: float = 0.0) -> dict:
    """The tick of the sample now fixed, taken at t, as the sampler presents it
    (`tests.ticks`): its outputs (returned), then its commit at the next sampling
    instant, t + period."""
    context.SetTime(t)
    outputs = {
        "tau": estimator.GetOutputPort("tau").Eval(context).copy(),
        "unknown": estimator.GetOutputPort("unknown_wrench").Eval(context).copy(),
        "external": np.array(
            [
                estimator.GetOutputPort(f"external_wrench_{s}").Eval(context)
                for s in estimator.sensor_names()
            ]
        ),
    }
    commit(estimator, context, t + estimator.config().period)
    return outputs


def test_system_matches_estimate(arm, arm_truth, legs):
    """The LeafSystem's outputs give what `estimate` gives; the fixed-base
    estimator without IMU has no imu ports."""
    arm_estimator = FloatingBaseTorqueEstimator(arm, _arm_config())
    for name in IMU_NAMES:
        assert not arm_estimator.HasInputPort(name)
    assert arm_estimator.num_input_ports() == 3 + 1  # q, v, vdot, wrench_wrist
    leg_estimator = FloatingBaseTorqueEstimator(legs["floating"], _leg_config())
    assert all(leg_estimator.HasInputPort(name) for name in IMU_NAMES)
    cases = [
        (arm_estimator, arm_truth.sample(np.random.default_rng(50), ("tool",))),
        (
            leg_estimator,
            _leg_truth(legs["floating"], True).sample(
                np.random.default_rng(51), ("thigh_lower", "foot")
            ),
        ),
    ]
    for estimator, sample in cases:
        context = estimator.CreateDefaultContext()
        _fix(estimator, context, sample)
        outputs = _step(estimator, context)
        result = _estimate(estimator, sample)
        np.testing.assert_allclose(outputs["tau"], result.tau, rtol=0, atol=1e-12)
        np.testing.assert_allclose(
            outputs["unknown"], result.unknown_wrench, rtol=0, atol=1e-12
        )
        np.testing.assert_allclose(
            outputs["external"], result.external_wrenches, rtol=0, atol=1e-12
        )
        np.testing.assert_allclose(outputs["tau"], sample["tau"], rtol=0, atol=TOL)


def test_step_without_imu_and_with_nested_sensors(arm, arm_truth, legs):
    """FloatingBaseTorqueEstimatorStep on plain arrays: the fixed-base arm without IMU
    takes None for the imu_* inputs (and for the wrenches without F/T sensor), the
    nested leg sensors work as in `estimate`, to the bit, and both match the truth."""
    arm_step = FloatingBaseTorqueEstimatorStep(arm, _arm_config())
    assert not arm_step.has_imu() and not arm_step.reads_angular_acceleration()
    assert arm_step.sensor_names() == ["wrist"]
    sample = arm_truth.sample(np.random.default_rng(52), ("tool",))
    joints = [sample[k] for k in ("q", "v", "vdot")]
    arm_step.step(0.0, *joints, None, None, None, sample["readings"])
    np.testing.assert_allclose(arm_step.tau, sample["tau"], rtol=0, atol=TOL)
    np.testing.assert_allclose(
        arm_step.external_wrench_wrist, sample["external"][0], rtol=0, atol=TOL
    )
    np.testing.assert_allclose(
        arm_step.unknown_wrench, sample["unknown"], rtol=0, atol=TOL
    )

    bare = FloatingBaseTorqueEstimatorStep(arm, _arm_config(sensors={}))
    assert bare.num_sensors() == 0 and bare.output_names() == ["tau", "unknown_wrench"]
    bare.step(0.0, *joints, None, None, None, None)
    assert np.all(np.isfinite(bare.tau)) and np.any(bare.tau != 0.0)

    leg_step = FloatingBaseTorqueEstimatorStep(legs["floating"], _leg_config())
    assert leg_step.nested_sensors() == {"ankle": "thigh"}
    truth = _leg_truth(legs["floating"], True)
    sample = truth.sample(np.random.default_rng(53), ("thigh_lower", "foot"))
    inputs = [sample[k] for k in ("q", "v", "vdot", *IMU_NAMES, "readings")]
    leg_step.step(0.0, *inputs)
    result = leg_step.estimate(*inputs)
    np.testing.assert_array_equal(leg_step.tau, result.tau)
    for k, name in enumerate(leg_step.sensor_names()):
        external = getattr(leg_step, f"external_wrench_{name}")
        np.testing.assert_array_equal(external, result.external_wrenches[k])
    np.testing.assert_allclose(leg_step.tau, sample["tau"], rtol=0, atol=TOL)
    np.testing.assert_allclose(
        result.external_wrenches, sample["external"], rtol=0, atol=TOL
    )


def test_step_kernels_compiled_equal_interpreted(arm, arm_truth, legs):
    """The kernels' other branches, compiled and as Python source, to the bit: no IMU
    and no F/T sensor (the fixed-base arm), the unknown-wrench link moving relative
    to the root (its Jacobian: the arm with an IMU on l2), nested sensors with a
    calibration (the legs)."""
    sample = arm_truth.sample(np.random.default_rng(54), ("tool",))
    joints = [sample[k] for k in ("q", "v", "vdot")]
    leg_truth = _leg_truth(legs["floating"], True)
    leg_samples = [
        leg_truth.sample(np.random.default_rng(55 + k), ()) for k in range(2)
    ]
    contact = leg_truth.sample(np.random.default_rng(57), ("thigh_lower", "foot"))
    leg_samples.append(contact)
    cases = [
        (arm, _arm_config(sensors={}), [[*joints, None, None, None, None]]),
        (
            arm,
            _arm_config(imu=True),
            [[*joints, *(np.zeros(3) for _ in IMU_NAMES), sample["readings"]]],
        ),
        (
            legs["floating"],
            _leg_config(offset_calibration_time=0.002, offset_calibration_start=0.0),
            [
                [s[k] for k in ("q", "v", "vdot", *IMU_NAMES, "readings")]
                for s in leg_samples
            ],
        ),
    ]
    for plant, config, ticks in cases:
        compiled = FloatingBaseTorqueEstimatorStep(plant, config)
        interpreted = FloatingBaseTorqueEstimatorStep(plant, config)
        for k, inputs in enumerate(ticks):
            compiled.step(1e-3 * k, *inputs)
            with kernels.interpreted():
                interpreted.step(1e-3 * k, *inputs)
            np.testing.assert_array_equal(compiled.state, interpreted.state)
            assert np.any(compiled.tau != 0.0)
    np.testing.assert_allclose(compiled.tau, leg_samples[-1]["tau"], rtol=0, atol=TOL)


def _station(q: np.ndarray, readings: dict[str, np.ndarray]):
    """A fixed-base "station" without IMU ports: constant encoders and F/T readings."""
    builder = DiagramBuilder()
    encoders = builder.AddSystem(ConstantVectorSource(q))
    builder.ExportOutput(encoders.get_output_port(), "q_measured")
    for name, reading in readings.items():
        source = builder.AddSystem(ConstantVectorSource(reading))
        builder.ExportOutput(source.get_output_port(), f"wrench_{name}")
    station = builder.Build()
    station.set_name("station")
    return station


@pytest.mark.parametrize("with_sensor", [True, False])
def test_add_estimator_fixed_base_without_imu(arm, arm_truth, with_sensor):
    """add_estimator on a station without IMU ports: it builds and runs; the arm held
    still, τ̂ is exact once the filters' window is full. Without F/T sensor there is
    no sensor filter and input_fault is still a (1,) port."""
    sample = arm_truth.sample(
        np.random.default_rng(60),
        wrenches_on=("tool",) if with_sensor else (),
        static=True,
    )
    config = _arm_config(window=5)
    readings = {"wrist": sample["readings"][0]}
    if not with_sensor:
        config.sensors = {}
        readings = {}
    builder = DiagramBuilder()
    station = builder.AddSystem(_station(sample["q"], readings))
    chain = add_estimator(builder, station, arm, config)
    assert (chain.sensor_filter is not None) == with_sensor
    if with_sensor:
        assert chain.sensor_filter.num_signals() == 6  # the F/T sensor only
    assert chain.input_fault.size() == 1
    diagram = builder.Build()
    simulator = Simulator(diagram)
    simulator.AdvanceTo(0.012)
    context = simulator.get_context()
    tau = chain.estimator.GetOutputPort("tau").Eval(
        chain.estimator.GetMyContextFromRoot(context)
    )
    np.testing.assert_allclose(tau, sample["tau"], rtol=0, atol=TOL)
    fault = chain.input_fault.get_system()
    assert chain.input_fault.Eval(fault.GetMyContextFromRoot(context))[0] == 0


# ------------------------------------------------------------------------ bad layouts


def test_bad_layouts(arm, legs):
    floating, welded = legs["floating"], legs["welded"]
    sensors = _leg_config().sensors
    cases = [
        (
            floating,
            _leg_config(imu=False),
            ValueError,
            r"TorqueEstimatorConfig.imu_frame is empty, but the base 'pelvis' is "
            "floating",
        ),
        (
            welded,
            _leg_config(
                sensors=dict(sensors, ankle=ForceTorqueSensorConfig("foot", "ankle2"))
            ),
            ValueError,
            r"F/T sensor 'ankle': body 'ankle2' is above its frame 'foot' \(on body "
            r"'foot'\): give the body right below the sensor",
        ),
        (
            floating,
            _leg_config(imu_frame="knee_parent"),  # a frame on the thigh_lower
            ValueError,
            "IMU frame 'knee_parent' is below an F/T sensor",
        ),
        (
            welded,
            _leg_config(sensors=dict(sensors, ankle=ForceTorqueSensorConfig("nope"))),
            KeyError,
            "F/T sensor 'ankle' frame 'nope' is not a frame or body",
        ),
        (
            welded,
            _leg_config(
                sensors=dict(sensors, toe=ForceTorqueSensorConfig("foot", "foot"))
            ),
            ValueError,
            "F/T sensors 'ankle' and 'toe' have the same body 'foot'",
        ),
        (
            arm,
            _arm_config(base_body="l1"),
            ValueError,
            "not a floating base, nor welded",
        ),
        (
            arm,
            _arm_config(joints=ARM_JOINTS[:-1]),
            ValueError,
            r"the fixed base and the 7 joints of the config cover 7; joints not in the "
            r"config: \['finger'\]",
        ),
    ]
    for plant, config, error, match in cases:
        with pytest.raises(error, match=match):
            FloatingBaseTorqueEstimator(plant, config)


def test_estimate_imu_arguments(arm, arm_truth, legs):
    """Without IMU the imu arguments must be None; with one they must be given."""
    sample = arm_truth.sample(np.random.default_rng(70))
    estimator = FloatingBaseTorqueEstimator(arm, _arm_config())
    args = (sample["q"], sample["v"], sample["vdot"])
    with pytest.raises(ValueError, match=r"\['imu_angular_velocity'\] given, but"):
        estimator.estimate(*args, None, np.zeros(3), None, sample["readings"])
    leg = FloatingBaseTorqueEstimator(legs["floating"], _leg_config())
    n = len(LEG_JOINTS)
    with pytest.raises(ValueError, match=r"\['imu_linear_acceleration'\] are None"):
        leg.estimate(
            *[np.zeros(n)] * 3, None, np.zeros(3), np.zeros(3), np.zeros((2, 6))
        )
    neglected = FloatingBaseTorqueEstimator(
        legs["floating"], _leg_config(angular_acceleration="neglected")
    )
    neglected.estimate(
        *[np.zeros(n)] * 3, np.zeros(3), np.zeros(3), None, np.zeros((2, 6))
    )


def test_two_bodies_welded_to_the_world_need_a_base_body():
    """A stand welded to the world next to the arm: which is the base? Named, it
    works (the stand is not part of the robot)."""
    plant = MultibodyPlant(0.0)
    (instance,) = Parser(plant).AddModelsFromString(_arm_urdf(world_joint=True), "urdf")
    stand = plant.AddRigidBody(
        "stand", instance, SpatialInertia.SolidBoxWithMass(5.0, 0.3, 0.3, 0.3)
    )
    plant.WeldFrames(plant.world_frame(), stand.body_frame())
    plant.Finalize()
    with pytest.raises(ValueError, match=r"welded to the world \['base', 'stand'\]"):
        FloatingBaseTorqueEstimator(plant, _arm_config())
    estimator = FloatingBaseTorqueEstimator(plant, _arm_config(base_body="base"))
    assert estimator.base_body().name() == "base"
