"""HRP-2's names, files and model loading, from its robot description
(models/hrp2/robot.yaml), for HRP-2's own experiments and tests: the generic paths
(station, builders, commands) read a `RobotDescription` instead.

Joint vectors of this project are always in HRP-2 order (`JOINT_NAMES`): right leg
0-5, left leg 6-11, chest 12-13, head 14-15, right arm 16-22, left arm 23-29.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import ModelInstanceIndex

from hrp2_drake.description import (
    RobotDescription,
    load_robot_description,
    models_root,
)
from hrp2_drake.estimation import estimator_config as estimation_config
from hrp2_drake.estimation.estimator_config import TorqueEstimatorConfig
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.multibody import JointIndexing, joint_indexing
from hrp2_drake.robot import ground_truth


def models_dir() -> Path:
    """models/hrp2 of the models folder (`description.models_root`: models/ of the
    source tree, or $HRP2_DRAKE_MODELS_ROOT if set)."""
    path = models_root() / "hrp2"
    if not (path / "robot.yaml").is_file():
        raise FileNotFoundError(
            f"HRP-2 model not found in {path}: install hrp2_drake in editable mode "
            "(pip install -e .) or set HRP2_DRAKE_MODELS_ROOT to the models folder"
        )
    return path


def description() -> RobotDescription:
    """HRP-2's robot description (shared, cached: do not modify)."""
    return load_robot_description(models_dir() / "robot.yaml", check=False)


_HRP2 = description()
URDF_FILE = _HRP2.model_file
SERVO_FILE = _HRP2.servo_file

JOINT_NAMES: tuple[str, ...] = tuple(_HRP2.joints)
NUM_JOINTS = len(JOINT_NAMES)
RIGHT_LEG: tuple[str, ...] = tuple(_HRP2.controlled_joints)
#: The paper's names of the right-leg joints (Table 1 order).
RIGHT_LEG_LABELS = tuple(_HRP2.joint_labels)

BASE_BODY = _HRP2.base_body  # the waist: the floating base of the model
IMU_BODY = _HRP2.unknown_wrench_body  # the torso, which carries the IMU
IMU_FRAME = _HRP2.imu_frame  # massless link welded to CHEST_LINK1 (the torso)
#: F/T sensor name -> the fixed joint that splits the end-effector at the sensor.
#: The joint's child link frame is the sensor frame.
FT_SENSORS: dict[str, str] = {
    "right_foot": "RLEG_FT_SENSOR",
    "left_foot": "LLEG_FT_SENSOR",
    "right_hand": "RARM_FT_SENSOR",
    "left_hand": "LARM_FT_SENSOR",
}
#: Body below each F/T sensor (the part whose weight and inertia the sensor sees).
FT_SENSOR_BODIES: dict[str, str] = {
    name: sensor.body for name, sensor in _HRP2.force_torque_sensors.items()
}


def add_hrp2(plant: MultibodyPlant) -> ModelInstanceIndex:
    """Parses models/hrp2/hrp2.urdf into `plant` (not finalized) and returns it."""
    return _HRP2.add_model(plant, weld_base=False)


def add_hrp2_with_model_error(
    plant: MultibodyPlant, error: float, seed: int = 0
) -> ModelInstanceIndex:
    """HRP-2 with every link's mass and COM scaled by its own random factor in
    [1 - error, 1 + error] (`RobotDescription.add_model`). error = 0 is `add_hrp2`."""
    if not 0 <= error < 1:
        raise ValueError(f"add_hrp2_with_model_error: error={error} must be in [0, 1)")
    return _HRP2.add_model(plant, weld_base=False, model_error=error, seed=seed)


def hrp2_joint_indexing(plant: MultibodyPlant) -> JointIndexing:
    """The JointIndexing of the 30 HRP-2 joints in a finalized `plant`.

    Checks that the plant's actuators are in HRP-2 joint order, so that the actuation
    vector is a joint vector.
    """
    indexing = joint_indexing(plant, JOINT_NAMES)
    if not np.array_equal(indexing.u, np.arange(NUM_JOINTS)):
        raise RuntimeError("the plant's actuators are not in HRP-2 joint order")
    return indexing


def load_trajectory() -> tuple[np.ndarray, np.ndarray]:
    """The stair-climbing reference (see ../shared/data/README.md).

    Returns:
        (t, q): times (s), shape (m,), and joint positions (rad), shape (m, 30), in
        HRP-2 joint order.
    """
    return _HRP2.load_trajectory()


def half_sitting() -> np.ndarray:
    """HRP-2's half-sitting pose (rad, 30): the first sample of the climbing motion."""
    return load_trajectory()[1][0].copy()


def estimator_config(window: int = 80, **options) -> TorqueEstimatorConfig:
    """The paper's estimator for HRP-2 (`estimation_config.estimator_config`): 30
    joints, torso IMU, four F/T sensors, and the unknown wrench on the torso (paper
    Sec. 2.4: "we always assume to have an external wrench on the torso"; the hanging
    robot's strings pull there)."""
    return estimation_config.estimator_config(description(), window, **options)


def estimator_plant(add_model=add_hrp2) -> MultibodyPlant:
    """HRP-2 alone with a floating base: the estimator's internal model (`add_model`:
    e.g. a model with errors, `add_hrp2_with_model_error`)."""
    plant = MultibodyPlant(0.0)
    add_model(plant)
    plant.Finalize()
    return plant


def true_motor_model(
    joint_names=RIGHT_LEG, direction: int = 0, servo_file: str = ""
) -> MotorModel:
    """HRP-2's emulated servo's effective Kτ, Kv, Kc: ground truth, for evaluation
    only (`ground_truth.true_motor_model`). `servo_file` as `StationConfig.servo_file`
    (empty: the calibrated servo)."""
    return ground_truth.true_motor_model(
        description(), joint_names, direction, servo_file
    )
