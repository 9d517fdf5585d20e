"""The whole-body balance QP (control/balance.py): every constraint it states holds
at its solution, its τ and f satisfy Drake's inverse dynamics, the CoM task tracks a
step in closed loop on the standing HRP-2, an infeasible problem is a fault without
NaN; the configs' and the contacts description's one-line errors."""

import contextlib
import copy

import numpy as np
import pytest
from pydrake.multibody.math import SpatialForce
from pydrake.multibody.tree import MultibodyForces
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource, MatrixGain

from hrp2_drake.control.balance import (
    BalanceConfig,
    BalanceFault,
    WholeBodyBalanceController,
    WholeBodyBalanceControllerStep,
    make_qp_backend,
)
from hrp2_drake.description import load_robot_description
from hrp2_drake.description.contacts import (
    BalanceDescription,
    ContactsDescription,
    SoleDescription,
)
from hrp2_drake.multibody import joint_indexing
from hrp2_drake.robot.station import standing_positions

PERIOD = 0.001  # s, the control period
TOLERANCE = 1e-6  # the solvers' (daqp's; OSQP's eps 1e-9 on forces of hundreds of N)


def _config(robot, **settings) -> BalanceConfig:
    """A BalanceConfig of `settings` with the robot's settings filled in."""
    return BalanceConfig(**settings).for_robot(robot.balance)


@pytest.fixture(scope="module")
def robot():
    return load_robot_description("hrp2")


@pytest.fixture(scope="module")
def standing(robot):
    """The plant alone, its standing state (lowest sole on z = 0), the indexing."""
    plant = robot.make_plant()
    context = plant.CreateDefaultContext()
    plant.SetPositions(context, standing_positions(robot))
    return (
        plant,
        plant.GetPositionsAndVelocities(context),
        joint_indexing(plant, robot.joints),
    )


@pytest.fixture(scope="module")
def step(robot, standing):
    return WholeBodyBalanceControllerStep(
        standing[0], _config(robot, joints=robot.joints), robot.contacts
    )


def perturbed_states(standing, count, seed=1, reach=0.02):
    """Standing states with the joints moved by ~0.03 rad, every velocity ~0.2,
    and CoM references within ~`reach` (m) of the standing CoM."""
    plant, x0, indexing = standing
    rng = np.random.default_rng(seed)
    context = plant.CreateDefaultContext()
    plant.SetPositionsAndVelocities(context, x0)
    com = plant.CalcCenterOfMassPositionInWorld(context)
    nq = plant.num_positions()
    for _ in range(count):
        x = x0.copy()
        x[indexing.q] += rng.normal(0.0, 0.03, indexing.size)
        x[nq:] = rng.normal(0.0, 0.2, plant.num_velocities())
        offset = rng.normal(0.0, reach, 3)
        ref = np.r_[com + offset, rng.normal(0.0, 0.05, 3), [0.0] * 3]
        yield x, ref


def test_the_qp_has_the_issues_size(step):
    """36 accelerations and 24 corner forces; the base's 6 rows and 6 per sole;
    30 torque rows and 4 per corner; the joints' and normal forces' bounds."""
    assert step.sizes() == (60, 18, 30 + 32, 30 + 8)


