"""Rollouts of servo models on the XL330 pendulum's real logs (hrp2_drake.robot.rollout)
and `hrp2-drake validate`: the emulated servo tracks a real log, the motor-model servo
reproduces the emulator when both obey the same law, the servo switched off lets the
pendulum swing as the closed-form dynamics say, and the command writes its report."""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from pydrake.multibody.plant import MultibodyPlant
from scipy.integrate import solve_ivp

from hrp2_drake import cli
from hrp2_drake.description import load_robot_description
from hrp2_drake.identification.logs import RobotLog, read_robot_log
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.robot.rollout import (
    MotorModelServo,
    emulated_servo,
    model_servo,
    rollout,
    rollout_errors,
    twin_servo,
)
from hrp2_drake.robot.servo import (
    SERVO_MECHANISMS,
    EmulatedPositionServo,
    effective_motor_parameters,
    load_servo_params,
    servo_torque,
)

ROBOT = "xl330_pendulum"
LOGS = Path(__file__).resolve().parents[1] / "models" / ROBOT / "logs"
# The pendulum of the URDF: a point mass at the arm's end, and the rotor inertia
# reflected through the gearbox (rotor inertia x gear ratio²).
MASS, LENGTH, GRAVITY = 0.49, 0.1, 9.81
INERTIA = MASS * LENGTH**2 + 1e-8 + 2.1648e-08 * 288.35**2


@pytest.fixture(scope="module")
def robot():
    return load_robot_description(ROBOT)


@pytest.fixture(scope="module")
def prior(xl330_prior):
    """The XL330's servo before calibration (BAM's m1, at kp 400): fixed, whatever
    the shipped servo.yaml holds."""
    return xl330_prior


@pytest.fixture(scope="module")
def plant(robot):
    plant = MultibodyPlant(0.001)
    robot.add_model(plant)
    plant.Finalize()
    return plant


def _log(robot, name: str, start: float, end: float) -> RobotLog:
    return read_robot_log(LOGS / f"{name}.json", robot.logs, robot.joints).slice(
        start, end
    )


def _linear(prior):
    """The prior servo reduced to eq. 6 exactly: no Coulomb friction, no encoder
    quantization (the mechanisms are switched off in the servo)."""
    params = dataclasses.replace(
        prior,
        joints={
            name: dataclasses.replace(joint, k3=0.0, encoder_resolution=0.0)
            for name, joint in prior.joints.items()
        },
    )
    eff = effective_motor_parameters(params, ["servo"])
    model = MotorModel(
        ["servo"], eff["k_tau"], eff["k_v"], gain=params.joints["servo"].gain
    )
    return params, model


def test_enabled_port_switches_the_drive_off_and_keeps_the_friction(prior, plant):
    servo = EmulatedPositionServo(plant, prior, ["servo"], 0.001, enable_port=True)
    context = servo.CreateDefaultContext()
    servo.GetInputPort("q_cmd").FixValue(context, [0.3])
    servo.GetInputPort("state").FixValue(context, [0.1, 0.7])
    p = prior.vectors(["servo"])
    direction = np.tanh(0.7 / p["v_coulomb"])
    error = 0.3 - np.rint(0.1 / p["encoder_resolution"]) * p["encoder_resolution"]
    v = np.array([0.7])
    servo.GetInputPort("enabled").FixValue(context, [0.0])
    off = servo.get_output_port().Eval(context)
    np.testing.assert_allclose(off, -p["k2"] * 0.7 - p["k3"] * direction, rtol=1e-12)
    # The per-step law and servo_torque agree bit for bit, on and off.
    expected = servo_torque(p, error, v, direction, np.array([0.0]))
    np.testing.assert_array_equal(off, expected)
    servo.GetInputPort("enabled").FixValue(context, [1.0])
    on = servo.get_output_port().Eval(context)
    np.testing.assert_array_equal(on, servo_torque(p, error, v, direction))
    np.testing.assert_array_equal(
        on, servo_torque(p, error, v, direction, np.array([1.0]))
    )
    assert on[0] > off[0] + 0.1


