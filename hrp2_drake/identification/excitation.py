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
`logs.IDENTIFICATION_LOG_SIGNALS` and `logs.save_log`), plus, in simulation only,
ground truth for evaluation. Nothing here reads the servo's parameters.

A station is any Diagram with the ports of docs/architecture.md: input `q_cmd` and
`applied_spatial_force`, outputs `q_measured`, `imu_linear_acceleration`,
`imu_angular_velocity`, `wrench_<sensor>`; `joint_torque_true` is logged if present.
"""

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.multibody.math import SpatialForce
from pydrake.multibody.plant import ExternallyAppliedSpatialForce
from pydrake.multibody.tree import BodyIndex
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import Context, Diagram, DiagramBuilder, LeafSystem
from pydrake.systems.primitives import TrajectorySource
from pydrake.trajectories import PiecewisePolynomial

from hrp2_drake.description.excitation import (
    CollectionConfig,
    PushConfig,
    SinusoidConfig,
)
from hrp2_drake.identification.logs import IDENTIFICATION_LOG_SIGNALS, IMU_LOG_SIGNALS
from hrp2_drake.simulation import add_loggers, logs_to_arrays, run_with_progress

# Phases of an identification log, per sample.
PHASE_TRANSITION, PHASE_HIGH_TORQUE, PHASE_HIGH_VELOCITY = 0, 1, 2


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
    """The joint reference and push profile of `config`, around `q_nominal` (rad,
    `joint_names` order): a hold of config.settle s, a move to the nominal pose, the
    pushes (configuration after configuration), the sinusoids (joint after joint,
    their reference sampled every 10 `dt` s), and a move back to the nominal pose."""
    config.validate()
    index = _joint_index(config, joint_names)
    q_initial = np.asarray(q_nominal, float)
    q_nominal = q_initial.copy()
    for name, offset in config.nominal_offsets.items():
        q_nominal[index[name]] += offset
    plan = _PlanSamples(q_initial, config.transition)
    t = plan.hold(q_initial, config.settle)
    t = plan.move_to(q_nominal, t)
    pushes = config.pushes
    rng = np.random.default_rng(pushes.seed)
    if pushes.body:
        for conf in pushes.configurations:
            q = np.asarray(q_nominal, float).copy()
            for name, offset in conf.items():
                q[index[name]] += offset
            t = plan.push(q, t, pushes, rng)
    for s in config.sinusoids:
        t = plan.sinusoid(q_nominal, index[s.joint], s, t, dt)
    t = plan.move_to(np.asarray(q_nominal, float), t)
    plan.wrench_t.append(t)
    plan.wrenches.append(np.zeros(6))
    return plan.plan()


def _joint_index(
    config: CollectionConfig, joint_names: Sequence[str]
) -> dict[str, int]:
    """{joint name: index}; a KeyError names a joint of `config` not in joint_names."""
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
    return index


class _PlanSamples:
    """The samples of an `ExcitationPlan` (`make_plan`), appended part after part:
    joint poses (`times`, `poses`), push wrenches (`wrench_t`, `wrenches`) and the
    phases; each part starts at the time t it is given and returns its end time (s).
    """

    def __init__(self, q_initial: np.ndarray, transition: float):
        self.transition = transition  # the time of a move (s)
        self.times = [0.0]
        self.poses = [q_initial]
        self.wrench_t = [0.0]
        self.wrenches = [np.zeros(6)]
        self.phases = []

    def hold(self, q: np.ndarray, t: float) -> float:
        """The pose q at time t."""
        self.times.append(t)
        self.poses.append(q)
        return t

    def move_to(self, q: np.ndarray, t: float) -> float:
        """A smooth (cubic, zero end velocities) move from the last pose to q, sampled
        densely."""
        start, q_start = self.times[-1], self.poses[-1]
        for s in np.linspace(0, 1, 21)[1:]:
            self.times.append(t + s * self.transition)
            self.poses.append(q_start + (3 * s**2 - 2 * s**3) * (q - q_start))
        self.phases.append((start, self.times[-1], PHASE_TRANSITION, -1))
        return self.times[-1]

    def push(
        self, q: np.ndarray, t: float, pushes: PushConfig, rng: np.random.Generator
    ) -> float:
        """A move to the configuration q, then the ramps of its pushes (random
        magnitudes and order from `rng`), back to no wrench."""
        bound = np.array([pushes.max_torque] * 3 + [pushes.max_force] * 3)
        t = self.move_to(q, t)
        start = t
        self.wrench_t.append(t)
        self.wrenches.append(np.zeros(6))
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
            self.wrench_t.append(t)
            self.wrenches.append(target * bound)
        t += pushes.ramp_duration
        self.wrench_t.append(t)
        self.wrenches.append(np.zeros(6))
        self.hold(q, t)
        self.phases.append((start, t, PHASE_HIGH_TORQUE, -1))
        return t

    def sinusoid(
        self, q_nominal: np.ndarray, j: int, s: SinusoidConfig, t: float, dt: float
    ) -> float:
        """A move to the start of joint j's sinusoid s, then the sinusoid around
        q_nominal, sampled every 10 dt (s)."""
        start = np.asarray(q_nominal, float).copy()
        start[j] += s.center_offset
        t = self.move_to(start, t)
        duration = s.end_time()
        local = np.linspace(0.0, duration, int(np.ceil(duration / (10 * dt))) + 1)
        for tau in local[1:]:
            q = np.asarray(q_nominal, float).copy()
            q[j] = increasing_sinusoid(tau, q_nominal[j] + s.center_offset, s)
            self.times.append(t + tau)
            self.poses.append(q)
        self.phases.append((t, t + duration, PHASE_HIGH_VELOCITY, j))
        return t + duration

    def plan(self) -> ExcitationPlan:
        """The plan of these samples."""
        # C1, no overshoot between the dense samples (10 ms on the sinusoids).
        q_traj = PiecewisePolynomial.CubicShapePreserving(
            np.array(self.times),
            np.array(self.poses).T,
            zero_end_point_derivatives=True,
        )
        wrench_traj = PiecewisePolynomial.FirstOrderHold(
            np.array(self.wrench_t), np.array(self.wrenches).T
        )
        return ExcitationPlan(q_traj, wrench_traj, self.phases)


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
    wrench_source = builder.AddNamedSystem(
        "wrench_source", TrajectorySource(plan.wrench)
    )
    if push_body_index is not None:
        push = builder.AddNamedSystem("push", PushSource(push_body_index, push_point))
        builder.Connect(wrench_source.get_output_port(), push.get_input_port())
        builder.Connect(
            push.get_output_port(), station.GetInputPort("applied_spatial_force")
        )
    ports = {
        "q_cmd": q_source.get_output_port(),
        "applied_wrench": wrench_source.get_output_port(),
    }
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
