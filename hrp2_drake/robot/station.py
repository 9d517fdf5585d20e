"""make_station(config): a simulated robot (HRP-2 by default, any robot description)
as one Diagram with named ports.

.. code-block:: text

                           ┌──────────────────────────────┐
    q_cmd ────────────────►│                              ├──► q_measured
    applied_spatial_force ►│   MultibodyPlant (robot)     ├──► imu_linear_acceleration
                           │                              │    (if an IMU)
                           │ + EmulatedPositionServo      ├──► imu_angular_velocity
                           │                              │    (if an IMU)
                           │ + encoders, IMU, F/T         ├──► wrench_<sensor> (each)
                           │   (+ fault injection)        ├──► sensor_time
                           │   (noise, bias, 1 kHz)       ├──► joint_torque_true
                           │                              ├──► state_true
                           │                              ├──► body_poses
                           └──────────────────────────────┘

The robot is `StationConfig.robot`, a robot description (hrp2_drake/description/):
its model, joints, IMU, F/T sensors, servo parameters and sensor noise.

Scenarios (`StationConfig.scenario`):
  - "fixed_base": the base welded at the description's base_pose (a fixed robot has
    only this one).
  - "hanging": floating base held by two strings (the description's
    scenarios.hanging, e.g. HRP-2's shoulders; spring-dampers to fixed anchors, as in
    the paper's Fig. 2b), feet in the air.
  - "standing": the soles (scenarios.soles) on flat ground.
  - "standing_on_block": one sole on a rigid block (the paper's Fig. 2a), the leg
    (scenarios.block) bent so that the sole rests on it.
  - "lowered": as a real humanoid is started: hanging from the strings of
    "hanging", its soles `LoweringConfig.feet_clearance` above the ground, then put
    down by a hoist (`robot.hoist`: a harness holds the torso's orientation and
    damps its sway, the anchors go down from `lowering.start` for
    `lowering.duration`; the strings end slack, the harness let go), standing on its
    soles at the end.
Every scenario but "hanging" has a ground (its top at z = 0), and `obstacles` adds
boxes (e.g. a table for an arm's force task).

`joint_torque_true` and `state_true` are ground truth, for evaluation only: estimators,
identification and controllers must not read them. `joint_torque_true` is the torque
the servo applied over the last plant step (the plant's net actuation, taken from the
actuators' order into the description's joint order: a URDF may declare its
transmissions in another order than its joints), the same step the accelerometer and
F/T readings come from.

The noise of every sensor is a pure function of `SensorsConfig.seed` and the sample
index (`SampledSignal`), so every run of a config repeats the same noise. One
`SensorSampler` samples every sensor (robot/sensors.py).
"""

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from pydrake.geometry import (
    Box,
    Meshcat,
    MeshcatVisualizer,
    MeshcatVisualizerParams,
    Role,
    SceneGraph,
)
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.multibody.plant import (
    AddMultibodyPlant,
    CoulombFriction,
    MultibodyPlant,
    MultibodyPlantConfig,
)
from pydrake.multibody.tree import LinearBushingRollPitchYaw, LinearSpringDamper
from pydrake.systems.framework import Diagram, DiagramBuilder, OutputPort
from pydrake.systems.primitives import Selector, SelectorParams
from pydrake.systems.sensors import Accelerometer, Gyroscope

from hrp2_drake.config import check_finite
from hrp2_drake.description import (
    RobotDescription,
    check_joint_positions,
    load_robot_description,
)
from hrp2_drake.description.sensors import SensorsConfig
from hrp2_drake.multibody import JointIndexing, joint_indexing, tree_joints
from hrp2_drake.robot.faults import FaultInjector, SensorFault
from hrp2_drake.robot.sensors import SensorSampler
from hrp2_drake.robot.servo import (
    SERVO_MECHANISMS,
    EmulatedPositionServo,
    ServoParams,
    load_servo_params,
)

SCENARIOS = ("fixed_base", "hanging", "standing", "standing_on_block", "lowered")
#: Drake's discrete contact approximations (MultibodyPlantConfig).
CONTACT_APPROXIMATIONS = ("tamsi", "sap", "similar", "lagged")
#: The smallest plant time step accepted (s): 1% of HRP-2's 1 ms.
MIN_TIME_STEP = 1e-5
GRAVITY = 9.81


def sensor_sizes(robot: RobotDescription) -> dict[str, int]:
    """The sensor ports of the robot's station and their sizes, in the order of its
    `sensor_time` output: q_measured, the IMU's two (if any), wrench_<sensor> each."""
    sizes = {"q_measured": len(robot.joints)}
    if robot.has_imu():
        sizes |= {"imu_linear_acceleration": 3, "imu_angular_velocity": 3}
    return sizes | {f"wrench_{name}": 6 for name in robot.force_torque_sensors}


