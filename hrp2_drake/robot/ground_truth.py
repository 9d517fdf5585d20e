"""Ground truth of a simulated robot, for evaluation only: what the emulated servo's
hidden parameters imply. Estimators, identification and controllers never read it."""

from collections.abc import Sequence

from hrp2_drake.description import RobotDescription
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.robot.servo import effective_motor_parameters, load_servo_params


def true_motor_model(
    robot: RobotDescription,
    joint_names: Sequence[str] = (),
    direction: int = 0,
    servo_file: str = "",
) -> MotorModel:
    """The emulated servo's effective Kτ, Kv, Kc of `joint_names` (default: the
    robot's controlled joints). `servo_file` as `StationConfig.servo_file` (empty:
    the description's servo_file)."""
    joints = list(joint_names or robot.controlled_joints)
    params = load_servo_params(servo_file, robot.source_file)
    eff = effective_motor_parameters(params, joints, direction)
    return MotorModel(joints, eff["k_tau"], eff["k_v"], eff["k_c"])
