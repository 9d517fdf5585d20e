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
from collections.abc import Sequence

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.multibody.math import SpatialForce
from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.framework import Context, DiscreteValues

from hrp2_drake.description.sensors import SensorsConfig
from hrp2_drake.kernels import kernel
from hrp2_drake.multibody import joint_indexing
from hrp2_drake.robot.faults import SensorFault, freeze_windows, update_stamps
from hrp2_drake.simulation import WitnessFreeLeafSystem
from hrp2_drake.step import sampling_offset


class SampledSignal:
    """The sampling law of one sensor: measurement = quantize(signal + bias + std n_k)
    (quantize: to the nearest multiple of the resolution, half to even; none where the
    resolution is 0).

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
        if self.resolution is not None:
            self._quantized = self.resolution > 0
            self._divisor = np.where(self._quantized, self.resolution, 1.0)
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
            y = np.where(
                self._quantized, np.round(y / self._divisor) * self.resolution, y
            )
        return y


def _raise_not_finite(name: str, signal: np.ndarray, t: float) -> None:
    """Raises the error of a sensor whose signal is not finite (a diverged
    simulation)."""
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
    """What F/T sensors read, from the reaction forces of the fixed joints at the
    sensors.

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


# The bus's constants (`SensorSampler._constants`): a row each over the buffer.
_BIAS, _QUANTUM = 0, 1  # the bias; the quantum (0: none)
# Its index table (`SensorSampler._table`, int64), a header: where the encoders, the
# accelerometer and the gyroscope (-1: no IMU) and the noisy channels start in the
# buffer, the stamps' discrete state group, the number of encoders; then the plant-state
# row of each encoder's joint; then, for each entry of the buffer, its discrete state
# group and its row there.
_ENCODERS, _ACCELEROMETER, _GYROSCOPE, _NOISY, _STAMPS, _NUM_ENCODERS = range(6)
_HEADER = 6


