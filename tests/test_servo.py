"""Hrp2ServoEmulation: the law itself, the effective motor model in closed loop on
the simulated robot, and the stability of the explicit torques at 1 kHz."""

import numpy as np
import pytest
from pydrake.multibody.math import SpatialForce
from pydrake.multibody.plant import ExternallyAppliedSpatialForce, MultibodyPlant
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import (
    ConstantValueSource,
    ConstantVectorSource,
    TrajectorySource,
)
from pydrake.common.value import AbstractValue
from pydrake.trajectories import PiecewisePolynomial

from hrp2_drake.robot import model
from hrp2_drake.robot.sensors import SensorsConfig
from hrp2_drake.robot.servo import (
    Hrp2ServoEmulation,
    effective_motor_parameters,
    explicit_stability_margin,
    load_servo_params,
)
from hrp2_drake.robot.station import StationConfig, initial_joint_positions, make_station

# The paper's Table 1 (Kτ in rad/(N·m), Kv in s), right leg.
TABLE1_K_TAU = np.array([0.212, 0.030, 0.12, 0.051, 0.177, 0.240]) * 1e-3
TABLE1_K_V = np.array([13.0, 6.332, 7.0, 6.561, 7.698, 6.0]) * 1e-3


@pytest.fixture(scope="module")
def params():
    return load_servo_params()


@pytest.fixture(scope="module")
def plant():
    plant = MultibodyPlant(0.001)
    model.add_hrp2(plant)
    plant.Finalize()
    return plant


def test_data_file_matches_table1(params):
    eff = effective_motor_parameters(params, model.RIGHT_LEG)
    # The data file keeps 9 significant digits.
    np.testing.assert_allclose(eff["k_tau"], TABLE1_K_TAU, rtol=1e-7)
    np.testing.assert_allclose(eff["k_v"], TABLE1_K_V, rtol=1e-7)
    # Left leg mirrors the right; every joint has a plausible, positive model.
    eff_all = effective_motor_parameters(params, model.JOINT_NAMES)
    np.testing.assert_allclose(eff_all["k_tau"][6:12], TABLE1_K_TAU, rtol=1e-7)
    assert np.all(eff_all["k_tau"] > 0) and np.all(eff_all["k_v"] > 0)


def test_servo_law_slope_is_k_tau(params, plant):
    """Outside the dead zone, at rest, Δq = Kτ τ + deadzone·sign(τ) exactly."""
    servo = Hrp2ServoEmulation(plant, params, model.JOINT_NAMES)
    context = servo.CreateDefaultContext()
    plant_context = plant.CreateDefaultContext()
    indexing = model.hrp2_joint_indexing(plant)
    q = plant.GetPositions(plant_context)
    # Joint angles on the encoder grid, so the quantization adds nothing.
    res = params.vectors(model.JOINT_NAMES)["encoder_resolution"]
    q[indexing.q] = np.round(model.half_sitting() / res) * res
    x = np.concatenate([q, np.zeros(plant.num_velocities())])
    servo.get_input_port(1).FixValue(context, x)
    eff = effective_motor_parameters(params, model.JOINT_NAMES)
    p = params.vectors(model.JOINT_NAMES)
    peak = p["k1"] * p["i_max"]  # N·m at current saturation
    # Commands for 20% and 40% of the peak torque, both signs, past the dead zone.
    dqs = [s * (eff["deadzone"] + eff["k_tau"] * f * peak) for s in (1, -1) for f in (0.2, 0.4)]
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
    servo = Hrp2ServoEmulation(plant, params, model.JOINT_NAMES)
    context = servo.CreateDefaultContext()
    q_cmd = model.half_sitting()
    q_cmd[3] = np.nan
    servo.get_input_port(0).FixValue(context, q_cmd)
    servo.get_input_port(1).FixValue(
        context, np.zeros(plant.num_positions() + plant.num_velocities())
    )
    with pytest.raises(ValueError, match="RLEG_JOINT3"):
        servo.get_output_port().Eval(context)


def test_explicit_torques_are_stable_at_1khz(params, plant):
    """Spectral radius < 1 per joint with the reflected inertia as inertia bound."""
    # Actuators are in joint order (checked by hrp2_joint_indexing).
    model.hrp2_joint_indexing(plant)
    reflected = np.array(
        [
            plant.get_joint_actuator(i).default_rotor_inertia()
            * plant.get_joint_actuator(i).default_gear_ratio() ** 2
            for i in plant.GetJointActuatorIndices()
        ]
    )
    radius = explicit_stability_margin(params, model.JOINT_NAMES, reflected, 1e-3)
    assert radius.max() < 1.0
    # ...and the same servo without the rotor inertia would not be stable.
    light = explicit_stability_margin(params, model.JOINT_NAMES, np.full(30, 1e-3), 1e-3)
    assert light.max() > 1.0


def _fixed_base(q_cmd_system, external_force=None):
    config = StationConfig(scenario="fixed_base", sensors=SensorsConfig.noiseless())
    builder = DiagramBuilder()
    station = builder.AddSystem(make_station(config))
    source = builder.AddSystem(q_cmd_system)
    builder.Connect(source.get_output_port(), station.GetInputPort("q_cmd"))
    if external_force is not None:
        push = builder.AddSystem(ConstantValueSource(AbstractValue.Make(external_force)))
        builder.Connect(push.get_output_port(), station.GetInputPort("applied_spatial_force"))
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
    eff = effective_motor_parameters(params, model.RIGHT_LEG)
    plant = MultibodyPlant(0.0)
    model.add_hrp2(plant)
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
    eff_pos = effective_motor_parameters(params, model.RIGHT_LEG, direction=+1)
    eff_neg = effective_motor_parameters(params, model.RIGHT_LEG, direction=-1)
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