@dataclass
class BoxObstacle:
    """A rigid box welded to the world (collision and illustration).

    Args:
        name: its geometry name.
        size: [x, y, z] edge lengths (m).
        pose: [x, y, z, roll, pitch, yaw] of its centre in the world (m, rad).
        friction: Coulomb friction coefficient (static = dynamic).
    """

    name: str = "box"
    size: list[float] = field(default_factory=lambda: [0.5, 0.5, 0.1])
    pose: list[float] = field(default_factory=lambda: [0.0] * 6)
    friction: float = 1.0


@dataclass
class HangingConfig:
    """The two strings of the "hanging" scenario.

    Args:
        string_length: free length of each string (m).
        stiffness: stiffness of each string (N/m).
        damping: damping along each string (N·s/m).
        feet_clearance: height of the soles above the ground at rest (m).
        sway_damping: [rotational (N·m·s/rad), translational (N·s/m)] damping of the
            torso's motion relative to the world: the friction of the lift and air
            that makes a hanging robot stop swinging (the strings alone leave the
            pendulum modes undamped).
    """

    string_length: float = 1.0
    stiffness: float = 20000.0
    damping: float = 400.0
    feet_clearance: float = 0.3
    sway_damping: list[float] = field(default_factory=lambda: [5.0, 50.0])


@dataclass
class LoweringConfig:
    """The hoist of the "lowered" scenario (its strings: `HangingConfig`'s).

    Args:
        feet_clearance: the soles' height above the ground while hanging (m).
        start: when the anchors start going down (s).
        duration: how long they take (s).
        slack: how far below the point where the soles touch (the strings at their
            free length, the robot's weight on them) the anchors end (m): the
            strings are slack then.
        hold_stiffness: the harness's rotational stiffness (N·m/rad) holding the
            hanging body's orientation until the robot stands (the strings alone
            let a robot whose CoM is not below them pitch and swing).
    """

    feet_clearance: float = 0.03
    start: float = 1.0
    duration: float = 1.0
    slack: float = 0.05
    hold_stiffness: float = 2000.0


