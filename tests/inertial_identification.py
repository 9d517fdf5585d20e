"""Off-line identification of the mass, centre of mass and offset of what an F/T sensor
carries (the foot or hand below it), from static configurations (paper Sec. 2.2).

With the bodies below the sensor at rest and touching nothing, the sensor reads the
weight of what it carries plus its offset:

    S = [c × m g; m g] + o        ([torque; force], sensor frame, about its origin)

where m is the mass below the sensor, c its centre of mass and g the gravity vector, all
in the sensor frame, and o the sensor's offset. S is linear in x = (m, m c, o), 10
unknowns, so readings in several orientations of the sensor give x by linear least
squares. The gravity direction in the sensor frame comes from the kinematics (e.g. the
IMU's accelerometer at rest reads −g in the IMU frame: rotate it into the sensor frame
and negate). Rotational inertia is not observable statically; a moving link below the
sensor (a gripper) is identified as one rigid load in its current configuration.

Test-only: no library code, script or command uses it; tests/test_torque_estimator.py
does (moved here from hrp2_drake/estimation/, issue 28).
"""

from typing import NamedTuple

import numpy as np

_WHERE = "identify_end_effector_inertia"


class EndEffectorInertia(NamedTuple):
    """Result of identify_end_effector_inertia (unpacks as (mass, com, offset)).

    Attributes:
        mass: kg.
        com: centre of mass (m, 3), sensor frame, from the sensor origin.
        offset: the sensor offset [torque; force] (N·m, N, 6), sensor frame.
    """

    mass: float
    com: np.ndarray
    offset: np.ndarray


def _skew(a: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def identify_end_effector_inertia(
    readings: np.ndarray, gravity_in_sensor_frame: np.ndarray, rcond: float = 1e-6
) -> EndEffectorInertia:
    """Identifies the load below an F/T sensor from m static, contact-free samples.

    Args:
        readings: (m, 6) sensor readings [torque; force] (N·m, N), sensor frame, about
            its origin, as wrench_<sensor> reports them (the wrench the load exerts on
            the body above the sensor).
        gravity_in_sensor_frame: (m, 3) the gravity vector (m/s², e.g. [0, 0, -9.81]
            for an upright sensor) in the sensor frame at each sample.
        rcond: the problem is rejected when the smallest singular value of the
            (column-scaled) regressor is below rcond times the largest.

    Returns:
        EndEffectorInertia(mass, com, offset), the linear least-squares fit.

    Raises:
        ValueError: wrong shapes, non-finite data, a non-positive mass, or
            orientations that do not excite every parameter: the force rows need two
            different gravity vectors (else m and the force offset mix), the torque
            rows need the differences of the gravity vectors to span a plane (else the
            centre of mass along their direction mixes with the torque offset), i.e.
            at least three different gravity directions.
    """
    S = np.asarray(readings, dtype=float)
    g = np.asarray(gravity_in_sensor_frame, dtype=float)
    if S.ndim != 2 or S.shape[1] != 6:
        raise ValueError(f"{_WHERE}: readings has shape {S.shape}, expected (m, 6)")
    if g.shape != (S.shape[0], 3):
        raise ValueError(
            f"{_WHERE}: gravity_in_sensor_frame has shape {g.shape}, expected "
            f"({S.shape[0]}, 3) (one gravity vector per reading)"
        )
    for name, value in (("readings", S), ("gravity_in_sensor_frame", g)):
        if not np.all(np.isfinite(value)):
            bad = np.argwhere(~np.isfinite(value))[0].tolist()
            raise ValueError(f"{_WHERE}: {name} is not finite at index {bad}")
    m = S.shape[0]
    # Unknowns x = [mass, mass * com (3), offset torque (3), offset force (3)].
    A = np.zeros((6 * m, 10))
    for i in range(m):
        rows = slice(6 * i, 6 * i + 6)
        block = A[rows]
        block[0:3, 1:4] = -_skew(g[i])  # (m c) × g = −[g]× (m c)
        block[0:3, 4:7] = np.eye(3)
        block[3:6, 0] = g[i]
        block[3:6, 7:10] = np.eye(3)
    b = S.reshape(-1)
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    singular = np.linalg.svd(A / scale, compute_uv=False)
    if singular[-1] < rcond * singular[0]:
        raise ValueError(
            f"{_WHERE}: the {m} orientations do not excite the 10 parameters "
            f"(singular values of the scaled regressor down to {singular[-1]:.3g}, "
            f"largest {singular[0]:.3g}): use at least three different gravity "
            "directions in the sensor frame"
        )
    x = np.linalg.lstsq(A / scale, b, rcond=None)[0] / scale
    mass = float(x[0])
    if not mass > 0:
        raise ValueError(f"{_WHERE}: identified a non-positive mass {mass:.4g} kg")
    return EndEffectorInertia(mass, x[1:4] / mass, x[4:10].copy())
