"""The floating base from the soles' kinematics (estimation/base_kinematics.py) on
HRP-2: with the soles where they stand, the estimate is the plant's own state (the
standing pose; the base and legs moved by the standing IK, velocities that keep the
soles still; the whole scene turned); one sole is enough; soles that disagree give
the documented average, the velocity numpy's least squares at the estimate; a
non-finite input keeps the last estimate; the LeafSystem outputs the step's numbers;
the one-line errors; the kernels compiled equal their Python source, and `warm_up`
compiles them without changing the state. With the gyro (`ImuFusion`): the first tick
is the kinematic estimate, the orientation integrates the gyro's rate, returns to
the soles' at the gain, learns a bias, skips a NaN reading; its errors in one line."""

import contextlib

import numpy as np
import pytest
from pydrake.common.eigen_geometry import AngleAxis, Quaternion
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from pydrake.multibody.tree import JacobianWrtVariable

from hrp2_drake import kernels
from hrp2_drake.control.balance_reference import StandingIk
from hrp2_drake.description import load_robot_description
from hrp2_drake.estimation import base_kinematics
from hrp2_drake.estimation.base_kinematics import (
    FloatingBaseFromSoles,
    FloatingBaseFromSolesStep,
    ImuFusion,
)
from hrp2_drake.multibody import joint_indexing
from hrp2_drake.robot.station import standing_positions

#: Turns of the whole scene (robot and soles), in the world: base quaternions far
#: from the identity, whose rotation matrices' largest diagonal entry is each of the
#: trace, x, y and z (every branch of the matrix-to-quaternion conversion).
TURNS = {
    "upright": RigidTransform(),
    "yawed": RigidTransform(RollPitchYaw(0.3, -0.2, 2.8), [0.5, -1.0, 0.2]),
    "rolled": RigidTransform(RollPitchYaw(2.9, 0.1, 0.2), [0.0, 0.3, 1.0]),
    "pitched": RigidTransform(RollPitchYaw(-0.1, 2.7, 0.0), [-0.4, 0.0, 0.0]),
    "quarter": RigidTransform(RollPitchYaw(0.0, 0.0, 1.5), [0.0, 0.0, 0.0]),
}


@pytest.fixture(scope="module")
def robot():
    return load_robot_description("hrp2")


@pytest.fixture(scope="module")
def hrp2(robot):
    """The plant alone, its standing positions, the joints' indexing, the soles."""
    plant = robot.make_plant()
    return (
        plant,
        standing_positions(robot),
        joint_indexing(plant, robot.joints),
        list(robot.contacts.soles),
    )


@pytest.fixture(scope="module")
def moved(robot, hrp2):
    """The standing positions with the CoM 2 cm to the left and 1 cm forward, the
    soles fixed (the standing IK moves the base and the legs)."""
    plant, standing, _, soles = hrp2
    ik = StandingIk(plant, robot.joints, soles, standing)
    return ik.solve(ik.com(standing) + [0.01, 0.02, 0.0])


def _base(plant):
    return plant.get_body(list(plant.GetFloatingBaseBodies())[0])


def _turned(plant, positions, X=TURNS["yawed"]):
    """`positions` with the base moved by X (in the world): the robot turned."""
    context = plant.CreateDefaultContext()
    plant.SetPositions(context, positions)
    base = _base(plant)
    plant.SetFreeBodyPose(context, base, X @ base.EvalPoseInWorld(context))
    return plant.GetPositions(context)


def _sole_poses(plant, positions, soles):
    context = plant.CreateDefaultContext()
    plant.SetPositions(context, positions)
    return {name: plant.GetFrameByName(name).CalcPoseInWorld(context) for name in soles}


def _sole_jacobians(plant, positions, soles):
    """The soles' stacked spatial-velocity Jacobians (6 rows each, world)."""
    context = plant.CreateDefaultContext()
    plant.SetPositions(context, positions)
    world = plant.world_frame()
    return np.vstack(
        [
            plant.CalcJacobianSpatialVelocity(
                context,
                JacobianWrtVariable.kV,
                plant.GetFrameByName(name),
                np.zeros(3),
                world,
                world,
            )
            for name in soles
        ]
    )


