"""The inverse dynamics' gains K_s, K_d for a position-feedback gain K6 of the Δq
controller (paper Sec. 4.2 and 5.3: K6 = K_τ (1 + K_p) K_s is the paper's tuning knob,
K6 = 1 the native position servo's position gain), or for a joint stiffness K_s
chosen in N·m/rad.
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
    # K6 / K_τ is the joint stiffness against a force τ̂ does not see
    # (`inverse_dynamics_gains`).
    ks = k6 / (k_tau * (1.0 + kp))
    return ks, _damping(ks, inertia, damping_ratio, where)


def inverse_dynamics_gains(
    stiffness, joint_inertia, kp=2.0, damping_ratio: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """K_s and K_d of eq. 12 for a joint stiffness K (N·m/rad, a number or (n,)): the
    stiffness the joint shows against a force the torque estimate τ̂ does not see (a
    hand on an arm without joint-torque or F/T sensors: τ̂ is the model's M q̈ + h).
    At rest τ̂ = h, so the Δq controller's K_p K_τ (τ* − τ̂) adds K_p K_s e_q to the
    servo's torque beside the feedforward's K_s e_q (eq. 13): the servo makes
    (1 + K_p) K_s e_q, and K_s = K / (1 + K_p) (K6 = K_τ K: K6 / K_τ is that
    stiffness). Against a force τ̂ does see (an F/T sensor between it and the
    joint), the stiffness is K_s = K / (1 + K_p) alone. K_d = 2 ζ sqrt(K_s M_jj)
    (`inverse_dynamics_gains_for_k6` says why), M_jj = `joint_inertia` (kg·m², a
    number or (n,)), K_p = `kp` (a number or (n,)).

    Returns:
        (ks, kd): (n,) arrays in N·m/rad and N·m·s/rad.
    """
    where = "inverse_dynamics_gains"
    n = max(np.size(stiffness), np.size(joint_inertia), np.size(kp))
    stiffness = gain_vector("stiffness", stiffness, n, where)
    inertia = gain_vector("joint_inertia", joint_inertia, n, where)
    kp = gain_vector("kp", kp, n, where)
    ks = stiffness / (1.0 + kp)
    return ks, _damping(ks, inertia, damping_ratio, where)


def _damping(ks, inertia, damping_ratio: float, where: str) -> np.ndarray:
    """K_d = 2 ζ sqrt(K_s M_jj) (N·m·s/rad)."""
    if not (math.isfinite(damping_ratio) and damping_ratio >= 0):
        raise ValueError(f"{where}: damping_ratio={damping_ratio} must be >= 0")
    return 2.0 * damping_ratio * np.sqrt(ks * inertia)
