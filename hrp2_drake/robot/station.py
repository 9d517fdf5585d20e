"""make_station(config): the simulated HRP-2 as one Diagram with named ports.

.. code-block:: text

                           ┌──────────────────────────────┐
    q_cmd ────────────────►│                              ├──► q_measured
    applied_spatial_force ►│   MultibodyPlant (HRP-2)     ├──► imu_linear_acceleration
                           │ + Hrp2ServoEmulation         ├──► imu_angular_velocity
                           │ + encoders, IMU, 4 F/T       ├──► wrench_<sensor> (x4)
                           │   (+ fault injection)        ├──► sensor_time
                           │   (noise, bias, 1 kHz)       ├──► joint_torque_true
                           │                              ├──► state_true
                           │                              ├──► body_poses
                           └──────────────────────────────┘

Scenarios (`StationConfig.scenario`):
  - "fixed_base": the waist welded 1 m above the ground.
  - "hanging": floating base held by two strings from the shoulders (spring-dampers to
    fixed anchors, as in the paper's Fig. 2b), feet in the air.
  - "standing": both feet on flat ground.
  - "standing_on_block": left foot on the ground, right foot on a rigid block
    (the paper's Fig. 2a); the right leg is bent so that the sole rests on the block.

`joint_torque_true` and `state_true` are ground truth, for evaluation only: estimators,
identification and controllers must not read them. `joint_torque_true` is the torque
the servo applied over the last plant step (the plant's net actuation, HRP-2 joint
order), the same step the accelerometer and F/T readings come from.

The noise of every sensor is a pure function of `SensorsConfig.seed` and the sample
index (`NoisySampler`), so every run of a config repeats the same noise.
"""


import functools
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from pydrake.geometry import Box, Meshcat, MeshcatVisualizer, MeshcatVisualizerParams, Role
from pydrake.math import RigidTransform
from pydrake.multibody.plant import (
    AddMultibodyPlant,
    CoulombFriction,
    MultibodyPlant,
    MultibodyPlantConfig,
)
from pydrake.multibody.tree import LinearBushingRollPitchYaw, LinearSpringDamper
from pydrake.systems.framework import Diagram, DiagramBuilder
from pydrake.systems.primitives import Demultiplexer, MatrixGain
from pydrake.systems.sensors import Accelerometer, Gyroscope

from hrp2_drake.multibody import JointIndexing
from hrp2_drake.robot import model
from hrp2_drake.robot.faults import FaultInjector, SensorClock, SensorFault
from hrp2_drake.robot.sensors import ForceTorqueReadout, NoisySampler, SensorsConfig
from hrp2_drake.robot.servo import (
    SERVO_MECHANISMS,
    Hrp2ServoEmulation,
    ServoParams,
    load_servo_params,
)

