"""InverseDynamicsController (paper eq. 12) and make_fixed_base_plant.

Reference values are computed another way: M, h and J from CalcMassMatrix,
CalcBiasTerm, CalcGravityGeneralizedForces and a world-frame Jacobian rotated into the
force frame, on a separate context; Drake's CalcInverseDynamics with gravity; and the
continuous plant's forward dynamics with the contact wrench applied as an external
force (which checks the sign and frame of f).
"""

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from pydrake.multibody.math import SpatialForce
from pydrake.multibody.plant import ExternallyAppliedSpatialForce, MultibodyPlant
from pydrake.multibody.tree import JacobianWrtVariable, MultibodyForces
from ticks import commit

from hrp2_drake import kernels
from hrp2_drake.config import load_config
from hrp2_drake.control import inverse_dynamics
from hrp2_drake.control.inverse_dynamics import (
    TORQUE_COMPONENTS,
    InverseDynamicsConfig,
    InverseDynamicsController,
    InverseDynamicsControllerStep,
    make_fixed_base_plant,
)
from hrp2_drake.multibody import joint_indexing
from hrp2_drake.paper import hrp2

kV = JacobianWrtVariable.kV
LEG = list(hrp2.RIGHT_LEG)
FOOT = hrp2.FT_SENSOR_BODIES["right_foot"]  # RLEG_FOOT: its frame is the F/T frame
KS = np.array([3000.0, 2500.0, 2000.0, 1500.0, 1000.0, 800.0])
KD = np.array([30.0, 25.0, 20.0, 15.0, 10.0, 8.0])
KF = np.array([0.5, 0.6, 0.7, 0.8, 0.9, 1.0])
PERIOD = 0.001  # s, the control period


@pytest.fixture(scope="module")
def fixed_plant() -> MultibodyPlant:
    return make_fixed_base_plant(hrp2.add_hrp2, hrp2.BASE_BODY)


@pytest.fixture(scope="module")
def floating_plant() -> MultibodyPlant:
    plant = MultibodyPlant(0.0)
    hrp2.add_hrp2(plant)
    plant.Finalize()
    return plant


def _config(**changes) -> InverseDynamicsConfig:
    values = dict(
        joints=LEG,
        ks=KS.tolist(),
        kd=KD.tolist(),
        force_frame=FOOT,
        kf=KF.tolist(),
        period=PERIOD,
    )
    values.update(changes)
    return InverseDynamicsConfig(**values)


def _nominal(plant: MultibodyPlant) -> np.ndarray:
    """The plant's positions at half-sitting."""
    q = plant.GetPositions(plant.CreateDefaultContext()).copy()
    q[joint_indexing(plant, hrp2.JOINT_NAMES).q] = hrp2.half_sitting()
    return q


def _inputs(seed: int, force: bool = True) -> dict:
    rng = np.random.default_rng(seed)
    q0 = hrp2.half_sitting()[:6]
    out = dict(
        q_ref=q0 + 0.1 * rng.standard_normal(6),
        v_ref=rng.standard_normal(6),
        vdot_ref=5.0 * rng.standard_normal(6),
        q=q0 + 0.1 * rng.standard_normal(6),
        v=rng.standard_normal(6),
    )
    if force:
        out["f_ref"] = np.array(
            [2.0, -3.0, 1.0, 10.0, -20.0, 300.0]
        ) + rng.standard_normal(6)
        out["f"] = np.array([1.0, -2.0, 0.5, 5.0, -10.0, 280.0]) + rng.standard_normal(
            6
        )
    return out


def _step(controller: InverseDynamicsController, inputs: dict) -> dict:
    """Every output of the first tick, with the inputs fixed (its sample)."""
    context = controller.CreateDefaultContext()
    for name, value in inputs.items():
        controller.GetInputPort(name).FixValue(context, value)
    names = ("tau_desired", *TORQUE_COMPONENTS)
    return {name: controller.GetOutputPort(name).Eval(context).copy() for name in names}


