import numpy as np
import pytest

from hrp2_drake.identification.fitting import (
    fit_asymmetric,
    fit_joints,
    fit_least_squares,
    fit_piecewise_linear,
    fit_two_stage,
    overestimation_share,
)
from hrp2_drake.identification.motor_model import MotorModel, PiecewiseLinearBranch

K_TAU = 0.177e-3  # rad/(N·m), Table 1, ankle pitch
K_V = 7.698e-3  # s


def _identification_log(
    seed: int,
    m: int,
    dead_zone: float = 0.0,
    coulomb: float = 0.0,
    noise: float = 0.0,
    static_velocity_noise: float = 1e-3,
):
    """Synthetic log (τ, q̇, Δq) of one joint, mimicking the data of Sec. 3.4.

    Half the samples are high-torque pushes at zero velocity (Sec. 3.4.1), half follow
    the increasing-amplitude sinusoid q = (a0 + a t) sin(2π f t) (Sec. 3.4.2). Δq
    follows eq. 6 plus a dead zone of the current control: an offset dead_zone *
    sign(i), with the current i needed for the joint torque plus a viscous friction.
    """
    rng = np.random.default_rng(seed)
    m_static = m // 2
    tau_static = 80.0 * np.sin(2 * np.pi * rng.uniform(size=m_static))
    dq_static = static_velocity_noise * rng.standard_normal(m_static)
    t = np.sort(rng.uniform(0.0, 20.0, m - m_static))
    a0, a, omega = 0.05, 0.03, 2 * np.pi * 0.5
    amplitude = a0 + a * t
    q = amplitude * np.sin(omega * t)
    dq_moving = a * np.sin(omega * t) + amplitude * omega * np.cos(omega * t)
    ddq = 2 * a * omega * np.cos(omega * t) - amplitude * omega**2 * np.sin(omega * t)
    tau_moving = 2.0 * ddq + 10.0 * np.sin(q)  # inertia 2 kg·m², gravity 10 N·m
    tau = np.concatenate([tau_static, tau_moving])
    dq = np.concatenate([dq_static, dq_moving])
    current_sign = np.sign(tau + 30.0 * dq)  # 30 N·m·s/rad viscous friction
    delta_q = (
        K_TAU * tau
        + K_V * dq
        + coulomb * np.sign(dq)
        + dead_zone * current_sign
        + noise * rng.standard_normal(m)
    )
    return tau, dq, delta_q


@pytest.mark.parametrize("coulomb", [False, True])
def test_least_squares_recovers_exact_parameters(coulomb):
    k_c = 1.5e-3 if coulomb else 0.0
    tau, dq, delta_q = _identification_log(0, 2000, coulomb=k_c)
    model = fit_least_squares(tau, dq, delta_q, coulomb=coulomb, joint_name="ankle")
    assert model.joint_names == ["ankle"]
    assert model["ankle"] == pytest.approx((K_TAU, K_V, k_c), rel=1e-9, abs=1e-15)
    report = model.reports["ankle"]
    assert report.samples == 2000 and report.residual_rms < 1e-15


@pytest.mark.parametrize(
    "m, coulomb, w", [(1000, False, 100.0), (4000, False, 100.0), (2000, True, 1e4)]
)
def test_newton_and_qp_agree(m, coulomb, w):
    log = _identification_log(1, m, dead_zone=2e-3, noise=2e-4)
    newton = fit_asymmetric(*log, w=w, method="newton", coulomb=coulomb)
    qp = fit_asymmetric(*log, w=w, method="qp", coulomb=coulomb)
    np.testing.assert_allclose(qp.k_tau, newton.k_tau, rtol=1e-6)
    np.testing.assert_allclose(qp.k_v, newton.k_v, rtol=1e-6)
    if coulomb:
        np.testing.assert_allclose(qp.k_c, newton.k_c, rtol=1e-6)
    # The optimum differs from least squares: the penalty is really asymmetric.
    assert abs(newton.k_v[0] - fit_least_squares(*log).k_v[0]) > 1e-4


def test_asymmetric_with_unit_weight_is_least_squares():
    log = _identification_log(2, 3000, dead_zone=2e-3, noise=2e-4)
    asymmetric = fit_asymmetric(*log, w=1.0)
    least_squares = fit_least_squares(*log)
    np.testing.assert_allclose(asymmetric.k_tau, least_squares.k_tau, rtol=1e-10)
    np.testing.assert_allclose(asymmetric.k_v, least_squares.k_v, rtol=1e-10)