@dataclass
class StationConfig:
    """Configuration of a simulated robot.

    Args:
        robot: its robot description: a robot.yaml path, or the name of a robot in
            models/ ("hrp2", "iiwa14"); empty: HRP-2.
        scenario: one of "fixed_base", "hanging", "standing", "standing_on_block"
            (a fixed robot: "fixed_base" only).
        time_step: the plant's discrete time step (s).
        initial_positions: the initial joint angles (rad, the description's joint
            order); empty for its home pose (HRP-2: half-sitting, the first sample of
            the climbing motion).
        sensors: noise, bias and sampling of the sensors; none: the description's.
        hanging: the strings of the "hanging" and "lowered" scenarios.
        lowering: the hoist of the "lowered" scenario.
        block_height: height of the block under the right foot (m),
            "standing_on_block" only.
        servo_file: the servo data file: a path, a preset of the description (HRP-2:
            "ideal", models/hrp2/servo_ideal.yaml: the paper's eq. 6 with a small dead
            zone, for tests of the exact linear law) or "calibrated" / empty (the
            description's servo_file; HRP-2's is calibrated to the real robot by
            `hrp2-drake calibrate`).
        faults: sensor faults to inject (`hrp2_drake.robot.faults`): what the sensor
            ports read; the ground truth is untouched.
        extra_command_latency: latency added to every joint's command (s, whole
            periods): a fault, on top of the servo's own.
        servo_gain: the servo's position gain (its own units, e.g. a Dynamixel's kp)
            for a servo file that states the gain its k4 holds at
            (`ServoParams.at_gain`); 0: the file's.
        servo_off: servo mechanisms to switch off (`SERVO_MECHANISMS`: "latency",
            "voltage_limit", "hysteresis", "deadzone").
        contact_approximation: Drake's discrete contact approximation.
        obstacles: boxes welded to the world.
        sample_lead: the sensors sample this long (s) before each multiple of their
            period, rounded up to whole plant steps (the plant's state changes only
            then): a controller ticking at those multiples acts on samples that old,
            as on a servo bus, where the command reaches the servos the bus's
            read-to-write delay after they sampled (`BusTiming.read_to_write`). 0:
            the sensors sample at the tick (a controller one period behind them).
    """

    robot: str = ""
    scenario: str = "hanging"
    time_step: float = 0.001
    initial_positions: list[float] = field(default_factory=list)
    sensors: SensorsConfig | None = None
    hanging: HangingConfig = field(default_factory=HangingConfig)
    lowering: LoweringConfig = field(default_factory=LoweringConfig)
    block_height: float = 0.05
    servo_file: str = ""
    servo_gain: float = 0.0
    servo_off: list[str] = field(default_factory=list)
    faults: list[SensorFault] = field(default_factory=list)
    extra_command_latency: float = 0.0
    contact_approximation: str = "sap"
    obstacles: list[BoxObstacle] = field(default_factory=list)
    sample_lead: float = 0.0

    def description(self) -> RobotDescription:
        """The robot description (checked against its model; cached)."""
        return load_robot_description(self.robot or None)

    def sensors_config(self) -> SensorsConfig:
        """The sensors: `sensors`, or the description's."""
        return self.sensors if self.sensors is not None else self.description().sensors

    def servo_params(self) -> ServoParams:
        """The servo parameters of `servo_file`, checked to cover every joint."""
        robot = self.description()
        try:
            params = load_servo_params(self.servo_file, robot.source_file)
        except (OSError, ValueError) as error:
            raise ValueError(f"StationConfig.servo_file: {error}") from None
        missing = [name for name in robot.joints if name not in params.joints]
        if missing:
            shown = ", ".join(missing[:3]) + (", ..." if len(missing) > 3 else "")
            raise ValueError(
                f"StationConfig.servo_file: {robot.servo_path(self.servo_file)}: "
                f"joints: no servo parameters for {len(missing)} joints of robot "
                f"'{robot.name}' ({shown})"
            )
        if self.servo_gain:
            if not (math.isfinite(self.servo_gain) and self.servo_gain > 0):
                raise ValueError(
                    f"StationConfig.servo_gain: must be finite and > 0 (0: the servo "
                    f"file's gain), got {self.servo_gain}"
                )
            params = params.at_gain(self.servo_gain)
        return params

    def servo_gain_in_use(self) -> float | None:
        """The position gain the station's servo runs at (the servo's own units):
        `servo_gain`, else the gain the servo file's joints state; None for a servo
        file that states none (a servo without a settable gain).

        Raises:
            ValueError: the servo file's joints state different gains (a motor model
                holds at one; set `servo_gain`).
        """
        if self.servo_gain:
            return float(self.servo_gain)
        gains = {j.gain for j in self.servo_params().joints.values() if j.gain > 0}
        if len(gains) > 1:
            raise ValueError(
                f"StationConfig.servo_gain: 0, and the servo file's joints state "
                f"different gains {sorted(gains)}: set one"
            )
        return float(gains.pop()) if gains else None

    def validate(self) -> None:
        """Raises ValueError naming the bad field: each value against its meaning (the
        robot's scenarios, joints and limits, the plant's step, the servo file)."""
        robot = self.description()
        self._validate_scenario(robot)
        self._validate_timing()
        self._validate_joints(robot)
        for k, fault in enumerate(self.faults):
            fault.validate(f"StationConfig.faults[{k}]", sensor_sizes(robot))
        self.sensors_config().validate(len(robot.joints), robot.sensor_names())
        self.servo_params()
        self._validate_scene()

    def _validate_scene(self) -> None:
        """The strings, the block and the obstacles: finite numbers of their sign."""
        where = "StationConfig.hanging"
        for name, strict in (
            ("string_length", True),
            ("stiffness", True),
            ("damping", False),
            ("feet_clearance", False),
        ):
            check_finite(getattr(self.hanging, name), f"{where}.{name}", 0.0, strict)
        for k, value in enumerate(self.hanging.sway_damping):
            check_finite(value, f"{where}.sway_damping[{k}]", 0.0, False)
        check_finite(self.block_height, "StationConfig.block_height", 0.0)
        where = "StationConfig.lowering"
        for name, strict in (
            ("feet_clearance", False),
            ("start", False),
            ("duration", True),
            ("slack", False),
            ("hold_stiffness", False),
        ):
            check_finite(getattr(self.lowering, name), f"{where}.{name}", 0.0, strict)
        for k, box in enumerate(self.obstacles):
            where = f"StationConfig.obstacles[{k}]"
            if len(box.size) != 3 or not all(
                math.isfinite(v) and v > 0 for v in box.size
            ):
                raise ValueError(f"{where}.size: 3 finite lengths > 0, got {box.size}")
            if len(box.pose) != 6 or not np.all(np.isfinite(box.pose)):
                raise ValueError(
                    f"{where}.pose: [x, y, z, roll, pitch, yaw], got {box.pose}"
                )
            check_finite(box.friction, f"{where}.friction", 0.0, False)

    def _validate_scenario(self, robot: RobotDescription) -> None:
        needs = {
            "hanging": robot.scenarios.hanging.body,
            "standing": robot.scenarios.soles,
            "standing_on_block": robot.scenarios.block.sole and robot.scenarios.soles,
            "lowered": robot.scenarios.hanging.body and robot.scenarios.soles,
        }
        if self.scenario not in SCENARIOS:
            fits = [
                s
                for s in SCENARIOS
                if s == "fixed_base" or (robot.base != "fixed" and needs[s])
            ]
            raise ValueError(
                f"StationConfig.scenario: unknown scenario '{self.scenario}', expected "
                f"one of {SCENARIOS} (robot '{robot.name}': {', '.join(fits)})"
            )
        if robot.base == "fixed" and self.scenario != "fixed_base":
            raise ValueError(
                f"StationConfig.scenario: '{self.scenario}', but robot '{robot.name}' "
                "is fixed-base: only 'fixed_base'"
            )
        if self.scenario in needs and not needs[self.scenario]:
            raise ValueError(
                f"StationConfig.scenario: '{self.scenario}' needs the robot "
                f"description's scenarios section, which robot '{robot.name}' does not "
                "fill"
            )
        if len(self.hanging.sway_damping) != 2:
            raise ValueError(
                "StationConfig.hanging.sway_damping: expected [rotational, "
                f"translational], got {self.hanging.sway_damping}"
            )
        if self.contact_approximation not in CONTACT_APPROXIMATIONS:
            raise ValueError(
                "StationConfig.contact_approximation: unknown discrete contact "
                f"approximation '{self.contact_approximation}', expected one of "
                f"{CONTACT_APPROXIMATIONS} (Drake's MultibodyPlantConfig)"
            )

    def _validate_timing(self) -> None:
        """The plant's step, the sensors' period and the command latency, in s."""
        check_finite(self.time_step, "StationConfig.time_step", MIN_TIME_STEP, False)
        period = self.sensors_config().period
        check_finite(period, "StationConfig.sensors.period", 0.0)
        if period < self.time_step * (1 - 1e-9):
            raise ValueError(
                f"StationConfig.sensors.period: {period:g} s is shorter than the "
                f"plant's time step ({self.time_step:g} s): the sensors cannot sample "
                "faster than the plant steps"
            )
        latency = self.extra_command_latency
        check_finite(latency, "StationConfig.extra_command_latency", 0.0, False)
        check_finite(self.sample_lead, "StationConfig.sample_lead", 0.0, False)
        if self.sample_lead_steps() * self.time_step >= period * (1 - 1e-9):
            raise ValueError(
                f"StationConfig.sample_lead: {self.sample_lead:g} s (whole plant "
                f"steps: {self.sample_lead_steps() * self.time_step:g} s) must be "
                f"shorter than the sensors' period ({period:g} s)"
            )

    def sample_lead_steps(self) -> int:
        """`sample_lead` in whole plant steps, rounded up."""
        return math.ceil(self.sample_lead / self.time_step - 1e-9)

    def _validate_joints(self, robot: RobotDescription) -> None:
        n = len(robot.joints)
        if len(self.initial_positions) not in (0, n):
            raise ValueError(
                f"StationConfig.initial_positions: {len(self.initial_positions)} "
                f"values, expected {n} (or none for the home pose)"
            )
        if self.initial_positions:
            q = np.array(self.initial_positions, float)
            if not np.all(np.isfinite(q)):
                j = int(np.flatnonzero(~np.isfinite(q))[0])
                raise ValueError(
                    f"StationConfig.initial_positions[{j}]: {robot.joints[j]} = "
                    f"{q[j]}, expected a finite angle (rad)"
                )
            where = "StationConfig.initial_positions"
            check_joint_positions(q[np.newaxis], where, robot)
        unknown = sorted(set(self.servo_off) - set(SERVO_MECHANISMS))
        if unknown:
            raise ValueError(
                f"StationConfig.servo_off: unknown servo mechanism(s) {unknown}, "
                f"expected some of {list(SERVO_MECHANISMS)}"
            )


