"""Sensor faults: the station's FaultInjector (each kind) and what the closed loop does
with a bad sample (the filters hold it, the torque controller falls back to position
control, nothing raises)."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder

from hrp2_drake.assembly.builders import (
    JointReference,
    build_torque_control,
    simulated_station,
)
from hrp2_drake.assembly.torque_control import (
    ControllerSettings,
    EstimatorSettings,
    TorqueControlConfig,
)
from hrp2_drake.paper import hrp2
from hrp2_drake.paper.motion import run_controller
from hrp2_drake.robot.faults import FaultInjector, SensorFault
from hrp2_drake.robot.station import StationConfig, initial_joint_positions


def _inject(faults, times):
    """The injector's output at `times` for a ramp input x(t) = t (1 kHz samples)."""
    from pydrake.systems.primitives import TrajectorySource
    from pydrake.trajectories import PiecewisePolynomial

    grid = np.arange(0.0, 0.1, 0.001)
    ramp = PiecewisePolynomial.ZeroOrderHold(grid, np.tile(grid, (3, 1)))
    builder = DiagramBuilder()
    source = builder.AddSystem(TrajectorySource(ramp))
    injector = builder.AddSystem(FaultInjector(3, faults, 0.001))
    builder.Connect(source.get_output_port(), injector.get_input_port())
    simulator = Simulator(builder.Build())
    context = injector.GetMyContextFromRoot(simulator.get_context())
    out = []
    for t in times:
        simulator.AdvanceTo(t)
        out.append(injector.get_output_port().Eval(context).copy())
    return np.array(out)


def test_each_fault_kind():
    times = [0.0095, 0.0105, 0.0125, 0.0155, 0.0205]
    # NaN burst on entry 1 from 10 to 15 ms.
    nan = _inject([SensorFault("s", "nan", 0.010, 0.005, [1])], times)
    assert np.isnan(nan[1:3, 1]).all() and np.isfinite(nan[:, [0, 2]]).all()
    assert np.isfinite(nan[[0, 3, 4]]).all()
    # Freeze: holds a value sampled before the fault.
    frozen = _inject([SensorFault("s", "freeze", 0.010, 0.005)], times)
    assert frozen[1, 0] == frozen[2, 0] and frozen[2, 0] < 0.010
    assert frozen[4, 0] > 0.019  # released
    # Zero, bias, one-period glitch.
    zero = _inject([SensorFault("s", "zero", 0.010, 0.005)], times)
    assert np.all(zero[1:3] == 0.0)
    bias = _inject([SensorFault("s", "bias", 0.010, np.inf, [], [0.5])], times)
    ramp = np.floor(np.array(times) * 1000 + 1e-6) / 1000  # the input at those times
    np.testing.assert_allclose(bias[:, 0], ramp + [0.0, 0.5, 0.5, 0.5, 0.5], atol=1e-12)
    glitch = _inject(
        [SensorFault("s", "glitch", 0.010, 1.0, [2], [1.0])], [0.0105, 0.0115]
    )
    assert glitch[0, 2] > 1.0 and glitch[1, 2] < 0.1


def test_fault_config_errors_name_the_field():
    with pytest.raises(ValueError, match=r"faults\[0\].signal.*wrench_nowhere"):
        StationConfig(faults=[SensorFault("wrench_nowhere")]).validate()
    with pytest.raises(ValueError, match=r"faults\[0\].kind"):
        StationConfig(faults=[SensorFault("q_measured", "melt")]).validate()
    with pytest.raises(ValueError, match=r"faults\[0\].indices"):
        StationConfig(
            faults=[SensorFault("imu_angular_velocity", indices=[3])]
        ).validate()


def test_a_campaign_whose_runs_raised_has_no_yes_verdict():
    """Runs that raised are not judged: every check names them, none holds."""
    from hrp2_drake.paper.faults import _verdict

    raised = "ValueError: k6 must be > 0"
    results = [
        {"experiment": "motion", "case": case, "raised": raised}
        for case in ("no fault", "position control", "F/T NaN burst (5 ms)")
    ]
    verdict = _verdict(results)
    assert not any(value for value in verdict.values() if isinstance(value, bool))
    assert (
        "motion: F/T NaN burst (5 ms) (raised, not judged)" in verdict["detected_late"]
    )


