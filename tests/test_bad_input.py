"""Bad input to `hrp2-drake`: one line naming the culprit, exit code 2, no traceback,
and nothing simulated (the simulations are replaced by a failure in these tests)."""

import numpy as np
import pytest

from hrp2_drake.cli import main
from hrp2_drake.identification.fitting import check_identified, fit_least_squares
from hrp2_drake.robot import model


def simulated(*args, **kwargs):
    raise AssertionError("simulated despite bad input")


@pytest.fixture(autouse=True)
def no_simulation(monkeypatch):
    """Any simulation fails the test: bad input must be refused before one starts."""
    from hrp2_drake.experiments import identification, motion, simulate

    monkeypatch.setattr(simulate, "run_simulate", simulated)
    monkeypatch.setattr(motion, "run_motion", simulated)
    monkeypatch.setattr(identification, "collect_log", simulated)


def refused(capsys, argv: list[str], *culprits: str, last_line: bool = False) -> str:
    """Runs the command; asserts exit code 2 and one error line naming `culprits`
    (with `last_line`, progress lines may precede it); returns the line."""
    code = main(argv)
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert code == 2, err
    assert lines and (last_line or len(lines) == 1), err
    line = lines[-1]
    assert line.startswith(f"hrp2-drake {argv[0]}: error: "), line
    for culprit in culprits:
        assert culprit in line, line
    return line


def trajectory_file(path, times=(0.0, 1.0), extra_columns=0, change=None):
    rows = np.array([np.concatenate([[t], model.half_sitting()]) for t in times])
    rows = np.hstack([rows, np.ones((len(rows), extra_columns))])
    if change is not None:
        rows[change[0], change[1]] = change[2]
    np.savetxt(path, rows)
    return str(path)


def motor_model_text(k_tau="1e-4", joints=model.RIGHT_LEG, extra=""):
    n = len(joints)
    return (
        f"joint_names: [{', '.join(joints)}]\n"
        f"k_tau: [{', '.join([k_tau] + ['1e-4'] * (n - 1))}]\n"
        f"k_v: [{', '.join(['1e-2'] * n)}]\n{extra}"
    )


def identification_log(path, rng_seed=0, **replace):
    """A short log of the right leg moving sinusoidally (after 1.5 s), with a position
    error Δq = q_cmd - q that is pure noise."""
    m = 3000
    t = np.arange(m) * 1e-3
    q = np.tile(model.half_sitting(), (m, 1))
    for j in range(6):
        q[:, j] += 0.1 * np.sin(2 * np.pi * (1 + 0.3 * j) * t) * (t > 1.5)
    noise = 1e-4 * np.random.default_rng(rng_seed).standard_normal(q.shape)
    log = dict(
        t=t,
        joint_names=np.array(model.JOINT_NAMES),
        q_measured=q,
        q_cmd=q + noise,
        imu_linear_acceleration=np.tile([0.0, 0.0, 9.81], (m, 1)),
        imu_angular_velocity=np.zeros((m, 3)),
        **{f"wrench_{name}": np.zeros((m, 6)) for name in model.FT_SENSORS},
    )
    log.update(replace)
    np.savez(path, **{k: v for k, v in log.items() if v is not None})
    return str(path)


# --------------------------------------------------------------- YAML config files
@pytest.mark.parametrize(
    "text, culprit",
    [
        ("station: {scenario: standing\nduration: [\n", "line 2"),  # syntax error
        ("station: {sensors: {gyro: {}}}\n", "station.sensors.gyro"),  # unknown key
        ("duration: abc\n", "duration"),  # wrong type
        ("station: 3\n", "station"),
        ("duration: 1\nduration: 2\n", "duplicated key 'duration'"),
        ("- 1\n", "expected a mapping"),
    ],
)
def test_config_file_errors_name_the_file_and_key(tmp_path, capsys, text, culprit):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    refused(capsys, ["simulate", "--config", str(path)], "bad.yaml", culprit)


def test_config_path_that_is_no_file(tmp_path, capsys):
    refused(capsys, ["simulate", "--config", str(tmp_path)], str(tmp_path), "folder")
    missing = tmp_path / "missing.yaml"
    refused(capsys, ["simulate", "--config", str(missing)], "missing.yaml")


