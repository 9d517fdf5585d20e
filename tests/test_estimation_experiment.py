"""The closed-loop estimation experiment (hrp2_drake/paper/estimation.py): a short
run of both scenarios with noisy default sensors, its numbers and its report files."""

import json

import numpy as np
import pytest
from pydrake.common.yaml import yaml_load_typed

from hrp2_drake.paper import hrp2
from hrp2_drake.paper.claims import GOAL_RMS_OVER_PEAK
from hrp2_drake.paper.estimation import (
    EstimationConfig,
    JointSinusoid,
    near_reversals,
    run_estimation_experiment,
    sinusoid_reference,
)

LEG = [hrp2.JOINT_NAMES.index(j) for j in hrp2.RIGHT_LEG]


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    """Both scenarios, 3.7 s each (1 s settle + 2.7 s of motion), windows 20, 30, 40,
    80: about 10 s on one core."""
    out = tmp_path_factory.mktemp("estimation")
    # The `ideal` servo: the accuracy asserted here is the estimator's; reproduce
    # reports the calibrated servo's (its Coulomb jumps cost accuracy at window 80).
    config = EstimationConfig(
        windows=[20, 30, 40, 80], duration_scale=0.3, servo_file="ideal"
    )
    summary = run_estimation_experiment(config, out)
    return out, summary


def test_report_files(report):
    out, summary = report
    for name in (
        "estimation.md",
        "estimation.json",
        "estimation_tau_hanging.png",
        "estimation_tau_standing.png",
    ):
        assert (out / name).stat().st_size > 1000, name
    assert json.loads((out / "estimation.json").read_text()) == summary
    text = (out / "estimation.md").read_text()
    for scenario in ("hanging", "standing"):
        assert f"### {scenario}, paper window (80)" in text
        assert f"### {scenario}, best window" in text
    assert "RLEG_JOINT5 (ankle roll)" in text
    # The per-signal chain (encoders 17, IMU 41): its own section, one delay for all,
    # the longest window's centre, which the error-minimising shift confirms (within
    # 1.5 samples: measured −1.5 hanging, where the uniform windows' shift is −1, see
    # test_delay_is_the_chains).
    for scenario in ("hanging", "standing"):
        assert f"### {scenario}, per-signal windows (encoders 17, imu 41)" in text
        per_signal = summary["scenarios"][scenario]["per_signal"]
        assert per_signal["delay_samples"] == pytest.approx(20)
        assert abs(per_signal["best_shift_samples"] - 20) <= 1.5, per_signal


@pytest.mark.parametrize("scenario", ["hanging", "standing"])
def test_delay_is_the_chains(report, scenario):
    """The shift that minimises the error is the chain's delay within 1 sample (the
    encoders' second difference refers to the plant step after the sample, while
    joint_torque_true is stamped at the end of its step: measured −1 hanging, where
    q̈ carries the torque, 0 standing, where the F/T sensors do)."""
    for window, w in report[1]["scenarios"][scenario]["windows"].items():
        assert w["delay_samples"] == pytest.approx((int(window) - 1) / 2)
        assert abs(w["best_shift_samples"] - w["delay_samples"]) <= 1.0


def test_hanging_accuracy(report):
    """Hanging, right leg tracking sinusoids. Measured on this run: best window 40,
    worst right-leg RMS/peak 2.93 % (ankle roll: RMS 0.105 N·m, peak 3.6 N·m; 3.06 %
    at 30, 6.5 % at 80). The goal (< 3 %) is met, but only just: in the 10 s default
    run the best window is 30 at 2.36 % and 40 gives 3.18 %. The ankle roll's small
    torque jumps by ~1.5 N·m in ~30 ms at each of its velocity reversals (servo
    Coulomb friction and dead zone; the same with noiseless sensors), which long
    windows smooth away, while short ones let the quantized encoders' q̈ noise into
    the hips (window 20: ankle roll 1.5 %, hip roll 5.0 %, hip pitch 4.0 %). The
    bound keeps a margin over the measured value rather than the goal; see the
    report to the lead."""
    result = report[1]["scenarios"]["hanging"]
    best = result["windows"][str(result["best_window"])]
    assert result["best_window"] in (30, 40)
    assert best["right_leg_worst_ratio"] < 0.035
    assert np.max(np.array(best["ratio"])[LEG]) == best["right_leg_worst_ratio"]
    # Every right-leg joint's RMS error is a few tenths of a N·m at most.
    assert np.max(np.array(best["rms"])[LEG]) < 0.3
    paper = result["windows"]["80"]
    assert np.max(np.array(paper["rms"])[LEG]) < 0.35  # measured 0.23
    assert paper["right_leg_worst_ratio"] > best["right_leg_worst_ratio"]
    # The ankle roll's error is concentrated at its velocity reversals.
    share = best["right_leg_error_share_near_reversals"][5]
    time_share = best["right_leg_time_share_near_reversals"][5]
    assert share > 0.5 and time_share < 0.2  # measured 65 % in 11 % of the time


