"""EmulatedPositionServo: the law itself (the `ideal` preset), the effective motor model
in closed loop on the simulated robot, the stability of the explicit torques at 1 kHz,
and each mechanism of the calibrated servo (latency, voltage limit, hysteresis)."""

import numpy as np
import pytest
from pydrake.common.value import AbstractValue
from pydrake.multibody.math import SpatialForce
from pydrake.multibody.plant import ExternallyAppliedSpatialForce, MultibodyPlant
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import (
    ConstantValueSource,
    ConstantVectorSource,
    TrajectorySource,
)
from pydrake.trajectories import PiecewisePolynomial

from hrp2_drake.description.sensors import SensorsConfig
from hrp2_drake.paper import hrp2
from hrp2_drake.robot.servo import (
    EmulatedPositionServo,
    effective_motor_parameters,
    explicit_stability_margin,
    load_servo_params,
)
from hrp2_drake.robot.station import (
    StationConfig,
    initial_joint_positions,
    make_station,
)

# The paper's Table 1 (Kτ in rad/(N·m), Kv in s), right leg.
TABLE1_K_TAU = np.array([0.212, 0.030, 0.12, 0.051, 0.177, 0.240]) * 1e-3
TABLE1_K_V = np.array([13.0, 6.332, 7.0, 6.561, 7.698, 6.0]) * 1e-3


@pytest.fixture(scope="module")
def params():
    """The `ideal` preset: the exact linear law these tests need."""
    return load_servo_params("ideal")


@pytest.fixture(scope="module")
def calibrated():
    return load_servo_params()


@pytest.fixture(scope="module")
def plant():
    plant = MultibodyPlant(0.001)
    hrp2.add_hrp2(plant)
    plant.Finalize()
    return plant


def test_data_file_matches_table1(params):
    eff = effective_motor_parameters(params, hrp2.RIGHT_LEG)
    # The data file keeps 9 significant digits.
    np.testing.assert_allclose(eff["k_tau"], TABLE1_K_TAU, rtol=1e-7)
    np.testing.assert_allclose(eff["k_v"], TABLE1_K_V, rtol=1e-7)
    # Left leg mirrors the right; every joint has a plausible, positive model.
    eff_all = effective_motor_parameters(params, hrp2.JOINT_NAMES)
    np.testing.assert_allclose(eff_all["k_tau"][6:12], TABLE1_K_TAU, rtol=1e-7)
    assert np.all(eff_all["k_tau"] > 0) and np.all(eff_all["k_v"] > 0)


def test_servo_law_slope_is_k_tau(params, plant):
    """Outside the dead zone, at rest, Δq = Kτ τ + deadzone·sign(τ) exactly."""
    servo = EmulatedPositionServo(plant, params, hrp2.JOINT_NAMES)
    context = servo.CreateDefaultContext()
    plant_context = plant.CreateDefaultContext()
    indexing = hrp2.hrp2_joint_indexing(plant)
    q = plant.GetPositions(plant_context)
    # Joint angles on the encoder grid, so the quantization adds nothing.
    res = params.vectors(hrp2.JOINT_NAMES)["encoder_resolution"]
    q[indexing.q] = np.round(hrp2.half_sitting() / res) * res
    x = np.concatenate([q, np.zeros(plant.num_velocities())])
    servo.get_input_port(1).FixValue(context, x)
    eff = effective_motor_parameters(params, hrp2.JOINT_NAMES)
    p = params.vectors(hrp2.JOINT_NAMES)
    peak = p["k1"] * p["i_max"]  # N·m at current saturation
    # Commands for 20% and 40% of the peak torque, both signs, past the dead zone.
    dqs = [
        s * (eff["deadzone"] + eff["k_tau"] * f * peak)
        for s in (1, -1)
        for f in (0.2, 0.4)
    ]
    taus = []
    for dq in dqs:
        servo.get_input_port(0).FixValue(context, q[indexing.q] + dq)
        taus.append(servo.get_output_port().Eval(context).copy())
    slope_pos = (dqs[1] - dqs[0]) / (taus[1] - taus[0])
    slope_neg = (dqs[3] - dqs[2]) / (taus[3] - taus[2])
    np.testing.assert_allclose(slope_pos, eff["k_tau"], rtol=1e-9)
    np.testing.assert_allclose(slope_neg, eff["k_tau"], rtol=1e-9)
    np.testing.assert_allclose(taus[1], 0.4 * peak, rtol=1e-9)
    offset = dqs[0] - eff["k_tau"] * taus[0]
    np.testing.assert_allclose(offset, eff["deadzone"], rtol=1e-9)
    # Inside the dead zone: no torque at all.
    servo.get_input_port(0).FixValue(context, q[indexing.q] + 0.5 * eff["deadzone"])
    np.testing.assert_allclose(servo.get_output_port().Eval(context), 0.0, atol=1e-12)