def _still_soles_velocity(plant, positions, soles, seed=0):
    """Velocities (the plant's v) that leave every sole still: the base's and the
    other joints' random (0.2 rad/s or m/s, 0.3 rad/s), the legs' solving the soles'
    rows (the legs' columns of the soles' Jacobians are square and invertible)."""
    J = _sole_jacobians(plant, positions, soles)
    base = np.arange(6) + _base(plant).floating_velocities_start_in_v()
    moves_a_sole = np.any(J != 0.0, axis=0)
    moves_a_sole[base] = False
    legs = np.flatnonzero(moves_a_sole)
    rng = np.random.default_rng(seed)
    v = rng.normal(0.0, 0.3, plant.num_velocities())
    v[base] = rng.normal(0.0, 0.2, 6)
    v[legs] = 0.0
    v[legs] = np.linalg.solve(J[:, legs], -J @ v)
    assert np.abs(J @ v).max() < 1e-12
    return v


def _estimate(hrp2, positions, velocities, poses):
    plant, _, indexing, _ = hrp2
    step = FloatingBaseFromSolesStep(plant, list(indexing.names), poses)
    step.step(0.0, positions[indexing.q], velocities[indexing.v])
    return step


def test_at_the_standing_pose_the_estimate_is_the_plants_positions(hrp2):
    plant, standing, _, soles = hrp2
    nq = plant.num_positions()
    step = _estimate(
        hrp2,
        standing,
        np.zeros(plant.num_velocities()),
        _sole_poses(plant, standing, soles),
    )
    np.testing.assert_allclose(step.robot_state[:nq], standing, rtol=0, atol=1e-12)
    np.testing.assert_allclose(step.robot_state[nq:], 0.0, rtol=0, atol=1e-12)
    assert step.valid[0] == 1.0


@pytest.mark.parametrize("turn", TURNS)
def test_a_motion_that_keeps_the_soles_still_is_estimated_exactly(hrp2, moved, turn):
    """The soles where they stood, the base and legs moved by the standing IK (to
    its 1e-10) and velocities that keep the soles still: the estimated [q; v] is the
    plant's, to 1e-9; the same with the whole scene turned."""
    plant, standing, _, soles = hrp2
    positions = _turned(plant, moved, TURNS[turn])
    poses = _sole_poses(plant, _turned(plant, standing, TURNS[turn]), soles)
    velocities = _still_soles_velocity(plant, positions, soles)
    step = _estimate(hrp2, positions, velocities, poses)
    nq = plant.num_positions()
    base = _base(plant)
    q0, v0 = base.floating_positions_start(), base.floating_velocities_start_in_v()
    assert np.abs(moved[q0 + 4 : q0 + 7] - standing[q0 + 4 : q0 + 7]).max() > 0.01
    assert np.abs(velocities[v0 : v0 + 6]).max() > 0.05
    np.testing.assert_allclose(step.robot_state[:nq], positions, rtol=0, atol=1e-9)
    np.testing.assert_allclose(step.robot_state[nq:], velocities, rtol=0, atol=1e-9)


def test_one_sole_is_enough(hrp2, moved):
    """The right sole alone: the base through the right leg, its velocity from the
    right sole's 6 rows (the left foot may move)."""
    plant, standing, _, _ = hrp2
    positions = _turned(plant, moved)
    poses = _sole_poses(plant, _turned(plant, standing), ["r_sole"])
    velocities = _still_soles_velocity(plant, positions, ["r_sole"], seed=1)
    assert (
        np.abs(_sole_jacobians(plant, positions, ["l_sole"]) @ velocities).max() > 0.01
    )
    step = _estimate(hrp2, positions, velocities, poses)
    np.testing.assert_allclose(
        step.robot_state, np.r_[positions, velocities], rtol=0, atol=1e-9
    )


