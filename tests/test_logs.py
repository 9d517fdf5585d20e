"""Real robots' logs in (issue 18): import at any rate, the valid mask, pooling gains,
one clear line for every bad log. Small slices of the real XL330 logs of
models/xl330_pendulum/logs (Rhoban's BAM, Apache-2.0)."""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from hrp2_drake.assembly.identification import IdentifyConfig
from hrp2_drake.cli import main
from hrp2_drake.description import load_robot_description
from hrp2_drake.identification.dataset import check_logs
from hrp2_drake.identification.joint_fits import identify_logs
from hrp2_drake.identification.logs import read_logs, read_robot_log, window_samples
from hrp2_drake.robot.station import StationConfig

ROBOT = "xl330_pendulum"
LOGS = Path(__file__).resolve().parents[1] / "models" / ROBOT / "logs"


@pytest.fixture(scope="module")
def robot():
    return load_robot_description(ROBOT)


def _bam(name: str) -> dict:
    return json.loads((LOGS / f"{name}.json").read_text())


def _write(tmp_path: Path, name: str, document: dict) -> Path:
    path = tmp_path / f"{name}.json"
    path.write_text(json.dumps(document))
    return path


def _config(**changes) -> IdentifyConfig:
    station = StationConfig(robot=ROBOT, scenario="fixed_base")
    return dataclasses.replace(
        IdentifyConfig(station=station, fit="least_squares"), **changes
    )


def test_a_jittery_bam_log_imports_on_a_uniform_grid(robot):
    raw = _bam("xl330_kp400_sin_sin")
    stamps = np.array([e["timestamp"] for e in raw["entries"]])
    steps = np.diff(stamps)
    assert steps.max() > 1.1 * np.median(
        steps
    )  # the old constant-grid check refused it
    log = read_robot_log(LOGS / "xl330_kp400_sin_sin.json", robot.logs, robot.joints)
    assert log.gain == 400.0
    assert 185 < log.raw_rate < 195
    np.testing.assert_allclose(np.diff(log.t), 1e-3, atol=1e-12)
    assert log.t[-1] == pytest.approx(stamps[-1] - stamps[0], abs=1e-3)
    # Measured position: interpolated between raw samples; command: held.
    raw_t = stamps - stamps[0]
    k = 1000
    before = np.searchsorted(raw_t, log.t[k], side="right") - 1
    assert log.q_cmd[k, 0] == raw["entries"][before]["goal_position"]
    lo, hi = sorted(
        (raw["entries"][before]["position"], raw["entries"][before + 1]["position"])
    )
    assert lo - 1e-12 <= log.q_measured[k, 0] <= hi + 1e-12


def test_the_valid_mask_follows_torque_enable(robot):
    log = read_robot_log(
        LOGS / "xl330_kp100_lift_and_drop.json", robot.logs, robot.joints
    )
    off = np.flatnonzero(~log.valid)
    assert log.valid[0] and not log.valid[-1]
    assert 1.9 < log.t[off[0]] < 2.1  # BAM switches the servo off at about 2 s
    assert np.all(~log.valid[off[0] :])


def test_windows_in_seconds_are_odd_sample_counts():
    assert window_samples(0.081, 0.001) == 81
    assert window_samples(0.08, 0.001) == 81
    assert window_samples(0.1, 0.005) == 21
    with pytest.raises(ValueError, match="fewer than 3 samples"):
        window_samples(0.01, 0.02, "IdentifyConfig.window")


def test_identification_leaves_out_servo_off_and_saturated_samples(robot):
    logs, rows = read_logs(
        [LOGS / "xl330_kp400_lift_and_drop.json", LOGS / "xl330_kp400_sin_sin.json"],
        robot,
    )
    result = identify_logs(robot, _config(), logs)
    data = result.data
    assert [r["log"] for r in rows] == [
        "xl330_kp400_lift_and_drop",
        "xl330_kp400_sin_sin",
    ]
    assert set(np.unique(data.segment)) == {0, 1}
    # No training sample lies where the servo was off (the drop of the first log).
    first = data.segment == 0
    assert not np.any(result.train & first & (data.t > 2.1))
    assert result.excluded["output saturated"] > 0
    assert not np.any(result.train & data.saturated[:, 0])


def test_logs_of_two_gains_pool_into_one_gain_aware_model(robot):
    paths = [LOGS / f"xl330_kp{kp}_sin_sin.json" for kp in (100, 400)]
    logs, _ = read_logs(paths, robot)
    result = identify_logs(robot, _config(), logs)
    model = result.identified
    assert model.gain == 100.0 and model.fit == "least_squares"
    per_gain = result.joints[0].per_gain
    assert set(per_gain) == {100.0, 400.0}
    k_tau_gain = [per_gain[g]["least_squares"]["k_tau"] for g in (100.0, 400.0)]
    # Kτ · kp of the two gains' separate fits agree (a P servo: output = kp Δq) and
    # the pooled model sits between them.
    assert max(k_tau_gain) / min(k_tau_gain) < 1.15
    assert min(k_tau_gain) <= model.k_tau[0] * 100.0 <= max(k_tau_gain)
    assert model.at_gain(400.0).k_tau[0] == pytest.approx(model.k_tau[0] / 4)


def _sliced(name: str, count: int = 400) -> dict:
    document = _bam(name)
    document["entries"] = document["entries"][:count]
    return document


def _case_unknown_column(document):
    for entry in document["entries"]:
        entry["pos"] = entry.pop("position")


def _case_backwards(document):
    document["entries"][50]["timestamp"] = document["entries"][48]["timestamp"]


