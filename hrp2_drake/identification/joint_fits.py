"""Motor identification from logs (paper Sec. 3, 5.2): every fit of the paper per
joint, on the training blocks of the logs, validated on their held-out blocks.

`identify_logs` runs it on a robot's logs (`logs.RobotLog`, from
`logs.read_robot_log` or a collection's `RobotLog.from_arrays`): non-causal estimates
of q̇ (`v`), q̈ and τ̂ (`dataset.estimate_logs`), then per joint the least-squares
(eq. 7), asymmetric (eq. 8), Coulomb and two-stage (Sec. 3.3.1) fits, the
piecewise-linear model of Sec. 3.2 (for comparison), a sweep of the asymmetric
weight w and, for logs of several servo gains, each gain's own fits.
`assembly/identification.py` and `tools/identify.py` call it, and `report.py` writes
its report; `robot/twin_calibration.py` compares a twin with it.

Δq = q_cmd − q is `delta_q` throughout, q̇ is `v`.
"""

import dataclasses
import logging
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from hrp2_drake.config import check_finite
from hrp2_drake.description import RobotDescription
from hrp2_drake.estimation.estimator_config import estimator_config
from hrp2_drake.estimation.torque_estimator import FloatingBaseTorqueEstimator
from hrp2_drake.identification.dataset import (
    IdentificationData,
    check_logs,
    estimate_logs,
    split_blocks,
)
from hrp2_drake.identification.excitation import PHASE_HIGH_TORQUE, PHASE_TRANSITION
from hrp2_drake.identification.fitting import (
    check_identified,
    fit_asymmetric,
    fit_least_squares,
    fit_piecewise_linear,
    fit_two_stage,
    overestimation_share,
)
from hrp2_drake.identification.logs import RobotLog
from hrp2_drake.identification.motor_model import MotorModel

_logger = logging.getLogger(__name__)

#: The fits `FitConfig.fit` may pick for motor_model.yaml, and what each is for.
FITS = ("asymmetric", "least_squares", "coulomb", "two_stage")
FIT_PURPOSE = {
    "asymmetric": "conservative (rarely over-estimates |Δq|): for the torque "
    "controller's feedforward, as the paper uses it",
    "least_squares": "the smallest prediction error: for prediction, rollouts and "
    "simulation",
    "coulomb": "least squares with a Coulomb term Kc sign(q̇): prediction where dry "
    "friction shows",
    "two_stage": "Kτ from near-zero-velocity samples, then Kv (Sec. 3.3.1)",
}
#: Longest filter window or stride (s): a longer one is a sample count in an old config.
MAX_WINDOW = 2.0
#: Initial breakpoints (N·m) of the piecewise-linear fit: the paper's, then wider ones
#: (Sec. 3.2.3: "it requires the user to provide an initial guess").
PIECEWISE_INITIAL_BREAKPOINTS = ((-0.5, 0.5), (-2.0, 2.0), (-5.0, 5.0))


