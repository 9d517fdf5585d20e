"""The inverse dynamics' gains K_s, K_d for a position-feedback gain K6 of the Δq
controller (paper Sec. 4.2 and 5.3: K6 = K_τ (1 + K_p) K_s is the paper's tuning knob,
K6 = 1 the native position servo's position gain).
"""

import math

import numpy as np

from hrp2_drake.control.inverse_dynamics import gain_vector


def inverse_dynamics_gains_for_k6(
    k_tau,
    k6,
    joint_inertia,
    kp=2.0,
    damping_ratio: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """K_s and K_d of eq. 12 for a position-feedback gain K6 (the paper's tuning knob,
    Sec. 4.2 and 5.3: K6 = 1 is the native position servo's position gain).

    K_s = K6 / (K_τ (1 + K_p)) per joint (inverse of K6 = K_τ (1 + K_p) K_s), and
    K_d = 2 ζ sqrt(K_s M_jj): if the torque loop tracks τ_d, each joint's error obeys
    M_jj ë + K_d ė + K_s e = 0, a second-order system of damping ratio ζ (the
    coupling of M_j's off-diagonal terms neglected; on HRP-2 M_jj is dominated by
    the reflected rotor inertia ρ² I_r, so it barely changes with the posture). Then
    K7 = K_τ (1 + K_p) K_d = 2 ζ sqrt(K6 K_τ (1 + K_p) M_jj).

    Args:
        k_tau: K_τ per joint (rad/(N·m)), a number or (n,).
        k6: K6 per joint (rad/rad), a number or (n,).
        joint_inertia: M_jj per joint (kg·m²), (n,) or a number, e.g. the diagonal
            of InverseDynamicsController.joint_space_model(q).mass_matrix.
        kp: K_p per joint, a number or (n,).
        damping_ratio: ζ (dimensionless, >= 0).

    Returns:
        (ks, kd): (n,) arrays in N·m/rad and N·m·s/rad.
    """
    sizes = [np.size(x) for x in (k_tau, k6, joint_inertia, kp)]
    n = max(sizes)
    where = "inverse_dynamics_gains_for_k6"
    k_tau = gain_vector("k_tau", k_tau, n, where)
    k6 = gain_vector("k6", k6, n, where)
    inertia = gain_vector("joint_inertia", joint_inertia, n, where)
    kp = gain_vector("kp", kp, n, where)
    if not np.all(k_tau > 0):
        raise ValueError(f"{where}: k_tau must be > 0, got {k_tau}")
    if not (math.isfinite(damping_ratio) and damping_ratio >= 0):
        raise ValueError(f"{where}: damping_ratio={damping_ratio} must be >= 0")
    ks = k6 / (k_tau * (1.0 + kp))
    kd = 2.0 * damping_ratio * np.sqrt(ks * inertia)
    return ks, kd
