"""The gain mapping of paper Sec. 4.2 between the user's gains {K_p, K_s, K_d, K_f}
and the position-servo-like gains {K6, K7, K8, K9}: test-only algebra (no library
code uses it; tests/test_torque_controller.py checks the Δq controller's eq. 13-14
with it). Moved here from hrp2_drake/control/torque_controller.py (issue 28).

Sec. 4.2: with τ_d from eq. 12 and τ̂ = M_j q̂̈ + ĥ_j − J_jᵀ f̂, Δq is

    Δq = K_τ (M_j q̈_d + ĥ_j − J_jᵀ f_d) + K_v q̂̇                        (eq. 13)
         + K6 e_q + K7 ė_q + K8 ë_q + K9 e_f                          (eq. 14)

    K6 = K_τ (I + K_p) K_s        K7 = K_τ (I + K_p) K_d
    K8 = K_τ K_p M_j              K9 = −K_τ (K_p J_jᵀ (I + K_f) + J_jᵀ K_f)

`gains_from_user` and `user_from_gains` map one set to the other.
"""

from typing import NamedTuple

import numpy as np


class TorqueControlGains(NamedTuple):
    """The gains of eq. 14: K6, K7, K8 (n, n) and K9 (n, k), None without a force
    task. K6 is in rad/rad, K7 in s, K8 in s², K9 in rad/N (rad/(N·m) for torque
    rows of the wrench)."""

    k6: np.ndarray
    k7: np.ndarray
    k8: np.ndarray
    k9: np.ndarray | None


class UserGains(NamedTuple):
    """The user's gains: K_p (n, n), K_s (n, n, N·m/rad), K_d (n, n, N·m·s/rad),
    K_f (k, k), None without a force task."""

    kp: np.ndarray
    ks: np.ndarray
    kd: np.ndarray
    kf: np.ndarray | None


def _as_matrix(name: str, value, size: int) -> np.ndarray:
    """A number, a vector (a diagonal) or a (size, size) matrix as a matrix."""
    array = np.asarray(value, dtype=float)
    if array.ndim == 0 or (array.ndim == 1 and array.size == 1):
        matrix = float(array.reshape(-1)[0]) * np.eye(size)
    elif array.shape == (size,):
        matrix = np.diag(array)
    elif array.shape == (size, size):
        matrix = array.copy()
    else:
        raise ValueError(
            f"gain mapping: '{name}' has shape {array.shape}, expected a number, "
            f"({size},) or ({size}, {size})"
        )
    if not np.all(np.isfinite(matrix)):
        raise ValueError(f"gain mapping: '{name}' is not finite")
    return matrix


def _joint_count(*values) -> int:
    """n from the first of `values` that is a vector or a matrix (1 if none)."""
    for value in values:
        if value is not None and np.ndim(value) >= 1 and np.size(value) > 1:
            return int(np.shape(value)[0])
    return 1


def _check_shape(name: str, value, shape: tuple[int, ...]) -> np.ndarray:
    array = np.asarray(value, dtype=float)
    if array.shape != shape:
        raise ValueError(
            f"gain mapping: '{name}' has shape {array.shape}, expected {shape}"
        )
    if not np.all(np.isfinite(array)):
        raise ValueError(f"gain mapping: '{name}' is not finite")
    return array


def _check_jacobian(jacobian, n: int) -> np.ndarray:
    """J_j as a finite (k, n) float array (raises ValueError otherwise)."""
    J = np.asarray(jacobian, dtype=float)
    if J.ndim != 2 or J.shape[1] != n:
        raise ValueError(
            f"gain mapping: 'jacobian' has shape {J.shape}, expected (k, {n})"
        )
    return _check_shape("jacobian", J, J.shape)


def gains_from_user(
    k_tau,
    kp,
    ks,
    kd,
    kf,
    mass_matrix: np.ndarray,
    jacobian: np.ndarray | None,
) -> TorqueControlGains:
    """{K_p, K_s, K_d, K_f} → {K6, K7, K8, K9} given K_τ, M_j, J_j (paper Sec. 4.2).

    Args:
        k_tau: K_τ (rad/(N·m)): a number, an (n,) diagonal or an (n, n) matrix.
        kp, ks, kd: K_p, K_s (N·m/rad), K_d (N·m·s/rad): the same forms.
        kf: K_f: a number, a (k,) diagonal or a (k, k) matrix; ignored without a
            force task.
        mass_matrix: M_j (n, n), e.g. InverseDynamicsController.joint_space_model.
        jacobian: J_j (k, n), the force task's Jacobian in the frame of f; None
            without a force task (then K9 is None).
    """
    M = np.asarray(mass_matrix, dtype=float)
    if M.ndim != 2 or M.shape[0] != M.shape[1]:
        raise ValueError(
            f"gain mapping: 'mass_matrix' has shape {M.shape}, expected (n, n)"
        )
    n = M.shape[0]
    M = _check_shape("mass_matrix", M, (n, n))
    K_tau = _as_matrix("k_tau", k_tau, n)
    Kp = _as_matrix("kp", kp, n)
    I = np.eye(n)
    k6 = K_tau @ (I + Kp) @ _as_matrix("ks", ks, n)  # K6 = K_τ (I + K_p) K_s
    k7 = K_tau @ (I + Kp) @ _as_matrix("kd", kd, n)  # K7 = K_τ (I + K_p) K_d
    k8 = K_tau @ Kp @ M  # K8 = K_τ K_p M_j
    k9 = None
    if jacobian is not None:
        J = _check_jacobian(jacobian, n)
        Kf = _as_matrix("kf", kf, J.shape[0])
        # K9 = −K_τ (K_p J_jᵀ (I + K_f) + J_jᵀ K_f)
        k9 = -K_tau @ (Kp @ J.T @ (np.eye(J.shape[0]) + Kf) + J.T @ Kf)
    return TorqueControlGains(k6, k7, k8, k9)