def test_servo_rejects_nan_command(params, plant):
    servo = EmulatedPositionServo(plant, params, hrp2.JOINT_NAMES)
    context = servo.CreateDefaultContext()
    q_cmd = hrp2.half_sitting()
    q_cmd[3] = np.nan
    servo.get_input_port(0).FixValue(context, q_cmd)
    servo.get_input_port(1).FixValue(
        context, np.zeros(plant.num_positions() + plant.num_velocities())
    )
    with pytest.raises(ValueError, match="RLEG_JOINT3"):
        servo.get_output_port().Eval(context)


def kernel_torque(servo, error, v, direction, enabled=None) -> np.ndarray:
    """The servo's per-step law (its kernel, with its packed constants) on the position
    error itself: what `servo_torque` computes from its parameters."""
    from hrp2_drake.robot.servo import _servo_law

    tau = np.empty(len(error))
    empty = np.zeros(0)
    _servo_law(
        servo._constants,
        np.asarray(error, dtype=float),
        empty,
        np.asarray(v, dtype=float),
        np.asarray(direction, dtype=float),
        empty if enabled is None else np.asarray(enabled, dtype=float),
        True,
        tau,
    )
    return tau


def dahl_step(s: np.ndarray, dq: np.ndarray, width: np.ndarray) -> np.ndarray:
    """Direction state after the joint moved dq (rad): the exact solution of Dahl's
    ds/dq = (1 - s sign(dq)) / width over the step; stays in [-1, 1] (the reference
    the servo's kernels are held to; moved here from robot/servo.py, issue 28)."""
    decay = np.exp(-np.abs(dq) / width)
    target = np.sign(dq)
    return np.where(dq == 0, s, target + (s - target) * decay)


def test_each_joint_follows_its_own_mechanisms_tick_by_tick(calibrated, plant):
    """The calibrated servo mixes joints with and without latency and hysteresis; with
    every third joint's encoder quantization off too, each tick's actuation is the
    law of each joint's own mechanisms (servo_torque on the command of `latency` ago,
    the quantized encoder, the Dahl state moved by the last tick's travel), exactly."""
    from dataclasses import replace

    from hrp2_drake.robot.servo import servo_torque

    names = hrp2.JOINT_NAMES
    params = type(calibrated)(
        {
            name: (
                replace(calibrated.joints[name], encoder_resolution=0.0)
                if k % 3 == 0
                else calibrated.joints[name]
            )
            for k, name in enumerate(names)
        }
    )
    p = params.vectors(names)
    delays = np.rint(p["latency"] / 1e-3).astype(int)
    dahl = p["hysteresis_width"] > 0
    assert set(delays) == {0, 1} and 0 < dahl.sum() < len(names)
    q0 = hrp2.half_sitting()
    servo = EmulatedPositionServo(plant, params, names, 1e-3, q0)
    context = servo.CreateDefaultContext()
    indexing = hrp2.hrp2_joint_indexing(plant)
    x = np.zeros(plant.num_positions() + plant.num_velocities())
    x[indexing.q] = q0
    servo.get_input_port(0).FixValue(context, q0)
    servo.get_input_port(1).FixValue(context, x)
    servo.ExecuteInitializationEvents(context)
    rng = np.random.default_rng(3)
    s, q_last, previous_command = np.zeros(len(names)), q0.copy(), q0.copy()
    res = p["encoder_resolution"]
    for _ in range(6):
        q = q0 + rng.normal(0.0, 2e-3, len(names))
        v = rng.normal(0.0, 0.3, len(names))
        q_cmd = q + rng.normal(0.0, 2e-3, len(names))
        x[indexing.q], x[plant.num_positions() + indexing.v] = q, v
        servo.get_input_port(0).FixValue(context, q_cmd)
        servo.get_input_port(1).FixValue(context, x)
        applied = np.where(delays > 0, previous_command, q_cmd)
        q_encoder = np.where(res > 0, np.round(q / np.where(res > 0, res, 1)) * res, q)
        direction = np.where(dahl, s, np.tanh(v / p["v_coulomb"]))
        expected = np.zeros(plant.num_actuators())
        expected[indexing.u] = servo_torque(p, applied - q_encoder, v, direction)
        np.testing.assert_array_equal(servo.get_output_port().Eval(context), expected)
        context.SetDiscreteState(servo.EvalUniquePeriodicDiscreteUpdate(context))
        width = np.where(dahl, p["hysteresis_width"], 1.0)
        s = np.where(dahl, dahl_step(s, q - q_last, width), 0.0)
        q_last, previous_command = q, q_cmd


