"""Configs are validated once, where they are loaded: `validate_config` runs the
config's own `validate()`, which must check every config nested in it; and a command
applies its options before that validation, never after it."""

import copy
import dataclasses
import importlib
import pkgutil
import shutil
from pathlib import Path

import numpy as np
import pytest
from cli_errors import refused

import hrp2_drake
from hrp2_drake.config import _callable_without_arguments, nested_configs
from hrp2_drake.description import load_robot_description
from hrp2_drake.estimation.base_kinematics import ImuFusion
from hrp2_drake.tools.record import RecordConfig


def _config_classes() -> list[type]:
    """Every config of hrp2_drake (a dataclass defined in it) with a `validate()`."""
    for info in pkgutil.walk_packages(hrp2_drake.__path__, "hrp2_drake."):
        importlib.import_module(info.name)
    found = {}
    for module in pkgutil.walk_packages(hrp2_drake.__path__, "hrp2_drake."):
        for value in vars(importlib.import_module(module.name)).values():
            if (
                isinstance(value, type)
                and dataclasses.is_dataclass(value)
                and value.__module__.startswith("hrp2_drake.")
                and callable(getattr(value, "validate", None))
            ):
                found[f"{value.__module__}.{value.__qualname__}"] = value
    return [found[name] for name in sorted(found)]


def _validated_below(config, path: str = "") -> list[tuple[str, object]]:
    """The configs nested in `config` that have a `validate()` of their own (through
    nested configs that have none)."""
    out = []
    for where, child in nested_configs(config, path):
        if _callable_without_arguments(getattr(child, "validate", None)):
            out.append((where, child))
        else:
            out += _validated_below(child, where)
    return out


#: Valid instances of the configs whose defaults are not (no robot name, no bus).
VALID = {
    "RobotDescription": lambda: copy.deepcopy(load_robot_description("hrp2")),
    "RecordConfig": lambda: RecordConfig(robot="xl330_pendulum"),
    "ImuFusion": lambda: ImuFusion("imu"),
}

#: The steps' configs that the builders fill with the control period: it has no
#: default, so they are made with one (s).
WITH_PERIOD = {
    "DelayPredictorConfig",
    "DisturbanceObserverConfig",
    "InverseDynamicsConfig",
    "TorqueControllerConfig",
}
PERIOD = 0.001


def _made(schema: type):
    """`schema`'s default instance (`VALID`'s, or with the control period)."""
    if schema.__name__ in VALID:
        return VALID[schema.__name__]()
    return schema(period=PERIOD) if schema.__name__ in WITH_PERIOD else schema()


def _composite_defaults():
    """(class, default instance) of each config whose defaults nest validated
    configs."""
    out = []
    for schema in _config_classes():
        config = _made(schema)
        if _callable_without_arguments(config.validate) and _validated_below(config):
            out.append(pytest.param(schema, config, id=schema.__name__))
    return out


#: Nested configs validated where they are used, not by their parent, and why.
VALIDATED_WHERE_USED = {
    ("IdentifyConfig", "station"): "a simulation's: validated by make_station when "
    "identify collects (without --log); a real robot's logs need only its description",
}


@pytest.mark.parametrize("schema, config", _composite_defaults())
def test_a_config_validates_every_config_nested_in_it(monkeypatch, schema, config):
    nested = [
        (where, child)
        for where, child in _validated_below(config)
        if (schema.__name__, where) not in VALIDATED_WHERE_USED
    ]
    called = set()
    for _, child in nested:
        original = type(child).validate

        def record(self, *args, _original=original, **kwargs):
            called.add(id(self))
            return _original(self, *args, **kwargs)

        monkeypatch.setattr(type(child), "validate", record)
    config.validate()
    missing = [where for where, child in nested if id(child) not in called]
    assert not missing, f"{schema.__name__}.validate() does not validate {missing}"


#: The configs whose defaults are refused on purpose, and why. Every other config's
#: defaults validate: one that stops validating fails below, never drops out.
INVALID_DEFAULTS = {
    "DisturbanceObserverConfig": "a system's config, made by code with its joints",
    "InverseDynamicsConfig": "a system's config, made by code with its joints",
    "DelayPredictorConfig": "a system's config, made by code with its joints",
    "TorqueControllerConfig": "a system's config, made by code with its joints",
    "TorqueEstimatorConfig": "a system's config, made by code with its joints",
    "ServoModel": "a servo model's control table, read from its file",
    "ServoParams": "a servo file's parameters of every joint, read from it",
}


