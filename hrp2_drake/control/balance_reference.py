"""References for a robot standing on its soles: which joints carry it (the legs), the
authors' CoM motion, and the joint angles that put the CoM there with the soles
fixed (inverse kinematics): the posture reference of the balance QP, and the whole
reference of the position-controlled baseline (the robot's own servo tracking it).

The inverse kinematics holds every sole at its pose, the base upright and the CoM at
its target, by moving the base and the legs (the joints the soles' Jacobians
involve), the other joints fixed: as many equations as unknowns on a robot with two
6-dof legs (12 + 3 + 3 = 6 + 12), solved by Gauss-Newton on Drake's Jacobians to
1e-10 (m, rad).
"""

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from pydrake.math import RotationMatrix
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import JacobianWrtVariable

from hrp2_drake.config import check_finite
from hrp2_drake.multibody import get_frame, joint_indexing

_WHERE = "balance reference"


def leg_joints(
    plant: MultibodyPlant, joints: Sequence[str], soles: Sequence[str]
) -> list[str]:
    """The joints among `joints` (one-dof, `plant`'s) between the floating base and
    any of the `soles` (frame names): the columns of the soles' Jacobians that are
    not zero, in `joints` order."""
    context = plant.CreateDefaultContext()
    indexing = joint_indexing(plant, joints)
    moved = np.zeros(plant.num_velocities(), dtype=bool)
    for sole in soles:
        J = plant.CalcJacobianSpatialVelocity(
            context,
            JacobianWrtVariable.kV,
            get_frame(plant, sole, "sole frame"),
            np.zeros(3),
            plant.world_frame(),
            plant.world_frame(),
        )
        moved |= np.any(J != 0.0, axis=0)
    return [name for name, v in zip(indexing.names, indexing.v) if moved[v]]


def sinusoid_com(
    com0: np.ndarray,
    t: np.ndarray,
    *,
    amplitude: float = 0.03,
    period: float = 2.0,
    shift_time: float = 1.0,
    hold_time: float = 0.5,
    axis: int = 1,
) -> np.ndarray:
    """The authors' CoM motion (sot-torque-control's balance test on HRP-2): from
    `com0` (m, world) a smooth shift to +`amplitude` along `axis` (a quintic over
    `shift_time`), held `hold_time`, then a sinusoid between +amplitude and
    −amplitude of `period` (s). Returns (len(t), 9): position, velocity,
    acceleration (m, m/s, m/s²)."""
    t = np.asarray(t, float)
    out = np.zeros((len(t), 9))
    out[:, :3] = com0
    s = np.clip(t / shift_time, 0.0, 1.0)
    shifting = t < shift_time
    p = amplitude * s**3 * (10 - 15 * s + 6 * s**2)
    v = amplitude * 30 * s**2 * (1 - s) ** 2 / shift_time * shifting
    a = amplitude * 60 * s * (1 - s) * (1 - 2 * s) / shift_time**2 * shifting
    start = shift_time + hold_time
    w = 2 * math.pi / period
    after = t >= start
    phase = w * (t - start)
    p = np.where(after, amplitude * np.cos(phase), p)
    v = np.where(after, -amplitude * w * np.sin(phase), v)
    a = np.where(after, -amplitude * w**2 * np.cos(phase), a)
    out[:, axis] += p
    out[:, 3 + axis] = v
    out[:, 6 + axis] = a
    return out