def initial_joint_positions(config: StationConfig) -> np.ndarray:
    """The scenario's initial joint angles (rad, the description's joint order): what
    the servo should hold."""
    robot = config.description()
    q = (
        np.array(config.initial_positions, float)
        if config.initial_positions
        else robot.home_positions()
    )
    if config.scenario == "standing_on_block":
        q = _raise_sole(robot, q, config.block_height)
    return q


@functools.lru_cache(maxsize=8)
def _kinematic_model(source_file: str) -> tuple[MultibodyPlant, JointIndexing]:
    """The robot alone (floating, no scenario), parsed once per description: for the
    kinematics that set a scenario up (sole heights, block and string placement)."""
    robot = load_robot_description(source_file)
    plant = MultibodyPlant(0.0)
    robot.add_model(plant, weld_base=False)
    plant.Finalize()
    return plant, joint_indexing(plant, robot.joints)


def _posed(robot: RobotDescription, q: np.ndarray, X_WB: RigidTransform | None = None):
    """(plant, context) of the kinematic model at joint angles q, base at X_WB
    (default: the origin, upright)."""
    plant, indexing = _kinematic_model(robot.source_file)
    context = plant.CreateDefaultContext()
    x = plant.GetPositions(context)
    x[indexing.q] = q
    plant.SetPositions(context, x)
    if X_WB is not None:
        plant.SetFreeBodyPose(context, plant.GetBodyByName(robot.base_body), X_WB)
    return plant, context