def test_per_step_law_is_servo_torque_bit_for_bit(calibrated, plant):
    """The servo's per-step law (array constants, minimum/maximum for clip) gives
    servo_torque's numbers exactly, in every regime: dead zone, driver saturation,
    the voltage limit either way and beyond the no-load speed, both directions."""
    from hrp2_drake.robot.servo import servo_torque

    names = hrp2.JOINT_NAMES
    p = calibrated.vectors(names)
    servo = EmulatedPositionServo(plant, calibrated, names, 1e-3, hrp2.half_sitting())
    rng = np.random.default_rng(7)
    for scale_e, scale_v in [(1e-4, 0.01), (3e-3, 0.5), (0.05, 3.0), (0.2, 8.0)]:
        for _ in range(200):
            error = rng.normal(0.0, scale_e, len(names))
            v = rng.normal(0.0, scale_v, len(names))
            direction = rng.uniform(-1.0, 1.0, len(names))
            expected = servo_torque(p, error, v, direction)
            actual = kernel_torque(servo, error, v, direction)
            assert actual.tobytes() == expected.tobytes()


def test_explicit_torques_are_stable_at_1khz(params, plant):
    """Spectral radius < 1 per joint with the reflected inertia as inertia bound."""
    # Actuators are in joint order (checked by hrp2_joint_indexing).
    hrp2.hrp2_joint_indexing(plant)
    reflected = np.array(
        [
            plant.get_joint_actuator(i).default_rotor_inertia()
            * plant.get_joint_actuator(i).default_gear_ratio() ** 2
            for i in plant.GetJointActuatorIndices()
        ]
    )
    radius = explicit_stability_margin(params, hrp2.JOINT_NAMES, reflected, 1e-3)
    assert radius.max() < 1.0
    # ...and the same servo without the rotor inertia would not be stable.
    light = explicit_stability_margin(params, hrp2.JOINT_NAMES, np.full(30, 1e-3), 1e-3)
    assert light.max() > 1.0


def _fixed_base(q_cmd_system, external_force=None):
    config = StationConfig(
        scenario="fixed_base", sensors=SensorsConfig.noiseless(), servo_file="ideal"
    )
    builder = DiagramBuilder()
    station = builder.AddSystem(make_station(config))
    source = builder.AddSystem(q_cmd_system)
    builder.Connect(source.get_output_port(), station.GetInputPort("q_cmd"))
    if external_force is not None:
        push = builder.AddSystem(
            ConstantValueSource(AbstractValue.Make(external_force))
        )
        builder.Connect(
            push.get_output_port(), station.GetInputPort("applied_spatial_force")
        )
    diagram = builder.Build()
    return diagram, station


def _grid(t0: float, t1: float, samples: int) -> np.ndarray:
    """Sample times on the plant's 1 ms grid (between grid points the discrete state
    lags a continuous command by up to a step)."""
    return np.round(np.linspace(t0, t1, samples), 3)


def _hold_average(simulator, station, t0: float, t1: float, samples: int = 20):
    """Mean of right-leg (q, joint_torque_true, v) over [t0, t1] (the servo chatters
    by ~0.1 N·m around rest: quantization and the steep Coulomb sign). q and v are
    the plant's, at the same instant as the command the servo sees."""
    out = []
    for t in _grid(t0, t1, samples):
        simulator.AdvanceTo(t)
        ctx = station.GetMyContextFromRoot(simulator.get_context())
        x = station.GetOutputPort("state_true").Eval(ctx)
        out.append(
            np.concatenate(
                [
                    x[:6],
                    station.GetOutputPort("joint_torque_true").Eval(ctx)[:6],
                    x[30:36],  # fixed base: x = [q (30); v (30)]
                ]
            )
        )
    mean = np.mean(out, axis=0)
    return mean[:6], mean[6:12], mean[12:]


def test_closed_loop_static_k_tau_within_1_percent(params):
    """A known external couple on the right foot, the servo holding: the slope of Δq
    against the joint torque is the data file's Kτ within 1%, for both signs."""
    q0 = initial_joint_positions(StationConfig(scenario="fixed_base"))
    eff = effective_motor_parameters(params, hrp2.RIGHT_LEG)
    plant = MultibodyPlant(0.0)
    hrp2.add_hrp2(plant)
    plant.Finalize()
    foot = plant.GetBodyByName("RLEG_FOOT").index()
    for sign in (1.0, -1.0):
        readings = []
        for scale in (1.0, 2.0):
            force = ExternallyAppliedSpatialForce()
            force.body_index = foot
            force.p_BoBq_B = np.zeros(3)
            couple = sign * scale * np.array([15.0, 20.0, 10.0])  # N·m
            force.F_Bq_W = SpatialForce(couple, np.zeros(3))
            diagram, station = _fixed_base(ConstantVectorSource(q0), [force])
            q, tau, _ = _hold_average(Simulator(diagram), station, 0.5, 0.6)
            readings.append((q0[:6] - q, tau))
        (dq1, tau1), (dq2, tau2) = readings
        assert np.all(np.abs(tau1 - tau2) > 9.0)  # every joint loaded
        assert np.all(np.sign(tau1) == np.sign(tau2))  # same side of the dead zone
        slope = (dq1 - dq2) / (tau1 - tau2)
        np.testing.assert_allclose(slope, eff["k_tau"], rtol=0.01)


