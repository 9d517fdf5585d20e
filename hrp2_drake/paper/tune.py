"""`hrp2-drake tune`: closed-loop tuning of the torque controller (paper Sec. 4).

Searches the knobs of `TorqueControlConfig` (per-joint K_p, K_d's damping ratio, the
common and per-joint/per-sensor Savitzky-Golay windows, the feedback signals, the delay
predictor, the disturbance observer's bandwidth; K6 only when asked) by simulating the
hanging HRP-2's right leg on the stair-climbing swing, with Optuna's TPE sampler.

.. code-block:: text

    Optuna study (main process)             executor (ProcessPoolExecutor, or a Dask
    study.journal on disk                   cluster through Client.get_executor())
      ask ─► suggest(SEARCH_SPACE) ─► TrialTask ─► run_trial: build_torque_control,
                                                   simulate, motion.evaluate
      tell ◄─ trial_cost(ratios vs position control) ◄─ per-joint errors, fallback,
                                                         saturation

Cost of a trial (`trial_cost`), from the paper's Tables 2-3 formulas (`motion.evaluate`)
on the 5 moving right-leg joints, each divided by the robot's own position control on
the same motion (r < 1: torque control more accurate):

    cost = max_j,k r_jk + mean_weight · mean_j,k r_jk
           + fallback_penalty · [fell back or the supervisor saw a fault]
           + saturation_penalty · (share of ticks with some |Δq| at delta_q_limit)

with r_j,average = average_error_j / average_error_j(position control) and likewise
for the maximum error. The goal (torque control at least as accurate as position
control on every joint, average and maximum) is met when max r <= 1 with no fallback.
A trial that fails to simulate costs FAILED_COST.

Both executors are concurrent.futures Executors: the ask/tell loop submits the same
picklable top-level function with the same picklable task to either, and waits on
the futures with concurrent.futures.wait (Dask's ClientExecutor returns
concurrent.futures.Future objects).
"""

import concurrent.futures as cf
import contextlib
import copy
import io
import json
import os
import socket
import time
import typing
import warnings
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from hrp2_drake import console
from hrp2_drake.assembly.torque_control import (
    EstimatorSettings,
    TorqueControlConfig,
    check_for_robot,
)
from hrp2_drake.config import (
    check_finite,
    field_at,
    field_type,
    one_line,
    replace_fields,
    set_field_at,
)
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.paper import hrp2
from hrp2_drake.paper.motion import estimation_delay
from hrp2_drake.report import markdown_table, pyplot, save_figure
from hrp2_drake.robot.station import StationConfig

INSTALL_HINT = "pip install -e '.[tune]'"
STUDY_FILE = "study.journal"
BASELINE_FILE = "position_control.json"
#: The cost of a trial whose simulation failed (raised, or gave non-finite errors).
FAILED_COST = 1000.0
#: What a trial's simulation raises when its configuration is bad (Drake's
#: RuntimeError, a NaN input's ValueError, an invalid sampled config's ValueError).
TRIAL_FAILURES = (RuntimeError, ValueError, ArithmeticError)
KINDS = ("int", "float", "log-float", "bool", "categorical")


class MissingDependencyError(ValueError):
    """The `tune` extra (optuna, dask[distributed]) is not installed."""