def test_model_servo_is_eq6_clamped_at_the_saturation(robot, plant):
    model = MotorModel(["servo"], [1.5], [0.06], [0.002], gain=400.0)
    delta_q_max = robot.position_loop.saturation_error(100.0)
    servo = model_servo(robot, model, 100.0)(plant, ["servo"])
    assert isinstance(servo, MotorModelServo)
    np.testing.assert_allclose(servo.delta_q_max, 1.0 / (100.0 * 2.87738e-3))
    context = servo.CreateDefaultContext()
    servo.GetInputPort("enabled").FixValue(context, [1.0])
    k_tau, k_v, k_c = 1.5 * 4, 0.06 * 4, 0.002 * 4  # at kp 100: every term x 400/100
    for q_cmd, v in [(0.5, 0.3), (5.0, -1.0), (-5.0, 2.0)]:
        servo.GetInputPort("q_cmd").FixValue(context, [q_cmd])
        servo.GetInputPort("state").FixValue(context, [0.2, v])
        delta_q = np.clip(q_cmd - 0.2, -delta_q_max, delta_q_max)
        expected = (delta_q - k_v * v - k_c * np.sign(v)) / k_tau
        np.testing.assert_allclose(servo.get_output_port().Eval(context), [expected])
    servo.GetInputPort("enabled").FixValue(context, [0.0])
    assert servo.get_output_port().Eval(context)[0] == 0.0
    with pytest.raises(ValueError, match="gain"):
        model_servo(robot, model, None)


def test_emulated_servo_tracks_a_real_log(robot, prior):
    log = _log(robot, "xl330_kp100_sin_time_square", 1.0, 2.0)
    result = rollout(robot, log, emulated_servo(prior, log.gain))
    assert result.q_sim.shape == log.q_measured.shape
    assert result.q_sim[0, 0] == log.q_measured[0, 0]
    errors = rollout_errors(log, result.q_sim)
    # Measured: MAE 31 mrad, max 90 mrad (the prior, uncalibrated).
    assert np.all(np.isfinite(errors.mae)) and errors.mae[0] < 0.3
    assert errors.servo_on_samples == len(log.t)


def _step_log(step: float, seconds: float, gain: float) -> RobotLog:
    """A command step of `step` rad at 0.1 s from rest at 0 (servo on throughout)."""
    t = np.arange(0.0, seconds + 1e-9, 0.001)
    q_cmd = np.where(t >= 0.1, step, 0.0)[:, None]
    return RobotLog(
        "step",
        t,
        np.zeros_like(q_cmd),
        q_cmd,
        np.ones(len(t), bool),
        gain,
        ["servo"],
        1000.0,
    )


@pytest.mark.parametrize("voltage_limit", [False, True])
def test_model_servo_reproduces_the_equivalent_emulated_servo(
    robot, prior, voltage_limit
):
    """The emulated servo without dead zone, latency, hysteresis, Coulomb friction and
    quantization is eq. 6 exactly; the model servo with effective_motor_parameters'
    Kτ, Kv must give the same trajectory. With the voltage limit on, the prior's
    voltage limit is where its PWM duty saturates (stall current = V/R, k5 = kt/R,
    no-load speed V/kt), so clamping Δq at the position loop's saturation error is
    the same torque-speed line."""
    params, model = _linear(prior)  # both given at kp 400
    if voltage_limit:
        # A 1.5 rad step at kp 400: |Δq| passes the saturation error
        # 1 / (400 · 2.877e-3) = 0.87 rad.
        log = _step_log(1.5, 1.0, 400.0)
        off = [m for m in SERVO_MECHANISMS if m != "voltage_limit"]
    else:
        # A real command at kp 100: both servos rescaled by at_gain.
        log = _log(robot, "xl330_kp100_sin_time_square", 1.0, 2.0)
        off = list(SERVO_MECHANISMS)
    emulated = rollout(robot, log, emulated_servo(params, log.gain, off=off))
    modelled = rollout(
        robot, log, model_servo(robot, model, log.gain, saturate=voltage_limit)
    )
    # Measured: 5.6e-17 rad without the limit (rounding: same law, same timing);
    # 7.5e-6 rad with it, from robot.yaml's output_per_gain (6 digits, 2.87738e-3)
    # against the servo file's k4, stall current and k5 (9 digits; i_s / ω0 and k5
    # agree to 4e-6 relative).
    atol = 5e-5 if voltage_limit else 1e-12
    np.testing.assert_allclose(modelled.q_sim, emulated.q_sim, rtol=0, atol=atol)
    if voltage_limit:
        delta_q = log.q_cmd[:, 0] - emulated.q_sim[:, 0]
        saturated = np.abs(delta_q) > robot.position_loop.saturation_error(log.gain)
        assert saturated.mean() > 0.05  # measured: 13% of the samples
        # Without the clamp the model servo pulls harder (measured: 0.31 rad apart).
        unclamped = rollout(
            robot, log, model_servo(robot, model, log.gain, saturate=False)
        )
        assert np.max(np.abs(unclamped.q_sim - modelled.q_sim)) > 0.05