def _case_gap(document):
    for entry in document["entries"][200:]:
        entry["timestamp"] += 0.5


def _case_no_valid(document):
    for entry in document["entries"]:
        entry["torque_enable"] = False


def _case_text(document):
    document["entries"][7]["position"] = "n/a"


BAD_LOGS = {
    # case: (edit, what the one line must say)
    "unknown column": (_case_unknown_column, "no column 'position' (logs.position[0])"),
    "timestamp backwards": (
        _case_backwards,
        "timestamp 'timestamp' goes backwards at sample 50",
    ),
    "gap longer than the window": (_case_gap, "longer than the filter window 0.081 s"),
    "no valid sample": (_case_no_valid, "no valid sample: column 'torque_enable'"),
    "text in a column": (
        _case_text,
        "column 'position' (logs.position[0]) has 1 values",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_LOGS))
def test_a_bad_log_gets_one_line(case, tmp_path, capsys):
    edit, expected = BAD_LOGS[case]
    document = _sliced("xl330_kp400_sin_sin")
    edit(document)
    path = _write(tmp_path, "bad", document)
    code = main(
        [
            "identify",
            "--robot",
            ROBOT,
            "--log",
            str(path),
            "--out",
            str(tmp_path / "out"),
        ]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1, err
    assert str(path) in err[0] and expected in err[0], err[0]


def test_pooling_gains_needs_every_logs_gain(tmp_path, capsys):
    with_gain = _write(tmp_path, "kp400", _sliced("xl330_kp400_sin_sin"))
    document = _sliced("xl330_kp100_sin_sin")
    del document["kp"]
    without = _write(tmp_path, "no_gain", document)
    code = main(
        [
            "identify",
            "--robot",
            ROBOT,
            "--log",
            str(with_gain),
            str(without),
            "--out",
            str(tmp_path / "out"),
        ]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert "no_gain.json: states no servo gain" in err[0]


def test_identify_a_bam_log_as_it_is(tmp_path, capsys):
    out = tmp_path / "out"
    path = _write(tmp_path, "slice", _sliced("xl330_kp400_sin_time_square", 1100))
    assert (
        main(
            [
                "identify",
                "--robot",
                ROBOT,
                "--log",
                str(path),
                "--fit",
                "least-squares",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    captured = capsys.readouterr()
    assert "least squares fit at servo gain 400" in captured.out
    assert "error" not in captured.err.lower()
    report = (out / "identification.md").read_text()
    assert (
        "paper" not in report.split("## Table 1")[1].split("##")[0]
    )  # no empty columns
    assert "emulator Kτ" not in report
    for fit in ("least_squares", "asymmetric", "coulomb", "two_stage"):
        assert (out / f"motor_model_{fit}.yaml").is_file()
    assert (out / "figure1_torque_vs_delta_q.png").is_file()


def _every(document: dict, k: int) -> dict:
    """The log with every k-th sample only: a robot that logs k times slower."""
    document["entries"] = document["entries"][::k]
    return document


def test_the_lowest_rate_follows_from_the_window(robot, tmp_path, capsys):
    """A log at 47.5 Hz (every 4th sample of a 190 Hz BAM log; BAM's Feetech logs are
    at 48.7 Hz) fills the 81 ms window with 3.9 raw samples: accepted. At 23.7 Hz it
    holds 1.9: refused on one line with the numbers, not as a time-unit error."""
    slow = _write(tmp_path, "slow", _every(_bam("xl330_kp400_sin_sin"), 4))
    log = read_robot_log(slow, robot.logs, robot.joints)
    assert 45 < log.raw_rate < 50
    check_logs([log], 0.081, "IdentifyConfig.window")  # no error
    slower = _write(tmp_path, "slower", _every(_bam("xl330_kp400_sin_sin"), 8))
    rate = read_robot_log(slower, robot.logs, robot.joints).raw_rate
    code = main(
        [
            "identify",
            "--robot",
            ROBOT,
            "--log",
            str(slower),
            "--out",
            str(tmp_path / "out"),
        ]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    line = err[0]
    assert f"slower.json: sampled at {rate:.4g} Hz" in line, line
    assert (
        f"window 0.081 s (IdentifyConfig.window) spans {0.081 * rate:.2f} raw" in line
    )
    assert "fewer than the 3 a window needs" in line, line
    assert f">= {3 / 0.081:.4g} Hz" in line and f">= {3 / rate:.4g} s" in line, line
    assert "time_unit" not in line


def test_identify_validates_its_config_once_and_reads_no_servo_file(
    tmp_path, capsys, monkeypatch
):
    """`identify --log`: IdentifyConfig.validate runs once (it ran three times), and
    no simulated station is validated (its servo file): logs need the robot's
    description only."""
    from hrp2_drake.robot import station

    calls = {"identify": 0, "station": 0}
    validate = IdentifyConfig.validate

    def counted(self):
        calls["identify"] += 1
        validate(self)

    def station_validated(self):
        calls["station"] += 1

    monkeypatch.setattr(IdentifyConfig, "validate", counted)
    monkeypatch.setattr(station.StationConfig, "validate", station_validated)
    path = _write(tmp_path, "slice", _sliced("xl330_kp400_sin_time_square", 1100))
    assert (
        main(
            [
                "identify",
                "--robot",
                ROBOT,
                "--log",
                str(path),
                "--fit",
                "least-squares",
                "--out",
                str(tmp_path / "out"),
            ]
        )
        == 0
    )
    assert calls == {"identify": 1, "station": 0}
    capsys.readouterr()