def _require(module: str):
    """Imports `module` (optuna, distributed) or raises one clear line."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise MissingDependencyError(
            f"hrp2-drake tune needs the '{module}' package: {INSTALL_HINT}"
        ) from None


# --------------------------------------------------------------------------------------
# The search space.


@dataclass(frozen=True)
class ParamSpec:
    """One searched knob of `TorqueControlConfig`.

    Args:
        name: the Optuna parameter's name (per-key specs: `name[key]`).
        kind: "int", "float", "log-float" (log-uniform), "bool", "categorical".
        field: the TorqueControlConfig field it sets, by its path (e.g.
            "controller.kp", `torque_control.field_at`). A spec whose field the
            config does not have is left out (reported).
        low, high: the range (int, float, log-float); step for int.
        choices: the values of a categorical.
        keys: one parameter per key: joints of a list field in the controlled joints'
            order (kp), or keys of a dict field (windows: joint, F/T sensor or
            "imu"). A list field that is a number gets one shared parameter.
        off: if not None, a bool parameter `name_on` is searched first, and the
            field is `off` when it is False (disturbance_observer: 0 = none).
        scale_of: the value is a fraction of this (already set) integer field (its
            path), rounded to an integer of the field's parity in [3, field]
            (windows: of `estimator.window`; the estimator centres every window on the
            longest one's centre, which needs the same parity).
        per_delay: the value is the product of the field and the estimation
            chain's delay (dimensionless), searched in [low, high] and set as value /
            delay once the windows are (the observer: bandwidth · delay <= 1 keeps
            a delayed integral-like loop's phase margin, in contact too).
        default: searched unless TuneConfig.exclude names it; False: only when
            TuneConfig.include names it (k6).
    """

    name: str
    kind: str
    field: str
    low: float = 0.0
    high: float = 0.0
    step: int = 1
    choices: tuple = ()
    keys: tuple[str, ...] = ()
    off: float | None = None
    scale_of: str = ""
    per_delay: bool = False
    default: bool = True


#: The search space, edited here. The per-joint parameters are the right leg's
#: (HRP-2's torque-controlled joints).
# fmt: off
SEARCH_SPACE: tuple[ParamSpec, ...] = (
    # Position feedback relative to the servo's stiffness (Sec. 4.2): fixed by the
    # user (TuneConfig.k6); searched only with `include: [k6]`.
    ParamSpec("k6", "log-float", "controller.k6", low=0.05, high=1.0, default=False),
    # K_p of eq. 11, per joint: the gain of the torque error in Δq, at most 1: with
    # an undelayed τ̂ eq. 11 is unstable for K_p > 1 (DeltaQTorqueController's
    # docstring), and short windows or the predictor come close to that. (Searched up
    # to 4 with windows down to 6 samples, the hanging leg tuned K_p = 1.5-2.7 on
    # three joints: unstable in the force experiment's contact.) 0 belongs in the
    # range: with the disturbance observer, K_p = 0 tracked best by hand.
    ParamSpec("kp", "float", "controller.kp", low=0.0, high=1.0, keys=hrp2.RIGHT_LEG),
    # K_d of eq. 12, through its damping ratio (acts with feedback_velocity=estimate).
    ParamSpec("damping_ratio", "float", "controller.damping_ratio", low=0.2, high=2.0),
    # The q̇ of ė_q (eq. 12) and of the friction feedforward K_v q̇ (eq. 10, 13).
    ParamSpec("feedback_velocity", "categorical", "controller.feedback_velocity",
              choices=("reference", "estimate")),
    ParamSpec("friction_velocity", "categorical", "controller.friction_velocity",
              choices=("reference", "estimate")),
    # The longest Savitzky-Golay window: the estimates' delay, (window - 1) / 2 ms.
    ParamSpec("window", "int", "estimator.window", low=15, high=100),
    # Per-joint and per-sensor windows, fractions of `window`, centred on its centre
    # (the same instant, the same delay): shorter, less lag of a fast signal's fit.
    # Not the F/T sensors': the hanging leg's foot touches nothing, so the tuning
    # motion cannot see their window (searched, it went to 10 samples, which the force
    # experiment's force feedback does not survive).
    ParamSpec("windows", "float", "estimator.windows", low=0.2, high=1.0,
              keys=hrp2.RIGHT_LEG + ("imu",), scale_of="estimator.window"),
    # The DelayPredictor: τ̂ (and q̂̇) carried from the delay to the present.
    ParamSpec("predictor", "bool", "observer.predictor"),
    # The disturbance observer's bandwidth (rad/s), or off (0), searched as bandwidth
    # x the estimates' delay: at most 1, the classical bound for a loop closed through
    # a delay. (Searched in rad/s up to 400 it tuned to 400 at a 16.5 ms delay: best
    # on the hanging leg, and unstable in the force experiment's contact.)
    ParamSpec("disturbance_observer", "log-float", "observer.disturbance_observer",
              low=0.05, high=1.0, off=0.0, per_delay=True),
)
# fmt: on


@dataclass(frozen=True)
class Param:
    """One Optuna parameter of the active space: a spec and, if per key, its key;
    `target` says how the field is set: "scalar", "list" (one per joint), "dict"."""

    spec: ParamSpec
    key: str = ""
    target: str = "scalar"

    @property
    def name(self) -> str:
        return f"{self.spec.name}[{self.key}]" if self.key else self.spec.name


def _field_kind(path: str) -> str | None:
    """ "list", "dict" or "scalar" for a TorqueControlConfig field (its path); None if
    absent."""
    hint = field_type(TorqueControlConfig, path)
    if hint is None:
        return None
    origin = typing.get_origin(hint)
    return {list: "list", dict: "dict"}.get(origin, "scalar")


def active_space(
    config: "TuneConfig", joints: list[str], space: tuple[ParamSpec, ...] = SEARCH_SPACE
) -> tuple[list[Param], list[str]]:
    """The Optuna parameters `config` searches, and notes on the specs left out.

    Args:
        joints: the torque-controlled joints (a list field's order).
    """
    params, notes = [], []
    for spec in space:
        if spec.kind not in KINDS:
            raise ValueError(
                f"SEARCH_SPACE {spec.name}: kind '{spec.kind}' not in {KINDS}"
            )
        if spec.name in config.exclude or not (
            spec.default or spec.name in config.include
        ):
            continue
        kind = _field_kind(spec.field)
        if kind is None:
            notes.append(
                f"{spec.name}: TorqueControlConfig has no field '{spec.field}'"
            )
            continue
        if not spec.keys or kind == "scalar":
            params.append(Param(spec))
            continue
        if kind == "list":
            missing = [k for k in spec.keys if k not in joints]
            if missing:
                raise ValueError(
                    f"SEARCH_SPACE {spec.name}: {missing} are not torque-controlled "
                    f"joints ({joints})"
                )
        params += [Param(spec, key, kind) for key in spec.keys]
    return params, notes


def suggest(trial, space: list[Param]) -> dict:
    """Asks `trial` (an optuna.Trial) for every parameter of `space` (define-by-run:
    an `off` spec's value only when its switch is on); returns trial.params."""
    for param in space:
        spec, name = param.spec, param.name
        if spec.off is not None and not trial.suggest_categorical(
            f"{name}_on", (False, True)
        ):
            continue
        if spec.kind == "int":
            trial.suggest_int(name, int(spec.low), int(spec.high), step=spec.step)
        elif spec.kind in ("float", "log-float"):
            trial.suggest_float(name, spec.low, spec.high, log=spec.kind == "log-float")
        elif spec.kind == "bool":
            trial.suggest_categorical(name, (False, True))
        else:
            trial.suggest_categorical(name, spec.choices)
    return dict(trial.params)


def _scaled(spec: ParamSpec, value: float, config: TorqueControlConfig) -> int:
    reference = int(field_at(config, spec.scale_of))
    lowest = 3 + (reference - 3) % 2  # the shortest window of reference's parity
    value = int(round(value * reference))
    value += (reference - value) % 2  # towards `reference`: its parity
    return min(reference, max(lowest, value))


def apply_params(
    base: TorqueControlConfig, params: dict, space: list[Param], joints: list[str]
) -> TorqueControlConfig:
    """`base` with the values of `params` (Optuna names) set; parameters of `space`
    absent from `params` keep the base's value, an `off` spec switched off gets `off`.
    """
    config = copy.deepcopy(base)
    # Scaled parameters last: they read the fields they scale (set first).
    for param in sorted(space, key=lambda p: (bool(p.spec.scale_of), p.spec.per_delay)):
        spec, name = param.spec, param.name
        if spec.off is not None and f"{name}_on" in params and not params[f"{name}_on"]:
            set_field_at(config, spec.field, spec.off)
            continue
        if name not in params:
            continue
        value = params[name]
        if spec.scale_of:
            value = _scaled(spec, value, config)
        if spec.per_delay:
            value = value / estimation_delay(config)
        if param.target == "list":
            values = list(field_at(config, spec.field))
            if len(values) == 1:
                values = values * len(joints)
            values[joints.index(param.key)] = float(value)
            set_field_at(config, spec.field, values)
        elif param.target == "dict":
            values = field_at(config, spec.field)
            values[param.key] = value
            if spec.scale_of and value == field_at(config, spec.scale_of):
                del values[param.key]  # the common window: left implicit
        else:
            set_field_at(config, spec.field, value)
    return config


def base_params(
    base: TorqueControlConfig, space: list[Param], joints: list[str]
) -> dict:
    """The Optuna parameters that `apply_params` turns back into `base` (the first,
    enqueued trial: the untuned configuration)."""
    out = {}
    for param in space:
        spec, name = param.spec, param.name
        value = field_at(base, spec.field)
        if param.target == "list":
            value = value[0] if len(value) == 1 else value[joints.index(param.key)]
        elif param.target == "dict":
            value = value.get(
                param.key, field_at(base, spec.scale_of) if spec.scale_of else None
            )
            if value is None:
                continue
        if spec.scale_of:
            value = value / field_at(base, spec.scale_of)
        if spec.per_delay:
            value = value * estimation_delay(base)
        if spec.off is not None:
            out[f"{name}_on"] = value != spec.off
            if value == spec.off:
                continue
        if spec.kind == "int":
            value = int(value)
        elif spec.kind in ("float", "log-float"):
            value = float(value)
        out[name] = value
    return out


# --------------------------------------------------------------------------------------
# The configuration.


def _default_torque_control() -> TorqueControlConfig:
    # As the motion experiment's: hanging, the F/T offsets calibrated at start-up.
    return TorqueControlConfig(
        estimator=EstimatorSettings(offset_calibration_time=0.25)
    )


@dataclass
class TuneConfig:
    """Configuration of `hrp2-drake tune`.

    Args:
        trials: trials to run in this invocation (added to those the study has).
        workers: trials in flight; 0 = auto: 2 local processes, or one per thread of
            the Dask cluster.
        scheduler: a Dask scheduler's address (tcp://host:port); empty: a local
            process pool. The cluster's workers need hrp2_drake (same version)
            installed; they receive the motor model and configs, not file paths.
        connect_timeout: how long to try to reach the scheduler (s).
        k6: the torque controller's position feedback relative to the servo (Sec.
            4.2), fixed (default 0.1: 10% of the servo's stiffness).
        include: SEARCH_SPACE names searched though not by default (k6: K6 is
            then searched in its range, `k6` is the first trial's).
        exclude: SEARCH_SPACE names left at torque_control's values.
        station: the robot (hanging, as in the paper's motion experiment).
        start, end: the part of the climbing motion simulated (s); the default is one
            full swing of the right leg (the motion repeats every 3 s).
        settle: the first pose held before the motion (s); errors count after it.
            Must be >= torque_control.start_time (errors of torque control only).
        smoothing: the reference spline's smoothing (`motion.climbing_reference`).
        torque_control: the base configuration: what the space does not search, and
            the study's first trial (its k6 is replaced by `k6`).
        motor_model: a MotorModel YAML file; empty: --motor-model, or identify one.
        seed: the TPE sampler's seed (offset by the trials already in the study).
        startup_trials: random trials before TPE models the cost.
        study_name: the Optuna study's name in out/study.journal.
        mean_weight, fallback_penalty, saturation_penalty: the cost's weights (see
            the module docstring).
    """

    trials: int = 40
    workers: int = 0
    scheduler: str = ""
    connect_timeout: float = 10.0
    k6: float = 0.1
    include: list[str] = field(default_factory=list)
    exclude: list[str] = field(default_factory=list)
    station: StationConfig = field(
        default_factory=lambda: StationConfig(scenario="hanging")
    )
    start: float = 2.0
    end: float = 5.0
    settle: float = 1.0
    smoothing: float = 1e-8
    torque_control: TorqueControlConfig = field(default_factory=_default_torque_control)
    motor_model: str = ""
    seed: int = 0
    startup_trials: int = 10
    study_name: str = "hrp2_tune"
    mean_weight: float = 0.1
    fallback_penalty: float = 10.0
    saturation_penalty: float = 5.0

    def validate(self) -> None:
        """Raises ValueError naming the bad field."""
        self.station.validate()
        self.torque_control.validate()
        for name in ("trials", "workers", "startup_trials", "seed"):
            value = getattr(self, name)
            low = 1 if name == "trials" else 0
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ValueError(
                    f"TuneConfig.{name}: {value!r} must be an integer >= {low}"
                )
        check_finite(self.connect_timeout, "TuneConfig.connect_timeout", 0.0)
        check_finite(self.k6, "TuneConfig.k6", 0.0)
        for name in (
            "mean_weight",
            "fallback_penalty",
            "saturation_penalty",
            "settle",
            "start",
        ):
            check_finite(getattr(self, name), f"TuneConfig.{name}", 0.0, strict=False)
        check_finite(self.smoothing, "TuneConfig.smoothing", 0.0)
        check_finite(self.end, "TuneConfig.end", 0.0)
        motion_end = float(hrp2.load_trajectory()[0][-1])
        if not self.start + 0.001 <= self.end <= motion_end:
            raise ValueError(
                f"TuneConfig.start, end: {self.start}-{self.end} s must be a part (1 "
                f"ms or more) of the climbing motion, 0-{motion_end:g} s"
            )
        robot = self.station.description()
        if robot.name != "hrp2":
            raise ValueError(
                f"TuneConfig.station.robot: '{robot.name}', but tune searches on "
                "HRP-2's climbing swing (its right leg): for another robot, "
                "`hrp2-drake track`"
            )
        check_for_robot(self.torque_control, robot, "TuneConfig.torque_control")
        joints = self.torque_control.controlled_joints(robot)
        try:
            active_space(self, joints)
        except ValueError as error:
            raise ValueError(
                f"TuneConfig.torque_control.joints: {error}: control them, or leave "
                "the parameter out (exclude)"
            ) from None
        if self.settle < self.torque_control.start_time:
            raise ValueError(
                f"TuneConfig.settle = {self.settle} s must be >= torque_control."
                f"start_time = {self.torque_control.start_time} s (errors are measured "
                "after settle: under torque control only)"
            )
        known = [spec.name for spec in SEARCH_SPACE]
        for name in ("include", "exclude"):
            unknown = [p for p in getattr(self, name) if p not in known]
            if unknown:
                raise ValueError(
                    f"TuneConfig.{name}: {unknown} not in SEARCH_SPACE {known}"
                )
        if self.scheduler and "://" not in self.scheduler and ":" not in self.scheduler:
            raise ValueError(
                f"TuneConfig.scheduler: '{self.scheduler}' is not a Dask scheduler "
                "address (tcp://host:port)"
            )
        if not self.study_name:
            raise ValueError("TuneConfig.study_name: empty")
        if self.motor_model and not Path(self.motor_model).is_file():
            raise ValueError(f"TuneConfig.motor_model: no file '{self.motor_model}'")

    def base(self) -> TorqueControlConfig:
        """The untuned torque control: torque_control with this k6."""
        return replace_fields(self.torque_control, {"controller.k6": self.k6})

    def quick(self) -> None:
        """A smoke run: 0.4 s of the swing's fastest part, 4 trials."""
        self.start, self.end, self.settle = (
            3.0,
            3.4,
            max(0.6, self.torque_control.start_time),
        )
        self.trials = min(self.trials, 4)
        self.startup_trials = min(self.startup_trials, 2)


# --------------------------------------------------------------------------------------
# One trial: a picklable task and a top-level function (spawned processes, Dask
# workers).


@dataclass
class TrialTask:
    """What a worker needs to run one closed-loop simulation."""

    station: StationConfig
    start: float
    end: float
    settle: float
    smoothing: float
    motor_model: MotorModel | None  # None: position control
    torque_control: TorqueControlConfig | None


_REFERENCES: dict = {}


def _reference(task: TrialTask):
    """The climbing reference of a task (built once per worker process)."""
    from hrp2_drake.paper.motion import MotionConfig, motion_reference

    key = (task.start, task.end, task.settle, task.smoothing)
    if key not in _REFERENCES:
        _REFERENCES[key] = motion_reference(
            MotionConfig(
                start=task.start,
                end=task.end,
                settle=task.settle,
                smoothing=task.smoothing,
            )
        )
    return _REFERENCES[key]


@contextlib.contextmanager
def _quiet(name: str):
    """No log lines of the logger `name`: neither Python's last-resort handler nor
    a console session's (`hrp2_drake.console`) prints them."""
    import logging

    logger, handler = logging.getLogger(name), logging.NullHandler()
    propagate = logger.propagate
    logger.addHandler(handler)
    logger.propagate = False
    try:
        yield
    finally:
        logger.propagate = propagate
        logger.removeHandler(handler)


def run_trial(task: TrialTask) -> dict:
    """Simulates one controller on the task's motion and returns its numbers: the
    moving joints' average, maximum and RMS errors (rad, paper Tables 2-3), the
    fallback time, the supervisor's faults, the share of ticks with a saturated Δq;
    or {"error": ...} if the simulation failed (TRIAL_FAILURES). Anything else (a
    TypeError...) is a bug, not a bad trial: it propagates and stops the study."""
    from hrp2_drake.assembly.builders import (
        build_position_control,
        build_torque_control,
        simulated_station,
    )
    from hrp2_drake.assembly.torque_control import delta_q_limit
    from hrp2_drake.paper.motion import evaluate, run_controller

    wall = time.perf_counter()
    reference = _reference(task)
    where = {"host": socket.gethostname(), "pid": os.getpid()}
    try:
        robot, station, period = simulated_station(task.station)
        if task.torque_control is None:
            control = build_position_control(robot, station, reference)
        else:
            # The fused controller: the diagram's signals, at less cost per step.
            control = build_torque_control(
                robot,
                station,
                reference,
                task.motor_model,
                task.torque_control,
                control_period=period,
                fused=True,
            )
        with _quiet("hrp2_drake.control"):  # the result reports the fallbacks
            signals = run_controller(
                control, reference.end_time(), "trial", stream=io.StringIO()
            )
    except TRIAL_FAILURES as error:  # the trial's cost says it
        return where | {
            "error": f"{type(error).__name__}: {one_line(error)}"[:500],
            "wall_time": time.perf_counter() - wall,
        }
    torque = task.torque_control
    delay = 0.0 if torque is None else (torque.estimator.window - 1) / 2 * 0.001 + 0.002
    run = evaluate("trial", None, signals, task.settle, delay)
    out = where | {
        "average_error": run.average_error,
        "max_error": run.max_error,
        "rms_error": run.rms_error,
        "fallback_time": run.fallback_time,
        "supervisor_faults": run.supervisor_faults,
        "wall_time": time.perf_counter() - wall,
    }
    if torque is not None:
        active = signals["t"] >= torque.start_time
        limit = delta_q_limit(task.station.description(), torque)
        saturated = np.abs(signals["delta_q"][active]) >= limit * (1 - 1e-9)
        out["saturation"] = float(saturated.any(axis=1).mean()) if active.any() else 0.0
        out["saturation_per_joint"] = saturated.mean(axis=0).tolist()
        out["torque_estimation_rms"] = run.torque_estimation_rms
    return out


def trial_cost(metrics: dict, position: dict, config: TuneConfig) -> tuple[float, dict]:
    """The cost of a trial's `metrics` (`run_trial`) against position control's, and
    the numbers kept with it (see the module docstring for the formula)."""
    if "error" in metrics:
        return FAILED_COST, {"failed": metrics["error"]}
    ratios = {}
    for key in ("average_error", "max_error"):
        reference = np.maximum(np.asarray(position[key]), 1e-12)
        ratios[key] = np.asarray(metrics[key]) / reference
    every = np.concatenate(list(ratios.values()))
    if not np.all(np.isfinite(every)):
        return FAILED_COST, {"failed": "non-finite tracking errors"}
    faults = metrics.get("supervisor_faults") not in (None, "none")
    fell_back = metrics.get("fallback_time") is not None or faults
    worst = float(every.max())
    cost = (
        worst
        + config.mean_weight * float(every.mean())
        + config.fallback_penalty * fell_back
        + config.saturation_penalty * metrics.get("saturation", 0.0)
    )
    details = {
        "worst_ratio": worst,
        "mean_ratio": float(every.mean()),
        "average_ratio": ratios["average_error"].tolist(),
        "max_ratio": ratios["max_error"].tolist(),
        "fell_back": bool(fell_back),
        "goal_met": bool(worst <= 1.0 and not fell_back),
    }
    return float(cost), details


# --------------------------------------------------------------------------------------
# Executors: one code path.


def _connect(config: TuneConfig):
    """A dask.distributed Client of config.scheduler, or a ValueError naming it."""
    distributed = _require("distributed")
    from distributed.comm import parse_address
    from distributed.comm.addressing import parse_host_port
    from distributed.comm.registry import backends

    where = f"scheduler '{config.scheduler}'"
    scheme, location = parse_address(config.scheduler)
    if scheme not in backends:
        raise ValueError(
            f"{where}: unknown protocol '{scheme}' (Dask's: {sorted(backends)}), "
            "expected tcp://host:port"
        )
    if scheme in ("tcp", "tls"):  # fail fast: Dask retries until its timeout
        try:
            host, port = parse_host_port(location)
            socket.create_connection(
                (host, port), min(config.connect_timeout, 5.0)
            ).close()
        except (OSError, ValueError, TypeError) as error:
            raise ValueError(
                f"{where}: cannot connect ({type(error).__name__}: {one_line(error)})"
            ) from None
    try:
        return distributed.Client(
            config.scheduler, timeout=config.connect_timeout, set_as_default=False
        )
    except Exception as error:  # OSError (timeout, refused), ValueError (address)...
        raise ValueError(
            f"scheduler '{config.scheduler}': cannot connect to a Dask scheduler there "
            f"({type(error).__name__}: {one_line(error)})"
        ) from None


def check_environment(config: TuneConfig) -> None:
    """Raises one clear line if optuna (or, with a scheduler, dask.distributed) is
    missing or the scheduler cannot be reached: before anything long runs."""
    _require("optuna")
    if config.scheduler:
        _connect(config).close()


@contextlib.contextmanager
def open_executor(config: TuneConfig):
    """A concurrent.futures Executor and (its description, trials in flight): a local
    spawn-process pool, or a Dask cluster's `Client.get_executor()`."""
    if not config.scheduler:
        workers = config.workers or 2
        with cf.ProcessPoolExecutor(workers, mp_context=get_context("spawn")) as pool:
            yield pool, f"local process pool ({workers} processes)", workers
        return
    client = _connect(config)
    try:
        threads = sum(client.nthreads().values())
        workers = config.workers or max(1, threads)
        executor = client.get_executor(pure=False)  # each trial runs, even if equal
        yield (
            executor,
            (
                f"Dask cluster at {config.scheduler} ({len(client.nthreads())} "
                f"workers, {threads} threads)"
            ),
            workers,
        )
    finally:
        client.close()


def _objective(config: TuneConfig, motor_model: MotorModel) -> dict:
    """What makes two studies' costs comparable (a resumed study must match it)."""
    from pydrake.common.yaml import yaml_dump_typed

    return {
        "station": yaml_dump_typed(config.station),
        "motion": [config.start, config.end, config.settle, config.smoothing],
        "base": yaml_dump_typed(config.base()),
        "weights": [
            config.mean_weight,
            config.fallback_penalty,
            config.saturation_penalty,
        ],
        "motor_model": {
            "joints": list(motor_model.joint_names),
            "k_tau": motor_model.k_tau.tolist(),
            "k_v": motor_model.k_v.tolist(),
            "k_c": motor_model.k_c.tolist(),
        },
    }


def _task(config: TuneConfig, motor_model, torque_control) -> TrialTask:
    return TrialTask(
        config.station,
        config.start,
        config.end,
        config.settle,
        config.smoothing,
        motor_model,
        torque_control,
    )


def _position_baseline(
    config: TuneConfig, out: Path, executor, objective: dict
) -> dict:
    """Position control's errors on the study's motion (cached in out/)."""
    path = out / BASELINE_FILE
    key = {"station": objective["station"], "motion": objective["motion"]}
    if path.is_file():
        cached = json.loads(path.read_text())
        if cached.get("key") == key:
            return cached
    metrics = executor.submit(run_trial, _task(config, None, None)).result()
    if "error" in metrics:
        raise RuntimeError(f"position control failed to simulate: {metrics['error']}")
    cached = {"key": key} | metrics
    path.write_text(json.dumps(cached, indent=1))
    return cached


# --------------------------------------------------------------------------------------
# The study.


@dataclass
class TuneResult:
    """What `run_tune` did: the study, its best trial and this run's numbers."""

    study: object  # optuna.Study
    best: object  # optuna.trial.FrozenTrial
    tuned: TorqueControlConfig
    position: dict
    executor: str
    trials_run: int
    wall_time: float
    notes: list[str]


def _open_study(config: TuneConfig, out: Path, objective: dict):
    optuna = _require("optuna")
    from optuna.storages import JournalStorage
    from optuna.storages.journal import JournalFileBackend

    storage = JournalStorage(JournalFileBackend(str(out / STUDY_FILE)))
    study = optuna.create_study(
        storage=storage,
        study_name=config.study_name,
        direction="minimize",
        load_if_exists=True,
    )
    saved = study.user_attrs.get("objective")
    if saved is None:
        study.set_user_attr("objective", objective)
    elif saved != objective:
        differ = sorted(k for k in objective if saved.get(k) != objective[k])
        raise ValueError(
            f"{out / STUDY_FILE}: study '{config.study_name}' was run with another "
            f"objective ({', '.join(differ)} differ), its costs are not comparable: "
            "use another --out or study_name"
        )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        study.sampler = optuna.samplers.TPESampler(
            seed=config.seed + len(study.trials),  # a resumed run draws new points
            n_startup_trials=config.startup_trials,
            multivariate=True,
            group=True,  # the conditional disturbance_observer
            constant_liar=True,  # trials in flight count as pending
        )
    return study


def _requeue(study, trial) -> None:
    """Marks a trial (an optuna Trial or FrozenTrial) that did not finish as failed
    and enqueues its parameters (the untuned one stays marked as such)."""
    from optuna.trial import TrialState

    study.tell(trial.number, state=TrialState.FAIL, skip_if_finished=True)
    untuned = {"untuned": True} if trial.user_attrs.get("untuned") else None
    study.enqueue_trial(trial.params, user_attrs=untuned)


def run_tune(
    config: TuneConfig, motor_model: MotorModel, out: Path, log=None
) -> TuneResult:
    """Runs `config.trials` trials of the study in `out` (created, or resumed), then
    writes tuned.yaml, tune.md, history.png and importances.png there.

    Args:
        config: validated where it was loaded (`validate_config`).
        log: called with one line per finished trial (default: stderr).
    """
    optuna = _require("optuna")
    from optuna.trial import TrialState
    from pydrake.common.yaml import yaml_dump_typed

    log = log or console.say
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    robot = config.station.description()
    base = config.base()
    joints = base.controlled_joints(robot)
    motor_model = motor_model.subset(joints)  # KeyError before simulating
    space, notes = active_space(config, joints)
    objective = _objective(config, motor_model)

    verbosity = optuna.logging.get_verbosity()
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    try:
        # The executor first: a scheduler that cannot be reached leaves no study.
        with open_executor(config) as (executor, label, in_flight):
            study = _open_study(config, out, objective)
            # A run that was killed leaves trials RUNNING: run them again.
            for stale in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
                _requeue(study, stale)
                notes.append(f"trial {stale.number} had not finished: enqueued again")
            if not study.trials:
                study.enqueue_trial(
                    base_params(base, space, joints), user_attrs={"untuned": True}
                )
            position = _position_baseline(config, out, executor, objective)
            wall, finished = _ask_tell(
                study,
                config,
                executor,
                in_flight,
                space,
                base,
                joints,
                motor_model,
                position,
                log,
            )
    finally:
        optuna.logging.set_verbosity(verbosity)

    best = study.best_trial
    tuned = load_tuned(best.user_attrs["torque_control"])
    result = TuneResult(study, best, tuned, position, label, finished, wall, notes)
    header = (
        f"# hrp2-drake tune: trial {best.number} of study '{config.study_name}', cost "
        f"{best.value:.4f}, worst error ratio vs position control "
        f"{best.user_attrs.get('worst_ratio', float('nan')):.3f}\n"
    )
    (out / "tuned.yaml").write_text(header + yaml_dump_typed(tuned))
    figures = _plots(study, out)
    (out / "tune.md").write_text(_report(result, config, figures))
    return result


def _ask_tell(
    study, config, executor, in_flight, space, base, joints, motor_model, position, log
) -> tuple[float, int]:
    """Keeps `in_flight` trials running until config.trials have finished; returns
    (wall time, trials finished)."""
    from pydrake.common.yaml import yaml_dump_typed

    pending: dict = {}
    asked = finished = 0
    start = time.perf_counter()
    try:
        while finished < config.trials:
            while len(pending) < in_flight and asked < config.trials:
                trial = study.ask()
                asked += 1
                with warnings.catch_warnings():
                    # The enqueued untuned trial may lie outside the space (the paper's
                    # K_p = 2 > 1): Optuna warns, and evaluates it as given.
                    warnings.filterwarnings("ignore", "Fixed parameter .* out of range")
                    params = suggest(trial, space)
                torque = apply_params(base, params, space, joints)
                trial.set_user_attr("torque_control", yaml_dump_typed(torque))
                future = executor.submit(run_trial, _task(config, motor_model, torque))
                pending[future] = trial
            done, _ = cf.wait(pending, return_when=cf.FIRST_COMPLETED)
            for future in done:
                trial = pending.pop(future)
                try:
                    metrics = future.result()
                except Exception as error:  # the executor's failure, not the trial's
                    _requeue(study, trial)
                    raise RuntimeError(
                        f"trial {trial.number} could not run: {type(error).__name__}: "
                        f"{one_line(error)}"
                    ) from error
                cost, details = trial_cost(metrics, position, config)
                for key, value in (metrics | details).items():
                    trial.set_user_attr(key, value)
                study.tell(trial, cost)
                finished += 1
                best = study.best_trial
                elapsed = time.perf_counter() - start
                log(
                    f"trial {trial.number}: cost {cost:.4f}"
                    + (
                        f" (failed: {metrics['error'][:80]})"
                        if "error" in metrics
                        else ""
                    )
                    + f"; best {best.value:.4f} (trial {best.number}); "
                    f"{finished}/{config.trials} in {elapsed:.1f} s"
                )
    finally:  # interrupted: what was in flight runs again next time
        for future, trial in pending.items():
            future.cancel()
            _requeue(study, trial)
    return time.perf_counter() - start, finished


def load_tuned(text: str) -> TorqueControlConfig:
    """A TorqueControlConfig from YAML text (tuned.yaml's), validated."""
    from hrp2_drake.config import load_config

    return load_config(TorqueControlConfig, data=text)


def _plots(study, out: Path) -> dict[str, str]:
    """history.png and importances.png; a note instead of a figure it cannot draw."""
    import optuna
    from optuna.trial import TrialState
    from optuna.visualization import matplotlib as plots

    plt = pyplot()
    figures = {}
    completed = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        warnings.simplefilter("ignore", UserWarning)  # "few trials per regime"
        ax = plots.plot_optimization_history(study)
        ax.figure.set_size_inches(8, 4.5)
        save_figure(ax.figure, out / "history.png", dpi=100, tight=True)
        figures["history"] = "history.png"
        if len(completed) < 2:
            figures["importances"] = (
                f"not drawn: {len(completed)} completed trial(s), importances need 2 "
                "or more"
            )
        else:
            try:
                # PED-ANOVA: Optuna's own (fANOVA needs scikit-learn).
                evaluator = optuna.importance.PedAnovaImportanceEvaluator()
                ax = plots.plot_param_importances(study, evaluator=evaluator)
                ax.figure.set_size_inches(8, 6)
                save_figure(ax.figure, out / "importances.png", dpi=100, tight=True)
                figures["importances"] = "importances.png"
            except Exception as error:  # too few distinct trials, one parameter...
                plt.close("all")
                figures["importances"] = (
                    f"not drawn: {type(error).__name__}: {one_line(error)}"
                )
    if figures["importances"] != "importances.png":  # not a previous run's
        (out / "importances.png").unlink(missing_ok=True)
    return figures


def _report(result: TuneResult, config: TuneConfig, figures: dict[str, str]) -> str:
    from optuna.trial import TrialState

    study, best = result.study, result.best
    completed = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    untuned = next((t for t in completed if t.user_attrs.get("untuned")), None)
    labels = [
        hrp2.RIGHT_LEG_LABELS[hrp2.RIGHT_LEG.index(j)] for j in hrp2.RIGHT_LEG[1:]
    ]
    rate = result.trials_run / max(result.wall_time, 1e-9) * 60
    lines = [
        "# Tuning the torque controller (`hrp2-drake tune`)",
        "",
        f"K6 = {result.tuned.controller.k6:g}; the climbing swing "
        f"{config.start:g}-{config.end:g} s after {config.settle:g} s holding its "
        "first pose, HRP-2 hanging. Cost: the worst ratio of torque control's error to "
        "position control's over the 5 moving joints and over average/maximum error "
        f"(paper Tables 2-3), + {config.mean_weight:g} x the mean ratio, + "
        f"{config.fallback_penalty:g} if it fell back, + "
        f"{config.saturation_penalty:g} x the share of saturated ticks.",
        "",
        f"- study: `{STUDY_FILE}` ('{config.study_name}'), {len(study.trials)} trials "
        f"({len(completed)} completed), {result.trials_run} in this run",
        f"- executor: {result.executor}",
        f"- wall time of this run: {result.wall_time:.1f} s, {rate:.2f} trials/min",
        f"- best: trial {best.number}, cost {best.value:.4f}; goal (at least as "
        f"accurate as position control everywhere) "
        f"{'met' if best.user_attrs.get('goal_met') else 'NOT met'}",
    ]
    if untuned is not None:
        lines.append(
            f"- untuned (trial {untuned.number}): cost {untuned.value:.4f}, worst "
            f"ratio {untuned.user_attrs.get('worst_ratio', float('nan')):.3f}"
        )
    lines += [f"- note: {note}" for note in result.notes]
    lines += ["", "## Best trial against position control", ""]
    lines += _best_trial_lines(best.user_attrs, result.position, labels)
    lines += ["", "## Best parameters", ""]
    rows = [
        [
            name,
            _fmt(untuned.params.get(name, "-") if untuned else "-"),
            _fmt(best.params.get(name, "-")),
        ]
        for name in sorted(set(best.params) | set(untuned.params if untuned else ()))
    ]
    lines += markdown_table(["parameter", "untuned", "best"], rows)
    lines += [
        "",
        "Written to `tuned.yaml` (a TorqueControlConfig: the `torque_control` of "
        "an experiment's config).",
        "",
        "## Figures",
        "",
    ]
    for name, value in figures.items():
        lines.append(
            f"![{name}]({value})" if value.endswith(".png") else f"- {name}: {value}"
        )
    return "\n".join(lines) + "\n"


def _best_trial_lines(attrs: dict, position: dict, labels: list[str]) -> list[str]:
    """The best trial's errors beside position control's per moving joint (rad·10³,
    and their ratios); a trial without them (it failed): the table's header alone."""
    rows = (
        [
            [
                label,
                f"{attrs['average_error'][j] * 1e3:.4f} "
                f"({position['average_error'][j] * 1e3:.4f})",
                f"{attrs['average_ratio'][j]:.3f}",
                f"{attrs['max_error'][j] * 1e3:.2f} "
                f"({position['max_error'][j] * 1e3:.2f})",
                f"{attrs['max_ratio'][j]:.3f}",
            ]
            for j, label in enumerate(labels)
        ]
        if "average_ratio" in attrs
        else []
    )
    header = ["joint", "average (x10³ rad)", "ratio", "maximum (mrad)", "ratio"]
    lines = markdown_table(header, rows)
    if "average_ratio" in attrs:
        lines += [
            "",
            "Cells: torque control (position control).",
            f"Saturated ticks: {attrs.get('saturation', 0.0) * 100:.2f}%; fell back: "
            f"{'yes' if attrs.get('fell_back') else 'no'}.",
        ]
    return lines


def _fmt(value) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)