@pytest.mark.parametrize("tight", [False, True], ids=["default", "tight"])
def test_the_solution_satisfies_every_constraint(robot, standing, tight):
    """At perturbed standing states; "tight": CoM references up to ~10 cm away,
    20 % of the torque limits, 5 rad/s². Measured in the tight states: 3 to 6
    corners at f_z = 0 (the CoP on a sole's edge), up to one torque and 10
    accelerations at their limits. Removing the pyramids', the torques' or the
    accelerations' rows from the QP makes this test fail (checked by hand); the
    f_z >= f_min bound alone is implied by the pyramids when f_min = 0."""
    plant, _, indexing = standing
    config = _config(robot, joints=robot.joints)
    if tight:
        config.torque_limit_scale, config.acceleration_limit = 0.2, 5.0
    step = WholeBodyBalanceControllerStep(plant, config, robot.contacts)
    mu = step.config().friction / np.sqrt(2.0)
    tau_max = step.torque_limits()
    context = plant.CreateDefaultContext()
    home = robot.home_positions()
    for x, ref in perturbed_states(standing, 5, reach=0.1 if tight else 0.02):
        assert step.step(0.0, x, home, ref) == BalanceFault.NONE
        qp = step.qp
        solution = np.r_[step.vdot, step.contact_forces]
        scale = np.abs(qp.b_eq).max()
        np.testing.assert_allclose(qp.A_eq @ solution, qp.b_eq, atol=TOLERANCE * scale)
        f = step.contact_forces.reshape(-1, 3)
        assert np.all(f[:, 2] >= -TOLERANCE)  # unilateral
        assert np.all(np.abs(f[:, :2]) <= mu * f[:, [2]] + TOLERANCE)  # pyramids
        assert np.all(np.abs(step.tau_desired) <= tau_max + TOLERANCE)
        limit = config.acceleration_limit + TOLERANCE
        assert np.all(np.abs(step.vdot[indexing.v]) <= limit)
        # The CoP of each sole inside its rectangle, in the moment form that holds
        # for an unloaded sole too: x0 f_z <= −τ_y <= x1 f_z, y0 f_z <= τ_x <= y1 f_z.
        wrenches = step.sole_wrenches.reshape(-1, 6)
        atol = TOLERANCE * scale
        for (tx, ty, _, _, _, fz), sole in zip(wrenches, step.soles()):
            rectangle = robot.contacts.soles[sole]
            assert rectangle.x[0] * fz - atol <= -ty <= rectangle.x[1] * fz + atol
            assert rectangle.y[0] * fz - atol <= tx <= rectangle.y[1] * fz + atol
        # The soles do not accelerate: their origins' spatial accelerations from
        # Drake's forward kinematics of (x, v̇), another path than the QP's rows.
        plant.SetPositionsAndVelocities(context, x)
        accelerations = plant.CalcSpatialAccelerationsFromVdot(context, step.vdot)
        for sole in step.soles():
            frame = plant.GetFrameByName(sole)
            body = frame.body()
            X_WB = body.EvalPoseInWorld(context)
            p_BS = frame.GetFixedPoseInBodyFrame().translation()
            p_BS_W = X_WB.rotation().multiply(p_BS)
            w_WB = body.EvalSpatialVelocityInWorld(context).rotational()
            A_WS = accelerations[int(body.index())].Shift(p_BS_W, w_WB)
            np.testing.assert_allclose(A_WS.get_coeffs(), 0.0, atol=1e-6)


def test_tau_and_f_satisfy_drakes_inverse_dynamics(robot, standing, step):
    """M v̇ + C v − τ_g − Σ Jᵀ f = Sᵀ τ: Drake's CalcInverseDynamics with the corner
    forces applied as external forces gives zero on the base and τ on the joints."""
    plant, _, indexing = standing
    context = plant.CreateDefaultContext()
    home = robot.home_positions()
    for x, ref in perturbed_states(standing, 3, seed=2):
        assert step.step(0.0, x, home, ref) == BalanceFault.NONE
        plant.SetPositionsAndVelocities(context, x)
        forces = MultibodyForces(plant)
        plant.CalcForceElementsContribution(context, forces)
        f = step.contact_forces.reshape(len(step.soles()), 4, 3)
        for k, sole in enumerate(step.soles()):
            frame = plant.GetFrameByName(sole)
            body = frame.body()
            R_WB = body.EvalPoseInWorld(context).rotation()
            R_WS = frame.CalcPoseInWorld(context).rotation()
            X_BS = frame.GetFixedPoseInBodyFrame()
            for corner, force in zip(robot.contacts.soles[sole].corners(), f[k]):
                body.AddInForce(
                    context,
                    R_WB.multiply(X_BS.multiply(corner)),
                    SpatialForce(np.zeros(3), R_WS.multiply(force)),
                    plant.world_frame(),
                    forces,
                )
        generalized = plant.CalcInverseDynamics(context, step.vdot, forces)
        np.testing.assert_allclose(generalized[:6], 0.0, atol=1e-6)
        np.testing.assert_allclose(generalized[indexing.v], step.tau_desired, atol=1e-6)