def test_the_plants_default_base_pose_does_not_enter(robot, hrp2, moved):
    """A plant whose base has a default pose (not the identity) gives the same
    estimate: the step's own context holds its base at the identity."""
    plant, standing, indexing, soles = hrp2
    other = robot.make_plant()
    other.SetDefaultFloatingBaseBodyPose(
        _base(other), RigidTransform(RollPitchYaw(0.1, 0.2, 0.3), [1.0, 2.0, 3.0])
    )
    poses = _sole_poses(plant, standing, soles)
    velocities = _still_soles_velocity(plant, moved, soles)
    q, v = moved[indexing.q], velocities[indexing.v]
    steps = [
        FloatingBaseFromSolesStep(p, list(indexing.names), poses)
        for p in (plant, other)
    ]
    for step in steps:
        step.step(0.0, q, v)
    np.testing.assert_array_equal(steps[1].robot_state, steps[0].robot_state)


def test_soles_that_disagree_give_the_average(hrp2, moved):
    """The left sole given 1 cm off (x) and turned 0.02 rad about its normal: the
    estimate is the mean of the two bases the legs give, X_WB_k = X_WS_k X_BS_k⁻¹:
    positions averaged, rotations at their geodesic midpoint (the normalised sum of
    the two unit quaternions). The left sole's 1 cm moves the base by 5 mm."""
    plant, _, _, soles = hrp2
    poses = _sole_poses(plant, moved, soles)
    offset = RigidTransform(RotationMatrix.MakeZRotation(0.02), [0.0, 0.0, 0.0])
    poses["l_sole"] = RigidTransform([0.01, 0.0, 0.0]) @ poses["l_sole"] @ offset
    step = _estimate(hrp2, moved, np.zeros(plant.num_velocities()), poses)
    context = plant.CreateDefaultContext()
    plant.SetPositions(context, moved)
    base = _base(plant)
    X_WB = [
        poses[name]
        @ plant.GetFrameByName(name).CalcPose(context, base.body_frame()).inverse()
        for name in soles
    ]
    right, left = (X.rotation().ToQuaternion() for X in X_WB)
    midpoint = right.slerp(0.5, left).wxyz()
    translation = 0.5 * (X_WB[0].translation() + X_WB[1].translation())
    q0 = base.floating_positions_start()
    np.testing.assert_allclose(step.robot_state[q0 : q0 + 4], midpoint, atol=1e-12)
    np.testing.assert_allclose(
        step.robot_state[q0 + 4 : q0 + 7], translation, rtol=0, atol=1e-12
    )
    # Without the turn, the 1 cm alone: the base 5 mm off, its rotation the truth.
    poses["l_sole"] = poses["l_sole"] @ offset.inverse()
    step = _estimate(hrp2, moved, np.zeros(plant.num_velocities()), poses)
    np.testing.assert_allclose(
        step.robot_state[q0 : q0 + 7] - moved[q0 : q0 + 7],
        [0, 0, 0, 0, 0.005, 0, 0],
        rtol=0,
        atol=1e-9,
    )


def test_the_velocity_is_the_least_squares_solution_at_the_estimate(hrp2, moved):
    """Joint velocities that do move the soles, soles that disagree: the base's
    velocity is numpy's least-squares solution of J_b v_b = −J_j v_j, the soles'
    Drake Jacobians at the estimated pose (to 1e-12 of its size)."""
    plant, _, indexing, soles = hrp2
    poses = _sole_poses(plant, moved, soles)
    poses["l_sole"] = (
        RigidTransform(RollPitchYaw(0.0, 0.01, 0.03), [0.01, 0.0, 0.0])
        @ (poses["l_sole"])
    )
    velocities = np.random.default_rng(2).normal(0.0, 0.3, plant.num_velocities())
    step = _estimate(hrp2, moved, velocities, poses)
    nq = plant.num_positions()
    J = _sole_jacobians(plant, step.robot_state[:nq], soles)
    base = _base(plant)
    b = np.arange(6) + base.floating_velocities_start_in_v()
    expected = np.linalg.lstsq(
        J[:, b], -J[:, indexing.v] @ velocities[indexing.v], rcond=None
    )[0]
    np.testing.assert_allclose(
        step.robot_state[nq + b], expected, rtol=0, atol=1e-12 * np.abs(expected).max()
    )
    np.testing.assert_array_equal(
        step.robot_state[nq + indexing.v], velocities[indexing.v]
    )


