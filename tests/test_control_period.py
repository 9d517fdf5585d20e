"""The torque-control chain runs at the robot's control period: a robot on a servo bus
(the XL330 pendulum at 100-500 Hz) gets every step updated once per period and
Savitzky-Golay derivatives in the period's units, in the diagram and in the fused
controller that `hrp2-drake control` clocks on the bus."""

import dataclasses

import numpy as np
import pytest

from hrp2_drake.assembly.builders import JointReference, torque_chain_parts
from hrp2_drake.assembly.torque_control import TorqueControlConfig, at_period
from hrp2_drake.control.fused import FusedController
from hrp2_drake.description import load_robot_description
from hrp2_drake.estimation.estimator_config import estimation_delay
from hrp2_drake.identification.motor_model import MotorModel


def _parts(period: float):
    robot = load_robot_description("xl330_pendulum")
    robot = dataclasses.replace(
        robot, sensors=dataclasses.replace(robot.sensors, period=period)
    )
    model = MotorModel(["servo"], np.array([1.44]), np.array([0.06]), np.zeros(1))
    reference = JointReference.hold(np.zeros(1), 2.0)
    config = at_period(TorqueControlConfig(), period)
    return torque_chain_parts(robot, reference, model, config, period=period)


@pytest.mark.parametrize("period", [0.002, 0.005, 0.01])
def test_every_step_at_the_control_period(period):
    parts = _parts(period)
    assert parts.period == period
    for config in (
        parts.estimator_config,
        parts.id_config,
        parts.controller_config,
    ):
        assert config.period == pytest.approx(period, rel=1e-12)
    # The same 80 ms window as at 1 kHz, in samples of this period.
    assert parts.estimator_config.window * period == pytest.approx(0.08, abs=period)
    # The settings' delay at this period is the chain's (what the balance
    # experiment shifts the true τ by): (N − 1)/2 periods.
    estimator = at_period(TorqueControlConfig(), period).estimator
    assert estimator.delay(period) == estimation_delay(parts.estimator_config)
    assert estimator.delay(period) == pytest.approx((estimator.window - 1) / 2 * period)


def test_fused_derivatives_at_200_hz():
    """Ticked every 5 ms on q = 0.2 sin(2π 0.4 t), the filters' q̇ and q̈ peak at the
    sinusoid's (1%), not 5 and 25 times it (derivatives taken with a 1 ms period)."""
    period = 0.005
    controller = FusedController(_parts(period))
    w, amplitude = 2 * np.pi * 0.4, 0.2
    controller.sensor_buffer[:] = 0.0
    controller.initialize(0.0)
    v, a = [], []
    for k in range(1, int(2.0 / period)):
        t = k * period
        controller.sensor_buffer[0] = amplitude * np.sin(w * t)
        controller.sensor_buffer[1:] = t
        controller.tick(t)
        if t > 0.5:
            v.append(controller.encoder_filter.derivative[0])
            a.append(controller.encoder_filter.second_derivative[0])
    assert np.max(np.abs(v)) == pytest.approx(amplitude * w, rel=0.01)
    assert np.max(np.abs(a)) == pytest.approx(amplitude * w * w, rel=0.01)
