"""The identified motor model that the torque controller reads (paper Sec. 3).

Per joint, the position-servo input error Δq = q_cmd - q that produces the joint
torque τ at joint velocity q̇ is (paper eq. 6)

    Δq = k_tau τ + k_v q̇ + k_c sign(q̇)

with τ in N·m, q̇ in rad/s and Δq in rad, so k_tau is in rad/(N·m), k_v in
rad/(rad/s) = s and k_c in rad. The paper drops the Coulomb term k_c (it did not
improve the fit), so it is zero unless a fit asks for it.

`PiecewiseLinearMotorModel` is the augmented model of Sec. 3.2.1 that the paper tried
and abandoned (its torque control was unstable); it is kept to reproduce that result.
"""

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
from pydrake.common.yaml import yaml_dump_typed

from hrp2_drake.config import load_config


@dataclass
class FitReport:
    """Diagnostics of one single-joint fit.

    Args:
        method: Which fit produced the model, e.g. "least_squares", "asymmetric newton".
        samples: Number of samples the fit used.
        residual_rms: RMS of Δq̂ - Δq over those samples (rad).
        overestimation_share: Fraction of those samples where the model over-estimates
            |Δq| (see `fitting.overestimation_share`).
        iterations: Iterations of an iterative fit (0 for a closed-form one).
        converged: False when an iterative fit stopped at its iteration limit.
    """

    method: str
    samples: int
    residual_rms: float
    overestimation_share: float
    iterations: int = 0
    converged: bool = True


class JointMotorParameters(NamedTuple):
    """The eq. 6 parameters of one joint: k_tau rad/(N·m), k_v s, k_c rad."""

    k_tau: float
    k_v: float
    k_c: float


class MotorModelFileError(ValueError, RuntimeError):
    """A motor-model file that cannot be read; the message names the file and the
    problem. (Also a RuntimeError: what `load` raised for an unknown key before.)"""


# yaml_load_typed reads the field types at run time: this module must not use
# `from __future__ import annotations` (it would turn them into strings).
@dataclass
class MotorModelFile:
    """YAML schema of `MotorModel.save` and `load` (k_c may be omitted: zeros)."""

    joint_names: list[str] = field(default_factory=list)
    k_tau: list[float] = field(default_factory=list)
    k_v: list[float] = field(default_factory=list)
    k_c: list[float] = field(default_factory=list)
    gain: float = 0.0
    fit: str = ""