def test_a_non_finite_input_keeps_the_last_estimate(hrp2, moved):
    plant, standing, indexing, soles = hrp2
    step = FloatingBaseFromSolesStep(
        plant, list(indexing.names), _sole_poses(plant, standing, soles)
    )
    q, v = moved[indexing.q], np.zeros(indexing.size)
    bad_q, bad_v = q.copy(), v.copy()
    bad_q[3], bad_v[7] = np.nan, np.inf
    step.step(0.0, bad_q, v)  # before any estimate: the default state, not valid
    assert step.valid[0] == 0.0
    np.testing.assert_array_equal(step.state, step.initial_state())
    step.step(0.0, q, v)
    estimate = step.state.copy()
    for inputs in ((bad_q, v), (q, bad_v)):
        step.step(0.001, *inputs)
        np.testing.assert_array_equal(step.state, estimate)
    assert np.all(np.isfinite(step.state)) and step.valid[0] == 1.0


def test_the_shell_outputs_the_steps_numbers(hrp2, moved):
    plant, standing, indexing, soles = hrp2
    poses = _sole_poses(plant, standing, soles)
    velocities = _still_soles_velocity(plant, moved, soles)
    q, v = moved[indexing.q], velocities[indexing.v]
    system = FloatingBaseFromSoles(plant, list(indexing.names), poses, 0.001)
    context = system.CreateDefaultContext()
    system.GetInputPort("q").FixValue(context, q)
    system.GetInputPort("v").FixValue(context, v)
    context.SetDiscreteState(system.EvalUniquePeriodicDiscreteUpdate(context))
    step = FloatingBaseFromSolesStep(plant, list(indexing.names), poses)
    step.step(0.0, q, v)
    np.testing.assert_allclose(
        system.GetOutputPort("state").Eval(context),
        step.robot_state,
        rtol=0,
        atol=1e-12,
    )


@pytest.mark.parametrize(
    "change, error, message",
    [
        ({"sole_poses": {}}, ValueError, "FloatingBaseFromSoles: no sole poses"),
        (
            {"sole_poses": {"no_sole": RigidTransform()}},
            KeyError,
            "sole frame 'no_sole' is not a frame or body of the plant",
        ),
        (
            {"fixed": True},
            ValueError,
            r"exactly one floating base body, it has none \(a fixed base\)",
        ),
        (
            {"joints": slice(1, None)},
            ValueError,
            r"29 joints given, the plant has 30: .* \(missing \['RLEG_JOINT0'\]\)",
        ),
        ({"joints": ["no_joint"]}, KeyError, "the plant has no joint named 'no_joint'"),
    ],
    ids=["no_sole", "unknown_sole", "fixed_base", "missing_joint", "unknown_joint"],
)
def test_errors_are_one_line_and_name_what_is_wrong(
    robot, hrp2, change, error, message
):
    plant, standing, indexing, soles = hrp2
    if change.get("fixed"):
        plant = robot.make_plant(weld_base=True)
    joints = change.get("joints", slice(None))
    if isinstance(joints, slice):
        joints = list(indexing.names)[joints]
    poses = change.get("sole_poses", _sole_poses(hrp2[0], standing, soles))
    with pytest.raises(error, match=message) as raised:
        FloatingBaseFromSolesStep(plant, joints, poses)
    assert "\n" not in str(raised.value)


def _cases(hrp2, moved):
    """(poses, q, v) of the kernels' tests: the scene turned (every quaternion
    branch), soles that disagree, one sole; velocities that move the soles."""
    plant, standing, indexing, soles = hrp2
    rng = np.random.default_rng(4)
    for turn in TURNS.values():
        positions = _turned(plant, moved, turn)
        poses = _sole_poses(plant, _turned(plant, standing, turn), soles)
        yield poses, positions[indexing.q], rng.normal(0.0, 0.3, indexing.size)
    poses = _sole_poses(plant, standing, soles)
    poses["l_sole"] = (
        RigidTransform(RollPitchYaw(0.02, 0.0, 0.03), [0.0, 0.01, 0.0])
        @ (poses["l_sole"])
    )
    yield poses, moved[indexing.q], rng.normal(0.0, 0.3, indexing.size)
    poses = _sole_poses(plant, standing, ["l_sole"])
    yield poses, moved[indexing.q], rng.normal(0.0, 0.3, indexing.size)


