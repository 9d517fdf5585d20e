"""A robot's simulated sensors: encoders, an IMU (optional) and 6-axis F/T sensors,
with noise (defaults: HRP-2-like magnitudes).

Each sensor is a clean signal from the plant, sampled at the control period (1 kHz),
plus a constant bias and white Gaussian noise (a pure function of the seed and the
sample index, so runs repeat), then quantized where the sensor is digital (encoders).

- Encoders: the joint positions, quantized at each joint's encoder resolution.
- IMU: Drake's `Accelerometer` (proper acceleration: the plant's gravity is passed,
  so a robot at rest reads +g upward) and `Gyroscope` on the IMU frame.
- F/T: the reaction forces of the fixed joints that split links at the sensors (feet,
  hands, a wrist) turned into what a sensor reads: the wrench that the body below the
  sensor exerts on the body above it, torque then force, in the sensor frame, about
  its origin. Standing still, an ankle sensor reads +z force.

The station samples them all with one `SensorSampler` (the robot's sensor bus: one
event per period for every sensor, which a simulation at 1 kHz pays for once).
`NoisySampler` (one signal), `ForceTorqueReadout` and `faults.SensorClock` are the
same laws as separate systems, for other diagrams; they give the same numbers
(tests/test_station.py checks it bit for bit).
"""

import math
from typing import Sequence

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.multibody.math import SpatialForce
from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.framework import Context, DiscreteValues

# The configs are the robot description's (plain data), imported here for this module's users.
from hrp2_drake.description.sensors import NoiseConfig, SensorsConfig  # noqa: F401
from hrp2_drake.multibody import joint_indexing
from hrp2_drake.robot.faults import SensorFault, freeze_windows, update_stamps
from hrp2_drake.simulation import WitnessFreeLeafSystem


class SampledSignal:
    """The sampling law of one sensor: measurement = quantize(signal + bias + std n_k).

    The noise n_k of sample k = round(t / period) is a pure function of (seed, k):
    drawn in blocks of `BLOCK` samples from a generator seeded with (seed, block) (the
    block in use is cached: a cache, not a state). Simulating the same context twice
    repeats the same noise.
    """

    BLOCK = 4096

    def __init__(
        self,
        size: int,
        std: np.ndarray,
        bias: np.ndarray,
        seed: int = 0,
        resolution: np.ndarray | None = None,
    ):
        self.size = size
        self.std = np.asarray(std, float)
        self.bias = np.asarray(bias, float)
        self.noisy = bool(np.any(self.std > 0))
        self.resolution = None if resolution is None else np.asarray(resolution, float)
        self._seed = int(seed)
        self._block_index = -1
        self._block = np.zeros((self.BLOCK, size))

    def noise(self, k: int) -> np.ndarray:
        """The unit white noise of sample k (a view into the cached block)."""
        block, row = divmod(k, self.BLOCK)
        return self.noise_block(block)[row]

    def noise_block(self, block: int) -> np.ndarray:
        """The unit white noise of samples BLOCK·block to BLOCK·(block + 1) − 1, one
        row each (cached)."""
        if block != self._block_index:
            rng = np.random.default_rng([self._seed, block])
            self._block = rng.standard_normal((self.BLOCK, self.size))
            self._block_index = block
        return self._block

    def sample(self, signal: np.ndarray, k: int) -> np.ndarray:
        """The measurement of sample k of a finite `signal` (a new array)."""
        y = signal + self.bias
        if self.noisy:
            y += self.std * self.noise(k)
        if self.resolution is not None:
            y = np.round(y / self.resolution) * self.resolution
        return y



def _raise_not_finite(name: str, signal: np.ndarray, t: float) -> None:
    """Raises the error of a sensor whose signal is not finite (a diverged simulation)."""
    raise RuntimeError(
        f"{name}: signal not finite at t={t:.4f} s "
        f"(entries {np.flatnonzero(~np.isfinite(signal)).tolist()}): "
        "the simulation diverged"
    )


