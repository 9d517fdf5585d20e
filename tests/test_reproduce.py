"""A CI-sized `hrp2-drake reproduce --quick`: every step runs, the report and the
numbers exist, and the verdicts are computed from them."""

import json

import pytest

from hrp2_drake.cli import main


@pytest.mark.slow
def test_reproduce_quick_writes_the_report_and_numbers(tmp_path, capsys):
    out = tmp_path / "reproduce"
    code = main(["reproduce", "--quick", "--no-replays", "--out", str(out)])
    assert code == 0, capsys.readouterr().err[-3000:]
    results = json.loads((out / "results.json").read_text())
    for step in ("identify", "estimation", "motion", "force", "stability", "components"):
        assert results[step].get("ok", True), (step, results[step].get("error"))
    assert len(results["identify"]["joints"]) == 6
    # position, 4 x K6, paper-literal, authors' code; beyond the paper: the tuned
    # K6 = 0.1, each improvement alone (observer, windows, predictor, the tuned one +
    # predictor, gains), the held-out motion (position control and the tuned one)
    assert len(results["motion"]["runs"]) == 7 + 6 + 2
    assert results["motion"]["improved"]["goal"]["holds"] in (True, False)
    assert "baseline" in results["force"]
    report = (out / "report.md").read_text()
    assert "## Verdicts" in report and report.count("| holds") >= 5
    for figure in (
        "identify/figure1_torque_vs_delta_q.png",
        "identify/figure3_friction_fit.png",
        "motion/figure4_tracking_error.png",
        "force/figure5_force_tracking.png",
        "components/figure6_components.png",
        "stability/figure_open_loop_stability.png",
        "estimation/estimation_tau_hanging.png",
    ):
        assert (out / figure).stat().st_size > 10000, figure
        assert f"({figure})" in report, figure
    assert results["total_seconds"] > 0