def test_the_compiled_kernels_equal_their_python_source(hrp2, moved):
    """The kernels compiled and as Python (`kernels.interpreted`) on the same
    inputs, without and with the IMU (two ticks): the states equal to 1e-12 of
    their size (loop-order sums both ways)."""
    plant, _, indexing, _ = hrp2
    results = []
    for interpreted in (False, True):
        context = kernels.interpreted() if interpreted else contextlib.nullcontext()
        with context:
            for poses, q, v in _cases(hrp2, moved):
                step = FloatingBaseFromSolesStep(plant, list(indexing.names), poses)
                step.step(0.0, q, v)
                results.append(step.state.copy())
                imu = ImuFusion("imu", [0.01, 0.0, -0.01], 2.0, 0.5)
                step = FloatingBaseFromSolesStep(
                    plant, list(indexing.names), poses, imu, 0.001
                )
                for k, gyro in enumerate(([0.1, 0.2, -0.3], [0.3, -0.1, 0.2])):
                    step.step(0.001 * k, q, v, np.array(gyro))
                results.append(step.state.copy())
    half = len(results) // 2
    for compiled, python in zip(results[:half], results[half:]):
        np.testing.assert_allclose(
            compiled, python, rtol=0, atol=1e-12 * np.abs(python).max()
        )


def test_warm_up_compiles_without_changing_the_state(hrp2, moved):
    """`warm_up` compiles (or loads) both kernels for a tick's arrays, the state
    untouched; frozen, ticks of both shells run and float32 inputs raise instead of
    compiling."""
    plant, standing, indexing, soles = hrp2
    poses = _sole_poses(plant, standing, soles)
    imu = ImuFusion("imu", gain=0.0)
    step = FloatingBaseFromSolesStep(plant, list(indexing.names), poses, imu, 0.001)
    q, v, gyro = moved[indexing.q], np.zeros(indexing.size), np.zeros(3)
    step.step(0.0, q, v, gyro)
    before = step.state.copy()
    step.warm_up()
    np.testing.assert_array_equal(step.state, before)
    if kernels.jit_enabled():
        # The tick's kernels (the quaternion helpers are compiled into them).
        ticks = {"base_joint_positions", "base_from_soles", "base_imu_fusion"}
        mine = [
            k
            for k in kernels.kernels()
            if k.py_func.__module__ == base_kinematics.__name__
            and k.py_func.__name__ in ticks
        ]
        assert len(mine) == 3 and all(k.signatures for k in mine)
    system = FloatingBaseFromSoles(plant, list(indexing.names), poses, 0.001, imu=imu)
    context = system.CreateDefaultContext()
    system.GetInputPort("q").FixValue(context, q)
    system.GetInputPort("v").FixValue(context, v)
    system.GetInputPort("gyro").FixValue(context, gyro)
    try:
        kernels.freeze()
        step.step(0.001, q, v, gyro)
        np.testing.assert_array_equal(step.state, before)
        context.SetDiscreteState(system.EvalUniquePeriodicDiscreteUpdate(context))
        np.testing.assert_array_equal(
            system.GetOutputPort("state").Eval(context), step.robot_state
        )
        if kernels.jit_enabled():
            with pytest.raises(TypeError):
                step.step(0.002, q.astype(np.float32), v, gyro)
    finally:
        kernels.thaw()


