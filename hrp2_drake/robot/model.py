"""The HRP-2 model: names, files, and loading models/hrp2 into a MultibodyPlant.

Joint vectors of this project are always in HRP-2 order (`JOINT_NAMES`): right leg
0-5, left leg 6-11, chest 12-13, head 14-15, right arm 16-22, left arm 23-29.
"""

from __future__ import annotations

import gzip
import os
from pathlib import Path

import numpy as np
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import ModelInstanceIndex

from hrp2_drake.multibody import JointIndexing, joint_indexing


def models_dir() -> Path:
    """models/hrp2 of the source tree, or $HRP2_DRAKE_MODELS if set."""
    env = os.environ.get("HRP2_DRAKE_MODELS")
    path = Path(env) if env else Path(__file__).resolve().parents[2] / "models" / "hrp2"
    if not (path / "hrp2.urdf").is_file():
        raise FileNotFoundError(
            f"HRP-2 model not found in {path}: install hrp2_drake in editable mode "
            "(pip install -e .) or set HRP2_DRAKE_MODELS to the models/hrp2 folder"
        )
    return path


URDF_FILE = "hrp2.urdf"
SERVO_FILE = "servo.yaml"
TRAJECTORY_FILE = "climbing32.pos.gz"

JOINT_NAMES: tuple[str, ...] = (
    *(f"RLEG_JOINT{i}" for i in range(6)),
    *(f"LLEG_JOINT{i}" for i in range(6)),
    "CHEST_JOINT0",
    "CHEST_JOINT1",
    "HEAD_JOINT0",
    "HEAD_JOINT1",
    *(f"RARM_JOINT{i}" for i in range(7)),
    *(f"LARM_JOINT{i}" for i in range(7)),
)
NUM_JOINTS = len(JOINT_NAMES)
RIGHT_LEG: tuple[str, ...] = JOINT_NAMES[:6]
#: The paper's names of the right-leg joints (Table 1 order).
RIGHT_LEG_LABELS = ("hip yaw", "hip roll", "hip pitch", "knee", "ankle pitch", "ankle roll")

BASE_BODY = "BODY"  # the waist: the floating base of the model
IMU_BODY = "CHEST_LINK1"
IMU_FRAME = "imu"  # massless link welded to CHEST_LINK1 (the torso)
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
    "right_foot": "RLEG_FOOT",
    "left_foot": "LLEG_FOOT",
    "right_hand": "RARM_HAND",
    "left_hand": "LARM_HAND",
}
SOLE_FRAMES: dict[str, str] = {"right_foot": "r_sole", "left_foot": "l_sole"}
#: Shoulder points (CHEST_LINK1 frame, m) where the hanging strings are tied.
SHOULDERS: dict[str, tuple[float, float, float]] = {
    "right": (0.008, -0.25, 0.181),
    "left": (0.008, 0.25, 0.181),
}


def add_hrp2(plant: MultibodyPlant) -> ModelInstanceIndex:
    """Parses models/hrp2/hrp2.urdf into `plant` (not finalized) and returns it."""
    (instance,) = Parser(plant).AddModels(str(models_dir() / URDF_FILE))
    return instance


def add_hrp2_with_model_error(
    plant: MultibodyPlant, error: float, seed: int = 0
) -> ModelInstanceIndex:
    """HRP-2 with every link's mass and COM scaled by its own random factor in
    [1 - error, 1 + error] (uniform, repeatable by seed; rotational inertias scale with
    the mass): a controller's or estimator's model that is wrong about the robot.
    error = 0 is `add_hrp2`."""
    import xml.etree.ElementTree as ElementTree

    if not 0 <= error < 1:
        raise ValueError(f"add_hrp2_with_model_error: error={error} must be in [0, 1)")
    if error == 0:
        return add_hrp2(plant)
    # Keep the file's `drake:` prefix on the tags Drake reads (gear ratio, rotor).
    ElementTree.register_namespace("drake", "http://drake.mit.edu")
    rng = np.random.default_rng(seed)
    root = ElementTree.fromstring((models_dir() / URDF_FILE).read_text())
    for inertial in root.iter("inertial"):
        mass_scale, com_scale = (float(v) for v in 1.0 + error * rng.uniform(-1.0, 1.0, 2))
        mass = inertial.find("mass")
        mass.set("value", f"{float(mass.get('value')) * mass_scale:.9g}")
        inertia = inertial.find("inertia")
        for key, value in inertia.attrib.items():
            inertia.set(key, f"{float(value) * mass_scale:.9g}")
        origin = inertial.find("origin")
        xyz = [float(v) * com_scale for v in origin.get("xyz").split()]
        origin.set("xyz", " ".join(f"{v:.9g}" for v in xyz))
    perturbed = ElementTree.tostring(root, encoding="unicode")
    (instance,) = Parser(plant).AddModelsFromString(perturbed, "urdf")
    return instance


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
    with gzip.open(models_dir() / TRAJECTORY_FILE, "rt") as stream:
        data = np.loadtxt(stream)
    return data[:, 0], data[:, 1 : 1 + NUM_JOINTS]


def half_sitting() -> np.ndarray:
    """HRP-2's half-sitting pose (rad, 30): the first sample of the climbing motion."""
    return load_trajectory()[1][0].copy()
