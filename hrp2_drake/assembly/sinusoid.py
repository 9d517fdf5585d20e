"""The joints' sinusoid that `track` and `control` run: every controlled joint around
the home pose (rad), joint k of n phase-shifted by k/n of a period, after a settle at
home; the check that it fits the robot's position and velocity limits."""

import numpy as np

from hrp2_drake.assembly.builders import JointReference
from hrp2_drake.config import check_finite
from hrp2_drake.description import RobotDescription, joint_limits


def check_sinusoid(
    robot: RobotDescription,
    q0: np.ndarray,
    amplitude: float,
    frequency: float,
    settle: float,
    where: str,
) -> None:
    """Raises ValueError naming `where`.<field> unless the sinusoids of
    `sinusoid_reference` around `q0` (rad, every joint of `robot`) fit the robot:
    settle >= 0 s, frequency > 0 Hz, and every controlled joint within its position
    limits (home ± amplitude, with its phase) and its velocity limit (amplitude · 2π ·
    frequency, rad/s)."""
    check_finite(settle, f"{where}.settle", 0.0, strict=False)
    check_finite(frequency, f"{where}.frequency", 0.0)
    check_finite(amplitude, f"{where}.amplitude", 0.0, strict=False)
    lower, upper, speed = joint_limits(robot)
    controlled = robot.controlled_joints
    for k, name in enumerate(controlled):
        j = robot.joints.index(name)
        # q = q0 + A (sin(ωs + φ) - sin φ): q0 - A (1 + sin φ) to q0 + A (1 - sin φ).
        shift = np.sin(2 * np.pi * k / len(controlled))
        low, high = q0[j] - amplitude * (1 + shift), q0[j] + amplitude * (1 - shift)
        if low < lower[j] - 1e-9 or high > upper[j] + 1e-9:
            raise ValueError(
                f"{where}.amplitude: {amplitude:g} rad moves {name} from {low:.3g} to "
                f"{high:.3g} rad, beyond its position limits [{lower[j]:.3g}, "
                f"{upper[j]:.3g}] rad"
            )
        peak = amplitude * 2 * np.pi * frequency
        if peak > speed[j]:
            raise ValueError(
                f"{where}.frequency: {frequency:g} Hz at amplitude {amplitude:g} rad "
                f"moves {name} at up to {peak:.3g} rad/s, beyond its velocity limit "
                f"{speed[j]:.3g} rad/s"
            )


def sinusoid_reference(
    robot: RobotDescription,
    q0: np.ndarray,
    amplitude: float,
    frequency: float,
    settle: float,
    duration: float,
) -> JointReference:
    """`q0` (rad, every joint of `robot`) for `settle` s, then for `duration` s every
    controlled joint on a sinusoid of `amplitude` (rad) and `frequency` (Hz), joint k
    of n phase-shifted by k/n of a period, its amplitude ramped in over the first
    period; sampled at 1 kHz."""
    t = np.arange(0.0, settle + duration + 1e-9, 0.001)
    n = len(robot.joints)
    q, v, a = np.tile(q0, (len(t), 1)), np.zeros((len(t), n)), np.zeros((len(t), n))
    w = 2 * np.pi * frequency
    s = np.clip(t - settle, 0.0, None)
    # Smooth envelope e(s) over the first period (C2 at both ends).
    x = np.clip(s * frequency, 0.0, 1.0)
    e = x**3 * (10 - 15 * x + 6 * x**2)
    de = 30 * x**2 * (1 - x) ** 2 * frequency
    dde = 60 * x * (1 - x) * (1 - 2 * x) * frequency**2
    controlled = robot.controlled_joints
    for k, name in enumerate(controlled):
        j = robot.joints.index(name)
        phase = 2 * np.pi * k / len(controlled)
        sin, cos = np.sin(w * s + phase) - np.sin(phase), np.cos(w * s + phase)
        A = amplitude
        q[:, j] += A * e * sin
        v[:, j] = A * (de * sin + e * w * cos)
        a[:, j] = A * (dde * sin + 2 * de * w * cos - e * w**2 * np.sin(w * s + phase))
    return JointReference.from_samples(t, q, v, a)