SCENARIOS = ("fixed_base", "hanging", "standing", "standing_on_block")
#: The sensor ports of the station and their sizes, in the order of its
#: `sensor_time` output.
SENSOR_SIZES: dict[str, int] = {
    "q_measured": model.NUM_JOINTS,
    "imu_linear_acceleration": 3,
    "imu_angular_velocity": 3,
    **{f"wrench_{name}": 6 for name in model.FT_SENSORS},
}
SENSOR_SIGNALS = tuple(SENSOR_SIZES)
GRAVITY = 9.81


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
class StationConfig:
    """Configuration of the simulated HRP-2 (load with `load_station_config`).

    Args:
        scenario: one of "fixed_base", "hanging", "standing", "standing_on_block".
        time_step: the plant's discrete time step (s).
        initial_positions: the 30 initial joint angles (rad), HRP-2 order; empty for
            half-sitting (the first sample of the climbing motion).
        sensors: noise, bias and sampling of the sensors.
        hanging: the strings of the "hanging" scenario.
        block_height: height of the block under the right foot (m),
            "standing_on_block" only.
        servo_file: the servo data file: a path, "ideal" (models/hrp2/servo_ideal.yaml:
            the paper's eq. 6 with a small dead zone, for tests of the exact linear
            law) or "calibrated" / empty (models/hrp2/servo.yaml, calibrated to the
            real robot by `hrp2-drake calibrate`).
        faults: sensor faults to inject (`hrp2_drake.robot.faults`): what the sensor
            ports read; the ground truth is untouched.
        extra_command_latency: latency added to every joint's command (s, whole
            periods): a fault, on top of the servo's own.
        servo_off: servo mechanisms to switch off (`SERVO_MECHANISMS`: "latency",
            "voltage_limit", "hysteresis", "deadzone").
        contact_approximation: Drake's discrete contact approximation.
    """

    scenario: str = "hanging"
    time_step: float = 0.001
    initial_positions: list[float] = field(default_factory=list)
    sensors: SensorsConfig = field(default_factory=SensorsConfig)
    hanging: HangingConfig = field(default_factory=HangingConfig)
    block_height: float = 0.05
    servo_file: str = ""
    servo_off: list[str] = field(default_factory=list)
    faults: list[SensorFault] = field(default_factory=list)
    extra_command_latency: float = 0.0
    contact_approximation: str = "sap"

    def validate(self) -> None:
        if self.scenario not in SCENARIOS:
            raise ValueError(
                f"StationConfig.scenario: unknown scenario '{self.scenario}', "
                f"expected one of {SCENARIOS}"
            )
        if len(self.initial_positions) not in (0, model.NUM_JOINTS):
            raise ValueError(
                f"StationConfig.initial_positions: {len(self.initial_positions)} values, "
                f"expected {model.NUM_JOINTS} (or none for half-sitting)"
            )
        unknown = sorted(set(self.servo_off) - set(SERVO_MECHANISMS))
        if unknown:
            raise ValueError(
                f"StationConfig.servo_off: unknown servo mechanism(s) {unknown}, "
                f"expected some of {list(SERVO_MECHANISMS)}"
            )
        for k, fault in enumerate(self.faults):
            fault.validate(f"StationConfig.faults[{k}]", SENSOR_SIZES)
        if len(self.hanging.sway_damping) != 2:
            raise ValueError(
                "StationConfig.hanging.sway_damping: expected [rotational, translational]"
                f", got {self.hanging.sway_damping}"
            )
        if not self.time_step > 0:
            raise ValueError(f"StationConfig.time_step must be > 0, got {self.time_step}")
        if set(self.sensors.force_torque) != set(model.FT_SENSORS):
            raise ValueError(
                "StationConfig.sensors.force_torque: sensors "
                f"{sorted(self.sensors.force_torque)}, expected {sorted(model.FT_SENSORS)}"
            )


def initial_joint_positions(config: StationConfig) -> np.ndarray:
    """The scenario's initial joint angles (rad, 30): what the servo should hold."""
    q = (
        np.array(config.initial_positions, float)
        if config.initial_positions
        else model.half_sitting()
    )
    if config.scenario == "standing_on_block":
        q = _raise_right_foot(q, config.block_height)
    return q


@functools.cache
def _kinematic_model() -> tuple[MultibodyPlant, JointIndexing]:
    """HRP-2 alone (floating, no scenario), parsed once: for the kinematics that set a
    scenario up (sole heights, block and string placement)."""
    plant = MultibodyPlant(0.0)
    model.add_hrp2(plant)
    plant.Finalize()
    return plant, model.hrp2_joint_indexing(plant)


def _posed(q: np.ndarray, X_WB: RigidTransform | None = None):
    """(plant, context) of the kinematic model at joint angles q, waist at X_WB
    (default: the origin, upright)."""
    plant, indexing = _kinematic_model()
    context = plant.CreateDefaultContext()
    x = plant.GetPositions(context)
    x[indexing.q] = q
    plant.SetPositions(context, x)
    if X_WB is not None:
        plant.SetFreeBodyPose(context, plant.GetBodyByName(model.BASE_BODY), X_WB)
    return plant, context