def _free_swing(t: np.ndarray, q0: float, k2: float, k3: float, v_coulomb: float):
    """The pendulum alone: I q̈ = −m g l sin q − k2 q̇ − k3 tanh(q̇ / v_s)."""

    def f(_, x):
        q, v = x
        tau = (
            -MASS * GRAVITY * LENGTH * np.sin(q) - k2 * v - k3 * np.tanh(v / v_coulomb)
        )
        return [v, tau / INERTIA]

    return solve_ivp(f, (t[0], t[-1]), [q0, 0.0], t_eval=t, rtol=1e-10, atol=1e-12).y[0]


def _servo_off_log(q0: float, seconds: float) -> RobotLog:
    t = np.arange(0.0, seconds + 1e-9, 0.001)
    q = np.full((len(t), 1), q0)
    return RobotLog(
        "servo_off",
        t,
        q,
        np.zeros_like(q),
        np.zeros(len(t), bool),
        400.0,
        ["servo"],
        1000.0,
    )


def test_servo_off_the_pendulum_swings_freely(robot, prior):
    log = _servo_off_log(0.6, 1.5)
    p = prior.vectors(["servo"])
    # Emulated servo, off: only its friction acts.
    params = dataclasses.replace(
        prior,
        joints={
            name: dataclasses.replace(joint, encoder_resolution=0.0)
            for name, joint in prior.joints.items()
        },
    )
    emulated = rollout(robot, log, emulated_servo(params, log.gain)).q_sim[:, 0]
    expected = _free_swing(log.t, 0.6, p["k2"][0], p["k3"][0], p["v_coulomb"][0])
    # Measured: 2.5e-3 rad (the plant's first-order step: 1.25e-3 at 0.5 ms).
    assert np.max(np.abs(emulated - expected)) < 1e-2
    # Friction: the second swing to the same side is lower (measured: 0.387 rad).
    first, second = emulated[log.t < 0.75].max(), emulated[log.t > 0.75].max()
    assert 0.3 < second < 0.5 and first <= 0.6 + 1e-9
    # Motor-model servo, off: no torque at all; the swing keeps its energy.
    model = MotorModel(["servo"], [1.5], [0.06], gain=400.0)
    free = rollout(robot, log, model_servo(robot, model, log.gain)).q_sim[:, 0]
    expected = _free_swing(log.t, 0.6, 0.0, 0.0, 1.0)
    # Measured: 2.5e-3 rad; the amplitude within 5e-6 rad (symplectic step).
    assert np.max(np.abs(free - expected)) < 1e-2
    np.testing.assert_allclose(
        [free.min(), free[log.t > 0.75].max()], [-0.6, 0.6], atol=1e-4
    )


def _sliced_json(source: Path, target: Path, seconds: float) -> Path:
    data = json.loads(source.read_text())
    t0 = data["entries"][0]["timestamp"]
    data["entries"] = [e for e in data["entries"] if e["timestamp"] - t0 <= seconds]
    target.write_text(json.dumps(data))
    return target


