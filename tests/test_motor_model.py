import numpy as np
import pytest

from hrp2_drake.identification.motor_model import (
    FitReport,
    MotorModel,
    PiecewiseLinearBranch,
    PiecewiseLinearMotorModel,
)


def _leg_model() -> MotorModel:
    # Table 1 of the paper, hip yaw, hip roll and knee (k_tau rad/(N·m), k_v s).
    return MotorModel(
        joint_names=["hip_yaw", "hip_roll", "knee"],
        k_tau=[0.212e-3, 0.030e-3, 0.051e-3],
        k_v=[13.0e-3, 6.332e-3, 6.561e-3],
        k_c=[1e-3, 0.0, -2e-3],
    )


def test_predict_one_sample_and_many():
    model = _leg_model()
    tau = np.array([10.0, -20.0, 30.0])
    dq = np.array([0.5, -1.0, 0.0])
    expected = np.array(
        [
            0.212e-3 * 10 + 13.0e-3 * 0.5 + 1e-3,
            0.030e-3 * -20 + 6.332e-3 * -1.0,
            0.051e-3 * 30,  # sign(0) = 0: no Coulomb term
        ]
    )
    np.testing.assert_allclose(model.predict(tau, dq), expected, rtol=1e-14)
    many = model.predict(np.tile(tau, (4, 1)), np.tile(dq, (4, 1)))
    np.testing.assert_allclose(many, np.tile(expected, (4, 1)), rtol=1e-14)


def test_one_joint_model_reads_1d_arrays_as_samples():
    model = MotorModel(["knee"], [2e-4], [7e-3])
    np.testing.assert_array_equal(model.k_c, [0.0])
    tau, dq = np.array([1.0, 2.0, 3.0]), np.array([-1.0, 0.0, 1.0])
    np.testing.assert_allclose(model.predict(tau, dq), 2e-4 * tau + 7e-3 * dq)


def test_predict_rejects_wrong_shapes():
    model = _leg_model()
    with pytest.raises(ValueError, match="differ"):
        model.predict(np.zeros(3), np.zeros(2))
    with pytest.raises(ValueError, match="n=3"):
        model.predict(np.zeros((5, 2)), np.zeros((5, 2)))


def test_lookup_subset_and_combine():
    model = _leg_model()
    assert model["knee"] == (0.051e-3, 6.561e-3, -2e-3)
    assert model.for_joint("hip_roll").k_v == 6.332e-3
    with pytest.raises(KeyError, match="ankle"):
        model.for_joint("ankle")

    sub = model.subset(["knee", "hip_yaw"])
    assert sub.joint_names == ["knee", "hip_yaw"]
    np.testing.assert_array_equal(sub.k_tau, [0.051e-3, 0.212e-3])
    with pytest.raises(KeyError, match="ankle"):
        model.subset(["ankle"])

    report = FitReport("least_squares", 100, 1e-4, 0.3)
    singles = {
        name: MotorModel(["joint"], *model[name], reports={"joint": report})
        for name in model.joint_names
    }
    combined = MotorModel.from_joints(singles)
    assert combined == model
    assert combined.reports == {name: report for name in model.joint_names}
    with pytest.raises(ValueError, match="has 3 joints, expected 1"):
        MotorModel.from_joints({"leg": model})


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(joint_names=[], k_tau=[], k_v=[]), "no joints"),
        (dict(joint_names=["a", "a"], k_tau=[1, 2], k_v=[1, 2]), "duplicate"),
        (dict(joint_names=["a", "b"], k_tau=[1], k_v=[1, 2]), "k_tau has 1 entries"),
        (dict(joint_names=["a"], k_tau=[1], k_v=[1], k_c=[1, 2]), "k_c has 2"),
        (dict(joint_names=["a", "b"], k_tau=[1, 2], k_v=[np.nan, 2]), r"k_v .*\['a'\]"),
    ],
)
def test_invalid_model_raises(kwargs, message):
    with pytest.raises(ValueError, match=message):
        MotorModel(**kwargs)


def test_yaml_round_trip(tmp_path):
    model = _leg_model()
    model.reports["knee"] = FitReport("least_squares", 10, 0.1, 0.5)
    path = tmp_path / "motor_model.yaml"
    model.save(path)
    loaded = MotorModel.load(path)
    assert loaded == model
    assert loaded.reports == {}  # diagnostics stay out of the file
    # bit-exact floats
    np.testing.assert_array_equal(loaded.k_tau, model.k_tau)


def test_yaml_without_k_c_means_zero(tmp_path):
    path = tmp_path / "table1.yaml"
    path.write_text("joint_names: [hip_pitch]\nk_tau: [0.12e-3]\nk_v: [7.0e-3]\n")
    model = MotorModel.load(path)
    assert model["hip_pitch"] == (0.12e-3, 7.0e-3, 0.0)


@pytest.mark.parametrize(
    "text, error, message",
    [
        (
            "joint_names: [a]\nk_tau: [1.0]\nk_v: [1.0]\nk_vv: [1.0]\n",
            RuntimeError,
            "k_vv",
        ),
        ("joint_names: [a, b]\nk_tau: [1.0]\nk_v: [1.0, 2.0]\n", ValueError, "k_tau"),
    ],
)
def test_yaml_load_rejects_bad_files(tmp_path, text, error, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(error, match=message):
        MotorModel.load(path)


def test_piecewise_linear_model_predicts_by_velocity_sign():
    # f(τ) = 0.1 τ for τ <= -1, τ + 0.9 in between, 0.1 τ + 1.8 for τ >= 1: continuous.
    positive = PiecewiseLinearBranch([0.1, 1.0, 0.1], [0.0, 0.9, 1.8], [-1.0, 1.0])
    negative = PiecewiseLinearBranch([0.2, 0.2, 0.2], [0.0, 0.0, 0.0], [-1.0, 1.0])
    model = PiecewiseLinearMotorModel("knee", positive, negative)
    tau = np.array([-3.0, -1.0, 0.0, 1.0, 3.0])
    np.testing.assert_allclose(positive(tau), [-0.3, -0.1, 0.9, 1.9, 2.1])
    np.testing.assert_allclose(
        model.predict(tau, np.full(5, 0.3)), [-0.3, -0.1, 0.9, 1.9, 2.1]
    )
    np.testing.assert_allclose(model.predict(tau, np.full(5, -0.3)), 0.2 * tau)
    np.testing.assert_allclose(
        model.predict(tau, np.zeros(5)), 0.5 * (positive(tau) + 0.2 * tau)
    )
    with pytest.raises(ValueError, match="τ1 < τ2"):
        PiecewiseLinearBranch([0, 0, 0], [0, 0, 0], [1.0, -1.0])