def _reference(plant, q_full, inputs, ks, kd, kf, base=None) -> dict:
    """Eq. 12 from CalcMassMatrix, CalcBiasTerm, CalcGravityGeneralizedForces and J."""
    ix = joint_indexing(plant, LEG)
    context = plant.CreateDefaultContext()
    q_full = q_full.copy()
    q_full[ix.q] = inputs["q"]
    plant.SetPositions(context, q_full)
    v_full = np.zeros(plant.num_velocities())
    v_full[ix.v] = inputs["v"]
    plant.SetVelocities(context, v_full)
    if base is not None:
        body, X_WB, w_WB_W = base
        plant.SetFreeBodyPose(context, body, X_WB)
        v_full[body.floating_velocities_start_in_v() + np.arange(3)] = w_WB_W
        plant.SetVelocities(context, v_full)
    M = plant.CalcMassMatrix(context)[np.ix_(ix.v, ix.v)]
    h = (plant.CalcBiasTerm(context) - plant.CalcGravityGeneralizedForces(context))[
        ix.v
    ]
    frame = plant.GetFrameByName(FOOT)
    J_W = plant.CalcJacobianSpatialVelocity(
        context, kV, frame, np.zeros(3), plant.world_frame(), plant.world_frame()
    )[:, ix.v]
    R_FW = frame.CalcRotationMatrixInWorld(context).inverse().matrix()
    J = np.vstack([R_FW @ J_W[:3], R_FW @ J_W[3:]])  # expressed in the force frame
    e_q = inputs["q_ref"] - inputs["q"]
    de_q = inputs["v_ref"] - inputs["v"]
    f_ref = inputs.get("f_ref", np.zeros(6))
    e_f = f_ref - inputs.get("f", np.zeros(6))
    f_star = f_ref + kf * e_f
    tau = M @ inputs["vdot_ref"] + h - J.T @ f_star + ks * e_q + kd * de_q
    return dict(tau=tau, M=M, h=h, J=J, e_f=e_f)


@pytest.mark.parametrize("seed", range(3))
def test_matches_independent_computation(fixed_plant, seed):
    nominal = _nominal(fixed_plant)
    controller = InverseDynamicsController(fixed_plant, _config(), nominal)
    inputs = _inputs(seed)
    out = _step(controller, inputs)
    ref = _reference(fixed_plant, nominal, inputs, KS, KD, KF)
    scale = 1.0 + np.max(np.abs(ref["tau"]))
    assert np.max(np.abs(out["tau_desired"] - ref["tau"])) < 1e-10 * scale

    # The terms, each against its definition, and their sum.
    J, e_f = ref["J"], ref["e_f"]
    feedforward = ref["M"] @ inputs["vdot_ref"] + ref["h"] - J.T @ inputs["f_ref"]
    np.testing.assert_allclose(out["tau_feedforward"], feedforward, atol=1e-9 * scale)
    np.testing.assert_allclose(
        out["tau_position_feedback"], KS * (inputs["q_ref"] - inputs["q"]), rtol=1e-14
    )
    np.testing.assert_allclose(
        out["tau_velocity_feedback"], KD * (inputs["v_ref"] - inputs["v"]), rtol=1e-14
    )
    np.testing.assert_allclose(out["tau_force_feedback"], -J.T @ (KF * e_f), atol=1e-10)
    np.testing.assert_allclose(out["tau_force_error"], -J.T @ e_f, atol=1e-10)
    total = sum(out[name] for name in TORQUE_COMPONENTS[:4])
    np.testing.assert_allclose(total, out["tau_desired"], atol=1e-12 * scale)

    # The same numbers without a Context.
    terms = controller.compute(**inputs)
    np.testing.assert_allclose(terms.tau_desired, out["tau_desired"], rtol=1e-14)
    model_j = controller.joint_space_model(inputs["q"], inputs["v"])
    np.testing.assert_allclose(model_j.mass_matrix, ref["M"], rtol=1e-12)
    np.testing.assert_allclose(model_j.bias, ref["h"], atol=1e-10)
    np.testing.assert_allclose(model_j.jacobian, J, atol=1e-12)


