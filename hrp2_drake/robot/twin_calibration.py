"""A robot's digital twin from its logs: the emulated servo calibrated by rollout
(`hrp2-drake calibrate --robot R --log ...`, `tools/twin.py`, runs it and reports).

The emulated servo (`hrp2_drake.robot.servo`) stands for the real robot, so its
parameters come from what the real robot did: each evaluation replays every log open
loop (`robot.rollout.rollout`: the logged command in, the robot's MultibodyPlant driven
by the emulated servo at the log's gain) and compares the simulated position with the
measured one. A real optimizer, scipy's `least_squares` (trust-region reflective,
within physical bounds), moves the servo's parameters to minimize the position error
of all the logs together (each log weighs the same).

The parameters it fits, per joint (`TWIN_PARAMETERS`), one per mechanism:

- stiffness `k4` (current per rad at the servo file's gain; the gain scales it),
- voltage limit `stall_current` and back-EMF `no_load_speed`, with k5 tied to them
  (k5 = stall_current / no_load_speed: a voltage-driven DC servo's current is
  (V·duty − k_e q̇) / R, so its back-EMF damping and its torque-speed line are one
  mechanism),
- viscous `k2`, Coulomb `k3` and load-dependent `load_friction` (gear efficiency)
  friction,
- dead zone `i_deadzone`,
- direction-dependent efficiency `k1_asymmetry` (load-dependent gear friction) and
  hysteresis `hysteresis_width`,
- `latency` of the command.

`k1` stays the prior's (only k1 · current is observable), and so do the encoder's
resolution and the gain the file states. The prior is the robot's servo file.

Cross-validation: `cross_validate` fits on the logs of each gain and reports the
rollout MAE on the logs of the others, for the twin and for the least-squares motor
model identified on the same logs (`identify --fit least-squares`).
"""

import copy
import math
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from multiprocessing import get_context

import numpy as np
import scipy.optimize

from hrp2_drake import console
from hrp2_drake.description import RobotDescription, load_robot_description
from hrp2_drake.identification.joint_fits import FitConfig, identify_logs
from hrp2_drake.identification.logs import RobotLog
from hrp2_drake.robot.rollout import model_servo, rollout, rollout_errors, twin_servo
from hrp2_drake.robot.servo import ServoParams

#: The fitted parameters: name -> (lower, upper, scale): "log" parameters move by
#: factors of the prior within [prior / bound, prior * bound]; "linear" ones within
#: [lower, upper].
TWIN_PARAMETERS = {
    "k4": ("log", 10.0),
    "stall_current": ("log", 10.0),
    "no_load_speed": ("log", 10.0),
    "k2": ("linear", (0.0, 0.05)),
    "k3": ("linear", (0.0, 0.1)),
    "i_deadzone": ("linear", (0.0, 0.2)),
    "load_friction": ("linear", (0.0, 0.6)),
    "k1_asymmetry": ("linear", (0.0, 0.8)),
    "hysteresis_width": ("linear", (0.0, 0.05)),
    "latency": ("linear", (0.0, 0.02)),
}
#: What `calibrate --log` fits by default: stiffness, back-EMF and voltage limit,
#: friction (viscous, Coulomb, load-dependent), dead zone, hysteresis, latency.
DEFAULT_PARAMETERS = (
    "k4",
    "stall_current",
    "no_load_speed",
    "k2",
    "k3",
    "load_friction",
    "i_deadzone",
    "hysteresis_width",
    "latency",
)
#: The residuals' sampling: one error every `RESIDUAL_PERIOD` seconds of each log.
RESIDUAL_PERIOD = 0.01
#: Fewest position residuals per fitted parameter: fewer, and the least-squares
#: problem is (nearly) underdetermined: any twin fits a few samples.
MIN_RESIDUALS_PER_PARAMETER = 10


@dataclass
class TwinConfig:
    """Configuration of a calibration from logs.

    Args:
        parameters: the servo parameters to fit (`TWIN_PARAMETERS`).
        max_evaluations: rollouts of all the logs at most, finite differences
            included; the best parameters met are kept.
        workers: processes for the rollouts (1: in this process).
        diff_step: finite-difference step, as a share of each parameter's range
            (linear) or of its log-range (log): large enough to step over the
            encoder's quantization and the latency's whole periods.
    """

    parameters: list[str] = field(default_factory=lambda: list(DEFAULT_PARAMETERS))
    max_evaluations: int = 150
    workers: int = 2
    diff_step: float = 0.05

    def validate(self) -> None:
        unknown = [p for p in self.parameters if p not in TWIN_PARAMETERS]
        if unknown or not self.parameters:
            raise ValueError(
                f"TwinConfig.parameters: unknown {unknown}, expected some of "
                f"{list(TWIN_PARAMETERS)}"
            )
        if self.max_evaluations < 1 or self.workers < 1:
            raise ValueError("TwinConfig: max_evaluations and workers must be >= 1")
        if not 0 < self.diff_step < 1:
            raise ValueError(f"TwinConfig.diff_step: in (0, 1), got {self.diff_step}")


