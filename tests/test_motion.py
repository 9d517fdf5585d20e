"""The motion-tracking experiment (paper Sec. 5.3) on a short part of the climbing
motion, and the control builders it stands on."""

import json

import numpy as np
import pytest

from hrp2_drake.cli import main
from hrp2_drake.experiments.builders import TorqueControlConfig
from hrp2_drake.experiments.motion import (
    MotionConfig,
    average_error,
    climbing_reference,
    run_motion,
    write_motion_report,
)
from hrp2_drake.robot import model


def test_average_error_is_the_papers_formula():
    e = np.array([[3.0, 1.0], [4.0, 1.0]])
    np.testing.assert_allclose(average_error(e), [5.0 / 2, np.sqrt(2) / 2])


def test_climbing_reference_is_smooth_and_close_to_the_data():
    reference = climbing_reference(end=6.0)
    t, q = model.load_trajectory()
    for time in (1.0, 3.0, 5.5):
        q_ref, v_ref, a_ref = reference.at(time)
        k = int(round(time / 0.005))
        assert np.abs(q_ref - q[k]).max() < 1e-3  # rad
    a = np.array([reference.at(x)[2][3] for x in np.arange(0.5, 6, 0.01)])
    assert np.abs(a).max() < 180.0  # knee, rad/s² (the raw data's spikes smoothed)


@pytest.fixture(scope="module")
def short_motion(identified_model):
    config = MotionConfig(start=3.0, end=4.5, settle=0.7, k6=[1.0, 0.1])
    config.torque_control = TorqueControlConfig(start_time=0.5)
    return run_motion(config, identified_model)


@pytest.mark.slow
def test_torque_control_beats_position_control_at_k6_1_not_at_0_1(short_motion):
    runs = {r.label: r for r in short_motion.runs}
    position = runs["position control"]
    strong, weak = runs["torque control K6=1"], runs["torque control K6=0.1"]
    for run in (strong, weak):
        assert run.fallback_time is None
    assert np.all(np.array(strong.average_error) < np.array(position.average_error))
    assert np.all(np.array(strong.max_error) < np.array(position.max_error))
    assert np.sum(np.array(weak.average_error) > np.array(position.average_error)) >= 4
    # Absolute bounds: K6 = 1 tracks the swing within 10 mrad on every moving joint.
    assert max(strong.max_error) < 0.010
    # The torque estimate during the motion (against the delayed truth): < 10% of peak.
    rms, peak = np.array(strong.torque_estimation_rms), np.array(strong.torque_estimation_peak)
    assert np.all(rms[peak > 20] < 0.1 * peak[peak > 20])


@pytest.mark.slow
def test_paper_literal_controller_falls_back(short_motion):
    literal = [r for r in short_motion.runs if "literal" in r.label][0]
    assert literal.fallback_time is not None


@pytest.mark.slow
def test_motion_report(short_motion, tmp_path):
    summary = write_motion_report(short_motion, tmp_path)
    assert (tmp_path / "figure4_tracking_error.png").stat().st_size > 20000
    text = (tmp_path / "motion.md").read_text()
    assert "Table 2" in text and "(0.115)" in text  # the paper's knee value beside ours
    data = json.loads((tmp_path / "motion.json").read_text())
    assert len(data["runs"]) == 4 and data["verdicts"] == summary["verdicts"]


@pytest.mark.slow
def test_experiment_command_with_a_saved_model(identified_model, tmp_path):
    path = tmp_path / "model.yaml"
    identified_model.save(path)
    config = tmp_path / "motion.yaml"
    config.write_text("start: 3.0\nend: 3.6\nsettle: 0.7\nk6: [1.0]\n")
    out = tmp_path / "out"
    code = main(
        ["experiment", "motion", "--config", str(config), "--motor-model", str(path)]
        + ["--out", str(out)]
    )
    assert code == 0
    assert json.loads((out / "motion.json").read_text())["runs"][1]["k6"] == 1.0


def test_torque_control_config_errors():
    with pytest.raises(ValueError, match="must end before start_time"):
        TorqueControlConfig(offset_calibration_time=0.5).validate()
    with pytest.raises(ValueError, match="friction_velocity"):
        TorqueControlConfig(friction_velocity="measured").validate()