def test_zero_errors_equals_drake_inverse_dynamics(fixed_plant):
    """No force task, q = q_ref, v = v_ref: τ_d is Drake's inverse dynamics with
    gravity (CalcForceElementsContribution), rotor inertia included."""
    nominal = _nominal(fixed_plant)
    controller = InverseDynamicsController(
        fixed_plant, _config(force_frame=""), nominal
    )
    inputs = _inputs(7, force=False)
    inputs["q_ref"] = inputs["q"]
    inputs["v_ref"] = inputs["v"]
    out = _step(controller, inputs)

    ix = joint_indexing(fixed_plant, LEG)
    context = fixed_plant.CreateDefaultContext()
    q_full = nominal.copy()
    q_full[ix.q] = inputs["q"]
    fixed_plant.SetPositions(context, q_full)
    v_full = np.zeros(fixed_plant.num_velocities())
    v_full[ix.v] = inputs["v"]
    fixed_plant.SetVelocities(context, v_full)
    vdot = np.zeros(fixed_plant.num_velocities())
    vdot[ix.v] = inputs["vdot_ref"]
    forces = MultibodyForces(fixed_plant)
    fixed_plant.CalcForceElementsContribution(context, forces)
    expected = fixed_plant.CalcInverseDynamics(context, vdot, forces)[ix.v]
    np.testing.assert_allclose(out["tau_desired"], expected, rtol=1e-12, atol=1e-10)
    np.testing.assert_allclose(out["tau_feedforward"], expected, rtol=1e-12, atol=1e-10)
    for name in TORQUE_COMPONENTS[1:]:
        assert not np.any(out[name])
    assert controller.num_input_ports() == 5  # no f_ref, f without a force task

    # The reflected rotor inertia ρ² I_r is in M_j (the actuators carry it).
    M = controller.joint_space_model(inputs["q"]).mass_matrix
    rotor = np.array(
        [
            fixed_plant.get_joint_actuator(a).default_rotor_inertia()
            * fixed_plant.get_joint_actuator(a).default_gear_ratio() ** 2
            for a in fixed_plant.GetJointActuatorIndices()
        ]
    )[ix.u]
    assert np.all(rotor > 0) and np.all(np.diag(M) > rotor)


def test_force_sign_and_frame_by_forward_dynamics(fixed_plant):
    """Apply τ_d to the continuous plant together with the wrench f (environment on
    the foot, about the F/T sensor origin, in the sensor frame) as an external force:
    the leg accelerates at q̈_d exactly when the controller's errors are zero (f = f*),
    which fixes the sign of −J_jᵀ f and the frame of J_j."""
    nominal = _nominal(fixed_plant)
    controller = InverseDynamicsController(fixed_plant, _config(), nominal)
    inputs = _inputs(3)
    inputs["q_ref"], inputs["v_ref"] = inputs["q"], inputs["v"]
    inputs["f"] = inputs["f_ref"]  # e_f = 0: f* = f
    tau = _step(controller, inputs)["tau_desired"]

    plant = fixed_plant
    ix = joint_indexing(plant, LEG)
    context = plant.CreateDefaultContext()
    q_full = nominal.copy()
    q_full[ix.q] = inputs["q"]
    plant.SetPositions(context, q_full)
    v_full = np.zeros(plant.num_velocities())
    v_full[ix.v] = inputs["v"]
    plant.SetVelocities(context, v_full)
    u = np.zeros(plant.num_actuated_dofs())
    u[ix.u] = tau
    plant.get_actuation_input_port().FixValue(context, u)
    frame = plant.GetFrameByName(FOOT)
    R_WF = frame.CalcRotationMatrixInWorld(context).matrix()
    force = ExternallyAppliedSpatialForce()
    force.body_index = frame.body().index()
    force.p_BoBq_B = frame.GetFixedPoseInBodyFrame().translation()
    f = inputs["f"]
    force.F_Bq_W = SpatialForce(R_WF @ f[:3], R_WF @ f[3:])
    plant.get_applied_spatial_force_input_port().FixValue(context, [force])
    vdot = plant.get_generalized_acceleration_output_port().Eval(context)
    np.testing.assert_allclose(vdot[ix.v], inputs["vdot_ref"], atol=1e-7)


