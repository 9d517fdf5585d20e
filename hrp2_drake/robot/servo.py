"""Hrp2ServoEmulation: the closed-source HRP-2 position servo (DESIGN.md).

Per joint, with e = q_cmd - q_encoder (paper eq. 5, plus what the paper found on the
robot, Sec. 3.2):

    i        = sat(deadzone(K4 e - K5 q̇, i_dz), i_max)          current, A
    K1(q̇)   = K1 (1 + a tanh(q̇ / v_s))                          K1± by direction
    τ_motor  = K1(q̇) i
    τ_fric   = K2 q̇ + K3 tanh(q̇ / v_s)                          viscous + Coulomb
    τ        = τ_motor - τ_fric                                  joint actuation

Without dead zone and saturation this is exactly the paper's eq. 6,
Δq = Kτ τ + Kv q̇ + Kc sign(q̇), with Kτ = 1/(K1 K4), Kv = (K1 K5 + K2)/(K1 K4),
Kc = K3/(K1 K4) (`effective_motor_parameters`). The parameters live in
models/hrp2/servo.yaml and are the hidden truth of the simulation: only
hrp2_drake.robot reads them; estimation, identification and control must find
everything from signals.

Stability: the torque is explicit (held over each plant step). Every joint carries
the reflected rotor inertia ρ² I_r, which bounds the joint-space inertia from below,
so the per-joint test in `explicit_stability_margin` bounds the whole robot's
discrete closed loop; tests/test_servo.py checks it and a closed-loop run.
"""


from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
from pydrake.common.yaml import yaml_load_typed
from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.framework import BasicVector, Context, LeafSystem

from hrp2_drake.multibody import JointIndexing, joint_indexing


@dataclass
class ServoJointParams:
    """Servo parameters of one joint.

    Args:
        k1: motor drive gain, joint side (N·m/A).
        k1_asymmetry: a in K1± = K1 (1 ± a), blended by tanh(q̇ / v_coulomb).
        k2: viscous friction (N·m·s/rad).
        k3: Coulomb friction (N·m).
        k4: proportional gain of the current command (A/rad).
        k5: derivative gain of the current command (A·s/rad).
        i_deadzone: dead zone of the current command (A).
        i_max: current saturation (A).
        v_coulomb: velocity scale of the smooth sign tanh(q̇ / v_coulomb) (rad/s).
        encoder_resolution: joint-side encoder quantum (rad).
    """

    k1: float = 1.0
    k1_asymmetry: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 1.0
    k5: float = 0.0
    i_deadzone: float = 0.0
    i_max: float = float("inf")
    v_coulomb: float = 0.05
    encoder_resolution: float = 0.0


@dataclass
class ServoParams:
    """Servo parameters of every joint, by joint name (models/hrp2/servo.yaml)."""

    joints: dict[str, ServoJointParams] = field(default_factory=dict)

    def vectors(self, names: Sequence[str]) -> dict[str, np.ndarray]:
        """Each parameter as an array over `names`."""
        missing = [n for n in names if n not in self.joints]
        if missing:
            raise KeyError(f"servo parameters missing for joints {missing}")
        keys = ServoJointParams.__dataclass_fields__.keys()
        return {k: np.array([getattr(self.joints[n], k) for n in names]) for k in keys}


def load_servo_params(path: str | Path | None = None) -> ServoParams:
    """Loads the servo data file (default: models/hrp2/servo.yaml)."""
    if path is None:
        from hrp2_drake.robot.model import SERVO_FILE, models_dir

        path = models_dir() / SERVO_FILE
    return yaml_load_typed(schema=ServoParams, filename=str(path))


def effective_motor_parameters(
    params: ServoParams, names: Sequence[str], direction: int = 0
) -> dict[str, np.ndarray]:
    """The effective Kτ, Kv, Kc of eq. 6 implied by the servo parameters.

    For evaluation only (the ground truth an identification is compared with).

    Args:
        direction: 0 for the nominal gain K1 (q̇ = 0), +1 / -1 for K1± (|q̇| >> v_s).

    Returns:
        dict with "k_tau" (rad/(N·m)), "k_v" (s), "k_c" (rad), and "deadzone" (rad,
        the Δq below which the servo produces no current at rest).
    """
    p = params.vectors(names)
    k1 = p["k1"] * (1.0 + direction * p["k1_asymmetry"])
    return {
        "k_tau": 1.0 / (k1 * p["k4"]),
        "k_v": (k1 * p["k5"] + p["k2"]) / (k1 * p["k4"]),
        "k_c": p["k3"] / (k1 * p["k4"]),
        "deadzone": p["i_deadzone"] / p["k4"],
    }


