"""The floating base's pose and velocity from the legs' kinematics, with every sole
flat where it stands: what a whole-body controller with contacts needs and a robot
without motion capture has (sot-torque-control's base estimator does the same from
the feet, fused with the IMU).

Each sole k stays at its pose X_WS_k (given: where it stood when the run started),
so the joint angles q_j give the base's pose X_WB_k = X_WS_k · X_BS_k(q_j)⁻¹ through
each leg; the estimate is their mean (positions averaged; the rotations' unit
quaternions averaged, signs aligned, and normalised: for two soles, the rotations'
geodesic midpoint). So soles whose given poses disagree (a sole that slipped) give
the average: a sole 1 cm off moves the estimate of two soles by 5 mm. The velocities
follow from the soles' not moving: J_k,b v_b + J_k,j v_j = 0 for every sole (6 rows
each, at the estimated pose), solved for the base's 6 velocities in the
least-squares sense.

Valid while every sole stays flat on the ground; a sole that slips or rotates makes
the estimate drift by as much (the balance experiments report when a sole moved).

Per tick (`FloatingBaseFromSolesStep.step`), Drake gives, with the joints at q_j and the
base at the identity pose (where the world frame and the base's coincide), each
sole's pose X_BS_k and its spatial-velocity Jacobian J_BS_k (the joint columns: the
sole's velocity relative to the base, in B): one SetPositions and, per sole, one
CalcRelativeTransform (read as a 4x4 matrix) and one Jacobian. The arithmetic is
two numba kernels: `base_joint_positions` (the inputs' finiteness, the joints into
the positions) and `base_from_soles` (the per-sole base poses, their mean, and the
velocities). At the estimated pose (R, p), with r_k = R p_BS_k and the floating
joint's velocities v_b = [ω_WB; v_WBo] (in the world), sole k's rows are

    ω_WB                 + R ω_BS_k = 0
    v_WBo − [r_k]× ω_WB  + R v_BS_k = 0      ([r]× x = r × x)

i.e. J_k,b = [[I, 0], [−[r_k]×, I]] and J_k,j v_j = diag(R, R) J_BS_k v_j: what
Drake's Jacobians at the estimated pose hold (rigid-body kinematics; no second
SetPositions, no second kinematics pass). The least-squares v_b solves the 6x6
normal equations (Σ_k J_k,bᵀ J_k,b) v_b = −Σ_k J_k,bᵀ J_k,j v_j by Cholesky, in the
kernel: each J_k,b is invertible (unit triangular), so the matrix is positive
definite, and well conditioned (its condition number is σ⁴ for one sole, σ =
(|r| + √(|r|² + 4)) / 2; 3.6 on HRP-2, |r_k| ≈ 0.66 m, one sole or both), so the
normal equations lose nothing against an SVD (numpy's lstsq on Drake's Jacobians at
the estimate agrees to 1e-12, the tests).

With an IMU (`ImuFusion`): the legs' kinematics give the base's orientation only
while every sole stays flat; a sole that rolls on its edge under a push tilts the
estimate with it (the mean of the soles' rotations), and a whole-body controller
then acts on a base that does not move. The gyro measures the IMU's rotation
directly. Per tick, after the kinematic estimate R_kin (above) is formed, a
complementary filter (Mahony's, its correction from the kinematics instead of the
accelerometer; sot-torque-control's base estimator fuses the IMU's orientation with
the feet's likewise) integrates the gyro's rate ω_I, its offset and estimated bias
b removed, corrected toward the kinematic estimate of the IMU's orientation
R_kin R_BI:

    e   = vee(skew(R_WIᵀ R_kin R_BI))      (the small rotation between them, in I)
    R_WI ← R_WI exp((ω_I − b + k e) dt),   b ← b − k_b e dt

(k, `gain`: the crossover, 1/s; k_b, `bias_gain`). The first tick starts from the
kinematic estimate. Then R_WB = R_WI R_BIᵀ, and the position and the linear velocity
follow from the soles at that orientation (their mean): p_WB = p_WS_k − R_WB p_BS_k
and v_WBo = r_k × ω_WB − R_WB v_BS_k. The angular velocity ω_WB stays the soles'
least squares (above): the gyro's rate in its place (less the torso joints' share)
brought its white noise (0.005 rad/s on HRP-2) into the QP's CoM and base damping,
and the legs' torques shook with it (τ̂'s error against the delayed torque 2-4x on
the hips, measured, issue 35); integrated into the orientation, that noise is
negligible. The gyro must describe the instant the joint velocities do (the same
filter, `control/torque_chain.py`'s base filter). A non-finite gyro keeps the
kinematic estimate for that tick.

.. code-block:: text

                 ┌─────────────────────┐
    q (n) ──────►│                     │
                 │ FloatingBaseFromSoles├──► state (nq + nv): the plant's [q; v]
    v (n) ──────►│                     │
    gyro (3) ───►│  (with an IMU)      │
                 └─────────────────────┘
"""