@dataclass
class FitConfig:
    """How the motor model is fitted to logs (the fitting keys of
    `hrp2-drake identify`'s config, `assembly.identification.IdentifyConfig`).

    Args:
        joints: the joints to identify; empty: the robot's controlled joints.
        window: Savitzky-Golay window of the non-causal estimates (s): the odd
            number of samples nearest to it at the log's rate (81 at 1 kHz).
        stride: keep one sample per `stride` seconds of the log.
        fit: the fit `motor_model.yaml` holds (`FITS`): "asymmetric" (eq. 8: rarely
            over-estimates |Δq|, conservative, what the paper's controller uses),
            "least_squares" (eq. 7: the smallest error, for prediction and
            simulation), "coulomb" (least squares with the Coulomb term), "two_stage"
            (Sec. 3.3.1).
        saturation_margin: a sample is left out of the fits where the servo's
            documented output (robot description's `position_loop`) exceeds this
            share of its limit anywhere in its filter window: in saturation Δq no
            longer sets the torque, and the driver's effective voltage already
            drops near full output.
        w: weight of over-estimation in the asymmetric penalty. The paper used 100;
            on our emulated servo (direction-dependent gain, dead zone) 100 leaves
            up to ~10% of held-out samples over-estimated by a hair (tenths of a
            mrad), 1000 keeps it under 5% at the same accuracy: the report's w sweep
            shows both.
        w_sweep: the weights of the sweep table (asymmetric fit only).
        zero_velocity_threshold: |q̇| below which a sample is static (rad/s),
            two-stage fit and Figure 1.
        held_out_block: length of the validation blocks (s).
        held_out_every: one block in `held_out_every` is held out for validation.
    """

    joints: list[str] = field(default_factory=list)
    window: float = 0.081
    stride: float = 0.005
    fit: str = "asymmetric"
    saturation_margin: float = 0.9
    w: float = 1000.0
    w_sweep: list[float] = field(
        default_factory=lambda: [1.0, 10.0, 100.0, 1000.0, 10000.0]
    )
    zero_velocity_threshold: float = 0.05
    held_out_block: float = 1.0
    held_out_every: int = 3

    def validate(self) -> None:
        """Raises ValueError naming the bad field (yaml_load_typed does not call it);
        the joints are checked against a robot by `check_joints`."""
        if len(set(self.joints)) != len(self.joints):
            raise ValueError(
                f"{self._name()}.joints: duplicated joints in {self.joints}"
            )
        for name, longest in (("window", MAX_WINDOW), ("stride", MAX_WINDOW)):
            value = getattr(self, name)
            check_finite(value, f"{self._name()}.{name}", 0.0)
            if value > longest:
                raise ValueError(
                    f"{self._name()}.{name}: {value:g} s, longer than {longest:g} s: "
                    f"{name}s are in seconds (81 samples at 1 kHz: 0.081)"
                )
        if self.fit not in FITS:
            raise ValueError(
                f"{self._name()}.fit: '{self.fit}', expected one of {FITS}"
            )
        check_finite(self.saturation_margin, f"{self._name()}.saturation_margin", 0.0)
        if self.held_out_every < 2:
            raise ValueError(
                f"{self._name()}.held_out_every must be >= 2, got {self.held_out_every}"
            )
        for name in ("zero_velocity_threshold", "held_out_block"):
            check_finite(getattr(self, name), f"{self._name()}.{name}", 0.0)
        check_finite(self.w, f"{self._name()}.w", 1.0, strict=False)
        if not self.w_sweep:
            raise ValueError(
                f"{self._name()}.w_sweep: empty, expected some weights >= 1"
            )
        for k, w in enumerate(self.w_sweep):
            check_finite(w, f"{self._name()}.w_sweep[{k}]", 1.0, strict=False)

    def _name(self) -> str:
        """The config's class name in messages (a subclass: its own)."""
        return type(self).__name__

    def identified_joints(self, robot: RobotDescription) -> list[str]:
        """`joints`, or the robot's controlled joints if empty."""
        return list(self.joints or robot.controlled_joints)

    def check_joints(self, robot: RobotDescription) -> None:
        """Raises ValueError unless every joint to identify is one of the robot's."""
        joints = self.identified_joints(robot)
        if not joints:
            raise ValueError(f"{self._name()}.joints: no joint to identify")
        unknown = [j for j in joints if j not in robot.joints]
        if unknown:
            raise ValueError(f"{self._name()}.joints: unknown joints {unknown}")


@dataclass
class JointResult:
    """Identification of one joint: every fit, validated on held-out samples."""

    joint: str
    models: dict[str, MotorModel]
    piecewise: object | None
    validation: dict[str, dict[str, float]]  # method -> {"rms", "overestimation"}
    samples: dict[str, int]
    w_sweep: dict[float, dict[str, float]]  # w -> k_tau, k_v, rms, overestimation
    #: per gain (logs of several gains): method -> {"k_tau", "k_v", "k_c"} times gain
    per_gain: dict[float, dict[str, dict[str, float]]] = field(default_factory=dict)
    piecewise_note: str = ""  # how the piecewise-linear fit went (report)


@dataclass
class IdentificationResult:
    joints: list[JointResult]
    data: IdentificationData
    held_out: np.ndarray
    train: np.ndarray
    config: FitConfig
    robot: RobotDescription
    identified: MotorModel  # the fit of config.fit: what motor_model.yaml holds
    #: τ̂ vs truth (N·m), if the log has truth
    estimation_rms: np.ndarray | None = None
    estimation_peak: np.ndarray | None = None
    #: the servo gain the models hold at (logs that state one), else 0
    gain: float = 0.0
    #: samples left out: servo off or filter edges, output saturated
    excluded: dict[str, int] = field(default_factory=dict)
    logs: list[dict] = field(default_factory=list)  # one row per log (real logs)


