"""Bad input to `hrp2-drake`: one line naming the culprit, exit code 2, no traceback,
and nothing simulated (the simulations are replaced by a failure in these tests)."""

import io
import zipfile
from functools import partial

import numpy as np
import pytest

from hrp2_drake.cli import main
from hrp2_drake.identification.fitting import check_identified, fit_least_squares
from hrp2_drake.paper import hrp2


def simulated(*args, **kwargs):
    raise AssertionError("simulated despite bad input")


@pytest.fixture(autouse=True)
def no_simulation(monkeypatch):
    """Any simulation (or estimation, or robot connection) fails the test: bad input
    must be refused before one starts."""
    from hrp2_drake.assembly import identification
    from hrp2_drake.paper import faults, motion
    from hrp2_drake.tools import control, estimate, simulate

    monkeypatch.setattr(simulate, "run_simulate", simulated)
    monkeypatch.setattr(motion, "run_motion", simulated)
    monkeypatch.setattr(identification, "collect_log", simulated)
    monkeypatch.setattr(estimate, "estimate_log", simulated)
    monkeypatch.setattr(control, "run_control", simulated)
    monkeypatch.setattr(faults, "run_fault_campaign", simulated)


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
    rows = np.array([np.concatenate([[t], hrp2.half_sitting()]) for t in times])
    rows = np.hstack([rows, np.ones((len(rows), extra_columns))])
    if change is not None:
        rows[change[0], change[1]] = change[2]
    np.savetxt(path, rows)
    return str(path)


def motor_model_text(k_tau="1e-4", joints=hrp2.RIGHT_LEG, extra=""):
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
    q = np.tile(hrp2.half_sitting(), (m, 1))
    for j in range(6):
        q[:, j] += 0.1 * np.sin(2 * np.pi * (1 + 0.3 * j) * t) * (t > 1.5)
    noise = 1e-4 * np.random.default_rng(rng_seed).standard_normal(q.shape)
    log = dict(
        t=t,
        joint_names=np.array(hrp2.JOINT_NAMES),
        q_measured=q,
        q_cmd=q + noise,
        imu_linear_acceleration=np.tile([0.0, 0.0, 9.81], (m, 1)),
        imu_angular_velocity=np.zeros((m, 3)),
        **{f"wrench_{name}": np.zeros((m, 6)) for name in hrp2.FT_SENSORS},
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


def test_a_window_the_collection_cannot_fill_is_refused_before_collecting(
    tmp_path, capsys
):
    """A window of 0.5 ms spans fewer than 3 samples of the collection's 1 ms log:
    refused before collecting (issue 28: after 50 s of it); `collect_log` fails the
    test if called."""
    config = tmp_path / "identify.yaml"
    config.write_text("window: 0.0005\n")
    refused(
        capsys,
        ["identify", "--config", str(config), "--out", str(tmp_path)],
        "IdentifyConfig.window",
        "0.0005 s spans fewer than 3 samples of 1 ms",
    )


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


# ------------------------------------------ every case of issue 20, one row each
def log_with_entry(path):
    """A log with an extra entry that is not an array."""
    identification_log(path)
    with zipfile.ZipFile(path, "a") as archive:
        archive.writestr("notes.txt", "recorded on the robot")


def log_with_forged_header(path):
    """A log whose q_measured header declares 10^12 rows (of 30 joints)."""
    identification_log(path)
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        header, dict(descr="<f8", fortran_order=False, shape=(10**12, 30))
    )
    with zipfile.ZipFile(path) as archive:
        entries = {name: archive.read(name) for name in archive.namelist()}
    entries["q_measured.npy"] = header.getvalue() + np.zeros(30).tobytes()
    with zipfile.ZipFile(path, "w") as archive:
        for name, data in entries.items():
            archive.writestr(name, data)


def write_case_files(folder, files: dict) -> None:
    """Each file of a case: text (with {d} the folder), bytes, a function of the path,
    or None for a folder."""
    for name, content in files.items():
        path = folder / name
        if content is None:
            path.mkdir()
        elif isinstance(content, str):
            path.write_text(content.replace("{d}", str(folder)))
        elif isinstance(content, bytes):
            path.write_bytes(content)
        else:
            content(path)