def _defaults(valid: bool):
    """(class, default instance) of each config (whose `validate()` takes no
    argument) whose defaults are valid, or refused (`INVALID_DEFAULTS`)."""
    out = []
    for schema in _config_classes():
        config = _made(schema)
        if _callable_without_arguments(config.validate) and valid != (
            schema.__name__ in INVALID_DEFAULTS
        ):
            out.append(pytest.param(config, id=schema.__name__))
    return out


def _valid_defaults():
    return _defaults(valid=True)


def test_the_configs_refused_by_default_are_the_ones_listed():
    names = {param.id for param in _defaults(valid=False)}
    assert names == set(INVALID_DEFAULTS)


@pytest.mark.parametrize("config", _defaults(valid=False))
def test_defaults_refused_on_purpose_are_refused(config):
    with pytest.raises(ValueError):
        copy.deepcopy(config).validate()


@pytest.mark.parametrize("config", _valid_defaults())
def test_validation_changes_nothing(config):
    before = copy.deepcopy(config)
    config.validate()
    assert config == before


def test_a_plain_gain_becomes_a_list_when_made_not_when_validated():
    from hrp2_drake.assembly.torque_control import ControllerSettings
    from hrp2_drake.config import set_field_at

    settings = ControllerSettings(kp=0.5, kf=1.0)
    assert settings.kp == [0.5] and settings.kf == [1.0]
    set_field_at(settings, "kp", 2.0)  # past the constructor: refused, not rewritten
    with pytest.raises(ValueError, match=r"controller\.kp: 2\.0, expected a list"):
        settings.validate()
    assert settings.kp == 2.0


# ------------------------------------------- bad input through the command line


def simulated(*args, **kwargs):
    raise AssertionError("simulated despite bad input")


@pytest.fixture
def no_simulation(monkeypatch):
    """Any simulation (or robot connection) fails the test: bad input is refused
    before one starts."""
    from hrp2_drake.assembly import identification
    from hrp2_drake.paper import estimation, stability
    from hrp2_drake.tools import control, simulate, track

    monkeypatch.setattr(estimation, "run_estimation_experiment", simulated)
    monkeypatch.setattr(stability, "run_stability_experiment", simulated)
    monkeypatch.setattr(simulate, "run_simulate", simulated)
    monkeypatch.setattr(track, "run_track", simulated)
    monkeypatch.setattr(control, "run_control", simulated)
    monkeypatch.setattr(identification, "collect_log", simulated)


def motor_model(joints: list[str]) -> str:
    n = len(joints)
    return (
        f"joint_names: [{', '.join(joints)}]\nk_tau: [{', '.join(['1e-4'] * n)}]\n"
        f"k_v: [{', '.join(['1e-2'] * n)}]\n"
    )


RIGHT_LEG = [f"RLEG_JOINT{k}" for k in range(6)]
IIWA = [f"iiwa_joint_{k}" for k in range(1, 8)]
SIMULATE = ["simulate", "--config", "{d}/config.yaml"]
TRACK = ["track", "--motor-model", "{d}/motor.yaml", "--config", "{d}/config.yaml"]
CONTROL = ["control", "--lcm", "memq://", "--motor-model", "{d}/motor.yaml"]
CONTROL += ["--config", "{d}/config.yaml"]
TUNE = ["tune", "--motor-model", "{d}/motor.yaml", "--config", "{d}/config.yaml"]
ESTIMATION = ["experiment", "estimation", "--config", "{d}/config.yaml"]
STABILITY = ["experiment", "stability", "--motor-model", "{d}/motor.yaml"]
STABILITY += ["--config", "{d}/config.yaml"]


def case(name, argv, config, *culprits, motor=RIGHT_LEG):
    return pytest.param(argv, config, motor, culprits, id=name)


