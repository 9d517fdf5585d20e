"""make_station: scenarios, sensors, configs, and the closed-loop behaviour the rest
of the project stands on (standing still, hanging, the F/T and IMU readings)."""

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest
from pydrake.multibody.math import SpatialForce
from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource

from hrp2_drake.config import load_config
from hrp2_drake.description.sensors import NoiseConfig, SensorsConfig
from hrp2_drake.multibody import joint_indexing
from hrp2_drake.paper import hrp2
from hrp2_drake.robot.faults import SensorClock, SensorFault
from hrp2_drake.robot.sensors import ForceTorqueReadout, NoisySampler, SensorSampler
from hrp2_drake.robot.servo import load_servo_params
from hrp2_drake.robot.station import (
    GRAVITY,
    StationConfig,
    force_torque_readouts,
    initial_joint_positions,
    make_station,
    sensor_sizes,
)
from hrp2_drake.tools.simulate import SimulateConfig, run_simulate


def _run(config: StationConfig, duration: float, q_offset=None):
    builder = DiagramBuilder()
    station = builder.AddSystem(make_station(config))
    q_cmd = initial_joint_positions(config)
    if q_offset is not None:
        q_cmd = q_cmd + q_offset
    source = builder.AddSystem(ConstantVectorSource(q_cmd))
    builder.Connect(source.get_output_port(), station.GetInputPort("q_cmd"))
    simulator = Simulator(builder.Build())
    simulator.AdvanceTo(duration)
    return station, station.GetMyContextFromRoot(simulator.get_context()), q_cmd


@pytest.fixture(scope="module")
def kinematic_plant():
    plant = MultibodyPlant(0.0)
    hrp2.add_hrp2(plant)
    plant.Finalize()
    return plant


def _mass_below(plant, body_name: str) -> float:
    """Mass of `body_name` and every body outboard of it."""
    body = plant.GetBodyByName(body_name)
    context = plant.CreateDefaultContext()
    total = body.get_mass(context)
    frontier = [body.index()]
    while frontier:
        parent = frontier.pop()
        for j in plant.GetJointIndices():
            joint = plant.get_joint(j)
            if joint.parent_body().index() == parent:
                total += joint.child_body().get_mass(context)
                frontier.append(joint.child_body().index())
    return total


def test_total_mass_is_hrp2s(kinematic_plant):
    context = kinematic_plant.CreateDefaultContext()
    assert kinematic_plant.CalcTotalMass(context) == pytest.approx(56.037, abs=1e-3)
    assert kinematic_plant.num_actuators() == 30


@pytest.fixture(scope="module")
def standing_noiseless():
    config = StationConfig(scenario="standing", sensors=SensorsConfig.noiseless())
    return _run(config, 1.0)


def test_ankle_ft_sum_to_weight_above(standing_noiseless, kinematic_plant):
    station, context, _ = standing_noiseless
    feet = sum(_mass_below(kinematic_plant, b) for b in ("RLEG_FOOT", "LLEG_FOOT"))
    weight_above = (56.037 - feet) * GRAVITY
    fz = [
        station.GetOutputPort(f"wrench_{side}_foot").Eval(context)[5]
        for side in ("right", "left")
    ]
    assert min(fz) > 0.3 * weight_above  # both feet loaded, read as +z
    assert sum(fz) == pytest.approx(weight_above, rel=0.01)


def test_wrist_ft_read_hand_weight(standing_noiseless, kinematic_plant):
    station, context, _ = standing_noiseless
    for sensor, body in (("right_hand", "RARM_HAND"), ("left_hand", "LARM_HAND")):
        wrench = station.GetOutputPort(f"wrench_{sensor}").Eval(context)
        weight = _mass_below(kinematic_plant, body) * GRAVITY
        assert np.linalg.norm(wrench[3:]) == pytest.approx(weight, rel=0.01)