def user_from_gains(
    k_tau,
    k6,
    k7,
    k9=None,
    jacobian: np.ndarray | None = None,
    *,
    kp=2.0,
    k8=None,
    mass_matrix: np.ndarray | None = None,
) -> UserGains:
    """{K6, K7, K9} (and K_p, or K8 with M_j) → {K_p, K_s, K_d, K_f}, the inverse of
    `gains_from_user` (paper Sec. 4.2).

    The set {K6, K7, K8, K9} over-determines the user's gains: K8 = K_τ K_p M_j fixes
    K_p by itself, so either K_p is given (default 2, the paper's) or it is computed
    from K8 and M_j (pass kp=None, k8 and mass_matrix): K_p = K_τ⁻¹ K8 M_j⁻¹.
    Then K_s = (K_τ (I + K_p))⁻¹ K6, K_d = (K_τ (I + K_p))⁻¹ K7, and K_f solves
    J_jᵀ K_f = (I + K_p)⁻¹ (−K_τ⁻¹ K9 − K_p J_jᵀ) (exactly when J_j has full row
    rank k, as the right leg's 6 x 6 Jacobian away from singularities).

    Args:
        k_tau: K_τ (rad/(N·m)): a number, an (n,) diagonal or an (n, n) matrix.
        k6, k7: K6, K7, same forms.
        k9: K9 (n, k); None without a force task (then K_f is None).
        jacobian: J_j (k, n), needed with k9.
        kp: K_p (same forms as k_tau), or None to compute it from k8 and mass_matrix.
        k8, mass_matrix: K8 and M_j (n, n), only with kp=None.

    Raises:
        ValueError: wrong shapes, singular K_τ (I + K_p) or M_j, a rank-deficient
            J_j, or a K9 that no K_f produces for these K_p, K_τ, J_j.
    """
    n = _joint_count(k_tau, k6, k7, kp, k8, mass_matrix)
    K_tau = _as_matrix("k_tau", k_tau, n)
    K6 = _as_matrix("k6", k6, n)
    K7 = _as_matrix("k7", k7, n)
    Kp = _user_kp(K_tau, kp, k8, mass_matrix, n)
    I = np.eye(n)
    A = K_tau @ (I + Kp)
    if np.linalg.cond(A) > 1e12:
        raise ValueError("user_from_gains: K_τ (I + K_p) is singular")
    ks = np.linalg.solve(A, K6)
    kd = np.linalg.solve(A, K7)
    kf = None
    if k9 is not None:
        if jacobian is None:
            raise ValueError("user_from_gains: k9 needs the jacobian")
        kf = _user_kf(K_tau, Kp, k9, _check_jacobian(jacobian, n))
    return UserGains(Kp, ks, kd, kf)


def _user_kp(K_tau: np.ndarray, kp, k8, mass_matrix, n: int) -> np.ndarray:
    """K_p of `user_from_gains`: `kp` as a matrix, or K_τ⁻¹ K8 M_j⁻¹ with kp=None."""
    if kp is None:
        if k8 is None or mass_matrix is None:
            raise ValueError("user_from_gains: with kp=None, give k8 and mass_matrix")
        K8 = _check_shape("k8", k8, (n, n))
        M = _check_shape("mass_matrix", mass_matrix, (n, n))
        # K8 = K_τ K_p M_j  →  K_p = K_τ⁻¹ K8 M_j⁻¹
        return np.linalg.solve(M.T, np.linalg.solve(K_tau, K8).T).T
    if k8 is not None or mass_matrix is not None:
        raise ValueError("user_from_gains: give kp, or k8 and mass_matrix, not both")
    return _as_matrix("kp", kp, n)


def _user_kf(K_tau: np.ndarray, Kp: np.ndarray, k9, J: np.ndarray) -> np.ndarray:
    """K_f of `user_from_gains`: the solution of J_jᵀ K_f = (I + K_p)⁻¹ (−K_τ⁻¹ K9 −
    K_p J_jᵀ), for a checked J_j (k, n) of full row rank and a K9 it can produce."""
    n, k = J.shape[1], J.shape[0]
    K9 = _check_shape("k9", k9, (n, k))
    if np.linalg.matrix_rank(J) < k:
        raise ValueError(
            f"user_from_gains: J_j has rank {np.linalg.matrix_rank(J)} < {k}: K_f "
            "is not determined by K9"
        )
    # K9 = −K_τ (K_p J_jᵀ + (I + K_p) J_jᵀ K_f)
    B = np.linalg.solve(np.eye(n) + Kp, -np.linalg.solve(K_tau, K9) - Kp @ J.T)
    kf, *_ = np.linalg.lstsq(J.T, B, rcond=None)
    residual = np.linalg.norm(J.T @ kf - B)
    if residual > 1e-8 * max(np.linalg.norm(B), 1e-300):
        raise ValueError(
            "user_from_gains: no K_f gives this K9 for these K_p, K_τ and J_j "
            f"(relative residual {residual / np.linalg.norm(B):.3g})"
        )
    return kf