class NoisySampler(WitnessFreeLeafSystem):
    """Samples a signal periodically, adding a bias and white Gaussian noise.

    .. code-block:: text

                  ┌──────────────┐
        signal ──►│ NoisySampler ├──► measurement
                  └──────────────┘

    measurement = quantize(signal + bias + std * n_k), updated every `period` (a
    discrete state: the reading holds between samples, like a sensor read by a 1 kHz
    controller), `SampledSignal`'s law and noise. Before the first sample the
    measurement is `initial` (zeros by default).

    Raises at the sample time if the signal is not finite (a diverged simulation).
    """

    def __init__(
        self,
        size: int,
        period: float,
        std: np.ndarray,
        bias: np.ndarray,
        seed: int = 0,
        resolution: np.ndarray | None = None,
        initial: np.ndarray | None = None,
    ):
        super().__init__()
        self._signal = self.DeclareVectorInputPort("signal", size)
        self._period = period
        self._law = SampledSignal(size, std, bias, seed, resolution)
        self._ones = np.ones(size)  # finite check: x·1 is finite iff every x_i is
        state = self.DeclareDiscreteState(
            np.zeros(size) if initial is None else np.asarray(initial, float)
        )
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._update)
        self.DeclareStateOutputPort("measurement", state)

    def noise(self, k: int) -> np.ndarray:
        """The unit white noise of sample k (a view into the cached block)."""
        return self._law.noise(k)

    def _update(self, context: Context, discrete_state: DiscreteValues) -> None:
        signal = self._signal.Eval(context)
        t = context.get_time()
        if not math.isfinite(signal.dot(self._ones)):
            _raise_not_finite(self.get_name(), signal, t)
        discrete_state.set_value(self._law.sample(signal, round(t / self._period)))


class ForceTorqueReadout(WitnessFreeLeafSystem):
    """What F/T sensors read, from the reaction forces of the fixed joints at the sensors.

    .. code-block:: text

                          ┌────────────────────┐
        reaction_forces ─►│ ForceTorqueReadout ├──► wrenches
                          └────────────────────┘

    Ports:
        reaction_forces: the plant's reaction-forces output (one SpatialForce per
            joint: the force on the child body at the joint's child frame, expressed
            in that frame).
        wrenches: 6 values per sensor in `sensors` order, [τ; f] (N·m, N) that the
            body below the sensor exerts on the body above it, about the sensor frame's
            origin, in the sensor frame.
    """

    def __init__(self, plant: MultibodyPlant, sensors: Sequence[tuple[str, str, str]]):
        """
        Args:
            plant: the finalized plant.
            sensors: (fixed joint, sensor frame, body below the sensor) per sensor;
                the frame is rigidly attached to the joint's bodies.
        """
        super().__init__()
        self._joints, self._maps = force_torque_maps(plant, sensors)
        self._reaction = self.DeclareAbstractInputPort(
            "reaction_forces", AbstractValue.Make([SpatialForce()])
        )
        self.DeclareVectorOutputPort("wrenches", 6 * len(self._joints), self._calc)

    def _calc(self, context: Context, output) -> None:
        forces = self._reaction.Eval(context)
        out = output.get_mutable_value()
        for k, j in enumerate(self._joints):
            out[6 * k : 6 * k + 6] = self._maps[k] @ forces[j].get_coeffs()