def _frame_position(q: np.ndarray, frame: str) -> np.ndarray:
    """Position in the world of `frame` with the waist at the origin, upright (m)."""
    plant, context = _posed(q)
    return plant.GetFrameByName(frame).CalcPoseInWorld(context).translation()


def _raise_right_foot(q: np.ndarray, height: float) -> np.ndarray:
    """Bends the right leg (hip pitch, knee; ankle pitch keeps the sole parallel) so
    that the right sole is `height` higher, at the same x, relative to the waist."""
    from scipy.optimize import least_squares

    def sole_xz(angles: np.ndarray) -> np.ndarray:
        qj = q.copy()
        qj[2], qj[3] = angles
        qj[4] = q[4] - (angles[0] - q[2]) - (angles[1] - q[3])
        return _frame_position(qj, model.SOLE_FRAMES["right_foot"])[[0, 2]]

    target = sole_xz(q[2:4]) + [0.0, height]
    fit = least_squares(lambda a: sole_xz(a) - target, q[2:4])
    if np.max(np.abs(fit.fun)) > 1e-6:
        raise ValueError(f"block_height {height} m is out of the right leg's reach")
    out = q.copy()
    out[2], out[3] = fit.x
    out[4] = q[4] - (fit.x[0] - q[2]) - (fit.x[1] - q[3])
    return out


def _lowest_sole_height(q: np.ndarray) -> float:
    """Height of the lowest sole when the waist is at the origin, upright."""
    return min(_frame_position(q, f)[2] for f in model.SOLE_FRAMES.values())


def _add_ground(plant: MultibodyPlant) -> None:
    # A thick box rather than a HalfSpace: same point contact for the sole spheres,
    # without Drake's warning that half spaces do not support deformable contact.
    X_WG = RigidTransform([0.0, 0.0, -0.05])
    plant.RegisterCollisionGeometry(
        plant.world_body(), X_WG, Box(6, 6, 0.1), "ground", CoulombFriction(1.0, 1.0)
    )
    plant.RegisterVisualGeometry(
        plant.world_body(), X_WG, Box(6, 6, 0.1), "ground", [0.8, 0.8, 0.75, 1.0]
    )


def _add_block(plant: MultibodyPlant, q: np.ndarray, height: float):
    """A rigid block under the right sole (horizontal position of the sole with the
    waist above the origin)."""
    p = _frame_position(q, model.SOLE_FRAMES["right_foot"])
    size = (0.36, 0.18, height)  # clear of the left foot (0.19 m apart)
    X_WB = RigidTransform([p[0] + 0.015, p[1], height / 2])
    shape = Box(*size)
    plant.RegisterCollisionGeometry(
        plant.world_body(), X_WB, shape, "block", CoulombFriction(1.0, 1.0)
    )
    plant.RegisterVisualGeometry(
        plant.world_body(), X_WB, shape, "block", [0.6, 0.3, 0.2, 1.0]
    )