@dataclass
class MotorModel:
    """Linear motor model Δq = k_tau τ + k_v q̇ + k_c sign(q̇) (paper eq. 6), per joint.

    Args:
        joint_names: Joint names, in the order of the parameter vectors.
        k_tau: Torque gains, rad/(N·m), shape (n,).
        k_v: Velocity gains, rad/(rad/s) = s, shape (n,).
        k_c: Coulomb offsets, rad, shape (n,); zeros when None.
        gain: the servo's position gain (its own units, e.g. a Dynamixel's kp) at
            which the parameters hold; 0: a model of one fixed servo. A P-controlled
            servo's output is proportional to its gain times Δq, so every term of
            eq. 6 scales as 1/gain: `at_gain` gives the model at another gain.
        fit: the fit that made it ("least_squares", "asymmetric", ...); "" unknown.
        reports: Fit diagnostics by joint name (not saved to YAML, not compared).
    """

    joint_names: list[str]
    k_tau: np.ndarray
    k_v: np.ndarray
    k_c: np.ndarray | None = None
    reports: dict[str, FitReport] = field(
        default_factory=dict, compare=False, repr=False
    )
    gain: float = 0.0
    fit: str = ""

    def __post_init__(self):
        self.joint_names = [str(name) for name in self.joint_names]
        n = len(self.joint_names)
        if n == 0:
            raise ValueError("MotorModel: no joints")
        if len(set(self.joint_names)) != n:
            raise ValueError(f"MotorModel: duplicate joint names in {self.joint_names}")
        if self.k_c is None:
            self.k_c = np.zeros(n)
        for name in ("k_tau", "k_v", "k_c"):
            value = np.array(getattr(self, name), dtype=float).reshape(-1)
            if value.shape != (n,):
                raise ValueError(
                    f"MotorModel: {name} has {value.size} entries but there are {n} "
                    f"joints {self.joint_names}"
                )
            if not np.all(np.isfinite(value)):
                bad = [j for j, v in zip(self.joint_names, value) if not np.isfinite(v)]
                raise ValueError(f"MotorModel: {name} is NaN or inf for joints {bad}")
            setattr(self, name, value)
        if not (math.isfinite(self.gain) and self.gain >= 0):
            raise ValueError(
                f"MotorModel: gain must be finite and >= 0, got {self.gain}"
            )
        self.gain = float(self.gain)

    def at_gain(self, gain: float | None) -> "MotorModel":
        """The model at servo gain `gain`: every parameter times self.gain / gain.
        None, or a model without gain, is returned as is.

        Raises:
            ValueError: `gain` is not finite and > 0.
        """
        if gain is None or not self.gain:
            return self
        if not (math.isfinite(gain) and gain > 0):
            raise ValueError(
                f"MotorModel.at_gain: gain must be finite and > 0, got {gain}"
            )
        scale = self.gain / gain
        return dataclasses.replace(
            self,
            k_tau=self.k_tau * scale,
            k_v=self.k_v * scale,
            k_c=self.k_c * scale,
            gain=float(gain),
        )

    def torque(self, delta_q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """The torque (N·m) a servo obeying the model gives at position error Δq and
        velocity q̇: eq. 6 solved for τ, τ = (Δq − k_v q̇ − k_c sign(q̇)) / k_tau."""
        return (
            np.asarray(delta_q, float) - self.k_v * v - self.k_c * np.sign(v)
        ) / self.k_tau

    def sign_errors(self) -> list[str]:
        """What makes the model no servo's (k_tau <= 0 or k_v < 0): one text per bad
        parameter, naming the joints and values; empty for a physical model."""
        errors = []
        for name, bad, bound in (
            ("k_tau", self.k_tau <= 0, "> 0"),
            ("k_v", self.k_v < 0, ">= 0"),
        ):
            if np.any(bad):
                joints = [j for j, b in zip(self.joint_names, bad) if b]
                errors.append(
                    f"{name} must be {bound} for joints {joints} "
                    f"({getattr(self, name)[bad].tolist()})"
                )
        return errors

    def __eq__(self, other) -> bool:
        return (
            isinstance(other, MotorModel)
            and self.joint_names == other.joint_names
            and self.gain == other.gain
            and all(
                np.array_equal(getattr(self, name), getattr(other, name))
                for name in ("k_tau", "k_v", "k_c")
            )
        )

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    def predict(self, tau: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Returns Δq (rad) for torques τ (N·m) and velocities q̇ (rad/s), eq. 6.

        tau and v have shape (n,) for one sample or (m, n) for m samples. For a
        one-joint model a 1-D array is read as m samples of that joint.
        """
        tau = np.asarray(tau, dtype=float)
        v = np.asarray(v, dtype=float)
        n = self.num_joints
        if tau.shape != v.shape:
            raise ValueError(f"predict: tau {tau.shape} and v {v.shape} differ")
        one_sample_or_one_joint = tau.ndim == 1 and n in (1, tau.size)
        if not (one_sample_or_one_joint or (tau.ndim == 2 and tau.shape[1] == n)):
            raise ValueError(
                f"predict: expected shape (n,) or (m, n) with n={n}, got {tau.shape}"
            )
        # eq. 6
        return self.k_tau * tau + self.k_v * v + self.k_c * np.sign(v)

    def for_joint(self, name: str) -> JointMotorParameters:
        """Returns (k_tau, k_v, k_c) of the named joint."""
        try:
            j = self.joint_names.index(name)
        except ValueError:
            raise KeyError(
                f"MotorModel: no joint {name!r} in {self.joint_names}"
            ) from None
        return JointMotorParameters(
            float(self.k_tau[j]), float(self.k_v[j]), float(self.k_c[j])
        )

    def __getitem__(self, name: str) -> JointMotorParameters:
        return self.for_joint(name)

    def subset(self, joint_names: list[str]) -> "MotorModel":
        """Returns the model of the given joints, in the given order."""
        missing = [name for name in joint_names if name not in self.joint_names]
        if missing:
            raise KeyError(f"MotorModel: no joints {missing} in {self.joint_names}")
        rows = [self.joint_names.index(name) for name in joint_names]
        return MotorModel(
            joint_names=list(joint_names),
            k_tau=self.k_tau[rows],
            k_v=self.k_v[rows],
            k_c=self.k_c[rows],
            reports={
                name: self.reports[name] for name in joint_names if name in self.reports
            },
            gain=self.gain,
            fit=self.fit,
        )

    @staticmethod
    def from_joints(models: Mapping[str, "MotorModel"]) -> "MotorModel":
        """Combines one-joint models into one, named and ordered by the mapping."""
        for name, model in models.items():
            if model.num_joints != 1:
                raise ValueError(
                    f"from_joints: the model for {name!r} has {model.num_joints} "
                    "joints, expected 1"
                )
        reports = {
            name: model.reports[model.joint_names[0]]
            for name, model in models.items()
            if model.joint_names[0] in model.reports
        }
        gains = {m.gain for m in models.values()}
        if len(gains) > 1:
            raise ValueError(
                "from_joints: the joints' models hold at different gains "
                f"{sorted(gains)}"
            )
        fits = {m.fit for m in models.values()}
        return MotorModel(
            joint_names=list(models),
            k_tau=np.concatenate([m.k_tau for m in models.values()]),
            k_v=np.concatenate([m.k_v for m in models.values()]),
            k_c=np.concatenate([m.k_c for m in models.values()]),
            reports=reports,
            gain=gains.pop(),
            fit=fits.pop() if len(fits) == 1 else "",
        )

    def save(self, path: str | Path) -> None:
        """Writes joint_names, k_tau, k_v, k_c to a YAML file (not the reports)."""
        data = MotorModelFile(
            joint_names=list(self.joint_names),
            k_tau=self.k_tau.tolist(),
            k_v=self.k_v.tolist(),
            k_c=self.k_c.tolist(),
            gain=self.gain,
            fit=self.fit,
        )
        yaml_dump_typed(data, filename=str(path))

    @staticmethod
    def load(path: str | Path) -> "MotorModel":
        """Reads a file written by `save`.

        Raises:
            FileNotFoundError, IsADirectoryError: `path` is not a file.
            MotorModelFileError: (a ValueError) naming the file and the problem: a
                YAML syntax error, an unknown key, a value of the wrong type, a size
                mismatch, NaN, or k_tau <= 0 or k_v < 0 (no servo works that way).
        """
        try:
            data = load_config(MotorModelFile, filename=path)
        except ValueError as error:
            raise MotorModelFileError(str(error)) from None
        fields = dataclasses.asdict(data)
        if not fields["k_c"]:
            fields["k_c"] = None
        try:
            loaded = MotorModel(**fields)
        except ValueError as error:
            raise MotorModelFileError(f"{path}: {error}") from None
        errors = loaded.sign_errors()
        if errors:
            raise MotorModelFileError(f"{path}: {errors[0]}")
        return loaded


@dataclass
class PiecewiseLinearBranch:
    """Continuous three-line function Δq = f(τ) of one velocity sign (Sec. 3.2.1).

    Line i is Δq = slopes[i] τ + intercepts[i]; line 0 holds for τ <= τ1, line 1 for
    τ1 <= τ <= τ2, line 2 for τ >= τ2, with breakpoints (τ1, τ2) the intersections of
    consecutive lines, so f is continuous.

    Args:
        slopes: k_τ1, k_τ2, k_τ3 in rad/(N·m).
        intercepts: q_1, q_2, q_3 in rad.
        breakpoints: τ1 < τ2 in N·m.
    """

    slopes: np.ndarray
    intercepts: np.ndarray
    breakpoints: np.ndarray

    def __post_init__(self):
        self.slopes = np.asarray(self.slopes, dtype=float).reshape(3)
        self.intercepts = np.asarray(self.intercepts, dtype=float).reshape(3)
        self.breakpoints = np.asarray(self.breakpoints, dtype=float).reshape(2)
        if not self.breakpoints[0] < self.breakpoints[1]:
            raise ValueError(
                f"breakpoints must satisfy τ1 < τ2, got {self.breakpoints}"
            )

    def __call__(self, tau: np.ndarray) -> np.ndarray:
        """Returns Δq (rad) at torques tau (N·m)."""
        tau = np.asarray(tau, dtype=float)
        segment = np.searchsorted(self.breakpoints, tau)
        return self.slopes[segment] * tau + self.intercepts[segment]


@dataclass
class PiecewiseLinearMotorModel:
    """Piecewise-linear model of one joint (Sec. 3.2.1).

    Δq = f_p(τ) if q̇ > 0 and f_n(τ) if q̇ < 0.

    The paper leaves q̇ = 0 undefined; `predict` returns the mean of both branches there.

    Args:
        joint_name: The joint.
        positive: f_p, the branch for sign(q̇) > 0.
        negative: f_n, the branch for sign(q̇) < 0.
        reports: Fit diagnostics by branch ("positive", "negative").
    """

    joint_name: str
    positive: PiecewiseLinearBranch
    negative: PiecewiseLinearBranch
    reports: dict[str, FitReport] = field(
        default_factory=dict, compare=False, repr=False
    )

    def predict(self, tau: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Returns Δq (rad) for torques τ (N·m) and velocities q̇ (rad/s) (any shape)."""
        tau = np.asarray(tau, dtype=float)
        v = np.asarray(v, dtype=float)
        if tau.shape != v.shape:
            raise ValueError(f"predict: tau {tau.shape} and v {v.shape} differ")
        f_p, f_n = self.positive(tau), self.negative(tau)
        return np.where(v > 0, f_p, np.where(v < 0, f_n, 0.5 * (f_p + f_n)))
