"""`hrp2-drake balance`'s start-up calibration: the robot calibrated as the authors
calibrated the real HRP-2 (sot-torque-control), never from ground truth (issue 35).

1. **The F/T offsets, the robot lifted.** The simulated robot starts in the station's
   "lowered" scenario: hanging from its strings, its soles a few cm above the ground,
   its servo holding the standing pose. With nothing touching the feet and hands,
   the estimator's offset calibration (`TorqueEstimatorConfig.offset_calibration_time`)
   averages each sensor's filtered reading plus the model's prediction of what the
   bodies below it weigh and accelerate (the compensated wrench S + ΣḢ): that is the
   reading's offset. The sensors' offsets are then frozen.
2. **The CoM offset, the robot put down.** The hoist lowers the robot onto its soles
   and the strings go slack. Standing still, the centre of pressure of the soles'
   measured external wrenches (the F/T sensors' readings, offsets removed) is where
   the true CoM stands; the model's CoM, from the encoders with the soles flat on the
   ground, is where the controller believes it stands: the CoM offset is the first
   minus the second, averaged over `com_window` (horizontal, m). With an exact model
   it measures what is left of the sensors' errors.

The balance runs then start standing with these offsets (the estimator starts with
them: `EstimatorSettings.offsets`) and, with `apply_com_offset`, torque control's
CoM reference moved by the CoM offset (the QP tracks the model's CoM: for the true
CoM to follow the reference, the model's follows the reference minus the offset).

What the simulated sensors' biases are (the description's noise model) is ground
truth: `calibration_error` compares with it for the report only.
"""

import math
from dataclasses import dataclass, field, replace

import numpy as np
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource

from hrp2_drake.config import check_finite
from hrp2_drake.description import RobotDescription
from hrp2_drake.estimation import estimator_config as estimation_config
from hrp2_drake.estimation.estimation_chain import add_estimator
from hrp2_drake.robot.station import (
    LoweringConfig,
    StationConfig,
    initial_joint_positions,
    make_station,
)
from hrp2_drake.simulation import add_loggers, logs_to_arrays, run_with_progress

_WHERE = "BalanceExperimentConfig.calibration"
#: The start of the offsets' average (s): the filters' windows filled.
OFFSET_START = 0.2


@dataclass
class CalibrationSettings:
    """The start-up calibration (module docstring).

    Args:
        enabled: calibrate before the runs; False: the F/T offsets zero and no CoM
            offset (the robot started on the ground, uncalibrated).
        offset_time: how long each F/T offset is averaged with the feet free (s,
            from 0.2 s; it must end before the hoist starts lowering).
        lowering: the hoist of the "lowered" scenario.
        com_window: [start, end] (s) of the CoM offset's average, the robot
            standing still on its soles (after the hoist is done).
        apply_com_offset: move torque control's CoM reference by the CoM offset.
    """

    enabled: bool = True
    offset_time: float = 0.5
    lowering: LoweringConfig = field(default_factory=LoweringConfig)
    com_window: list[float] = field(default_factory=lambda: [2.5, 3.0])
    apply_com_offset: bool = True

    def validate(self) -> None:
        check_finite(self.offset_time, f"{_WHERE}.offset_time", 0.0)
        if OFFSET_START + self.offset_time > self.lowering.start:
            raise ValueError(
                f"{_WHERE}.offset_time: the offsets' average ({OFFSET_START} s + "
                f"{self.offset_time} s) must end before the hoist lowers the robot "
                f"(lowering.start {self.lowering.start} s)"
            )
        window = self.com_window
        done = self.lowering.start + self.lowering.duration
        if (
            len(window) != 2
            or not all(math.isfinite(t) for t in window)
            or not done <= window[0] < window[1]
        ):
            raise ValueError(
                f"{_WHERE}.com_window: [start, end] (s) after the hoist is done "
                f"({done:g} s), start < end; got {window}"
            )


def calibrate(
    station: StationConfig, window: int, settings: CalibrationSettings
) -> dict:
    """The calibration run (module docstring) of the robot of `station` (its
    standing pose held by its servo), the estimator's filters `window` samples long.

    Returns:
        {"ft_offsets": {sensor: [torque; force] (N·m, N, sensor frame)},
        "com_offset_m": [x, y] (world), "calibration_error": the offsets against
        the simulated sensors' biases (ground truth, for the report)}.
    """
    robot = station.description()
    lowered = replace(station, scenario="lowered", lowering=settings.lowering)
    q0 = initial_joint_positions(station)
    period = lowered.sensors_config().period
    builder = DiagramBuilder()
    robot_station = builder.AddNamedSystem("station", make_station(lowered))
    hold = builder.AddNamedSystem("hold", ConstantVectorSource(q0))
    builder.Connect(hold.get_output_port(), robot_station.GetInputPort("q_cmd"))
    config = estimation_config.estimator_config(
        robot,
        window,
        offset_calibration_time=settings.offset_time,
        offset_calibration_start=OFFSET_START,
        period=period,
    )
    chain = add_estimator(
        builder,
        robot_station,
        robot.make_plant(),
        config,
        lead=lowered.sample_lead_steps() * lowered.time_step,
    )
    # Every sample (the IMU's noise averages out over them).
    ports = {"q": chain.encoder_filter.GetOutputPort("value")}
    for name in robot.sensor_names():
        ports[name] = chain.estimator.GetOutputPort(f"external_wrench_{name}")
    if robot.has_imu():
        for name in ("imu_linear_acceleration", "imu_angular_velocity"):
            ports[name] = robot_station.GetOutputPort(name)
    loggers = add_loggers(builder, ports, period)
    simulator = Simulator(builder.Build())
    end = settings.com_window[1]
    run_with_progress(simulator, end, "calibration: lifted, then put down", steps=2)
    context = simulator.get_context()
    estimator_context = chain.estimator.GetMyContextFromRoot(context)
    offsets = chain.estimator.offsets(estimator_context)
    logs = logs_to_arrays(loggers, context)
    rows = (logs["t"] >= settings.com_window[0]) & (logs["t"] <= end)
    com_offset = _com_offset(robot, logs, rows)
    imu_offset = []
    if robot.has_imu():
        imu_offset = _imu_offset(robot, logs, rows, logs["q"][rows].mean(axis=0))
    ft_offsets = {
        name: offsets[k].tolist() for k, name in enumerate(robot.sensor_names())
    }
    return {
        "ft_offsets": ft_offsets,
        "imu_offset": imu_offset,
        "com_offset_m": com_offset.tolist(),
        "calibration_error": calibration_error(lowered, ft_offsets, imu_offset),
    }


