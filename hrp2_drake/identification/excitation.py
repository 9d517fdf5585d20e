"""Data collection for motor identification (paper Sec. 3.4), as diagrams on a station.

Two kinds of excitation, run on a robot held in the air (the "hanging" scenario):

- High-velocity (3.4.2): the position servo tracks an increasing-amplitude sinusoid
  q_d(t) = q0 + (a0 + a t) sin(2π f t) on one joint at a time.
- High-torque, near-zero velocity (3.4.1): the robot holds a set of leg configurations
  while "a person" pushes on the foot: piecewise-linear ramps of an external wrench
  (an `ExternallyAppliedSpatialForce` on the foot body): each of the 6 axes once with
  each sign, in random order and magnitude, then random combinations, so that every
  joint of the leg sees large torques of both signs.

The result is an identification log: what a real robot would record (see
`IDENTIFICATION_LOG_SIGNALS` and `save_log`), plus, in simulation only, ground truth
for evaluation. Nothing here reads the servo's parameters.

A station is any Diagram with the ports of DESIGN.md: input `q_cmd` and
`applied_spatial_force`, outputs `q_measured`, `imu_linear_acceleration`,
`imu_angular_velocity`, `wrench_<sensor>`; `joint_torque_true` is logged if present.
"""

import copy
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.multibody.math import SpatialForce
from pydrake.multibody.plant import ExternallyAppliedSpatialForce
from pydrake.multibody.tree import BodyIndex
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import Context, Diagram, DiagramBuilder, LeafSystem
from pydrake.systems.primitives import TrajectorySource
from pydrake.trajectories import PiecewisePolynomial

from hrp2_drake.simulation import add_loggers, logs_to_arrays, run_with_progress

# Phases of an identification log, per sample.
PHASE_TRANSITION, PHASE_HIGH_TORQUE, PHASE_HIGH_VELOCITY = 0, 1, 2

#: Signals every identification log holds (besides "t", "phase", "excited_joint"):
#: what a real robot records, rad. A robot with an IMU adds its
#: `IMU_LOG_SIGNALS` (m/s², rad/s), and every F/T sensor s its "wrench_<s>" ([N·m; N]).
IDENTIFICATION_LOG_SIGNALS = ("q_cmd", "q_measured")
IMU_LOG_SIGNALS = ("imu_linear_acceleration", "imu_angular_velocity")


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
                raise ValueError(f"CollectionConfig.sinusoids[{s.joint}]: bad amplitudes/duration")
        if self.pushes.extra_ramps < 0:
            raise ValueError("CollectionConfig.pushes.extra_ramps must be >= 0")

    def is_empty(self) -> bool:
        return not (self.sinusoids or self.pushes.body)

    def scaled(self, duration_scale: float, seed: int | None = None) -> "CollectionConfig":
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


@dataclass
class ExcitationPlan:
    """What the collection commands: joint references, pushes, and per-sample labels."""

    q_cmd: PiecewisePolynomial  # (n,) joint reference for the servo
    wrench: PiecewisePolynomial  # (6,) [torque; force] on the pushed body, world frame
    phases: list[tuple[float, float, int, int]]  # (t_start, t_end, phase, joint index)

    @property
    def duration(self) -> float:
        return self.q_cmd.end_time()


def increasing_sinusoid(t: np.ndarray, q0: float, s: SinusoidConfig) -> np.ndarray:
    """q_d(t) = q0 + (a0 + a t) sin(2π f t), paper Sec. 3.4.2."""
    a = (s.amplitude_end - s.amplitude_start) / s.end_time()
    return q0 + (s.amplitude_start + a * t) * np.sin(2 * np.pi * s.frequency() * t)


