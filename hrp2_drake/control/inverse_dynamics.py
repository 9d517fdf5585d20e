"""InverseDynamicsController: desired joint torques from a joint trajectory and an
optional contact-force task (paper Sec. 4.1.3, eq. 12), and `make_fixed_base_plant`,
which builds the fixed-base model the paper's controller uses (footnote 3).

Eq. 12, for the n controlled joints j (e.g. the six joints of the right leg):

    τ_d = M_j q̈_d + ĥ_j − J_jᵀ f* + K_s e_q + K_d ė_q,    f* = f_d + K_f e_f

with e_q = q_d − q̂, ė_q = q̇_d − q̂̇, e_f = f_d − f̂. M_j is the controlled joints'
block of the mass matrix (it includes the actuators' reflected rotor inertia ρ² I_r
when the model's JointActuators carry it), ĥ_j their rows of the Coriolis,
centrifugal and gravity generalized forces, J_j the controlled joints' columns of the
force frame's spatial-velocity Jacobian. The gains are diagonal.

Besides τ_d the controller outputs the terms it is made of, so that the torque
controller can split its Δq into the six components of paper Sec. 5.5 (see
`DeltaQTorqueController` in torque_controller.py):

    τ_d = tau_feedforward + tau_position_feedback + tau_velocity_feedback
          + tau_force_feedback

    tau_feedforward       = M_j q̈_d + ĥ_j − J_jᵀ f_d     (the feedforward of eq. 13)
    tau_position_feedback = K_s e_q
    tau_velocity_feedback = K_d ė_q
    tau_force_feedback    = −J_jᵀ K_f e_f
    tau_force_error       = −J_jᵀ e_f                    (not part of τ_d: the torque
                                                          of the force error, which
                                                          K9 of Sec. 4.2 also weighs)
"""

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from pydrake.math import RigidTransform
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import (
    BodyIndex,
    FixedOffsetFrame,
    Frame,
    JacobianWrtVariable,
    ModelInstanceIndex,
    MultibodyForces,
    QuaternionFloatingJoint,
    RigidBody,
    SpatialInertia,
    WeldJoint,
)
from pydrake.systems.framework import Context, InputPort

from hrp2_drake.kernels import kernel
from hrp2_drake.multibody import (
    check_joint_names,
    check_vector,
    copy_joint,
    floating_base,
    get_frame,
    joint_indexing,
    tree_joints,
)
from hrp2_drake.step import Step, StepSystem

_WHERE = "InverseDynamicsController"
_ROOT = "inverse_dynamics_root"  # the part model's massless floating body
_logger = logging.getLogger(__name__)

#: The components of τ_d (and tau_force_error), in the order of the output ports
#: after tau_desired; DeltaQTorqueController has input ports of the same names.
TORQUE_COMPONENTS: tuple[str, ...] = (
    "tau_feedforward",
    "tau_position_feedback",
    "tau_velocity_feedback",
    "tau_force_feedback",
    "tau_force_error",
)


def gain_vector(
    name: str, value, size: int, where: str, allow_inf: bool = False
) -> np.ndarray:
    """A diagonal gain (or a per-joint bound) as a vector of `size` entries.

    Args:
        name: the gain's name, for the error message (e.g. "ks").
        value: a number (the same gain for every entry) or a sequence of 1 or
            `size` numbers.
        size: the number of entries (joints, or 6 for a wrench).
        where: who asks, for the error message.
        allow_inf: accept +inf (a bound that never binds).

    Raises:
        ValueError: a wrong size, a NaN (or infinite, unless allowed) value, or a
            negative value; the message names `where` and `name`.
    """
    array = np.atleast_1d(np.asarray(value, dtype=float))
    if array.ndim != 1 or array.size not in (1, size):
        raise ValueError(
            f"{where}.{name}: expected one value or {size} values, got "
            f"{np.shape(value)} ({value!r})"
        )
    if np.any(np.isnan(array)) or not (allow_inf or np.all(np.isfinite(array))):
        raise ValueError(f"{where}.{name} is not finite: {value!r}")
    if np.any(array < 0):
        raise ValueError(f"{where}.{name} must be >= 0, got {value!r}")
    return np.broadcast_to(array, (size,)).copy()


# yaml_load_typed reads the field types at run time: this module must not use
# `from __future__ import annotations`.
@dataclass
class InverseDynamicsConfig:
    """Configuration of InverseDynamicsController (eq. 12).

    Every gain is diagonal and given as a list of one value (the same for every joint
    or axis) or of one value per joint (per wrench axis for kf); in Python a plain
    number is accepted too. `inverse_dynamics_gains_for_k6` (gains.py)
    computes ks and kd from the paper's K6.

    Args:
        joints: names of the n controlled one-dof joints, in the order of every joint
            vector of the controller (e.g. the six right-leg joints).
        ks: stiffness K_s (N·m/rad), 1 or n values.
        kd: damping K_d (N·m·s/rad), 1 or n values.
        force_frame: name of the frame (or body) of the force task: f_ref and f are
            wrenches about its origin, expressed in it (for HRP-2's right foot, the
            F/T sensor frame "RLEG_FOOT"). Empty: no force task, pure motion control
            (no f_ref / f ports).
        kf: force gain K_f (dimensionless), 1 or 6 values, on [torque; force].
        floating_base: False (default, the paper's footnote 3): the model has a fixed
            base (see `make_fixed_base_plant`). True: the model has a floating base
            whose orientation and angular velocity are inputs; the base's
            acceleration is taken as zero (see the class docstring).
        period: the control period (s; a keyword, no default).
    """

    joints: list[str] = field(default_factory=list)
    ks: list[float] = field(default_factory=lambda: [100.0])
    kd: list[float] = field(default_factory=lambda: [10.0])
    force_frame: str = ""
    kf: list[float] = field(default_factory=lambda: [0.0])
    floating_base: bool = False
    period: float = field(kw_only=True)

    def validate(self) -> None:
        """Raises ValueError naming the bad field (yaml_load_typed does not call it)."""
        where = "InverseDynamicsConfig"
        check_joint_names(self.joints, where)
        n = len(self.joints)
        gain_vector("ks", self.ks, n, where)
        gain_vector("kd", self.kd, n, where)
        gain_vector("kf", self.kf, 6, where)
        if not (math.isfinite(self.period) and self.period > 0):
            raise ValueError(f"{where}.period={self.period} must be > 0 (s)")