def make_station(config: StationConfig, meshcat: Meshcat | None = None) -> Diagram:
    """Builds the station Diagram (module docstring) for `config`.

    The default context of the returned diagram holds the scenario's initial state.
    If `meshcat` is given, a MeshcatVisualizer publishes the illustration geometry.
    """
    config.validate()
    q0 = initial_joint_positions(config)
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(
        MultibodyPlantConfig(
            time_step=config.time_step,
            discrete_contact_approximation=config.contact_approximation,
        ),
        builder,
    )
    model.add_hrp2(plant)
    base = plant.GetBodyByName(model.BASE_BODY)
    base_height = -_lowest_sole_height(q0)
    if config.scenario == "fixed_base":
        X_WB0 = RigidTransform([0.0, 0.0, 1.0])
        plant.WeldFrames(plant.world_frame(), base.body_frame(), X_WB0)
    elif config.scenario == "hanging":
        X_WB0 = RigidTransform([0.0, 0.0, base_height + config.hanging.feet_clearance])
    else:
        X_WB0 = RigidTransform([0.0, 0.0, base_height])
    if config.scenario != "hanging":
        _add_ground(plant)
    if config.scenario == "standing_on_block":
        _add_block(plant, q0, config.block_height)
    if config.scenario == "hanging":
        _add_strings(plant, q0, X_WB0, config.hanging)
    plant.Finalize()
    plant.set_name("plant")

    indexing = model.hrp2_joint_indexing(plant)
    for name, angle in zip(indexing.names, q0):
        plant.GetJointByName(name).set_default_angle(angle)
    if config.scenario != "fixed_base":
        plant.SetDefaultFloatingBaseBodyPose(base, X_WB0)

    servo_params = load_servo_params(config.servo_file or None)
    servo = builder.AddNamedSystem(
        "servo",
        Hrp2ServoEmulation(
            plant,
            servo_params,
            model.JOINT_NAMES,
            period=config.time_step,
            initial_q_cmd=q0,
            off=config.servo_off,
            extra_latency=config.extra_command_latency,
        ),
    )
    builder.Connect(plant.get_state_output_port(), servo.get_input_port(1))
    builder.Connect(servo.get_output_port(), plant.get_actuation_input_port())
    builder.ExportInput(servo.get_input_port(0), "q_cmd")
    builder.ExportInput(plant.get_applied_spatial_force_input_port(), "applied_spatial_force")

    _add_sensors(builder, plant, indexing, config.sensors, q0, servo_params, config.faults)

    builder.ExportOutput(plant.get_net_actuation_output_port(), "joint_torque_true")
    builder.ExportOutput(plant.get_state_output_port(), "state_true")
    builder.ExportOutput(plant.get_body_poses_output_port(), "body_poses")
    builder.ExportOutput(plant.get_contact_results_output_port(), "contact_results")
    if meshcat is not None:
        MeshcatVisualizer.AddToBuilder(
            builder, scene_graph, meshcat, MeshcatVisualizerParams(role=Role.kIllustration)
        )
    diagram = builder.Build()
    diagram.set_name(f"hrp2_station_{config.scenario}")
    return diagram


def _add_strings(
    plant: MultibodyPlant, q0: np.ndarray, X_WB0: RigidTransform, cfg: HangingConfig
) -> None:
    """Two strings from fixed anchors to the shoulders, stretched by the weight."""
    plant_k, context = _posed(q0, X_WB0)
    torso_k = plant_k.GetBodyByName(model.IMU_BODY)
    X_WT = torso_k.EvalPoseInWorld(context)
    stretch = plant_k.CalcTotalMass(context) * GRAVITY / (2 * cfg.stiffness)
    torso = plant.GetBodyByName(model.IMU_BODY)
    for p_TS in model.SHOULDERS.values():
        anchor = X_WT @ np.array(p_TS) + [0.0, 0.0, cfg.string_length + stretch]
        plant.AddForceElement(
            LinearSpringDamper(
                plant.world_body(), anchor, torso, p_TS,
                cfg.string_length, cfg.stiffness, cfg.damping,
            )
        )
    rotational, translational = cfg.sway_damping
    plant.AddForceElement(
        LinearBushingRollPitchYaw(
            plant.world_frame(), torso.body_frame(), [0.0] * 3, [rotational] * 3,
            [0.0] * 3, [translational] * 3,
        )
    )