import math
from dataclasses import dataclass, field

import numpy as np
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.multibody.math import SpatialVelocity
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import JacobianWrtVariable, JointIndex
from pydrake.systems.framework import Context

from hrp2_drake.config import check_finite
from hrp2_drake.kernels import kernel
from hrp2_drake.multibody import floating_base, get_frame, joint_indexing
from hrp2_drake.step import Step, StepSystem

_WHERE = "FloatingBaseFromSoles"

# The kernels' index table (`FloatingBaseFromSolesStep._pack`, int64): a header, then
# the joints' positions in q and velocities in v.
(
    _NQ,  # the plant's positions
    _NJ,  # the joints, n
    _BASE_Q,  # the base's [w, x, y, z, p_x, p_y, p_z] in q
    _BASE_V,  # its velocities [ω_WB; v_WBo] (in W) in v
    _HEADER,
) = range(5)
# The kernel's work array (float64): the normal equations' matrix (6x6) and
# right-hand side (6), one sole's J_k,b (6x6), J_BS_k v_j (6) and −J_k,j v_j (6),
# R_WB (3x3).
_A, _B, _JB, _S, _C, _R, _WORK = 0, 36, 42, 78, 84, 90, 99


@kernel
def rotation_quaternion(R):
    """R's unit quaternion (w, x, y, z), w >= 0: from the largest of its trace and
    diagonal (Drake's RotationMatrix::ToQuaternion, simbody's)."""
    trace = R[0, 0] + R[1, 1] + R[2, 2]
    if trace >= R[0, 0] and trace >= R[1, 1] and trace >= R[2, 2]:
        w = 1.0 + trace
        x = R[2, 1] - R[1, 2]
        y = R[0, 2] - R[2, 0]
        z = R[1, 0] - R[0, 1]
    elif R[0, 0] >= R[1, 1] and R[0, 0] >= R[2, 2]:
        w = R[2, 1] - R[1, 2]
        x = 1.0 - (trace - 2.0 * R[0, 0])
        y = R[0, 1] + R[1, 0]
        z = R[0, 2] + R[2, 0]
    elif R[1, 1] >= R[2, 2]:
        w = R[0, 2] - R[2, 0]
        x = R[0, 1] + R[1, 0]
        y = 1.0 - (trace - 2.0 * R[1, 1])
        z = R[1, 2] + R[2, 1]
    else:
        w = R[1, 0] - R[0, 1]
        x = R[0, 2] + R[2, 0]
        y = R[1, 2] + R[2, 1]
        z = 1.0 - (trace - 2.0 * R[2, 2])
    scale = 1.0 / math.sqrt(w * w + x * x + y * y + z * z)
    if w < 0.0:
        scale = -scale
    return scale * w, scale * x, scale * y, scale * z


@kernel
def quaternion_rotation(qw, qx, qy, qz, R):
    """R (3x3, written) of the unit quaternion (qw, qx, qy, qz), as Drake's."""
    R[0, 0] = 1.0 - 2.0 * (qy * qy + qz * qz)
    R[0, 1] = 2.0 * (qx * qy - qw * qz)
    R[0, 2] = 2.0 * (qx * qz + qw * qy)
    R[1, 0] = 2.0 * (qx * qy + qw * qz)
    R[1, 1] = 1.0 - 2.0 * (qx * qx + qz * qz)
    R[1, 2] = 2.0 * (qy * qz - qw * qx)
    R[2, 0] = 2.0 * (qx * qz - qw * qy)
    R[2, 1] = 2.0 * (qy * qz + qw * qx)
    R[2, 2] = 1.0 - 2.0 * (qx * qx + qy * qy)