@pytest.mark.slow
@pytest.mark.parametrize(
    "fault",
    [
        SensorFault("wrench_right_foot", "nan", 0.7, 0.005),
        SensorFault("q_measured", "nan", 0.7, 0.005, [3]),
        SensorFault("wrench_right_foot", "freeze", 0.7, 0.1),
    ],
    ids=["ft_nan_burst", "encoder_nan_burst", "ft_freeze"],
)
def test_a_bad_sample_hands_back_to_the_servo_and_torque_control_resumes(fault):
    """A fault during torque control (fixed base, holding the pose): nothing raises,
    the supervisor detects it within 10 ms and ramps to position control without a
    step in q_cmd, and ramps back once the fault has been clear for reentry_time."""
    station = StationConfig(scenario="fixed_base", servo_file="ideal", faults=[fault])
    q0 = initial_joint_positions(station)
    reference = JointReference.hold(q0, 1.5)
    config = TorqueControlConfig(
        controller=ControllerSettings(k6=1.0), estimator=EstimatorSettings(window=40)
    )
    robot, simulated, period = simulated_station(station)
    control = build_torque_control(
        robot,
        simulated,
        reference,
        hrp2.true_motor_model(servo_file="ideal"),
        config,
        control_period=period,
    )
    signals = run_controller(control, 1.3, "fault", stream=open("/dev/null", "w"))
    t = signals["t"]
    fault_bits = signals["supervisor_fault"][:, 0]
    mode = signals["supervisor_mode"][:, 0]
    detected = t[np.argmax((t >= fault.start) & (fault_bits > 0))]
    assert fault.start <= detected <= fault.start + 0.010
    assert np.all(fault_bits[t < fault.start] == 0)
    assert mode[(t > 0.56) & (t < fault.start)].min() == 1.0  # torque control ran
    assert mode[(t > detected + 0.06) & (t < detected + 0.1)].max() == 0.0
    assert mode[-1] == 1.0  # resumed
    assert np.all(np.isfinite(signals["q_cmd"]))
    leg = [hrp2.JOINT_NAMES.index(j) for j in hrp2.RIGHT_LEG]
    steps = np.abs(np.diff(signals["q_cmd"][:, leg], axis=0)).max()
    assert steps < 0.002  # rad per period, mode switches included
    error = np.abs(signals["q_ref"][:, leg] - signals["q_measured"][:, leg])
    assert np.nanmax(error[t > 0.6]) < 0.01


def test_model_error_and_extra_latency():
    """The controllers' wrong model: every link's mass within ±20%, the same joints
    and actuators; the extra latency: whole periods on every joint's command."""
    from pydrake.multibody.plant import MultibodyPlant

    from hrp2_drake.robot.servo import EmulatedPositionServo, load_servo_params

    exact, wrong = MultibodyPlant(0.0), MultibodyPlant(0.0)
    hrp2.add_hrp2(exact)
    hrp2.add_hrp2_with_model_error(wrong, 0.2, seed=3)
    exact.Finalize()
    wrong.Finalize()
    ratios = np.array(
        [
            wrong.get_body(i).default_mass() / exact.get_body(i).default_mass()
            for i in exact.GetBodyIndices(exact.GetModelInstanceByName("hrp2"))
            if exact.get_body(i).default_mass() > 0
        ]
    )
    assert np.all(np.abs(ratios - 1) <= 0.2) and np.std(ratios) > 0.05
    assert wrong.num_actuators() == exact.num_actuators() == 30
    with pytest.raises(ValueError, match="error"):
        hrp2.add_hrp2_with_model_error(MultibodyPlant(0.0), 1.5)
    params = load_servo_params()
    servo = EmulatedPositionServo(
        exact, params, hrp2.JOINT_NAMES, 1e-3, extra_latency=0.002
    )
    base = EmulatedPositionServo(exact, params, hrp2.JOINT_NAMES, 1e-3)
    np.testing.assert_array_equal(servo._delays, base._delays + 2)  # in periods


def test_sensor_clock_stops_for_a_frozen_driver():
    from hrp2_drake.robot.faults import SensorClock

    clock = SensorClock(["a", "b"], [SensorFault("b", "freeze", 0.010, 0.005)], 0.001)
    simulator = Simulator(clock)
    context = simulator.get_context()
    stamps = {}
    for t in (0.0085, 0.0125, 0.0175):
        simulator.AdvanceTo(t)
        stamps[t] = clock.get_output_port().Eval(context).copy()
    np.testing.assert_allclose(stamps[0.0085], [0.008, 0.008])
    np.testing.assert_allclose(stamps[0.0125], [0.012, 0.009])  # b stopped at 9 ms
    np.testing.assert_allclose(stamps[0.0175], [0.017, 0.017])