@pytest.mark.parametrize(
    "text, culprit",
    [
        ("station: {sensors: {period: 0}}\n", "period"),  # was a ZeroDivisionError
        ("station: {sensors: {seed: -1}}\n", "seed"),
        ("station: {sensors: {accelerometer: {std: [1, 2]}}}\n", "accelerometer.std"),
        ("duration: .inf\n", "duration"),  # would run forever
        ("duration: 0\n", "duration"),
        ("log_period: .nan\n", "log_period"),
        (
            "station: {initial_positions: [" + ", ".join(["9.0"] * 30) + "]}\n",
            "RLEG_JOINT0",
        ),
    ],
)
def test_simulate_settings_are_validated_before_simulating(
    tmp_path, capsys, text, culprit
):
    path = tmp_path / "simulate.yaml"
    path.write_text(text)
    refused(capsys, ["simulate", "--config", str(path)], "simulate.yaml", culprit)


@pytest.mark.parametrize(
    "text, culprit",
    [
        ("k6: []\n", "k6"),
        ("k6: [0.5, 0]\n", "k6[1]"),
        ("start: 5.0\nend: 2.0\n", "end"),  # end before start
        ("end: 30.0\n", "end"),  # beyond the motion
        ("settle: -1\n", "settle"),
    ],
)
def test_motion_settings_are_validated_before_simulating(
    tmp_path, capsys, text, culprit
):
    config = tmp_path / "motion.yaml"
    config.write_text(text)
    motor_model = tmp_path / "motor_model.yaml"
    motor_model.write_text(motor_model_text())
    argv = [
        "experiment",
        "motion",
        "--config",
        str(config),
        "--motor-model",
        str(motor_model),
    ]
    refused(capsys, argv + ["--out", str(tmp_path / "out")], "motion.yaml", culprit)


# ------------------------------------------------------------------ command options
@pytest.mark.parametrize(
    "argv, culprit",
    [
        (["simulate", "--duration", "inf"], "--duration"),
        (["simulate", "--duration", "nan"], "--duration"),
        (["simulate", "--duration", "0"], "--duration"),
        (["simulate", "--duration", "-1"], "--duration"),
        (["simulate", "--seed", "-1"], "--seed"),
        (["identify", "--duration-scale", "0"], "--duration-scale"),
        (["experiment", "motion", "--end", "-2"], "--end"),
        (["experiment", "estimation", "--end", "5"], "--end"),
        (["calibrate", "--jobs", "0"], "--jobs"),
    ],
)
def test_bad_option_values(capsys, argv, culprit):
    refused(capsys, argv, culprit)


def test_out_that_cannot_be_a_folder(tmp_path, capsys):
    existing = tmp_path / "results.txt"
    existing.write_text("keep me")
    refused(capsys, ["simulate", "--out", str(existing)], "--out", "results.txt")
    refused(
        capsys, ["simulate", "--out", str(existing / "sub")], "--out", "results.txt"
    )
    assert existing.read_text() == "keep me"


# ------------------------------------------------------------------ trajectory files
@pytest.mark.parametrize(
    "kwargs, culprit",
    [
        (dict(times=(0.0, 1.0, 0.5)), "strictly increasing"),
        (dict(times=(0.0, 1.0, 1.0)), "strictly increasing"),
        (dict(extra_columns=2), "33 columns"),
        (dict(change=(1, 1 + 3, 50.0)), "RLEG_JOINT3"),  # 50 rad: beyond the limits
        (dict(change=(1, 5, np.nan)), "NaN"),
        (dict(times=(0.0,)), "1 rows"),
    ],
)
def test_trajectory_file_errors(tmp_path, capsys, kwargs, culprit):
    path = trajectory_file(tmp_path / "motion.pos", **kwargs)
    refused(capsys, ["simulate", "--trajectory", path], "motion.pos", culprit)


def test_trajectory_path_that_is_no_table(tmp_path, capsys):
    text = tmp_path / "notes.pos"
    text.write_text("time and angles\n")
    refused(capsys, ["simulate", "--trajectory", str(text)], "notes.pos", "numbers")
    refused(
        capsys, ["simulate", "--trajectory", str(tmp_path)], str(tmp_path), "folder"
    )