def _frame_position(robot: RobotDescription, q: np.ndarray, frame: str) -> np.ndarray:
    """Position in the world of `frame` with the base at the origin, upright (m)."""
    plant, context = _posed(robot, q)
    return plant.GetFrameByName(frame).CalcPoseInWorld(context).translation()


def _raise_sole(robot: RobotDescription, q: np.ndarray, height: float) -> np.ndarray:
    """Bends the block's leg (hip pitch, knee; ankle pitch keeps the sole parallel) so
    that its sole is `height` higher, at the same x, relative to the base."""
    from scipy.optimize import least_squares

    block = robot.scenarios.block
    hip, knee, ankle = (robot.joints.index(name) for name in block.joints)

    def bent(angles: np.ndarray) -> np.ndarray:
        qj = q.copy()
        qj[hip], qj[knee] = angles
        qj[ankle] = q[ankle] - (angles[0] - q[hip]) - (angles[1] - q[knee])
        return qj

    def sole_xz(angles: np.ndarray) -> np.ndarray:
        return _frame_position(robot, bent(angles), block.sole)[[0, 2]]

    start = np.array([q[hip], q[knee]])
    target = sole_xz(start) + [0.0, height]
    fit = least_squares(lambda a: sole_xz(a) - target, start)
    if np.max(np.abs(fit.fun)) > 1e-6:
        raise ValueError(f"block_height {height} m is out of the leg's reach")
    return bent(fit.x)


def standing_positions(
    robot: RobotDescription, q: np.ndarray | None = None
) -> np.ndarray:
    """The generalized positions of the robot's model (`robot.make_plant()`'s order)
    standing: the joints at q (default: the home pose), the base upright above the
    origin with the lowest sole (`scenarios.soles`) on z = 0, as the "standing"
    scenario starts."""
    q = robot.home_positions() if q is None else np.asarray(q, float)
    plant, context = _posed(
        robot, q, RigidTransform([0.0, 0.0, -_lowest_sole_height(robot, q)])
    )
    return plant.GetPositions(context)


def _lowest_sole_height(robot: RobotDescription, q: np.ndarray) -> float:
    """Height of the lowest sole when the base is at the origin, upright."""
    return min(_frame_position(robot, q, f)[2] for f in robot.scenarios.soles)


def _add_box(
    plant: MultibodyPlant, name: str, X_WB: RigidTransform, size, color, friction=1.0
):
    shape = Box(*size)
    plant.RegisterCollisionGeometry(
        plant.world_body(), X_WB, shape, name, CoulombFriction(friction, friction)
    )
    plant.RegisterVisualGeometry(plant.world_body(), X_WB, shape, name, color)


def _add_ground(plant: MultibodyPlant) -> None:
    # A thick box rather than a HalfSpace: same point contact for the sole spheres,
    # without Drake's warning that half spaces do not support deformable contact.
    _add_box(
        plant,
        "ground",
        RigidTransform([0.0, 0.0, -0.05]),
        (6, 6, 0.1),
        [0.8, 0.8, 0.75, 1.0],
    )


def _add_block(
    plant: MultibodyPlant, robot: RobotDescription, q: np.ndarray, height: float
):
    """A rigid block under the block's sole (horizontal position of the sole with the
    base above the origin)."""
    p = _frame_position(robot, q, robot.scenarios.block.sole)
    size = (0.36, 0.18, height)  # HRP-2: clear of the left foot (0.19 m apart)
    X_WB = RigidTransform([p[0] + 0.015, p[1], height / 2])
    _add_box(plant, "block", X_WB, size, [0.6, 0.3, 0.2, 1.0])


