"""`hrp2-drake estimate` on a simulated iiwa log: the wrist F/T sensor's bias, warned
about without `--calibrate-offsets`, removed with it; bad segments get one line."""

import json
from pathlib import Path

import pytest

from hrp2_drake.cli import main


@pytest.fixture(scope="module")
def iiwa_log(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    assert (
        main(["simulate", "--robot", "iiwa14", "--duration", "1.5", "--out", str(out)])
        == 0
    )
    return next(out.glob("*.npz"))


def _estimate(log, out, *extra):
    assert (
        main(
            [
                "estimate",
                "--robot",
                "iiwa14",
                "--log",
                str(log),
                "--out",
                str(out),
                *extra,
            ]
        )
        == 0
    )
    return json.loads((out / "estimate.json").read_text())


def test_the_bias_is_warned_about_then_calibrated_away(iiwa_log, tmp_path, capsys):
    raw = _estimate(iiwa_log, tmp_path / "raw")
    assert (
        len(raw["bias_warnings"]) == 1 and "sensor 'wrist'" in raw["bias_warnings"][0]
    )
    assert "warning: sensor 'wrist'" in capsys.readouterr().out
    assert "**Warning:**" in (tmp_path / "raw" / "estimate.md").read_text()
    # Measured: A1 0.41 N·m RMS (the bias carried into τ̂), A4 1.1.
    assert raw["rms_error_vs_truth"]["iiwa_joint_1"] > 0.2
    calibrated = _estimate(iiwa_log, tmp_path / "cal", "--calibrate-offsets", "0.2:0.6")
    assert calibrated["bias_warnings"] == [] and "wrist" in calibrated["offsets"]
    # Measured: 0.05 (A1) to 0.11 (A4) N·m, 8-10x better on every loaded joint.
    for joint, rms in calibrated["rms_error_vs_truth"].items():
        assert rms < 0.2, joint
        assert rms < raw["rms_error_vs_truth"][joint] / 3 or rms < 0.01, joint


@pytest.mark.parametrize(
    "segment, words",
    [
        ("0.6", "expected START:END"),
        ("0.6:0.2", "START must be < END"),
        ("0.2:9", "outside the log"),
        ("0.2:0.2001", "fewer than 10"),
    ],
)
def test_bad_segments_are_one_line(iiwa_log, tmp_path, capsys, segment, words):
    code = main(
        [
            "estimate",
            "--robot",
            "iiwa14",
            "--log",
            str(iiwa_log),
            "--out",
            str(tmp_path),
            "--calibrate-offsets",
            segment,
        ]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert (
        code == 2
        and len(err) == 1
        and words in err[0]
        and "--calibrate-offsets" in err[0]
    )


def test_estimate_reads_a_robots_own_log(tmp_path):
    """`estimate --robot xl330_pendulum --log` its own BAM JSON (issue 28: refused as
    "a text file, expected an .npz archive"): read like `identify` and `validate`
    read it (resampled to 1 kHz), τ̂ that of the pendulum's closed form,
    (m l² + ρ² I_r) q̈ + m g l sin q on the same centred filters."""
    import numpy as np

    from hrp2_drake.description import load_robot_description
    from hrp2_drake.estimation.savitzky_golay import savgol_filter_offline
    from hrp2_drake.identification.logs import read_robot_log

    robot = load_robot_description("xl330_pendulum")
    source = Path(robot.source_file).parent / "logs" / "xl330_kp400_sin_sin.json"
    document = json.loads(source.read_text())
    document["entries"] = document["entries"][:300]  # 1.6 s
    path = tmp_path / "sin_sin.json"
    path.write_text(json.dumps(document))
    out = tmp_path / "out"
    assert (
        main(
            [
                "estimate",
                "--robot",
                "xl330_pendulum",
                "--log",
                str(path),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    log = read_robot_log(path, robot.logs, robot.joints)
    result = np.load(out / "estimate.npz")
    assert json.loads((out / "estimate.json").read_text())["samples"] == len(log.t)
    q, v, vdot = (x[:, 0] for x in savgol_filter_offline(log.q_measured, 1e-3, 81, 2))
    inertia = 0.49 * 0.1**2 + 1e-8 + 288.35**2 * 2.1648e-8
    tau = inertia * vdot + 0.49 * 9.81 * 0.1 * np.sin(q)
    np.testing.assert_allclose(result["v"][:, 0], v, rtol=0, atol=1e-12)
    np.testing.assert_allclose(result["tau"][:, 0], tau, rtol=0, atol=1e-6)
    assert np.abs(tau).max() > 0.1  # the pendulum swings: a torque to check