def test_standing_accuracy(report):
    """Standing (squat, sway, lean, chest yaw, arms): every right-leg joint loaded
    (peaks 3.8-63 N·m); measured worst right-leg RMS/peak 2.13 % at the best window
    (30; 2.47 % at 20, 2.66 % at 40), 6.0 % at 80 (hip yaw, the least loaded). Goal
    met (0.97 % at 40 in the 10 s default run)."""
    result = report[1]["scenarios"]["standing"]
    best = result["windows"][str(result["best_window"])]
    assert result["goal_met"]
    assert best["right_leg_worst_ratio"] < GOAL_RMS_OVER_PEAK
    assert np.min(np.array(best["peak"])[LEG]) > 3.0  # every joint is loaded
    assert np.max(np.array(best["rms"])[LEG]) < 0.4  # measured 0.26 (hip pitch)
    # The robot stayed up: the waist leans with the commanded 0.1 rad torso lean.
    assert result["base_max_tilt_rad"] < 0.15
    assert result["base_height_range_m"][0] > 0.55


def test_config_yaml_and_validation():
    config = yaml_load_typed(
        schema=EstimationConfig,
        data="""
windows: [40, 80]
duration: 3.0
motions:
  hanging:
    - {joint: RLEG_JOINT3, amplitude: 0.2, frequency: 1.0}
""",
    )
    config.validate()
    assert config.motion("hanging") == [JointSinusoid("RLEG_JOINT3", 0.2, 1.0)]
    assert len(config.motion("standing")) > 3  # the default
    with pytest.raises(RuntimeError, match="windw"):
        yaml_load_typed(schema=EstimationConfig, data="windw: [80]")
    for changes, match in [
        ({"windows": [40]}, "paper's 80"),
        ({"scenarios": ["flying"]}, "scenarios"),
        ({"windows": [80, 80]}, "duplicates"),
        ({"calibration_time": 1.0}, "calibration must end"),
        ({"motions": {"hanging": [JointSinusoid("KNEE")]}}, "KNEE"),
        ({"per_signal_windows": {"imu": 40}}, r"per_signal_windows: .*another parity"),
        (
            {"per_signal_windows": {"hip": 41}},
            r"per_signal_windows: .*'hip' is not a joint",
        ),
    ]:
        with pytest.raises(ValueError, match=match):
            EstimationConfig(**changes).validate()


def test_helpers():
    """The reference holds q0 until the start and ramps the sinusoid in; reversal
    masks per joint (the delayed truth: tests/test_accuracy.py)."""
    q0 = hrp2.half_sitting()
    t, q = sinusoid_reference(
        q0, [JointSinusoid("RLEG_JOINT3", 0.5, 1.0)], start=1.0, ramp=0.5, duration=3.0
    )
    knee = hrp2.JOINT_NAMES.index("RLEG_JOINT3")
    np.testing.assert_allclose(q[t <= 1.0], np.tile(q0, (np.sum(t <= 1.0), 1)))
    late = t >= 1.5
    np.testing.assert_allclose(
        q[late, knee], q0[knee] + 0.5 * np.sin(2 * np.pi * (t[late] - 1.0)), atol=1e-12
    )
    near = near_reversals(t, q[:, [knee]], 0.03)
    # Reversals at 1.75, 2.25, 2.75 s (the ramp's first one is earlier).
    for time in (1.75, 2.25, 2.75):
        assert near[np.argmin(np.abs(t - time)), 0]
    assert not near[np.argmin(np.abs(t - 2.0)), 0]