def test_imu_reads_plus_g_standing_still():
    """Default (noisy, biased) IMU: the mean over 0.5 s is +g along the torso's z
    within bias + noise."""
    config = SimulateConfig(station=StationConfig(scenario="standing"), duration=1.0)
    signals = run_simulate(config).signals
    accel = signals["imu_linear_acceleration"][500:]
    gyro = signals["imu_angular_velocity"][500:]
    mean = accel.mean(axis=0)
    assert mean[2] == pytest.approx(GRAVITY, abs=0.1)
    assert np.linalg.norm(mean[:2]) < 0.15
    assert np.abs(gyro.mean(axis=0)).max() < 0.005


def test_imu_noise_has_the_configured_statistics():
    """Waist welded (the torso barely moves): the accelerometer's spread is the
    configured white noise and its mean is g plus the configured bias."""
    config = SimulateConfig(station=StationConfig(scenario="fixed_base"), duration=1.0)
    accel = run_simulate(config).signals["imu_linear_acceleration"][100:]
    assert accel.std(axis=0) == pytest.approx([0.02] * 3, rel=0.2)
    bias = np.array(config.station.sensors_config().accelerometer.bias)
    np.testing.assert_allclose(accel.mean(axis=0) - [0, 0, GRAVITY], bias, atol=0.01)


@pytest.mark.slow
def test_standing_holds_half_sitting_for_10_s():
    config = SimulateConfig(station=StationConfig(scenario="standing"), duration=10.0)
    signals = run_simulate(config).signals
    base = signals["state_true"][:, :7]  # [quaternion wxyz, xyz]
    drift = np.linalg.norm(base[-1, 4:7] - base[0, 4:7])
    tilt = 2 * np.arccos(np.clip(np.abs(base[:, 0]), 0, 1)).max()
    assert drift < 0.005  # m
    assert tilt < 0.01  # rad
    q_err = signals["q_cmd"] - signals["q_measured"]
    assert np.abs(q_err[1000:]).max() < 0.01  # rad
    v = signals["state_true"][-1, 37:]
    assert np.abs(v).max() < 0.05


@pytest.mark.slow
def test_hanging_settles_and_the_base_moves():
    config = SimulateConfig(station=StationConfig(scenario="hanging"), duration=8.0)
    signals = run_simulate(config).signals
    base_xyz = signals["state_true"][:, 4:7]
    base_v = signals["state_true"][:, 37:43]
    assert np.linalg.norm(base_v[-1]) < 0.01  # settled
    assert np.abs(base_xyz - base_xyz[0]).max() > 0.002  # the strings let it move
    assert np.isfinite(signals["q_measured"]).all()


def test_fixed_base_step_response_is_stable():
    """Every joint commanded 0.05 rad away: the explicit servo torques converge with
    no oscillation growing, on the light distal joints too."""
    config = StationConfig(scenario="fixed_base", sensors=SensorsConfig.noiseless())
    offset = np.full(hrp2.NUM_JOINTS, 0.05)
    station, context, q_cmd = _run(config, 1.5, offset)
    x = station.GetOutputPort("state_true").Eval(context)
    q, v = x[:30], x[30:]
    assert np.abs(v).max() < 0.01
    assert np.abs(q_cmd - q).max() < 0.02  # Kτ τ + dead zone under gravity


def test_standing_on_block_loads_the_right_foot_on_the_block():
    config = StationConfig(
        scenario="standing_on_block",
        block_height=0.05,
        sensors=SensorsConfig.noiseless(),
    )
    station, context, _ = _run(config, 1.0)
    plant = station.GetSubsystemByName("plant")
    fz_right = station.GetOutputPort("wrench_right_foot").Eval(context)[5]
    fz_left = station.GetOutputPort("wrench_left_foot").Eval(context)[5]
    assert fz_right > 150 and fz_left > 150
    poses = station.GetOutputPort("body_poses").Eval(context)
    foot = plant.GetBodyByName("RLEG_FOOT").index()
    sole_z = poses[int(foot)].translation()[2] - 0.02  # sensor 0.02 m above the sole
    assert sole_z == pytest.approx(0.05, abs=0.003)


