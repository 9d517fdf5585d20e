"""The first real robot, models/xl330_pendulum: a Dynamixel XL330 position servo
driving a 0.49 kg, 0.10 m pendulum (one joint, fixed base, no IMU, no F/T sensor).

- `hrp2-drake track --robot xl330_pendulum` runs on its simulated twin: torque
  control against the servo's own position control.
- Identification windows are in seconds: logs of the same servo at 50 Hz, 200 Hz and
  1 kHz give the same motor model.

Whatever servo.yaml holds (the twin is recalibrated to the real logs): nothing here
depends on its values.
"""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from hrp2_drake.assembly.identification import IdentifyConfig
from hrp2_drake.cli import main
from hrp2_drake.identification.joint_fits import identify_logs
from hrp2_drake.identification.logs import RobotLog, read_logs
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.robot.rollout import emulated_servo, rollout
from hrp2_drake.robot.station import StationConfig
from hrp2_drake.tools.track import motor_model_at_station_gain

ROBOT = "xl330_pendulum"
#: The servo gain of the synthetic logs (the XL330's kp, firmware units).
GAIN = 400.0


def test_track_runs_on_the_twin(tmp_path, capsys):
    """`track` on a one-joint robot without F/T sensors: the force task is off by
    default, the motor model identified on the twin, both rows in the report."""
    config = tmp_path / "track.yaml"
    config.write_text("duration: 1.0\nk6: [1.0]\n")
    argv = ["track", "--robot", ROBOT, "--config", str(config), "--out", str(tmp_path)]
    code = main(argv)
    assert code == 0, capsys.readouterr().err
    report = (tmp_path / "track.md").read_text()
    assert "| position control |" in report
    assert "| torque control K6=1 |" in report
    assert "HRP-2" not in report
    # Its own torque-control settings (K_p = 1), named; the --config sets none.
    assert "the robot's control file `" in report and "K_p = 1," in report
    summary = json.loads((tmp_path / "track.json").read_text())
    assert summary["robot"] == ROBOT
    assert summary["torque_control_from"]["robot_file"].endswith("control.yaml")
    assert summary["torque_control_from"]["user_file"] == ""
    assert "force_task" not in summary
    # The model identified on the twin holds at the station's servo gain (servo.yaml's).
    gain = StationConfig(robot=ROBOT, scenario="fixed_base").servo_gain_in_use()
    assert summary["motor_model_gain"] == gain
    for errors in summary["tracking"].values():
        assert np.all(np.isfinite(errors["maximum"]))


def test_track_reads_the_motor_model_at_the_station_gain():
    """A model that holds at a gain is scaled to the gain the station's servo runs at:
    servo.yaml's, or StationConfig.servo_gain; a model without gain is used as is."""
    station = StationConfig(robot=ROBOT, scenario="fixed_base")
    file_gain = station.servo_params().joints["servo"].gain
    assert station.servo_gain_in_use() == file_gain
    model = MotorModel(["servo"], [2.0], [0.16], gain=100.0)
    at_file = motor_model_at_station_gain(model, station)
    assert at_file.gain == file_gain
    assert at_file.k_tau[0] == pytest.approx(2.0 * 100.0 / file_gain)
    at_200 = motor_model_at_station_gain(
        model, dataclasses.replace(station, servo_gain=200.0)
    )
    assert (at_200.gain, at_200.k_tau[0], at_200.k_v[0]) == pytest.approx(
        (200.0, 1.0, 0.08)
    )
    no_gain = MotorModel(["servo"], [2.0], [0.16])
    assert motor_model_at_station_gain(no_gain, station) is no_gain


def _synthetic_csv(path: Path, rate: float, seed: int, duration: float = 6.0) -> None:
    """A log of the emulated servo (servo.yaml at GAIN) written at `rate` (Hz) with
    timestamps jittered by ±20 % of the period, as CSV: t, position, goal_position, kp.

    The command, an increasing sinusoid about the hanging pose (0.8 Hz, up to 0.7 rad,
    peak velocity about 2.5 rad/s), changes at the jittered sample times and is held
    in between (what a servo receives from a bus at that rate); the plant runs on a
    1 kHz grid (`rollout`), and each sample's position is read at its own time."""
    period = 1.0 / rate
    n = int(round(duration * rate)) + 1
    rng = np.random.default_rng(seed)
    t_raw = np.arange(n) * period + rng.uniform(-0.2 * period, 0.2 * period, n)
    t_raw -= t_raw[0]
    command = 0.7 * (t_raw / duration) * np.sin(2 * np.pi * 0.8 * t_raw)
    grid = np.arange(0.0, t_raw[-1], 0.001)
    held = np.searchsorted(t_raw, grid, side="right") - 1  # zero-order hold
    station = StationConfig(robot=ROBOT, scenario="fixed_base")
    log = RobotLog(
        source=str(path),
        t=grid,
        q_measured=np.zeros((len(grid), 1)),  # only its first sample is read: at rest
        q_cmd=command[held][:, None],
        valid=np.ones(len(grid), bool),
        gain=GAIN,
        joint_names=["servo"],
        raw_rate=rate,
    )
    servo = emulated_servo(station.servo_params(), GAIN)
    q_sim = rollout(station.description(), log, servo).q_sim
    position = np.interp(t_raw, grid, q_sim[:, 0])
    rows = np.column_stack([t_raw, position, command, np.full(n, GAIN)])
    np.savetxt(
        path,
        rows,
        delimiter=",",
        header="t,position,goal_position,kp",
        comments="",
        fmt="%.10g",
    )


def test_windows_in_seconds_give_the_same_fit_at_any_rate(tmp_path):
    """The least-squares Kτ and Kv of logs at 50 Hz, 200 Hz and 1 kHz, read through a
    CSV log format onto the description's grid, with one window of 0.1 s.

    Measured (servo.yaml before calibration, seeds 0-2; and with 4 ms latency, 10 mrad
    hysteresis and a dead zone added): spread (max/min - 1) 0.2-0.4 % for Kτ and
    0.2-0.4 % for Kv. Tolerance: 2 %."""
    station = StationConfig(robot=ROBOT, scenario="fixed_base")
    robot = station.description()
    log_format = dataclasses.replace(
        robot.logs,
        format="csv",
        samples="",
        time="t",
        time_unit=1.0,
        position=["position"],
        command=["goal_position"],
        position_unit=1.0,
        valid="",
        gain="kp",
    )
    csv_robot = dataclasses.replace(robot, logs=log_format)
    config = IdentifyConfig(station=station, window=0.1, w_sweep=[1000.0])
    fits = {}
    for rate in (50.0, 200.0, 1000.0):
        path = tmp_path / f"xl330_{rate:g}hz.csv"
        _synthetic_csv(path, rate, seed=0)
        logs, rows = read_logs([path], csv_robot)
        assert rows[0]["raw_rate_hz"] == pytest.approx(rate, rel=0.02)
        assert logs[0].gain == GAIN
        result = identify_logs(robot, config, logs)
        model = result.joints[0].models["least_squares"]
        assert model.gain == GAIN
        fits[rate] = (model.k_tau[0], model.k_v[0])
    k_tau, k_v = (np.array(values) for values in zip(*fits.values()))
    assert np.all(k_tau > 0) and np.all(k_v > 0), fits
    assert k_tau.max() / k_tau.min() - 1 < 0.02, fits
    assert k_v.max() / k_v.min() - 1 < 0.02, fits
