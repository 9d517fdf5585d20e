"""The simulated sensors' noise, bias and sampling, as a robot description holds them
(`RobotDescription.sensors`): plain data. `hrp2_drake.robot.sensors` turns them into
the systems that sample a robot's sensors.
"""

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np


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
                    f"SensorsConfig.force_torque: unknown sensors {unknown}, the robot "
                    f"has {sorted(sensor_names)}"
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


#: The quantities a sensor range is given for, and what measures them.
RANGE_QUANTITIES: dict[str, str] = {
    "force": "F/T sensors' force (N)",
    "torque": "F/T sensors' torque (N·m)",
    "acceleration": "accelerometer (m/s²)",
    "angular_velocity": "gyroscope (rad/s)",
}


@dataclass
class SensorRanges:
    """The rated ranges of the robot's sensors (`RobotDescription.sensor_ranges`):
    the magnitude a reading of one axis cannot exceed when the sensor works. A
    supervisor (`control.safety`) takes an entry beyond it for `range_samples` samples
    in a row as a fault. They belong to the robot's sensors, so no generic default:
    a range too low makes false faults, one too high checks nothing; a supervisor
    monitoring a sensor whose range is not given refuses to start (one line naming
    this field). 0: not given.

    Args:
        force: every F/T sensor's force range, per axis (N).
        torque: every F/T sensor's torque range, per axis (N·m).
        acceleration: the accelerometer's range, per axis (m/s²).
        angular_velocity: the gyroscope's range, per axis (rad/s).
    """

    force: float = 0.0
    torque: float = 0.0
    acceleration: float = 0.0
    angular_velocity: float = 0.0

    def validate(self) -> None:
        """Raises ValueError naming the bad field (`sensor_ranges.<name>`)."""
        for name in RANGE_QUANTITIES:
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(
                    f"sensor_ranges.{name}: must be finite and >= 0 (0: not given), "
                    f"got {value}"
                )