def test_encoders_are_quantized():
    station, context, _ = _run(StationConfig(scenario="fixed_base"), 0.05)
    from hrp2_drake.robot.servo import load_servo_params

    res = load_servo_params().vectors(hrp2.JOINT_NAMES)["encoder_resolution"]
    q = station.GetOutputPort("q_measured").Eval(context)
    np.testing.assert_allclose(q / res, np.round(q / res), atol=1e-6)


def test_noise_repeats_with_the_seed():
    def accel(seed):
        cfg = SimulateConfig(
            station=StationConfig(scenario="fixed_base"), duration=0.05
        )
        cfg.station.sensors = dataclasses.replace(
            cfg.station.sensors_config(), seed=seed
        )
        return run_simulate(cfg).signals["imu_linear_acceleration"]

    a, b, c = accel(1), accel(1), accel(2)
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).max() > 1e-3


def test_config_errors_say_what_and_where(tmp_path):
    with pytest.raises(ValueError, match=r"sensors\.accelerometer\.stdd"):
        load_config(StationConfig, data="sensors: {accelerometer: {stdd: [1]}}")
    with pytest.raises(ValueError, match=r"foo"):
        load_config(StationConfig, data="foo: 1")
    with pytest.raises(ValueError, match="unknown scenario 'walking'"):
        load_config(StationConfig, data="scenario: walking")
    with pytest.raises(ValueError, match="initial_positions: 3 values"):
        load_config(StationConfig, data="initial_positions: [0, 0, 0]")
    path = tmp_path / "station.yaml"
    path.write_text("scenario: standing\nsensors: {seed: 4}\n")
    config = load_config(StationConfig, filename=path)
    assert config.scenario == "standing" and config.sensors_config().seed == 4
    bad_noise = StationConfig(sensors=SensorsConfig())
    bad_noise.sensors.accelerometer = NoiseConfig(std=[0.1, 0.2])
    with pytest.raises(
        ValueError, match=r"Config\.accelerometer\.std must hold 1 or 3"
    ):
        make_station(bad_noise)
    with pytest.raises(KeyError, match="no joint 'RLEG_FT'"):
        plant = MultibodyPlant(0.0)
        hrp2.add_hrp2(plant)
        plant.Finalize()
        ForceTorqueReadout(plant, [("RLEG_FT", "RLEG_FOOT", "RLEG_FOOT")])


