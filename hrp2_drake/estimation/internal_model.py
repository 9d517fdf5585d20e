"""The estimator's internal model of a robot (`torque_estimator`'s module docstring):
a copy of the plant's bodies, frames, joints and actuators re-rooted at a massless
body welded to the IMU frame (or to a fixed base's frame without IMU), with a massless
mount and a 6-dof joint above each F/T sensor's body, and no gravity.
"""

from dataclasses import dataclass

import numpy as np
from pydrake.math import RigidTransform
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import (
    BodyIndex,
    FixedOffsetFrame,
    FrameIndex,
    ModelInstanceIndex,
    QuaternionFloatingJoint,
    RigidBody,
    SpatialInertia,
    WeldJoint,
)
from pydrake.systems.framework import Context

from hrp2_drake.multibody import copy_joint, tree_joints

#: The estimator's error messages start with the system's name.
WHERE = "FloatingBaseTorqueEstimator"
ROOT = "torque_estimator_imu_root"  # the internal model's floating body


@dataclass
class ModelSensor:
    """An F/T sensor as the estimator finds it on the plant, and its parts in the
    internal model (`internal_model` fills them)."""

    name: str
    frame: object  # the sensor Frame S (of the user's plant)
    body: RigidBody  # the body right below the sensor, B (of the user's plant)
    X_BS: RigidTransform
    bodies: list[int]  # BodyIndex of every body below the sensor (B's subtree)
    port: object = None
    # In the internal model (see internal_model):
    model_body: RigidBody | None = None  # B
    model_frame: object = None  # S, on B
    p_BoSo_S: np.ndarray | None = None  # where external wrenches are applied
    joint: object = None  # the 6-dof joint above B
    rows: np.ndarray | None = None  # its 6 velocities


def internal_model(
    plant: MultibodyPlant,
    context: Context,
    root_frame: object,
    sensors: list[ModelSensor],
) -> tuple[MultibodyPlant, dict[int, object]]:
    """The estimator's internal model of `plant` (torque_estimator's docstring): its
    bodies (with their inertias in `context`), frames, joints and actuators (rotor
    inertias and gear ratios in `context`), without geometry, force elements or
    gravity, with
    - a massless floating root body welded to `root_frame` (the IMU frame, or the
      fixed base's frame without IMU), every joint of the robot's tree oriented away
      from it (a revolute or prismatic joint turned around keeps its q and generalized
      force with the opposite axis, a weld its inverse pose); the joints to the world
      (the base's floating joint or weld) are left out, and the bodies out of the
      robot's tree (none for a model of the robot alone) are welded to the world;
    - above each F/T sensor's body B, a massless "mount" body at B's place on the
      joint that holds B, and a 6-dof joint (QuaternionFloatingJoint) from a frame S on
      the mount to the frame S on B. At the identity (kept for ever, at rest) the model
      moves as `plant` does; the joint's generalized forces in an inverse dynamics are
      the wrench [torque about So; force] in S that the mount applies to B's subtree.

    Fills each sensor's model_* fields and rows. Returns the model (finalized) and the
    model's copy of every frame of `plant` by frame index.

    Raises:
        ValueError: a joint of `plant` that is neither revolute, prismatic nor weld
            (nor the floating joint of the base).
    """
    model, frames = _copy_bodies_and_frames(plant, context)
    # The tree rooted at the IMU's body, and the joint that holds each body.
    holder = tree_joints(plant, root_frame.body().index())
    root_instance = _add_root(model, plant, root_frame, frames, set(holder))
    by_body = {int(sensor.body.index()): sensor for sensor in sensors}
    for child, (_, joint) in sorted(holder.items()):
        forward = int(joint.child_body().index()) == child
        on_parent, on_child = (
            (joint.frame_on_parent(), joint.frame_on_child())
            if forward
            else (joint.frame_on_child(), joint.frame_on_parent())
        )
        F = frames[int(on_parent.index())]
        M = frames[int(on_child.index())]
        sensor = by_body.get(child)
        if sensor is not None:
            M = _mount_sensor(model, sensor, child, on_child, root_instance)
        try:
            copy_joint(model, plant, context, joint, F, M, forward)
        except ValueError as error:
            raise ValueError(f"{WHERE}: {error} (besides the floating base)") from None
    model.Finalize()
    for sensor in sensors:
        # QuaternionFloatingJoint velocities: [ω_FM; v_FM] in F (= S at the identity).
        sensor.rows = sensor.joint.velocity_start() + np.arange(6)
    return model, frames