def add_scenario_plant(
    builder: DiagramBuilder,
    config: StationConfig,
    robot: RobotDescription,
    q0: np.ndarray,
) -> tuple[MultibodyPlant, SceneGraph]:
    """The station's MultibodyPlant alone, added to `builder` and finalized: the robot
    and its scenario (weld, ground, block, obstacles or strings), the default state the
    scenario's initial one (joint angles q0, base pose). `make_station` adds the servo
    and the sensors to it."""
    plant, scene_graph = AddMultibodyPlant(
        MultibodyPlantConfig(
            time_step=config.time_step,
            discrete_contact_approximation=config.contact_approximation,
        ),
        builder,
    )
    fixed = config.scenario == "fixed_base"
    robot.add_model(plant, weld_base=fixed)
    base = plant.GetBodyByName(robot.base_body)
    if fixed:
        X_WB0 = robot.base_transform()
    elif config.scenario in ("hanging", "lowered"):
        clearance = (
            config.hanging.feet_clearance
            if config.scenario == "hanging"
            else config.lowering.feet_clearance
        )
        X_WB0 = RigidTransform([0.0, 0.0, -_lowest_sole_height(robot, q0) + clearance])
    else:
        X_WB0 = RigidTransform([0.0, 0.0, -_lowest_sole_height(robot, q0)])
    if config.scenario != "hanging":
        _add_ground(plant)
    if config.scenario == "standing_on_block":
        _add_block(plant, robot, q0, config.block_height)
    for box in config.obstacles:
        x, y, z, roll, pitch, yaw = box.pose
        _add_box(
            plant,
            box.name,
            RigidTransform(RollPitchYaw(roll, pitch, yaw), [x, y, z]),
            box.size,
            [0.5, 0.5, 0.6, 1.0],
            box.friction,
        )
    if config.scenario == "hanging":
        _add_strings(plant, robot, q0, X_WB0, config.hanging)
    plant.Finalize()
    plant.set_name("plant")
    for name, angle in zip(robot.joints, q0):
        plant.GetJointByName(name).set_default_angle(angle)
    if not fixed:
        plant.SetDefaultFloatingBaseBodyPose(base, X_WB0)
    return plant, scene_graph


def make_station(
    config: StationConfig, meshcat: Meshcat | None = None, servo_enable: bool = False
) -> Diagram:
    """Builds the station Diagram (module docstring) for `config`.

    The default context of the returned diagram holds the scenario's initial state.
    If `meshcat` is given, a MeshcatVisualizer publishes the illustration geometry.
    With `servo_enable`, the servo's `enabled` input is exported as `servo_enabled`
    (per joint, 1 on: a real servo's torque enable; it must then be given). A robot
    on a bus (its description's `bus`) takes its goal positions in encoder pulses:
    q_cmd is rounded to them (`BusDescription.quantized`).
    """
    config.validate()
    robot = config.description()
    q0 = initial_joint_positions(config)
    builder = DiagramBuilder()
    plant, scene_graph = add_scenario_plant(builder, config, robot, q0)
    indexing = joint_indexing(plant, robot.joints)

    servo_params = config.servo_params()
    servo = builder.AddNamedSystem(
        "servo",
        EmulatedPositionServo(
            plant,
            servo_params,
            robot.joints,
            period=config.time_step,
            initial_q_cmd=q0,
            off=config.servo_off,
            extra_latency=config.extra_command_latency,
            enable_port=servo_enable,
            command_resolution=robot.bus.quantum() if robot.bus.active else 0.0,
        ),
    )
    builder.Connect(plant.get_state_output_port(), servo.GetInputPort("state"))
    builder.Connect(servo.GetOutputPort("actuation"), plant.get_actuation_input_port())
    builder.ExportInput(servo.GetInputPort("q_cmd"), "q_cmd")
    if servo_enable:
        builder.ExportInput(servo.GetInputPort("enabled"), "servo_enabled")
    if config.scenario == "lowered":
        forces = _add_hoist(builder, plant, robot, q0, config)
        builder.ExportInput(forces.GetInputPort("external"), "applied_spatial_force")
    else:
        builder.ExportInput(
            plant.get_applied_spatial_force_input_port(), "applied_spatial_force"
        )

    _add_sensors(
        builder,
        plant,
        robot,
        indexing,
        config.sensors_config(),
        q0,
        servo_params,
        config.faults,
        config.sample_lead_steps() * config.time_step,
    )

    builder.ExportOutput(_in_joint_order(builder, plant, indexing), "joint_torque_true")
    builder.ExportOutput(plant.get_state_output_port(), "state_true")
    builder.ExportOutput(plant.get_body_poses_output_port(), "body_poses")
    builder.ExportOutput(plant.get_contact_results_output_port(), "contact_results")
    if meshcat is not None:
        MeshcatVisualizer.AddToBuilder(
            builder,
            scene_graph,
            meshcat,
            MeshcatVisualizerParams(role=Role.kIllustration),
        )
    diagram = builder.Build()
    diagram.set_name(f"{robot.name}_station_{config.scenario}")
    return diagram