@pytest.mark.parametrize(
    "argv, config, motor, culprits",
    [
        # A scenario given is never replaced (was: fixed_base, silently).
        case(
            "unknown scenario, fixed robot",
            SIMULATE + ["--robot", "iiwa14"],
            "station: {scenario: flying}\n",
            "config.yaml",
            "StationConfig.scenario",
            "'flying'",
            "robot 'iiwa14': fixed_base)",
        ),
        case(
            "unknown scenario, fixed robot in the file",
            SIMULATE,
            "station: {robot: iiwa14, scenario: flying}\n",
            "StationConfig.scenario",
            "'flying'",
            "'hanging'",
            "iiwa14': fixed_base)",
        ),
        case(
            "floating scenario, fixed robot",
            SIMULATE + ["--robot", "iiwa14"],
            "station: {scenario: hanging}\n",
            "StationConfig.scenario",
            "'hanging'",
            "only 'fixed_base'",
        ),
        case(
            "track: unknown scenario, floating robot",
            TRACK + ["--robot", "hrp2"],
            "station: {scenario: flying}\n",
            "StationConfig.scenario",
            "'flying'",
            "robot 'hrp2': fixed_base, hanging, standing, standing_on_block, lowered)",
        ),
        # The scene: NaN, inf and negative numbers.
        case(
            "NaN string stiffness",
            SIMULATE,
            "station: {hanging: {stiffness: .nan}}\n",
            "StationConfig.hanging.stiffness",
            "finite",
        ),
        case(
            "negative sway damping",
            SIMULATE,
            "station: {hanging: {sway_damping: [5.0, -1.0]}}\n",
            "StationConfig.hanging.sway_damping[1]",
            ">= 0",
        ),
        case(
            "negative block height",
            SIMULATE,
            "station: {block_height: -0.05}\n",
            "StationConfig.block_height",
            "> 0",
        ),
        case(
            "infinite obstacle",
            SIMULATE,
            "station: {obstacles: [{size: [1.0, 1.0, .inf]}]}\n",
            "StationConfig.obstacles[0].size",
            "finite",
        ),
        case(
            "negative obstacle friction",
            SIMULATE,
            "station: {obstacles: [{friction: -0.5}]}\n",
            "StationConfig.obstacles[0].friction",
            ">= 0",
        ),
        # Windows: the config's key, the samples and the time.
        case(
            "control: a window of 1 sample",
            CONTROL,
            "torque_control: {estimator: {window: 1}}\n",
            "config.yaml",
            "TorqueControlConfig.estimator.window",
            "1 sample",
            "1 ms",
            "3 or more",
        ),
        case(
            "control: a per-joint window of 1 sample",
            CONTROL,
            "torque_control: {estimator: {windows: {RLEG_JOINT3: 1}}}\n",
            "TorqueControlConfig.estimator.windows['RLEG_JOINT3']",
            "1 sample",
            "1 ms",
        ),
        case(
            "estimation: a per-signal window of 1 sample",
            ESTIMATION,
            "per_signal_window: 1\n",
            "config.yaml",
            "EstimationConfig.per_signal_window: 1 sample (1 ms at 1 kHz)",
        ),
        case(
            "estimation: a window of 2 samples",
            ESTIMATION,
            "windows: [80, 2]\n",
            "EstimationConfig.windows[1]: 2 samples (2 ms",
        ),
        case(
            "stability: a window of 1 sample",
            STABILITY,
            "window: 1\n",
            "StabilityConfig.window: 1 sample (1 ms at 1 kHz)",
        ),
        case(
            "control: NaN damping ratio",
            CONTROL,
            "torque_control: {controller: {damping_ratio: .nan}}\n",
            "TorqueControlConfig.controller.damping_ratio",
            "finite",
        ),
        case(
            "control: negative damping ratio",
            CONTROL,
            "torque_control: {controller: {damping_ratio: -0.7}}\n",
            "TorqueControlConfig.controller.damping_ratio",
            ">= 0",
        ),
        # Joints: names and the sequences that must match them.
        case(
            "control: unknown joint",
            CONTROL,
            "torque_control: {joints: [RLEG_JOINT0, KNEE]}\n",
            "ControlConfig.torque_control.joints",
            "'KNEE'",
            "'hrp2'",
        ),
        case(
            "control: a joint twice",
            CONTROL,
            "torque_control: {joints: [RLEG_JOINT0, RLEG_JOINT0]}\n",
            "ControlConfig.torque_control.joints",
            "more than once",
        ),
        case(
            "control: kp of 2 values for 6 joints",
            CONTROL,
            "torque_control: {controller: {kp: [1.0, 2.0]}}\n",
            "ControlConfig.torque_control.controller.kp",
            "2 values",
            "one or 6",
        ),
        case(
            "track: kp of 3 values for 7 joints",
            TRACK,
            "torque_control: {controller: {kp: [1.0, 2.0, 3.0]}}\n",
            "TrackConfig.torque_control.controller.kp",
            "one or 7",
            motor=IIWA,
        ),
        case(
            "control: a window of an unknown signal",
            CONTROL,
            "torque_control: {estimator: {windows: {nowhere: 5}}}\n",
            "ControlConfig.torque_control.estimator.windows",
            "'nowhere'",
        ),
        case(
            "track: an unknown force frame",
            TRACK,
            "torque_control: {controller: {force_frame: nowhere}}\n",
            "TrackConfig.torque_control.controller.force_frame",
            "'nowhere'",
            motor=IIWA,
        ),
        case(
            "control: torque control after the end",
            CONTROL,
            "duration: 2.0\ntorque_control: {start_time: 3.0}\n",
            "ControlConfig.torque_control.start_time",
            "never start",
        ),
        case(
            "tune: another robot",
            TUNE,
            "station: {robot: iiwa14, scenario: fixed_base}\n",
            "TuneConfig.station.robot",
            "'iiwa14'",
        ),
        case(
            "tune: kp's joints not controlled",
            TUNE,
            "torque_control: {joints: [RLEG_JOINT0]}\n",
            "TuneConfig.torque_control.joints",
            "RLEG_JOINT1",
            "exclude",
        ),
        case(
            "track: a force that pulls",
            TRACK,
            "press: 5.0\nforce_amplitude: 8.0\n",
            "TrackConfig.force_amplitude",
            "pull",
            motor=IIWA,
        ),
        case(
            "tune: kp of 2 values",
            TUNE,
            "torque_control: {controller: {kp: [1.0, 2.0]}}\n",
            "TuneConfig.torque_control.controller.kp",
            "one or 6",
        ),
    ],
)
def test_bad_config_is_one_line_naming_the_key(
    tmp_path, capsys, no_simulation, argv, config, motor, culprits
):
    (tmp_path / "config.yaml").write_text(config)
    (tmp_path / "motor.yaml").write_text(motor_model(motor))
    argv = [a.replace("{d}", str(tmp_path)) for a in argv]
    refused(capsys, argv + ["--out", str(tmp_path / "out")], *culprits)