def test_sensor_sampler_is_the_separate_sensors_bit_for_bit():
    """The station's SensorSampler gives, sample for sample and bit for bit, what a
    NoisySampler per sensor (same seeds), ForceTorqueReadout and SensorClock give
    (the station before they were fused), across a noise block (4096 samples) and
    through a "freeze" of one sensor's stamps."""
    config = StationConfig(scenario="hanging")
    robot, cfg = config.description(), config.sensors_config()
    plant = MultibodyPlant(0.001)
    robot.add_model(plant, weld_base=False)
    plant.Finalize()
    names, n = list(robot.joints), len(robot.joints)
    q0 = initial_joint_positions(config)
    resolution = load_servo_params().vectors(names)["encoder_resolution"]
    readouts = force_torque_readouts(plant, robot)
    faults = [SensorFault("imu_angular_velocity", "freeze", 0.010, 0.005)]
    fused = SensorSampler(
        plant,
        names,
        cfg,
        q0,
        resolution,
        imu=True,
        force_torque=[(s, *r) for s, r in zip(robot.sensor_names(), readouts)],
        faults=faults,
    )
    seed = 1000 * cfg.seed
    ft_noise = [
        cfg.force_torque_noise(s).vectors(6, "ft") for s in robot.sensor_names()
    ]
    separate = {
        "q_measured": NoisySampler(
            n, cfg.period, *cfg.encoder.vectors(n, "enc"), seed + 1, resolution, q0
        ),
        "imu_linear_acceleration": NoisySampler(
            3, cfg.period, *cfg.accelerometer.vectors(3, "acc"), seed + 2
        ),
        "imu_angular_velocity": NoisySampler(
            3, cfg.period, *cfg.gyroscope.vectors(3, "gyro"), seed + 3
        ),
        "wrenches": NoisySampler(
            24,
            cfg.period,
            np.concatenate([std for std, _ in ft_noise]),
            np.concatenate([bias for _, bias in ft_noise]),
            seed + 4,
        ),
    }
    readout = ForceTorqueReadout(plant, readouts)
    clock = SensorClock(list(sensor_sizes(robot)), faults, cfg.period)
    contexts = {
        system: system.CreateDefaultContext()
        for system in [fused, readout, clock, *separate.values()]
    }
    indexing = hrp2.hrp2_joint_indexing(plant)
    rng = np.random.default_rng(5)
    for k in (0, 1, 11, 13, 16, 4095, 4096, 4097, 9000):
        x = rng.normal(0.0, 0.3, plant.num_positions() + plant.num_velocities())
        acc, gyro = rng.normal(0.0, 5.0, 3), rng.normal(0.0, 0.5, 3)
        forces = [
            SpatialForce(rng.normal(0.0, 50.0, 6)) for _ in range(plant.num_joints())
        ]
        signals = {
            "q_measured": x[indexing.q],
            "imu_linear_acceleration": acc,
            "imu_angular_velocity": gyro,
        }
        for context in contexts.values():
            context.SetTime(k * cfg.period)
        readout.get_input_port().FixValue(contexts[readout], forces)
        signals["wrenches"] = readout.get_output_port().Eval(contexts[readout])
        ports = {"state": x, "linear_acceleration": acc, "angular_velocity": gyro}
        for name, value in ports.items():
            fused.GetInputPort(name).FixValue(contexts[fused], value)
        fused.GetInputPort("reaction_forces").FixValue(contexts[fused], forces)
        for name, sampler in separate.items():
            sampler.get_input_port().FixValue(contexts[sampler], signals[name])
        for system in (fused, clock, *separate.values()):
            context = contexts[system]
            context.SetDiscreteState(system.EvalUniquePeriodicDiscreteUpdate(context))

        def read(system, port):
            return system.GetOutputPort(port).Eval(contexts[system]).tobytes()

        for name in ("q_measured", "imu_linear_acceleration", "imu_angular_velocity"):
            assert read(fused, name) == read(separate[name], "measurement"), (k, name)
        wrenches = np.concatenate(
            [
                fused.GetOutputPort(f"wrench_{s}").Eval(contexts[fused])
                for s in robot.sensor_names()
            ]
        )
        assert wrenches.tobytes() == read(separate["wrenches"], "measurement"), k
        assert read(fused, "sensor_time") == read(clock, "sensor_time"), k


# --- The SensorSampler's kernel (hrp2_drake.kernels) ------------------------------


def _hanging_sampler(resolution_of=None):
    """The hanging HRP-2's SensorSampler (IMU, 4 F/T sensors, a freeze fault), its
    plant and robot; `resolution_of(resolution)`: the encoders' quanta to use."""
    config = StationConfig(scenario="hanging")
    robot, cfg = config.description(), config.sensors_config()
    plant = MultibodyPlant(0.001)
    robot.add_model(plant, weld_base=False)
    plant.Finalize()
    names = list(robot.joints)
    resolution = load_servo_params().vectors(names)["encoder_resolution"]
    if resolution_of is not None:
        resolution = resolution_of(resolution)
    readouts = force_torque_readouts(plant, robot)
    sampler = SensorSampler(
        plant,
        names,
        cfg,
        initial_joint_positions(config),
        resolution,
        imu=True,
        force_torque=[(s, *r) for s, r in zip(robot.sensor_names(), readouts)],
        faults=[SensorFault("imu_angular_velocity", "freeze", 0.010, 0.005)],
    )
    return sampler, plant, robot