def make_plan(
    config: CollectionConfig,
    joint_names: Sequence[str],
    q_nominal: np.ndarray,
    dt: float = 0.001,
) -> ExcitationPlan:
    """The joint reference and push profile of `config`, around `q_nominal`."""
    config.validate()
    index = {name: i for i, name in enumerate(joint_names)}
    for s in config.sinusoids:
        if s.joint not in index:
            raise KeyError(f"CollectionConfig.sinusoids: unknown joint '{s.joint}'")
    for where, offsets in [("nominal_offsets", config.nominal_offsets)] + [
        ("pushes.configurations", conf) for conf in config.pushes.configurations
    ]:
        for name in offsets:
            if name not in index:
                raise KeyError(f"CollectionConfig.{where}: unknown joint '{name}'")
    q_initial = np.asarray(q_nominal, float)
    q_nominal = q_initial.copy()
    for name, offset in config.nominal_offsets.items():
        q_nominal[index[name]] += offset
    times = [0.0]
    poses = [q_initial]
    wrench_t = [0.0]
    wrenches = [np.zeros(6)]
    phases = []
    t = config.settle

    def move_to(q: np.ndarray, t: float) -> float:
        # Smooth (cubic, zero end velocities) move, sampled densely.
        start, q_start = times[-1], poses[-1]
        for s in np.linspace(0, 1, 21)[1:]:
            times.append(t + s * config.transition)
            poses.append(q_start + (3 * s**2 - 2 * s**3) * (q - q_start))
        phases.append((start, times[-1], PHASE_TRANSITION, -1))
        return times[-1]

    times.append(t)
    poses.append(q_initial)
    t = move_to(q_nominal, t)
    pushes = config.pushes
    rng = np.random.default_rng(pushes.seed)
    if pushes.body:
        bound = np.array([pushes.max_torque] * 3 + [pushes.max_force] * 3)
        for conf in pushes.configurations:
            q = np.asarray(q_nominal, float).copy()
            for name, offset in conf.items():
                q[index[name]] += offset
            t = move_to(q, t)
            start = t
            wrench_t.append(t)
            wrenches.append(np.zeros(6))
            single = [(axis, sign) for axis in range(6) for sign in (-1, 1)]
            order = rng.permutation(len(single))
            for k in range(len(single) + pushes.extra_ramps):
                # One axis at a time (both signs of each), then one or two at a time,
                # like a hand pushing.
                target = np.zeros(6)
                if k < len(single):
                    axis, sign = single[order[k]]
                    target[axis] = sign * rng.uniform(0.6, 1.0)
                else:
                    axes = rng.choice(6, size=rng.integers(1, 3), replace=False)
                    target[axes] = rng.uniform(0.5, 1.0, size=len(axes)) * rng.choice(
                        [-1, 1], size=len(axes)
                    )
                t += pushes.ramp_duration
                wrench_t.append(t)
                wrenches.append(target * bound)
            t += pushes.ramp_duration
            wrench_t.append(t)
            wrenches.append(np.zeros(6))
            times.append(t)
            poses.append(q)
            phases.append((start, t, PHASE_HIGH_TORQUE, -1))
    for s in config.sinusoids:
        j = index[s.joint]
        start = np.asarray(q_nominal, float).copy()
        start[j] += s.center_offset
        t = move_to(start, t)
        duration = s.end_time()
        local = np.linspace(0.0, duration, int(np.ceil(duration / (10 * dt))) + 1)
        for tau in local[1:]:
            q = np.asarray(q_nominal, float).copy()
            q[j] = increasing_sinusoid(tau, q_nominal[j] + s.center_offset, s)
            times.append(t + tau)
            poses.append(q)
        phases.append((t, t + duration, PHASE_HIGH_VELOCITY, j))
        t += duration
    t = move_to(np.asarray(q_nominal, float), t)
    wrench_t.append(t)
    wrenches.append(np.zeros(6))
    # C1, no overshoot between the dense samples (10 ms on the sinusoids).
    q_traj = PiecewisePolynomial.CubicShapePreserving(
        np.array(times), np.array(poses).T, zero_end_point_derivatives=True
    )
    wrench_traj = PiecewisePolynomial.FirstOrderHold(
        np.array(wrench_t), np.array(wrenches).T
    )
    return ExcitationPlan(q_traj, wrench_traj, phases)


class PushSource(LeafSystem):
    """An external wrench on one body, from a 6-vector input [torque; force] (world
    frame, N·m and N) applied at a point of the body.

    .. code-block:: text

                  ┌────────────┐
        wrench ──►│ PushSource ├──► applied_spatial_force
                  └────────────┘
    """

    def __init__(self, body_index: BodyIndex, point: Sequence[float]):
        super().__init__()
        self._force = ExternallyAppliedSpatialForce()
        self._force.body_index = body_index
        self._force.p_BoBq_B = np.asarray(point, float)
        self._wrench = self.DeclareVectorInputPort("wrench", 6)
        self.DeclareAbstractOutputPort(
            "applied_spatial_force",
            lambda: AbstractValue.Make([ExternallyAppliedSpatialForce()]),
            self._calc,
        )

    def _calc(self, context: Context, output: AbstractValue) -> None:
        w = self._wrench.Eval(context)
        self._force.F_Bq_W = SpatialForce(w[:3], w[3:])
        output.set_value([self._force])


