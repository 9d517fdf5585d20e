"""A robot's simulated sensors: encoders, an IMU (optional) and 6-axis F/T sensors,
with noise (defaults: HRP-2-like magnitudes).

Each sensor is a clean signal from the plant followed by a `NoisySampler`: sampled at
the control period (1 kHz), plus a constant bias and white Gaussian noise (a pure
function of the seed and the sample index, so runs repeat), then quantized where the
sensor is digital (encoders).

- Encoders: the joint positions, quantized at each joint's encoder resolution.
- IMU: Drake's `Accelerometer` (proper acceleration: the plant's gravity is passed,
  so a robot at rest reads +g upward) and `Gyroscope` on the IMU frame.
- F/T: `ForceTorqueReadout` turns the reaction forces of the fixed joints that split
  links at the sensors (feet, hands, a wrist) into what a sensor reads: the wrench that
  the body below the sensor exerts on the body above it, torque then force, in the
  sensor frame, about its origin. Standing still, an ankle sensor reads +z force.
"""

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.multibody.math import SpatialForce
from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.framework import Context, DiscreteValues, LeafSystem


@dataclass
class NoiseConfig:
    """Noise of one sensor.

    Args:
        std: white-noise standard deviation per axis (one value: every axis), in the
            sensor's unit (rad, m/s², rad/s, N·m and N).
        bias: constant offset per axis (one value: every axis), same unit.
    """

    std: list[float] = field(default_factory=lambda: [0.0])
    bias: list[float] = field(default_factory=lambda: [0.0])

    def vectors(self, size: int, where: str) -> tuple[np.ndarray, np.ndarray]:
        """(std, bias) broadcast to `size`; a wrong length is a ValueError."""
        out = []
        for name in ("std", "bias"):
            value = np.asarray(getattr(self, name), dtype=float)
            if value.size == 1:
                value = np.full(size, value.item())
            if value.shape != (size,) or not np.all(np.isfinite(value)):
                raise ValueError(
                    f"{where}.{name} must hold 1 or {size} finite values, "
                    f"got {getattr(self, name)}"
                )
            out.append(value)
        if np.any(out[0] < 0):
            raise ValueError(f"{where}.std must be >= 0, got {self.std}")
        return out[0], out[1]


def _default_ft() -> NoiseConfig:
    # 6-axis sensors of the JR3/ATI class: ~0.5 N and ~0.02 N·m noise at 1 kHz. Their
    # offsets (a few N, a few 0.01 N·m, drifting between power-ups) are per sensor:
    # a robot description gives them in `force_torque`.
    return NoiseConfig([0.02, 0.02, 0.02, 0.5, 0.5, 0.5], [0.0])


@dataclass
class SensorsConfig:
    """Sensor noise, bias and sampling (defaults: HRP-2-like magnitudes).

    Args:
        period: sampling period of every sensor (s).
        seed: seed of the noise generators (same seed, same noise).
        encoder_quantization: quantize encoder readings at the joint resolution of
            a 4000-count motor encoder through the gear (models/hrp2/README.md).
        encoder: additional encoder noise (rad); none by default.
        accelerometer: m/s². MEMS-class: 0.02 m/s² noise, ~0.05 m/s² bias.
        gyroscope: rad/s. 0.005 rad/s noise, ~0.002 rad/s bias.
        force_torque: per sensor name, [τx, τy, τz, fx, fy, fz] in N·m and N;
            a sensor not listed has `force_torque_default`.
        force_torque_default: the F/T sensors not in `force_torque`.
    """

    period: float = 0.001
    seed: int = 0
    encoder_quantization: bool = True
    encoder: NoiseConfig = field(default_factory=NoiseConfig)
    accelerometer: NoiseConfig = field(
        default_factory=lambda: NoiseConfig([0.02], [0.05, -0.03, 0.04])
    )
    gyroscope: NoiseConfig = field(
        default_factory=lambda: NoiseConfig([0.005], [0.002, -0.001, 0.0015])
    )
    force_torque: dict[str, NoiseConfig] = field(default_factory=dict)
    force_torque_default: NoiseConfig = field(default_factory=_default_ft)

    def force_torque_noise(self, name: str) -> NoiseConfig:
        """The noise of F/T sensor `name`."""
        return self.force_torque.get(name, self.force_torque_default)

    def validate(
        self, num_joints: int | None = None, sensor_names: Sequence[str] | None = None
    ) -> None:
        """Raises ValueError naming the bad field (yaml_load_typed does not call it):
        the period must be finite and > 0, the seed >= 0, and each noise config must
        hold 1 or as many values as its sensor has axes (the encoders' only when the
        number of joints is given); `force_torque` may only name the given sensors."""
        if not (math.isfinite(self.period) and self.period > 0):
            raise ValueError(
                "SensorsConfig.period must be a finite number > 0 (s), "
                f"got {self.period}"
            )
        if self.seed < 0:
            raise ValueError(f"SensorsConfig.seed must be >= 0, got {self.seed}")
        if num_joints is not None:
            self.encoder.vectors(num_joints, "SensorsConfig.encoder")
        self.accelerometer.vectors(3, "SensorsConfig.accelerometer")
        self.gyroscope.vectors(3, "SensorsConfig.gyroscope")
        self.force_torque_default.vectors(6, "SensorsConfig.force_torque_default")
        for name, noise in self.force_torque.items():
            noise.vectors(6, f"SensorsConfig.force_torque.{name}")
        if sensor_names is not None:
            unknown = sorted(set(self.force_torque) - set(sensor_names))
            if unknown:
                raise ValueError(
                    f"SensorsConfig.force_torque: unknown sensors {unknown}, the robot has "
                    f"{sorted(sensor_names)}"
                )

    @staticmethod
    def noiseless(period: float = 0.001) -> "SensorsConfig":
        """Perfect sensors (no noise, no bias, no quantization), for tests."""
        zero = NoiseConfig([0.0], [0.0])
        return SensorsConfig(
            period=period,
            encoder_quantization=False,
            encoder=zero,
            accelerometer=zero,
            gyroscope=zero,
            force_torque_default=zero,
        )