def test_floating_base_option(fixed_plant, floating_plant):
    nominal = _nominal(floating_plant)
    floating = InverseDynamicsController(
        floating_plant, _config(floating_base=True), nominal
    )
    assert floating.GetInputPort("base_orientation").size() == 4
    inputs = _inputs(11)

    # Base upright and still (ports unconnected): the fixed-base model's τ_d.
    fixed = InverseDynamicsController(fixed_plant, _config(), _nominal(fixed_plant))
    np.testing.assert_allclose(
        _step(floating, inputs)["tau_desired"],
        _step(fixed, inputs)["tau_desired"],
        rtol=1e-12,
        atol=1e-9,
    )

    # Tilted, rotating base: the joint rows of the floating model (zero base
    # acceleration), and, without rotation, the model welded at that tilt.
    R_WB = RotationMatrix(RollPitchYaw(0.3, -0.2, 0.5))
    w_B = np.array([0.4, -0.3, 0.2])
    tilted = dict(
        inputs,
        base_orientation=R_WB.ToQuaternion().wxyz(),
        base_angular_velocity=w_B,
    )
    out = _step(floating, tilted)
    base = floating_plant.GetBodyByName(hrp2.BASE_BODY)
    ref = _reference(
        floating_plant,
        nominal,
        inputs,
        KS,
        KD,
        KF,
        base=(base, RigidTransform(R_WB, [0.0, 0.0, 0.0]), R_WB @ w_B),
    )
    np.testing.assert_allclose(out["tau_desired"], ref["tau"], rtol=1e-10, atol=1e-8)

    welded = make_fixed_base_plant(
        hrp2.add_hrp2, hrp2.BASE_BODY, RigidTransform(R_WB, [0.0, 0.0, 1.0])
    )
    still = dict(tilted, base_angular_velocity=np.zeros(3))
    np.testing.assert_allclose(
        _step(floating, still)["tau_desired"],
        _step(InverseDynamicsController(welded, _config(), _nominal(welded)), inputs)[
            "tau_desired"
        ],
        rtol=1e-10,
        atol=1e-8,
    )


def test_outputs_are_this_ticks(fixed_plant):
    """One tick from sample to command: the outputs are eq. 12 on the inputs as they
    are now (direct feedthrough from every input), before any update; the commit at
    the next sampling instant stores that tick as the state, whatever the inputs do
    afterwards, and the outputs follow the new inputs at once."""
    controller = InverseDynamicsController(fixed_plant, _config())
    for i in range(controller.num_input_ports()):
        for j in range(controller.num_output_ports()):
            assert controller.HasDirectFeedthrough(i, j)
    timing = controller.GetUniquePeriodicDiscreteUpdateAttribute()
    assert (timing.period_sec(), timing.offset_sec()) == (0.001, 0.0)

    context = controller.CreateDefaultContext()
    group = controller.step_group("tau_desired")
    first, second = _inputs(0), _inputs(1)
    expected = [_step(controller, inputs)["tau_desired"] for inputs in (first, second)]
    assert np.all(np.abs(expected[0] - expected[1]) > 1e-6)
    for name, value in first.items():
        controller.GetInputPort(name).FixValue(context, value)
    tau = controller.GetOutputPort("tau_desired")

    def committed():
        return context.get_discrete_state(group).get_value()

    np.testing.assert_array_equal(tau.Eval(context), expected[0])
    assert not np.any(committed())  # no update yet
    commit(controller, context, 0.001)
    np.testing.assert_array_equal(committed(), expected[0])
    for name, value in second.items():
        controller.GetInputPort(name).FixValue(context, value)
    np.testing.assert_array_equal(tau.Eval(context), expected[1])
    np.testing.assert_array_equal(committed(), expected[0])


