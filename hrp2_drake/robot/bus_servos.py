"""The simulated robot's servos as a servo bus sees them (`SimulatedServos`): what the
emulated Protocol 2.0 servos (`hardware.sim_servo`) stand on, and what the in-process
run with a bus's timing drives (`hardware.in_process.run_on_bus_in_process`).

A bus servo is a set of registers over a physical joint. Here the joint is the
robot's simulated station (MultibodyPlant, the emulated position servo: for a real
servo, its digital twin), advanced on demand (`advance_to`). What a servo's
registers set goes in: its goal position (`set_goal`), its torque enable
(`set_enabled`), its position P gain (`set_gain`); and what a hand does to the
arm, for hand-guiding experiments: a torque on joints (`set_external_torque`), a
force on a body (`set_external_force`, through every joint at once). What it
measures comes out (`present`): its encoder (the joint angle at the encoder's
resolution), its velocity, its motor current, its PWM duty (the documented position
loop's output), its supply voltage and its temperature.

The robot side of the simulation: it reads the plant's state and the servo's
parameters, as the real servo's own electronics measure them. Nothing on the
controller's side reads this module.
"""

import math
from dataclasses import dataclass, replace

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.multibody.math import SpatialForce
from pydrake.multibody.plant import ExternallyAppliedSpatialForce
from pydrake.systems.analysis import Simulator

from hrp2_drake.multibody import joint_indexing
from hrp2_drake.robot.station import (
    StationConfig,
    initial_joint_positions,
    make_station,
)

#: The temperature the simulated servos report (°C): the ambient of the real
#: XL330's logs (models/xl330_pendulum/logs: `temp` 30).
AMBIENT_TEMPERATURE = 30.0


@dataclass
class ServoReadings:
    """What every servo measures now (joint order, SI units).

    Attributes:
        position: the encoder's joint angle (rad): the true angle at the encoder's
            resolution.
        velocity: the joint velocity (rad/s).
        current: the motor current (A).
        pwm: the position loop's output, a duty cycle in [-1, 1] (0 where torque is
            off).
        voltage: the supply voltage (V).
        temperature: °C.
    """

    position: np.ndarray
    velocity: np.ndarray
    current: np.ndarray
    pwm: np.ndarray
    voltage: np.ndarray
    temperature: np.ndarray