@kernel
def base_joint_positions(q, v, positions, table):
    """Whether q and v (the joints, constructor order) are finite; if they are, q
    written into the plant positions `positions` (whose base stays at the identity
    pose)."""
    n = table[_NJ]
    total = 0.0
    for i in range(n):
        total += q[i] + v[i]
    if not math.isfinite(total):
        return False
    for i in range(n):
        positions[table[_HEADER + i]] = q[i]
    return True


# Whole: one compiled pass on the tick's arrays; a split costs calls (scripts/bench.py)
@kernel
def base_from_soles(v, X_WS, X_BS, J, positions, table, work, robot_state):
    """The robot's [q; v] (`robot_state`) from the soles' poses X_WS (soles, 4, 4),
    the base-to-sole poses X_BS (soles, 4, 4) and Jacobians J (soles, 6, nv, the
    joint columns: J_BS_k in B) at the joint positions `positions`, and the joint
    velocities v (the module docstring has the equations). Sums in loop order."""
    nq, n = table[_NQ], table[_NJ]
    bq, bv = table[_BASE_Q], table[_BASE_V]
    jv = _HEADER + n
    soles = X_WS.shape[0]
    R = work[_R:_WORK].reshape((3, 3))
    # The base's pose through each sole, X_WB_k = X_WS_k X_BS_k⁻¹; the mean.
    qw, qx, qy, qz = 0.0, 0.0, 0.0, 0.0
    px, py, pz = 0.0, 0.0, 0.0
    for k in range(soles):
        for i in range(3):
            for j in range(3):
                R[i, j] = (
                    X_WS[k, i, 0] * X_BS[k, j, 0]
                    + X_WS[k, i, 1] * X_BS[k, j, 1]
                    + X_WS[k, i, 2] * X_BS[k, j, 2]
                )
        px += X_WS[k, 0, 3] - (
            R[0, 0] * X_BS[k, 0, 3] + R[0, 1] * X_BS[k, 1, 3] + R[0, 2] * X_BS[k, 2, 3]
        )
        py += X_WS[k, 1, 3] - (
            R[1, 0] * X_BS[k, 0, 3] + R[1, 1] * X_BS[k, 1, 3] + R[1, 2] * X_BS[k, 2, 3]
        )
        pz += X_WS[k, 2, 3] - (
            R[2, 0] * X_BS[k, 0, 3] + R[2, 1] * X_BS[k, 1, 3] + R[2, 2] * X_BS[k, 2, 3]
        )
        w, x, y, z = rotation_quaternion(R)
        scale = 1.0
        # Aligned with the sum so far (q and −q are the same rotation).
        if qw * w + qx * x + qy * y + qz * z < 0.0:
            scale = -scale
        qw += scale * w
        qx += scale * x
        qy += scale * y
        qz += scale * z
    scale = 1.0 / math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    if qw < 0.0:
        scale = -scale
    qw, qx, qy, qz = scale * qw, scale * qx, scale * qy, scale * qz
    for i in range(nq):
        robot_state[i] = positions[i]
    robot_state[bq] = qw
    robot_state[bq + 1] = qx
    robot_state[bq + 2] = qy
    robot_state[bq + 3] = qz
    robot_state[bq + 4] = px / soles
    robot_state[bq + 5] = py / soles
    robot_state[bq + 6] = pz / soles
    # R of the estimate (of its quaternion, as Drake computes it from q).
    quaternion_rotation(qw, qx, qy, qz, R)
    # The soles do not move: Σ_k J_k,bᵀ J_k,b v_b = −Σ_k J_k,bᵀ J_k,j v_j.
    A = work[_A:_B].reshape((6, 6))
    b = work[_B:_JB]
    Jb = work[_JB:_S].reshape((6, 6))
    s = work[_S:_C]
    c = work[_C:_R]
    for i in range(6):
        b[i] = 0.0
        for j in range(6):
            A[i, j] = 0.0
            Jb[i, j] = 1.0 if i == j else 0.0
    for k in range(soles):
        # J_k,j v_j = diag(R, R) J_BS_k v_j: the joints' part in B, rotated.
        for r in range(6):
            total = 0.0
            for i in range(n):
                total += J[k, r, table[jv + i]] * v[i]
            s[r] = total
        for r in range(3):
            c[r] = -(R[r, 0] * s[0] + R[r, 1] * s[1] + R[r, 2] * s[2])
            c[3 + r] = -(R[r, 0] * s[3] + R[r, 1] * s[4] + R[r, 2] * s[5])
        # J_k,b's lower-left block −[r_k]×, r_k = R p_BS_k.
        x, y, z = X_BS[k, 0, 3], X_BS[k, 1, 3], X_BS[k, 2, 3]
        r0 = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z
        r1 = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z
        r2 = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z
        Jb[3, 1], Jb[3, 2] = r2, -r1
        Jb[4, 0], Jb[4, 2] = -r2, r0
        Jb[5, 0], Jb[5, 1] = r1, -r0
        for i in range(6):
            for j in range(6):
                total = 0.0
                for m in range(6):
                    total += Jb[m, i] * Jb[m, j]
                A[i, j] += total
            total = 0.0
            for m in range(6):
                total += Jb[m, i] * c[m]
            b[i] += total
    # Cholesky, A = L Lᵀ (L in A's lower triangle), then L y = b, Lᵀ v_b = y.
    for j in range(6):
        total = A[j, j]
        for m in range(j):
            total -= A[j, m] * A[j, m]
        A[j, j] = math.sqrt(total)
        for i in range(j + 1, 6):
            total = A[i, j]
            for m in range(j):
                total -= A[i, m] * A[j, m]
            A[i, j] = total / A[j, j]
    for i in range(6):
        total = b[i]
        for m in range(i):
            total -= A[i, m] * b[m]
        b[i] = total / A[i, i]
    for i in range(5, -1, -1):
        total = b[i]
        for m in range(i + 1, 6):
            total -= A[m, i] * b[m]
        b[i] = total / A[i, i]
    for i in range(6):
        robot_state[nq + bv + i] = b[i]
    for i in range(n):
        robot_state[nq + table[jv + i]] = v[i]