def test_the_com_task_tracks_a_step_in_closed_loop(robot):
    """HRP-2 standing on the ground (the station's plant, SAP contact, 1 ms), the
    QP's torques applied directly (no servo, no Δq chain): a +2 cm CoM step in y.
    Measured (default gains, K_p = 30/s², K_d = 11/s): the error in y is 18.2 mm
    at 0.1 s, 3.3 mm at 0.6 s, 0.18 mm at 1.2 s, 0.001 mm at 1.5 s (0.04 mm of
    overshoot at 1.8 s); x moves by 0.1 mm and z by 0.2 mm (the soles sink into
    SAP's compliant ground); no fault. Asserted: within 0.5 mm at 1.5 s."""
    from hrp2_drake.robot.station import StationConfig, add_scenario_plant

    builder = DiagramBuilder()
    q0 = robot.home_positions()
    station = StationConfig(scenario="standing")
    plant, _ = add_scenario_plant(builder, station, robot, q0)
    model = robot.make_plant()
    controller = builder.AddSystem(
        WholeBodyBalanceController(
            model, _config(robot, joints=robot.joints), robot.contacts, PERIOD
        )
    )
    indexing = joint_indexing(plant, robot.joints)
    B = np.zeros((plant.num_actuated_dofs(), indexing.size))
    B[indexing.u, np.arange(indexing.size)] = 1.0
    to_actuation = builder.AddSystem(MatrixGain(B))
    builder.Connect(
        controller.GetOutputPort("tau_desired"), to_actuation.get_input_port()
    )
    builder.Connect(to_actuation.get_output_port(), plant.get_actuation_input_port())
    builder.Connect(plant.get_state_output_port(), controller.GetInputPort("state"))
    posture = builder.AddSystem(ConstantVectorSource(q0))
    builder.Connect(posture.get_output_port(), controller.GetInputPort("q_ref"))
    context = plant.CreateDefaultContext()
    com0 = plant.CalcCenterOfMassPositionInWorld(context)
    target = com0 + [0.0, 0.02, 0.0]
    reference = builder.AddSystem(ConstantVectorSource(np.r_[target, np.zeros(6)]))
    builder.Connect(reference.get_output_port(), controller.GetInputPort("com_ref"))
    diagram = builder.Build()
    simulator = Simulator(diagram)
    simulator.AdvanceTo(1.5)
    root = simulator.get_context()
    plant_context = plant.GetMyContextFromRoot(root)
    com = plant.CalcCenterOfMassPositionInWorld(plant_context)
    controller_context = controller.GetMyContextFromRoot(root)
    assert controller.GetOutputPort("fault_count").Eval(controller_context)[0] == 0
    assert abs(com[1] - target[1]) < 0.5e-3, com - target
    assert np.all(np.abs((com - com0)[[0, 2]]) < 0.5e-3), com - com0


def test_an_infeasible_problem_is_a_fault_without_nan(robot, standing):
    """Zero torque limits and no joint acceleration: the robot cannot be held (the
    arms' gravity torques have no contact force to balance them: infeasible, where
    zero torques alone are not: the robot may fall with its feet on the ground
    within the acceleration limits); the step reports it,
    counts it and outputs the static torque, finite; once solved, a fault keeps
    the last good torque."""
    plant, x, _ = standing
    home = robot.home_positions()
    context = plant.CreateDefaultContext()
    plant.SetPositionsAndVelocities(context, x)
    ref = np.r_[plant.CalcCenterOfMassPositionInWorld(context), np.zeros(6)]
    config = _config(
        robot, joints=robot.joints, torque_limit_scale=0.0, acceleration_limit=0.0
    )
    step = WholeBodyBalanceControllerStep(plant, config, robot.contacts)
    fault = step.step(0.0, x, home, ref)
    assert fault in (BalanceFault.INFEASIBLE, BalanceFault.SOLVER_FAILED)
    assert step.fault[0] == fault and step.fault_count[0] == 1
    assert np.all(np.isfinite(step.state))
    assert np.abs(step.tau_desired).max() > 1.0  # the static torque, not zero
    good = WholeBodyBalanceControllerStep(
        plant, _config(robot, joints=robot.joints), robot.contacts
    )
    assert good.step(0.0, x, home, ref) == BalanceFault.NONE
    tau = good.tau_desired.copy()
    bad = x.copy()
    bad[10] = np.nan
    assert good.step(0.0, bad, home, ref) == BalanceFault.INPUT_NOT_FINITE
    np.testing.assert_array_equal(good.tau_desired, tau)
    assert np.all(np.isfinite(good.state)) and good.fault_count[0] == 1