def test_one_floating_base_lookup_names_the_caller():
    """multibody.floating_base: none (a fixed base) or two, one line naming the
    caller; one, that body."""
    from pydrake.multibody.plant import MultibodyPlant
    from pydrake.multibody.tree import SpatialInertia

    from hrp2_drake.multibody import floating_base

    def plant(welded: bool, bodies: int) -> MultibodyPlant:
        plant = MultibodyPlant(0.0)
        for k in range(bodies):
            inertia = SpatialInertia.SolidBoxWithMass(1, 1, 1, 1)
            body = plant.AddRigidBody(f"box{k}", inertia)
        if welded:
            plant.WeldFrames(plant.world_frame(), body.body_frame())
        plant.Finalize()
        return plant

    with pytest.raises(ValueError, match=r"^X: .*exactly one .* none \(a fixed base"):
        floating_base(plant(True, 1), "X")
    with pytest.raises(ValueError, match=r"^X: .* \['box0', 'box1'\]: do Y$"):
        floating_base(plant(False, 2), "X", advice="do Y")
    assert floating_base(plant(False, 1), "X", quaternion=True).name() == "box0"


# With an IMU (ImuFusion): the gyro's rate integrated, corrected toward the soles.


def _gyro(plant, positions, velocities):
    """What a noiseless gyro on HRP-2's IMU frame reads (rad/s, its frame)."""
    context = plant.CreateDefaultContext()
    plant.SetPositions(context, positions)
    plant.SetVelocities(context, velocities)
    frame = plant.GetFrameByName("imu")
    R_WI = frame.CalcPoseInWorld(context).rotation()
    return R_WI.inverse() @ frame.CalcSpatialVelocityInWorld(context).rotational()


def _imu_step(hrp2, poses, **fusion):
    plant, _, indexing, _ = hrp2
    imu = ImuFusion("imu", **fusion)
    return FloatingBaseFromSolesStep(plant, list(indexing.names), poses, imu, 0.001)


@pytest.mark.parametrize("turn", ["upright", "rolled"])
def test_with_the_gyro_a_still_soles_motion_is_estimated_exactly(hrp2, moved, turn):
    """The first tick starts from the soles' kinematics: with the gyro's reading of
    the same motion the estimated [q; v] is the plant's, to 1e-9."""
    plant, standing, indexing, soles = hrp2
    positions = _turned(plant, moved, TURNS[turn])
    poses = _sole_poses(plant, _turned(plant, standing, TURNS[turn]), soles)
    velocities = _still_soles_velocity(plant, positions, soles)
    step = _imu_step(hrp2, poses)
    gyro = _gyro(plant, positions, velocities)
    step.step(0.0, positions[indexing.q], velocities[indexing.v], gyro)
    nq = plant.num_positions()
    np.testing.assert_allclose(step.robot_state[:nq], positions, rtol=0, atol=1e-9)
    np.testing.assert_allclose(step.robot_state[nq:], velocities, rtol=0, atol=1e-9)


def _base_rotation(plant, state):
    q0 = _base(plant).floating_positions_start()
    w, x, y, z = state[q0 : q0 + 4]
    return RotationMatrix(Quaternion(w, x, y, z))


def test_without_correction_the_orientation_is_the_gyros_integral(hrp2, moved):
    """Gain 0, the joints still: the base turns by the gyro's constant rate,
    R_WB(t) = R_WB(0) R_BI exp(ω t) R_BIᵀ, to 1e-12 after 500 ticks; its velocity
    stays the soles' (zero: the joints are still)."""
    plant, standing, indexing, soles = hrp2
    poses = _sole_poses(plant, standing, soles)
    step = _imu_step(hrp2, poses, gain=0.0)
    q, v = moved[indexing.q], np.zeros(indexing.size)
    omega = np.array([0.2, -0.1, 0.05])
    step.step(0.0, q, v, np.zeros(3))
    R0 = _base_rotation(plant, step.robot_state)
    for k in range(500):
        step.step(0.001 * (k + 1), q, v, omega)
    context = plant.CreateDefaultContext()
    plant.SetPositions(context, moved)
    R_BI = plant.CalcRelativeTransform(
        context, _base(plant).body_frame(), plant.GetFrameByName("imu")
    ).rotation()
    turned = RotationMatrix(
        AngleAxis(0.5 * np.linalg.norm(omega), omega / np.linalg.norm(omega))
    )
    expected = R0 @ R_BI @ turned @ R_BI.inverse()
    R = _base_rotation(plant, step.robot_state)
    assert np.abs(R.matrix() - expected.matrix()).max() < 1e-12
    v0 = plant.num_positions() + _base(plant).floating_velocities_start_in_v()
    np.testing.assert_array_equal(step.robot_state[v0 : v0 + 6], 0.0)