# The IMU fusion's constants (`FloatingBaseFromSolesStep._imu_constants`, float64).
_PERIOD, _GAIN, _BIAS_GAIN, _OFFSET, _IMU_CONSTANTS = 0, 1, 2, 3, 6
# Its state (the step's `attitude`): the IMU frame's orientation R_WI as a unit
# quaternion [w, x, y, z] (NaN before a first tick), the gyro's bias estimate (3).
_ATTITUDE, _BIAS, _IMU_STATE = 0, 4, 7


# Whole: one compiled pass on the tick's arrays; a split costs calls (scripts/bench.py)
@kernel
def base_imu_fusion(
    gyro, v, X_BI, X_WS, X_BS, J, table, constants, imu, work, robot_state
):
    """The base's orientation from the gyro (rad/s, the IMU's frame), corrected
    toward the soles' kinematic estimate (already in `robot_state`,
    `base_from_soles`), then its position and linear velocity from the soles at that
    orientation (module docstring, "With an IMU"): X_BI (4, 4) is the IMU frame's
    pose in B at the joint positions; `imu` is the filter's state (R_WI's
    quaternion, NaN before a first tick; the gyro's bias), updated. A non-finite
    gyro changes nothing."""
    nq, n = table[_NQ], table[_NJ]
    bq, bv = table[_BASE_Q], table[_BASE_V]
    jv = _HEADER + n
    soles = X_WS.shape[0]
    if not math.isfinite(gyro[0] + gyro[1] + gyro[2]):
        return
    dt = constants[_PERIOD]
    R = work[_R:_WORK].reshape((3, 3))
    Rk = work[_A : _A + 9].reshape((3, 3))
    Ri = work[_A + 9 : _A + 18].reshape((3, 3))
    # The kinematic estimate of R_WI: R_WB (the soles') R_BI.
    quaternion_rotation(
        robot_state[bq],
        robot_state[bq + 1],
        robot_state[bq + 2],
        robot_state[bq + 3],
        R,
    )
    for i in range(3):
        for j in range(3):
            Rk[i, j] = (
                R[i, 0] * X_BI[0, j] + R[i, 1] * X_BI[1, j] + R[i, 2] * X_BI[2, j]
            )
    # The gyro's rate, its offset and estimated bias removed (the IMU's frame).
    wx = gyro[0] - constants[_OFFSET] - imu[_BIAS]
    wy = gyro[1] - constants[_OFFSET + 1] - imu[_BIAS + 1]
    wz = gyro[2] - constants[_OFFSET + 2] - imu[_BIAS + 2]
    if not math.isfinite(imu[_ATTITUDE]):
        w, x, y, z = rotation_quaternion(Rk)
    else:
        w, x = imu[_ATTITUDE], imu[_ATTITUDE + 1]
        y, z = imu[_ATTITUDE + 2], imu[_ATTITUDE + 3]
        quaternion_rotation(w, x, y, z, Ri)
        # e = vee(skew(R_WIᵀ R_kin)): the rotation (small) from the estimate to the
        # kinematic one, in the IMU's frame.
        e = work[_B : _B + 3]
        for c in range(3):
            a, b = (c + 1) % 3, (c + 2) % 3
            # (Riᵀ Rk)[b, a] − (Riᵀ Rk)[a, b]
            e[c] = 0.5 * (
                Ri[0, b] * Rk[0, a]
                + Ri[1, b] * Rk[1, a]
                + Ri[2, b] * Rk[2, a]
                - Ri[0, a] * Rk[0, b]
                - Ri[1, a] * Rk[1, b]
                - Ri[2, a] * Rk[2, b]
            )
        gain, bias_gain = constants[_GAIN], constants[_BIAS_GAIN]
        ux, uy, uz = wx + gain * e[0], wy + gain * e[1], wz + gain * e[2]
        for c in range(3):
            imu[_BIAS + c] -= bias_gain * dt * e[c]
        # q ⊗ exp(u dt / 2)
        angle = math.sqrt(ux * ux + uy * uy + uz * uz) * dt
        if angle > 0.0:
            s = math.sin(0.5 * angle) / (angle / dt)
            cw = math.cos(0.5 * angle)
            dx, dy, dz = s * ux, s * uy, s * uz
            w, x, y, z = (
                w * cw - x * dx - y * dy - z * dz,
                w * dx + x * cw + y * dz - z * dy,
                w * dy - x * dz + y * cw + z * dx,
                w * dz + x * dy - y * dx + z * cw,
            )
        scale = 1.0 / math.sqrt(w * w + x * x + y * y + z * z)
        w, x, y, z = scale * w, scale * x, scale * y, scale * z
    imu[_ATTITUDE], imu[_ATTITUDE + 1] = w, x
    imu[_ATTITUDE + 2], imu[_ATTITUDE + 3] = y, z
    quaternion_rotation(w, x, y, z, Ri)
    # R_WB = R_WI R_BIᵀ.
    for i in range(3):
        for j in range(3):
            R[i, j] = (
                Ri[i, 0] * X_BI[j, 0] + Ri[i, 1] * X_BI[j, 1] + Ri[i, 2] * X_BI[j, 2]
            )
    # Its quaternion (w >= 0), and R again as Drake computes it from q.
    w, x, y, z = rotation_quaternion(R)
    quaternion_rotation(w, x, y, z, R)
    robot_state[bq], robot_state[bq + 1] = w, x
    robot_state[bq + 2], robot_state[bq + 3] = y, z
    # The angular velocity stays the soles' (`base_from_soles`): the gyro's
    # noise through it shook the QP's forces (module docstring).
    s = work[_S:_C]
    om = work[_C : _C + 3]
    for r in range(3):
        om[r] = robot_state[nq + bv + r]
    # Position and velocity: the mean over the soles at R_WB,
    # p = p_WS_k − R p_BS_k, v_WBo = r_k × ω_WB − R v_BS_k (r_k = R p_BS_k).
    px, py, pz, vx, vy, vz = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    for k in range(soles):
        x, y, z = X_BS[k, 0, 3], X_BS[k, 1, 3], X_BS[k, 2, 3]
        r0 = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z
        r1 = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z
        r2 = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z
        px += X_WS[k, 0, 3] - r0
        py += X_WS[k, 1, 3] - r1
        pz += X_WS[k, 2, 3] - r2
        for r in range(3):
            total = 0.0
            for i in range(n):
                total += J[k, 3 + r, table[jv + i]] * v[i]
            s[r] = total
        vx += (
            r1 * om[2] - r2 * om[1] - (R[0, 0] * s[0] + R[0, 1] * s[1] + R[0, 2] * s[2])
        )
        vy += (
            r2 * om[0] - r0 * om[2] - (R[1, 0] * s[0] + R[1, 1] * s[1] + R[1, 2] * s[2])
        )
        vz += (
            r0 * om[1] - r1 * om[0] - (R[2, 0] * s[0] + R[2, 1] * s[1] + R[2, 2] * s[2])
        )
    robot_state[bq + 4] = px / soles
    robot_state[bq + 5] = py / soles
    robot_state[bq + 6] = pz / soles
    robot_state[nq + bv + 3] = vx / soles
    robot_state[nq + bv + 4] = vy / soles
    robot_state[nq + bv + 5] = vz / soles