def _sampler_updates(
    sampler, plant, ks=(0, 1, 11, 13, 4095, 4096, 4097)
) -> list[bytes]:
    """Every output of `sampler` after an update at each sample k of random inputs."""
    context = sampler.CreateDefaultContext()
    rng = np.random.default_rng(9)
    period = sampler._period
    out = []
    for k in ks:
        context.SetTime(k * period)
        x = rng.normal(0.0, 0.3, plant.num_positions() + plant.num_velocities())
        sampler.GetInputPort("state").FixValue(context, x)
        sampler.GetInputPort("linear_acceleration").FixValue(
            context, rng.normal(0, 5, 3)
        )
        sampler.GetInputPort("angular_velocity").FixValue(
            context, rng.normal(0, 0.5, 3)
        )
        sampler.GetInputPort("reaction_forces").FixValue(
            context,
            [SpatialForce(rng.normal(0.0, 50.0, 6)) for _ in range(plant.num_joints())],
        )
        context.SetDiscreteState(sampler.EvalUniquePeriodicDiscreteUpdate(context))
        for port in range(sampler.num_output_ports()):
            out.append(sampler.get_output_port(port).Eval(context).tobytes())
    return out


def test_sensor_sampler_kernel_compiled_equals_interpreted():
    """The SensorSampler's compiled kernel and its Python source give the same
    readings and stamps to the bit (elementwise code), across a noise block; both
    name the channel whose signal is not finite."""
    import contextlib

    from hrp2_drake import kernels

    sampler, plant, _ = _hanging_sampler()
    compiled = _sampler_updates(sampler, plant)
    # (With NUMBA_DISABLE_JIT both are the Python source.)
    with kernels.interpreted() if kernels.jit_enabled() else contextlib.nullcontext():
        interpreted_sampler, _, _ = _hanging_sampler()
        interpreted = _sampler_updates(interpreted_sampler, plant)
    assert compiled == interpreted
    for interpret in (False, True):
        with kernels.interpreted() if interpret else contextlib.nullcontext():
            context = sampler.CreateDefaultContext()
            context.SetTime(0.002)
            sampler.GetInputPort("state").FixValue(
                context, np.zeros(plant.num_positions() + plant.num_velocities())
            )
            sampler.GetInputPort("linear_acceleration").FixValue(
                context, [0, np.inf, 0]
            )
            sampler.GetInputPort("angular_velocity").FixValue(context, np.zeros(3))
            sampler.GetInputPort("reaction_forces").FixValue(
                context, [SpatialForce(np.zeros(6))] * plant.num_joints()
            )
            with pytest.raises(
                RuntimeError, match="imu_accelerometer: signal not finite"
            ):
                sampler.EvalUniquePeriodicDiscreteUpdate(context)


def test_sensor_sampler_warm_up_then_frozen_updates_and_a_new_signature_raises():
    """The constructor compiles (or loads) the kernel for an update's types; frozen,
    updates run, and a call with float32 arrays raises instead of compiling."""
    from hrp2_drake import kernels
    from hrp2_drake.robot import sensors

    if not kernels.jit_enabled():
        pytest.skip("NUMBA_DISABLE_JIT: nothing compiles")
    sampler, plant, _ = _hanging_sampler()
    assert sensors._sample_bus.signatures
    sensors._sample_bus.disable_compile()  # kernels.freeze(), for this module's kernel
    try:
        frozen = _sampler_updates(sampler, plant, ks=(0, 1, 2))
        groups = tuple(group.copy() for group in sampler._groups)
        arguments = [
            sampler._constants,
            sampler._table,
            np.zeros(80),
            np.zeros(3),
            np.zeros(3),
            sampler._signals.copy(),
            sampler._noise_block,
            0,
            groups,
            0.0,
            True,
        ]
        assert sensors._sample_bus(*arguments)  # the compiled signature
        arguments[2] = np.zeros(80, dtype=np.float32)
        with pytest.raises(TypeError, match="float32"):
            sensors._sample_bus(*arguments)
    finally:
        sensors._sample_bus.disable_compile(False)
    assert frozen == _sampler_updates(sampler, plant, ks=(0, 1, 2))