def make_fixed_base_plant(
    add_model: Callable[[MultibodyPlant], object],
    base_body: str,
    X_WB: RigidTransform | None = None,
) -> MultibodyPlant:
    """A finalized continuous MultibodyPlant of a robot with its base welded to the
    world: the fixed-base model of the paper's controller (footnote 3).

    Args:
        add_model: adds the robot to a plant (e.g. hrp2_drake.paper.hrp2.add_hrp2;
            control never imports the robot package, the caller passes it).
        base_body: name of the body to weld (for HRP-2 "BODY", the waist).
        X_WB: pose of the base in the world (default identity: upright, so that
            gravity is −z of the base frame).

    Raises:
        KeyError: `base_body` is not a body of the model.
    """
    plant = MultibodyPlant(time_step=0.0)
    add_model(plant)
    if not plant.HasBodyNamed(base_body):
        raise KeyError(f"make_fixed_base_plant: base body '{base_body}' is not a body")
    plant.WeldFrames(
        plant.world_frame(),
        plant.GetBodyByName(base_body).body_frame(),
        X_WB if X_WB is not None else RigidTransform(),
    )
    plant.Finalize()
    return plant


class _FrameCopies:
    """The copies of a plant's frames in a part model (`_moved_part`), each made once:
    on the copy of its body, or welded to `anchor` (the part's root, at the world's
    place) where it is in `context` if its body does not move (has no copy)."""

    def __init__(
        self,
        model: MultibodyPlant,
        context: Context,
        bodies: dict[int, RigidBody],
        anchor: Frame,
    ):
        self._model, self._context, self._bodies = model, context, bodies
        self._anchor = anchor
        self._copies: dict[int, Frame] = {}

    def __call__(self, original: Frame) -> Frame:
        index = int(original.index())
        if index not in self._copies:
            self._copies[index] = self._copy(original)
        return self._copies[index]

    def _copy(self, original: Frame) -> Frame:
        model = self._model
        body = self._bodies.get(int(original.body().index()))
        if body is None:  # does not move: on the root, where it is in the world
            return model.AddFrame(
                FixedOffsetFrame(
                    original.name(),
                    self._anchor,
                    original.CalcPoseInWorld(self._context),
                    original.model_instance(),
                )
            )
        if original.is_body_frame():
            return body.body_frame()
        return model.AddFrame(
            FixedOffsetFrame(
                original.name(),
                body.body_frame(),
                original.GetFixedPoseInBodyFrame(),
                original.model_instance(),
            )
        )


def _moved_part(
    plant: MultibodyPlant,
    context: Context,
    joints: list[str],
    frame: Frame | None,
) -> tuple[MultibodyPlant, Frame | None, RigidBody] | None:
    """A copy of the part of a fixed-base `plant` that `joints` move: the bodies
    outboard of them (with their inertias in `context`), the revolute or prismatic
    `joints` themselves (with their actuators' rotor inertias and gear ratios), every
    other joint between those bodies welded at its pose in `context`, the joints that
    hold the part welded at their pose in `context` to a massless root body, whose
    6-dof joint (QuaternionFloatingJoint) to the world stays at the identity; gravity as
    in `plant`, no other force element. With the other joints at rest, its M_j, ĥ_j
    and J_j are exactly those of `plant` at `context`'s positions: a leg's inverse
    dynamics on 6 bodies instead of the whole robot's. The root at rest with the
    proper acceleration −g (an upward acceleration of the whole part, in the world),
    in an inverse dynamics without gravity's forces, is the part at rest under
    gravity: an inverse dynamics with gravity in one call
    (`InverseDynamicsControllerStep`).

    Returns (model, copy of `frame`: on the body's copy, or welded to the root if
    `frame` is not on a moved body, the root), or None if a joint of `joints` is
    neither revolute nor prismatic (the caller then uses `plant` itself).
    """
    controlled = [plant.GetJointByName(name) for name in joints]
    if any(j.type_name() not in ("revolute", "prismatic") for j in controlled):
        return None
    moved = {
        int(b)
        for b in plant.GetBodiesKinematicallyAffectedBy([j.index() for j in controlled])
    }
    # The joint that holds each moved body, breadth-first from the world.
    holder = {
        b: joint
        for b, (_, joint) in tree_joints(
            plant, plant.world_body().index(), True
        ).items()
        if b in moved
    }
    model, root = _rooted_model(plant)
    copies = {}
    for b in holder:
        body = plant.get_body(BodyIndex(b))
        copies[b] = model.AddRigidBody(
            body.name(),
            body.model_instance(),
            body.CalcSpatialInertiaInBodyFrame(context),
        )
    copy_frame = _FrameCopies(model, context, copies, root.body_frame())
    _copy_holding_joints(
        model, plant, context, holder, {int(j.index()) for j in controlled}, copy_frame
    )
    frame_copy = copy_frame(frame) if frame is not None else None
    model.Finalize()
    return model, frame_copy, root


def _rooted_model(plant: MultibodyPlant) -> tuple[MultibodyPlant, RigidBody]:
    """An empty continuous model with `plant`'s gravity and model instances, and its
    massless root body on a 6-dof joint to the world (`_moved_part`)."""
    model = MultibodyPlant(time_step=0.0)
    model.mutable_gravity_field().set_gravity_vector(
        plant.gravity_field().gravity_vector()
    )
    for i in range(2, plant.num_model_instances()):  # 0: world, 1: default
        model.AddModelInstance(plant.GetModelInstanceName(ModelInstanceIndex(i)))
    root = model.AddRigidBody(
        _ROOT, model.AddModelInstance(_ROOT), SpatialInertia.Zero()
    )
    model.AddJoint(
        QuaternionFloatingJoint(
            f"{_ROOT}_joint", model.world_frame(), root.body_frame()
        )
    )
    return model, root


def _copy_holding_joints(
    model: MultibodyPlant,
    plant: MultibodyPlant,
    context: Context,
    holder: dict,
    controlled: set[int],
    copy_frame: _FrameCopies,
) -> None:
    """Adds to `model` the joint that holds each moved body ({body index: joint},
    breadth-first from the world): the `controlled` joints (their indices) as
    copies, every other one welded at its pose in `context`."""
    for b, joint in holder.items():
        # A joint turned around (its child inboard) keeps its q and its generalized
        # force with the opposite axis; a weld takes its inverse pose.
        forward = int(joint.child_body().index()) == b
        on_parent, on_child = (
            (joint.frame_on_parent(), joint.frame_on_child())
            if forward
            else (joint.frame_on_child(), joint.frame_on_parent())
        )
        F, M = copy_frame(on_parent), copy_frame(on_child)
        if int(joint.index()) not in controlled:
            X_FM = on_child.CalcPose(context, on_parent)
            model.AddJoint(WeldJoint(joint.name(), F, M, X_FM))
            continue
        copy_joint(model, plant, context, joint, F, M, forward)