def _in_joint_order(
    builder: DiagramBuilder, plant: MultibodyPlant, indexing: JointIndexing
) -> OutputPort:
    """The plant's net actuation (actuator order) in `indexing`'s joint order: each
    joint's entry is its actuator's (`JointIndexing.u`), copied, never summed."""
    rows = SelectorParams.OutputSelection
    params = SelectorParams(
        inputs=[
            SelectorParams.InputPortParams(name="actuation", size=plant.num_actuators())
        ],
        outputs=[
            SelectorParams.OutputPortParams(
                name="joint_torque",
                selections=[
                    rows(input_port_index=0, input_offset=int(u)) for u in indexing.u
                ],
            )
        ],
    )
    order = builder.AddNamedSystem("joint_order", Selector(params))
    builder.Connect(plant.get_net_actuation_output_port(), order.get_input_port())
    return order.get_output_port()


def _add_strings(
    plant: MultibodyPlant,
    robot: RobotDescription,
    q0: np.ndarray,
    X_WB0: RigidTransform,
    cfg: HangingConfig,
) -> None:
    """Two strings from fixed anchors to the description's hanging points, stretched
    by the weight."""
    hanging = robot.scenarios.hanging
    plant_k, context = _posed(robot, q0, X_WB0)
    X_WT = plant_k.GetBodyByName(hanging.body).EvalPoseInWorld(context)
    stretch = (
        plant_k.CalcTotalMass(context) * GRAVITY / (len(hanging.points) * cfg.stiffness)
    )
    torso = plant.GetBodyByName(hanging.body)
    for p_TS in hanging.points:
        anchor = X_WT @ np.array(p_TS) + [0.0, 0.0, cfg.string_length + stretch]
        plant.AddForceElement(
            LinearSpringDamper(
                plant.world_body(),
                anchor,
                torso,
                p_TS,
                cfg.string_length,
                cfg.stiffness,
                cfg.damping,
            )
        )
    rotational, translational = cfg.sway_damping
    plant.AddForceElement(
        LinearBushingRollPitchYaw(
            plant.world_frame(),
            torso.body_frame(),
            [0.0] * 3,
            [rotational] * 3,
            [0.0] * 3,
            [translational] * 3,
        )
    )


def _add_hoist(
    builder: DiagramBuilder,
    plant: MultibodyPlant,
    robot: RobotDescription,
    q0: np.ndarray,
    config: StationConfig,
):
    """The "lowered" scenario's hoist (`robot.hoist.Hoist`) on the plant's applied
    forces, beside the station's own input: returns the `ForceSum` whose "external"
    input that is. The anchors start as "hanging"'s (above the string points, the
    free length plus the weight's stretch) and go down by the soles' clearance, that
    stretch and `lowering.slack`."""
    from hrp2_drake.robot.hoist import ForceSum, Hoist

    hanging, lowering = config.hanging, config.lowering
    strings = robot.scenarios.hanging
    X_WB0 = RigidTransform(
        [0.0, 0.0, -_lowest_sole_height(robot, q0) + lowering.feet_clearance]
    )
    plant_k, context = _posed(robot, q0, X_WB0)
    X_WT = plant_k.GetBodyByName(strings.body).EvalPoseInWorld(context)
    stretch = (
        plant_k.CalcTotalMass(context)
        * GRAVITY
        / (len(strings.points) * hanging.stiffness)
    )
    anchors = [
        X_WT @ np.array(p_TS) + [0.0, 0.0, hanging.string_length + stretch]
        for p_TS in strings.points
    ]
    hoist = builder.AddNamedSystem(
        "hoist",
        Hoist(
            plant.GetBodyByName(strings.body).index(),
            strings.points,
            anchors,
            hanging.string_length,
            hanging.stiffness,
            hanging.damping,
            hanging.sway_damping,
            lowering.start,
            lowering.duration,
            lowering.feet_clearance + stretch + lowering.slack,
            lowering.hold_stiffness,
            X_WT.rotation(),
        ),
    )
    builder.Connect(
        plant.get_body_poses_output_port(), hoist.GetInputPort("body_poses")
    )
    builder.Connect(
        plant.get_body_spatial_velocities_output_port(),
        hoist.GetInputPort("body_spatial_velocities"),
    )
    forces = builder.AddNamedSystem("applied_forces", ForceSum())
    builder.Connect(hoist.get_output_port(), forces.GetInputPort("hoist"))
    builder.Connect(
        forces.get_output_port(), plant.get_applied_spatial_force_input_port()
    )
    return forces