@dataclass
class TwinFit:
    """A calibrated twin and how it got there."""

    params: ServoParams
    logs: list[str]
    evaluations: int
    wall_time: float
    cost_start: float
    cost_end: float
    message: str


class _BudgetSpent(Exception):
    """The optimizer asked for more rollouts than `TwinConfig.max_evaluations`."""


class _Space:
    """The map between the fitted parameters of every joint and the unit-scaled
    vector the optimizer moves."""

    def __init__(self, prior: ServoParams, joints: Sequence[str], names: Sequence[str]):
        self.prior = prior
        self.entries = [(j, n) for j in joints for n in names]

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lower = [
            -1.0 if TWIN_PARAMETERS[n][0] == "log" else 0.0 for _, n in self.entries
        ]
        return np.array(lower), np.ones(len(self.entries))

    def start(self) -> np.ndarray:
        x = []
        for joint, name in self.entries:
            kind, bound = TWIN_PARAMETERS[name]
            value = getattr(self.prior.joints[joint], name)
            if kind == "log":
                x.append(0.0)  # the prior itself
            else:
                lo, hi = bound
                x.append(min(max((value - lo) / (hi - lo), 0.0), 1.0))
        return np.array(x)

    def params(self, x: np.ndarray) -> ServoParams:
        params = copy.deepcopy(self.prior)
        for (joint, name), value in zip(self.entries, x):
            kind, bound = TWIN_PARAMETERS[name]
            if kind == "log":
                prior = getattr(self.prior.joints[joint], name)
                setattr(params.joints[joint], name, prior * bound ** float(value))
            else:
                lo, hi = bound
                setattr(params.joints[joint], name, lo + (hi - lo) * float(value))
        for joint in params.joints.values():
            # One mechanism: k5 = i_s / ω0 (module docstring).
            joint.k5 = joint.stall_current / joint.no_load_speed
        return params


# ---------------------------------------------------------------- rollouts
_WORKER: dict = {}


def _init_worker(program: str, robot_file: str, logs: Sequence[RobotLog]) -> None:
    console.start_worker(program, "rollouts")
    _WORKER["robot"] = load_robot_description(robot_file)
    _WORKER["logs"] = list(logs)


def _rollout_error(args: tuple) -> np.ndarray:
    """`_position_error` of log k, in a worker."""
    params, k = args
    return _position_error(_WORKER["robot"], _WORKER["logs"][k], params)


def _residual_count(log: RobotLog) -> int:
    """How many position residuals `_position_error` gives of `log`."""
    every = max(1, int(round(RESIDUAL_PERIOD / log.period)))
    return len(log.t[::every]) * len(log.joint_names)


def check_enough_data(logs: Sequence[RobotLog], config: "TwinConfig") -> None:
    """Raises ValueError unless the logs give `MIN_RESIDUALS_PER_PARAMETER` position
    residuals per fitted parameter (a twin of a 57 ms log fits anything)."""
    joints = len(logs[0].joint_names) if logs else 0
    parameters = len(config.parameters) * joints
    residuals = sum(_residual_count(log) for log in logs)
    needed = MIN_RESIDUALS_PER_PARAMETER * parameters
    if residuals < needed:
        seconds = sum(float(log.t[-1]) for log in logs)
        raise ValueError(
            f"calibrate --log: {seconds:.3g} s of logs give {residuals} position "
            f"residuals (one every {RESIDUAL_PERIOD * 1e3:g} ms per joint) for "
            f"{parameters} parameters; a twin needs at least "
            f"{MIN_RESIDUALS_PER_PARAMETER} per parameter ({needed}, about "
            f"{needed / joints * RESIDUAL_PERIOD:.2g} s of logs)"
        )


def _position_error(
    robot: RobotDescription, log: RobotLog, params: ServoParams
) -> np.ndarray:
    """q_sim − q_measured of one rollout (rad), one row every RESIDUAL_PERIOD."""
    q_sim = rollout(robot, log, twin_servo(params, log)).q_sim
    every = max(1, int(round(RESIDUAL_PERIOD / log.period)))
    return (q_sim - log.q_measured)[::every]


class Rollouts:
    """Rollouts of the emulated servo on a set of logs, in worker processes that
    hold the robot and the logs for their life (one log per task)."""

    def __init__(self, robot: RobotDescription, logs: Sequence[RobotLog], workers: int):
        self.robot = robot
        self.logs = list(logs)
        self._pool = None
        if workers > 1 and len(self.logs) > 1:
            self._pool = ProcessPoolExecutor(
                max_workers=min(workers, len(self.logs)),
                mp_context=get_context("spawn"),
                initializer=_init_worker,
                initargs=(console.program(), robot.source_file, self.logs),
            )

    def errors(self, params: ServoParams) -> list[np.ndarray]:
        if self._pool is None:
            return [_position_error(self.robot, log, params) for log in self.logs]
        tasks = [(params, k) for k in range(len(self.logs))]
        return list(self._pool.map(_rollout_error, tasks))

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()