def test_asymmetric_fit_rarely_overestimates_held_out_data():
    training = _identification_log(3, 5000, dead_zone=2e-3, noise=2e-4)
    held_out = _identification_log(4, 5000, dead_zone=2e-3, noise=2e-4)
    asymmetric = fit_asymmetric(*training, w=100.0)
    least_squares = fit_least_squares(*training)
    assert overestimation_share(asymmetric, *held_out) < 0.05
    assert overestimation_share(least_squares, *held_out) > 0.25
    assert asymmetric.reports["joint"].overestimation_share < 0.05
    assert asymmetric.reports["joint"].method == "asymmetric newton"


def test_overestimation_share_counts_beyond_the_data_sign():
    model = MotorModel(["j"], [1.0], [0.0])
    tau = np.array([2.0, 0.5, -2.0, -0.5, 0.1])
    delta_q = np.array([1.0, 1.0, -1.0, -1.0, 0.0])
    # over-estimated: 2 > 1 and -2 < -1, and 0.1 > 0 (Δq = 0 counts as positive)
    assert overestimation_share(model, tau, np.zeros(5), delta_q) == pytest.approx(0.6)
    two_joints = MotorModel(["a", "b"], [1.0, 0.1], [0.0, 0.0])
    shares = overestimation_share(
        two_joints, np.tile(tau, (2, 1)).T, np.zeros((5, 2)), np.tile(delta_q, (2, 1)).T
    )
    np.testing.assert_allclose(shares, [0.6, 0.2])


def test_two_stage_recovers_k_tau():
    tau, dq, delta_q = _identification_log(5, 4000, noise=1e-5)
    model = fit_two_stage(tau, dq, delta_q, zero_velocity_threshold=0.01, w=100.0)
    assert model.k_tau[0] == pytest.approx(K_TAU, rel=0.01)
    assert model.k_v[0] == pytest.approx(K_V, rel=0.02)
    assert model.reports["joint"].method == "two_stage newton"
    qp = fit_two_stage(tau, dq, delta_q, zero_velocity_threshold=0.01, method="qp")
    np.testing.assert_allclose(
        [qp.k_tau[0], qp.k_v[0]], [model.k_tau[0], model.k_v[0]], rtol=1e-6
    )


def test_two_stage_needs_both_sets():
    tau, dq, delta_q = _identification_log(6, 1000)
    with pytest.raises(ValueError, match=r"'knee', stage 1 \(0 samples.*too few"):
        fit_two_stage(tau, np.abs(dq) + 1.0, delta_q, 0.01, joint_name="knee")
    with pytest.raises(ValueError, match=r"'knee', stage 2 \(0 samples.*too few"):
        fit_two_stage(tau, dq, delta_q, 100.0, joint_name="knee")
    with pytest.raises(ValueError, match="zero_velocity_threshold"):
        fit_two_stage(tau, dq, delta_q, 0.0)


def _continuous_branch(breakpoints, slopes, q1) -> PiecewiseLinearBranch:
    (t1, t2), (k1, k2, k3) = breakpoints, slopes
    q2 = q1 + (k1 - k2) * t1
    return PiecewiseLinearBranch(slopes, [q1, q2, q2 + (k2 - k3) * t2], breakpoints)