def force_torque_readouts(
    plant: MultibodyPlant, robot: RobotDescription
) -> list[tuple[str, str, str]]:
    """(fixed joint, sensor frame, body below) of each F/T sensor: the joint whose
    reaction force the sensor reads is the one that holds its body (towards the base).
    That it is a weld the description checked when it was loaded
    (`RobotDescription.check_model`, naming the file and the field)."""
    holders = tree_joints(plant, plant.GetBodyByName(robot.base_body).index())
    out = []
    for name, sensor in robot.force_torque_sensors.items():
        body = robot.sensor_body(name, plant)
        _, joint = holders[int(plant.GetBodyByName(body).index())]
        out.append((joint.name(), sensor.frame, body))
    return out


def _add_sensors(
    builder: DiagramBuilder,
    plant: MultibodyPlant,
    robot: RobotDescription,
    indexing: JointIndexing,
    cfg: SensorsConfig,
    q0: np.ndarray,
    servo: ServoParams,
    faults: Sequence[SensorFault] = (),
    lead: float = 0.0,
) -> None:
    """The sensors: Drake's Accelerometer and Gyroscope on the IMU frame, and one
    SensorSampler for the whole bus (encoders, IMU, F/T sensors, stamps); each sensor
    port through a FaultInjector if a fault names it."""
    resolution = None
    if cfg.encoder_quantization:
        resolution = servo.vectors(indexing.names)["encoder_resolution"]
    sensors = builder.AddNamedSystem(
        "sensors",
        SensorSampler(
            plant,
            indexing.names,
            cfg,
            q0,
            resolution,
            imu=robot.has_imu(),
            force_torque=[
                (name, *readout)
                for name, readout in zip(
                    robot.sensor_names(), force_torque_readouts(plant, robot)
                )
            ],
            faults=faults,
            lead=lead,
        ),
    )
    builder.Connect(plant.get_state_output_port(), sensors.GetInputPort("state"))

    if robot.has_imu():
        _add_imu(builder, plant, robot.imu_frame, sensors)
    if robot.sensor_names():
        builder.Connect(
            plant.get_reaction_forces_output_port(),
            sensors.GetInputPort("reaction_forces"),
        )

    for name in sensor_sizes(robot):  # q_measured, the IMU's, wrench_<sensor> each
        _export_sensor(builder, sensors.GetOutputPort(name), name, faults, cfg.period)
    # The time stamp of every sensor's latest sample (sensor_sizes order).
    builder.ExportOutput(sensors.GetOutputPort("sensor_time"), "sensor_time")


def _add_imu(
    builder: DiagramBuilder,
    plant: MultibodyPlant,
    imu_frame: str,
    sensors: SensorSampler,
) -> None:
    """Drake's Accelerometer (proper acceleration: the plant's gravity vector) and
    Gyroscope on `imu_frame`, wired to the plant's body outputs and to the
    SensorSampler's IMU inputs."""
    imu = plant.GetFrameByName(imu_frame)
    X_BS = imu.GetFixedPoseInBodyFrame()
    body = imu.body()
    accel = builder.AddNamedSystem(
        "accelerometer",
        Accelerometer(body, X_BS, plant.gravity_field().gravity_vector()),
    )
    gyro = builder.AddNamedSystem("gyroscope", Gyroscope(body, X_BS))
    builder.Connect(
        plant.get_body_poses_output_port(), accel.get_body_poses_input_port()
    )
    builder.Connect(
        plant.get_body_spatial_velocities_output_port(),
        accel.get_body_velocities_input_port(),
    )
    builder.Connect(
        plant.get_body_spatial_accelerations_output_port(),
        accel.get_body_accelerations_input_port(),
    )
    builder.Connect(
        plant.get_body_poses_output_port(), gyro.get_body_poses_input_port()
    )
    builder.Connect(
        plant.get_body_spatial_velocities_output_port(),
        gyro.get_body_velocities_input_port(),
    )
    builder.Connect(
        accel.get_measurement_output_port(),
        sensors.GetInputPort("linear_acceleration"),
    )
    builder.Connect(
        gyro.get_measurement_output_port(), sensors.GetInputPort("angular_velocity")
    )


def _export_sensor(
    builder: DiagramBuilder,
    port: OutputPort,
    name: str,
    faults: Sequence[SensorFault],
    period: float,
) -> None:
    """Exports a sensor port as `name`, through a FaultInjector (sampling every
    `period` s) if a fault names it."""
    mine = [f for f in faults if f.signal == name]
    if mine:
        injector = builder.AddNamedSystem(
            f"faults_{name}", FaultInjector(port.size(), mine, period)
        )
        builder.Connect(port, injector.get_input_port())
        port = injector.get_output_port()
    builder.ExportOutput(port, name)