def identify_logs(
    robot: RobotDescription, config: FitConfig, logs: Sequence[RobotLog]
) -> IdentificationResult:
    """Non-causal estimation of each log, then every fit per joint on the pooled
    training samples, validated on held-out blocks of every log. `config` is
    validated by its loader (`FitConfig.validate`: once per command).

    Logs that state the servo's gain pool into one gain-aware model: each sample's Δq
    is brought to the reference gain (the smallest of the logs) by Δq · gain /
    reference (a P-controlled servo's output is gain · Δq), and the models hold at
    that gain (`MotorModel.gain`). Samples where the servo is off, or its output near
    its documented limit, are left out.

    Raises:
        ValueError: one line naming the log or the joint (`check_logs`, the
            estimation, a joint that its data do not identify).
    """
    config.check_joints(robot)
    check_logs(logs, config.window, f"{type(config).__name__}.window")
    _logger.info("estimating and fitting ...")
    gains = [log.gain for log in logs]
    reference = min(gains) if gains[0] is not None else 0.0
    estimator = FloatingBaseTorqueEstimator(robot.make_plant(), estimator_config(robot))
    data = estimate_logs(
        logs,
        estimator,
        config.window,
        config.stride,
        robot.position_loop.saturation_error,
        config.saturation_margin,
    )
    if reference:
        data.delta_q = data.delta_q * (data.gain / reference)[:, None]
    held = np.zeros(len(data.t), bool)
    for k in range(len(logs)):
        rows = data.segment == k
        held[rows] = split_blocks(
            data.t[rows], config.held_out_block, config.held_out_every
        )
    usable = data.usable & (data.phase != PHASE_TRANSITION)
    columns = {name: i for i, name in enumerate(estimator.config().joints)}
    results = [
        _identify_joint(
            config,
            data,
            usable & ~data.saturated[:, columns[name]],
            held,
            columns[name],
            name,
            reference,
        )
        for name in config.identified_joints(robot)
    ]
    chosen = MotorModel.from_joints({r.joint: r.models[config.fit] for r in results})
    rms = peak = None
    if data.tau_true is not None:
        err = data.tau[data.usable] - data.tau_true[data.usable]
        rms = np.sqrt(np.mean(err**2, axis=0))
        peak = np.abs(data.tau_true[data.usable]).max(axis=0)
    excluded = {
        "servo off or filter edges": int(np.count_nonzero(~data.usable)),
        "output saturated": int(
            np.count_nonzero(data.usable & data.saturated.any(axis=1))
        ),
    }
    train = usable & ~held & ~data.saturated.any(axis=1)  # of every joint
    return IdentificationResult(
        results,
        data,
        held,
        train,
        config,
        robot,
        chosen,
        rms,
        peak,
        reference,
        excluded,
    )


def _identify_joint(
    config: FitConfig,
    data: IdentificationData,
    usable: np.ndarray,
    held: np.ndarray,
    j: int,
    name: str,
    gain: float,
) -> JointResult:
    """Every fit of one joint on its training samples, validated on held-out ones."""
    train, test = usable & ~held, usable & held
    if not np.any(train):
        raise ValueError(
            f"joint {name!r}: no sample to identify from: every sample has the servo "
            "off, its output saturated, or lies within a filter window of a log's edge"
        )
    tau, v, delta_q = data.joint(j, train)
    models = _fits(config, tau, v, delta_q, name, gain)
    # Refuse data that identify no motor (noise, too little excitation): the
    # two models the controller and a prediction read must be positive and explain
    # the data.
    check_identified(models["least_squares"], tau, v, delta_q)
    check_identified(models["asymmetric"], tau, v, delta_q, min_explained=None)
    # The piecewise-linear model of Sec. 3.2 has no velocity term: the paper fitted
    # it to the static high-torque data (Fig. 1), and so do we (an unlabelled log:
    # its near-zero-velocity samples).
    labelled = bool(np.any(data.phase >= 0))
    static = np.abs(data.v[:, j]) < config.zero_velocity_threshold
    pushes = train & (data.phase == PHASE_HIGH_TORQUE if labelled else static)
    piecewise, piecewise_note = _fit_piecewise(data.joint(j, pushes), name)
    tau_h, v_h, delta_q_h = data.joint(j, test)
    validation = {}
    static_h = test & (data.phase == PHASE_HIGH_TORQUE if labelled else static)
    for method, fitted in list(models.items()) + [("piecewise_linear", piecewise)]:
        samples = (
            data.joint(j, static_h)
            if method == "piecewise_linear"
            else (tau_h, v_h, delta_q_h)
        )
        if fitted is None or samples[0].size == 0:
            continue
        residual = fitted.predict(*samples[:2]) - samples[2]
        validation[method] = {
            "rms": float(np.sqrt(np.mean(residual**2))),
            "overestimation": overestimation_share(fitted, *samples),
        }
    sweep = {}
    for w in config.w_sweep:
        fitted = fit_asymmetric(tau, v, delta_q, w, joint_name=name)
        sweep[w] = {
            "k_tau": float(fitted.k_tau[0]),
            "k_v": float(fitted.k_v[0]),
            "rms": _rms(fitted, tau_h, v_h, delta_q_h),
            "overestimation": overestimation_share(fitted, tau_h, v_h, delta_q_h),
        }
    per_gain = {}
    log_gains = np.unique(data.gain[train]) if gain else []
    for g in log_gains if len(log_gains) > 1 else []:
        rows = train & (data.gain == g)
        tau_g, v_g, delta_q_g = data.joint(j, rows)
        fitted = _fits(config, tau_g, v_g, delta_q_g * gain / g, name, g)
        per_gain[float(g)] = {
            m: {p: float(getattr(f, p)[0] * g) for p in ("k_tau", "k_v", "k_c")}
            for m, f in fitted.items()
        }
    samples = {"train": int(train.sum()), "held_out": int(test.sum())}
    return JointResult(
        name, models, piecewise, validation, samples, sweep, per_gain, piecewise_note
    )


