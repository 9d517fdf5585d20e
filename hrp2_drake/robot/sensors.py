"""HRP-2's sensors: encoders, torso IMU, and four 6-axis F/T sensors, with noise.

Each sensor is a clean signal from the plant followed by a `NoisySampler`: sampled at
the control period (1 kHz), plus a constant bias and white Gaussian noise (a pure
function of the seed and the sample index, so runs repeat), then quantized where the
sensor is digital (encoders).

- Encoders: the joint positions, quantized at each joint's encoder resolution.
- IMU: Drake's `Accelerometer` (proper acceleration: the plant's gravity is passed,
  so a robot at rest reads +g upward) and `Gyroscope` on the torso's IMU frame.
- F/T: `ForceTorqueReadout` turns the reaction forces of the fixed joints that split
  the feet and hands at the sensors into what a sensor reads: the wrench that the body
  below the sensor (foot, hand) exerts on the body above it, torque then force, in the
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

from hrp2_drake.robot import model


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


def _default_ft() -> dict[str, NoiseConfig]:
    # HRP-2-like 6-axis sensors (JR3-class): ~0.5 N and ~0.02 N·m noise at 1 kHz,
    # offsets of a few N / a few 0.01 N·m that drift between power-ups.
    std = [0.02, 0.02, 0.02, 0.5, 0.5, 0.5]
    return {
        "right_foot": NoiseConfig(std, [0.04, -0.03, 0.02, 2.0, -1.5, 4.0]),
        "left_foot": NoiseConfig(std, [-0.02, 0.05, -0.01, -1.0, 2.5, -3.0]),
        "right_hand": NoiseConfig(std, [0.01, -0.02, 0.01, 0.8, -0.6, 1.2]),
        "left_hand": NoiseConfig(std, [-0.01, 0.01, 0.02, -0.5, 0.9, -1.0]),
    }


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
        force_torque: per sensor name, [τx, τy, τz, fx, fy, fz] in N·m and N.
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
    force_torque: dict[str, NoiseConfig] = field(default_factory=_default_ft)

    def validate(self) -> None:
        """Raises ValueError naming the bad field (yaml_load_typed does not call it):
        the period must be finite and > 0, the seed >= 0, and each noise config must
        hold 1 or as many values as its sensor has axes."""
        if not (math.isfinite(self.period) and self.period > 0):
            raise ValueError(
                "SensorsConfig.period must be a finite number > 0 (s), "
                f"got {self.period}"
            )
        if self.seed < 0:
            raise ValueError(f"SensorsConfig.seed must be >= 0, got {self.seed}")
        self.encoder.vectors(model.NUM_JOINTS, "SensorsConfig.encoder")
        self.accelerometer.vectors(3, "SensorsConfig.accelerometer")
        self.gyroscope.vectors(3, "SensorsConfig.gyroscope")
        for name, noise in self.force_torque.items():
            noise.vectors(6, f"SensorsConfig.force_torque.{name}")

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
            force_torque={name: zero for name in _default_ft()},
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
        if not np.all(np.isfinite(signal)):
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
    """What F/T sensors read, from the reaction forces of the joints at the sensors.

    .. code-block:: text

                          ┌────────────────────┐
        reaction_forces ─►│ ForceTorqueReadout ├──► wrenches
                          └────────────────────┘

    Ports:
        reaction_forces: the plant's reaction-forces output (one SpatialForce per
            joint: the force on the child body at the joint's child frame, expressed
            in that frame).
        wrenches: 6 values per sensor in `sensor_joints` order, [τ; f] (N·m, N) that
            the child (foot, hand) exerts on the parent, about the sensor origin, in
            the sensor frame (the joint's child frame).
    """

    def __init__(self, plant: MultibodyPlant, sensor_joints: Sequence[str]):
        super().__init__()
        self._joints = []
        for name in sensor_joints:
            if not plant.HasJointNamed(name):
                raise KeyError(f"ForceTorqueReadout: the plant has no joint '{name}'")
            self._joints.append(int(plant.GetJointByName(name).index()))
        self._reaction = self.DeclareAbstractInputPort(
            "reaction_forces", AbstractValue.Make([SpatialForce()])
        )
        self.DeclareVectorOutputPort("wrenches", 6 * len(self._joints), self._calc)

    def _calc(self, context: Context, output) -> None:
        forces = self._reaction.Eval(context)
        out = output.get_mutable_value()
        for k, j in enumerate(self._joints):
            # The sensor reads the opposite of the force on the child.
            out[6 * k : 6 * k + 6] = -forces[j].get_coeffs()