def explicit_stability_margin(
    params: ServoParams, names: Sequence[str], inertia: np.ndarray, time_step: float
) -> np.ndarray:
    """Spectral radius, per joint, of the servo + joint inertia, symplectic Euler.

    The linearised joint is I v̇ = -k q - c v with k = K1 K4 and the largest
    damping the servo can show, c = K1+ K5 + K2 + K3 / v_s (the slope of the smooth
    Coulomb sign at q̇ = 0, and K1+ >= K1). The plant integrates
    v' = v + h (-k q - c v) / I, q' = q + h v'. A radius < 1 means stable; since the
    joint-space inertia of the whole robot is at least diag(inertia) (reflected rotor
    inertia), the per-joint bound holds for the coupled robot.

    Args:
        inertia: a lower bound of each joint's inertia (kg·m²), e.g. ρ² I_r.
        time_step: the plant's time step (s).
    """
    p = params.vectors(names)
    k = p["k1"] * p["k4"]
    c = p["k1"] * (1 + p["k1_asymmetry"]) * p["k5"] + p["k2"] + p["k3"] / p["v_coulomb"]
    radius = np.empty(len(names))
    h = time_step
    for j in range(len(names)):
        a = np.array(
            [[1 - h * c[j] / inertia[j], -h * k[j] / inertia[j]], [0.0, 1.0]]
        )
        # q' = q + h v' -> second row uses the updated velocity.
        a[1] = [h * a[0, 0], 1 + h * a[0, 1]]
        radius[j] = max(abs(np.linalg.eigvals(a)))
    return radius


class Hrp2ServoEmulation(LeafSystem):
    """The HRP-2 position servo: q_cmd and the plant state in, joint torques out.

    .. code-block:: text

                   ┌─────────────────────┐
        q_cmd ────►│                     │
                   │ Hrp2ServoEmulation  ├──► actuation
        state ────►│                     │
                   └─────────────────────┘

    Ports:
        q_cmd: commanded joint positions (rad), n = len(joint_names), joint order.
        state: the plant's state [q; v].
        actuation: joint torques (N·m) in the plant's actuation order, to be
            connected to the plant's actuation input.

    The encoder quantization (`encoder_resolution`) applies to the position error,
    like the real servo; the velocity is the plant's (a real servo differentiates
    motor-side encoder counts at a high rate).
    """

    def __init__(
        self,
        plant: MultibodyPlant,
        params: ServoParams,
        joint_names: Sequence[str],
    ):
        super().__init__()
        self._indexing: JointIndexing = joint_indexing(plant, joint_names)
        if np.any(self._indexing.u < 0):
            missing = [n for n, u in zip(joint_names, self._indexing.u) if u < 0]
            raise ValueError(f"Hrp2ServoEmulation: joints without actuator: {missing}")
        self._p = params.vectors(joint_names)
        self._nq = plant.num_positions()
        self._num_actuators = plant.num_actuators()
        n = len(joint_names)
        self._q_cmd = self.DeclareVectorInputPort("q_cmd", n)
        self._state = self.DeclareVectorInputPort(
            "state", plant.num_positions() + plant.num_velocities()
        )
        self.DeclareVectorOutputPort("actuation", plant.num_actuators(), self._calc)

    @property
    def joint_names(self) -> tuple[str, ...]:
        return self._indexing.names

    def joint_torques(self, q_cmd: np.ndarray, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """The servo law (module docstring) on joint vectors; N·m."""
        p = self._p
        res = p["encoder_resolution"]
        q_encoder = np.where(res > 0, np.round(q / np.where(res > 0, res, 1)) * res, q)
        u = p["k4"] * (q_cmd - q_encoder) - p["k5"] * v
        current = np.sign(u) * np.clip(np.abs(u) - p["i_deadzone"], 0.0, p["i_max"])
        smooth_sign = np.tanh(v / p["v_coulomb"])
        k1 = p["k1"] * (1.0 + p["k1_asymmetry"] * smooth_sign)
        return k1 * current - p["k2"] * v - p["k3"] * smooth_sign

    def _calc(self, context: Context, output: BasicVector) -> None:
        q_cmd = self._q_cmd.Eval(context)
        if not np.all(np.isfinite(q_cmd)):
            bad = [self.joint_names[i] for i in np.flatnonzero(~np.isfinite(q_cmd))]
            raise ValueError(f"Hrp2ServoEmulation: q_cmd is not finite for {bad}")
        x = self._state.Eval(context)
        q = x[self._indexing.q]
        v = x[self._nq + self._indexing.v]
        tau = self.joint_torques(q_cmd, q, v)
        actuation = np.zeros(self._num_actuators)
        actuation[self._indexing.u] = tau
        output.set_value(actuation)