def collect(
    station: Diagram,
    plan: ExcitationPlan,
    push_body_index: BodyIndex | None,
    push_point: Sequence[float] = (0.0, 0.0, 0.0),
    log_period: float = 0.001,
    progress: bool = True,
) -> dict[str, np.ndarray]:
    """Runs `plan` on `station` and returns the identification log.

    Returns:
        {"t", "phase", "excited_joint", "q_cmd", "q_measured", "imu_*",
        "wrench_<sensor>", ["joint_torque_true"], "applied_wrench"} as arrays with
        one row per sample.
    """
    builder = DiagramBuilder()
    builder.AddNamedSystem("station", station)
    q_source = builder.AddNamedSystem("q_cmd_source", TrajectorySource(plan.q_cmd))
    builder.Connect(q_source.get_output_port(), station.GetInputPort("q_cmd"))
    wrench_source = builder.AddNamedSystem("wrench_source", TrajectorySource(plan.wrench))
    if push_body_index is not None:
        push = builder.AddNamedSystem("push", PushSource(push_body_index, push_point))
        builder.Connect(wrench_source.get_output_port(), push.get_input_port())
        builder.Connect(push.get_output_port(), station.GetInputPort("applied_spatial_force"))
    ports = {"q_cmd": q_source.get_output_port(), "applied_wrench": wrench_source.get_output_port()}
    for i in range(station.num_output_ports()):
        port = station.get_output_port(i)
        name = port.get_name()
        if (
            name in IDENTIFICATION_LOG_SIGNALS + IMU_LOG_SIGNALS
            or name.startswith("wrench_")
            or name == "joint_torque_true"
        ):
            ports[name] = port
    loggers = add_loggers(builder, ports, log_period)
    simulator = Simulator(builder.Build())
    if progress:
        run_with_progress(simulator, plan.duration, "identification data")
    else:
        simulator.AdvanceTo(plan.duration)
    log = logs_to_arrays(loggers, simulator.get_context())
    phase = np.zeros(len(log["t"]), dtype=int)
    joint = np.full(len(log["t"]), -1, dtype=int)
    for start, end, kind, j in plan.phases:
        inside = (log["t"] >= start) & (log["t"] < end)
        phase[inside] = kind
        joint[inside] = j
    log["phase"] = phase
    log["excited_joint"] = joint
    return log


def save_log(path: str | Path, log: dict[str, np.ndarray], joint_names: Sequence[str]) -> None:
    """Writes an identification log (.npz, one array per signal, plus joint names)."""
    np.savez_compressed(path, joint_names=np.array(list(joint_names)), **log)


def load_log(path: str | Path) -> tuple[dict[str, np.ndarray], list[str]]:
    """Reads a log written by `save_log` or by a real robot in the same format.

    Raises:
        FileNotFoundError, IsADirectoryError: `path` is not a file.
        ValueError: not a readable .npz archive (`dataset.read_npz`), a required
            signal is missing, or sizes disagree.
    """
    from hrp2_drake.identification.dataset import read_npz

    log = read_npz(path, "identification log")
    required = ("t", "joint_names", *IDENTIFICATION_LOG_SIGNALS)
    missing = [key for key in required if key not in log]
    if missing:
        raise ValueError(f"{path}: identification log lacks {missing}")
    names = [str(n) for n in log.pop("joint_names")]
    m, n = len(log["t"]), len(names)
    for key, value in log.items():
        if value.shape[0] != m:
            raise ValueError(f"{path}: '{key}' has {value.shape[0]} samples, 't' has {m}")
    for key in ("q_cmd", "q_measured"):
        if log[key].shape != (m, n):
            raise ValueError(f"{path}: '{key}' has shape {log[key].shape}, expected ({m}, {n})")
    return log, names