def test_config_from_yaml():
    # The period is the code's (the control period), never the file's.
    defaults = InverseDynamicsConfig(period=PERIOD)
    config = load_config(
        InverseDynamicsConfig,
        data=f"joints: {LEG}\nks: [1000.0]\nkd: [1, 2, 3, 4, 5, 6]\n"
        f"force_frame: {FOOT}\nkf: [1.0]\n",
        defaults=defaults,
    )
    assert config.kd == [1, 2, 3, 4, 5, 6] and config.ks == [1000.0]
    with pytest.raises(ValueError, match="unknown key"):
        load_config(
            InverseDynamicsConfig,
            data=f"joints: {LEG}\nkss: [1.0]\n",
            defaults=defaults,
        )
    with pytest.raises(ValueError, match="kd"):
        load_config(
            InverseDynamicsConfig,
            data=f"joints: {LEG}\nkd: [1.0, 2.0]\n",
            defaults=defaults,
        )


def test_bad_inputs(fixed_plant, floating_plant):
    with pytest.raises(ValueError, match="ks"):
        InverseDynamicsController(fixed_plant, _config(ks=[1.0, 2.0]))
    with pytest.raises(ValueError, match="kf"):
        InverseDynamicsController(fixed_plant, _config(kf=[1.0] * 5))
    with pytest.raises(ValueError, match="kd"):
        InverseDynamicsController(fixed_plant, _config(kd=-1.0))
    with pytest.raises(ValueError, match="joints is empty"):
        InverseDynamicsController(fixed_plant, _config(joints=[]))
    with pytest.raises(KeyError, match="NO_SUCH_JOINT"):
        InverseDynamicsController(
            fixed_plant, _config(joints=LEG[:5] + ["NO_SUCH_JOINT"])
        )
    with pytest.raises(KeyError, match="no_such_frame"):
        InverseDynamicsController(fixed_plant, _config(force_frame="no_such_frame"))
    with pytest.raises(ValueError, match="fixed-base"):
        InverseDynamicsController(floating_plant, _config())
    with pytest.raises(ValueError, match="floating base"):
        InverseDynamicsController(fixed_plant, _config(floating_base=True))
    with pytest.raises(ValueError, match="nominal_positions"):
        InverseDynamicsController(fixed_plant, _config(), np.zeros(3))
    with pytest.raises(KeyError, match="NOPE"):
        make_fixed_base_plant(hrp2.add_hrp2, "NOPE")

    controller = InverseDynamicsController(fixed_plant, _config())
    inputs = _inputs(0)
    inputs["v"] = inputs["v"].copy()
    inputs["v"][2] = np.nan
    # A bad sample never raises in the loop: NaN in, NaN out (the Δq controller then
    # falls back to position control).
    outputs = _step(controller, inputs)
    assert all(np.all(np.isnan(value)) for value in outputs.values())
    with pytest.raises(ValueError, match="f_ref"):
        controller.compute(**dict(_inputs(0), f_ref=np.full(6, np.inf)))
    with pytest.raises(ValueError, match="floating_base"):
        controller.compute(**_inputs(0), base_orientation=[1.0, 0.0, 0.0, 0.0])
    motion_only = InverseDynamicsController(fixed_plant, _config(force_frame=""))
    with pytest.raises(ValueError, match="force_frame"):
        motion_only.compute(**_inputs(0))


# --------------------------------------------------------------------- the step


