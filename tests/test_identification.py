"""Motor identification on simulated data: collection, non-causal estimation, fits,
and the `hrp2-drake identify` command on a saved log (paper Sec. 3, 5.2)."""

import json

import numpy as np
import pytest

from hrp2_drake.cli import main
from hrp2_drake.description.excitation import SinusoidConfig
from hrp2_drake.identification.excitation import (
    PHASE_HIGH_TORQUE,
    PHASE_HIGH_VELOCITY,
    increasing_sinusoid,
    make_plan,
)
from hrp2_drake.identification.logs import load_log, save_log
from hrp2_drake.paper import hrp2


def test_increasing_sinusoid_is_the_papers_and_ends_at_rest():
    s = SinusoidConfig(
        joint="x",
        amplitude_start=0.02,
        amplitude_end=0.3,
        peak_velocity=1.5,
        duration=6.0,
    )
    t = np.linspace(0, s.end_time(), 5001)
    q = increasing_sinusoid(t, 0.1, s)
    a = (s.amplitude_end - s.amplitude_start) / s.end_time()
    np.testing.assert_allclose(
        q, 0.1 + (0.02 + a * t) * np.sin(2 * np.pi * s.frequency() * t)
    )
    assert abs(s.end_time() - s.duration) <= 0.5 / s.frequency()
    assert np.cos(2 * np.pi * s.frequency() * s.end_time()) == pytest.approx(
        0, abs=1e-9
    )
    assert np.abs(np.gradient(q, t)).max() == pytest.approx(1.5, rel=0.05)


def test_plan_rejects_unknown_joints():
    config = hrp2.description().identification.scaled(0.25, 0)
    config.sinusoids[0].joint = "RLEG_JOINT9"
    with pytest.raises(KeyError, match="RLEG_JOINT9"):
        make_plan(config, hrp2.JOINT_NAMES, hrp2.half_sitting())


@pytest.fixture(scope="module")
def short_log(short_identification):
    return short_identification[:3]


@pytest.mark.slow
def test_collection_excites_every_right_leg_joint(short_log):
    _, log, _ = short_log
    tau = log["joint_torque_true"][:, :6]
    pushes = log["phase"] == PHASE_HIGH_TORQUE
    # Large torques of both signs on every right-leg joint during the pushes...
    assert np.all(tau[pushes].max(axis=0) > 20) and np.all(
        tau[pushes].min(axis=0) < -20
    )
    # ...and each joint's own sinusoid reaches its peak velocity.
    for j in range(6):
        moving = (log["phase"] == PHASE_HIGH_VELOCITY) & (log["excited_joint"] == j)
        v = np.gradient(log["q_measured"][moving, j], log["t"][moving])
        assert np.abs(v).max() > 1.5


@pytest.mark.slow
def test_identification_recovers_the_emulator_within_10_percent(short_identification):
    result = short_identification[3]
    truth = hrp2.true_motor_model()
    k_tau = result.identified.k_tau
    k_v = result.identified.k_v
    np.testing.assert_allclose(k_tau, truth.k_tau, rtol=0.10)
    np.testing.assert_allclose(k_v, truth.k_v, rtol=0.10)
    for joint in result.joints:
        asym = joint.validation["asymmetric"]["overestimation"]
        symmetric = joint.validation["least_squares"]["overestimation"]
        assert asym < 0.05, joint.joint
        assert symmetric > asym, joint.joint
    # The non-causal torque estimate is within 3% of each joint's peak torque.
    assert np.all(result.estimation_rms[:6] < 0.03 * result.estimation_peak[:6])


@pytest.mark.slow
def test_identify_command_on_a_saved_log(short_log, tmp_path, capsys):
    config, log, names = short_log
    path = tmp_path / "robot_log.npz"
    # What a real robot records: no ground truth, no phase labels.
    real = {
        k: v
        for k, v in log.items()
        if k not in ("joint_torque_true", "phase", "excited_joint", "applied_wrench")
    }
    save_log(path, real, names)
    out = tmp_path / "out"
    assert main(["identify", "--log", str(path), "--out", str(out)]) == 0
    summary = json.loads((out / "identification.json").read_text())
    assert set(summary["joints"]) == set(hrp2.RIGHT_LEG)
    assert "emulator" not in summary["joints"]["RLEG_JOINT3"]  # no ground truth read
    assert (out / "figure1_torque_vs_delta_q.png").stat().st_size > 10000
    assert (out / "figure3_friction_fit.png").stat().st_size > 10000
    from hrp2_drake.identification.motor_model import MotorModel

    identified = MotorModel.load(out / "motor_model.yaml")
    assert identified.joint_names == list(hrp2.RIGHT_LEG)
    # Without labels every sample (moves between parts too) is used: still within 10%.
    truth = hrp2.true_motor_model()
    np.testing.assert_allclose(identified.k_tau, truth.k_tau, rtol=0.10)
    np.testing.assert_allclose(identified.k_v, truth.k_v, rtol=0.10)


def test_log_errors_name_the_problem(tmp_path):
    path = tmp_path / "bad.npz"
    np.savez(
        path, t=np.arange(3.0), joint_names=np.array(["a"]), q_cmd=np.zeros((3, 1))
    )
    with pytest.raises(ValueError, match="lacks"):
        load_log(path)
    m = 10
    np.savez(
        path,
        t=np.arange(m) * 1e-3,
        joint_names=np.array(["a", "b"]),
        q_cmd=np.zeros((m, 2)),
        q_measured=np.zeros((m, 3)),
        imu_linear_acceleration=np.zeros((m, 3)),
        imu_angular_velocity=np.zeros((m, 3)),
        wrench_foot=np.zeros((m, 6)),
    )
    with pytest.raises(ValueError, match="q_measured"):
        load_log(path)
