"""The second robot end to end, from its description alone (models/iiwa14/robot.yaml):
identify its motor model on its emulated servo, then torque-control it against its
position servo, in free space and with a force task at the tool."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hrp2_drake.assembly.identification import IdentifyConfig
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.robot.station import StationConfig
from hrp2_drake.tools.identify import run_identify
from hrp2_drake.tools.track import TrackConfig, run_track

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


@pytest.fixture(scope="module")
def identified(tmp_path_factory):
    out = tmp_path_factory.mktemp("identify")
    station = StationConfig(robot="iiwa14", scenario="fixed_base")
    summary = run_identify(IdentifyConfig(station=station, duration_scale=0.25), out)
    return summary, MotorModel.load(out / "motor_model.yaml")


def test_identification_against_the_emulator(identified):
    summary, model = identified
    assert model.joint_names == [f"iiwa_joint_{k}" for k in range(1, 8)]
    for joint, row in summary["joints"].items():
        emulator = row["emulator"]
        least_squares = row["least_squares"]
        # Measured (scale 0.25): least squares Kτ within 1-8%, Kv within 3%.
        assert least_squares["k_tau"] == pytest.approx(emulator["k_tau"], rel=0.15), (
            joint
        )
        assert least_squares["k_v"] == pytest.approx(emulator["k_v"], rel=0.05), joint
        # The asymmetric fit (w = 1000) under-estimates Kτ, by design, and by up to
        # ~50% on the arm's joints with the most friction for their torque: a finding
        # of the closing note, not hidden here.
        assert 0.3 < row["asymmetric"]["k_tau"] / emulator["k_tau"] <= 1.05, joint
        # Measured: Kv within 6.1% (A3), the rest within 2%.
        assert row["asymmetric"]["k_v"] == pytest.approx(emulator["k_v"], rel=0.1), (
            joint
        )


def test_torque_control_beats_the_position_servo_and_presses(identified, tmp_path):
    _, model = identified
    config = TrackConfig(duration=2.5, k6=[1.0], force_duration=2.0)
    summary = run_track(config, model, tmp_path)
    position = np.array(summary["tracking"]["position control"]["maximum"])
    torque = np.array(summary["tracking"]["torque control K6=1"]["maximum"])
    # Measured: position servo 6-10 mrad (its lag Kv q̇), torque control 0.3-1.3.
    assert np.all(torque < 0.5 * position), (torque, position)
    force = summary["force_task"]
    # Measured: RMS 1.7 N on 20 ± 10 N, amplitude ratio 0.96.
    assert force["rms_error_N"] < 3.0
    assert 0.8 < force["amplitude_ratio"] < 1.2
    for name in ("track.md", "track_errors.png", "track_force.png"):
        assert (tmp_path / name).is_file()


def test_examples_run(tmp_path):
    """scripts/example_*.py, a user's starting points, run as they are."""
    python = sys.executable
    model = tmp_path / "model.yaml"
    runs = [
        [python, SCRIPTS / "example_estimate_torques.py", "--duration", "1.0"],
        [
            python,
            SCRIPTS / "example_identify_motor_model.py",
            "--duration-scale",
            "0.25",
            "--out",
            model,
        ],
        [
            python,
            SCRIPTS / "example_torque_control.py",
            "--motor-model",
            model,
            "--duration",
            "2.0",
        ],
    ]
    for argv in runs:
        done = subprocess.run(
            list(map(str, argv)), capture_output=True, text=True, cwd=tmp_path
        )
        assert done.returncode == 0, done.stderr[-2000:]
        assert "iiwa" in done.stdout
