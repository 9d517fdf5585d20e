"""The balance control's closed loop (hrp2_drake/assembly/balance.py): the fused
controller with its balance front end (hrp2_drake/control/fused.py) against the
diagram of separate systems on the standing HRP-2, and the fused controller's QP
fault (an event, a fallback for the supervisor) with compiling frozen."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.trajectories import PiecewisePolynomial

from hrp2_drake import kernels
from hrp2_drake.assembly.balance import (
    BalanceControlConfig,
    balance_chain_parts,
    build_balance_control,
    resolved,
)
from hrp2_drake.assembly.builders import JointReference, simulated_station
from hrp2_drake.assembly.torque_control import EstimatorSettings, TorqueControlConfig
from hrp2_drake.control.balance import BalanceConfig, BalanceFault
from hrp2_drake.control.balance_reference import StandingIk, leg_joints
from hrp2_drake.control.fused import FusedController
from hrp2_drake.control.safety import describe_faults
from hrp2_drake.control.torque_chain import EventKind, torque_chain
from hrp2_drake.hardware.in_process import run_in_process
from hrp2_drake.robot.ground_truth import true_motor_model
from hrp2_drake.robot.station import StationConfig, make_station, standing_positions
from hrp2_drake.simulation import add_loggers, logs_to_arrays

STANDING = StationConfig(scenario="standing")
DURATION = 0.8  # s: torque control from 0.2 s, the supervisor's ramp, 0.55 s of it
START = 0.2  # s


def _setup(balance: BalanceConfig | None = None):
    """HRP-2 standing: its description, the standing pose, the joints' reference
    (the pose held), a CoM reference 1 cm to the left of the pose's CoM, the legs'
    true motor model and a fast config (window 21, torque control from START)."""
    robot = STANDING.description()
    standing = standing_positions(robot)
    plant = robot.make_plant()
    soles = list(robot.contacts.soles)
    ik = StandingIk(plant, robot.joints, soles, standing)
    reference = JointReference.hold(ik.joint_angles(standing), DURATION + 1.0)
    com = np.r_[ik.com(standing) + [0.0, 0.01, 0.0], np.zeros(6)]
    com_reference = PiecewisePolynomial(com.reshape(9, 1))
    motor_model = true_motor_model(robot, leg_joints(plant, robot.joints, soles))
    config = BalanceControlConfig(
        balance=balance or BalanceConfig(),
        torque=TorqueControlConfig(
            start_time=START, estimator=EstimatorSettings(window=21)
        ),
    )
    return robot, standing, reference, com_reference, motor_model, config


def _run(fused: bool) -> dict[str, np.ndarray]:
    robot, standing, reference, com_reference, motor_model, config = _setup()
    _, station, period = simulated_station(STANDING)
    control = build_balance_control(
        robot,
        station,
        reference,
        com_reference,
        standing,
        motor_model,
        config,
        control_period=period,
        fused=fused,
    )
    builder = DiagramBuilder()
    diagram = builder.AddSystem(control.diagram)
    loggers = add_loggers(
        builder, {n: diagram.GetOutputPort(n) for n in control.output_names()}, period
    )
    simulator = Simulator(builder.Build())
    simulator.AdvanceTo(DURATION)
    return logs_to_arrays(loggers, simulator.get_context())


@pytest.mark.slow
def test_fused_balance_control_equals_the_separate_systems():
    separate, fused = _run(fused=False), _run(fused=True)
    assert sorted(separate) == sorted(fused)
    for name in separate:
        # Measured: bitwise equal (the same steps on the same numbers).
        np.testing.assert_allclose(
            fused[name], separate[name], rtol=0, atol=1e-12, err_msg=name
        )
    # Not a trivial run: the QP solved every tick, the supervisor ramped to torque
    # control and the Δq controller drove the legs; the base from the soles is
    # the plant's base (the soles stay flat).
    assert separate["balance_fault_count"][-1, 0] == 0
    assert separate["supervisor_mode"][-1, 0] == 1.0
    assert np.abs(separate["delta_q"]).max() > 1e-3
    base_z = separate["base_state"][-1, 6]
    assert abs(base_z - separate["state_true"][-1, 6]) < 1e-3


def test_a_qp_fault_is_an_event_and_keeps_position_control():
    """An infeasible QP (no torque, no joint acceleration allowed) at every tick:
    one BALANCE_FAULT event (when it starts) and the supervisor's fault in the same
    tick (one tick from sample to command), the supervisor never hands over to
    torque control, and the command is the reference. The kernels compiled by
    warm_up alone: compiling is frozen while the loop runs. Solved by pydrake's OSQP,
    which calls this problem infeasible (daqp, the default, finds its bounds'
    working set overdetermined: a SOLVER_FAILED; with 1 % of the torque limits it
    alternates between the two codes, an event at each change)."""
    balance = BalanceConfig(
        torque_limit_scale=0.0, acceleration_limit=0.0, solver="osqp"
    )
    robot, standing, reference, com_reference, motor_model, config = _setup(balance)
    period = STANDING.sensors_config().period
    config = resolved(robot, config)
    controller = FusedController(
        balance_chain_parts(
            robot, reference, standing, motor_model, config, period=period
        )
    )
    controller.warm_up()
    make_station(STANDING)  # its servo's and sensors' kernels, before freezing
    controller.com_ref[:] = com_reference.value(0.0).ravel()
    ticks = int(0.3 / period)
    with kernels.compile_disabled():
        out = run_in_process(STANDING, controller, reference, ticks)
    # The QP's fault when it starts, and the supervisor's in the same tick (its
    # controller fallback: the Δq controller's plus the QP's code of this tick).
    assert controller.recorded_events() == [
        (0.0, EventKind.BALANCE_FAULT, BalanceFault.INFEASIBLE),
        (0.0, EventKind.SUPERVISOR_FAULT, 128),
    ]
    assert describe_faults(128) == "torque controller fallback"
    signals = controller.signals()
    assert signals["balance_fault"][0] == BalanceFault.INFEASIBLE
    assert signals["balance_fault_count"][0] == ticks
    assert np.all(np.isfinite(signals["tau_desired"]))
    assert controller.torque_active() == 0.0
    np.testing.assert_array_equal(out[-1][0], reference.at(0.0)[0])


def test_the_base_reads_its_own_filter_and_the_gyro():
    """The base's state comes from a filter of its own (BaseEstimateConfig: 10
    samples by default, order 2, centred, over the encoders and the gyro) and the
    gyro's offset is the estimator's found one; `imu: false` leaves the gyro out;
    a bad setting is one line naming it."""
    robot, standing, reference, _, motor_model, config = _setup()
    period = STANDING.sensors_config().period
    config.torque.estimator.imu_offset = [0.0, 0.0, 0.0, 0.002, -0.001, 0.003]
    for imu in (True, False):
        config.base.imu = imu
        parts = balance_chain_parts(
            robot,
            reference,
            standing,
            motor_model,
            resolved(robot, config),
            period=period,
        )
        rows = {row.name: row for row in torque_chain(parts).rows}
        names = list(rows)
        assert names.index("base_filter") < names.index("base")
        step = rows["base_filter"].make_step()
        size = len(robot.joints) + (3 if imu else 0)
        assert step.num_signals() == size and step.windows() == (10,) * size
        assert ("gyro" in rows["base"].inputs) is imu
        if imu:
            assert parts.balance.imu.frame == robot.imu_frame
            assert parts.balance.imu.gyro_offset == [0.002, -0.001, 0.003]
        else:
            assert parts.balance.imu is None
    for field, value, message in [
        ("velocity_window", 2, r"base.velocity_window: an integer >= 3"),
        ("imu_gain", -1.0, r"base.imu_gain must be >= 0, got -1.0"),
    ]:
        bad = BalanceControlConfig()
        setattr(bad.base, field, value)
        with pytest.raises(ValueError, match=message) as raised:
            bad.validate()
        assert "\n" not in str(raised.value)