class InverseDynamicsTerms(NamedTuple):
    """τ_d of eq. 12 and its terms (N·m, n each, config.joints order).

    tau_desired = feedforward + position_feedback + velocity_feedback +
    force_feedback; force_error = −J_jᵀ e_f is not part of it (see the module
    docstring).
    """

    tau_desired: np.ndarray
    feedforward: np.ndarray
    position_feedback: np.ndarray
    velocity_feedback: np.ndarray
    force_feedback: np.ndarray
    force_error: np.ndarray


class JointSpaceModel(NamedTuple):
    """The controlled joints' dynamics at one state.

    Attributes:
        mass_matrix: M_j (kg·m² for revolute joints), (n, n).
        bias: ĥ_j, Coriolis, centrifugal and gravity generalized forces (N·m), (n,).
        jacobian: J_j, (6, n): the spatial velocity [ω; v] of the force frame in the
            world, expressed in the force frame, per unit q̇_j; None without a force
            task.
    """

    mass_matrix: np.ndarray
    bias: np.ndarray
    jacobian: np.ndarray | None


def _find_base(plant: MultibodyPlant, floating: bool) -> RigidBody | None:
    """The floating base body of `plant` (None with a fixed base), checked against
    config.floating_base."""
    if not floating:
        bases = sorted(int(b) for b in plant.GetFloatingBaseBodies())
        if bases:
            names = [plant.get_body(BodyIndex(b)).name() for b in bases]
            raise ValueError(
                f"{_WHERE}: the plant has the floating base(s) {names}, but the "
                "controller uses a fixed-base model (paper footnote 3): build it "
                "with make_fixed_base_plant, or set config.floating_base"
            )
        return None
    return floating_base(plant, f"{_WHERE}: config.floating_base")


# InverseDynamicsControllerStep's index table (`_pack`, int64): a header, then the
# index lists.
(
    _N,  # n, the controlled joints
    _NQ,  # the model's positions,
    _NV,  # and velocities
    _FLAGS,  # _FORCE_TASK
    _BASE_Q,  # a floating base's quaternion [w, x, y, z] in q (else 0)
    _BASE_V,  # its velocities [ω_WB; v_WBo] (in W) in v (else 0)
    # Where each part of the work array starts (x = [q; v] of the model at 0):
    _W_VDOT,  # v̇ of the model (nv)
    _W_GAINS,  # K_s (n), K_d (n), K_f (6)
    _W_FORCE,  # e_f (6), K_f e_f (6)
    # Where each index list starts in the table:
    _T_JQ,  # the joints' positions in q (n)
    _T_JV,  # their velocities in v (n)
    _HEADER,
) = range(12)
_FORCE_TASK = 1
# What inverse_dynamics_inputs returns: the sample is finite; it is not, and τ_d
# was (a new NaN event); it is not, nor was τ_d.
_FINITE, _NEW_NAN, _NAN = 0, 1, 2


@kernel
def inverse_dynamics_inputs(inputs, work, state, table):
    """`InverseDynamicsControllerStep.step`'s check and scatter: if the sum of `inputs`
    ([q_ref; v_ref; vdot_ref; q; v (; f_ref; f)]) is not finite, the whole state (the
    outputs) becomes NaN and the result says whether τ_d was finite (`_NEW_NAN`) or not
    (`_NAN`); else q, v of the joints go into x = [q; v] of the model and vdot_ref into
    its v̇ (the other entries stay: nominal positions, zero velocities and
    accelerations, the root's or base's), and the result is `_FINITE`. Copies only."""
    n = table[_N]
    total = 0.0
    for i in range(inputs.shape[0]):
        total += inputs[i]
    if not math.isfinite(total):
        tau_desired = 0.0
        for i in range(n):
            tau_desired += state[i]
        for i in range(state.shape[0]):
            state[i] = math.nan
        return _NEW_NAN if math.isfinite(tau_desired) else _NAN
    nq = table[_NQ]
    vd = table[_W_VDOT]
    jq = table[_T_JQ]
    jv = table[_T_JV]
    for i in range(n):
        work[table[jq + i]] = inputs[3 * n + i]
    for i in range(n):
        work[nq + table[jv + i]] = inputs[4 * n + i]
    for i in range(n):
        work[vd + table[jv + i]] = inputs[2 * n + i]
    return _FINITE


@kernel
def inverse_dynamics_base(orientation, angular_velocity, work, table):
    """A floating base's pose and velocity into x = [q; v] of the model: the
    quaternion `orientation` [w, x, y, z] divided by its norm, at the origin, and
    ω_WB = R_WB ω_B (`angular_velocity` in B) with zero linear velocity. Returns the
    norm; nothing is written unless it is within [0.9, 1.1]. R_WB is Drake's
    RotationMatrix of the quaternion, to the bit (its formula, its sums' order)."""
    w = orientation[0]
    x = orientation[1]
    y = orientation[2]
    z = orientation[3]
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    if not 0.9 <= norm <= 1.1:
        return norm
    w /= norm
    x /= norm
    y /= norm
    z /= norm
    q = table[_BASE_Q]
    work[q] = w
    work[q + 1] = x
    work[q + 2] = y
    work[q + 3] = z
    s = 2.0 / ((x * x + z * z) + (y * y + w * w))
    sx, sy, sz = s * x, s * y, s * z
    swx, swy, swz = sx * w, sy * w, sz * w
    sxx, sxy, sxz = sx * x, sy * x, sz * x
    syy, syz, szz = sy * y, sz * y, sz * z
    ax, ay, az = angular_velocity[0], angular_velocity[1], angular_velocity[2]
    v = table[_NQ] + table[_BASE_V]
    work[v] = (1.0 - syy - szz) * ax + (sxy - swz) * ay + (sxz + swy) * az
    work[v + 1] = (sxy + swz) * ax + (1.0 - sxx - szz) * ay + (syz - swx) * az
    work[v + 2] = (sxz - swy) * ax + (syz + swx) * ay + (1.0 - sxx - syy) * az
    return norm