def test_the_shell_outputs_the_steps_numbers(robot, standing):
    """The LeafSystem's first update equals a fresh step's first tick (a step
    has a history: the last tick's forces, `force_rate_weight`)."""
    plant, x, _ = standing
    step = WholeBodyBalanceControllerStep(
        plant, _config(robot, joints=robot.joints), robot.contacts
    )
    home = robot.home_positions()
    context = plant.CreateDefaultContext()
    plant.SetPositionsAndVelocities(context, x)
    ref = np.r_[plant.CalcCenterOfMassPositionInWorld(context) + [0, 0.01, 0], [0] * 6]
    system = WholeBodyBalanceController(
        plant, _config(robot, joints=robot.joints), robot.contacts, PERIOD
    )
    system_context = system.CreateDefaultContext()
    system.GetInputPort("state").FixValue(system_context, x)
    system.GetInputPort("q_ref").FixValue(system_context, home)
    system.GetInputPort("com_ref").FixValue(system_context, ref)
    updated = system.EvalUniquePeriodicDiscreteUpdate(system_context)
    system_context.SetDiscreteState(updated)
    assert step.step(0.0, x, home, ref) == BalanceFault.NONE
    np.testing.assert_allclose(
        system.GetOutputPort("tau_desired").Eval(system_context),
        step.tau_desired,
        atol=1e-9,
    )
    assert system.GetOutputPort("fault").Eval(system_context)[0] == 0


@pytest.mark.parametrize(
    "change, message",
    [
        ({"solver": "cplex"}, "BalanceConfig.solver: 'cplex', expected one of"),
        ({"friction": 0.0}, "BalanceConfig.friction: must be > 0"),
        ({"com_kp": -1.0}, "BalanceConfig.com_kp: must be finite and >= 0"),
        ({"acceleration_weight": 0.0}, "acceleration_weight: must be > 0"),
        ({"joints": []}, "BalanceConfig.joints is empty"),
        ({"soles": ["r_foot"]}, r"BalanceConfig.soles: \['r_foot'\] have no rectangle"),
        ({"friction": 1.5}, "BalanceConfig.friction: 1.5 exceeds the description's"),
    ],
)
def test_config_errors_name_the_field(robot, standing, change, message):
    config = _config(robot, joints=robot.joints)
    for key, value in change.items():
        setattr(config, key, value)
    with pytest.raises(ValueError, match=message):
        WholeBodyBalanceControllerStep(standing[0], config, robot.contacts)


def test_the_robot_gives_what_the_config_leaves_unset(robot, standing):
    """BalanceConfig's friction, least corner force and CoM gains left None are the
    robot's (HRP-2's robot.yaml `balance`); a value the config sets wins; a robot
    that gives none has the generic ones but no friction (one line naming the field);
    a step refuses a config never filled in."""
    filled = BalanceConfig().for_robot(robot.balance)
    assert (filled.friction, filled.min_normal_force) == (0.3, 10.0)
    assert (filled.com_kp, filled.com_kd) == (150.0, 24.5)
    assert BalanceConfig(com_kp=60.0).for_robot(robot.balance).com_kp == 60.0
    bare = BalanceDescription()
    generic = BalanceConfig(friction=0.5).for_robot(bare)
    assert (generic.min_normal_force, generic.com_kp, generic.com_kd) == (
        0.0,
        30.0,
        11.0,
    )
    with pytest.raises(ValueError, match=r"^r.yaml: balance.friction: not given"):
        BalanceConfig().for_robot(bare, where="r.yaml")
    with pytest.raises(ValueError, match="unset .None: the robot's.: fill them"):
        WholeBodyBalanceControllerStep(
            standing[0], BalanceConfig(joints=robot.joints), robot.contacts
        )