def test_step_equals_controller(fixed_plant):
    """InverseDynamicsControllerStep driven by plain arrays (no systems Context) gives
    the controller's outputs bit for bit, and eq. 12's numbers."""
    nominal = _nominal(fixed_plant)
    controller = InverseDynamicsController(fixed_plant, _config(), nominal)
    step = InverseDynamicsControllerStep(fixed_plant, _config(), nominal)
    names = ("tau_desired", *TORQUE_COMPONENTS)
    assert [name for name, _ in step.layout()] == list(names)
    assert step.state_size == 6 * 6 and not np.any(step.state)
    for seed in (0, 1):
        inputs = _inputs(seed)
        assert step.step(0.001 * seed, **inputs) is False
        out = _step(controller, inputs)
        for row, name in enumerate(names):
            np.testing.assert_array_equal(getattr(step, name), out[name])
            np.testing.assert_array_equal(step.outputs[row], out[name])
        np.testing.assert_array_equal(step.terms, step.outputs[1:])
    ref = _reference(fixed_plant, nominal, inputs, KS, KD, KF)
    np.testing.assert_allclose(step.tau_desired, ref["tau"], rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(
        step.tau_position_feedback, KS * (inputs["q_ref"] - inputs["q"]), rtol=1e-14
    )

    # compute() leaves the state alone and gives the same numbers.
    before = step.state.copy()
    terms = step.compute(**_inputs(5))
    np.testing.assert_array_equal(step.state, before)
    step.step(0.0, **_inputs(5))
    np.testing.assert_array_equal(terms.tau_desired, step.tau_desired)
    np.testing.assert_array_equal(terms.force_error, step.tau_force_error)

    # NaN in, NaN out, reported once (True) while the outputs were finite.
    bad = dict(_inputs(2), f=np.full(6, np.nan))
    assert step.step(0.0, **bad) is True
    assert np.all(np.isnan(step.state))
    assert step.step(0.0, **bad) is False
    step.step(0.0, **_inputs(2))
    assert np.all(np.isfinite(step.state))

    # Bound to a slice of a larger buffer (a fused controller's state): the named
    # arrays and the views follow.
    buffer = np.zeros(step.state_size + 3)
    step.bind(buffer[3:])
    step.step(0.0, **_inputs(0))
    np.testing.assert_array_equal(
        buffer[3:9], _step(controller, _inputs(0))["tau_desired"]
    )
    assert np.shares_memory(step.terms, buffer) and np.shares_memory(
        step.outputs, buffer
    )


def test_step_without_force_task(fixed_plant):
    """No force task: f_ref, f are ignored; the force terms are zero."""
    nominal = _nominal(fixed_plant)
    config = _config(force_frame="")
    step = InverseDynamicsControllerStep(fixed_plant, config, nominal)
    controller = InverseDynamicsController(fixed_plant, config, nominal)
    inputs = _inputs(4, force=False)
    assert not step.has_force_task()
    step.step(0.0, **inputs)
    out = _step(controller, inputs)
    np.testing.assert_array_equal(step.tau_desired, out["tau_desired"])
    np.testing.assert_array_equal(step.tau_feedforward, out["tau_feedforward"])
    assert not np.any(step.tau_force_feedback) and not np.any(step.tau_force_error)
    np.testing.assert_array_equal(
        step.tau_desired,
        step.tau_feedforward + step.tau_position_feedback + step.tau_velocity_feedback,
    )


def test_step_floating_base(floating_plant):
    nominal = _nominal(floating_plant)
    config = _config(floating_base=True)
    step = InverseDynamicsControllerStep(floating_plant, config, nominal)
    controller = InverseDynamicsController(floating_plant, config, nominal)
    R_WB = RotationMatrix(RollPitchYaw(0.2, -0.1, 0.4))
    inputs = dict(
        _inputs(6),
        base_orientation=R_WB.ToQuaternion().wxyz(),
        base_angular_velocity=np.array([0.3, -0.2, 0.1]),
    )
    step.step(0.0, **inputs)
    np.testing.assert_array_equal(
        step.tau_desired, _step(controller, inputs)["tau_desired"]
    )
    with pytest.raises(ValueError, match="base_angular_velocity"):
        step.step(0.0, **dict(inputs, base_angular_velocity=np.full(3, np.nan)))


def _id_steps(fixed_plant, floating_plant):
    """Steps of every kernel branch: fixed base with and without the force task (the
    leg's part model), floating base with the force task; and their inputs."""
    R_WB = RotationMatrix(RollPitchYaw(0.2, -0.1, 0.4))
    base = dict(
        base_orientation=1.02 * R_WB.ToQuaternion().wxyz(),  # normalized in the step
        base_angular_velocity=np.array([0.3, -0.2, 0.1]),
    )
    return [
        (
            lambda: InverseDynamicsControllerStep(
                fixed_plant, _config(), _nominal(fixed_plant)
            ),
            _inputs(20),
        ),
        (
            lambda: InverseDynamicsControllerStep(
                fixed_plant, _config(force_frame=""), _nominal(fixed_plant)
            ),
            _inputs(21, force=False),
        ),
        (
            lambda: InverseDynamicsControllerStep(
                floating_plant, _config(floating_base=True), _nominal(floating_plant)
            ),
            dict(_inputs(22), **base),
        ),
    ]


def test_step_kernels_compiled_equal_interpreted(fixed_plant, floating_plant):
    """The numba kernels give their Python source's numbers to the bit (eq. 12, the
    floating base's pose, the NaN event)."""
    for make, inputs in _id_steps(fixed_plant, floating_plant):
        compiled, interpreted = make(), make()
        assert compiled.step(0.0, **inputs) is False
        with kernels.interpreted():
            assert interpreted.step(0.0, **inputs) is False
        np.testing.assert_array_equal(compiled.state, interpreted.state)
        assert np.all(np.isfinite(compiled.state)) and np.any(compiled.state != 0.0)
        bad = dict(inputs, q=np.full(6, np.nan))
        assert compiled.step(0.0, **bad) is True
        with kernels.interpreted():
            assert interpreted.step(0.0, **bad) is True
        assert np.all(np.isnan(compiled.state)) and np.all(np.isnan(interpreted.state))


def test_step_gravity_as_the_roots_acceleration(fixed_plant):
    """The part model's root accelerates upward (−g) instead of gravity's forces
    (CalcForceElementsContribution, one Drake call less): τ_d is the plant's own
    inverse dynamics with gravity, to rounding."""
    nominal = _nominal(fixed_plant)
    step = InverseDynamicsControllerStep(fixed_plant, _config(force_frame=""), nominal)
    ix = joint_indexing(fixed_plant, LEG)
    context = fixed_plant.CreateDefaultContext()
    forces = MultibodyForces(fixed_plant)
    for seed in range(3):
        inputs = _inputs(30 + seed, force=False)
        step.step(0.0, **inputs)
        q_full = nominal.copy()
        q_full[ix.q] = inputs["q"]
        v_full = np.zeros(fixed_plant.num_velocities())
        v_full[ix.v] = inputs["v"]
        fixed_plant.SetPositions(context, q_full)
        fixed_plant.SetVelocities(context, v_full)
        vdot = np.zeros(fixed_plant.num_velocities())
        vdot[ix.v] = inputs["vdot_ref"]
        fixed_plant.CalcForceElementsContribution(context, forces)
        forces.mutable_generalized_forces()[:] = 0.0  # joint damping: not in ĥ_j
        expected = fixed_plant.CalcInverseDynamics(context, vdot, forces)[ix.v]
        scale = np.abs(expected).max()
        np.testing.assert_allclose(
            step.tau_feedforward, expected, rtol=0, atol=1e-13 * scale
        )


def test_step_warm_up_then_no_compiling(fixed_plant, floating_plant):
    """`warm_up` compiles (or loads) the kernels for a tick's arrays without changing
    the state; frozen, real ticks run and a kernel called with float32 arrays raises
    instead of compiling."""
    for make, inputs in _id_steps(fixed_plant, floating_plant):
        step = make()
        step.step(0.0, **inputs)
        before = step.state.copy()
        step.warm_up()
        np.testing.assert_array_equal(step.state, before)
        kernels.freeze()
        try:
            step.step(0.001, **inputs)
            np.testing.assert_array_equal(step.state, before)
            # From a fused controller's input rows, filled in place.
            assert step.step(0.002, *step.input_rows) is False
            assert step.step(0.003, **dict(inputs, v=np.full(6, np.inf))) is True
            if kernels.jit_enabled():
                with pytest.raises(TypeError):
                    inverse_dynamics.inverse_dynamics_inputs(
                        step.inputs.astype(np.float32),
                        step._work,
                        step.state,
                        step._table,
                    )
        finally:
            kernels.thaw()