@kernel
def inverse_dynamics_outputs(G, J, inputs, work, state, table):
    """Eq. 12 and its terms into `state` ((6, n): τ_d, then TORQUE_COMPONENTS'
    order) from G = M v̇ + h of the model (the controlled joints' rows are
    M_j q̈_d + ĥ_j), J the force frame's Jacobian (6, nv; unused without a force
    task), `inputs` and the gains in the work array.

    Elementwise as the numpy code before (bitwise): the errors, the gains, the sums of
    the terms. Reductions: J_jᵀ f_d, J_jᵀ K_f e_f and J_jᵀ e_f, each a loop over the
    6 rows summing in order without fma (numpy's matmul before)."""
    n = table[_N]
    jv = table[_T_JV]
    ks = table[_W_GAINS]
    kd = ks + n
    kf = ks + 2 * n
    # K_s e_q and K_d ė_q.
    for i in range(n):
        state[2 * n + i] = work[ks + i] * (inputs[i] - inputs[3 * n + i])
    for i in range(n):
        state[3 * n + i] = work[kd + i] * (inputs[n + i] - inputs[4 * n + i])
    if not table[_FLAGS] & _FORCE_TASK:
        # Eq. 12 without a force task: τ_d = M_j q̈_d + ĥ_j + K_s e_q + K_d ė_q.
        for i in range(n):
            tau_model = G[table[jv + i]]
            state[i] = (tau_model + state[2 * n + i]) + state[3 * n + i]
            state[n + i] = tau_model
            state[4 * n + i] = 0.0
            state[5 * n + i] = 0.0
        return
    f_ref = 5 * n
    f = 5 * n + 6
    e_f = table[_W_FORCE]
    kf_e_f = e_f + 6
    for r in range(6):
        work[e_f + r] = inputs[f_ref + r] - inputs[f + r]
    for r in range(6):
        work[kf_e_f + r] = work[kf + r] * work[e_f + r]
    for i in range(n):
        c = table[jv + i]
        jt_f_d = 0.0
        for r in range(6):
            jt_f_d += J[r, c] * inputs[f_ref + r]
        jt_kf_e_f = 0.0
        for r in range(6):
            jt_kf_e_f += J[r, c] * work[kf_e_f + r]
        jt_e_f = 0.0
        for r in range(6):
            jt_e_f += J[r, c] * work[e_f + r]
        # M_j q̈_d + ĥ_j − J_jᵀ f_d, −J_jᵀ K_f e_f and −J_jᵀ e_f.
        state[n + i] = G[c] - jt_f_d
        state[4 * n + i] = -jt_kf_e_f
        state[5 * n + i] = -jt_e_f
        # Eq. 12: τ_d = M_j q̈_d + ĥ_j − J_jᵀ (f_d + K_f e_f) + K_s e_q + K_d ė_q.
        state[i] = ((state[n + i] + state[2 * n + i]) + state[3 * n + i]) + state[
            4 * n + i
        ]