MOTOR = {"motor.yaml": motor_model_text()}
CONTROL = ["control", "--lcm", "memq://", "--motor-model", "{d}/motor.yaml"]
CONTROL += ["--config", "{d}/control.yaml"]
FAULTS = ["experiment", "faults", "--motor-model", "{d}/motor.yaml"]
FAULTS += ["--config", "{d}/faults.yaml"]
SIMULATE = ["simulate", "--config", "{d}/simulate.yaml"]
ESTIMATE = ["estimate", "--log", "{d}/log.npz"]
IDENTIFY = ["identify", "--log", "{d}/log.npz"]
SERVO = "station: {servo_file: {d}/servo.yaml}\n"
NAN_POSE = "station: {initial_positions: [" + ", ".join([".nan"] * 30) + "]}\n"
NARROW = np.zeros((3000, 5))  # 5 columns
SERVO_K7 = "joints:\n  RLEG_JOINT0: {k7: 1}\n"
DEEP = "duration: " + "[" * 20000 + "]" * 20000 + "\n"


def case(name, argv, files, *culprits):
    return pytest.param(argv, files, culprits, id=name)


@pytest.mark.parametrize(
    "argv, files, culprits",
    [
        # Silently accepted.
        case(
            "sensor period below the plant step",
            SIMULATE,
            {"simulate.yaml": "station: {sensors: {period: 1.0e-7}}\n"},
            "simulate.yaml",
            "sensors.period",
            "time step",
        ),
        case(
            "log period longer than the run",
            SIMULATE,
            {"simulate.yaml": "duration: 0.2\nlog_period: 10.0\n"},
            "simulate.yaml",
            "log_period",
            "longer than the run",
        ),
        case(
            "control: kf NaN",
            CONTROL,
            MOTOR | {"control.yaml": "torque_control: {controller: {kf: [.nan]}}\n"},
            "control.yaml",
            "controller.kf[0]",
            "finite",
        ),
        case(
            "control: a supervisor.period (the robot's sensors.period)",
            CONTROL,
            MOTOR | {"control.yaml": "torque_control: {supervisor: {period: 0.05}}\n"},
            "control.yaml",
            "torque_control.supervisor: SafetyConfig: 'period' moved to",
            "sensors.period",
        ),
        # Keys of a layout that changed: where each one went, on one line.
        case(
            "control: flat torque_control keys",
            CONTROL,
            MOTOR
            | {"control.yaml": "torque_control: {k6: 0.1, safety: {period: 1}}\n"},
            "control.yaml",
            "torque_control: TorqueControlConfig: 'k6' moved to "
            "'controller.k6', 'safety' moved to 'supervisor'",
        ),
        case(
            "control: the loop's keys at the top",
            CONTROL,
            MOTOR | {"control.yaml": "silence_timeout: 0.1\n"},
            "control.yaml",
            "'silence_timeout' moved to 'loop.silence_timeout'",
        ),
        case(
            "control: a station",
            CONTROL,
            MOTOR | {"control.yaml": "station: {robot: iiwa14}\n"},
            "control.yaml",
            "ControlConfig: 'station' moved to 'robot'",
        ),
        case(
            "control: loop.silence_timeout below two periods",
            CONTROL,
            MOTOR | {"control.yaml": "loop: {silence_timeout: 0.001}\n"},
            "control.yaml",
            "ControlConfig.loop.silence_timeout",
            "two periods",
        ),
        case(
            "force: flat keys of its torque control",
            [
                "experiment",
                "force",
                "--motor-model",
                "{d}/motor.yaml",
                "--config",
                "{d}/force.yaml",
            ],
            MOTOR | {"force.yaml": "torque_control: {window: 40}\n"},
            "force.yaml",
            "'window' moved to 'estimator.window'",
        ),
        case(
            "control: negative frequency",
            CONTROL,
            MOTOR | {"control.yaml": "frequency: -0.4\n"},
            "control.yaml",
            "frequency",
            "> 0",
        ),
        case(
            "control: frequency 2 kHz",
            CONTROL,
            MOTOR | {"control.yaml": "frequency: 2000\n"},
            "control.yaml",
            "frequency",
            "velocity limit",
        ),
        case(
            "control: amplitude 50 rad",
            CONTROL,
            MOTOR | {"control.yaml": "amplitude: 50\n"},
            "control.yaml",
            "amplitude",
            "position limits",
        ),
        case(
            "control: negative settle",
            CONTROL,
            MOTOR | {"control.yaml": "settle: -2\n"},
            "control.yaml",
            "settle",
        ),
        case(
            "faults: negative k6",
            FAULTS,
            MOTOR | {"faults.yaml": "k6: -1\n"},
            "faults.yaml",
            "k6",
        ),
        case(
            "faults: fault before the run",
            FAULTS,
            MOTOR | {"faults.yaml": "motion_fault_time: -5\n"},
            "faults.yaml",
            "motion_fault_time",
        ),
        # Unclear or internal.
        case(
            "20 000-deep YAML",
            SIMULATE,
            {"simulate.yaml": DEEP},
            "simulate.yaml",
            "nested",
        ),
        case(
            "servo file: unknown field",
            SIMULATE,
            {"simulate.yaml": SERVO, "servo.yaml": SERVO_K7},
            "servo_file",
            "servo.yaml",
            "k7",
        ),
        case(
            "servo file: empty",
            SIMULATE,
            {"simulate.yaml": SERVO, "servo.yaml": ""},
            "servo_file",
            "servo.yaml",
            "joints",
        ),
        case(
            "log header of 10^12 rows",
            ESTIMATE,
            {"log.npz": log_with_forged_header},
            "log.npz",
            "'q_measured'",
            "header",
        ),
        case(
            "log with an entry that is no array",
            IDENTIFY,
            {"log.npz": log_with_entry},
            "log.npz",
            "notes.txt",
            "not an array",
        ),
        case(
            "joint_torque_true of the wrong width",
            ESTIMATE,
            {"log.npz": partial(identification_log, joint_torque_true=NARROW)},
            "log.npz",
            "'joint_torque_true'",
            "(3000, 30)",
        ),
        case(
            "unknown contact approximation",
            SIMULATE,
            {"simulate.yaml": "station: {contact_approximation: magic}\n"},
            "simulate.yaml",
            "contact_approximation",
            "'magic'",
            "'sap'",
        ),
        case(
            "faults: no worker",
            FAULTS,
            MOTOR | {"faults.yaml": "jobs: 0\n"},
            "faults.yaml",
            "jobs",
        ),
        case(
            "F/T array of 5 columns",
            ESTIMATE,
            {"log.npz": partial(identification_log, wrench_right_foot=NARROW)},
            "log.npz",
            "'wrench_right_foot'",
            "(3000, 6)",
        ),
        case(
            "log that is no zip",
            ESTIMATE,
            {"log.npz": b"PK\x03\x04" + b"\x00" * 40},
            "log.npz",
            "zip",
        ),
        case(
            "negative extra_command_latency",
            SIMULATE,
            {"simulate.yaml": "station: {extra_command_latency: -1}\n"},
            "simulate.yaml",
            "extra_command_latency",
        ),
        case(
            "NaN initial_positions",
            SIMULATE,
            {"simulate.yaml": NAN_POSE},
            "simulate.yaml",
            "initial_positions",
            "RLEG_JOINT0",
        ),
        case(
            "missing servo file of the iiwa",
            SIMULATE + ["--robot", "iiwa14"],
            {"simulate.yaml": SERVO},
            "servo.yaml",
            "not found",
            "'iiwa14'",
        ),
        case(
            "a folder as the log", ESTIMATE, {"log.npz": None}, "log.npz", "is a folder"
        ),
        case(
            "a text file as the log",
            ESTIMATE,
            {"log.npz": "t q\n0 1\n"},
            "log.npz",
            "text file",
            "expected an .npz",
        ),
    ],
)
def test_every_bad_input_is_one_line(tmp_path, capsys, argv, files, culprits):
    write_case_files(tmp_path, files)
    argv = [a.replace("{d}", str(tmp_path)) for a in argv]
    line = refused(capsys, argv + ["--out", str(tmp_path / "out")], *culprits)
    assert "internal error" not in line and "pickled" not in line


# -------------------------------------------------------------- --debug, and bugs
def test_debug_lets_the_exception_through(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("duration: [\n")
    with pytest.raises(ValueError, match="bad.yaml"):
        main(["--debug", "simulate", "--config", str(path)])
    with pytest.raises(ValueError, match="bad.yaml"):
        main(["simulate", "--debug", "--config", str(path)])


def test_an_internal_error_is_one_line_too(monkeypatch, tmp_path, capsys):
    from hrp2_drake.tools import simulate

    def bug(*args, **kwargs):
        raise RuntimeError("something\nbroke")

    monkeypatch.setattr(simulate, "run_simulate", bug)
    assert main(["simulate", "--out", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert "internal error" in err and "--debug" in err and "something; broke" in err