def test_closed_loop_constant_velocity_k_v_within_1_percent(params):
    """Ramps at two constant speeds on the right leg: (Δq - Kτ± τ) grows with q̇ at
    the data file's Kv± within 1%."""
    q0 = initial_joint_positions(StationConfig(scenario="fixed_base"))
    eff_pos = effective_motor_parameters(params, hrp2.RIGHT_LEG, direction=+1)
    eff_neg = effective_motor_parameters(params, hrp2.RIGHT_LEG, direction=-1)
    speeds = (0.3, 0.6)  # rad/s
    directions = np.array([1, -1, 1, 1, -1, 1])  # stay inside the joint limits
    samples = []
    for speed in speeds:
        times = [0.0, 0.2, 0.9]
        ramp = np.tile(q0, (3, 1))
        ramp[2, :6] += directions * speed * 0.7
        traj = PiecewisePolynomial.FirstOrderHold(times, ramp.T)
        diagram, station = _fixed_base(TrajectorySource(traj))
        q, tau, v = _hold_average(Simulator(diagram), station, 0.75, 0.85)
        q_cmd = np.mean([traj.value(t).ravel()[:6] for t in _grid(0.75, 0.85, 20)], 0)
        samples.append((q_cmd - q, tau, v))
    (dq1, tau1, v1), (dq2, tau2, v2) = samples
    np.testing.assert_allclose(np.abs(v1), speeds[0], rtol=0.02)
    np.testing.assert_allclose(np.abs(v2), speeds[1], rtol=0.02)
    # Kτ and Kv of the direction of motion (K1+ or K1-).
    k_tau = np.where(directions > 0, eff_pos["k_tau"], eff_neg["k_tau"])
    k_v = np.where(directions > 0, eff_pos["k_v"], eff_neg["k_v"])
    friction_part = (dq2 - k_tau * tau2) - (dq1 - k_tau * tau1)
    np.testing.assert_allclose(friction_part / (v2 - v1), k_v, rtol=0.01)


# --- The calibrated servo's mechanisms -------------------------------------------


def test_calibrated_file_keeps_table1_and_adds_every_mechanism(calibrated):
    """The identified Kτ, Kv of the calibrated servo are still Table 1 (Kv with the
    latency in it); the right leg has latency, a voltage limit, hysteresis and a dead
    zone of the authors' measured size (0.3-3 mrad half-width, not 0.04-0.3)."""
    eff = effective_motor_parameters(calibrated, hrp2.RIGHT_LEG)
    np.testing.assert_allclose(eff["k_tau"], TABLE1_K_TAU, rtol=1e-7)
    np.testing.assert_allclose(eff["k_v"], TABLE1_K_V, rtol=1e-7)
    p = calibrated.vectors(hrp2.RIGHT_LEG)
    assert np.all(p["latency"] > 0)
    assert np.all(p["hysteresis_width"] > 0)
    assert np.all(np.isfinite(p["no_load_speed"][1:]))  # the moving joints
    assert np.all((eff["deadzone"] > 3e-4) & (eff["deadzone"] < 3e-3))
    ideal = effective_motor_parameters(load_servo_params("ideal"), hrp2.RIGHT_LEG)
    assert np.all(eff["deadzone"] > 2 * ideal["deadzone"])


def _single_joint_servo(plant, overrides: dict, off=()):
    """The ideal preset with `overrides` on every joint."""
    from dataclasses import replace

    base = load_servo_params("ideal")
    params = type(base)({n: replace(j, **overrides) for n, j in base.joints.items()})
    q0 = hrp2.half_sitting()
    return (
        EmulatedPositionServo(plant, params, hrp2.JOINT_NAMES, 1e-3, q0, off),
        params,
        q0,
    )


