"""`hrp2-drake calibrate`: the priors from the authors' measurements, the servo it
builds, the committed servo.yaml, and a short end-to-end run."""

import json

import numpy as np
import pytest

from hrp2_drake.cli import main
from hrp2_drake.paper import hrp2
from hrp2_drake.paper.calibrate import (
    PWL_FITS,
    CalibrationConfig,
    build_servo,
    pwl_priors,
)
from hrp2_drake.robot.servo import (
    effective_motor_parameters,
    load_servo_params,
    save_servo_params,
)

TABLE1 = hrp2.description().published_motor_model  # the paper's Table 1: 10³ Kτ, 10³ Kv
TABLE1_K_TAU, TABLE1_K_V = np.array([TABLE1[j] for j in hrp2.RIGHT_LEG]).T * 1e-3


def test_pwl_priors_are_the_central_segments_of_the_authors_fits():
    # Right knee: + branch slope 2.415e-3 between 2.521 and 2.827 N·m, - branch 8.33e-4
    # between -8.328 and -7.159 N·m (sot-torque-control's PWL file).
    half_width, coulomb = pwl_priors("RLEG_JOINT3")
    widths = [2.415e-3 * (2.827010 - 2.521347), 8.33e-4 * (-7.158899 + 8.327572)]
    assert half_width == pytest.approx(np.mean(widths) / 2, rel=1e-3)
    centres = [(2.521347 + 2.827010) / 2, (-8.327572 - 7.158899) / 2]
    assert coulomb == pytest.approx((centres[0] - centres[1]) / 2, rel=1e-6)
    # Every leg joint has a fit; the left hip yaw's + branch did not converge.
    assert set(PWL_FITS) == set(hrp2.JOINT_NAMES[:12])
    assert pwl_priors("LLEG_JOINT0")[1] is None


def test_build_servo_keeps_table1_and_adds_the_mechanisms():
    config = CalibrationConfig()
    speeds = {j: 5.0 + k for k, j in enumerate(hrp2.RIGHT_LEG[1:])}
    servo = build_servo(config, speeds)
    eff = effective_motor_parameters(servo, hrp2.RIGHT_LEG)
    # servo_ideal.yaml keeps 9 significant digits.
    np.testing.assert_allclose(eff["k_tau"], TABLE1_K_TAU, rtol=1e-7)
    np.testing.assert_allclose(eff["k_v"], TABLE1_K_V, rtol=1e-7)  # latency included
    np.testing.assert_allclose(eff["latency"], config.latency)
    np.testing.assert_allclose(
        eff["deadzone"], [pwl_priors(j)[0] for j in hrp2.RIGHT_LEG], rtol=1e-12
    )
    p = servo.vectors(hrp2.JOINT_NAMES)
    # The left leg mirrors the right leg's no-load speeds; hip yaws and the upper
    # body have no voltage limit (no data).
    np.testing.assert_allclose(p["no_load_speed"][7:12], p["no_load_speed"][1:6])
    assert np.isinf(p["no_load_speed"][0]) and np.all(np.isinf(p["no_load_speed"][12:]))
    # The left hip yaw takes the right one's Coulomb friction.
    assert p["k3"][6] == pytest.approx(p["k3"][0])


def test_committed_servo_is_what_calibrate_writes(tmp_path):
    """models/hrp2/servo.yaml = build_servo(defaults, its own no-load speeds): nothing
    in it was edited by hand."""
    committed = load_servo_params()
    speeds = {j: committed.joints[j].no_load_speed for j in hrp2.RIGHT_LEG[1:]}
    rebuilt = build_servo(CalibrationConfig(), speeds)
    path = tmp_path / "servo.yaml"
    save_servo_params(rebuilt, path, ["test"])
    again = load_servo_params(path)
    for name in hrp2.JOINT_NAMES:
        a, b = committed.joints[name], again.joints[name]
        for key, value in vars(a).items():
            assert getattr(b, key) == pytest.approx(value, rel=1e-8), (name, key)


def test_config_errors_are_one_line():
    with pytest.raises(ValueError, match="no_load_speed_bounds"):
        CalibrationConfig(no_load_speed_bounds=[5.0, 2.0]).validate()
    with pytest.raises(ValueError, match="jobs"):
        CalibrationConfig(jobs=3).validate()


@pytest.mark.slow
def test_calibrate_command_end_to_end(tmp_path):
    """A short calibration (the first swing, one optimizer step): the servo file, the
    report with its fit table and plots; the voltage limit is what raises the knee's
    error above the ideal preset's."""
    config = tmp_path / "calibrate.yaml"
    config.write_text("settle: 0.5\nend: 4.2\nmax_iterations: 1\n")
    out = tmp_path / "calibrate"
    assert main(["calibrate", "--config", str(config), "--out", str(out)]) == 0
    servo = load_servo_params(out / "servo.yaml")
    assert np.all(np.isfinite(servo.vectors(hrp2.RIGHT_LEG[1:])["no_load_speed"]))
    report = (out / "calibration.md").read_text()
    assert "## Fit per joint" in report and "## Table 2's N" in report
    for figure in (
        "calibration_history.png",
        "calibration_fit.png",
        "calibration_knee_error.png",
    ):
        assert (out / figure).stat().st_size > 10000
        assert f"({figure})" in report
    summary = json.loads((out / "calibration.json").read_text())
    assert 10000 < summary["sample_count"]["n"] < 13000
    assert len(summary["history"]) == 2  # the point and its finite-difference neighbour
    knee = 2
    assert summary["max_error"][knee] > 1.5 * summary["ideal"]["max"][knee]
    assert (
        summary["ablation"]["voltage_limit off"]["max"][knee]
        < summary["max_error"][knee]
    )