def force_torque_maps(
    plant: MultibodyPlant, sensors: Sequence[tuple[str, str, str]]
) -> tuple[list[int], np.ndarray]:
    """(joint indices, (k, 6, 6) maps) of F/T sensors (`ForceTorqueReadout`): sensor k
    reads maps[k] @ the reaction force of joint k, [τ; f] about Co in C.

    Args:
        plant: the finalized plant.
        sensors: (fixed joint, sensor frame, body below the sensor) per sensor; the
            frame is rigidly attached to the joint's bodies.
    """
    context = plant.CreateDefaultContext()
    joints, maps = [], []
    for joint_name, frame_name, body_name in sensors:
        if not plant.HasJointNamed(joint_name):
            raise KeyError(f"ForceTorqueReadout: the plant has no joint '{joint_name}'")
        joint = plant.GetJointByName(joint_name)
        below = plant.GetBodyByName(body_name)
        # The reaction is the force on the child: the sensor reads its opposite
        # when the child is the body below the sensor.
        sign = -1.0 if joint.child_body().index() == below.index() else 1.0
        X_SC = joint.frame_on_child().CalcPose(
            context, plant.GetFrameByName(frame_name)
        )
        R, p = X_SC.rotation().matrix(), X_SC.translation()
        # [τ; f] about Co in C -> about So in S: f_S = R f, τ_S = R τ + p × (R f).
        cross = np.array([[0, -p[2], p[1]], [p[2], 0, -p[0]], [-p[1], p[0], 0]])
        T = np.zeros((6, 6))
        T[:3, :3] = R
        T[:3, 3:] = cross @ R
        T[3:, 3:] = R
        joints.append(int(joint.index()))
        maps.append(sign * T)
    return joints, np.array(maps).reshape(-1, 6, 6)


def _sensor_laws(
    config: SensorsConfig,
    num_joints: int,
    encoder_resolution: np.ndarray | None,
    imu: bool,
    force_torque_names: Sequence[str],
) -> dict[str, SampledSignal]:
    """The `SampledSignal` law of each channel of a `SensorSampler`, by channel name
    (the former samplers' names, for errors), in the seeds' order: encoders,
    accelerometer and gyroscope (with an IMU), the F/T sensors side by side."""
    n = num_joints
    seeds = iter(range(1000 * config.seed + 1, 1000 * config.seed + 100))
    laws = {
        "encoders": SampledSignal(
            n,
            *config.encoder.vectors(n, "sensors.encoder"),
            next(seeds),
            encoder_resolution,
        )
    }
    if imu:
        for name, noise in (
            ("accelerometer", config.accelerometer),
            ("gyroscope", config.gyroscope),
        ):
            vectors = noise.vectors(3, f"sensors.{name}")
            laws[f"imu_{name}"] = SampledSignal(3, *vectors, next(seeds))
    if force_torque_names:
        stds, biases = zip(
            *(
                config.force_torque_noise(s).vectors(6, f"sensors.force_torque.{s}")
                for s in force_torque_names
            )
        )
        laws["force_torque"] = SampledSignal(
            6 * len(force_torque_names),
            np.concatenate(stds),
            np.concatenate(biases),
            next(seeds),
        )
    return laws