class StandingIk:
    """The joint angles of a robot standing on `soles` (fixed where they are at
    `positions`) with its base upright and its CoM at a target (module docstring).

    Args:
        plant: a finalized MultibodyPlant of the robot alone, one floating base.
        joints: every joint, the order of the returned angles.
        soles: the sole frames that stay fixed.
        positions: the plant's positions the robot starts from (the soles' poses
            and the other joints' angles are taken from it).
    """

    def __init__(
        self,
        plant: MultibodyPlant,
        joints: Sequence[str],
        soles: Sequence[str],
        positions: np.ndarray,
    ):
        self._plant = plant
        self._context = plant.CreateDefaultContext()
        plant.SetPositions(self._context, positions)
        self._indexing = joint_indexing(plant, joints)
        bases = list(plant.GetFloatingBaseBodies())
        if len(bases) != 1:
            raise ValueError(f"{_WHERE}: the plant needs exactly one floating base")
        self._base = plant.get_body(bases[0])
        self._frames = [get_frame(plant, s, "sole frame") for s in soles]
        self._X_WS = [f.CalcPoseInWorld(self._context) for f in self._frames]
        legs = leg_joints(plant, joints, soles)
        v0 = self._base.floating_velocities_start_in_v()
        self._columns = np.r_[
            np.arange(v0, v0 + 6), self._indexing.subset(legs).v
        ].astype(int)
        self._positions = np.array(positions, float)
        self.legs = legs

    def com(self, positions: np.ndarray) -> np.ndarray:
        self._plant.SetPositions(self._context, positions)
        return self._plant.CalcCenterOfMassPositionInWorld(self._context)

    def solve(
        self, com: np.ndarray, start: np.ndarray | None = None, tolerance=1e-10
    ) -> np.ndarray:
        """The plant's positions with the CoM at `com` (m, world), from `start`
        (default: the constructor's positions). Raises ValueError if Gauss-Newton
        does not reach `tolerance` in 30 iterations (a target out of reach)."""
        plant, context = self._plant, self._context
        world = plant.world_frame()
        kV = JacobianWrtVariable.kV
        q = np.array(self._positions if start is None else start, float)
        rows = 6 * len(self._frames) + 6
        J = np.zeros((rows, plant.num_velocities()))
        error = np.zeros(rows)
        for _ in range(30):
            plant.SetPositions(context, q)
            for k, (frame, X_WS) in enumerate(zip(self._frames, self._X_WS)):
                X = frame.CalcPoseInWorld(context)
                block = slice(6 * k, 6 * k + 6)
                error[block] = np.r_[
                    _rotation_error(X_WS.rotation(), X.rotation()),
                    X_WS.translation() - X.translation(),
                ]
                J[block] = plant.CalcJacobianSpatialVelocity(
                    context, kV, frame, np.zeros(3), world, world
                )
            base = slice(rows - 6, rows - 3)
            X_WB = self._base.EvalPoseInWorld(context)
            error[base] = _rotation_error(RotationMatrix(), X_WB.rotation())
            J[base] = plant.CalcJacobianSpatialVelocity(
                context, kV, self._base.body_frame(), np.zeros(3), world, world
            )[:3]
            error[rows - 3 :] = com - plant.CalcCenterOfMassPositionInWorld(context)
            J[rows - 3 :] = plant.CalcJacobianCenterOfMassTranslationalVelocity(
                context, kV, world, world
            )
            if np.max(np.abs(error)) < tolerance:
                return q
            step = np.zeros(plant.num_velocities())
            step[self._columns] = np.linalg.lstsq(
                J[:, self._columns], error, rcond=None
            )[0]
            q = q + plant.MapVelocityToQDot(context, step)
            q0 = self._base.floating_positions_start()
            q[q0 : q0 + 4] /= np.linalg.norm(q[q0 : q0 + 4])
        raise ValueError(
            f"{_WHERE}: no pose puts the CoM at {np.round(com, 4).tolist()} m with the "
            f"soles fixed (error {np.max(np.abs(error)):.2e} after 30 iterations)"
        )

    def joint_angles(self, positions: np.ndarray) -> np.ndarray:
        """The joints' angles (constructor order) of plant positions."""
        return positions[self._indexing.q]

    def trajectory(self, com: np.ndarray) -> np.ndarray:
        """Plant positions for each CoM target (rows of `com`, m), each solve
        started from the previous one's answer: (len(com), nq)."""
        out = np.zeros((len(com), self._plant.num_positions()))
        q = self._positions
        for k, target in enumerate(com):
            q = out[k] = self.solve(target, q)
        return out


def _rotation_error(target: RotationMatrix, current: RotationMatrix) -> np.ndarray:
    """The rotation from `current` to `target` as angle · axis in the world (rad)."""
    R = target.multiply(current.inverse())
    angle_axis = R.ToAngleAxis()
    return angle_axis.angle() * angle_axis.axis()


@dataclass
class ComSinusoid:
    """The authors' CoM motion (`sinusoid_com`, sot-torque-control's balance test on
    HRP-2) as a config: `control --motion balance` runs it from `settle` to the run's
    end, the balance experiment (`experiments.balance.runner.ComMotion`) for a duration.

    Args:
        axis: "x" or "y" (the world's).
        amplitude: ± (m) about the standing CoM.
        period: the sinusoid's (s).
        shift_time: the first shift to +amplitude (s).
        hold_time: held at +amplitude before the sinusoid (s).
    """

    axis: str = "y"
    amplitude: float = 0.03
    period: float = 2.0
    shift_time: float = 1.0
    hold_time: float = 0.5

    def validate(self, where: str = "ComSinusoid") -> None:
        if self.axis not in ("x", "y"):
            raise ValueError(f"{where}.axis: '{self.axis}', expected 'x' or 'y'")
        check_finite(self.amplitude, f"{where}.amplitude", 0.0, strict=False)
        for name in ("period", "shift_time"):
            check_finite(getattr(self, name), f"{where}.{name}", 0.0)
        check_finite(self.hold_time, f"{where}.hold_time", 0.0, strict=False)

    def samples(self, com0: np.ndarray, t: np.ndarray, settle: float) -> np.ndarray:
        """(len(t), 9): the CoM's position, velocity and acceleration at the times
        `t` (s): at `com0` (m, world) until `settle`, then the motion."""
        com = sinusoid_com(
            com0,
            t - settle,
            amplitude=self.amplitude,
            period=self.period,
            shift_time=self.shift_time,
            hold_time=self.hold_time,
            axis="xy".index(self.axis),
        )
        com[t < settle] = np.r_[com0, np.zeros(6)]
        return com