def test_every_joint_must_be_listed(robot, standing):
    message = "BalanceConfig.joints: 29 joints, but the plant"
    with pytest.raises(ValueError, match=message):
        WholeBodyBalanceControllerStep(
            standing[0], _config(robot, joints=robot.joints[1:]), robot.contacts
        )


@pytest.mark.parametrize(
    "contacts, message",
    [
        (ContactsDescription(0.0, {"r_sole": SoleDescription()}), "contacts.friction"),
        (
            ContactsDescription(1.0, {"r_sole": SoleDescription([0.1, -0.1], [0, 1])}),
            r"contacts.soles.r_sole.x: expected \[low, high\]",
        ),
    ],
)
def test_contacts_errors_name_the_key(contacts, message):
    with pytest.raises(ValueError, match=message):
        contacts.validate()


def test_a_sole_frame_must_be_in_the_model(standing):
    contacts = ContactsDescription(1.0, {"no_sole": SoleDescription([0, 1], [0, 1])})
    with pytest.raises(ValueError, match="contacts.soles.no_sole: no frame 'no_sole'"):
        contacts.check_model(standing[0])


def test_hrp2s_soles_are_its_models_contact_rectangle(robot, standing):
    """The description's rectangle is the one the four corner spheres of the model
    span (models/hrp2/README.md), so the CoP the QP allows is one the simulated foot
    can carry."""
    assert sorted(robot.contacts.soles) == sorted(robot.scenarios.soles)
    for sole in robot.contacts.soles.values():
        assert sole.x == [-0.105, 0.135] and sole.y == [-0.07, 0.07]


def test_a_missing_pip_solver_is_one_line(monkeypatch, step):
    import builtins

    real_import = builtins.__import__

    def no_daqp(name, *args, **kwargs):
        if name == "daqp":
            raise ImportError("no daqp")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_daqp)
    with pytest.raises(ValueError, match=r"'daqp' is not installed: pip install"):
        make_qp_backend(copy.deepcopy(step.qp), "daqp")


def test_the_compiled_kernels_equal_their_python_source(robot, standing):
    """The QP's assembly and outputs (balance_assemble, balance_outputs) compiled
    and as Python (`kernels.interpreted`), on the same states: equal to 1e-12 of τ's
    size (loop-order sums both ways; daqp and OSQP see the same numbers)."""
    from hrp2_drake import kernels

    plant = standing[0]
    home = robot.home_positions()
    results = []
    for interpreted in (False, True):
        step = WholeBodyBalanceControllerStep(
            plant, _config(robot, joints=robot.joints), robot.contacts
        )
        context = kernels.interpreted() if interpreted else contextlib.nullcontext()
        with context:
            for x, ref in perturbed_states(standing, 2, seed=3):
                assert step.step(0.0, x, home, ref) == BalanceFault.NONE
                qp = step.qp
                results.append((qp.H.copy(), qp.A_in.copy(), step.state.copy()))
    for compiled, python in zip(results[:2], results[2:]):
        for a, b in zip(compiled, python):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * np.abs(a).max())


