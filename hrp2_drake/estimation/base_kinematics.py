"""The floating base's pose and velocity from the legs' kinematics, with every sole
flat where it stands: what a whole-body controller with contacts needs and a robot
without motion capture has (sot-torque-control's base estimator does the same from
the feet, fused with the IMU).

Each sole k stays at its pose X_WS_k (given: where it stood when the run started),
so the joint angles q_j give the base's pose X_WB_k = X_WS_k · X_BS_k(q_j)⁻¹ through
each leg; the estimate is their mean (positions averaged; the rotations' unit
quaternions averaged, signs aligned, and normalised). The velocities follow from the
soles' not moving: J_k,b v_b + J_k,j v_j = 0 for every sole (6 rows each, Jacobians
at the estimated pose), solved for the base's 6 velocities in the least-squares sense.

Valid while every sole stays flat on the ground; a sole that slips or rotates makes
the estimate drift by as much (the balance experiments report when a sole moved).

.. code-block:: text

                 ┌─────────────────────┐
    q (n) ──────►│                     │
                 │ FloatingBaseFromSoles├──► state (nq + nv): the plant's [q; v]
    v (n) ──────►│                     │
                 └─────────────────────┘
"""

import math

import numpy as np
from pydrake.common.eigen_geometry import Quaternion
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import JacobianWrtVariable
from pydrake.systems.framework import Context, DiscreteValues

from hrp2_drake.multibody import get_frame, joint_indexing
from hrp2_drake.step import Step, StepSystem

_WHERE = "FloatingBaseFromSoles"


class BaseFromSolesStep(Step):
    """The per-tick arithmetic of FloatingBaseFromSoles (module docstring).

    State:
        robot_state (nq + nv): the robot's [q; v] in the plant's order (its
            floating base's quaternion, position, ω and velocity in the world), at
            the last tick.
        valid (1): 1 once a tick had finite inputs (before: the plant's default
            state with the joints at zero).
    """

    def __init__(
        self,
        plant: MultibodyPlant,
        joints: list[str],
        sole_poses: dict[str, RigidTransform],
    ):
        """
        Args:
            plant: a finalized MultibodyPlant of the robot alone, one floating base
                with a quaternion joint; it must outlive the step.
            joints: every joint of the robot, the order of the inputs q and v.
            sole_poses: each sole frame's pose in the world, X_WS (where it
                stands; at least one sole).

        Raises:
            ValueError: no sole, a plant whose joints are not all listed, a base
                without a quaternion joint.
            KeyError: an unknown joint or frame.
        """
        super().__init__()
        if not sole_poses:
            raise ValueError(f"{_WHERE}: no sole poses")
        self._plant = plant
        self._context = plant.CreateDefaultContext()
        self._indexing = joint_indexing(plant, joints)
        bases = list(plant.GetFloatingBaseBodies())
        if len(bases) != 1:
            raise ValueError(f"{_WHERE}: the plant needs exactly one floating base")
        base = plant.get_body(bases[0])
        if not base.has_quaternion_dofs():
            raise ValueError(f"{_WHERE}: the base needs a quaternion floating joint")
        nv = plant.num_velocities()
        if nv != 6 + self._indexing.size:
            raise ValueError(
                f"{_WHERE}: {self._indexing.size} joints given, the plant has "
                f"{nv - 6}: list every joint"
            )
        self._base = base
        self._base_frame = base.body_frame()
        self._frames = [get_frame(plant, name, "sole frame") for name in sole_poses]
        self._X_WS = [RigidTransform(X) for X in sole_poses.values()]
        self._q0 = base.floating_positions_start()
        self._v0 = base.floating_velocities_start_in_v()
        self._nq = plant.num_positions()
        self._J = np.zeros((6 * len(self._frames), nv))
        self._zero3 = np.zeros(3)
        self._declare("robot_state", plant.GetPositionsAndVelocities(self._context))
        self._declare("valid", [0.0])
        self._finalize()

    def step(self, t: float, q: np.ndarray, v: np.ndarray) -> None:
        """One tick from the joint angles q (rad) and velocities v (rad/s), the
        constructor's joint order; a non-finite input keeps the last estimate."""
        if not math.isfinite(q.sum() + v.sum()):
            return
        plant, context = self._plant, self._context
        positions = self.robot_state[: self._nq]
        positions[self._indexing.q] = q
        # The base at the origin: X_BS of each sole, then the base's pose per sole.
        positions[self._q0 : self._q0 + 7] = [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
        plant.SetPositions(context, positions)
        translation = np.zeros(3)
        wxyz = np.zeros(4)
        for frame, X_WS in zip(self._frames, self._X_WS):
            X_BS = frame.CalcPose(context, self._base_frame)
            X_WB = X_WS.multiply(X_BS.inverse())
            translation += X_WB.translation()
            quaternion = X_WB.rotation().ToQuaternion().wxyz()
            if wxyz @ quaternion < 0.0:
                quaternion = -quaternion
            wxyz += quaternion
        wxyz /= np.linalg.norm(wxyz)
        translation /= len(self._frames)
        X_WB = RigidTransform(RotationMatrix(Quaternion(wxyz)), translation)
        plant.SetFreeBodyPose(context, self._base, X_WB)
        positions[:] = plant.GetPositions(context)
        # The soles do not move: J_b v_b = −J_j v_j, least squares.
        for k, frame in enumerate(self._frames):
            self._J[6 * k : 6 * k + 6] = plant.CalcJacobianSpatialVelocity(
                context,
                JacobianWrtVariable.kV,
                frame,
                self._zero3,
                plant.world_frame(),
                plant.world_frame(),
            )
        base = slice(self._v0, self._v0 + 6)
        velocities = self.robot_state[self._nq :]
        velocities[self._indexing.v] = v
        velocities[base] = np.linalg.lstsq(
            self._J[:, base], -self._J[:, self._indexing.v] @ v, rcond=None
        )[0]
        self.valid[0] = 1.0


class FloatingBaseFromSoles(StepSystem):
    """The floating base's state from the legs' kinematics (module docstring).

    Inputs:
        q (n, rad), v (n, rad/s): every joint, the constructor's joint order (the
            encoders or the Savitzky-Golay estimates).

    Output (discrete state, updated every `period`):
        state (nq + nv): the plant's [q; v] with the base from the soles.
    """

    def __init__(
        self,
        plant: MultibodyPlant,
        joints: list[str],
        sole_poses: dict[str, RigidTransform],
        period: float,
    ):
        super().__init__()
        step = BaseFromSolesStep(plant, joints, sole_poses)
        self._q = self.DeclareVectorInputPort("q", len(joints))
        self._v = self.DeclareVectorInputPort("v", len(joints))
        self._declare_step_state(step)
        self._declare_step_output("state", "robot_state")
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._update)

    def step(self) -> BaseFromSolesStep:
        return self._step

    def _update(self, context: Context, discrete_state: DiscreteValues) -> None:
        self._load(discrete_state)
        self._step.step(
            context.get_time(), self._q.Eval(context), self._v.Eval(context)
        )
        self._store(discrete_state)