def test_a_model_with_a_kinematic_loop_names_the_model_file(
    tmp_path, capsys, no_simulation
):
    folder = tmp_path / "looped"
    shutil.copytree(Path(hrp2_drake.__file__).parents[1] / "models" / "iiwa14", folder)
    urdf = folder / "iiwa14.urdf"
    loop = (
        '<joint name="loop" type="fixed"><parent link="iiwa_link_7"/>'
        '<child link="iiwa_link_2"/></joint>\n</robot>'
    )
    urdf.write_text(urdf.read_text().replace("</robot>", loop))
    argv = ["simulate", "--robot", str(folder / "robot.yaml")]
    refused(
        capsys,
        argv + ["--out", str(tmp_path / "out")],
        "robot.yaml: model_file",
        f"'{urdf}'",
        "loops",
    )


def test_a_log_label_of_the_wrong_shape_is_one_line(tmp_path, capsys, no_simulation):
    """A 2-D `phase` (was a numpy broadcasting error)."""
    from hrp2_drake.paper import hrp2

    m = 3000
    t = np.arange(m) * 1e-3
    q = np.tile(hrp2.half_sitting(), (m, 1))
    q[:, :6] += 0.1 * np.sin(2 * np.pi * t)[:, np.newaxis]
    np.savez(
        tmp_path / "log.npz",
        t=t,
        joint_names=np.array(hrp2.JOINT_NAMES),
        q_measured=q,
        q_cmd=q + 1e-4,
        imu_linear_acceleration=np.tile([0.0, 0.0, 9.81], (m, 1)),
        imu_angular_velocity=np.zeros((m, 3)),
        phase=np.zeros((m, 2)),
        **{f"wrench_{name}": np.zeros((m, 6)) for name in hrp2.FT_SENSORS},
    )
    argv = ["identify", "--log", str(tmp_path / "log.npz")]
    refused(
        capsys,
        argv + ["--out", str(tmp_path / "out")],
        "log.npz",
        "'phase'",
        f"({m}, 2)",
        f"expected ({m},)",
    )