class SimulatedServos:
    """The station behind a robot's servo bus (module docstring).

    The servos power up with torque off (the joints free but for their friction) and
    the goal at the home pose. `set_gain` rebuilds the station at the new gain and
    carries its whole state over (plant, servo, sensors): the emulated servo's law is
    built at one gain (`StationConfig.servo_gain`).

    Args:
        config: the simulated robot (its description must have a `bus`).
    """

    def __init__(self, config: StationConfig):
        config.validate()
        self.robot = robot = config.description()
        if not robot.bus.active:
            raise ValueError(
                f"robot '{robot.name}': its description has no bus (bus.kind empty)"
            )
        self._config = config
        self.joints = list(robot.joints)
        n = len(self.joints)
        self._goal = initial_joint_positions(config)
        self._enabled = np.zeros(n)
        self._external = np.zeros(n)
        self._forces: dict[str, np.ndarray] = {}  # body -> force (N, world)
        self._gain = float(config.servo_gain_in_use() or robot.position_loop.gain)
        self._simulator = None
        self._build(self._gain)
        self._voltage = np.full(n, robot.bus.supply_voltage)
        self.temperature = np.full(n, AMBIENT_TEMPERATURE)

    def _build(self, gain: float) -> None:
        """The station at servo gain `gain`, its context carried over from the
        current one (if any)."""
        station = make_station(
            replace(self._config, servo_gain=gain), servo_enable=True
        )
        simulator = Simulator(station)
        context = simulator.get_mutable_context()
        if self._simulator is not None:
            context.SetTimeStateAndParametersFrom(self._simulator.get_context())
        self._station, self._context = station, context
        self._q_cmd = station.GetInputPort("q_cmd")
        self._enable = station.GetInputPort("servo_enabled")
        self._q_cmd.FixValue(context, self._goal)
        self._enable.FixValue(context, self._enabled)
        self._servo = station.GetSubsystemByName("servo")
        self._servo_context = self._servo.GetMyContextFromRoot(context)
        self._state = station.GetOutputPort("state_true")
        plant = station.GetSubsystemByName("plant")
        indexing = joint_indexing(plant, self.joints)
        self._q_rows = indexing.q
        self._v_rows = plant.num_positions() + indexing.v
        self._plant, self._plant_context = plant, plant.GetMyContextFromRoot(context)
        self._indexing_v = indexing.v
        self._spatial_forces = station.GetInputPort("applied_spatial_force")
        self._fix_external()
        initialized = self._simulator is not None
        self._simulator = simulator
        if not initialized:
            simulator.Initialize()
        self._gain = gain

    # ---------------------------------------------------------------- time

    @property
    def time(self) -> float:
        """The robot's time (s)."""
        return self._context.get_time()

    def advance_to(self, t: float) -> None:
        """Simulates until robot time `t` (s) with the registers as they are; a time
        already passed does nothing."""
        if t > self._context.get_time():
            self._simulator.AdvanceTo(t)

    # ---------------------------------------------------------------- registers

    def set_goal(self, q: np.ndarray) -> None:
        """The goal positions of every servo (rad, joint order)."""
        self._goal[:] = q
        self._q_cmd.FixValue(self._context, self._goal)

    @property
    def external_torque(self) -> np.ndarray:
        return self._external.copy()

    def set_external_torque(self, tau: np.ndarray) -> None:
        """An external torque on every joint (N·m, joint order), held until changed:
        what a hand pushing the arm applies (the plant's applied generalized force,
        which the station leaves free)."""
        self._external[:] = tau
        self._fix_external()

    @property
    def external_forces(self) -> dict[str, np.ndarray]:
        """The forces `set_external_force` holds: body name -> force (N, world)."""
        return {body: force.copy() for body, force in self._forces.items()}

    def set_external_force(self, body: str, force) -> None:
        """A force (N, 3 values in the world frame, the arm's base frame on a fixed
        robot) on body `body` at its origin, held until changed (zero lets go): a
        hand pushing the arm there, through every joint at once (an
        ExternallyAppliedSpatialForce on the plant). Raises ValueError in one line
        for a body the model lacks or a force that is not 3 finite numbers."""
        self.check_body(body, "external force")
        force = np.asarray(force, dtype=float)
        if force.shape != (3,) or not np.all(np.isfinite(force)):
            raise ValueError(
                f"external force on '{body}': expected 3 finite numbers (N), got "
                f"{np.asarray(force).tolist()}"
            )
        self._forces[body] = force.copy()
        self._fix_external()

    def check_body(self, body: str, where: str) -> None:
        """Raises ValueError (one line, naming the model's bodies) unless the
        robot's model has a body `body`."""
        if not self._plant.HasBodyNamed(body):
            plant = self._plant
            names = [
                plant.get_body(index).name()
                for index in plant.GetBodyIndices(self._model_instance())
            ]
            raise ValueError(
                f"{where}: no body '{body}' in {self.robot.name}'s model (its bodies: "
                f"{', '.join(names)})"
            )

    def _model_instance(self):
        plant = self._plant
        joint = plant.GetJointByName(self.joints[0])
        return joint.model_instance()

    def joint_positions(self) -> np.ndarray:
        """The true joint angles (rad, joint order): ground truth, for evaluation
        only (the servos report them at the encoder's resolution: `present`)."""
        return self._state.Eval(self._context)[self._q_rows].copy()

    def body_position(self, body: str) -> np.ndarray:
        """The true position of body `body`'s origin in the world (m): ground
        truth, for evaluation only (no controller reads it)."""
        self.check_body(body, "body position")
        pose = self._plant.EvalBodyPoseInWorld(
            self._plant_context, self._plant.GetBodyByName(body)
        )
        return pose.translation().copy()

    def _fix_external(self) -> None:
        plant = self._plant
        forces = np.zeros(plant.num_velocities())
        forces[self._indexing_v] = self._external
        plant.get_applied_generalized_force_input_port().FixValue(
            self._plant_context, forces
        )
        spatial = []
        for body, force in self._forces.items():
            applied = ExternallyAppliedSpatialForce()
            applied.body_index = plant.GetBodyByName(body).index()
            applied.p_BoBq_B = np.zeros(3)
            applied.F_Bq_W = SpatialForce(np.zeros(3), force)
            spatial.append(applied)
        value = AbstractValue.Make([ExternallyAppliedSpatialForce()])
        value.set_value(spatial)
        self._spatial_forces.FixValue(self._context, value)

    def set_enabled(self, enabled: np.ndarray) -> None:
        """Torque enable per servo (1 on, 0 off)."""
        self._enabled[:] = enabled
        self._enable.FixValue(self._context, self._enabled)

    def set_gain(self, gain: float) -> None:
        """The position P gain (the servo's units) of every servo: the station is
        rebuilt at it, its state carried over."""
        if not (math.isfinite(gain) and gain > 0):
            raise ValueError(f"servo gain: must be finite and > 0, got {gain}")
        if gain != self._gain:
            self._build(float(gain))

    @property
    def gain(self) -> float:
        return self._gain

    @property
    def goal(self) -> np.ndarray:
        return self._goal.copy()

    @property
    def enabled(self) -> np.ndarray:
        return self._enabled.copy()

    # ---------------------------------------------------------------- readings

    def present(self) -> ServoReadings:
        """What every servo measures now (`ServoReadings`)."""
        x = self._state.Eval(self._context)
        q, v = x[self._q_rows], x[self._v_rows]
        position = self._servo.encoder(q)
        loop = self.robot.position_loop
        duty = loop.output_per_gain * self._gain * (self._goal - position)
        duty = np.clip(duty, -loop.output_limit, loop.output_limit) * (
            self._enabled > 0.5
        )
        return ServoReadings(
            position=position,
            velocity=v.copy(),
            current=self._servo.current(self._servo_context),
            pwm=duty,
            voltage=self._voltage.copy(),
            temperature=self.temperature.copy(),
        )