class InverseDynamicsControllerStep(Step):
    """Eq. 12 for one sample, outside Drake's systems framework: the per-tick
    arithmetic of InverseDynamicsController (its docstring has the model, the frames,
    the units and the error semantics), written once for it and for a fused
    controller.

    State (the outputs; N·m, n each, config.joints order, zero at construction):
        tau_desired: τ_d of eq. 12.
        tau_feedforward, tau_position_feedback, tau_velocity_feedback,
        tau_force_feedback, tau_force_error: its terms (TORQUE_COMPONENTS order).
    Views on it: `outputs` (6, n), every row above in that order, and `terms` (5, n),
    the TORQUE_COMPONENTS rows (what `DeltaQTorqueControllerStep.step` takes as
    `terms`).

    `step` rewrites the whole state every tick; it reads only `tau_desired` (to
    report a new NaN event): `carried`, what a shell loads before a tick. Its
    workspace is one private context of the (sub-)model and one MultibodyForces, made
    here, with the kernels' work array and index table (`_pack`).

    Per tick: a kernel (`inverse_dynamics_inputs`) checks the inputs and writes them
    into x = [q; v] and v̇ of the model (and `inverse_dynamics_base` the base's pose
    and ω with a floating base); then Drake: one SetPositionsAndVelocities, one
    inverse dynamics with gravity (M_j q̈_d + ĥ_j: the model's root, or the floating
    base, at the proper acceleration −g, no force element; only the plant itself
    welded to the world takes its gravity as force elements, one call more) and, with
    a force task, the Jacobian; then a kernel (`inverse_dynamics_outputs`) writes eq.
    12 and its terms. Pybind calls per tick, the right leg of HRP-2's fixed-base
    model: 2 (3 with a force task); the numpy version had 3 (4), 9 (10) with a
    floating base. A tick allocates only what Drake's Python bindings return (the
    inverse dynamics and, with a force task, the Jacobian).

    Rounding: M_j q̈_d + ĥ_j with gravity as the root's acceleration is Drake's
    inverse dynamics summing other terms (the numpy version applied gravity's
    forces); the force task's J_jᵀ products are sums in the kernel (numpy's matmul
    before); with a floating base, the model's quaternion is the input's over its
    norm (Drake stored its rotation matrix's, converted back). Measured against the
    numpy version on HRP-2's closed loop (2 s, tuned right leg), each tick's inputs
    given to both: τ_d within 3.6e-15 N·m (7e-16 of its largest entry); with a force
    task at the foot, 1.4e-14 (4e-16); floating base, tilted and rotating, with the
    force task, 5e-14 (2e-15). The feedback terms are bitwise (elementwise).
    """

    #: The state arrays that `step` reads (the rest it rewrites every tick).
    carried: tuple[str, ...] = ("tau_desired",)

    def __init__(
        self,
        plant: MultibodyPlant,
        config: InverseDynamicsConfig,
        nominal_positions: np.ndarray | None = None,
    ):
        """
        Args:
            plant, config, nominal_positions: as InverseDynamicsController's (the
                plant must outlive the step; it is never modified).

        Raises:
            ValueError: a bad config, an unfinalized plant, a base that does not
                match config.floating_base, a force frame on the world.
            KeyError: an unknown joint or frame.
        """
        super().__init__()
        config.validate()
        if not plant.is_finalized():
            raise ValueError(f"{_WHERE}: the plant must be finalized")
        self._plant = plant
        self._config = config
        self._indexing = joint_indexing(plant, config.joints)
        n = self._n = self._indexing.size
        self._ks = gain_vector("ks", config.ks, n, "InverseDynamicsConfig")
        self._kd = gain_vector("kd", config.kd, n, "InverseDynamicsConfig")
        self._kf = gain_vector("kf", config.kf, 6, "InverseDynamicsConfig")
        self._base = _find_base(plant, config.floating_base)
        self._force_frame = None
        if config.force_frame:
            self._force_frame = get_frame(plant, config.force_frame, "force frame")
            if self._force_frame.body().index() == plant.world_body().index():
                raise ValueError(
                    f"{_WHERE}: force frame '{config.force_frame}' is on the world"
                )
        self._make_model(nominal_positions)
        self._make_work_arrays()
        self._declare("tau_desired", np.zeros(n))
        for name in TORQUE_COMPONENTS:
            self._declare(name, np.zeros(n))
        self._finalize()
        self._table = self._pack()

    def _make_model(self, nominal_positions: np.ndarray | None) -> None:
        """The model in which eq. 12 is computed (InverseDynamicsController's
        docstring), one private context of it and one MultibodyForces."""
        plant, config = self._plant, self._config
        plant_context = plant.CreateDefaultContext()
        if nominal_positions is not None:
            plant.SetPositions(
                plant_context,
                check_vector(
                    "nominal_positions",
                    nominal_positions,
                    plant.num_positions(),
                    _WHERE,
                ),
            )
        moved = None
        if self._base is None:
            moved = _moved_part(plant, plant_context, config.joints, self._force_frame)
        self._root = None
        if moved is None:
            self._model, self._context = plant, plant_context
            self._model_force_frame = self._force_frame
        else:
            self._model, self._model_force_frame, self._root = moved
            self._context = self._model.CreateDefaultContext()
        model = self._model
        self._forces = MultibodyForces(model)
        self._world = model.world_frame()
        indexing = joint_indexing(model, config.joints)
        self._jq = indexing.q
        self._jv = indexing.v
        # The quaternion floating joint whose proper acceleration −g carries gravity
        # (the part's root's or the floating base's): its first position and
        # velocity; None: the plant welded to the world, whose gravity enters as
        # force elements.
        self._accelerated = None
        if self._root is not None:
            joint = model.GetJointByName(f"{_ROOT}_joint")
            self._accelerated = (joint.position_start(), joint.velocity_start())
        elif self._base is not None:
            if not self._base.has_quaternion_dofs():
                raise ValueError(
                    f"{_WHERE}: the floating base '{self._base.name()}' must have a "
                    "quaternion floating joint (velocities [ω_WB; v_WBo])"
                )
            self._accelerated = (
                self._base.floating_positions_start(),
                self._base.floating_velocities_start_in_v(),
            )
        # Gravity (in ĥ_j) without an accelerated body: the body forces of the
        # model's gravity field when that is its only force element
        # (CalcForceElementsContribution; cheaper than CalcGravityGeneralizedForces),
        # with the joint damping that call adds as generalized forces cleared.
        self._gravity_only = model.num_force_elements() == 1
        self._damped = any(
            np.any(model.get_joint(j).default_damping_vector() != 0.0)
            for j in model.GetJointIndices()
        )
        # A view on the forces' generalized forces (no call to clear them).
        self._generalized_forces = self._forces.mutable_generalized_forces()

    def _make_work_arrays(self) -> None:
        n = self._n
        model = self._model
        nq, nv = model.num_positions(), model.num_velocities()
        self._zero3 = np.zeros(3)
        self._zero6 = np.zeros(6)
        self._identity_quaternion = np.array([1.0, 0.0, 0.0, 0.0])
        # Per tick: the inputs land in the rows of one work array (one sum checks
        # them all for NaN and infinity).
        #: The work array [q_ref; v_ref; vdot_ref; q; v (; f_ref; f)] (`_new_inputs`)
        #: and its rows, `input_rows`: a caller may fill them in place and pass the
        #: rows to `step` (which copies an argument only if it is not its row).
        self.inputs = self._new_inputs()
        self.input_rows: tuple[np.ndarray, ...] = tuple(
            self.inputs[i * n : (i + 1) * n] for i in range(5)
        ) + (
            (self.inputs[5 * n : 5 * n + 6], self.inputs[5 * n + 6 :])
            if self._force_frame is not None
            else ()
        )
        # The kernels' work array: x = [q; v] of the model, its v̇, K_s, K_d, K_f,
        # e_f, K_f e_f.
        sizes = [nq + nv, nv, n, n, 6, 6, 6]
        self._work = np.zeros(sum(sizes))
        self._work_starts = np.cumsum([0, *sizes[:-1]])
        x, vdot, ks, kd, kf, _, _ = np.split(self._work, self._work_starts[1:])
        self._x, self._vdot_full = x, vdot
        self._q_full = x[:nq]
        self._q_full[:] = model.GetPositions(self._context)
        ks[:], kd[:], kf[:] = self._ks, self._kd, self._kf
        self._base_q = self._base_v = 0
        if self._accelerated is not None:
            # At the origin, at rest but for the base's ω (`inverse_dynamics_base`),
            # accelerating upward: −g, in the world.
            self._base_q, self._base_v = self._accelerated
            self._q_full[self._base_q : self._base_q + 7] = [1, 0, 0, 0, 0, 0, 0]
            g_W = model.gravity_field().gravity_vector()
            self._vdot_full[self._base_v + 3 : self._base_v + 6] = -g_W
        self._no_jacobian = np.zeros((6, nv), order="F")  # without a force task

    def _pack(self) -> np.ndarray:
        """The kernels' index table (int64): the header (`_N`..`_T_JV`: sizes, the
        flags, the base's rows, where each part of the work array and of the table
        starts), then the joints' positions and velocities in the model. The state's
        layout is the kernels': tau_desired, then TORQUE_COMPONENTS."""
        n = self._n
        names = [name for name, _ in self.layout()]
        assert names == ["tau_desired", *TORQUE_COMPONENTS]
        assert self.state_size == 6 * n
        header = [
            n,
            self._model.num_positions(),
            self._model.num_velocities(),
            _FORCE_TASK if self._force_frame is not None else 0,
            self._base_q,
            self._base_v,
            *self._work_starts[1:3],
            self._work_starts[5],
            _HEADER,
            _HEADER + n,
        ]
        assert len(header) == _HEADER
        return np.concatenate([header, self._jq, self._jv]).astype(np.int64)

    def warm_up(self) -> None:
        """Compiles (or loads) the kernels for the step's arrays (its inputs and state,
        Drake's inverse dynamics and Jacobian, F-ordered), on copies of the work
        array, the inputs and the state."""
        work, state, inputs = self._work.copy(), self.state.copy(), self.inputs.copy()
        inverse_dynamics_inputs(inputs, work, state, self._table)
        if self._base is not None:
            inverse_dynamics_base(
                self._identity_quaternion, self._zero3, work, self._table
            )
        G = np.zeros(self._model.num_velocities())
        inverse_dynamics_outputs(G, self._no_jacobian, inputs, work, state, self._table)

    def _views_changed(self) -> None:
        n = self._n
        self.outputs = self.state[: 6 * n].reshape(6, n)
        self.terms = self.outputs[1:]

    def _new_inputs(self) -> np.ndarray:
        """A work array for the inputs: [q_ref; v_ref; vdot_ref; q; v] (n each), then
        [f_ref; f] (6 each) with a force task."""
        return np.zeros(5 * self._n + (12 if self._force_frame is not None else 0))

    # ----------------------------------------------------------------- accessors

    def plant(self) -> MultibodyPlant:
        return self._plant

    def config(self) -> InverseDynamicsConfig:
        return self._config

    def joint_names(self) -> tuple[str, ...]:
        return self._indexing.names

    def has_force_task(self) -> bool:
        return self._force_frame is not None

    def has_floating_base(self) -> bool:
        return self._base is not None

    # ----------------------------------------------------------------- per tick

    def step(
        self,
        t: float,
        q_ref: np.ndarray,
        v_ref: np.ndarray,
        vdot_ref: np.ndarray,
        q: np.ndarray,
        v: np.ndarray,
        f_ref: np.ndarray | None = None,
        f: np.ndarray | None = None,
        base_orientation: np.ndarray | None = None,
        base_angular_velocity: np.ndarray | None = None,
    ) -> bool:
        """One tick of eq. 12: the state becomes τ_d and its terms.

        Args:
            t: the time (s); unused (the law is static), for a uniform step call.
            q_ref, v_ref, vdot_ref: q_d (rad), q̇_d (rad/s), q̈_d (rad/s²), n each.
            q, v: q̂ (rad), q̂̇ (rad/s), n each.
            f_ref, f: f_d and f̂ (6 each, [torque; force], N·m and N, force frame),
                with a force task; None: zero. Ignored without a force task.
            base_orientation, base_angular_velocity: with config.floating_base, the
                base's quaternion [w, x, y, z] and ω_WB in the base frame (rad/s);
                None: identity and zero.

        Returns:
            True when this tick's q_ref, v_ref, vdot_ref, q, v, f_ref or f is not
            finite while the previous τ_d was: a new NaN event (the state is then
            all NaN, as after every tick with a non-finite sample; no exception,
            so that the Δq controller falls back to position control). Else False.

        Raises:
            ValueError: a base argument without config.floating_base, a non-finite
                one, or a quaternion whose norm is off by more than 10 %.
        """
        rows = self.input_rows
        for row, value in zip(rows, (q_ref, v_ref, vdot_ref, q, v)):
            if value is not row:
                row[:] = value
        if self._force_frame is not None:
            if f_ref is not rows[5]:
                rows[5][:] = self._zero6 if f_ref is None else f_ref
            if f is not rows[6]:
                rows[6][:] = self._zero6 if f is None else f
        # NaN in, NaN out (the whole state), or the inputs into the model's x, v̇.
        status = inverse_dynamics_inputs(
            self.inputs, self._work, self.state, self._table
        )
        if status != _FINITE:
            return status == _NEW_NAN
        self._set_base(base_orientation, base_angular_velocity)
        self._evaluate(self.inputs, self.state)
        return False

    def _check_base(self, base_orientation, base_angular_velocity):
        if self._base is None:
            raise ValueError(f"{_WHERE}: base arguments need config.floating_base")
        if base_orientation is not None:
            base_orientation = np.ascontiguousarray(
                check_vector("base_orientation", base_orientation, 4, _WHERE)
            )
        if base_angular_velocity is not None:
            base_angular_velocity = np.ascontiguousarray(
                check_vector("base_angular_velocity", base_angular_velocity, 3, _WHERE)
            )
        return base_orientation, base_angular_velocity

    def _set_base(self, base_orientation, base_angular_velocity) -> None:
        """With a floating base, its pose and ω into the model's x (None: identity
        and zero); base arguments without one raise ValueError."""
        if base_orientation is not None or base_angular_velocity is not None:
            base_orientation, base_angular_velocity = self._check_base(
                base_orientation, base_angular_velocity
            )
        if self._base is None:
            return
        wxyz = (
            self._identity_quaternion if base_orientation is None else base_orientation
        )
        w_B = self._zero3 if base_angular_velocity is None else base_angular_velocity
        norm = inverse_dynamics_base(wxyz, w_B, self._work, self._table)
        if not 0.9 <= norm <= 1.1:
            raise ValueError(
                f"{_WHERE}: base_orientation {wxyz} is not a unit quaternion "
                f"(norm {norm:.3g})"
            )

    def _evaluate(self, inputs: np.ndarray, state: np.ndarray) -> None:
        """Eq. 12 of the model's x and v̇ (the inputs already in them) into `state`
        (the step's, or one of its layout), from `inputs` (`_new_inputs`' layout):
        Drake's calls, then `inverse_dynamics_outputs`."""
        model, context, forces = self._model, self._context, self._forces
        model.SetPositionsAndVelocities(context, self._x)
        # M_j q̈_d + ĥ_j: one inverse dynamics with the other accelerations at zero
        # (CalcInverseDynamics returns M v̇ + C v − τ_applied) and gravity.
        if self._accelerated is None:  # gravity's forces applied
            if self._gravity_only:
                model.CalcForceElementsContribution(context, forces)
                if self._damped:
                    self._generalized_forces[:] = 0.0
            else:  # gravity as an applied generalized force, no body forces
                self._generalized_forces[:] = model.CalcGravityGeneralizedForces(
                    context
                )
        G = model.CalcInverseDynamics(context, self._vdot_full, forces)
        J = self._no_jacobian
        if self._model_force_frame is not None:
            frame = self._model_force_frame
            J = model.CalcJacobianSpatialVelocity(
                context, JacobianWrtVariable.kV, frame, self._zero3, self._world, frame
            )
        inverse_dynamics_outputs(G, J, inputs, self._work, state, self._table)

    def _jacobian(self) -> np.ndarray | None:
        """J_j: the force frame F's J_V_WF_F, controlled joints' columns (6, n)."""
        frame = self._model_force_frame
        if frame is None:
            return None
        J = self._model.CalcJacobianSpatialVelocity(
            self._context,
            JacobianWrtVariable.kV,
            frame,
            self._zero3,
            self._world,
            frame,
        )
        return J[:, self._jv]

    # ----------------------------------------------------------------- one sample

    def _fill(self, q_ref, v_ref, vdot_ref, q, v, f_ref, f) -> np.ndarray:
        """A new inputs array of these (checked) values."""
        inputs = self._new_inputs()
        n = self._n
        for i, value in enumerate((q_ref, v_ref, vdot_ref, q, v)):
            inputs[i * n : (i + 1) * n] = value
        if self._force_frame is not None:
            inputs[5 * n : 5 * n + 6] = f_ref
            inputs[5 * n + 6 :] = f
        return inputs

    def joint_space_model(
        self,
        q: np.ndarray,
        v: np.ndarray | None = None,
        base_orientation: np.ndarray | None = None,
        base_angular_velocity: np.ndarray | None = None,
    ) -> JointSpaceModel:
        """InverseDynamicsController.joint_space_model (its docstring)."""
        n = self._n
        q = check_vector("q", q, n, _WHERE)
        v = np.zeros(n) if v is None else check_vector("v", v, n, _WHERE)
        zero = np.zeros(n)
        inputs = self._fill(zero, zero, zero, q, v, self._zero6, self._zero6)
        inverse_dynamics_inputs(inputs, self._work, np.zeros(6 * n), self._table)
        self._set_base(base_orientation, base_angular_velocity)
        plant, context = self._model, self._context
        plant.SetPositionsAndVelocities(context, self._x)
        mass_matrix = plant.CalcMassMatrix(context)[np.ix_(self._jv, self._jv)]
        # h = C(q, v) v − τ_g(q): CalcBiasTerm leaves gravity out.
        h = plant.CalcBiasTerm(context) - plant.CalcGravityGeneralizedForces(context)
        return JointSpaceModel(mass_matrix, h[self._jv], self._jacobian())

    def compute(
        self,
        q_ref: np.ndarray,
        v_ref: np.ndarray,
        vdot_ref: np.ndarray,
        q: np.ndarray,
        v: np.ndarray,
        f_ref: np.ndarray | None = None,
        f: np.ndarray | None = None,
        base_orientation: np.ndarray | None = None,
        base_angular_velocity: np.ndarray | None = None,
    ) -> InverseDynamicsTerms:
        """InverseDynamicsController.compute (its docstring): eq. 12 for one sample,
        checked, in new arrays; the state is left alone."""
        n = self._n
        if self._force_frame is None and (f_ref is not None or f is not None):
            raise ValueError(f"{_WHERE}: f_ref and f need config.force_frame")
        if self._base is None and (
            base_orientation is not None or base_angular_velocity is not None
        ):
            raise ValueError(f"{_WHERE}: base arguments need config.floating_base")
        args = [
            check_vector(name, value, n, _WHERE)
            for name, value in (
                ("q_ref", q_ref),
                ("v_ref", v_ref),
                ("vdot_ref", vdot_ref),
                ("q", q),
                ("v", v),
            )
        ]
        f_ref = (
            self._zero6 if f_ref is None else check_vector("f_ref", f_ref, 6, _WHERE)
        )
        f = self._zero6 if f is None else check_vector("f", f, 6, _WHERE)
        inputs = self._fill(*args, f_ref, f)
        out = np.zeros((6, n))
        inverse_dynamics_inputs(inputs, self._work, out.reshape(-1), self._table)
        self._set_base(base_orientation, base_angular_velocity)
        self._evaluate(inputs, out.reshape(-1))
        return InverseDynamicsTerms(*out)


