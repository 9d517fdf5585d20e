"""HRP-2 wiring of the robot-agnostic packages: the estimator's names, the estimator's
floating-base model, the identification data collection, and the motor model's
ground truth for evaluation.

This is the only place (with hrp2_drake.robot) that knows HRP-2's names; estimation,
identification and control take them as arguments.
"""

from pydrake.multibody.plant import MultibodyPlant

from hrp2_drake.estimation.torque_estimator import TorqueEstimatorConfig
from hrp2_drake.identification.excitation import CollectionConfig
from hrp2_drake.experiments import ground_truth
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.robot import model


def estimator_config(window: int = 80, **options) -> TorqueEstimatorConfig:
    """The paper's estimator for HRP-2 (`RobotDescription.estimator_config`): 30
    joints, torso IMU, four F/T sensors, and the unknown wrench on the torso (paper
    Sec. 2.4: "we always assume to have an external wrench on the torso"; the hanging
    robot's strings pull there)."""
    return model.description().estimator_config(window, **options)


def estimator_plant(add_model=model.add_hrp2) -> MultibodyPlant:
    """HRP-2 alone with a floating base: the estimator's internal model (`add_model`:
    e.g. a model with errors, `model.add_hrp2_with_model_error`)."""
    plant = MultibodyPlant(0.0)
    add_model(plant)
    plant.Finalize()
    return plant


def right_leg_collection(duration_scale: float = 1.0, seed: int = 0) -> CollectionConfig:
    """HRP-2's identification excitation (models/hrp2/robot.yaml): high-torque pushes
    on the right foot in three leg configurations, then one increasing-amplitude
    sinusoid per right-leg joint; the left leg spread out of the way.
    `duration_scale` shortens everything (e.g. 0.25 for tests)."""
    return model.description().identification.scaled(duration_scale, seed)


def true_motor_model(
    joint_names=model.RIGHT_LEG, direction: int = 0, servo_file: str = ""
) -> MotorModel:
    """HRP-2's emulated servo's effective Kτ, Kv, Kc: ground truth, for evaluation
    only (`ground_truth.true_motor_model`). `servo_file` as `StationConfig.servo_file`
    (empty: the calibrated servo)."""
    return ground_truth.true_motor_model(
        model.description(), joint_names, direction, servo_file
    )