def _first_change_time(plant, latency: float) -> float:
    """A q_cmd step out of a 1 kHz controller (a zero-order hold, like our
    controllers' state outputs) at t = 10 ms: when the servo's torque first moves."""
    from pydrake.systems.primitives import ZeroOrderHold

    servo, _, q0 = _single_joint_servo(plant, {"latency": latency})
    builder = DiagramBuilder()
    step = q0 + 0.01
    traj = PiecewisePolynomial.ZeroOrderHold(
        [0.0, 0.0095, 1.0], np.column_stack([q0, step, step])
    )
    source = builder.AddSystem(TrajectorySource(traj))
    hold = builder.AddSystem(ZeroOrderHold(1e-3, len(q0)))
    builder.Connect(source.get_output_port(), hold.get_input_port())
    builder.AddSystem(servo)
    builder.Connect(hold.get_output_port(), servo.get_input_port(0))
    x = np.zeros(plant.num_positions() + plant.num_velocities())
    x[hrp2.hrp2_joint_indexing(plant).q] = q0
    state = builder.AddSystem(ConstantVectorSource(x))
    builder.Connect(state.get_output_port(), servo.get_input_port(1))
    diagram = builder.Build()
    simulator = Simulator(diagram)
    hold.GetMyMutableContextFromRoot(simulator.get_mutable_context()).SetDiscreteState(
        q0
    )
    simulator.Initialize()
    context = servo.GetMyContextFromRoot(simulator.get_context())
    before = servo.get_output_port().Eval(context).copy()
    for t in (np.arange(1, 200) + 0.5) * 1e-4:  # between the 1 ms ticks
        simulator.AdvanceTo(t)
        if np.abs(servo.get_output_port().Eval(context) - before).max() > 1e-9:
            return t
    return np.inf


@pytest.mark.parametrize("latency", [0.001, 0.003])
def test_latency_delays_a_step_by_whole_periods(plant, latency):
    """A q_cmd step reaches the servo's torque exactly `latency` after it does with
    no latency (the ideal preset)."""
    reference = _first_change_time(plant, 0.0)
    assert reference < 0.0115
    assert _first_change_time(plant, latency) - reference == pytest.approx(
        latency, abs=1e-6
    )