def test_warm_up_compiles_the_signatures_of_a_tick(robot, standing, monkeypatch):
    """warm_up calls each kernel with arrays of the types and layouts a tick passes
    (Drake's column-major mass matrix is copied into the step's own): a fused
    loop, compiling frozen after warm_up, never meets a new signature. The
    signatures are compared, not compiled: another test may have compiled them."""
    import numba

    from hrp2_drake.control import balance

    seen = {"warm_up": set(), "tick": set()}
    phase = ["warm_up"]
    for name in ("balance_assemble", "balance_outputs"):
        kernel = getattr(balance, name)

        def typed(*args, kernel=kernel, name=name):
            seen[phase[0]].add((name, tuple(numba.typeof(a) for a in args)))
            return kernel(*args)

        monkeypatch.setattr(balance, name, typed)
    plant, x, _ = standing
    step = WholeBodyBalanceControllerStep(
        plant, _config(robot, joints=robot.joints), robot.contacts
    )
    step.warm_up()
    phase[0] = "tick"
    for x, ref in perturbed_states(standing, 2, seed=5):
        assert step.step(0.0, x, robot.home_positions(), ref) == BalanceFault.NONE
    assert len(seen["tick"]) == 2  # one signature per kernel
    assert seen["tick"] <= seen["warm_up"]


def test_daqp_solves_the_same_qp_as_osqp_and_reports_infeasibility(robot, standing):
    """daqp (the default solver) and pydrake's OSQP (selectable): the same τ on
    perturbed states (to 1e-3 N·m: OSQP's tolerance on a cost that is flat in the
    forces' distribution), warm-started tick after tick; the infeasible problem is a
    fault."""
    plant, x, _ = standing
    home = robot.home_positions()
    assert BalanceConfig().solver == "daqp"
    fast = WholeBodyBalanceControllerStep(
        plant, _config(robot, joints=robot.joints), robot.contacts
    )
    osqp = WholeBodyBalanceControllerStep(
        plant, _config(robot, joints=robot.joints, solver="osqp"), robot.contacts
    )
    for state, ref in perturbed_states(standing, 3, seed=4):
        assert osqp.step(0.0, state, home, ref) == BalanceFault.NONE
        assert fast.step(0.0, state, home, ref) == BalanceFault.NONE
        np.testing.assert_allclose(fast.tau_desired, osqp.tau_desired, atol=1e-3)
    # 1 % of the torque limits, no joint acceleration (with both at 0, daqp finds
    # the bounds' working set overdetermined: exit -6, a SOLVER_FAILED).
    config = _config(
        robot,
        joints=robot.joints,
        solver="daqp",
        torque_limit_scale=0.01,
        acceleration_limit=0.0,
    )
    infeasible = WholeBodyBalanceControllerStep(plant, config, robot.contacts)
    ref = np.r_[np.zeros(3), np.zeros(6)]
    assert infeasible.step(0.0, x, home, ref) == BalanceFault.INFEASIBLE
    assert np.all(np.isfinite(infeasible.state))


def test_the_force_rate_weight_smooths_the_forces_from_tick_to_tick(robot, standing):
    """force_rate_weight pulls each tick's contact forces toward the last tick's
    solution: after a step in the CoM reference, the forces move less in one tick
    than without it (and every constraint still holds); before a first solve there
    is no last solution, so the first tick is the same as without it."""
    plant, x, _ = standing
    home = robot.home_positions()
    context = plant.CreateDefaultContext()
    plant.SetPositionsAndVelocities(context, x)
    still = np.r_[plant.CalcCenterOfMassPositionInWorld(context), np.zeros(6)]
    moved = still + np.r_[0.0, 0.02, 0.0, np.zeros(6)]
    changes = {}
    for weight in (0.0, 1.0):
        step = WholeBodyBalanceControllerStep(
            plant,
            _config(robot, joints=robot.joints, force_rate_weight=weight),
            robot.contacts,
        )
        assert step.step(0.0, x, home, still) == BalanceFault.NONE
        before = step.contact_forces.copy()
        changes.setdefault("first", []).append(before)
        assert step.step(0.0, x, home, moved) == BalanceFault.NONE
        changes[weight] = np.abs(step.contact_forces - before).max()
        normal = step.contact_forces[2::3]
        assert normal.min() >= step.config().min_normal_force - TOLERANCE
    np.testing.assert_allclose(*changes["first"], atol=TOLERANCE)
    assert changes[1.0] < 0.5 * changes[0.0]