def _fits(config, tau, v, delta_q, name: str, gain: float) -> dict[str, MotorModel]:
    """Every linear fit of `FITS`, each model holding at `gain` and naming its fit."""
    models = {
        "least_squares": fit_least_squares(tau, v, delta_q, joint_name=name),
        "asymmetric": fit_asymmetric(tau, v, delta_q, config.w, joint_name=name),
        "coulomb": fit_least_squares(tau, v, delta_q, coulomb=True, joint_name=name),
        "two_stage": fit_two_stage(
            tau, v, delta_q, config.zero_velocity_threshold, config.w, joint_name=name
        ),
    }
    return {
        method: dataclasses.replace(model, gain=float(gain), fit=method)
        for method, model in models.items()
    }


def _rms(model: MotorModel, tau, v, delta_q) -> float:
    if not tau.size:
        return math.nan
    return float(np.sqrt(np.mean((model.predict(tau, v) - delta_q) ** 2)))


def _fit_piecewise(samples, name: str):
    """The piecewise-linear fit from the first initial guess that works, and a note
    for the report (why there is none, or which guesses failed first).

    The piecewise-linear model is the one the paper tried and abandoned (Sec. 3.2),
    fitted for comparison only; its algorithm needs a good initial guess (the
    paper's words): the paper's breakpoints in N·m, then ones at 10% and 30% of the
    joint's peak static torque (a small servo). A guess that fails is expected, not an
    error: the report says so, the console only in debug."""
    tau = samples[0]
    peak = float(np.percentile(np.abs(tau), 95)) if tau.size else 0.0
    guesses = PIECEWISE_INITIAL_BREAKPOINTS + tuple(
        (-f * peak, f * peak)
        for f in (0.1, 0.3)
        if f * peak < PIECEWISE_INITIAL_BREAKPOINTS[0][1]
    )
    failed = []
    for guess in guesses:
        try:
            fitted = fit_piecewise_linear(
                *samples, initial_breakpoints=guess, joint_name=name
            )
        except ValueError as error:
            failed.append((guess, _reason(error)))
            continue
        note = f"from {_breakpoints(guess)} N·m"
        note += f"; {_failures(failed)}" if failed else ""
        _logger.debug("%s: piecewise-linear model (for comparison only) %s", name, note)
        return fitted, note
    note = f"not fitted: {_failures(failed)}"
    _logger.debug("%s: piecewise-linear model (for comparison only) %s", name, note)
    return None, note


def _reason(error: ValueError) -> str:
    """Why a piecewise-linear fit failed, short: "the lines no longer intersect in
    order" (no joint, branch, breakpoints, iteration nor advice)."""
    text = str(error).split(";")[0].rsplit(": ", 1)[-1]
    return re.sub(r" \(breakpoints \[[^\]]*\] at iteration \d+\)", "", text)


def _breakpoints(guess: tuple[float, float]) -> str:
    return f"({guess[0]:g}, {guess[1]:g})"


def _failures(failed: list[tuple[tuple[float, float], str]]) -> str:
    """ "from (-0.5, 0.5) and (-2, 2) it did not converge (<reasons>)"."""
    guesses = " and ".join(_breakpoints(g) for g, _ in failed)
    reasons = "; ".join(dict.fromkeys(why for _, why in failed))
    return f"from {guesses} it did not converge ({reasons})"
