"""The robot's LCM channels: its sensors and its position command as LCM messages,
with the simulated station's port names, so that the controller does not change
between simulation and hardware (the LCM iiwa driver next to `SimIiwaDriver` in
Drake). Two sides of the same channels: the controller's loop
(`hardware.lcm_link.LcmLink`) and the robot's bridge
(`hardware.robot_bridge.RobotBridge`, `hrp2-drake sim-robot`, the reference for a real
robot's bridge). Which rows of the
fused controller's sensor buffer each channel fills: `control.fused.ControllerLayout`.

Channels (`LcmChannels`, prefix P = the robot's name in capitals by default), all at
1 kHz, SI units, joint vectors in the robot description's joint order:

| channel | type | content |
| --- | --- | --- |
| P_Q_CMD | `drake.lcmt_drake_signal` | controller → robot: position command (rad); coord = joint names |
| P_Q_MEASURED | `drake.lcmt_drake_signal` | robot → controller: encoders (rad); coord = joint names |
| P_IMU | `drake.lcmt_drake_signal` | robot → controller: [a_x, a_y, a_z (m/s², proper acceleration, IMU frame), ω_x, ω_y, ω_z (rad/s)] (robots with an IMU) |
| P_WRENCH_<SENSOR> | `drake.lcmt_force_torque` | robot → controller: one F/T sensor, fx, fy, fz (N), tx, ty, tz (N·m), sensor frame, as the sensor reads |

`timestamp` is the sender's clock: µs in `lcmt_drake_signal`, ms in `lcmt_force_torque`
(as Drake documents it). The controller uses it only to tell a new sample from a
repeated one, and stamps each channel's signals with its own time of the sample
(`sensor_time`), so that a silent or frozen sensor goes stale there.
"""  # noqa: E501 (the channel table's rows cannot be split)

from dataclasses import dataclass

from hrp2_drake.description import RobotDescription
from hrp2_drake.hardware.messages import SignalCodec, WrenchCodec

IMU_COORDS = ("acc_x", "acc_y", "acc_z", "gyro_x", "gyro_y", "gyro_z")


@dataclass
class LcmChannels:
    """The channel names of one robot (module docstring).

    Args:
        prefix: the first word of every channel; empty: the robot's name in capitals.
    """

    prefix: str = ""

    def resolved(self, robot: RobotDescription) -> "LcmChannels":
        return LcmChannels(self.prefix or robot.name.upper())

    @property
    def q_cmd(self) -> str:
        return f"{self.prefix}_Q_CMD"

    @property
    def q_measured(self) -> str:
        return f"{self.prefix}_Q_MEASURED"

    @property
    def imu(self) -> str:
        return f"{self.prefix}_IMU"

    def wrench(self, sensor: str) -> str:
        return f"{self.prefix}_WRENCH_{sensor.upper()}"

    def sensors(self, robot: RobotDescription) -> list[str]:
        """The robot → controller channels, in `sensor_sizes` order."""
        out = [self.q_measured] + ([self.imu] if robot.has_imu() else [])
        return out + [self.wrench(s) for s in robot.sensor_names()]

    def codecs(self, robot: RobotDescription) -> list:
        """A codec per sensor channel (`sensors` order)."""
        out = [SignalCodec(robot.joints, self.q_measured)]
        if robot.has_imu():
            out.append(SignalCodec(IMU_COORDS, self.imu))
        return out + [WrenchCodec(self.wrench(s)) for s in robot.sensor_names()]