def _angle_to_kinematics(plant, step, kinematic):
    R = _base_rotation(plant, step.robot_state)
    return (R.inverse() @ kinematic).ToAngleAxis().angle()


def test_the_correction_returns_to_the_soles_at_the_gain(hrp2, moved):
    """A still robot, a gyro that reads zero: an attitude 10 mrad off the soles'
    returns at the gain (1/s): after 1 s of gain 2, exp(−2) of it (to 1 %)."""
    plant, standing, indexing, soles = hrp2
    poses = _sole_poses(plant, standing, soles)
    step = _imu_step(hrp2, poses, gain=2.0)
    q, v, zero = moved[indexing.q], np.zeros(indexing.size), np.zeros(3)
    step.step(0.0, q, v, zero)
    kinematic = _base_rotation(plant, step.robot_state)
    off = RotationMatrix(AngleAxis(0.01, [0.6, 0.8, 0.0]))
    R_WI = off @ RotationMatrix(Quaternion(*step.attitude[:4]))
    step.attitude[:4] = R_WI.ToQuaternion().wxyz()
    for k in range(1000):
        step.step(0.001 * (k + 1), q, v, zero)
    angle = _angle_to_kinematics(plant, step, kinematic)
    assert angle == pytest.approx(0.01 * np.exp(-2.0), rel=0.01)


def test_the_bias_is_learnt_and_a_bad_gyro_reading_is_skipped(hrp2, moved):
    """A still robot whose gyro reads a constant bias b beyond its given offset:
    with a bias gain the estimate learns b (to 1e-5 rad/s after 30 s) and the
    attitude returns to the soles'; a NaN reading leaves the attitude as it was and
    the tick's estimate the soles' kinematics."""
    plant, standing, indexing, soles = hrp2
    poses = _sole_poses(plant, standing, soles)
    offset = [0.001, 0.0, -0.002]
    step = _imu_step(hrp2, poses, gain=1.0, bias_gain=0.5, gyro_offset=offset)
    q, v = moved[indexing.q], np.zeros(indexing.size)
    b = np.array([0.003, -0.002, 0.001])
    reading = b + offset
    for k in range(30000):
        step.step(0.001 * k, q, v, reading)
    np.testing.assert_allclose(step.attitude[4:], b, rtol=0, atol=1e-5)
    kinematic = _estimate(hrp2, moved, np.zeros(plant.num_velocities()), poses)
    R_kin = _base_rotation(plant, kinematic.robot_state)
    assert _angle_to_kinematics(plant, step, R_kin) < 1e-5
    attitude = step.attitude.copy()
    step.step(30.0, q, v, np.array([np.nan, 0.0, 0.0]))
    np.testing.assert_array_equal(step.attitude, attitude)
    np.testing.assert_array_equal(step.robot_state, kinematic.robot_state)


@pytest.mark.parametrize(
    "fusion, period, message",
    [
        ({"gyro_offset": [0.0, 0.0]}, 0.001, r"ImuFusion.gyro_offset: three finite"),
        ({"gain": -1.0}, 0.001, r"ImuFusion.gain must be >= 0, got -1.0"),
        ({"bias_gain": np.nan}, 0.001, r"ImuFusion.bias_gain must be a finite number"),
        ({}, 0.0, r"ImuFusion: the period must be finite and > 0 \(s\), got 0.0"),
    ],
    ids=["offset", "gain", "bias_gain", "period"],
)
def test_imu_errors_are_one_line(hrp2, fusion, period, message):
    plant, standing, indexing, soles = hrp2
    poses = _sole_poses(plant, standing, soles)
    with pytest.raises(ValueError, match=message) as raised:
        FloatingBaseFromSolesStep(
            plant, list(indexing.names), poses, ImuFusion("imu", **fusion), period
        )
    assert "\n" not in str(raised.value)
    with pytest.raises(KeyError, match="IMU frame 'no_imu'"):
        FloatingBaseFromSolesStep(
            plant, list(indexing.names), poses, ImuFusion("no_imu"), 0.001
        )