def test_validate_writes_its_report(tmp_path, prior, capsys):
    eff = effective_motor_parameters(prior, ["servo"])
    model = MotorModel(["servo"], eff["k_tau"], eff["k_v"], gain=400.0)
    model.save(tmp_path / "motor_model.yaml")
    logs = [
        _sliced_json(LOGS / f"{name}.json", tmp_path / f"{name}.json", 1.0)
        for name in ("xl330_kp100_up_and_down", "xl330_kp400_lift_and_drop")
    ]
    out = tmp_path / "out"
    argv = [
        "validate",
        "--robot",
        ROBOT,
        "--motor-model",
        str(tmp_path / "motor_model.yaml"),
        "--log",
        *map(str, logs),
        "--out",
        str(out),
    ]
    assert cli.main(argv) == 0
    summary = json.loads((out / "validate.json").read_text())
    assert [row["log"] for row in summary["logs"]] == [p.stem for p in logs]
    for row in summary["logs"]:
        assert (out / row["figure"]).is_file()
        assert 0 < row["mae_mrad"]["servo"] < 300
    assert "mean of 2" in (out / "validate.md").read_text()
    capsys.readouterr()

    argv[4] = str(tmp_path / "missing.yaml")
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("hrp2-drake validate: error:")
    assert "missing.yaml" in err[0]


def test_validate_bad_inputs_are_one_line(tmp_path, capsys):
    log = _sliced_json(
        LOGS / "xl330_kp100_up_and_down.json", tmp_path / "log.json", 0.5
    )
    other = MotorModel(["knee"], [1.0], [0.05], gain=400.0)
    other.save(tmp_path / "other.yaml")
    no_gain = json.loads(log.read_text())
    del no_gain["kp"]
    (tmp_path / "no_gain.json").write_text(json.dumps(no_gain))
    (tmp_path / "broken.json").write_text("{not json")
    MotorModel(["servo"], [1.5], [0.06], gain=400.0).save(tmp_path / "model.yaml")
    cases = [
        (tmp_path / "other.yaml", log, "no joints ['servo']"),
        (tmp_path / "model.yaml", tmp_path / "broken.json", "broken.json"),
        (tmp_path / "model.yaml", tmp_path / "no_gain.json", "states no servo gain"),
        (tmp_path / "model.yaml", tmp_path / "absent.json", "absent.json"),
    ]
    for model, path, expected in cases:
        code = cli.main(
            [
                "validate",
                "--robot",
                ROBOT,
                "--motor-model",
                str(model),
                "--log",
                str(path),
                "--out",
                str(tmp_path / "out"),
            ]
        )
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2, err
        assert len(err) == 1 and expected in err[0], err


def test_validate_rolls_out_the_shipped_twin(robot, tmp_path, capsys):
    """`validate --motor-model` a servo file (issue 28): the shipped digital twin
    (models/xl330_pendulum/servo.yaml, `calibrate --log`'s) judged on a log in one
    command; its errors are those of the twin's own rollout (`twin_servo`)."""
    servo_file = LOGS.parent / "servo.yaml"
    log_path = _sliced_json(
        LOGS / "xl330_kp100_sin_sin.json", tmp_path / "sin_sin.json", 1.0
    )
    out = tmp_path / "out"
    argv = [
        "validate",
        "--robot",
        ROBOT,
        "--motor-model",
        str(servo_file),
        "--log",
        str(log_path),
        "--out",
        str(out),
    ]
    assert cli.main(argv) == 0
    summary = json.loads((out / "validate.json").read_text())
    assert summary["model_kind"] == "servo file" and summary["model_gain"] is None
    log = read_robot_log(log_path, robot.logs, robot.joints)
    params = load_servo_params(servo_file, robot.source_file)
    errors = rollout_errors(log, rollout(robot, log, twin_servo(params, log)).q_sim)
    row = summary["logs"][0]
    assert row["mae_mrad"]["servo"] == pytest.approx(errors.mae[0] * 1e3, rel=1e-9)
    assert row["max_error_mrad"]["servo"] == pytest.approx(
        errors.max_error[0] * 1e3, rel=1e-9
    )
    assert 0 < row["mae_mrad"]["servo"] < 40  # measured: 31.4 mrad on this second
    assert "Digital twin (servo file)" in (out / "validate.md").read_text()
    capsys.readouterr()