def test_an_encoder_of_resolution_zero_is_not_quantized():
    """A joint whose encoder resolution is 0 reads its angle unquantized (bias and
    noise added), in the SensorSampler as in a NoisySampler; the others quantized."""
    zero = [0, 7]

    def with_zeros(resolution):
        resolution = resolution.copy()
        resolution[zero] = 0.0
        return resolution

    sampler, plant, robot = _hanging_sampler(with_zeros)
    cfg = StationConfig(scenario="hanging").sensors_config()
    n = len(robot.joints)
    resolution = with_zeros(
        load_servo_params().vectors(list(robot.joints))["encoder_resolution"]
    )
    separate = NoisySampler(
        n, cfg.period, *cfg.encoder.vectors(n, "enc"), 1000 * cfg.seed + 1, resolution
    )
    indexing = hrp2.hrp2_joint_indexing(plant)
    x = np.random.default_rng(2).normal(
        0.0, 0.3, plant.num_positions() + plant.num_velocities()
    )
    readings = []
    for system, port, value in (
        (sampler, "state", x),
        (separate, "signal", x[indexing.q]),
    ):
        context = system.CreateDefaultContext()
        context.SetTime(0.003)
        system.GetInputPort(port).FixValue(context, value)
        if system is sampler:
            system.GetInputPort("linear_acceleration").FixValue(context, np.zeros(3))
            system.GetInputPort("angular_velocity").FixValue(context, np.zeros(3))
            system.GetInputPort("reaction_forces").FixValue(
                context, [SpatialForce(np.zeros(6))] * plant.num_joints()
            )
        context.SetDiscreteState(system.EvalUniquePeriodicDiscreteUpdate(context))
        readings.append(context.get_discrete_state(0).get_value().copy())
    q_measured, expected = readings
    assert q_measured.tobytes() == expected.tobytes()
    assert np.all(np.isfinite(q_measured))
    quantized = np.setdiff1d(np.arange(n), zero)
    np.testing.assert_allclose(
        q_measured[quantized] / resolution[quantized],
        np.round(q_measured[quantized] / resolution[quantized]),
        atol=1e-6,
    )
    assert np.all(q_measured[zero] != np.round(q_measured[zero] / 1e-5) * 1e-5)


MODELS = Path(__file__).resolve().parents[1] / "models"


def _iiwa_with_actuators_reordered(folder: Path, order: list[int]) -> Path:
    """models/iiwa14 with its URDF's transmissions (so the plant's actuators) declared
    in `order` (1-based joint numbers), its joints as they were."""
    source = MODELS / "iiwa14"
    urdf = (source / "iiwa14.urdf").read_text()
    blocks = re.findall(r"  <transmission name=.*?</transmission>\n", urdf, re.S)
    assert len(blocks) == 7
    first = urdf.index(blocks[0])
    rest = urdf[first:]
    for block in blocks:
        rest = rest.replace(block, "", 1)
    reordered = "".join(blocks[k - 1] for k in order)
    (folder / "iiwa14.urdf").write_text(urdf[:first] + reordered + rest)
    text = (source / "robot.yaml").read_text()
    text = text.replace(
        "servo_file: servo.yaml", f"servo_file: {source / 'servo.yaml'}"
    )
    (folder / "robot.yaml").write_text(text)
    return folder / "robot.yaml"


def test_joint_torque_true_is_in_joint_order_whatever_the_actuators_order(tmp_path):
    """On an iiwa whose URDF declares its actuators in another order than its joints,
    `joint_torque_true` is each joint's torque in the description's joint order: the
    same vector as the iiwa as shipped (actuators in joint order), not its actuators'
    order (which would put A2's 48 N·m of gravity on another joint)."""
    order = [7, 4, 1, 6, 2, 5, 3]
    robot = _iiwa_with_actuators_reordered(tmp_path, order)
    reordered = StationConfig(robot=str(robot), scenario="fixed_base")
    plant = reordered.description().make_plant()
    names = reordered.description().joints
    u = joint_indexing(plant, names).u
    np.testing.assert_array_equal(u[np.array(order) - 1], np.arange(7))
    torques = []
    for config in (StationConfig(robot="iiwa14", scenario="fixed_base"), reordered):
        station, context, _ = _run(config, 0.2)
        torques.append(station.GetOutputPort("joint_torque_true").Eval(context).copy())
    shipped, permuted = torques
    # the description's note: gravity torques A2 -48.4 N·m, A4 30.9 N·m at home
    assert shipped[1] < -40.0 and shipped[3] > 25.0
    np.testing.assert_allclose(permuted, shipped, rtol=0.0, atol=1e-9)