def test_piecewise_linear_recovers_each_branch():
    positive = _continuous_branch([-0.3, 0.7], [2e-4, 4e-3, 1.5e-4], -2e-3)
    negative = _continuous_branch([-0.8, 0.2], [1.8e-4, 5e-3, 2.2e-4], -1e-3)
    rng = np.random.default_rng(7)
    m = 4000
    tau = np.concatenate([rng.uniform(-30, 30, m // 2), rng.uniform(-2, 2, m // 2)])
    dq = rng.choice([-1.0, 1.0], m) * rng.uniform(0.01, 1.0, m)
    delta_q = np.where(dq > 0, positive(tau), negative(tau))

    model = fit_piecewise_linear(tau, dq, delta_q, joint_name="hip_pitch")
    for fitted, true in ((model.positive, positive), (model.negative, negative)):
        np.testing.assert_allclose(fitted.breakpoints, true.breakpoints, atol=1e-6)
        np.testing.assert_allclose(fitted.slopes, true.slopes, rtol=1e-6)
        np.testing.assert_allclose(fitted.intercepts, true.intercepts, atol=1e-9)
        # continuous at the breakpoints
        for i, t in enumerate(fitted.breakpoints):
            left = fitted.slopes[i] * t + fitted.intercepts[i]
            right = fitted.slopes[i + 1] * t + fitted.intercepts[i + 1]
            assert left == pytest.approx(right, abs=1e-15)
    assert model.reports["positive"].converged
    assert model.reports["positive"].iterations <= 10
    np.testing.assert_allclose(model.predict(tau, dq), delta_q, atol=1e-12)


def test_piecewise_linear_bounds_the_central_slope():
    positive = _continuous_branch([-0.3, 0.7], [2e-4, 4e-3, 1.5e-4], -2e-3)
    rng = np.random.default_rng(8)
    tau = rng.uniform(-5, 5, 2000)
    dq = rng.choice([-1.0, 1.0], 2000)
    delta_q = positive(tau)
    model = fit_piecewise_linear(tau, dq, delta_q, central_slope_bounds=(0.0, 2e-3))
    assert model.positive.slopes[1] == pytest.approx(2e-3)


def test_piecewise_linear_raises_without_central_samples():
    rng = np.random.default_rng(9)
    tau = rng.choice([-1.0, 1.0], 1000) * rng.uniform(1.0, 30.0, 1000)
    dq = rng.choice([-1.0, 1.0], 1000)
    with pytest.raises(
        ValueError, match=r"'knee', branch v > 0: segment 2.* 0 samples"
    ):
        fit_piecewise_linear(tau, dq, 1e-4 * tau, joint_name="knee")


def test_fit_joints_combines_columns():
    ankle = _identification_log(10, 1000)
    knee = tuple(2.0 * x for x in _identification_log(11, 1000))  # Δq/τ unchanged
    tau, dq, delta_q = (np.column_stack([a, k]) for a, k in zip(ankle, knee))
    model = fit_joints(fit_least_squares, tau, dq, delta_q, ["ankle", "knee"])
    assert model.joint_names == ["ankle", "knee"]
    np.testing.assert_allclose(model.k_tau, [K_TAU, K_TAU], rtol=1e-9)
    assert set(model.reports) == {"ankle", "knee"}


def _bad_logs():
    """Logs that cannot identify the model, each with the error it must raise."""
    tau, dq, delta_q = _identification_log(12, 200, dead_zone=1e-3)
    nan_dq = dq.copy()
    nan_dq[5] = np.nan
    return {
        "mismatched lengths": ((tau, dq[:-1], delta_q), "mismatched lengths"),
        "nan": ((tau, nan_dq, delta_q), "v has 1 NaN or inf"),
        "no motion": ((tau, 1e-5 * dq, delta_q), "no motion"),
        "no torque": ((0 * tau, dq, delta_q), "no torque"),
        "rank deficiency": ((3 * dq, dq, delta_q), "rank-deficient"),
        "2-D": ((tau[:, None], dq, delta_q), "tau must be a 1-D array"),
        "zero delta_q": ((tau, dq, 0 * delta_q), "delta_q is zero everywhere"),
        "few samples": ((tau[:5], dq[:5], delta_q[:5]), "too few samples"),
    }


@pytest.mark.parametrize("fit", [fit_least_squares, fit_asymmetric])
@pytest.mark.parametrize("problem", list(_bad_logs()))
def test_bad_data_raise_naming_joint_and_problem(fit, problem):
    log, message = _bad_logs()[problem]
    with pytest.raises(ValueError, match=r"joint 'ankle_roll'.*" + message):
        fit(*log, joint_name="ankle_roll")


@pytest.mark.parametrize("problem", ["mismatched lengths", "nan", "no torque"])
def test_bad_data_raise_in_two_stage_and_piecewise_fits(problem):
    log, message = _bad_logs()[problem]
    with pytest.raises(ValueError, match=r"joint 'knee'.*" + message):
        fit_two_stage(*log, 0.01, joint_name="knee")
    if problem != "no torque":  # the piecewise fit needs no torque column
        with pytest.raises(ValueError, match=r"joint 'knee'.*" + message):
            fit_piecewise_linear(*log, joint_name="knee")


def test_bad_options_raise():
    log = _identification_log(13, 200)
    with pytest.raises(ValueError, match="w must be"):
        fit_asymmetric(*log, w=0.5)
    with pytest.raises(ValueError, match="method must be"):
        fit_asymmetric(*log, method="cvx")
    # q̇ > 0 everywhere: the Coulomb column sign(q̇) = 1 equals the torque column.
    tau, dq = np.ones(50), np.linspace(1.0, 2.0, 50)
    with pytest.raises(ValueError, match="rank-deficient"):
        fit_least_squares(tau, dq, 1e-3 * dq, coulomb=True)