class InverseDynamicsController(StepSystem):
    """Desired joint torques by inverse dynamics with an optional force task (paper
    eq. 12).

    .. code-block:: text

                                 ┌───────────────────────────┐
        q_ref ──────────────────►│                           ├──► tau_desired
        v_ref ──────────────────►│                           ├──► tau_feedforward
        vdot_ref ───────────────►│                           ├──► tau_position_feedback
        q ──────────────────────►│ InverseDynamicsController ├──► tau_velocity_feedback
        v ──────────────────────►│                           ├──► tau_force_feedback
        f_ref ──────────────────►│  (force task only)        ├──► tau_force_error
        f ──────────────────────►│  (force task only)        │
        base_orientation ───────►│  (floating base only)     │
        base_angular_velocity ──►│  (floating base only)     │
                                 └───────────────────────────┘

    Inputs (n = len(config.joints), every joint vector in config.joints order):
        q_ref, v_ref, vdot_ref (n each): the reference trajectory q_d (rad), q̇_d
            (rad/s), q̈_d (rad/s²).
        q, v (n each): the estimated joint positions q̂ (rad) and velocities q̂̇
            (rad/s) (e.g. Savitzky-Golay estimates of the encoders).
        f_ref, f (6 each, only with config.force_frame): the desired and the
            estimated contact wrench [torque; force] (N·m, N) that the environment
            exerts on the robot, about the origin of the force frame, expressed in
            the force frame. This is the f of eq. 1 (M v̇ + h − Jᵀ f = Sᵀ τ), e.g.
            FloatingBaseTorqueEstimator's external_wrench_<sensor>. An F/T sensor
            reads the wrench that the bodies below it exert on the body above it,
            which is this wrench plus the weight and inertia of the foot (same
            sign): a raw reading can stand in for f when those are negligible.
            Standing on the right foot, f is about +m g along the sole's normal.
        base_orientation (4, only with config.floating_base): the quaternion
            [w, x, y, z] of the base's orientation R_WB in the world (normalized
            here; a norm off by more than 10 % raises). Unconnected: identity.
        base_angular_velocity (3, only with config.floating_base): ω_WB of the base
            (rad/s), expressed in the base frame B (as a gyro on the base reads it).
            Unconnected: zero.

    Outputs (the tick of the inputs held now, direct feedthrough; committed every
    config.period, `hrp2_drake.step.StepSystem`), N·m, n each:
        tau_desired: τ_d of eq. 12.
        tau_feedforward: M_j q̈_d + ĥ_j − J_jᵀ f_d (without a force task, M_j q̈_d
            + ĥ_j).
        tau_position_feedback: K_s e_q.
        tau_velocity_feedback: K_d ė_q.
        tau_force_feedback: −J_jᵀ K_f e_f (zero without a force task).
        tau_force_error: −J_jᵀ e_f (zero without a force task); not part of τ_d.

    The model. Only the controlled joints move: their positions and velocities are
    the q, v inputs, every other position is `nominal_positions` and every other
    velocity is zero, and the accelerations of every other degree of freedom are
    zero. With a fixed base (default, paper footnote 3) M_j, ĥ_j and J_j are then
    exactly those of the fixed-base model; for a chain hanging from the base, such
    as a leg, they do not depend on the other joints at all. The controller computes
    them on a private copy of the part of `plant` that the controlled joints move
    (the bodies outboard of them, every other joint welded at `nominal_positions`,
    hung from a massless root body whose upward acceleration −g stands for gravity;
    e.g. HRP-2's right leg: 6 bodies instead of the robot's 31), which gives the same
    numbers, to rounding, for less work per update (plant itself if a controlled
    joint is neither revolute nor prismatic). With config.floating_base the
    controller keeps one private context of `plant` itself; the base pose is
    (base_orientation, zero position) and its spatial velocity is (ω_WB, zero
    linear velocity); M_j, ĥ_j, J_j are the joint rows and columns of the floating-
    base model, so gravity follows the base's tilt and ĥ_j includes the base's
    angular velocity (neither the base position nor its linear velocity affects
    joint torques, paper Sec. 2.3), but the base acceleration is taken as zero (the
    controller does not know it; gravity enters as the base's upward acceleration
    −g, the same joint rows): eq. 12 as the paper writes it, with the floating
    model's joint block.

    ĥ_j holds the rigid-body terms only (bias and gravity): the model's force
    elements (joint damping, springs) are left out, because friction is the motor
    model's business (eq. 10) and because the torque estimate τ̂ (eq. 2) is a
    rigid-body torque too; Sec. 4.2 needs the same ĥ in both.

    The arithmetic is `InverseDynamicsControllerStep`'s (this system is its shell:
    ports, state groups, the periodic event and the NaN warning).

    Errors: in the periodic update a NaN or infinite sample of q_ref, v_ref, vdot_ref,
    q, v, f_ref or f makes every output NaN (logged once), so that the Δq controller
    falls back to position control instead of the loop stopping; `compute` and the
    base inputs raise ValueError naming the port; an unknown joint or frame name
    raises KeyError; a floating-base plant without
    config.floating_base (or the converse) raises ValueError.
    """

    def __init__(
        self,
        plant: MultibodyPlant,
        config: InverseDynamicsConfig,
        nominal_positions: np.ndarray | None = None,
        lead: float = 0.0,
    ):
        """
        Args:
            plant: a finalized MultibodyPlant of the robot alone: with a fixed base
                (`make_fixed_base_plant`) by default, or with a floating base when
                config.floating_base. It must outlive the controller; it is never
                modified. Its default parameters (masses, inertias, rotor inertias,
                gear ratios) are used.
            config: joints, gains and options (validated here).
            nominal_positions: the plant's position vector (plant.num_positions())
                that sets every position other than the controlled joints' (and the
                floating base's); default: the plant's default positions.
            lead: the samples arrive this long (s) before each multiple of the
                period (`StepSystem`: the commits follow the sampler).
        """
        super().__init__()
        step = InverseDynamicsControllerStep(plant, config, nominal_positions)
        n = len(config.joints)

        # Ports.
        self._q_ref = self.DeclareVectorInputPort("q_ref", n)
        self._v_ref = self.DeclareVectorInputPort("v_ref", n)
        self._vdot_ref = self.DeclareVectorInputPort("vdot_ref", n)
        self._q = self.DeclareVectorInputPort("q", n)
        self._v = self.DeclareVectorInputPort("v", n)
        self._f_ref = self._f = None
        if step.has_force_task():
            self._f_ref = self.DeclareVectorInputPort("f_ref", 6)
            self._f = self.DeclareVectorInputPort("f", 6)
        self._base_orientation = self._base_angular_velocity = None
        if step.has_floating_base():
            self._base_orientation = self.DeclareVectorInputPort("base_orientation", 4)
            self._base_angular_velocity = self.DeclareVectorInputPort(
                "base_angular_velocity", 3
            )
        self._declare_step_state(step)
        for name in ("tau_desired", *TORQUE_COMPONENTS):
            self._declare_step_output(name)
        self._declare_commit(config.period, lead)
        # Per tick, the step's state arrays that it reads (it rewrites the others):
        # the only ones loaded from the context.
        self._tick_loads = [
            (self.step_group(name), step.state[step.rows(name)])
            for name in step.carried
        ]
        ports = [self._q_ref, self._v_ref, self._vdot_ref, self._q, self._v]
        self._sample_ports = ports
        if self._f is not None:
            ports += [self._f_ref, self._f]

    # ----------------------------------------------------------------- accessors

    def plant(self) -> MultibodyPlant:
        return self._step.plant()

    def config(self) -> InverseDynamicsConfig:
        return self._step.config()

    def joint_names(self) -> tuple[str, ...]:
        return self._step.joint_names()

    def has_force_task(self) -> bool:
        return self._step.has_force_task()

    # ----------------------------------------------------------------- computation

    def joint_space_model(
        self,
        q: np.ndarray,
        v: np.ndarray | None = None,
        base_orientation: np.ndarray | None = None,
        base_angular_velocity: np.ndarray | None = None,
    ) -> JointSpaceModel:
        """M_j, ĥ_j and J_j of the controller's model at joint positions q (rad) and
        velocities v (rad/s, default zero); the base arguments as the ports of the
        same names (floating base only). For the gain mapping of Sec. 4.2 and for
        `inverse_dynamics_gains_for_k6`'s joint inertia.
        """
        return self._step.joint_space_model(
            q, v, base_orientation, base_angular_velocity
        )

    def compute(
        self,
        q_ref: np.ndarray,
        v_ref: np.ndarray,
        vdot_ref: np.ndarray,
        q: np.ndarray,
        v: np.ndarray,
        f_ref: np.ndarray | None = None,
        f: np.ndarray | None = None,
        base_orientation: np.ndarray | None = None,
        base_angular_velocity: np.ndarray | None = None,
    ) -> InverseDynamicsTerms:
        """Eq. 12 for one sample, without a Context (same units and frames as the
        ports; f_ref and f default to zero, the base arguments to the identity
        orientation and zero angular velocity).

        Raises:
            ValueError: a wrong size or a non-finite value, naming the argument; f_ref
                or f without a force task, base arguments without a floating base.
        """
        return self._step.compute(
            q_ref,
            v_ref,
            vdot_ref,
            q,
            v,
            f_ref,
            f,
            base_orientation,
            base_angular_velocity,
        )

    def _optional(self, port: InputPort | None, context: Context):
        if port is None or not port.HasValue(context):
            return None
        return port.Eval(context)

    def _tick(self, context: Context, t: float) -> None:
        # The hot path of every control period (scripts/bench.py --only tick).
        f_ref = f = None
        if self._f is not None:
            f_ref, f = self._f_ref.Eval(context), self._f.Eval(context)
        base = (None, None)  # a fixed base has no base inputs
        if self._base_orientation is not None:
            base = (
                self._optional(self._base_orientation, context),
                self._optional(self._base_angular_velocity, context),
            )
        new_nan = self._step.step(
            t,
            self._q_ref.Eval(context),
            self._v_ref.Eval(context),
            self._vdot_ref.Eval(context),
            self._q.Eval(context),
            self._v.Eval(context),
            f_ref,
            f,
            *base,
        )
        if new_nan:
            self._log_nan(context)

    def _log_nan(self, context: Context) -> None:
        # A bad sample must not take the loop down: NaN in, NaN out (the Δq controller
        # downstream then falls back to position control); logged once.
        bad = [
            port.get_name()
            for port in self._sample_ports
            if not math.isfinite(port.Eval(context).sum())
        ]
        _logger.warning(
            "%s %s: input %s not finite at t = %.6g s: outputs NaN",
            _WHERE,
            self.GetSystemPathname(),
            bad,
            context.get_time(),
        )