@dataclass
class ImuFusion:
    """The IMU in the base's estimate ("With an IMU", the module docstring).

    Args:
        frame: the IMU's frame (the robot's `imu_frame`), where its gyro measures.
        gyro_offset: the gyro's offset found before the run (rad/s, its frame;
            subtracted from every reading), zeros if none was found.
        gain: how fast the estimate returns to the soles' kinematics (1/s): the
            complementary filter's crossover; 0 trusts the gyro alone.
        bias_gain: how fast the gyro's remaining bias is learnt from that
            difference (1/s²); 0: none.
    """

    frame: str
    gyro_offset: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    gain: float = 1.0
    bias_gain: float = 0.0

    def validate(self, period: float) -> None:
        """Raises ValueError naming the bad field: three finite offsets, gains
        finite and >= 0, a period finite and > 0."""
        where = f"{_WHERE}: ImuFusion"
        offset = np.asarray(self.gyro_offset, dtype=float)
        if offset.shape != (3,) or not np.all(np.isfinite(offset)):
            raise ValueError(
                f"{where}.gyro_offset: three finite rates (rad/s), got "
                f"{self.gyro_offset}"
            )
        for name in ("gain", "bias_gain"):
            check_finite(getattr(self, name), f"{where}.{name}", 0.0, strict=False)
        if not (math.isfinite(period) and period > 0.0):
            raise ValueError(
                f"{where}: the period must be finite and > 0 (s), got {period}"
            )