def test_voltage_limit_is_the_torque_speed_line(plant):
    """With a large position error the current sits on the voltage limit
    i = i_s (1 - q̇/ω0) at every constant speed (and braking is not limited until
    -i_s (1 + q̇/ω0) < -i_max); switched off, it is the driver's i_max."""
    servo, params, q0 = _single_joint_servo(
        plant,
        {"stall_current": 30.0, "no_load_speed": 5.0, "k5": 0.0, "k2": 0.0, "k3": 0.0},
    )
    off, _, _ = _single_joint_servo(
        plant,
        {"stall_current": 30.0, "no_load_speed": 5.0, "k5": 0.0, "k2": 0.0, "k3": 0.0},
        off=("voltage_limit",),
    )
    p = params.vectors(hrp2.JOINT_NAMES)
    q_cmd = q0 + 0.5  # far outside the dead zone: the current command saturates
    for speed in (0.0, 1.0, 2.5, 4.0, 5.0, 6.0):
        v = np.full(30, speed)
        # v >> v_s: the direction gain is K1 (1 + a) for these positive speeds.
        k1 = p["k1"] * (1 + p["k1_asymmetry"] * np.tanh(speed / p["v_coulomb"]))
        limited = servo.joint_torques(q_cmd, q0, v)
        expected = k1 * np.minimum(p["i_max"], 30.0 * (1 - speed / 5.0))
        np.testing.assert_allclose(limited, expected, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(
            off.joint_torques(q_cmd, q0, v), k1 * p["i_max"], rtol=1e-12
        )
    # Braking at speed (error against the motion) draws up to the driver's limit.
    braking = servo.joint_torques(q0 - 0.5, q0, np.full(30, 4.0))
    k1 = p["k1"] * (1 + p["k1_asymmetry"] * np.tanh(4.0 / p["v_coulomb"]))
    np.testing.assert_allclose(
        braking, -k1 * np.minimum(p["i_max"], 30.0 * 1.8), rtol=1e-12
    )


def test_voltage_limit_caps_the_speed_in_closed_loop():
    """Fixed base, the right knee commanded 1.2 rad away: the servo saturates and the
    knee runs at the speed where the torque-speed line meets its friction, below the
    no-load speed; without the limit it runs more than twice as fast."""
    q0 = initial_joint_positions(StationConfig(scenario="fixed_base"))
    q_cmd = q0.copy()
    q_cmd[3] += 1.2
    speeds = {}
    for off in ((), ("voltage_limit",)):
        config = StationConfig(
            scenario="fixed_base",
            sensors=SensorsConfig.noiseless(),
            servo_off=list(off),
        )
        builder = DiagramBuilder()
        station = builder.AddSystem(make_station(config))
        source = builder.AddSystem(ConstantVectorSource(q_cmd))
        builder.Connect(source.get_output_port(), station.GetInputPort("q_cmd"))
        simulator = Simulator(builder.Build())
        ctx = station.GetMyContextFromRoot(simulator.get_context())
        peak = 0.0
        for t in np.arange(1, 40) * 0.005:
            simulator.AdvanceTo(t)
            peak = max(peak, abs(station.GetOutputPort("state_true").Eval(ctx)[30 + 3]))
        speeds[off] = peak
    p = load_servo_params().vectors(["RLEG_JOINT3"])
    w0, i_s = p["no_load_speed"][0], p["stall_current"][0]
    k1 = p["k1"][0] * (1 + p["k1_asymmetry"][0])
    # Torque-speed line = viscous + Coulomb friction (gravity and inertia aside).
    v_friction = (k1 * i_s - p["k3"][0]) / (k1 * i_s / w0 + p["k2"][0])
    assert speeds[()] < w0
    assert speeds[()] == pytest.approx(v_friction, rel=0.1)
    assert speeds[("voltage_limit",)] > 2 * speeds[()]


def test_direction_state_switches_with_hysteresis(plant):
    """The joint moves forward, then back: the direction state (which sets K1± and
    the Coulomb friction) keeps the old direction after the velocity reversal and
    crosses zero only after the joint travelled δ ln 2 back (Dahl), at a different
    position on the way back than on the way out: a hysteresis loop, not sign(q̇)."""
    width = 3e-4
    servo, _, q0 = _single_joint_servo(plant, {"hysteresis_width": width})
    builder = DiagramBuilder()
    builder.AddSystem(servo)
    indexing = hrp2.hrp2_joint_indexing(plant)
    # q(t) = q0 + A sin(2π t): forward until 0.25 s, back until 0.75 s.
    times = np.arange(0.0, 1.0001, 0.001)
    amplitude = 0.005
    x = np.zeros((plant.num_positions() + plant.num_velocities(), len(times)))
    x[indexing.q] = q0[:, None] + amplitude * np.sin(2 * np.pi * times)
    x[plant.num_positions() + indexing.v] = (
        amplitude * 2 * np.pi * np.cos(2 * np.pi * times)
    )
    state = builder.AddSystem(
        TrajectorySource(PiecewisePolynomial.FirstOrderHold(times, x))
    )
    builder.Connect(state.get_output_port(), servo.get_input_port(1))
    command = builder.AddSystem(ConstantVectorSource(q0))
    builder.Connect(command.get_output_port(), servo.get_input_port(0))
    simulator = Simulator(builder.Build())
    context = servo.GetMyContextFromRoot(simulator.get_context())
    s, q = [], []
    for t in times[1:]:
        simulator.AdvanceTo(t)
        s.append(context.get_discrete_state(0).get_value()[3])
        q.append(x[indexing.q[3], int(round(t * 1000))])
    s, q = np.array(s), np.array(q)
    t = times[1:]
    # Right after the reversal at 0.25 s the state still says "forward".
    assert s[np.searchsorted(t, 0.2505)] > 0.99
    # It crosses zero after the joint travelled δ ln 2 back from its peak.
    cross = np.argmax((t > 0.25) & (s < 0))
    travel = q0[3] + amplitude - q[cross]
    assert travel == pytest.approx(width * np.log(2), abs=2e-5)
    # Way out vs way back: at the same position and speed magnitude, opposite states.
    mid_out = np.searchsorted(t, 0.05)
    mid_back = np.searchsorted(t, 0.45)
    assert s[mid_out] > 0.99 and s[mid_back] < -0.99
    # With the hysteresis off, the state follows tanh(q̇ / v_s) at once: the
    # torque at a given (q, q̇) then does not depend on the history.
    off, _, _ = _single_joint_servo(
        plant, {"hysteresis_width": width}, off=("hysteresis",)
    )
    ctx = off.CreateDefaultContext()
    off.get_input_port(0).FixValue(ctx, q0)
    off.get_input_port(1).FixValue(ctx, x[:, 260])
    tanh_torque = off.get_output_port().Eval(ctx)[3]
    expected = off.joint_torques(
        q0, x[indexing.q, 260], x[plant.num_positions() + indexing.v, 260]
    )[3]
    assert tanh_torque == pytest.approx(expected, rel=1e-12)


def test_unknown_mechanism_is_one_clear_error(plant, params):
    with pytest.raises(ValueError, match="unknown mechanism.*'backlash'"):
        EmulatedPositionServo(plant, params, hrp2.JOINT_NAMES, off=("backlash",))
    with pytest.raises(ValueError, match="StationConfig.servo_off"):
        StationConfig(servo_off=["latencies"]).validate()
    with pytest.raises(FileNotFoundError, match="ideal"):
        load_servo_params("no_such_servo.yaml")


def test_calibrated_servo_is_stable_at_1khz(calibrated, plant):
    """The calibrated servo's explicit torques, with the Dahl presliding spring and on
    the voltage limit, are stable per joint with the reflected inertia (and the
    30-joint station holds half-sitting: tests/test_station.py)."""
    reflected = np.array(
        [
            plant.get_joint_actuator(i).default_rotor_inertia()
            * plant.get_joint_actuator(i).default_gear_ratio() ** 2
            for i in plant.GetJointActuatorIndices()
        ]
    )
    assert (
        explicit_stability_margin(calibrated, hrp2.JOINT_NAMES, reflected, 1e-3).max()
        < 1.0
    )


# --- The kernels (hrp2_drake.kernels) ---------------------------------------------


def _kernel_servo(calibrated, plant):
    """The calibrated servo with every mechanism: latency of 1 and 2 periods (1 ms
    extra), hysteresis on some joints, every third joint's encoder unquantized, the
    enabled port and a goal quantum."""
    from dataclasses import replace

    names = hrp2.JOINT_NAMES
    params = type(calibrated)(
        {
            name: (
                replace(calibrated.joints[name], encoder_resolution=0.0)
                if k % 3 == 0
                else calibrated.joints[name]
            )
            for k, name in enumerate(names)
        }
    )
    return EmulatedPositionServo(
        plant,
        params,
        names,
        1e-3,
        hrp2.half_sitting(),
        extra_latency=1e-3,
        enable_port=True,
        command_resolution=2e-5,
    )


def _servo_ticks(servo, plant, ticks: int = 40) -> list[bytes]:
    """What the servo gives over random ticks (its actuation, its motor current, its
    state after each update, and the public per-joint methods), as bytes."""
    indexing = hrp2.hrp2_joint_indexing(plant)
    context = servo.CreateDefaultContext()
    q0 = hrp2.half_sitting()
    x = np.zeros(plant.num_positions() + plant.num_velocities())
    x[indexing.q] = q0
    servo.get_input_port(0).FixValue(context, q0)
    servo.get_input_port(1).FixValue(context, x)
    servo.get_input_port(2).FixValue(context, np.ones(len(q0)))
    servo.ExecuteInitializationEvents(context)
    rng = np.random.default_rng(17)
    out = []
    for tick in range(ticks):
        q = q0 + rng.normal(0.0, 2e-3, len(q0))
        v = rng.normal(0.0, 0.5, len(q0))
        if tick % 5 == 0:
            v[::4] = 0.0  # no travel: the direction state holds
            q[::4] = x[indexing.q][::4]
        x[indexing.q], x[plant.num_positions() + indexing.v] = q, v
        q_cmd = q + rng.normal(0.0, 3e-3, len(q0))
        enabled = (rng.uniform(size=len(q0)) > 0.2).astype(float)
        servo.get_input_port(0).FixValue(context, q_cmd)
        servo.get_input_port(1).FixValue(context, x)
        servo.get_input_port(2).FixValue(context, enabled)
        out.append(servo.get_output_port().Eval(context).tobytes())
        out.append(servo.current(context).tobytes())
        s = context.get_discrete_state(0).get_value()[: len(q0)]
        out.append(servo.joint_torques(q_cmd, q, v, s, enabled).tobytes())
        out.append(servo.motor_current(q_cmd, q, v).tobytes())
        out.append(servo.encoder(q).tobytes())
        context.SetDiscreteState(servo.EvalUniquePeriodicDiscreteUpdate(context))
        out.append(context.get_discrete_state(0).get_value().tobytes())
    return out


def test_kernels_compiled_equal_interpreted(calibrated, plant):
    """The servo's compiled kernels and their Python source give the same outputs
    and states to the bit (elementwise code), tick after tick, every mechanism on;
    both refuse a non-finite command."""
    import contextlib

    from hrp2_drake import kernels

    servo = _kernel_servo(calibrated, plant)
    compiled = _servo_ticks(servo, plant)
    # (With NUMBA_DISABLE_JIT both are the Python source.)
    with kernels.interpreted() if kernels.jit_enabled() else contextlib.nullcontext():
        interpreted = _servo_ticks(_kernel_servo(calibrated, plant), plant)
        context = servo.CreateDefaultContext()
        q_cmd = hrp2.half_sitting()
        q_cmd[7] = np.nan
        servo.get_input_port(0).FixValue(context, q_cmd)
        servo.get_input_port(1).FixValue(
            context, np.zeros(plant.num_positions() + plant.num_velocities())
        )
        servo.get_input_port(2).FixValue(context, np.ones(len(q_cmd)))
        for evaluate in (
            servo.get_output_port().Eval,
            servo.current,
            servo.EvalUniquePeriodicDiscreteUpdate,
        ):
            with pytest.raises(ValueError, match="LLEG_JOINT1"):
                evaluate(context)
    assert len(compiled) == len(interpreted)
    for k, (a, b) in enumerate(zip(compiled, interpreted)):
        assert a == b, k


def test_kernels_give_servo_torque_bit_for_bit_at_the_edges(calibrated, plant):
    """At the law's edges (zeros of either sign, the voltage limit's ends, infinite
    speeds, the driver off, NaN inputs) the kernel gives servo_torque's numbers: the
    same bits, but NaN's sign, which numpy leaves to the CPU."""
    from hrp2_drake.robot.servo import servo_torque

    names = hrp2.JOINT_NAMES
    p = calibrated.vectors(names)
    servo = EmulatedPositionServo(plant, calibrated, names, 1e-3, hrp2.half_sitting())
    rng = np.random.default_rng(23)
    specials = np.array([0.0, -0.0, np.inf, -np.inf, np.nan])
    n = len(names)
    for trial in range(300):
        error = rng.normal(0.0, 1e-3, n)
        error[rng.integers(0, 3, n) == 0] = rng.choice([0.0, -0.0])
        v = rng.normal(0.0, 1.0, n)
        pick = rng.integers(0, 6, n)
        v = np.where(pick == 1, p["no_load_speed"], v)
        v = np.where(pick == 2, -p["no_load_speed"], v)
        v = np.where(pick == 3, rng.choice([0.0, -0.0], n), v)
        direction = rng.uniform(-1.0, 1.0, n)
        direction[rng.integers(0, 4, n) == 0] = 0.0
        if trial % 3 == 0:
            error[rng.integers(n)] = rng.choice(specials)
            v[rng.integers(n)] = rng.choice(specials)
            direction[rng.integers(n)] = rng.choice(specials)
        enabled = rng.choice([0.0, 0.5, 1.0, np.nan], n) if trial % 2 else None
        with np.errstate(invalid="ignore"):  # inf / inf, inf · 0: NaN
            expected = servo_torque(p, error, v, direction, enabled)
            actual = kernel_torque(servo, error, v, direction, enabled)
        nan = np.isnan(expected)
        np.testing.assert_array_equal(np.isnan(actual), nan)
        assert actual[~nan].tobytes() == expected[~nan].tobytes(), trial


def test_warm_up_then_frozen_the_servo_runs_and_a_new_signature_raises(
    calibrated, plant
):
    """The constructor compiles (or loads) every kernel for a tick's types; frozen,
    the servo's output, update and methods run, and a kernel called with float32
    arrays raises instead of compiling."""
    from hrp2_drake import kernels
    from hrp2_drake.robot import servo as servo_module

    if not kernels.jit_enabled():
        pytest.skip("NUMBA_DISABLE_JIT: nothing compiles")
    servo = _kernel_servo(calibrated, plant)
    unlatched = EmulatedPositionServo(
        plant, calibrated, hrp2.JOINT_NAMES, 1e-3, hrp2.half_sitting(), off=["latency"]
    )
    # kernels.freeze() on the servo's kernels (freeze() itself needs every kernel of
    # the process compiled, those of the modules this test imports and does not run
    # too): each has its signature after the constructor's warm_up.
    mine = [
        dispatcher
        for dispatcher in kernels.kernels()
        if dispatcher.py_func.__module__ == servo_module.__name__
    ]
    assert len(mine) >= 6 and all(dispatcher.signatures for dispatcher in mine)
    for dispatcher in mine:
        dispatcher.disable_compile()
    try:
        compiled = _servo_ticks(servo, plant, ticks=3)
        context = unlatched.CreateDefaultContext()
        x = np.zeros(plant.num_positions() + plant.num_velocities())
        unlatched.get_input_port(0).FixValue(context, hrp2.half_sitting())
        unlatched.get_input_port(1).FixValue(context, x)
        assert np.all(np.isfinite(unlatched.get_output_port().Eval(context)))
        context.SetDiscreteState(unlatched.EvalUniquePeriodicDiscreteUpdate(context))
        servo_module._encoder_readings(servo._constants, np.zeros(30), np.zeros(30))
        with pytest.raises(TypeError, match="float32"):
            servo_module._encoder_readings(
                servo._constants, np.zeros(30, dtype=np.float32), np.zeros(30)
            )
    finally:
        for dispatcher in mine:
            dispatcher.disable_compile(False)
    assert compiled == _servo_ticks(_kernel_servo(calibrated, plant), plant, ticks=3)
