"""The hoist of the "lowered" scenario: a floating robot hanging from two strings whose
anchors go down, so that the robot, lifted at first with its feet free, stands on its
soles at the end, the strings slack (`robot.station`). This is how a real humanoid is
started: lifted, its F/T sensors' offsets found with the feet free, then put down.

.. code-block:: text

                             ┌───────┐
    body_poses ─────────────►│ Hoist ├──► applied_spatial_force
    body_spatial_velocities ►│       │
                             └───────┘

Each string pulls the body it is tied to (the description's `scenarios.hanging`)
toward its anchor with the tension k (ℓ − ℓ₀) + c ℓ̇ while it is stretched (ℓ > ℓ₀,
the tension never negative: a string does not push), ℓ its length. The anchors go
down by `drop` between `start` and `start + duration` (a smooth cosine profile: no
step in speed). The harness holds the body's orientation (a rotational spring of
`hold_stiffness` to its pose at t = 0: the strings alone would let the robot pitch
until its CoM hangs below them, and swing, and land pitched), and damps its motion
(the "hanging" scenario's sway damping, `HangingConfig.sway_damping`); both fade out
over the lowering: a robot standing on its soles is neither held nor damped by the
world.

`ForceSum` concatenates the hoist's forces with the station's own
`applied_spatial_force` input (pushes), which may stay unconnected.
"""

import math
from collections.abc import Sequence

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.math import SpatialForce, SpatialVelocity
from pydrake.multibody.plant import ExternallyAppliedSpatialForce
from pydrake.multibody.tree import BodyIndex
from pydrake.systems.framework import Context, LeafSystem


def _force_list() -> AbstractValue:
    return AbstractValue.Make([ExternallyAppliedSpatialForce()])


class Hoist(LeafSystem):
    """The strings of a hoist that lowers its robot (module docstring).

    Args:
        body_index: the body the strings are tied to.
        points: where, in its frame (m), one per string.
        anchors: each string's anchor in the world at t = 0 (m).
        length: the strings' free length ℓ₀ (m).
        stiffness, damping: k (N/m) and c (N·s/m) of each string.
        sway_damping: [rotational (N·m·s/rad), translational (N·s/m)] damping of
            the body's motion in the world, faded out while lowering.
        hold_stiffness: the harness's rotational stiffness (N·m/rad) to the body's
            orientation at t = 0 (`initial_rotation`), faded out while lowering.
        initial_rotation: the body's orientation in the world at t = 0.
        start, duration: when the anchors start going down, and for how long (s).
        drop: how far they go down (m).
    """

    def __init__(
        self,
        body_index: BodyIndex,
        points: Sequence[Sequence[float]],
        anchors: Sequence[Sequence[float]],
        length: float,
        stiffness: float,
        damping: float,
        sway_damping: Sequence[float],
        start: float,
        duration: float,
        drop: float,
        hold_stiffness: float = 0.0,
        initial_rotation: RotationMatrix | None = None,
    ):
        super().__init__()
        self._body = body_index
        self._points = [np.asarray(p, float) for p in points]
        self._anchors = [np.asarray(a, float) for a in anchors]
        self._length, self._k, self._c = length, stiffness, damping
        self._rotational, self._translational = sway_damping
        self._start, self._duration, self._drop = start, duration, drop
        self._hold = hold_stiffness
        self._R0 = initial_rotation or RotationMatrix()
        self._poses = self.DeclareAbstractInputPort(
            "body_poses", AbstractValue.Make([RigidTransform()])
        )
        self._velocities = self.DeclareAbstractInputPort(
            "body_spatial_velocities", AbstractValue.Make([SpatialVelocity()])
        )
        self.DeclareAbstractOutputPort("applied_spatial_force", _force_list, self._calc)

    def lowered(self, t: float) -> float:
        """The share of the drop done at t: 0 before `start`, 1 after it ends."""
        s = (t - self._start) / self._duration
        if s <= 0.0:
            return 0.0
        if s >= 1.0:
            return 1.0
        return 0.5 - 0.5 * math.cos(math.pi * s)

    def _calc(self, context: Context, output: AbstractValue) -> None:
        t = context.get_time()
        share = self.lowered(t)
        speed = 0.0  # the anchors' downward speed (m/s)
        if 0.0 < share < 1.0:
            s = (t - self._start) / self._duration
            speed = 0.5 * math.pi * math.sin(math.pi * s) * self._drop / self._duration
        X_WB = self._poses.Eval(context)[int(self._body)]
        V_WB = self._velocities.Eval(context)[int(self._body)]
        R = X_WB.rotation().matrix()
        w, v = V_WB.rotational(), V_WB.translational()
        forces = []
        for p_B, anchor in zip(self._points, self._anchors):
            p_BQ_W = R @ p_B
            p_WQ = X_WB.translation() + p_BQ_W
            anchor_now = anchor - [0.0, 0.0, self._drop * share]
            d = anchor_now - p_WQ
            length = float(np.linalg.norm(d))
            if length <= self._length or length == 0.0:
                continue
            u = d / length
            # ℓ̇: the anchor's velocity (down) minus the point's, along u.
            v_Q = v + np.cross(w, p_BQ_W)
            rate = float(u @ (np.array([0.0, 0.0, -speed]) - v_Q))
            tension = max(0.0, self._k * (length - self._length) + self._c * rate)
            forces.append(self._force(p_B, np.zeros(3), tension * u))
        fade = 1.0 - share
        if fade > 0.0:
            # The rotation from the initial orientation, as angle × axis (world).
            error = (X_WB.rotation() @ self._R0.inverse()).ToAngleAxis()
            held = error.angle() * error.axis()
            forces.append(
                self._force(
                    np.zeros(3),
                    -fade * (self._hold * held + self._rotational * w),
                    -fade * self._translational * v,
                )
            )
        output.set_value(forces)

    def _force(self, p_B, torque, force) -> ExternallyAppliedSpatialForce:
        f = ExternallyAppliedSpatialForce()
        f.body_index = self._body
        f.p_BoBq_B = np.asarray(p_B, float)
        f.F_Bq_W = SpatialForce(np.asarray(torque, float), np.asarray(force, float))
        return f


class ForceSum(LeafSystem):
    """The forces of `hoist` and of `external` in one list; `external` may stay
    unconnected.

    .. code-block:: text

                  ┌──────────┐
        hoist ───►│ ForceSum ├──► applied_spatial_force
        external ►│          │
                  └──────────┘
    """

    def __init__(self):
        super().__init__()
        self._hoist = self.DeclareAbstractInputPort("hoist", _force_list())
        self._external = self.DeclareAbstractInputPort("external", _force_list())
        self.DeclareAbstractOutputPort("applied_spatial_force", _force_list, self._calc)

    def _calc(self, context: Context, output: AbstractValue) -> None:
        forces = list(self._hoist.Eval(context))
        if self._external.HasValue(context):
            forces += list(self._external.Eval(context))
        output.set_value(forces)