# ------------------------------------------------------------ identification logs
def test_log_file_errors_name_the_file_and_array(tmp_path, capsys):
    out = ["--out", str(tmp_path / "out")]
    good = identification_log(tmp_path / "log.npz")
    truncated = tmp_path / "truncated.npz"
    data = open(good, "rb").read()
    truncated.write_bytes(data[: len(data) // 2])
    refused(capsys, ["identify", "--log", str(truncated)] + out, "truncated.npz")

    t = np.arange(3000) * 1e-3
    cases = {
        "text_t.npz": (dict(t=np.array([f"{x:.3f}" for x in t])), "array 't'"),
        "backwards.npz": (
            dict(t=np.concatenate([t[:100], t[100:][::-1]])),
            "array 't'",
        ),
        "gap.npz": (dict(t=np.where(t > 1, t + 0.5, t)), "array 't'"),
        "nan.npz": (
            dict(imu_angular_velocity=np.full((3000, 3), np.nan)),
            "array 'imu_angular_velocity'",
        ),
        "missing.npz": (dict(q_cmd=None), "q_cmd"),
        "names.npz": (
            dict(joint_names=np.array([f"J{i}" for i in range(30)])),
            "array 'joint_names'",
        ),
    }
    for name, (replace, culprit) in cases.items():
        path = identification_log(tmp_path / name, **replace)
        refused(capsys, ["identify", "--log", path] + out, name, culprit)
    refused(capsys, ["identify", "--log", str(tmp_path)] + out, str(tmp_path), "folder")
    refused(capsys, ["identify", "--log", str(tmp_path / "none.npz")] + out, "none.npz")
    assert not (tmp_path / "out" / "motor_model.yaml").exists()


def test_identification_refuses_noise_and_writes_no_model(tmp_path, capsys):
    # Δq is pure noise: the fit found Kτ ≈ -2e-9 and wrote it, exit 0.
    path = identification_log(tmp_path / "noise.npz")
    out = tmp_path / "out"
    line = refused(
        capsys,
        ["identify", "--log", path, "--out", str(out)],
        "noise.npz",
        "RLEG_JOINT",
        "do not identify",
        last_line=True,
    )
    assert "no motor model written" in line
    assert not (out / "motor_model.yaml").exists()
    assert not (out / "motor_model_least_squares.yaml").exists()


def test_check_identified_refuses_what_identifies_no_motor():
    rng = np.random.default_rng(1)
    m = 2000
    tau = 20 * np.sin(np.linspace(0, 20, m))
    dq = np.cos(np.linspace(0, 33, m))
    k_tau, k_v = 1e-4, 7e-3
    law = k_tau * tau + k_v * dq
    good = fit_least_squares(
        tau, dq, law + 1e-5 * rng.standard_normal(m), joint_name="knee"
    )
    check_identified(good, tau, dq, law)  # identified: no error
    noise = 1e-4 * rng.standard_normal(m)
    fitted = fit_least_squares(tau, dq, noise, joint_name="knee")
    with pytest.raises(ValueError, match=r"'knee'.*explains"):
        check_identified(fitted, tau, dq, noise)
    backwards = fit_least_squares(tau, dq, -law, joint_name="knee")  # Δq against τ
    with pytest.raises(ValueError, match=r"'knee'.*k_tau = -0.0001 .* is not > 0"):
        check_identified(backwards, tau, dq, -law)
    no_excitation = 1e-9 * np.ones(m) + 1e-4 * rng.standard_normal(m)
    tiny = fit_least_squares(tau, dq, no_excitation, joint_name="knee")
    with pytest.raises(ValueError, match="knee"):
        check_identified(tiny, tau, dq, no_excitation)


# ------------------------------------------------------------------- motor models
@pytest.mark.parametrize(
    "text, culprit",
    [
        (motor_model_text(extra="k_x: [0]\n"), "k_x"),  # unknown key
        ("joint_names: [RLEG_JOINT0\nk_tau: [1e-4]\n", "line 2"),  # syntax error
        (motor_model_text(k_tau="abc"), "k_tau[0]"),
        (motor_model_text(k_tau="-1e-4"), "k_tau"),  # no servo works that way
        (motor_model_text(joints=["RLEG_JOINT0"]), "RLEG_JOINT1"),  # joints missing
    ],
)
def test_motor_model_file_errors(tmp_path, capsys, text, culprit):
    path = tmp_path / "model.yaml"
    path.write_text(text)
    argv = ["experiment", "motion", "--motor-model", str(path), "--end", "3.0"]
    refused(capsys, argv + ["--out", str(tmp_path / "out")], "model.yaml", culprit)


# -------------------------------------------------------------- --debug, and bugs
def test_debug_lets_the_exception_through(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("duration: [\n")
    with pytest.raises(ValueError, match="bad.yaml"):
        main(["--debug", "simulate", "--config", str(path)])
    with pytest.raises(ValueError, match="bad.yaml"):
        main(["simulate", "--debug", "--config", str(path)])


def test_an_internal_error_is_one_line_too(monkeypatch, tmp_path, capsys):
    from hrp2_drake.experiments import simulate

    def bug(*args, **kwargs):
        raise RuntimeError("something\nbroke")

    monkeypatch.setattr(simulate, "run_simulate", bug)
    assert main(["simulate", "--out", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert "internal error" in err and "--debug" in err and "something; broke" in err
