"""`hrp2-drake estimate` on a simulated iiwa log: the wrist F/T sensor's bias, warned
about without `--calibrate-offsets`, removed with it; bad segments get one line."""

import json

import pytest

from hrp2_drake.cli import main


@pytest.fixture(scope="module")
def iiwa_log(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    assert main(["simulate", "--robot", "iiwa14", "--duration", "1.5", "--out", str(out)]) == 0
    return next(out.glob("*.npz"))


def _estimate(log, out, *extra):
    assert main(["estimate", "--robot", "iiwa14", "--log", str(log), "--out", str(out),
                 *extra]) == 0
    return json.loads((out / "estimate.json").read_text())


def test_the_bias_is_warned_about_then_calibrated_away(iiwa_log, tmp_path, capsys):
    raw = _estimate(iiwa_log, tmp_path / "raw")
    assert len(raw["bias_warnings"]) == 1 and "sensor 'wrist'" in raw["bias_warnings"][0]
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


@pytest.mark.parametrize("segment, words", [
    ("0.6", "expected START:END"),
    ("0.6:0.2", "START must be < END"),
    ("0.2:9", "outside the log"),
    ("0.2:0.2001", "fewer than 10"),
])
def test_bad_segments_are_one_line(iiwa_log, tmp_path, capsys, segment, words):
    code = main(["estimate", "--robot", "iiwa14", "--log", str(iiwa_log), "--out",
                 str(tmp_path), "--calibrate-offsets", segment])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and words in err[0] and "--calibrate-offsets" in err[0]