def _posed(robot: RobotDescription, plant, context, q: np.ndarray) -> None:
    """The model posed by the encoders `q`, its first sole flat at the origin."""
    for name, angle in zip(robot.joints, q):
        plant.GetJointByName(name).set_angle(context, angle)
    base = plant.GetBodyByName(robot.base_body)
    sole = plant.GetFrameByName(next(iter(robot.contacts.soles)))
    plant.SetFreeBodyPose(context, base, RigidTransform())
    X_BS = sole.CalcPoseInWorld(context)  # the base at the origin: X_BS
    plant.SetFreeBodyPose(context, base, X_BS.inverse())


def _com_offset(robot: RobotDescription, logs: dict, rows: np.ndarray) -> np.ndarray:
    """The mean over `rows` of the measured CoP minus the model's CoM (x, y, m): the
    CoP of every F/T sensor's external wrench on the soles' plane, the model posed
    by the encoders (`_posed`)."""
    plant = robot.make_plant()
    context = plant.CreateDefaultContext()
    frames = {
        name: plant.GetFrameByName(s.frame)
        for name, s in robot.force_torque_sensors.items()
    }
    out = []
    for k in np.nonzero(rows)[0]:
        _posed(robot, plant, context, logs["q"][k])
        force, moment = np.zeros(3), np.zeros(3)
        for name, frame in frames.items():
            X_WF = frame.CalcPoseInWorld(context)
            R, p = X_WF.rotation().matrix(), X_WF.translation()
            wrench = logs[name][k]
            f = R @ wrench[3:]
            force += f
            moment += R @ wrench[:3] + np.cross(p, f)
        cop = np.array([-moment[1], moment[0]]) / force[2]
        com = plant.CalcCenterOfMassPositionInWorld(context)[:2]
        out.append(cop - com)
    return np.mean(out, axis=0)


def _imu_offset(
    robot: RobotDescription, readings: dict, rows: np.ndarray, q: np.ndarray
) -> list[float]:
    """The IMU's offsets [accelerometer; gyroscope] (m/s², rad/s, its frame), the
    robot standing still over `rows` (the encoders' mean `q`): as the authors found
    them, the gyro's mean reading, and the accelerometer's mean reading minus what
    it reads standing still, gravity in its frame (here from the model posed by
    the encoders, `_posed`, rather than assumed upright)."""
    plant = robot.make_plant()
    context = plant.CreateDefaultContext()
    _posed(robot, plant, context, q)
    R_WI = plant.GetFrameByName(robot.imu_frame).CalcPoseInWorld(context).rotation()
    still = R_WI.inverse() @ -plant.gravity_field().gravity_vector()
    acc = readings["imu_linear_acceleration"][rows].mean(axis=0) - still
    gyro = readings["imu_angular_velocity"][rows].mean(axis=0)
    return [float(v) for v in (*acc, *gyro)]


def calibration_error(
    station: StationConfig, ft_offsets: dict, imu_offset: list[float]
) -> dict:
    """Each F/T sensor's largest torque and force error of its offset against the
    simulated sensor's bias (ground truth: for the report only), N·m and N; the
    IMU's ("imu": the accelerometer's, m/s², and the gyro's, rad/s)."""
    sensors = station.sensors_config()
    out = {}
    if imu_offset:
        acc = np.abs(
            np.asarray(imu_offset[:3]) - sensors.accelerometer.vectors(3, "")[1]
        )
        gyro = np.abs(np.asarray(imu_offset[3:]) - sensors.gyroscope.vectors(3, "")[1])
        out["imu"] = {
            "accelerometer_error": float(acc.max()),
            "gyroscope_error": float(gyro.max()),
        }
    for name, offset in ft_offsets.items():
        _, bias = sensors.force_torque_noise(name).vectors(6, name)
        error = np.abs(np.asarray(offset) - bias)
        out[name] = {
            "bias": bias.tolist(),
            "torque_error_Nm": float(error[:3].max()),
            "force_error_N": float(error[3:].max()),
        }
    return out
