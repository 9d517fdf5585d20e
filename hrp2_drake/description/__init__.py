"""RobotDescription: one YAML file describes a robot to the whole framework.

A robot is data, not code. `models/hrp2/robot.yaml` describes HRP-2 (floating base,
torso IMU, four F/T sensors); `models/iiwa14/robot.yaml` a fixed-base arm with a wrist
F/T sensor and no IMU. The station, the estimator, identification, the controllers'
builders and the `hrp2-drake` commands read it; nothing in the generic paths knows a
robot's names.

Every path in a description is relative to the folder of the description file.
`load_robot_description` reads the YAML (unknown keys, wrong types: one line naming
the key), then parses the model into a MultibodyPlant and checks every name against it;
an error names the field, e.g.
`models/arm/robot.yaml: force_torque_sensors.wrist.frame: no frame 'ft' in the model`.

The fields are documented on the dataclasses below; `models/hrp2/robot.yaml` is a
commented example.

The description is the bottom layer of the package, plain data: it imports only
pydrake, numpy, the standard library, `hrp2_drake.config` and `hrp2_drake.multibody`.
The configs it holds live beside it, in `sensors` (the simulated sensors' noise),
`excitation` (the identification excitation) and `logs` (how the robot's logs are
read); the modules that use them (`robot.sensors`, `identification.excitation`,
`identification.logs`) import them from here.
"""

import functools
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import BodyIndex, ModelInstanceIndex, RigidBody

from hrp2_drake.config import load_config, one_line
from hrp2_drake.description.bus import BusDescription, check_bus_period
from hrp2_drake.description.contacts import BalanceDescription, ContactsDescription
from hrp2_drake.description.excitation import CollectionConfig
from hrp2_drake.description.logs import LogFormat
from hrp2_drake.description.sensors import SensorRanges, SensorsConfig
from hrp2_drake.multibody import is_strictly_below, tree_joints

BASES = ("floating", "fixed")
#: The robot of every command without --robot.
DEFAULT_ROBOT = "hrp2"


@dataclass
class ForceTorqueSensorDescription:
    """One 6-axis F/T sensor.

    Args:
        frame: the sensor frame (a frame or body of the model): readings are [torque;
            force] about its origin, in it.
        body: the body right below the sensor, on the side away from the base. The
            sensor carries it and everything beyond it (e.g. a gripper, a payload).
            `frame` must be rigidly attached to it and must not lie beyond it. In
            simulation the body must hang from a fixed joint (the sensor splits a
            rigid link there, as URDFs model F/T sensors): its reaction force is what
            the sensor reads. Empty: the body of `frame`.
    """

    frame: str = ""
    body: str = ""


@dataclass
class HangingDescription:
    """Where the "hanging" scenario's two strings are tied (a floating robot).

    Args:
        body: the body the strings pull on (HRP-2: the torso).
        points: the attachment points in that body's frame (m).
    """

    body: str = ""
    points: list[list[float]] = field(default_factory=list)


@dataclass
class BlockDescription:
    """The "standing_on_block" scenario: one sole on a block, raised by bending the leg.

    Args:
        sole: the sole frame that stands on the block.
        joints: [hip pitch, knee, ankle pitch] of that leg: the first two raise the
            sole, the third keeps it parallel to the ground.
    """

    sole: str = ""
    joints: list[str] = field(default_factory=list)


@dataclass
class ScenariosDescription:
    """What the legged scenarios need (empty for a fixed-base robot).

    Args:
        soles: the sole frames (contact frames at the bottom of the feet): "standing"
            puts the lowest on the ground.
        hanging: the strings of "hanging".
        block: the leg on the block of "standing_on_block".
    """

    soles: list[str] = field(default_factory=list)
    hanging: HangingDescription = field(default_factory=HangingDescription)
    block: BlockDescription = field(default_factory=BlockDescription)