class SensorSampler(WitnessFreeLeafSystem):
    """Every sensor of a simulated robot sampled at once each period, as a robot's
    sensor bus delivers them: the encoders, the IMU (if any) and the F/T sensors, each
    with its `SampledSignal` law (bias, noise, quantization), and the time stamp of
    each sensor's latest sample.

    .. code-block:: text

                                ┌───────────────┐
        state ─────────────────►│               ├──► q_measured
        linear_acceleration ───►│               ├──► imu_linear_acceleration (IMU)
          (IMU)                 │ SensorSampler ├──► imu_angular_velocity    (IMU)
        angular_velocity (IMU) ►│               ├──► wrench_<sensor> (each)
        reaction_forces (F/T) ─►│               ├──► sensor_time
                                └───────────────┘

    Inputs: the plant's state [q; v] (the encoders read q of the joints), the clean
    IMU signals (Drake's Accelerometer and Gyroscope outputs), the plant's reaction
    forces (the F/T sensors, `force_torque_maps`).

    Outputs (discrete state, updated every `config.period`): what a NoisySampler per
    sensor, ForceTorqueReadout and SensorClock give, number for number: the same laws
    and seeds (1000 seed + 1, + 2, ... in the order encoders, accelerometer,
    gyroscope, F/T sensors), and the same error when a signal is not finite. Before
    the first sample the encoders read `initial_q`, the others zero.

    Why one system: at 1 kHz every Python event costs its dispatch whatever it
    computes; one event for the whole bus instead of six systems (four samplers, the
    F/T readout, the clock) saves about 15 us per simulated millisecond
    (scripts/bench_closed_loop.py).
    """

    def __init__(
        self,
        plant: MultibodyPlant,
        joint_names: Sequence[str],
        config: SensorsConfig,
        initial_q: np.ndarray,
        encoder_resolution: np.ndarray | None = None,
        imu: bool = True,
        force_torque: Sequence[tuple[str, str, str, str]] = (),
        faults: Sequence[SensorFault] = (),
        lead: float = 0.0,
    ):
        """
        Args:
            plant: the station's finalized plant (`state` is its state).
            joint_names: the encoders' joints, in the order of q_measured.
            config: noise, bias, period and seed.
            initial_q: what the encoders read before the first sample (rad).
            encoder_resolution: each joint's encoder quantum (rad); None: no
                quantization.
            imu: whether there is an IMU (its two inputs and outputs).
            force_torque: (sensor name, fixed joint, sensor frame, body below the
                sensor) of each F/T sensor (see ForceTorqueReadout).
            faults: the station's faults: a "freeze" stops its sensor's stamp.
            lead: sample this long (s, less than a period) before each multiple of
                the period: a bus reads the sensors `lead` before the controller's
                command reaches the servos (`StationConfig.sample_lead`).
        """
        super().__init__()
        names = [sensor[0] for sensor in force_torque]
        self._period = config.period
        if not 0 <= lead < config.period:
            raise ValueError(
                f"SensorSampler: lead {lead} s must be >= 0 and shorter than the period "
                f"({config.period} s)"
            )
        self._offset = (config.period - lead) % config.period
        laws = _sensor_laws(config, len(joint_names), encoder_resolution, imu, names)
        views = self._make_buffers(laws)
        self._declare_inputs(plant, joint_names, views, imu, force_torque)
        self._declare_outputs(views, initial_q, imu, names, faults)
        self.DeclarePeriodicDiscreteUpdateEvent(config.period, self._offset, self._update)

    def _make_buffers(
        self, laws: dict[str, SampledSignal]
    ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """One buffer of every clean signal and one of every measurement, channel
        after channel (the noisy ones last), with views per channel: one finite check,
        one bias addition and one noise addition for the whole bus. Returns the
        (signal, measurement) views of each channel."""
        order = sorted(laws, key=lambda name: laws[name].noisy)  # stable
        size = sum(law.size for law in laws.values())
        self._signals, self._measurements = np.zeros(size), np.zeros(size)
        self._bias = np.concatenate([laws[name].bias for name in order])
        self._ones = np.ones(size)  # finite check: x·1 is finite iff every x_i is
        self._channels = []  # (name, law, signal view, measurement view)
        start = 0
        for name in order:
            rows = slice(start, start + laws[name].size)
            self._channels.append(
                (name, laws[name], self._signals[rows], self._measurements[rows])
            )
            start += laws[name].size
        # The noisy channels in the seeds' order, which the stable sort kept.
        self._noisy_laws = [law for law in laws.values() if law.noisy]
        noisy_size = sum(law.size for law in self._noisy_laws)
        self._noisy_measurements = self._measurements[size - noisy_size :]
        self._noise_block_index = -1
        self._noise_block = np.zeros((SampledSignal.BLOCK, noisy_size))
        self._quantized = [
            (law, m) for _, law, _, m in self._channels if law.resolution is not None
        ]
        return {
            name: (signal, measurement)
            for name, _, signal, measurement in self._channels
        }

    def _declare_inputs(
        self,
        plant: MultibodyPlant,
        joint_names: Sequence[str],
        views: dict[str, tuple[np.ndarray, np.ndarray]],
        imu: bool,
        force_torque: Sequence[tuple[str, str, str, str]],
    ) -> None:
        """The input ports, and where each one's signal goes (its channel's view)."""
        self._state = self.DeclareVectorInputPort(
            "state", plant.num_positions() + plant.num_velocities()
        )
        self._q_rows = joint_indexing(plant, joint_names).q
        self._encoder_signal = views["encoders"][0]
        self._imu = []  # (input port, signal view)
        if imu:
            for port, channel in (
                ("linear_acceleration", "imu_accelerometer"),
                ("angular_velocity", "imu_gyroscope"),
            ):
                self._imu.append(
                    (self.DeclareVectorInputPort(port, 3), views[channel][0])
                )
        self._reaction = None
        if force_torque:
            self._reaction = self.DeclareAbstractInputPort(
                "reaction_forces", AbstractValue.Make([SpatialForce()])
            )
            self._joints, self._maps = force_torque_maps(
                plant, [sensor[1:] for sensor in force_torque]
            )
            # The F/T signals as k 6x1 columns: one matmul maps every sensor's
            # reaction force (numpy applies the same product to each, so the numbers
            # are ForceTorqueReadout's).
            self._force_torque_signal = views["force_torque"][0].reshape(-1, 6, 1)

    def _declare_outputs(
        self,
        views: dict[str, tuple[np.ndarray, np.ndarray]],
        initial_q: np.ndarray,
        imu: bool,
        names: Sequence[str],
        faults: Sequence[SensorFault],
    ) -> None:
        """A discrete state group and an output port per sensor port (its channel's
        measurement view), then the stamps."""
        self._outputs = []  # (group, measurement view)
        ports = [("q_measured", views["encoders"][1], np.asarray(initial_q, float))]
        if imu:
            ports += [
                ("imu_linear_acceleration", views["imu_accelerometer"][1], np.zeros(3)),
                ("imu_angular_velocity", views["imu_gyroscope"][1], np.zeros(3)),
            ]
        for k, sensor in enumerate(names):
            wrench = views["force_torque"][1][6 * k : 6 * k + 6]
            ports.append((f"wrench_{sensor}", wrench, np.zeros(6)))
        for port, measurement, initial in ports:
            group = self.DeclareDiscreteState(initial)
            self.DeclareStateOutputPort(port, group)
            self._outputs.append((int(group), measurement))
        # The stamps, in the same order (the station's sensor_sizes).
        self._freezes = freeze_windows([port for port, _, _ in ports], faults)
        stamps = self.DeclareDiscreteState(len(ports))
        self._stamps_group = int(stamps)
        self.DeclareStateOutputPort("sensor_time", stamps)

    def _update(self, context: Context, state: DiscreteValues) -> None:
        t = context.get_time()
        np.take(self._state.Eval(context), self._q_rows, out=self._encoder_signal)
        for port, signal in self._imu:
            signal[:] = port.Eval(context)
        if self._reaction is not None:
            forces = self._reaction.Eval(context)
            reactions = np.array([forces[j].get_coeffs() for j in self._joints])
            np.matmul(self._maps, reactions[:, :, None], out=self._force_torque_signal)
        if not math.isfinite(self._signals.dot(self._ones)):
            for name, _, signal, _ in self._channels:
                if not np.all(np.isfinite(signal)):
                    _raise_not_finite(name, signal, t)
        # SampledSignal.sample of every channel, operation by operation on the whole
        # bus (each entry sees the same operations, so the numbers are the same).
        k = round((t - self._offset) / self._period)
        measurements = self._measurements
        np.add(self._signals, self._bias, out=measurements)
        if self._noisy_laws:
            self._noisy_measurements += self._noise(k)
        for law, measurement in self._quantized:
            # (np.rint is np.round, without np.round's Python layer.)
            measurement[:] = np.rint(measurement / law.resolution) * law.resolution
        for group, measurement in self._outputs:
            state.set_value(group, measurement)
        update_stamps(state.get_mutable_value(self._stamps_group), t, self._freezes)

    def _noise(self, k: int) -> np.ndarray:
        """std · n_k of every noisy channel, side by side in the buffer's order: a row
        of a block of BLOCK samples, made once per block (the channels share k)."""
        block, row = divmod(k, SampledSignal.BLOCK)
        if block != self._noise_block_index:
            self._noise_block = np.concatenate(
                [law.std * law.noise_block(block) for law in self._noisy_laws], axis=1
            )
            self._noise_block_index = block
        return self._noise_block[row]