def _copy_bodies_and_frames(
    plant: MultibodyPlant, context: Context
) -> tuple[MultibodyPlant, dict[int, object]]:
    """The internal model's first step: a plant without gravity holding `plant`'s model
    instances, bodies (inertias in `context`) and frames (the ephemeral ones left
    out). Returns it (not finalized) and its copy of each frame by `plant`'s frame
    index."""
    model = MultibodyPlant(0.0)
    model.mutable_gravity_field().set_gravity_vector(np.zeros(3))
    for i in range(2, plant.num_model_instances()):  # 0: world, 1: default
        model.AddModelInstance(plant.GetModelInstanceName(ModelInstanceIndex(i)))
    for i in range(1, plant.num_bodies()):
        body = plant.get_body(BodyIndex(i))
        model.AddRigidBody(
            body.name(),
            body.model_instance(),
            body.CalcSpatialInertiaInBodyFrame(context),
        )
    frames: dict[int, object] = {}
    for i in range(plant.num_frames()):
        frame = plant.get_frame(FrameIndex(i))
        if frame.is_ephemeral():
            continue  # e.g. the frames of the base's floating joint, rebuilt by Drake
        body_frame = model.get_body(frame.body().index()).body_frame()
        frames[i] = (
            body_frame
            if frame.is_body_frame()
            else model.AddFrame(
                FixedOffsetFrame(
                    frame.name(),
                    body_frame,
                    frame.GetFixedPoseInBodyFrame(),
                    frame.model_instance(),
                )
            )
        )
    return model, frames


def _add_root(
    model: MultibodyPlant,
    plant: MultibodyPlant,
    root_frame: object,
    frames: dict[int, object],
    held: set[int],
) -> ModelInstanceIndex:
    """Adds the internal model's massless floating root body, welded to the copy of
    `root_frame`, and welds to the world the bodies out of the robot's tree (neither
    the root frame's body nor one of `held`, the bodies a joint of the tree holds).
    Returns the root's model instance."""
    in_tree = held | {int(root_frame.body().index())}
    root_instance = model.AddModelInstance(ROOT)
    root = model.AddRigidBody(ROOT, root_instance, SpatialInertia.Zero())
    model.AddJoint(
        WeldJoint(
            f"{ROOT}_weld",
            root.body_frame(),
            frames[int(root_frame.index())],
            RigidTransform(),
        )
    )
    for i in range(1, plant.num_bodies()):
        if i not in in_tree:  # not the robot's: keep it out of the model's dofs
            model.WeldFrames(
                model.world_frame(), model.get_body(BodyIndex(i)).body_frame()
            )
    return root_instance


def _mount_sensor(
    model: MultibodyPlant,
    sensor: ModelSensor,
    child: int,
    on_child: object,
    root_instance: ModelInstanceIndex,
) -> object:
    """Hangs body B (index `child`) below F/T sensor `sensor`: a massless mount at B's
    place and a 6-dof joint from the frame S on the mount to the frame S on B. Fills
    the sensor's model_body, model_frame, joint and p_BoSo_S. Returns the mount's frame
    that the joint holding B attaches to (at `on_child`'s pose)."""
    B = model.get_body(BodyIndex(child))
    mount = model.AddRigidBody(
        f"{sensor.name}_ft_sensor_mount", root_instance, SpatialInertia.Zero()
    )
    M = model.AddFrame(
        FixedOffsetFrame(
            f"{sensor.name}_ft_sensor_mount_joint",
            mount.body_frame(),
            on_child.GetFixedPoseInBodyFrame(),
        )
    )
    sensor.model_body = B
    sensor.model_frame = model.AddFrame(
        FixedOffsetFrame(
            f"{sensor.name}_ft_sensor",
            B.body_frame(),
            sensor.X_BS,
            root_instance,
        )
    )
    S_mount = model.AddFrame(
        FixedOffsetFrame(
            f"{sensor.name}_ft_sensor_on_mount",
            mount.body_frame(),
            sensor.X_BS,
        )
    )
    sensor.joint = model.AddJoint(
        QuaternionFloatingJoint(
            f"{sensor.name}_ft_sensor_joint", S_mount, sensor.model_frame
        )
    )
    R_BS = sensor.X_BS.rotation().matrix()
    sensor.p_BoSo_S = R_BS.T @ sensor.X_BS.translation()
    return M


# --------------------------------------------------------------------- the chain
