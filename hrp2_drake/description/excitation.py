"""A robot's identification excitation (`RobotDescription.identification`), as plain
data: one increasing sinusoid per joint and pushes on one body (paper Sec. 3.4).
`hrp2_drake.identification.excitation` plans and runs the collection from it.
"""

import copy
from dataclasses import dataclass, field

import numpy as np


@dataclass
class SinusoidConfig:
    """One joint's increasing-amplitude sinusoid (paper 3.4.2).

    Args:
        joint: joint name.
        center_offset: offset of the sinusoid's centre from the nominal pose (rad),
            e.g. to keep a leg clear of the other one.
        amplitude_start: a0 (rad).
        amplitude_end: a0 + a T (rad), reached at the end.
        peak_velocity: the velocity amplitude reached at the end (rad/s); sets the
            frequency f = peak_velocity / (2π amplitude_end).
        duration: T (s), rounded by `end_time` to end at a peak of the sinusoid
            (zero velocity), so that the move away from it is gentle.
    """

    joint: str = ""
    center_offset: float = 0.0
    amplitude_start: float = 0.02
    amplitude_end: float = 0.3
    peak_velocity: float = 1.0
    duration: float = 8.0

    def frequency(self) -> float:
        return self.peak_velocity / (2 * np.pi * self.amplitude_end)

    def end_time(self) -> float:
        """The duration rounded to end at a peak: (k + 1/4) periods."""
        f = self.frequency()
        return (max(round(f * self.duration - 0.25), 0) + 0.25) / f


@dataclass
class PushConfig:
    """Pushes on one body in several joint configurations (paper 3.4.1).

    Args:
        body: the pushed body (e.g. the foot below the F/T sensor).
        point: where the push is applied, in the body frame (m).
        configurations: joint offsets from the nominal pose, one list per
            configuration, as {joint name: offset (rad)}.
        max_force: bound of each force component (N).
        max_torque: bound of each couple component (N·m).
        ramp_duration: time of one ramp between two wrenches (s).
        extra_ramps: ramps per configuration after the 12 single-axis ones (random
            combinations of one or two axes).
        seed: seed of the random wrenches.
    """

    body: str = ""
    point: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    configurations: list[dict[str, float]] = field(default_factory=lambda: [{}])
    max_force: float = 100.0
    max_torque: float = 30.0
    ramp_duration: float = 0.6
    extra_ramps: int = 8
    seed: int = 0


@dataclass
class CollectionConfig:
    """A whole identification data collection.

    Args:
        nominal_offsets: {joint name: offset (rad)} from the station's initial pose for
            the whole collection (e.g. the other leg spread out of the way).
        pushes: the high-torque part (none if `pushes.body` is empty).
        sinusoids: the high-velocity part, one joint at a time.
        transition: time to move smoothly between parts (s).
        settle: time to hold at the start (s).
    """

    nominal_offsets: dict[str, float] = field(default_factory=dict)
    pushes: PushConfig = field(default_factory=PushConfig)
    sinusoids: list[SinusoidConfig] = field(default_factory=list)
    transition: float = 1.0
    settle: float = 1.0

    def validate(self) -> None:
        for s in self.sinusoids:
            if not (0 < s.amplitude_start <= s.amplitude_end and s.duration > 0):
                raise ValueError(
                    f"CollectionConfig.sinusoids[{s.joint}]: bad amplitudes/duration"
                )
        if self.pushes.extra_ramps < 0:
            raise ValueError("CollectionConfig.pushes.extra_ramps must be >= 0")

    def is_empty(self) -> bool:
        return not (self.sinusoids or self.pushes.body)

    def scaled(
        self, duration_scale: float, seed: int | None = None
    ) -> "CollectionConfig":
        """A copy shortened (or lengthened) by `duration_scale`: the pushes' random
        ramps and the sinusoids' durations (each at least 2 s) scale, the 12
        single-axis pushes stay; `seed` replaces the pushes' seed if given."""
        out = copy.deepcopy(self)
        out.pushes.extra_ramps = round(self.pushes.extra_ramps * duration_scale)
        if seed is not None:
            out.pushes.seed = seed
        for s in out.sinusoids:
            s.duration = max(2.0, s.duration * duration_scale)
        return out
