"""The robot calibrated as a real one is (issue 35, item 1): the station's "lowered"
scenario (hanging, feet free, then put down by the hoist), the calibration that finds
the F/T offsets lifted and the CoM offset standing, the estimator starting with given
offsets, the QP's CoM reference moved by the CoM offset; the settings' one-line
errors."""

import re
from dataclasses import replace

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource
from pydrake.trajectories import PiecewisePolynomial

from hrp2_drake.assembly.balance import offset_com_reference
from hrp2_drake.assembly.torque_control import TorqueControlConfig, check_for_robot
from hrp2_drake.estimation import estimator_config as estimation_config
from hrp2_drake.estimation.estimator_step import FloatingBaseTorqueEstimatorStep
from hrp2_drake.experiments.balance.calibration import CalibrationSettings, calibrate
from hrp2_drake.robot.station import (
    LoweringConfig,
    StationConfig,
    initial_joint_positions,
    make_station,
)

STANDING = StationConfig(scenario="standing")


def test_lowered_hangs_with_its_feet_free_then_stands_on_its_soles():
    """Hanging, the soles read no contact (their readings within a few N of the
    feet's weight and the biases); after the hoist, the soles carry the robot's
    weight, the strings are slack (the hoist pulls nothing) and the soles stand flat
    and still."""
    config = replace(STANDING, scenario="lowered")
    robot = config.description()
    station = make_station(config)
    builder = DiagramBuilder()
    station = builder.AddSystem(station)
    hold = builder.AddSystem(ConstantVectorSource(initial_joint_positions(config)))
    builder.Connect(hold.get_output_port(), station.GetInputPort("q_cmd"))
    simulator = Simulator(builder.Build())
    context = simulator.get_context()
    plant = station.GetSubsystemByName("plant")
    hoist = station.GetSubsystemByName("hoist")
    mass = plant.CalcTotalMass(plant.GetMyContextFromRoot(context))
    feet = ("wrench_right_foot", "wrench_left_foot")

    def normal_forces():
        station_context = station.GetMyContextFromRoot(context)
        return [station.GetOutputPort(f).Eval(station_context)[5] for f in feet]

    simulator.AdvanceTo(0.8)
    assert max(abs(f) for f in normal_forces()) < 20.0  # a foot's weight, biases
    simulator.AdvanceTo(3.0)
    assert sum(normal_forces()) == pytest.approx(mass * 9.81, rel=0.03)
    assert hoist.get_output_port().Eval(hoist.GetMyContextFromRoot(context)) == []
    plant_context = plant.GetMyContextFromRoot(context)
    assert np.abs(plant.GetVelocities(plant_context)[:6]).max() < 1e-3
    for sole in robot.contacts.soles:
        R = plant.GetFrameByName(sole).CalcPoseInWorld(plant_context).rotation()
        assert abs(R.matrix()[2, 2] - 1.0) < 1e-5  # flat


def test_calibration_finds_the_biases_lifted_and_no_com_offset():
    """The F/T offsets found lifted are the simulated sensors' biases (what the
    calibration never reads: compared here) to 0.1 N and 0.01 N·m, the IMU's found
    standing to 0.01 m/s² and 0.001 rad/s (a tenth of the biases); with the exact
    model the CoM offset standing is under 1 mm."""
    result = calibrate(STANDING, 40, CalibrationSettings())
    sensors = STANDING.sensors_config()
    acc, gyro = result["imu_offset"][:3], result["imu_offset"][3:]
    np.testing.assert_allclose(acc, sensors.accelerometer.vectors(3, "")[1], atol=0.01)
    np.testing.assert_allclose(gyro, sensors.gyroscope.vectors(3, "")[1], atol=0.001)
    for name, offset in result["ft_offsets"].items():
        _, bias = sensors.force_torque_noise(name).vectors(6, name)
        np.testing.assert_allclose(offset[:3], bias[:3], atol=0.01)
        np.testing.assert_allclose(offset[3:], bias[3:], atol=0.1)
    assert np.linalg.norm(result["com_offset_m"]) < 1e-3


