"""Robot-agnostic helpers on a MultibodyPlant: joint indexing, name look-ups and
the floating base.

Every package of hrp2_drake (robot, estimation, control, identification) addresses
joints by name through these helpers, so nothing depends on Drake's internal ordering
of positions and velocities (which, for a floating base, is not the URDF order).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import (
    BodyIndex,
    Frame,
    JointIndex,
    PrismaticJoint,
    RevoluteJoint,
    RigidBody,
    WeldJoint,
)
from pydrake.systems.framework import Context, InputPort


@dataclass(frozen=True)
class JointIndexing:
    """Where a list of one-dof joints lives in a plant's vectors.

    Attributes:
        names: the joint names, in the order of every joint vector of this project.
        q: index of each joint in the plant's position vector q.
        v: index of each joint in the plant's velocity vector v.
        u: index of each joint's actuator in the plant's actuation vector, or -1.
    """

    names: tuple[str, ...]
    q: np.ndarray
    v: np.ndarray
    u: np.ndarray

    @property
    def size(self) -> int:
        return len(self.names)

    def positions(self, plant_q: np.ndarray) -> np.ndarray:
        return plant_q[self.q]

    def subset(self, names: Sequence[str]) -> JointIndexing:
        """The indexing of `names`, which must be among these joints."""
        rows = [self.index_of(n) for n in names]
        return JointIndexing(tuple(names), self.q[rows], self.v[rows], self.u[rows])

    def index_of(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(
                f"joint '{name}' is not among the {self.size} joints "
                f"({', '.join(self.names[:4])}, ...)"
            ) from None


def joint_indexing(plant: MultibodyPlant, names: Sequence[str]) -> JointIndexing:
    """Builds the JointIndexing of one-dof joints `names` in a finalized `plant`.

    Raises:
        KeyError: a name is not a joint of the plant.
        ValueError: a joint has more or less than one degree of freedom.
    """
    actuator_of: dict[JointIndex, int] = {}
    for index in plant.GetJointActuatorIndices():
        actuator = plant.get_joint_actuator(index)
        actuator_of[actuator.joint().index()] = actuator.input_start()
    q, v, u = [], [], []
    for name in names:
        if not plant.HasJointNamed(name):
            raise KeyError(f"the plant has no joint named '{name}'")
        joint = plant.GetJointByName(name)
        if joint.num_positions() != 1 or joint.num_velocities() != 1:
            raise ValueError(
                f"joint '{name}' has {joint.num_positions()} positions: "
                "only one-dof joints are supported"
            )
        q.append(joint.position_start())
        v.append(joint.velocity_start())
        u.append(actuator_of.get(joint.index(), -1))
    return JointIndexing(tuple(names), np.array(q), np.array(v), np.array(u))


def get_frame(plant: MultibodyPlant, name: str, what: str = "frame") -> Frame:
    """The frame `name` of `plant` (a body's frame or any named frame).

    Raises:
        KeyError: with the `what` role in the message (e.g. "IMU frame").
    """
    if plant.HasFrameNamed(name):
        return plant.GetFrameByName(name)
    if plant.HasBodyNamed(name):
        return plant.GetBodyByName(name).body_frame()
    raise KeyError(f"{what} '{name}' is not a frame or body of the plant")


def check_vector(name: str, value: np.ndarray, size: int, where: str) -> np.ndarray:
    """Raises ValueError if `value` is not a finite vector of `size` entries."""
    value = np.asarray(value, dtype=float)
    if value.shape != (size,):
        raise ValueError(
            f"{where}: '{name}' has shape {value.shape}, expected ({size},)"
        )
    bad = np.flatnonzero(~np.isfinite(value))
    if bad.size:
        raise ValueError(f"{where}: '{name}' is not finite at entries {bad.tolist()}")
    return value


def check_joint_names(names: Sequence[str], where: str) -> None:
    """Raises ValueError if `names` is empty or repeats a joint."""
    if not names:
        raise ValueError(f"{where}.joints is empty")
    duplicates = sorted({j for j in names if list(names).count(j) > 1})
    if duplicates:
        raise ValueError(f"{where}.joints: duplicated joints {duplicates}")


def eval_finite(port: InputPort, context: Context, where: str) -> np.ndarray:
    """The value of a vector input port; ValueError naming the port, the time and the
    entries if it is not finite (a NaN from a sensor must not reach a controller)."""
    value = port.Eval(context)
    if not math.isfinite(value.sum()):
        bad = np.flatnonzero(~np.isfinite(value))
        raise ValueError(
            f"{where}: input port '{port.get_name()}' is not finite at "
            f"t = {context.get_time():.6g} s, at indices {bad.tolist()}"
        )
    return value


def floating_base(
    plant: MultibodyPlant, where: str, quaternion: bool = False, advice: str = ""
) -> RigidBody:
    """The one floating base body of `plant` (finalized): the one look-up of the
    estimator, inverse dynamics, the base from the soles and the balance QP.

    Raises ValueError naming `where` unless the plant has exactly one floating base
    body and, if `quaternion`, its floating joint has quaternion positions
    ([w, x, y, z, p]; velocities [ω_WB; v_WBo] in the world). `advice` ends the
    message (what the caller can change)."""
    bases = sorted(int(b) for b in plant.GetFloatingBaseBodies())
    if len(bases) != 1:
        names = [plant.get_body(BodyIndex(b)).name() for b in bases]
        raise ValueError(
            f"{where}: the plant needs exactly one floating base body, it has "
            f"{names or 'none (a fixed base)'}" + (f": {advice}" if advice else "")
        )
    base = plant.get_body(BodyIndex(bases[0]))
    if quaternion and not base.has_quaternion_dofs():
        raise ValueError(
            f"{where}: the floating base '{base.name()}' needs a quaternion floating "
            "joint (velocities [ω_WB; v_WBo] in the world)"
        )
    return base


def tree_joints(plant: MultibodyPlant, root, through_world: bool = False) -> dict:
    """{body index: (parent body index, the joint that holds it)} of every body of the
    tree rooted at the body `root` (a BodyIndex), breadth first (a parent comes before
    its children). Joints to the world are skipped unless `through_world` (e.g. to
    root the tree at the world itself)."""
    world = int(plant.world_body().index())
    links: dict[int, list] = {}
    for j in plant.GetJointIndices():
        joint = plant.get_joint(j)
        a, b = int(joint.parent_body().index()), int(joint.child_body().index())
        if world in (a, b) and not through_world:
            continue
        links.setdefault(a, []).append((b, joint))
        links.setdefault(b, []).append((a, joint))
    holder: dict[int, tuple] = {}
    queue, seen = [int(root)], {int(root)}
    while queue:
        a = queue.pop(0)
        for b, joint in links.get(a, []):
            if b not in seen:
                seen.add(b)
                holder[b] = (a, joint)
                queue.append(b)
    return holder


def tree_parents(plant: MultibodyPlant, base) -> dict[int, int]:
    """Parent body index of every body of the tree rooted at the body `base` (a
    BodyIndex), through the joints between bodies (those to the world, floating or
    welds, ignored); -1 for the base."""
    return {int(base): -1} | {b: a for b, (a, _) in tree_joints(plant, base).items()}


def is_strictly_below(parent: dict[int, int], body: int, ancestor: int) -> bool:
    """Whether `body` lies in the subtree of `ancestor`, `ancestor` excluded
    (`parent`: a `tree_parents` map)."""
    b = parent.get(body, -1)
    while b != -1:
        if b == ancestor:
            return True
        b = parent.get(b, -1)
    return False


def copy_joint(
    model: MultibodyPlant,
    plant: MultibodyPlant,
    context: Context,
    joint,
    frame_on_parent: Frame,
    frame_on_child: Frame,
    forward: bool,
):
    """Adds to `model` (not finalized) a copy of `plant`'s revolute, prismatic or weld
    `joint` between the model's frames `frame_on_parent` (inboard) and
    `frame_on_child`, and a copy of its actuator (rotor inertia and gear ratio in
    `context`). A joint turned around (`forward` False: its child is inboard in
    `model`) keeps its q and its generalized force with the opposite axis, a weld its
    inverse pose. Returns the copy.

    Raises:
        ValueError: another kind of joint, naming it.
    """
    sign = 1.0 if forward else -1.0
    kind = joint.type_name()
    F, M = frame_on_parent, frame_on_child
    if kind == "revolute":
        copy = RevoluteJoint(joint.name(), F, M, sign * joint.revolute_axis())
    elif kind == "prismatic":
        copy = PrismaticJoint(joint.name(), F, M, sign * joint.translation_axis())
    elif kind == "weld":
        copy = WeldJoint(
            joint.name(), F, M, joint.X_FM() if forward else joint.X_FM().inverse()
        )
    else:
        raise ValueError(
            f"joint '{joint.name()}' is a {kind} joint; only revolute, prismatic and "
            "weld joints are supported"
        )
    copy = model.AddJoint(copy)
    for index in plant.GetJointActuatorIndices():
        actuator = plant.get_joint_actuator(index)
        if actuator.joint().index() == joint.index():
            added = model.AddJointActuator(
                actuator.name(), copy, actuator.effort_limit()
            )
            added.set_default_rotor_inertia(actuator.rotor_inertia(context))
            added.set_default_gear_ratio(actuator.gear_ratio(context))
    return copy