def _add_sensors(
    builder: DiagramBuilder,
    plant: MultibodyPlant,
    indexing: JointIndexing,
    cfg: SensorsConfig,
    q0: np.ndarray,
    servo: ServoParams,
    faults: Sequence[SensorFault] = (),
) -> None:
    seeds = iter(range(1000 * cfg.seed + 1, 1000 * cfg.seed + 100))

    def export(port, name: str) -> None:
        """Exports a sensor port, through a FaultInjector if a fault names it."""
        mine = [f for f in faults if f.signal == name]
        if mine:
            injector = builder.AddNamedSystem(
                f"faults_{name}", FaultInjector(port.size(), mine, cfg.period)
            )
            builder.Connect(port, injector.get_input_port())
            port = injector.get_output_port()
        builder.ExportOutput(port, name)

    def sampler(name: str, signal_port, std, bias, resolution=None, initial=None):
        size = len(std)
        system = builder.AddNamedSystem(
            name,
            NoisySampler(size, cfg.period, std, bias, next(seeds), resolution, initial),
        )
        builder.Connect(signal_port, system.get_input_port())
        return system.get_output_port()

    # Encoders: joint positions from the plant state, quantized.
    nx = plant.num_positions() + plant.num_velocities()
    select = np.zeros((indexing.size, nx))
    select[np.arange(indexing.size), indexing.q] = 1.0
    positions = builder.AddNamedSystem("joint_positions", MatrixGain(select))
    builder.Connect(plant.get_state_output_port(), positions.get_input_port())
    resolution = None
    if cfg.encoder_quantization:
        resolution = servo.vectors(indexing.names)["encoder_resolution"]
    export(
        sampler(
            "encoders",
            positions.get_output_port(),
            *cfg.encoder.vectors(indexing.size, "sensors.encoder"),
            resolution,
            q0,
        ),
        "q_measured",
    )

    # IMU in the torso.
    imu = plant.GetFrameByName(model.IMU_FRAME)
    X_BS = imu.GetFixedPoseInBodyFrame()
    body = imu.body()
    accel = builder.AddNamedSystem(
        "accelerometer", Accelerometer(body, X_BS, plant.gravity_field().gravity_vector())
    )
    gyro = builder.AddNamedSystem("gyroscope", Gyroscope(body, X_BS))
    builder.Connect(plant.get_body_poses_output_port(), accel.get_body_poses_input_port())
    builder.Connect(
        plant.get_body_spatial_velocities_output_port(), accel.get_body_velocities_input_port()
    )
    builder.Connect(
        plant.get_body_spatial_accelerations_output_port(),
        accel.get_body_accelerations_input_port(),
    )
    builder.Connect(plant.get_body_poses_output_port(), gyro.get_body_poses_input_port())
    builder.Connect(
        plant.get_body_spatial_velocities_output_port(), gyro.get_body_velocities_input_port()
    )
    export(
        sampler(
            "imu_accelerometer",
            accel.get_measurement_output_port(),
            *cfg.accelerometer.vectors(3, "sensors.accelerometer"),
        ),
        "imu_linear_acceleration",
    )
    export(
        sampler(
            "imu_gyroscope",
            gyro.get_measurement_output_port(),
            *cfg.gyroscope.vectors(3, "sensors.gyroscope"),
        ),
        "imu_angular_velocity",
    )

    # Four F/T sensors: one readout, one sampler, then one port per sensor.
    names = list(model.FT_SENSORS)
    readout = builder.AddNamedSystem(
        "force_torque_readout", ForceTorqueReadout(plant, list(model.FT_SENSORS.values()))
    )
    builder.Connect(plant.get_reaction_forces_output_port(), readout.get_input_port())
    stds, biases = zip(*(cfg.force_torque[n].vectors(6, f"sensors.force_torque.{n}")
                         for n in names))
    sampled = sampler(
        "force_torque",
        readout.get_output_port(),
        np.concatenate(stds),
        np.concatenate(biases),
    )
    demux = builder.AddNamedSystem("force_torque_demux", Demultiplexer([6] * len(names)))
    builder.Connect(sampled, demux.get_input_port())
    for k, name in enumerate(names):
        export(demux.get_output_port(k), f"wrench_{name}")

    # The time stamp of every sensor's latest sample (SENSOR_SIGNALS order).
    clock = builder.AddNamedSystem(
        "sensor_clock", SensorClock(SENSOR_SIGNALS, faults, cfg.period)
    )
    builder.ExportOutput(clock.get_output_port(), "sensor_time")