def test_the_estimator_starts_with_the_given_offsets():
    """The F/T offsets it is given are its offsets from the start (and after a
    reset); the IMU's offsets are subtracted from its readings: τ̂ with readings
    offset by them equals τ̂ without offsets on the readings themselves."""
    robot = STANDING.description()
    offset = [0.1, -0.2, 0.3, 1.0, -2.0, 3.0]
    config = estimation_config.estimator_config(robot, offsets={"left_foot": offset})
    step = FloatingBaseTorqueEstimatorStep(robot.make_plant(), config)
    imu = [0.05, -0.03, 0.04, 0.002, -0.001, 0.0015]
    shifted = FloatingBaseTorqueEstimatorStep(
        robot.make_plant(), replace(config, imu_offset=imu)
    )
    n, k = len(robot.joints), len(robot.sensor_names())
    rng = np.random.default_rng(0)
    q, v, vdot = (rng.normal(0, 0.1, n) for _ in range(3))
    acc, gyro = np.array([0.3, -0.2, 9.7]), np.array([0.01, 0.02, -0.01])
    alpha, wrenches = np.zeros(3), rng.normal(0, 5, (k, 6))
    step.step(0.0, q, v, vdot, acc, gyro, alpha, wrenches)
    shifted.step(0.0, q, v, vdot, acc + imu[:3], gyro + imu[3:], alpha, wrenches)
    np.testing.assert_allclose(shifted.tau, step.tau, atol=1e-9)
    offsets = step.offsets()
    np.testing.assert_array_equal(
        offsets[robot.sensor_names().index("left_foot")], offset
    )
    assert np.count_nonzero(offsets) == 6
    step.reset()  # the initial state keeps them
    np.testing.assert_array_equal(step.offsets(), offsets)


def test_settings_errors_name_the_field():
    robot = STANDING.description()
    control = TorqueControlConfig()
    control.estimator.offsets = {"left_knee": [0.0] * 6}
    with pytest.raises(ValueError, match=r"^T\.estimator\.offsets: \['left_knee'\]"):
        check_for_robot(control, robot, "T")
    control.estimator.offsets = {"left_foot": [0.0] * 5}
    with pytest.raises(ValueError, match=r"estimator\.offsets\['left_foot'\]: 6"):
        control.validate()
    early = CalibrationSettings(offset_time=1.0)
    with pytest.raises(ValueError, match="offset_time: .* must end before the hoist"):
        early.validate()
    window = CalibrationSettings(com_window=[1.5, 3.0])
    with pytest.raises(ValueError, match=r"com_window: .* after the hoist is done"):
        window.validate()
    with pytest.raises(ValueError, match=r"StationConfig\.lowering\.duration"):
        replace(STANDING, lowering=LoweringConfig(duration=0.0)).validate()


def test_the_com_offset_moves_the_qps_reference_by_minus_it():
    times = [0.0, 1.0, 2.0]
    values = np.arange(27.0).reshape(9, 3)
    reference = PiecewisePolynomial.FirstOrderHold(times, values)
    moved = offset_com_reference(reference, [0.01, -0.02])
    for t in (0.0, 0.5, 2.0):
        difference = moved.value(t)[:, 0] - reference.value(t)[:, 0]
        np.testing.assert_allclose(difference, [-0.01, 0.02] + [0.0] * 7, atol=1e-12)
    assert offset_com_reference(reference, [0.0, 0.0]) is reference


def test_a_robot_without_strings_is_not_calibrated_but_says_so(tmp_path):
    """A robot on its soles but without scenarios.hanging cannot be lifted: one line
    naming the setting that runs it uncalibrated."""
    from pathlib import Path

    from hrp2_drake.experiments.balance.runner import BalanceExperimentConfig

    folder = Path(STANDING.description().source_file).parent
    text = (folder / "robot.yaml").read_text()
    for key in ("model_file", "trajectory_file", "servo_file"):
        text = re.sub(
            rf"^{key}: (\S+)",
            lambda m, key=key: f"{key}: {folder / m.group(1)}",
            text,
            flags=re.M,
        )
    text = text.replace("    body: CHEST_LINK1\n", '    body: ""\n').replace(
        "    points: [[0.008, -0.25, 0.181], [0.008, 0.25, 0.181]]", "    points: []"
    )
    (tmp_path / "robot.yaml").write_text(text)
    config = BalanceExperimentConfig()
    config.station.robot = str(tmp_path / "robot.yaml")
    with pytest.raises(ValueError, match="no scenarios.hanging .*enabled: false"):
        config.validate()
    config.calibration.enabled = False
    config.validate()