@kernel
def _sample_bus(
    c,
    table,
    x,
    acceleration,
    angular_velocity,
    signals,
    noise,
    row,
    groups,
    t,
    stamp_all,
):
    """`SensorSampler._update`'s arithmetic: the encoders' (from the plant's state x)
    and the IMU's signals into the signal buffer (whose F/T part is filled), then, if
    every signal is finite, each channel's `SampledSignal` law on the whole buffer,
    measurement = quantize(signal + bias [+ std n_k, the noisy channels, from row
    `row` of `noise`, the block of std · n]), written into its discrete state group
    (`groups`: a view on each group of the sampler's discrete state, in group order),
    and, with `stamp_all`, every stamp set to t. Elementwise: numpy's numbers bit for
    bit. Returns False, writing no group, if a signal is not finite."""
    num_encoders = table[_NUM_ENCODERS]
    encoders = table[_ENCODERS]
    for i in range(num_encoders):
        signals[encoders + i] = x[table[_HEADER + i]]
    accelerometer = table[_ACCELEROMETER]
    if accelerometer >= 0:
        gyroscope = table[_GYROSCOPE]
        for i in range(3):
            signals[accelerometer + i] = acceleration[i]
            signals[gyroscope + i] = angular_velocity[i]
    size = signals.shape[0]
    for i in range(size):
        if not math.isfinite(signals[i]):
            return False
    noisy = table[_NOISY]
    group_of = _HEADER + num_encoders
    row_of = group_of + size
    for i in range(size):
        value = signals[i] + c[_BIAS, i]
        if i >= noisy:
            value += noise[row, i - noisy]
        quantum = c[_QUANTUM, i]
        if quantum > 0.0:
            value = np.rint(value / quantum) * quantum
        groups[table[group_of + i]][table[row_of + i]] = value
    if stamp_all:
        stamps = groups[table[_STAMPS]]
        for i in range(stamps.shape[0]):
            stamps[i] = t
    return True


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
    (scripts/bench_closed_loop.py). Its arithmetic is one numba kernel
    (`_sample_bus`), but for the F/T sensors' matrix products, which stay numpy's
    (BLAS: ForceTorqueReadout's numbers); the kernel writes every reading into a
    discrete state of the sampler's own, which one call copies into the update's
    (one pybind11 crossing, not one per output).
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
        self._offset = sampling_offset(config.period, lead, "SensorSampler")
        self._lead = lead
        laws = _sensor_laws(config, len(joint_names), encoder_resolution, imu, names)
        starts = self._make_buffers(laws)
        self._declare_inputs(plant, joint_names, starts, imu, force_torque)
        self._declare_outputs(starts, initial_q, imu, names, faults)
        self.DeclarePeriodicDiscreteUpdateEvent(
            config.period, self._offset, self._update
        )
        self.warm_up()

    def period(self) -> float:
        """The sampling period (s)."""
        return self._period

    def lead(self) -> float:
        """How long (s) before each multiple of the period the sensors sample."""
        return self._lead

    def _make_buffers(self, laws: dict[str, SampledSignal]) -> dict[str, int]:
        """One buffer of every clean signal, channel after channel (the noisy ones
        last): one finite check, one bias addition and one noise addition for the
        whole bus. Returns where each channel starts in it."""
        order = sorted(laws, key=lambda name: laws[name].noisy)  # stable
        size = sum(law.size for law in laws.values())
        self._signals = np.zeros(size)
        self._constants = np.zeros((_QUANTUM + 1, size))
        self._constants[_BIAS] = np.concatenate([laws[name].bias for name in order])
        self._constants[_QUANTUM] = np.concatenate(
            [
                np.zeros(laws[name].size)
                if laws[name].resolution is None
                else np.broadcast_to(laws[name].resolution, (laws[name].size,))
                for name in order
            ]
        )
        self._channels = []  # (name, signal view)
        starts = {}
        start = 0
        for name in order:
            starts[name] = start
            self._channels.append(
                (name, self._signals[start : start + laws[name].size])
            )
            start += laws[name].size
        # The noisy channels in the seeds' order, which the stable sort kept.
        self._noisy_laws = [law for law in laws.values() if law.noisy]
        noisy_size = sum(law.size for law in self._noisy_laws)
        self._noisy_start = size - noisy_size
        self._noise_block_index = -1
        self._noise_block = np.zeros((SampledSignal.BLOCK, noisy_size))
        return starts

    def _declare_inputs(
        self,
        plant: MultibodyPlant,
        joint_names: Sequence[str],
        starts: dict[str, int],
        imu: bool,
        force_torque: Sequence[tuple[str, str, str, str]],
    ) -> None:
        """The input ports (each one's signal goes to its channel in the buffer)."""
        self._state = self.DeclareVectorInputPort(
            "state", plant.num_positions() + plant.num_velocities()
        )
        self._q_rows = joint_indexing(plant, joint_names).q
        self._imu = []  # the two input ports
        if imu:
            for port in ("linear_acceleration", "angular_velocity"):
                self._imu.append(self.DeclareVectorInputPort(port, 3))
        self._no_imu = np.zeros(0)
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
            start = starts["force_torque"]
            self._force_torque_signal = self._signals[
                start : start + 6 * len(force_torque)
            ].reshape(-1, 6, 1)

    def _declare_outputs(
        self,
        starts: dict[str, int],
        initial_q: np.ndarray,
        imu: bool,
        names: Sequence[str],
        faults: Sequence[SensorFault],
    ) -> None:
        """A discrete state group and an output port per sensor port (its channel's
        entries of the buffer), then the stamps; the kernel's table, and the sampler's
        own discrete state that the kernel writes."""
        initial_q = np.asarray(initial_q, float)
        ports = [("q_measured", starts["encoders"], initial_q)]
        if imu:
            ports += [
                ("imu_linear_acceleration", starts["imu_accelerometer"], np.zeros(3)),
                ("imu_angular_velocity", starts["imu_gyroscope"], np.zeros(3)),
            ]
        for k, sensor in enumerate(names):
            ports.append(
                (f"wrench_{sensor}", starts["force_torque"] + 6 * k, np.zeros(6))
            )
        size = self._signals.size
        group_of, row_of = (
            np.zeros(size, dtype=np.int64),
            np.zeros(size, dtype=np.int64),
        )
        for port, start, initial in ports:
            group = self.DeclareDiscreteState(initial)
            self.DeclareStateOutputPort(port, group)
            group_of[start : start + initial.size] = int(group)
            row_of[start : start + initial.size] = np.arange(initial.size)
        # The stamps, in the same order (the station's sensor_sizes).
        self._freezes = freeze_windows([port for port, _, _ in ports], faults)
        stamps = self.DeclareDiscreteState(len(ports))
        self._stamps_group = int(stamps)
        self.DeclareStateOutputPort("sensor_time", stamps)
        header = np.zeros(_HEADER, dtype=np.int64)
        header[_ENCODERS] = starts["encoders"]
        header[_ACCELEROMETER] = starts.get("imu_accelerometer", -1)
        header[_GYROSCOPE] = starts.get("imu_gyroscope", -1)
        header[_NOISY] = self._noisy_start
        header[_STAMPS] = self._stamps_group
        header[_NUM_ENCODERS] = len(self._q_rows)
        self._table = np.concatenate([header, self._q_rows, group_of, row_of])
        # What an update computes, written by the kernel into the groups of a discrete
        # state of our own (views on each, in group order), then copied into the
        # update's by one call (DiscreteValues.SetFrom). Every group is written at
        # every update (the stamps a freeze holds: from the update's own), so nothing
        # carries over from one context to another.
        self._scratch = self.AllocateDiscreteVariables()
        self._groups = tuple(
            self._scratch.get_mutable_value(group)
            for group in range(self._scratch.num_groups())
        )

    def warm_up(self) -> None:
        """Compiles (or loads from numba's cache) `_sample_bus` for an update's types
        (the inputs' values and the discrete state groups: 1-D C-contiguous float64;
        the buffers; the noise block, 2-D), on copies, so that
        `hrp2_drake.kernels.freeze()` can follow. The constructor calls it (see
        `EmulatedPositionServo.warm_up`)."""
        x = np.zeros(int(self._q_rows.max(initial=-1)) + 1)
        imu = np.zeros(3) if self._imu else self._no_imu
        groups = tuple(group.copy() for group in self._groups)
        _sample_bus(
            self._constants,
            self._table,
            x,
            imu,
            imu,
            self._signals.copy(),
            self._noise_block,
            0,
            groups,
            0.0,
            True,
        )

    def _update(self, context: Context, state: DiscreteValues) -> None:
        t = context.get_time()
        x = self._state.Eval(context)
        acceleration = angular_velocity = self._no_imu
        if self._imu:
            acceleration = self._imu[0].Eval(context)
            angular_velocity = self._imu[1].Eval(context)
        if self._reaction is not None:
            forces = self._reaction.Eval(context)
            reactions = np.array([forces[j].get_coeffs() for j in self._joints])
            np.matmul(self._maps, reactions[:, :, None], out=self._force_torque_signal)
        # SampledSignal.sample of every channel, operation by operation on the whole
        # bus (each entry sees the same operations, so the numbers are the same).
        row = self._noise_row(round((t - self._offset) / self._period))
        if not _sample_bus(
            self._constants,
            self._table,
            x,
            acceleration,
            angular_velocity,
            self._signals,
            self._noise_block,
            row,
            self._groups,
            t,
            not self._freezes,
        ):
            for name, signal in self._channels:
                if not np.all(np.isfinite(signal)):
                    _raise_not_finite(name, signal, t)
        if self._freezes:
            stamps = self._groups[self._stamps_group]
            stamps[:] = state.get_value(self._stamps_group)
            update_stamps(stamps, t, self._freezes)
        state.SetFrom(self._scratch)

    def _noise_row(self, k: int) -> int:
        """The row of sample k in the noise block (std · n of every noisy channel,
        side by side in the buffer's order, BLOCK samples: made once per block, the
        channels share k), the block made if it is a new one."""
        block, row = divmod(k, SampledSignal.BLOCK)
        if self._noisy_laws and block != self._noise_block_index:
            self._noise_block = np.concatenate(
                [law.std * law.noise_block(block) for law in self._noisy_laws], axis=1
            )
            self._noise_block_index = block
        return row
