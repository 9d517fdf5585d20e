"""HRP-2 wiring of the robot-agnostic packages: the estimator's names, the estimator's
floating-base model, the identification data collection, and the motor model's
ground truth for evaluation.

This is the only place (with hrp2_drake.robot) that knows HRP-2's names; estimation,
identification and control take them as arguments.
"""

from pydrake.multibody.plant import MultibodyPlant

from hrp2_drake.estimation.torque_estimator import (
    ForceTorqueSensorConfig,
    TorqueEstimatorConfig,
)
from hrp2_drake.identification.excitation import (
    CollectionConfig,
    PushConfig,
    SinusoidConfig,
)
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.robot import model


def estimator_config(window: int = 80, **options) -> TorqueEstimatorConfig:
    """The paper's estimator for HRP-2: 30 joints, torso IMU, four F/T sensors, and
    the unknown wrench on the torso (paper Sec. 2.4: "we always assume to have an
    external wrench on the torso"; the hanging robot's strings pull there)."""
    options.setdefault("unknown_wrench_body", model.IMU_BODY)
    sensors = {
        name: ForceTorqueSensorConfig(frame=model.FT_SENSOR_BODIES[name])
        for name in model.FT_SENSORS
    }
    return TorqueEstimatorConfig(
        joints=list(model.JOINT_NAMES),
        imu_frame=model.IMU_FRAME,
        sensors=sensors,
        window=window,
        **options,
    )


def estimator_plant(add_model=model.add_hrp2) -> MultibodyPlant:
    """HRP-2 alone with a floating base: the estimator's internal model (`add_model`:
    e.g. a model with errors, `model.add_hrp2_with_model_error`)."""
    plant = MultibodyPlant(0.0)
    add_model(plant)
    plant.Finalize()
    return plant


# Peak right-leg velocities of the climbing motion (rad/s) are 0, 0.61, 1.93, 3.91,
# 2.45, 0.61: the sinusoids reach 1.2x that, and at least 2 rad/s, so that the model is
# identified on the whole operating range (paper Sec. 3.4) and the friction offsets
# (Coulomb, dead zone), which a model without intercept folds into Kv, weigh little.
_SINUSOIDS = (
    # joint, centre offset, final amplitude (rad), peak velocity (rad/s)
    ("RLEG_JOINT0", 0.0, 0.35, 2.0),
    ("RLEG_JOINT1", -0.1, 0.2, 2.0),  # centred outward: the feet must not touch
    ("RLEG_JOINT2", 0.0, 0.5, 2.3),
    ("RLEG_JOINT3", 0.0, 0.7, 4.7),
    ("RLEG_JOINT4", 0.0, 0.6, 2.9),
    ("RLEG_JOINT5", 0.0, 0.25, 2.0),
)


def right_leg_collection(duration_scale: float = 1.0, seed: int = 0) -> CollectionConfig:
    """High-torque pushes on the right foot in three leg configurations, then one
    increasing-amplitude sinusoid per right-leg joint; the left leg spread out of the
    way. `duration_scale` shortens everything (e.g. 0.25 for tests)."""
    leg = model.RIGHT_LEG
    extra_ramps = round(8 * duration_scale)
    return CollectionConfig(
        nominal_offsets={"LLEG_JOINT1": 0.25},
        pushes=PushConfig(
            body=model.FT_SENSOR_BODIES["right_foot"],
            point=[0.015, 0.0, -0.02],  # the middle of the sole
            configurations=[
                {},
                {leg[2]: -0.4, leg[3]: 0.6, leg[4]: -0.2},  # hip flexed, knee bent
                {leg[2]: 0.3, leg[3]: -0.6, leg[4]: 0.3},  # leg almost straight
            ],
            max_force=150.0,
            max_torque=40.0,
            extra_ramps=extra_ramps,
            seed=seed,
        ),
        sinusoids=[
            SinusoidConfig(
                joint=name,
                center_offset=center,
                amplitude_end=amplitude,
                peak_velocity=velocity,
                duration=max(2.0, 8.0 * duration_scale),
            )
            for name, center, amplitude, velocity in _SINUSOIDS
        ],
    )


def true_motor_model(
    joint_names=model.RIGHT_LEG, direction: int = 0, servo_file: str = ""
) -> MotorModel:
    """The emulated servo's effective Kτ, Kv, Kc: ground truth, for evaluation only.
    `servo_file` as `StationConfig.servo_file` (empty: the calibrated servo)."""
    from hrp2_drake.robot.servo import effective_motor_parameters, load_servo_params

    eff = effective_motor_parameters(load_servo_params(servo_file or None), joint_names, direction)
    return MotorModel(list(joint_names), eff["k_tau"], eff["k_v"], eff["k_c"])