@dataclass
class PositionLoopDescription:
    """The servo's position loop as its maker documents it (public facts of the
    firmware, not the emulator's hidden parameters): its output (a PWM duty cycle, a
    current command) is gain · output_per_gain · (q_cmd − q), limited to
    ±output_limit. Identification uses it to find the samples where the output
    saturates; a rollout of a motor model clamps Δq there.

    Args:
        output_per_gain: the loop's output per rad of error and per unit of gain
            (the servo's own gain units); 0: not documented (no saturation found).
        output_limit: the saturation of the output.
        gain: the servo's gain when a log states none (its own units); 0: unknown.
    """

    output_per_gain: float = 0.0
    output_limit: float = math.inf
    gain: float = 0.0

    def validate(self) -> None:
        for name in ("output_per_gain", "gain"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(
                    f"position_loop.{name}: must be finite and >= 0, got {value}"
                )
        if not self.output_limit > 0:
            raise ValueError(
                f"position_loop.output_limit: must be > 0, got {self.output_limit}"
            )

    def saturation_error(self, gain: float | None) -> float:
        """|q_cmd − q| (rad) at which the output saturates with `gain`; inf if the
        loop is not documented or the gain unknown."""
        gain = gain or self.gain
        if not (self.output_per_gain > 0 and gain and math.isfinite(self.output_limit)):
            return math.inf
        return self.output_limit / (gain * self.output_per_gain)


@dataclass
class RobotDescription:
    """A robot, as the framework needs to know it (load with `load_robot_description`).

    Args:
        name: a short identifier (reports, file names).
        model_file: the URDF or SDF (relative to this file's folder). The actuators'
            rotor inertia and gear ratio come from its `drake:` tags.
        base: "floating" (a mobile robot: the estimator needs an IMU) or "fixed"
            (welded to the world: gravity is known, no IMU needed).
        base_body: the floating base body, or the body welded to the world.
        base_pose: [x, y, z, roll, pitch, yaw] (m, rad) of base_body in the world
            where it is welded: a fixed robot always, a floating one in the
            "fixed_base" scenario.
        joints: every one-dof joint of the model, in the order of every joint vector
            (q, τ, q_cmd); each must be actuated.
        controlled_joints: the torque-controlled (and identified) subset.
        joint_labels: human names of the controlled joints for reports (empty: the
            joint names).
        imu_frame: the IMU frame (accelerometer and gyroscope axes); empty: no IMU
            (fixed base only).
        force_torque_sensors: by name (the name makes the ports wrench_<name>); they
            may be nested (one inside the chain above another).
        unknown_wrench_body: the link that carries the unknown external wrench
            (paper Sec. 2.4); empty: the base.
        tool_frame: where a force task acts (empty: none), e.g. an arm's tool tip.
        force_sensor: the F/T sensor that measures the force task's wrench.
        servo_file: the emulated position servo's parameters (simulation only).
        servo_presets: other servo files by preset name, e.g. {ideal: servo_ideal.yaml}.
        control_file: the torque control's settings that work on this robot at its
            rate: a YAML file with a `torque_control:` mapping, what a user's
            --config holds for it (e.g. `torque_control: {controller: {kp: [1.0]}}`).
            `hrp2-drake control` and `track` start from it: the command's defaults,
            this file over them, the user's --config over both. Empty: none (the
            commands' defaults, the paper's).
        sensors: noise, bias and sampling of the simulated sensors.
        sensor_ranges: the sensors' rated ranges (`description.sensors.SensorRanges`):
            what the safety supervisor takes as out of range; none given: a
            supervisor monitoring those sensors refuses to start.
        initial_positions: the home pose (rad, `joints` order); empty: the first
            sample of trajectory_file.
        trajectory_file: a reference motion (text or .gz: time, then the joint
            angles), or empty.
        scenarios: what the legged scenarios need.
        contacts: the soles' rectangles and friction (`description.contacts`), for
            a whole-body controller with contacts; empty: none.
        balance: the balance controller's settings that belong to the robot (the
            friction it counts on, the least force per sole corner, its CoM gains:
            `description.contacts.BalanceDescription`).
        identification: the excitation of `hrp2-drake identify` (pushes on a body
            and one increasing sinusoid per controlled joint); empty: none (identify
            then needs a collection of its own).
        logs: how the robot's own logs are read (`description.logs.LogFormat`):
            format, columns, units, servo gain, the grid they are resampled to.
        position_loop: the servo's documented position loop (saturation, gain).
        bus: the servo bus the robot's joints are on (`description.bus`; empty
            `kind`: none). A robot on a bus runs at the bus's rate: `sensors.period`
            is its period, which the bus must carry; its servos' position P gain is
            `position_loop.gain`.
        published_motor_model: Kτ and Kv published for this robot, per joint, as
            [10³ Kτ, 10³ Kv] (Kτ in rad/(N·m), Kv in rad·s/rad; so the numbers are in
            mrad/(N·m) and mrad·s/rad), the way the paper's Table 1 prints them
            (HRP-2: that table, its source cited in robot.yaml); identification
            reports compare with them. Empty: none published.
    """

    name: str = ""
    model_file: str = ""
    base: str = "floating"
    base_body: str = ""
    base_pose: list[float] = field(default_factory=lambda: [0.0] * 6)
    joints: list[str] = field(default_factory=list)
    controlled_joints: list[str] = field(default_factory=list)
    joint_labels: list[str] = field(default_factory=list)
    imu_frame: str = ""
    force_torque_sensors: dict[str, ForceTorqueSensorDescription] = field(
        default_factory=dict
    )
    unknown_wrench_body: str = ""
    tool_frame: str = ""
    force_sensor: str = ""
    servo_file: str = "servo.yaml"
    servo_presets: dict[str, str] = field(default_factory=dict)
    control_file: str = ""
    sensors: SensorsConfig = field(default_factory=SensorsConfig)
    sensor_ranges: SensorRanges = field(default_factory=SensorRanges)
    initial_positions: list[float] = field(default_factory=list)
    trajectory_file: str = ""
    scenarios: ScenariosDescription = field(default_factory=ScenariosDescription)
    contacts: ContactsDescription = field(default_factory=ContactsDescription)
    balance: BalanceDescription = field(default_factory=BalanceDescription)
    identification: CollectionConfig = field(default_factory=CollectionConfig)
    logs: LogFormat = field(default_factory=LogFormat)
    position_loop: PositionLoopDescription = field(
        default_factory=PositionLoopDescription
    )
    bus: BusDescription = field(default_factory=BusDescription)
    published_motor_model: dict[str, list[float]] = field(default_factory=dict)
    #: The description file (set by the loader; paths are relative to its folder).
    source_file: str = ""

    @property
    def folder(self) -> Path:
        return Path(self.source_file).parent

    # ------------------------------------------------------------ plain checks

    def validate(self) -> None:
        """What can be checked without the model (the loader then checks the names
        against the model, `check_model`)."""
        self._validate_names_and_joints()
        self._validate_force_torque_sensors()
        if self.initial_positions and len(self.initial_positions) != len(self.joints):
            raise ValueError(
                f"initial_positions: {len(self.initial_positions)} values for "
                f"{len(self.joints)} joints"
            )
        self.contacts.validate()
        self.balance.validate()
        self.sensor_ranges.validate()
        if (self.balance.friction or 0.0) > self.contacts.friction > 0:
            raise ValueError(
                f"balance.friction: {self.balance.friction} exceeds contacts.friction "
                f"{self.contacts.friction}: the controller would count on friction "
                "the ground does not give"
            )
        if not self.initial_positions and not self.trajectory_file:
            raise ValueError(
                "initial_positions: empty and no trajectory_file to take the home pose "
                "from"
            )
        self._validate_scenarios()
        self.sensors.validate(len(self.joints), list(self.force_torque_sensors))
        self.logs.validate(len(self.joints))
        self.position_loop.validate()
        self.identification.validate()
        self._validate_bus()
        self._validate_published_motor_model()

    def _validate_names_and_joints(self) -> None:
        """The name, the model file, the base and its pose, the joints' lists and
        labels, and the IMU a floating base needs."""
        if not self.name:
            raise ValueError("name: empty")
        if not self.model_file:
            raise ValueError("model_file: empty")
        if self.base not in BASES:
            raise ValueError(f"base: '{self.base}', expected one of {BASES}")
        if not self.base_body:
            raise ValueError("base_body: empty")
        if len(self.base_pose) != 6 or not all(
            math.isfinite(v) for v in self.base_pose
        ):
            raise ValueError(
                f"base_pose: expected 6 finite numbers [x, y, z, roll, pitch, yaw], "
                f"got {self.base_pose}"
            )
        if not self.joints:
            raise ValueError("joints: empty")
        for key in ("joints", "controlled_joints"):
            names = getattr(self, key)
            twice = sorted({n for n in names if names.count(n) > 1})
            if twice:
                raise ValueError(f"{key}: joints listed twice {twice}")
        outside = [j for j in self.controlled_joints if j not in self.joints]
        if outside:
            raise ValueError(f"controlled_joints: {outside} are not in joints")
        if self.joint_labels and len(self.joint_labels) != len(self.controlled_joints):
            raise ValueError(
                f"joint_labels: {len(self.joint_labels)} labels for "
                f"{len(self.controlled_joints)} controlled joints"
            )
        if self.base == "floating" and not self.imu_frame:
            raise ValueError(
                "imu_frame: empty, but a floating-base robot needs an IMU (its base "
                "motion is not known otherwise)"
            )

    def _validate_force_torque_sensors(self) -> None:
        """The F/T sensors' names (they name ports) and frames, and `force_sensor`."""
        for name, sensor in self.force_torque_sensors.items():
            if not (name and name.replace("_", "a").isalnum() and name.isascii()):
                raise ValueError(
                    f"force_torque_sensors: '{name}' must be a snake_case identifier "
                    "(it names ports)"
                )
            if not sensor.frame:
                raise ValueError(f"force_torque_sensors.{name}.frame: empty")
        if self.force_sensor and self.force_sensor not in self.force_torque_sensors:
            raise ValueError(
                f"force_sensor: '{self.force_sensor}' is not one of "
                f"force_torque_sensors {sorted(self.force_torque_sensors)}"
            )

    def _validate_scenarios(self) -> None:
        """The scenarios' points and joints."""
        hanging = self.scenarios.hanging
        if any(len(p) != 3 for p in hanging.points):
            raise ValueError(
                "scenarios.hanging.points: expected [x, y, z] points, got "
                f"{hanging.points}"
            )
        block = self.scenarios.block
        if block.sole and len(block.joints) != 3:
            raise ValueError(
                "scenarios.block.joints: expected [hip pitch, knee, ankle pitch], "
                f"got {block.joints}"
            )

    def _validate_published_motor_model(self) -> None:
        """The published motor model's joints and values."""
        for joint, values in self.published_motor_model.items():
            if joint not in self.joints:
                raise ValueError(f"published_motor_model: '{joint}' is not in joints")
            if len(values) != 2 or not all(math.isfinite(v) and v >= 0 for v in values):
                raise ValueError(
                    f"published_motor_model.{joint}: expected [10³ Kτ, 10³ Kv], two "
                    f"finite numbers >= 0, got {values}"
                )

    def _validate_bus(self) -> None:
        """The bus against the joints, the sensors' period (the bus's) and the gain
        it sets."""
        bus = self.bus
        bus.validate(len(self.joints))
        if not bus.active:
            return
        check_bus_period(bus, self.sensors.period, "sensors.period")
        gain = bus.servo_model().register("position_p_gain")
        low, high = gain.limits()
        value = self.position_loop.gain
        if not (value == int(value) and low <= value <= high and value > 0):
            raise ValueError(
                f"position_loop.gain: {value:g}, but a robot on a bus sets it in its "
                f"servos' Position P Gain: an integer from 1 to {high}"
            )

    # ------------------------------------------------------------ files

    def path(self, relative: str) -> Path:
        """A path of the description, relative to its folder."""
        return Path(self.folder) / relative

    def model_path(self) -> Path:
        return self.path(self.model_file)

    def servo_path(self, preset: str = "") -> Path:
        """The servo file: `servo_file` for "" or "calibrated", a preset's by name,
        or any other string as a path (relative to the working directory)."""
        if preset in ("", "calibrated"):
            return self.path(self.servo_file)
        if preset in self.servo_presets:
            return self.path(self.servo_presets[preset])
        return Path(preset)

    def control_path(self) -> Path | None:
        """The robot's control file (`control_file`), or None if it has none."""
        return self.path(self.control_file) if self.control_file else None

    def labels(self) -> list[str]:
        """Labels of the controlled joints (their names if none are given)."""
        return list(self.joint_labels or self.controlled_joints)

    def sensor_names(self) -> list[str]:
        return list(self.force_torque_sensors)

    def sensor_body(self, name: str, plant: MultibodyPlant) -> str:
        """The body right below F/T sensor `name`: its `body`, or its frame's body."""
        sensor = self.force_torque_sensors[name]
        return sensor.body or plant.GetFrameByName(sensor.frame).body().name()

    def has_imu(self) -> bool:
        return bool(self.imu_frame)

    def base_transform(self) -> RigidTransform:
        x, y, z, roll, pitch, yaw = self.base_pose
        return RigidTransform(RollPitchYaw(roll, pitch, yaw), [x, y, z])

    # ------------------------------------------------------------ the model

    def add_model(
        self,
        plant: MultibodyPlant,
        weld_base: bool | None = None,
        model_error: float = 0.0,
        seed: int = 0,
    ) -> ModelInstanceIndex:
        """Parses the model into `plant` (not finalized) and returns its instance.

        Args:
            weld_base: weld base_body to the world at base_pose (unless the model
                welds it itself); None: if the robot is fixed.
            model_error: every link's mass and COM scaled by its own random factor in
                [1 - e, 1 + e] (uniform, repeatable by `seed`; rotational inertias
                scale with the mass): a controller's or estimator's model that is wrong
                about the robot (URDF models only); 0: the model as it is.
        """
        if not 0 <= model_error < 1:
            raise ValueError(f"model_error={model_error} must be in [0, 1)")
        if model_error == 0:
            (instance,) = Parser(plant).AddModels(str(self.model_path()))
        else:
            if self.model_path().suffix.lower() != ".urdf":
                raise ValueError(
                    f"model_error needs a URDF model, got '{self.model_file}'"
                )
            text = _perturbed_urdf(self.model_path().read_text(), model_error, seed)
            parser = Parser(plant)
            parser.package_map().PopulateFromFolder(str(self.folder))
            (instance,) = parser.AddModelsFromString(text, "urdf")
        weld = self.base == "fixed" if weld_base is None else weld_base
        if weld:
            if not plant.HasBodyNamed(self.base_body, instance):
                raise ValueError(f"base_body: no body '{self.base_body}' in the model")
            base = plant.GetBodyByName(self.base_body, instance)
            welded = any(
                plant.get_joint(j).child_body().index() == base.index()
                and plant.get_joint(j).parent_body().index()
                == plant.world_body().index()
                for j in plant.GetJointIndices(instance)
            )
            if not welded:
                plant.WeldFrames(
                    plant.world_frame(), base.body_frame(), self.base_transform()
                )
        return instance

    def make_plant(
        self, weld_base: bool | None = None, model_error: float = 0.0, seed: int = 0
    ) -> MultibodyPlant:
        """The robot alone, finalized, continuous (fixed: welded at base_pose;
        floating: free, or welded with `weld_base`): e.g. the estimator's model, or,
        welded, the inverse dynamics' (paper footnote 3). `add_model` says what
        model_error does."""
        plant = MultibodyPlant(0.0)
        self.add_model(plant, weld_base, model_error, seed)
        plant.Finalize()
        return plant

    def sensor_of_body(self, body: str) -> str:
        """The F/T sensor whose body is `body` (or whose frame is `body`), else the
        description's force_sensor."""
        for name, sensor in self.force_torque_sensors.items():
            if body and body in (sensor.body, sensor.frame):
                return name
        if self.force_sensor:
            return self.force_sensor
        raise ValueError(f"robot '{self.name}': no F/T sensor carries '{body}'")

    def home_positions(self) -> np.ndarray:
        """The home pose (rad, joints order)."""
        if self.initial_positions:
            return np.array(self.initial_positions, float)
        return self.load_trajectory()[1][0].copy()

    def load_trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """(t, q) of trajectory_file: times (m,), joint angles (m, n)."""
        if not self.trajectory_file:
            raise ValueError(f"robot '{self.name}': trajectory_file: none")
        path = self.path(self.trajectory_file)
        data = np.loadtxt(path)  # numpy reads .gz transparently
        n = len(self.joints)
        if data.ndim != 2 or data.shape[1] < 1 + n:
            raise ValueError(
                f"{path}: expected rows of time + {n} joint angles, got shape "
                f"{data.shape}"
            )
        return data[:, 0], data[:, 1 : 1 + n]

    def check_model(self, plant: MultibodyPlant) -> None:
        """Checks every name against `plant` (finalized, from `make_plant`); a
        ValueError names the field."""
        base = self._check_base(plant)
        self._check_joints(plant)
        holders = tree_joints(plant, base.index())
        below = self._check_force_torque_sensors(plant, base, holders)
        parent = {int(base.index()): -1} | {b: a for b, (a, _) in holders.items()}
        self._check_imu(plant, parent, below)
        self._check_other_names(plant)
        self.contacts.check_model(plant)
        self._check_home(plant)

    def _check_base(self, plant: MultibodyPlant) -> RigidBody:
        """base_body is in the model, floating or fixed as `base` says; returns it."""
        if not plant.HasBodyNamed(self.base_body):
            raise ValueError(f"base_body: no body '{self.base_body}' in the model")
        base = plant.GetBodyByName(self.base_body)
        if self.base == "floating" and not base.is_floating_base_body():
            raise ValueError(
                f"base: 'floating', but '{self.base_body}' is not a floating body of "
                "the model (is it welded to the world?)"
            )
        if self.base == "fixed" and plant.GetFloatingBaseBodies():
            names = [
                plant.get_body(BodyIndex(b)).name()
                for b in plant.GetFloatingBaseBodies()
            ]
            raise ValueError(
                f"base: 'fixed', but the model has floating bodies {names}"
            )
        return base

    def _check_joints(self, plant: MultibodyPlant) -> None:
        """`joints` are the model's one-dof joints, all of them, each actuated."""
        for j, name in enumerate(self.joints):
            if not plant.HasJointNamed(name):
                raise ValueError(f"joints[{j}]: no joint '{name}' in the model")
            joint = plant.GetJointByName(name)
            if joint.num_velocities() != 1:
                raise ValueError(
                    f"joints[{j}]: '{name}' is a {joint.type_name()} joint, expected "
                    "one degree of freedom"
                )
        dofs = plant.num_velocities() - (6 if self.base == "floating" else 0)
        if dofs != len(self.joints):
            listed = set(self.joints)
            missing = [
                plant.get_joint(j).name()
                for j in plant.GetJointIndices()
                if plant.get_joint(j).num_velocities() == 1
                and plant.get_joint(j).name() not in listed
            ]
            raise ValueError(
                f"joints: {len(self.joints)} listed, the model has {dofs} joint "
                f"degrees of freedom; not listed: {missing}"
            )
        actuated = {
            plant.get_joint_actuator(a).joint().name()
            for a in plant.GetJointActuatorIndices()
        }
        unactuated = [name for name in self.joints if name not in actuated]
        if unactuated:
            raise ValueError(f"joints: {unactuated} have no actuator in the model")

    def _check_force_torque_sensors(
        self, plant: MultibodyPlant, base: RigidBody, holders: dict[int, tuple]
    ) -> dict[str, int]:
        """Each sensor's frame and body are in the model, the body is below the sensor
        (not the base, not above its frame, rigidly holding it) and hangs from a fixed
        joint (the sensor: what it reads is that joint's reaction force). `holders`:
        `tree_joints` from the base. Returns the index of each sensor's body, by
        sensor name."""
        world = plant.world_body().index()
        parent = {int(base.index()): -1} | {b: a for b, (a, _) in holders.items()}
        below = {}
        for name, sensor in self.force_torque_sensors.items():
            where = f"force_torque_sensors.{name}"
            if not plant.HasFrameNamed(sensor.frame):
                raise ValueError(
                    f"{where}.frame: no frame '{sensor.frame}' in the model"
                )
            frame = plant.GetFrameByName(sensor.frame)
            body_name = sensor.body or frame.body().name()
            if not plant.HasBodyNamed(body_name):
                raise ValueError(f"{where}.body: no body '{body_name}' in the model")
            body = plant.GetBodyByName(body_name)
            if body.index() == base.index() or body.index() == world:
                raise ValueError(
                    f"{where}.body: '{body_name}' is the base; give the body right "
                    "below the sensor"
                )
            welded = {b.index() for b in plant.GetBodiesWeldedTo(body)} | {body.index()}
            if frame.body().index() not in welded:
                raise ValueError(
                    f"{where}.frame: '{sensor.frame}' is not rigidly attached to body "
                    f"'{body_name}'"
                )
            if is_strictly_below(parent, int(frame.body().index()), int(body.index())):
                raise ValueError(
                    f"{where}.body: '{body_name}' is above its frame '{sensor.frame}' "
                    f"(on body '{frame.body().name()}'): give the body right below the "
                    "sensor"
                )
            _, joint = holders[int(body.index())]
            if joint.type_name() != "weld":
                raise ValueError(
                    f"{where}.body: '{body_name}' hangs from {joint.type_name()} "
                    f"joint '{joint.name()}'; an F/T sensor is a fixed joint above "
                    "its body (its reaction force is what the sensor reads)"
                )
            below[name] = int(body.index())
        return below

    def _check_imu(
        self, plant: MultibodyPlant, parent: dict[int, int], below: dict[str, int]
    ) -> None:
        """The IMU frame (if any) is in the model, on the base side of every F/T
        sensor (`below`: each sensor's body index)."""
        if not self.imu_frame:
            return
        if not plant.HasFrameNamed(self.imu_frame):
            raise ValueError(f"imu_frame: no frame '{self.imu_frame}' in the model")
        imu_body = int(plant.GetFrameByName(self.imu_frame).body().index())
        for name, index in below.items():
            if imu_body == index or is_strictly_below(parent, imu_body, index):
                raise ValueError(
                    f"imu_frame: '{self.imu_frame}' is below F/T sensor '{name}': the "
                    "IMU must be on the base side of every sensor"
                )

    def _check_other_names(self, plant: MultibodyPlant) -> None:
        """The bodies, frames and joints that the unknown wrench, the tool, the
        scenarios and the identification excitation name."""
        for key, value in (
            ("unknown_wrench_body", self.unknown_wrench_body),
            ("scenarios.hanging.body", self.scenarios.hanging.body),
        ):
            if value and not plant.HasBodyNamed(value):
                raise ValueError(f"{key}: no body '{value}' in the model")
        frames = [("tool_frame", self.tool_frame)] + [
            (f"scenarios.soles[{k}]", s) for k, s in enumerate(self.scenarios.soles)
        ]
        if self.scenarios.block.sole:
            frames.append(("scenarios.block.sole", self.scenarios.block.sole))
        for key, value in frames:
            if value and not plant.HasFrameNamed(value):
                raise ValueError(f"{key}: no frame '{value}' in the model")
        for k, name in enumerate(self.scenarios.block.joints):
            if name not in self.joints:
                raise ValueError(
                    f"scenarios.block.joints[{k}]: '{name}' is not in joints"
                )
        for k, name in enumerate(s.joint for s in self.identification.sinusoids):
            if name not in self.joints:
                raise ValueError(
                    f"identification.sinusoids[{k}].joint: '{name}' is not in joints"
                )
        push = self.identification.pushes.body
        if push and not plant.HasBodyNamed(push):
            raise ValueError(
                f"identification.pushes.body: no body '{push}' in the model"
            )

    def _check_home(self, plant: MultibodyPlant) -> None:
        """The home pose is within the model's joint limits."""
        home = self.home_positions()
        for j, name in enumerate(self.joints):
            joint = plant.GetJointByName(name)
            low, high = (
                joint.position_lower_limits()[0],
                joint.position_upper_limits()[0],
            )
            if not low - 1e-9 <= home[j] <= high + 1e-9:
                raise ValueError(
                    f"initial_positions[{j}]: {name} = {home[j]:.6g} rad is outside "
                    f"its limits [{low:.6g}, {high:.6g}]"
                )


@functools.lru_cache(maxsize=8)
def _joint_limits(source_file: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    robot = load_robot_description(source_file)
    plant = robot.make_plant()
    joints = [plant.GetJointByName(name) for name in robot.joints]
    lower = np.array([j.position_lower_limits()[0] for j in joints])
    upper = np.array([j.position_upper_limits()[0] for j in joints])
    speed = np.array([j.velocity_upper_limits()[0] for j in joints])
    return lower, upper, speed


def joint_limits(robot: RobotDescription) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lower, upper) position limits (rad) and the velocity limits (rad/s) of the
    robot's joints, in its joint order, as the MultibodyPlant reads them from the
    model (inf where the model gives none)."""
    return _joint_limits(robot.source_file)


def check_joint_positions(
    q: np.ndarray, where: str, robot: RobotDescription, tolerance: float = 1e-9
) -> None:
    """Raises ValueError naming `where`, the first offending joint and row unless every
    row of q (m, n) lies within the robot's joint position limits."""
    lower, upper, _ = joint_limits(robot)
    outside = (q < lower - tolerance) | (q > upper + tolerance)
    if np.any(outside):
        row, j = np.argwhere(outside)[0]
        raise ValueError(
            f"{where}: {robot.joints[j]} = {q[row, j]:.6g} rad (row {row}) is "
            f"outside its position limits [{lower[j]:.6g}, {upper[j]:.6g}] rad "
            f"({np.count_nonzero(np.any(outside, axis=1))} rows out of limits)"
        )


def _perturbed_urdf(text: str, error: float, seed: int) -> str:
    """URDF text with every link's mass and COM scaled by its own random factor in
    [1 - error, 1 + error] (rotational inertias scale with the mass)."""
    import xml.etree.ElementTree as ElementTree

    # Keep the file's `drake:` prefix on the tags Drake reads (gear ratio, rotor).
    ElementTree.register_namespace("drake", "http://drake.mit.edu")
    rng = np.random.default_rng(seed)
    root = ElementTree.fromstring(text)
    for inertial in root.iter("inertial"):
        mass_scale, com_scale = (
            float(v) for v in 1.0 + error * rng.uniform(-1.0, 1.0, 2)
        )
        mass = inertial.find("mass")
        mass.set("value", f"{float(mass.get('value')) * mass_scale:.9g}")
        inertia = inertial.find("inertia")
        for key, value in inertia.attrib.items():
            inertia.set(key, f"{float(value) * mass_scale:.9g}")
        origin = inertial.find("origin")
        if origin is not None:
            xyz = [float(v) * com_scale for v in origin.get("xyz", "0 0 0").split()]
            origin.set("xyz", " ".join(f"{v:.9g}" for v in xyz))
    return ElementTree.tostring(root, encoding="unicode")


def models_root() -> Path:
    """models/ of the source tree, or $HRP2_DRAKE_MODELS_ROOT if set."""
    env = os.environ.get("HRP2_DRAKE_MODELS_ROOT")
    return Path(env) if env else Path(__file__).resolve().parents[2] / "models"


def robot_file(robot: str | Path | None = None) -> Path:
    """The description file of `robot`: a path to a robot.yaml (or to a folder holding
    one), or the name of a robot in models/ ("hrp2", "iiwa14"); None or "": HRP-2."""
    spec = str(robot) if robot else DEFAULT_ROBOT
    path = Path(spec)
    if not path.exists() and (models_root() / spec / "robot.yaml").is_file():
        path = models_root() / spec / "robot.yaml"
    if path.is_dir():
        path = path / "robot.yaml"
    if not path.is_file():
        known = sorted(p.parent.name for p in models_root().glob("*/robot.yaml"))
        raise FileNotFoundError(
            f"robot description '{spec}' not found: give a robot.yaml path or one of "
            f"{known}"
        )
    return path.resolve()


def load_robot_description(
    robot: str | Path | None = None, check: bool = True
) -> RobotDescription:
    """Reads and checks a robot description (`robot_file` says what `robot` may be).
    Cached per file (the result is shared: do not modify it, `copy.deepcopy` first).

    Raises:
        FileNotFoundError: no such description or model file.
        ValueError: a bad field, named, with the file.
    """
    path = robot_file(robot)
    return _load(str(path), path.stat().st_mtime_ns, check)


@functools.lru_cache(maxsize=16)
def _load(path: str, mtime: int, check: bool) -> RobotDescription:
    description = load_config(RobotDescription, filename=path)
    description.source_file = path
    if not description.model_path().is_file():
        raise FileNotFoundError(
            f"{path}: model_file: '{description.model_path()}' not found"
        )
    trajectory = description.trajectory_file
    if trajectory and not description.path(trajectory).is_file():
        raise ValueError(
            f"{path}: trajectory_file: '{description.path(trajectory)}' not found"
        )
    control = description.control_path()
    if control is not None and not control.is_file():
        raise FileNotFoundError(f"{path}: control_file: '{control}' not found")
    if check:
        try:
            plant = description.make_plant()
        except RuntimeError as error:  # Drake's: the parser's, or a kinematic loop
            raise ValueError(
                f"{path}: model_file '{description.model_path()}': {one_line(error)}"
            ) from error
        except ValueError as error:
            raise ValueError(f"{path}: {error}") from error
        try:
            description.check_model(plant)
        except (ValueError, RuntimeError) as error:
            raise ValueError(f"{path}: {error}") from error
    return description