class FloatingBaseFromSolesStep(Step):
    """The per-tick arithmetic of FloatingBaseFromSoles (module docstring).

    State:
        robot_state (nq + nv): the robot's [q; v] in the plant's order (its
            floating base's quaternion [w, x, y, z] with w >= 0, position, ω and
            velocity in the world), at the last tick.
        valid (1): 1 once a tick had finite inputs (before: the plant's default
            state with the joints at zero).
        attitude (7, with an IMU): the IMU's orientation R_WI as a quaternion
            [w, x, y, z] (NaN before a first tick) and the gyro's estimated bias
            (rad/s, its frame).

    Per tick: one private context of the plant; Drake's calls: the positions, per
    sole its pose in the base's frame (and its 4x4 matrix) and its Jacobian (7 on
    two soles; with an IMU, its frame's pose too: 8); the rest is two kernels
    (`base_joint_positions`, `base_from_soles`), three with an IMU
    (`base_imu_fusion`), on arrays allocated once.
    """

    def __init__(
        self,
        plant: MultibodyPlant,
        joints: list[str],
        sole_poses: dict[str, RigidTransform],
        imu: ImuFusion | None = None,
        period: float = 0.0,
    ):
        """
        Args:
            plant: a finalized MultibodyPlant of the robot alone, one floating base
                with a quaternion joint between the world and the base body's
                frame; it must outlive the step and is never modified.
            joints: every joint of the robot, the order of the inputs q and v.
            sole_poses: each sole frame's pose in the world, X_WS (where it
                stands; at least one sole).
            imu: the IMU's part in the estimate (module docstring), None: the
                soles' kinematics alone.
            period: the update period (s), with an IMU (the gyro's integration).

        Raises:
            ValueError: no sole, a plant whose joints are not all listed (the
                message names them), a plant without exactly one floating base,
                a base without a quaternion joint, a bad `imu` or period (named).
            KeyError: an unknown joint or frame.
        """
        super().__init__()
        if not sole_poses:
            raise ValueError(f"{_WHERE}: no sole poses (at least one sole is needed)")
        self._plant = plant
        self._context = plant.CreateDefaultContext()
        try:
            self._indexing = joint_indexing(plant, joints)
            self._frames = [get_frame(plant, name, "sole frame") for name in sole_poses]
        except KeyError as error:
            raise KeyError(f"{_WHERE}: {error.args[0]}") from None
        base = self._base = floating_base(plant, _WHERE, quaternion=True)
        _check_base_joint(plant, base)
        self._check_joints()
        self._base_frame = base.body_frame()
        self._world = plant.world_frame()
        self._kV = JacobianWrtVariable.kV
        ns, nv = len(self._frames), plant.num_velocities()
        self._X_WS = np.array(
            [RigidTransform(X).GetAsMatrix4() for X in sole_poses.values()]
        )
        self._X_BS = np.zeros((ns, 4, 4))
        self._J = np.zeros((ns, 6, nv))
        self._zero3 = np.zeros(3)
        self._work = np.zeros(_WORK)
        self._table = self._pack()
        # The joints' positions, the base at the identity pose (never changed; the
        # plant's default pose of its base may be another).
        self._positions = plant.GetPositions(self._context)
        q0 = base.floating_positions_start()
        self._positions[q0 : q0 + 7] = [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
        self._declare("robot_state", plant.GetPositionsAndVelocities(self._context))
        self._declare("valid", [0.0])
        self._imu = imu
        if imu is not None:
            imu.validate(period)
            self._imu_frame = get_frame(plant, imu.frame, "IMU frame")
            self._imu_constants = np.array(
                [period, imu.gain, imu.bias_gain, *imu.gyro_offset], dtype=float
            )
            assert self._imu_constants.size == _IMU_CONSTANTS
            self._X_BI = np.eye(4)
            attitude = np.zeros(_IMU_STATE)
            attitude[_ATTITUDE] = math.nan  # no first tick yet
            self._declare("attitude", attitude)
        self._finalize()

    def _pack(self) -> np.ndarray:
        """The kernels' index table (int64; its header at the module's top)."""
        base, indexing = self._base, self._indexing
        header = [
            self._plant.num_positions(),
            indexing.size,
            base.floating_positions_start(),
            base.floating_velocities_start_in_v(),
        ]
        assert len(header) == _HEADER
        return np.concatenate([header, indexing.q, indexing.v]).astype(np.int64)

    def _check_joints(self) -> None:
        """Every one-dof joint of the plant must be among the step's joints."""
        plant, listed = self._plant, set(self._indexing.v.tolist())
        missing = []
        for index in plant.GetJointIndices():
            joint = plant.get_joint(JointIndex(index))
            if joint.num_velocities() == 1 and joint.velocity_start() not in listed:
                missing.append(joint.name())
        if missing or plant.num_velocities() != 6 + self._indexing.size:
            raise ValueError(
                f"{_WHERE}: {self._indexing.size} joints given, the plant has "
                f"{plant.num_velocities() - 6}: list every joint (missing {missing})"
            )

    def warm_up(self) -> None:
        """Compiles (or loads) the kernels on copies of the step's arrays (the
        inputs C-contiguous float64, as both shells pass them)."""
        zeros = np.zeros(self._indexing.size)
        positions = self._positions.copy()
        base_joint_positions(zeros, zeros, positions, self._table)
        X_BS = np.zeros_like(self._X_BS)
        X_BS[:] = np.eye(4)
        J, work = np.zeros_like(self._J), np.zeros_like(self._work)
        robot_state = self.state[self.rows("robot_state")].copy()
        base_from_soles(
            zeros, self._X_WS, X_BS, J, positions, self._table, work, robot_state
        )
        if self._imu is not None:
            base_imu_fusion(
                np.zeros(3),
                zeros,
                np.eye(4),
                self._X_WS,
                X_BS,
                J,
                self._table,
                self._imu_constants,
                self.state[self.rows("attitude")].copy(),
                work,
                robot_state,
            )

    def step(
        self, t: float, q: np.ndarray, v: np.ndarray, gyro: np.ndarray | None = None
    ) -> None:
        """One tick from the joint angles q (rad) and velocities v (rad/s), the
        constructor's joint order, and with an IMU its gyro's reading (rad/s, its
        frame); a non-finite input keeps the last estimate."""
        positions = self._positions
        if not base_joint_positions(q, v, positions, self._table):
            return
        plant, context, base, world = (
            self._plant,
            self._context,
            self._base_frame,
            self._world,
        )
        X_BS, J, kV, zero3 = self._X_BS, self._J, self._kV, self._zero3
        plant.SetPositions(context, positions)
        # The base at the identity pose: the world is B, the Jacobian J_BS in B.
        for k, frame in enumerate(self._frames):
            X_BS[k] = plant.CalcRelativeTransform(context, base, frame).GetAsMatrix4()
            J[k] = plant.CalcJacobianSpatialVelocity(
                context, kV, frame, zero3, world, world
            )
        base_from_soles(
            v,
            self._X_WS,
            X_BS,
            J,
            positions,
            self._table,
            self._work,
            self.robot_state,
        )
        if self._imu is not None:
            X_BI = self._X_BI
            X_BI[:] = plant.CalcRelativeTransform(
                context, base, self._imu_frame
            ).GetAsMatrix4()
            base_imu_fusion(
                gyro,
                v,
                X_BI,
                self._X_WS,
                X_BS,
                J,
                self._table,
                self._imu_constants,
                self.attitude,
                self._work,
                self.robot_state,
            )
        self.valid[0] = 1.0


def _check_base_joint(plant: MultibodyPlant, base) -> None:
    """Raises ValueError unless the floating joint of `base` has positions the body's
    pose in the world [w, x, y, z, p] and velocities its [ω_WB; v_WBo] in the world
    (checked on a scratch context)."""
    context = plant.CreateDefaultContext()
    X_WB = RigidTransform(RollPitchYaw(0.1, -0.2, 0.3), [0.4, -0.5, 0.6])
    V_WB = SpatialVelocity(w=[0.1, 0.2, 0.3], v=[0.4, 0.5, 0.6])
    plant.SetFreeBodyPose(context, base, X_WB)
    plant.SetFreeBodySpatialVelocity(context, base, V_WB)
    q0, v0 = base.floating_positions_start(), base.floating_velocities_start_in_v()
    q = plant.GetPositions(context)[q0 : q0 + 7]
    v = plant.GetVelocities(context)[v0 : v0 + 6]
    expected_q = np.r_[X_WB.rotation().ToQuaternion().wxyz(), X_WB.translation()]
    if not (
        np.allclose(q, expected_q, rtol=0, atol=1e-15)
        and np.allclose(v, V_WB.get_coeffs(), rtol=0, atol=1e-15)
    ):
        raise ValueError(
            f"{_WHERE}: the floating base '{base.name()}''s joint must hold its pose "
            "[w, x, y, z, p] and [ω_WB; v_WBo] in the world (no frame offsets)"
        )


class FloatingBaseFromSoles(StepSystem):
    """The floating base's state from the legs' kinematics (module docstring).

    Inputs:
        q (n, rad), v (n, rad/s): every joint, the constructor's joint order (the
            encoders or the Savitzky-Golay estimates).

    Output (this tick's, `StepSystem`):
        state (nq + nv): the plant's [q; v] with the base from the soles.
    """

    def __init__(
        self,
        plant: MultibodyPlant,
        joints: list[str],
        sole_poses: dict[str, RigidTransform],
        period: float,
        lead: float = 0.0,
        imu: ImuFusion | None = None,
    ):
        """
        Args:
            plant, joints, sole_poses, imu: as `FloatingBaseFromSolesStep`'s.
            period: the update period (s).
            lead: the samples arrive this long (s) before each multiple of `period`
                (`StepSystem`: the commits follow the sampler).
        """
        super().__init__()
        step = FloatingBaseFromSolesStep(plant, joints, sole_poses, imu, period)
        self._q = self.DeclareVectorInputPort("q", len(joints))
        self._v = self.DeclareVectorInputPort("v", len(joints))
        self._gyro = self.DeclareVectorInputPort("gyro", 3) if imu else None
        self._declare_step_state(step)
        self._declare_step_output("state", "robot_state")
        self._declare_commit(period, lead)

    def step(self) -> FloatingBaseFromSolesStep:
        return self._step

    def _tick(self, context: Context, t: float) -> None:
        gyro = self._gyro.Eval(context) if self._gyro else None
        self._step.step(t, self._q.Eval(context), self._v.Eval(context), gyro)