class NoisySampler(LeafSystem):
    """Samples a signal periodically, adding a bias and white Gaussian noise.

    .. code-block:: text

                  ┌──────────────┐
        signal ──►│ NoisySampler ├──► measurement
                  └──────────────┘

    measurement = quantize(signal + bias + std * n_k), updated every `period` (a
    discrete state: the reading holds between samples, like a sensor read by a 1 kHz
    controller). Before the first sample the measurement is `initial` (zeros by
    default).

    The noise n_k of sample k = round(t / period) is a pure function of (seed, k):
    drawn in blocks of `_BLOCK` samples from a generator seeded with (seed, block).
    Simulating the same context twice repeats the same noise, and no generator state
    lives outside the context.

    Raises at the sample time if the signal is not finite (a diverged simulation).
    """

    _BLOCK = 4096

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
        self._size = size
        self._period = period
        self._std = np.asarray(std, float)
        self._bias = np.asarray(bias, float)
        self._seed = int(seed)
        self._noisy = bool(np.any(self._std > 0))
        self._block_index = -1
        self._block = np.zeros((self._BLOCK, size))
        self._resolution = None if resolution is None else np.asarray(resolution, float)
        self._ones = np.ones(size)  # finite check: x·1 is finite iff every x_i is
        state = self.DeclareDiscreteState(
            np.zeros(size) if initial is None else np.asarray(initial, float)
        )
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._update)
        self.DeclareStateOutputPort("measurement", state)

    def noise(self, k: int) -> np.ndarray:
        """The unit white noise of sample k (a view into the cached block)."""
        block, row = divmod(k, self._BLOCK)
        if block != self._block_index:
            rng = np.random.default_rng([self._seed, block])
            self._block = rng.standard_normal((self._BLOCK, self._size))
            self._block_index = block
        return self._block[row]

    def _update(self, context: Context, discrete_state: DiscreteValues) -> None:
        signal = self._signal.Eval(context)
        if not math.isfinite(signal.dot(self._ones)):
            raise RuntimeError(
                f"{self.get_name()}: signal not finite at t={context.get_time():.4f} s "
                f"(entries {np.flatnonzero(~np.isfinite(signal)).tolist()}): "
                "the simulation diverged"
            )
        y = signal + self._bias
        if self._noisy:
            y += self._std * self.noise(round(context.get_time() / self._period))
        if self._resolution is not None:
            y = np.round(y / self._resolution) * self._resolution
        discrete_state.set_value(y)


class ForceTorqueReadout(LeafSystem):
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
        context = plant.CreateDefaultContext()
        self._joints, maps = [], []
        for joint_name, frame_name, body_name in sensors:
            if not plant.HasJointNamed(joint_name):
                raise KeyError(f"ForceTorqueReadout: the plant has no joint '{joint_name}'")
            joint = plant.GetJointByName(joint_name)
            below = plant.GetBodyByName(body_name)
            # The reaction is the force on the child: the sensor reads its opposite
            # when the child is the body below the sensor.
            sign = -1.0 if joint.child_body().index() == below.index() else 1.0
            X_SC = joint.frame_on_child().CalcPose(context, plant.GetFrameByName(frame_name))
            R, p = X_SC.rotation().matrix(), X_SC.translation()
            # [τ; f] about Co in C -> about So in S: f_S = R f, τ_S = R τ + p × (R f).
            cross = np.array([[0, -p[2], p[1]], [p[2], 0, -p[0]], [-p[1], p[0], 0]])
            T = np.zeros((6, 6))
            T[:3, :3] = R
            T[:3, 3:] = cross @ R
            T[3:, 3:] = R
            self._joints.append(int(joint.index()))
            maps.append(sign * T)
        self._maps = np.array(maps).reshape(-1, 6, 6)
        self._reaction = self.DeclareAbstractInputPort(
            "reaction_forces", AbstractValue.Make([SpatialForce()])
        )
        self.DeclareVectorOutputPort("wrenches", 6 * len(self._joints), self._calc)

    def _calc(self, context: Context, output) -> None:
        forces = self._reaction.Eval(context)
        out = output.get_mutable_value()
        for k, j in enumerate(self._joints):
            out[6 * k : 6 * k + 6] = self._maps[k] @ forces[j].get_coeffs()
