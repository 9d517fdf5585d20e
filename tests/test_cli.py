"""The `hrp2-drake` command line."""

import json

import numpy as np

from hrp2_drake.cli import main


def test_simulate_writes_log_summary_and_replay(tmp_path, capsys):
    code = main(
        ["simulate", "--scenario", "fixed_base", "--duration", "0.2"]
        + ["--out", str(tmp_path), "--html"]
    )
    assert code == 0
    log = np.load(tmp_path / "simulate_fixed_base.npz")
    assert log["q_measured"].shape == (201, 30)
    assert log["wrench_right_foot"].shape == (201, 6)
    assert log["t"][-1] == 0.2
    summary = json.loads((tmp_path / "simulate_fixed_base.json").read_text())
    assert summary["max_abs_tracking_error_rad"] < 0.05
    html = (tmp_path / "simulate_fixed_base.html").read_text()
    assert "<html" in html.lower() and len(html) > 10000
    assert "real time" in capsys.readouterr().err  # progress


def test_simulate_follows_a_trajectory_file(tmp_path):
    from hrp2_drake.paper import hrp2

    q0 = hrp2.half_sitting()
    rows = np.array([np.concatenate([[t], q0]) for t in (0.0, 1.0)])
    rows[1, 1 + 3] += 0.1  # right knee +0.1 rad over 1 s
    path = tmp_path / "traj.pos"
    np.savetxt(path, rows)
    code = main(
        ["simulate", "--scenario", "hanging", "--duration", "1.8"]
        + ["--trajectory", str(path), "--out", str(tmp_path)]
    )
    assert code == 0
    log = np.load(tmp_path / "simulate_hanging.npz")
    assert log["q_measured"][-1, 3] - log["q_measured"][0, 3] > 0.08


def test_simulate_reports_bad_input(tmp_path, capsys):
    assert main(["simulate", "--trajectory", str(tmp_path / "missing.pos")]) == 2
    assert "missing.pos" in capsys.readouterr().err
    config = tmp_path / "bad.yaml"
    config.write_text("station: {scenario: standing, sensors: {gyro: {}}}\n")
    assert main(["simulate", "--config", str(config)]) == 2
    assert "station.sensors.gyro" in capsys.readouterr().err


def test_help_and_option_errors_return_exit_codes(capsys):
    assert main(["--help"]) == 0
    assert "--debug" in capsys.readouterr().out
    assert main(["simulate", "--duration", "soon"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "argument --duration" in err