def fit_twin(
    robot: RobotDescription,
    logs: Sequence[RobotLog],
    prior: ServoParams,
    config: TwinConfig | None = None,
    label: str = "twin",
) -> TwinFit:
    """Fits the emulated servo's parameters to `logs` by rollout (module docstring).

    Raises:
        ValueError: too little data for the parameters (`check_enough_data`).
    """
    config = config or TwinConfig()
    check_enough_data(logs, config)
    space = _Space(prior, robot.joints, config.parameters)
    rollouts = Rollouts(robot, logs, config.workers)
    evaluations = [0]
    best = {"cost": math.inf, "x": space.start()}
    start = time.perf_counter()

    def residuals(x: np.ndarray) -> np.ndarray:
        if evaluations[0] >= config.max_evaluations:
            raise _BudgetSpent
        errors = rollouts.errors(space.params(x))
        r = np.concatenate([e.ravel() / math.sqrt(e.size) for e in errors])
        evaluations[0] += 1
        cost = float(r @ r)
        if cost < best["cost"]:
            best.update(cost=cost, x=x.copy())
        if evaluations[0] % 10 == 1:
            console.say(
                f"{label}: rollout {evaluations[0]} of at most "
                f"{config.max_evaluations}, "
                f"best RMS error {math.sqrt(best['cost'] / len(logs)) * 1e3:.1f} mrad"
            )
        return r

    try:
        r0 = residuals(space.start())
        result = scipy.optimize.least_squares(
            residuals,
            space.start(),
            bounds=space.bounds(),
            method="trf",
            diff_step=config.diff_step,
            x_scale=1.0,
        )
        message = result.message
    except _BudgetSpent:
        message = (
            f"stopped after {config.max_evaluations} rollouts of every log (the budget)"
        )
    finally:
        rollouts.close()
    params = space.params(best["x"])
    return TwinFit(
        params=params,
        logs=[log.name for log in logs],
        evaluations=evaluations[0],
        wall_time=time.perf_counter() - start,
        cost_start=float(r0 @ r0),
        cost_end=best["cost"],
        message=str(message),
    )


def rollout_table(
    robot: RobotDescription, logs: Sequence[RobotLog], servo_of_log
) -> dict[str, dict[str, float]]:
    """Rollout MAE, maximum error and MAE with the servo on (rad, mean over joints)
    per log; `servo_of_log(log)`: the servo factory replaying it."""
    out = {}
    for log in logs:
        e = rollout_errors(log, rollout(robot, log, servo_of_log(log)).q_sim)
        out[log.name] = {
            "mae": float(np.mean(e.mae)),
            "max": float(np.mean(e.max_error)),
            "mae_servo_on": float(np.mean(e.mae_servo_on)),
        }
    return out


def twin_errors(
    robot: RobotDescription, logs: Sequence[RobotLog], params: ServoParams
) -> dict[str, dict[str, float]]:
    """`rollout_table` of the twin with `params`."""
    return rollout_table(robot, logs, lambda log: twin_servo(params, log))


def model_errors(
    robot: RobotDescription, logs: Sequence[RobotLog], model
) -> dict[str, dict[str, float]]:
    """`rollout_table` of a servo that obeys an identified motor model instead
    (`rollout.model_servo`, at each log's gain)."""
    return rollout_table(robot, logs, lambda log: model_servo(robot, model, log.gain))


def least_squares_model(robot: RobotDescription, logs: Sequence[RobotLog]):
    """The least-squares motor model (`identify --fit least-squares`) of `logs`."""
    return identify_logs(robot, FitConfig(fit="least_squares"), logs).identified


@dataclass
class CrossValidation:
    """Fit on the logs of one gain, rollout MAE on the others (rad, per log)."""

    train_gain: float
    twin: TwinFit
    twin_errors: dict[str, dict[str, float]]
    model_errors: dict[str, dict[str, float]]


def cross_validate(
    robot: RobotDescription,
    logs: Sequence[RobotLog],
    prior: ServoParams,
    config: TwinConfig,
) -> list[CrossValidation]:
    """For each gain of the logs: the twin and the least-squares motor model fitted
    on that gain's logs, rolled out on the logs of the other gains."""
    gains = sorted({log.gain for log in logs if log.gain is not None})
    results = []
    for gain in gains:
        train = [log for log in logs if log.gain == gain]
        test = [log for log in logs if log.gain != gain]
        twin = fit_twin(robot, train, prior, config, label=f"twin on gain {gain:g}")
        model = least_squares_model(robot, train)
        results.append(
            CrossValidation(
                gain,
                twin,
                twin_errors(robot, test, twin.params),
                model_errors(robot, test, model),
            )
        )
    return results
