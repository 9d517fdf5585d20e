"""ROBOTIS' OpenMANIPULATOR-X, models/open_manipulator_x: four Dynamixel XM430-W350-T
position servos on one bus (IDs 11-14, 1 Mbit/s), fixed base, rigid gripper, its
servo from datasheets (no logs yet).

- The description loads, its bus validates and carries the sensors' period.
- The station builds; holding the home pose under position control, the arm sags by
  what the servo's stiffness and gravity say, to within the encoder's quantum.
- The emulated servo is stable under explicit integration at the plant's step.
"""

import math

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator

from hrp2_drake.description import load_robot_description
from hrp2_drake.description.bus import check_bus_period
from hrp2_drake.robot.servo import effective_motor_parameters, explicit_stability_margin
from hrp2_drake.robot.station import StationConfig, make_station

ROBOT = "open_manipulator_x"
JOINTS = ["joint1", "joint2", "joint3", "joint4"]
#: One pulse of the XM430's 12-bit absolute encoder (rad).
QUANTUM = 2 * math.pi / 4096


@pytest.fixture(scope="module")
def robot():
    return load_robot_description(ROBOT)


@pytest.fixture(scope="module")
def station_config():
    return StationConfig(robot=ROBOT, scenario="fixed_base")


def test_description_loads(robot):
    assert robot.name == ROBOT
    assert robot.base == "fixed" and robot.base_body == "link1"
    assert robot.joints == JOINTS and robot.controlled_joints == JOINTS
    assert not robot.has_imu() and robot.sensor_names() == []
    plant = robot.make_plant()
    assert plant.num_positions() == 4 and plant.num_actuators() == 4
    # The gripper is welded: only the four arm joints move.
    for name in ("gripper_left_joint", "gripper_right_joint"):
        assert plant.GetJointByName(name).num_positions() == 0
    # The home pose is within the limits ROBOTIS gives.
    q0 = np.array(robot.initial_positions)
    assert np.all(q0 > plant.GetPositionLowerLimits())
    assert np.all(q0 < plant.GetPositionUpperLimits())
    # Each actuator: the XM430-W350's gear ratio, a reflected inertia of
    # 1.195e-2 kg m^2.
    for index in plant.GetJointActuatorIndices():
        actuator = plant.get_joint_actuator(index)
        assert actuator.default_gear_ratio() == 353.5
        reflected = (
            actuator.default_gear_ratio() ** 2 * actuator.default_rotor_inertia()
        )
        assert reflected == pytest.approx(1.195e-2, rel=1e-3)


def test_bus_validates_and_carries_the_period(robot):
    bus = robot.bus
    bus.validate(len(robot.joints))
    assert bus.active and bus.model == "XM430-W350"
    assert bus.ids == [11, 12, 13, 14] and bus.baud == 1_000_000
    timing = bus.timing()
    assert timing.cycle <= robot.sensors.period
    check_bus_period(bus, robot.sensors.period)  # raises if it does not
    # 4 servos, 8 bytes each (present velocity and position), return delay 0:
    # 180 + 4 x 190 + 1000 (adapter) + 500 (compute) + 340 µs = 2.78 ms of the 4 ms.
    assert timing.cycle == pytest.approx(2.78e-3, abs=1e-6)
    # The position loop's documented saturation at the factory gain 800.
    assert robot.position_loop.gain == 800.0
    expected = 1.0 / (800 * (4096 / (2 * math.pi)) / (128 * 885))
    assert robot.position_loop.saturation_error(None) == pytest.approx(
        expected, rel=1e-5
    )


def test_holding_home_sags_by_the_servo_stiffness(robot, station_config):
    """q_cmd fixed at home for 1 s. The servo acts on encoder pulses: with e the error
    in pulses, the torque K1 K4 e takes whole-pulse steps (29 mN m), so the arm comes
    to rest on the pulse boundary where K1 K4 e crosses the gravity torque g(q); the
    true error q_cmd - q is then within half a pulse (0.77 mrad) of K_tau g(q).
    Measured: -17.64, -17.64, -2.30 mrad on joints 2-4 against K_tau g = -17.41,
    -18.30, -2.79 mrad; joint 1 (no gravity torque) 0."""
    station = make_station(station_config)
    context = station.CreateDefaultContext()
    q_home = np.array(robot.initial_positions)
    station.GetInputPort("q_cmd").FixValue(context, q_home)
    simulator = Simulator(station, context)
    simulator.AdvanceTo(0.5)
    q_half = station.GetOutputPort("state_true").Eval(context)[:4].copy()
    simulator.AdvanceTo(1.0)
    state = station.GetOutputPort("state_true").Eval(context)
    q, v = state[:4], state[4:]

    plant = station.GetSubsystemByName("plant")
    plant_context = plant.CreateDefaultContext()
    plant.SetPositions(plant_context, q)
    gravity = -plant.CalcGravityGeneralizedForces(plant_context)  # what the servos hold
    k_tau = effective_motor_parameters(station_config.servo_params(), robot.joints)[
        "k_tau"
    ]
    assert k_tau == pytest.approx(np.full(4, 1 / (1.7826087 * 10.5887492)), rel=1e-6)
    predicted = k_tau * gravity
    error = robot.bus.quantized(q_home) - q  # the command as the servos take it
    assert np.all(np.abs(error - predicted) <= QUANTUM / 2 + 5e-5)
    # The sag is real: over 10 pulses on the shoulder and the elbow.
    assert np.all(error[1:3] < -10 * QUANTUM)
    # At rest, no drift over the last 0.5 s.
    assert np.all(np.abs(v) < 0.01)
    assert np.all(np.abs(q - q_half) < 5e-5)


def test_servo_is_stable_at_the_plant_step(robot, station_config):
    """explicit_stability_margin with the reflected rotor inertia as the lower bound
    of every joint's inertia: spectral radius below 1 at the station's 1 ms step."""
    plant = robot.make_plant()
    inertia = np.array(
        [
            plant.get_joint_actuator(i).default_gear_ratio() ** 2
            * plant.get_joint_actuator(i).default_rotor_inertia()
            for i in plant.GetJointActuatorIndices()
        ]
    )
    radius = explicit_stability_margin(
        station_config.servo_params(), robot.joints, inertia, station_config.time_step
    )
    margin = 1.0 - radius
    assert np.all(margin > 0)
    # The position loop on the rotor alone is overdamped; its slow pole is about
    # 1 - h K1 K4 / (K1 K5 + K2 + K3 / v_s) = 0.9905 (exact radius 0.98999876).
    assert radius == pytest.approx(np.full(4, 0.98999876), abs=1e-6)
