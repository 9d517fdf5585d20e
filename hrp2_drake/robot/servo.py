"""EmulatedPositionServo: a robot's emulated position servo (docs/architecture.md), a current
loop behind a position-error command as in closed-source servo boards (first
modelled on HRP-2's); its parameters come from the robot description's servo_file
(e.g. HRP-2: models/hrp2/servo.yaml; the iiwa: models/iiwa14/servo.yaml).

Per joint, with e = q_cmd(t - d) - q_encoder (paper eq. 5, plus what the paper and the
authors' measurements show of a real servo, Sec. 3.2; each robot's models/<name>/README.md
gives the source of every mechanism and number):

    u        = K4 e - K5 q̇                                       current command, A
    i        = clip(deadzone(u, i_dz), i_lo(q̇), i_hi(q̇))        dead zone, limits
    i_hi     = min(i_max,  i_s (1 - q̇ / ω0))                     voltage limit
    i_lo     = max(-i_max, -i_s (1 + q̇ / ω0))                    (back-EMF)
    s        = direction state in [-1, 1] (Dahl: ds/dq = (1 - s sign(q̇)) / δ)
    τ        = K1 (1 + a s) i - K2 q̇ - (K3 + μ |K1 (1 + a s) i|) s   joint actuation

With the servo switched off (its "enabled" input 0: a real servo's torque_enable
false) the driver is off: i = 0 (no drive, no dead zone, no back-EMF braking) and
only the mechanical friction acts, τ = -K2 q̇ - K3 s.

Mechanisms (each switchable off, `SERVO_MECHANISMS`):
  - "latency": the command reaches the servo board d = `latency` seconds after the
    controller sent it (whole control periods).
  - "voltage_limit": the motor's supply voltage caps the current it can drive
    against its back-EMF, i ≤ (V - k_e ρ q̇) / R: the torque-speed line through the
    stall current i_s = V / R and the joint-side no-load speed ω0 = V / (k_e ρ).
  - "hysteresis": the direction-dependent gain K1 (1 ± a) and the Coulomb friction
    switch after the joint has moved `hysteresis_width` δ in the new direction (Dahl
    presliding: gear lost motion, stiction), not at sign(q̇). Off, or δ = 0: s =
    tanh(q̇ / v_s), instantaneous, as in the `ideal` preset.
  - "deadzone": the current dead zone i_dz.

Without dead zone, saturation and latency this is exactly the paper's eq. 6,
Δq = Kτ τ + Kv q̇ + Kc sign(q̇), with Kτ = 1/(K1 K4), Kv = (K1 K5 + K2)/(K1 K4),
Kc = K3/(K1 K4); the latency adds d to the Kv an identification measures, since it
sees Δq = q_cmd(t) - q with the command as sent (`effective_motor_parameters`).
The parameters live in the robot description's servo files (e.g. HRP-2:
models/hrp2/servo.yaml, calibrated by `hrp2-drake calibrate`, or servo_ideal.yaml, the
`ideal` preset: eq. 6 with a small dead zone and Coulomb term) and are the hidden truth
of the simulation: only hrp2_drake.robot reads them; estimation, identification and
control must find everything from signals.

Stability: the torque is explicit (held over each plant step). Every joint carries
the reflected rotor inertia ρ² I_r, which bounds the joint-space inertia from below,
so the per-joint test in `explicit_stability_margin` bounds the whole robot's
discrete closed loop; tests/test_servo.py checks it and a closed-loop run.
"""


import copy
import functools
import math
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.framework import BasicVector, Context, DiscreteValues

from hrp2_drake.config import load_config
from hrp2_drake.multibody import JointIndexing, joint_indexing
from hrp2_drake.simulation import WitnessFreeLeafSystem

#: The servo mechanisms that can be switched off (`EmulatedPositionServo(..., off=...)`,
#: `StationConfig.servo_off`).
SERVO_MECHANISMS = ("latency", "voltage_limit", "hysteresis", "deadzone")


@dataclass
class ServoJointParams:
    """Servo parameters of one joint.

    Args:
        k1: motor drive gain, joint side (N·m/A).
        k1_asymmetry: a in K1± = K1 (1 ± a), by direction of motion.
        k2: viscous friction (N·m·s/rad).
        k3: Coulomb friction (N·m).
        k4: proportional gain of the current command (A/rad).
        k5: derivative gain of the current command (A·s/rad).
        i_deadzone: dead zone of the current command (A).
        i_max: current saturation of the driver (A).
        v_coulomb: velocity scale of the smooth sign tanh(q̇ / v_coulomb) (rad/s),
            used when the direction state has no hysteresis.
        encoder_resolution: joint-side encoder quantum (rad).
        latency: transport latency of the command from the controller to the servo
            board (s, rounded to whole servo periods); 0: none.
        stall_current: supply voltage over winding resistance, V / R (A): the current
            the motor draws at rest with the full voltage; inf: no voltage limit.
        no_load_speed: joint-side speed where the back-EMF equals the supply voltage,
            V / (k_e ρ) (rad/s); inf: no voltage limit.
        hysteresis_width: joint travel after a reversal over which the direction
            state switches (rad; Dahl presliding, gear lost motion); 0: the state is
            tanh(q̇ / v_coulomb), switching exactly with the sign of q̇.
        load_friction: gear friction that grows with the load: a share μ of the
            motor's torque |k1 (1 + a s) i| added to the Coulomb friction k3 (a
            gearbox's efficiency; BAM's "load friction" of small servos). 0: none.
        gain: the servo's own position gain (its firmware units, e.g. a Dynamixel's
            kp) at which k4 holds; a P-controlled servo's k4 is proportional to it
            (`ServoParams.at_gain`). 0: a servo without a settable gain.
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
    latency: float = 0.0
    stall_current: float = float("inf")
    no_load_speed: float = float("inf")
    hysteresis_width: float = 0.0
    load_friction: float = 0.0
    gain: float = 0.0

    def validate(self, where: str) -> None:
        positive = ("k1", "k4", "i_max", "v_coulomb", "stall_current", "no_load_speed")
        for name in positive:
            value = getattr(self, name)
            if not value > 0:
                raise ValueError(f"{where}.{name}: must be > 0, got {value}")
        non_negative = (
            "k2", "k3", "k5", "i_deadzone", "encoder_resolution", "latency",
            "hysteresis_width", "gain",
        )
        for name in non_negative:
            value = getattr(self, name)
            if not (value >= 0 and math.isfinite(value)):
                raise ValueError(f"{where}.{name}: must be finite and >= 0, got {value}")
        if math.isfinite(self.stall_current) != math.isfinite(self.no_load_speed):
            raise ValueError(
                f"{where}: stall_current and no_load_speed set the voltage limit together "
                f"(both finite, or both .inf), got {self.stall_current}, {self.no_load_speed}"
            )
        if not 0 <= self.load_friction < 1:
            raise ValueError(f"{where}.load_friction: must be in [0, 1), got {self.load_friction}")
        if not 0 <= self.k1_asymmetry < 1:
            raise ValueError(f"{where}.k1_asymmetry: must be in [0, 1), got {self.k1_asymmetry}")


@dataclass
class ServoParams:
    """Servo parameters of every joint, by joint name (a robot description's
    servo_file, e.g. models/hrp2/servo.yaml)."""

    joints: dict[str, ServoJointParams] = field(default_factory=dict)

    def vectors(self, names: Sequence[str]) -> dict[str, np.ndarray]:
        """Each parameter as an array over `names`."""
        missing = [n for n in names if n not in self.joints]
        if missing:
            raise KeyError(f"servo parameters missing for joints {missing}")
        keys = ServoJointParams.__dataclass_fields__.keys()
        return {k: np.array([getattr(self.joints[n], k) for n in names]) for k in keys}

    def at_gain(self, gain: float) -> "ServoParams":
        """The servo run at position gain `gain` (the servo's own units): k4 of each
        joint that states its `gain` scaled by gain / that gain (a P-controlled
        servo's current command, or voltage, is proportional to its gain); the other
        joints unchanged.

        Raises:
            ValueError: `gain` is not finite and > 0.
        """
        if not (math.isfinite(gain) and gain > 0):
            raise ValueError(f"servo gain: must be finite and > 0, got {gain}")
        scaled = copy.deepcopy(self)
        for joint in scaled.joints.values():
            if joint.gain > 0:
                joint.k4 *= gain / joint.gain
                joint.gain = gain
        return scaled

    def validate(self, source: str = "") -> None:
        """Raises ValueError naming the joint and parameter (after `source`: a file)."""
        prefix = f"{source}: " if source else ""
        if not self.joints:
            raise ValueError(
                f"{prefix}joints: none, expected the servo parameters of every joint "
                "(an empty file?)"
            )
        for name, joint in self.joints.items():
            joint.validate(f"{prefix}joints.{name}")


def servo_file_path(path: str | Path | None = None, robot: str | Path | None = None) -> Path:
    """The servo data file: a path, a preset of the robot description (e.g. "ideal"),
    or None / "" / "calibrated" for the robot's `servo_file` (`robot` as
    `load_robot_description`: None for the default robot)."""
    from hrp2_drake.description import load_robot_description

    return load_robot_description(robot, check=False).servo_path(str(path or ""))


def load_servo_params(
    path: str | Path | None = None, robot: str | Path | None = None
) -> ServoParams:
    """Loads a servo data file: a path, a preset name ("ideal", "calibrated"), or None
    (the robot's calibrated servo); see `servo_file_path`.

    Raises:
        FileNotFoundError, IsADirectoryError: no such file (naming the robot's presets).
        ValueError: naming the file and the key: a YAML error, an unknown or mistyped
            key, no joints, a parameter out of its range.
    """
    from hrp2_drake.description import load_robot_description

    description = load_robot_description(robot, check=False)
    filename = description.servo_path(str(path or ""))
    if not filename.is_file():
        presets = ["calibrated", *description.servo_presets]
        what = "is a folder" if filename.is_dir() else "not found"
        error = IsADirectoryError if filename.is_dir() else FileNotFoundError
        raise error(
            f"servo file {filename} {what} (give a path or one of {presets} of robot "
            f"'{description.name}')"
        )
    return copy.deepcopy(_read_servo_file(str(filename), filename.stat().st_mtime_ns))


@functools.lru_cache(maxsize=16)
def _read_servo_file(filename: str, mtime_ns: int) -> ServoParams:
    """The servo file, read once per version (`mtime_ns`): callers get copies."""
    return load_config(ServoParams, filename=filename)


def save_servo_params(params: ServoParams, path: str | Path, header: Sequence[str]) -> None:
    """Writes a servo data file that `load_servo_params` reads back: every parameter
    of every joint (9 significant digits, .inf for no limit), after `header` as
    comment lines."""
    lines = [f"# {h}" if h else "#" for h in header]
    lines.append("joints:")
    for name, joint in params.joints.items():
        lines.append(f"  {name}:")
        for key, value in asdict(joint).items():
            text = ".inf" if value == math.inf else f"{value:.9g}"
            lines.append(f"    {key}: {text}")
    Path(path).write_text("\n".join(lines) + "\n")


def effective_motor_parameters(
    params: ServoParams, names: Sequence[str], direction: int = 0
) -> dict[str, np.ndarray]:
    """The effective Kτ, Kv, Kc of eq. 6 implied by the servo parameters.

    For evaluation only (the ground truth an identification is compared with). Kv
    includes the command latency d: an identification sees Δq = q_cmd - q with the
    command as the controller sent it, which leads the one the servo acts on by q̇ d.

    Args:
        direction: 0 for the nominal gain K1 (q̇ = 0), +1 / -1 for K1± (|q̇| >> v_s).

    Returns:
        dict with "k_tau" (rad/(N·m)), "k_v" (s), "k_c" (rad), "latency" (s) and
        "deadzone" (rad, the Δq below which the servo produces no current at rest).
    """
    p = params.vectors(names)
    k1 = p["k1"] * (1.0 + direction * p["k1_asymmetry"])
    return {
        "k_tau": 1.0 / (k1 * p["k4"]),
        "k_v": (k1 * p["k5"] + p["k2"]) / (k1 * p["k4"]) + p["latency"],
        "k_c": p["k3"] / (k1 * p["k4"]),
        "latency": p["latency"].copy(),
        "deadzone": p["i_deadzone"] / p["k4"],
    }


def explicit_stability_margin(
    params: ServoParams, names: Sequence[str], inertia: np.ndarray, time_step: float
) -> np.ndarray:
    """Spectral radius, per joint, of the servo + joint inertia, symplectic Euler.

    The linearised joint is I v̇ = -k q - c v with k = K1 K4 and the largest
    damping the servo can show, c = K1+ K5 + K2 + K3 / v_s (the slope of the smooth
    Coulomb sign at q̇ = 0, and K1+ >= K1). With hysteresis the Coulomb term is the
    Dahl presliding spring K3 s with s' = s + h v' / δ, i.e. a stiffness K3 / δ, in
    place of the K3 / v_s damping. On the voltage limit
    the current no longer depends on q but falls with q̇: k = 0 and c gets
    K1+ i_s / ω0 in place of K1+ K5; the larger radius of the two cases is returned.
    The plant integrates v' = v + h (-k q - c v) / I, q' = q + h v'. A radius
    < 1 means stable; since the joint-space inertia of the whole robot is at least
    diag(inertia) (reflected rotor inertia), the per-joint bound holds for the
    coupled robot. (The latency delays the command only: it does not enter the
    servo's own loop.)

    Args:
        inertia: a lower bound of each joint's inertia (kg·m²), e.g. ρ² I_r.
        time_step: the plant's time step (s).
    """
    p = params.vectors(names)
    h = time_step
    k1_plus = p["k1"] * (1 + p["k1_asymmetry"])
    radius = np.empty(len(names))
    for j in range(len(names)):
        dahl = p["hysteresis_width"][j] > 0
        coulomb_damping = 0.0 if dahl else p["k3"][j] / p["v_coulomb"][j]
        cases = [(p["k1"][j] * p["k4"][j], k1_plus[j] * p["k5"][j])]
        if math.isfinite(p["no_load_speed"][j]) and math.isfinite(p["stall_current"][j]):
            cases.append((0.0, k1_plus[j] * p["stall_current"][j] / p["no_load_speed"][j]))
        worst = 0.0
        for k, c_servo in cases:
            c = c_servo + p["k2"][j] + coulomb_damping
            if dahl:
                # s follows q exactly (s - q / δ is conserved while the presliding
                # spring is linear): the Coulomb term is a spring K3 / δ.
                k = k + p["k3"][j] / p["hysteresis_width"][j]
            m = inertia[j]
            a = np.array([[1 - h * c / m, -h * k / m], [0.0, 1.0]])
            a[1] = [h * a[0, 0], 1 + h * a[0, 1]]  # q' = q + h v'
            if k == 0:
                # No stiffness (on the voltage limit, no Dahl spring): q is a free
                # integrator that feeds nothing back; judge v alone.
                a = a[:1, :1]
            worst = max(worst, max(abs(np.linalg.eigvals(a))))
        radius[j] = worst
    return radius


def servo_torque(
    p: dict[str, np.ndarray],
    error: np.ndarray,
    v: np.ndarray,
    direction: np.ndarray,
    enabled: np.ndarray | None = None,
) -> np.ndarray:
    """The servo law (module docstring), N·m: joint torque for the position error
    e = q_cmd − q_encoder (rad) the board sees, the joint velocity v (rad/s) and the
    direction state (tanh(q̇ / v_s) without hysteresis). `p`: `ServoParams.vectors`
    (arrays over the joints, or one joint's scalars). `enabled`: per joint, > 0.5 on,
    otherwise off (current 0, friction only); None: on."""
    u = p["k4"] * error - p["k5"] * v
    current = np.sign(u) * np.maximum(np.abs(u) - p["i_deadzone"], 0.0)
    # Driver limit and the voltage limit |R i + k_e ρ q̇| <= V (v / inf = 0: no limit).
    back_emf = v / p["no_load_speed"]
    upper = np.minimum(p["i_max"], p["stall_current"] * (1.0 - back_emf))
    lower = np.maximum(-p["i_max"], -p["stall_current"] * (1.0 + back_emf))
    current = np.clip(current, lower, upper)
    if enabled is not None:
        current = np.where(enabled > 0.5, current, 0.0)  # torque_enable off: no drive
    drive = p["k1"] * (1.0 + p["k1_asymmetry"] * direction) * current
    coulomb = p["k3"] + p["load_friction"] * np.abs(drive)
    return drive - p["k2"] * v - coulomb * direction


def dahl_step(s: np.ndarray, dq: np.ndarray, width: np.ndarray) -> np.ndarray:
    """Direction state after the joint moved dq (rad): the exact solution of Dahl's
    ds/dq = (1 - s sign(dq)) / width over the step; stays in [-1, 1]."""
    decay = np.exp(-np.abs(dq) / width)
    target = np.sign(dq)
    return np.where(dq == 0, s, target + (s - target) * decay)


def _applied_parameters(
    params: ServoParams,
    joint_names: Sequence[str],
    period: float,
    off: Sequence[str],
    extra_latency: float,
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The servo's parameters as arrays over `joint_names` (`ServoParams.vectors`)
    with the mechanisms `off` switched off, and each joint's command delay in whole
    servo periods of `period` s (its latency, none with "latency" off, plus
    `extra_latency` s).

    Raises:
        KeyError: a joint without servo parameters.
        ValueError: `extra_latency` is not finite and >= 0.
    """
    n = len(joint_names)
    p = params.vectors(joint_names)
    if "deadzone" in off:
        p["i_deadzone"] = np.zeros(n)
    if "voltage_limit" in off:
        p["stall_current"] = np.full(n, np.inf)
        p["no_load_speed"] = np.full(n, np.inf)
    if "hysteresis" in off:
        p["hysteresis_width"] = np.zeros(n)
    delays = np.rint(p["latency"] / period).astype(int)
    if "latency" in off:
        delays[:] = 0
    if not (math.isfinite(extra_latency) and extra_latency >= 0):
        raise ValueError(
            f"EmulatedPositionServo: extra_latency must be finite and >= 0, got {extra_latency}"
        )
    delays = delays + int(np.rint(extra_latency / period))
    return p, delays


class EmulatedPositionServo(WitnessFreeLeafSystem):
    """The emulated position servo: q_cmd and the plant state in, joint torques out.

    .. code-block:: text

                   ┌───────────────────────┐
        q_cmd ────►│                       │
        state ────►│ EmulatedPositionServo ├──► actuation
      enabled ────►│                       │
     (optional)    └───────────────────────┘

    Ports:
        q_cmd: commanded joint positions (rad), n = len(joint_names), joint order.
        state: the plant's state [q; v].
        enabled: (only with `enable_port=True`) per joint, 1 on, 0 off: a real
            servo's torque_enable. Off, the joint's current is 0 and only its
            friction acts (module docstring); its latency buffer and direction state
            keep running.
        actuation: joint torques (N·m) in the plant's actuation order, to be
            connected to the plant's actuation input.

    Discrete state (one group, updated every `period`): the direction state s of each
    joint, its position at the last update, and the commands in transit (one row per
    period of the longest latency). A joint
    with latency d = k periods acts on the command its board received k periods ago;
    with d = 0 (or "latency" off) on q_cmd directly, as the `ideal` preset does.

    A bus servo takes its goal in encoder pulses: with `command_resolution` (rad, the
    goal register's quantum; 0: none) q_cmd is rounded to the nearest pulse (half to
    even), as `BusDescription.quantized` rounds it.

    The encoder quantization (`encoder_resolution`) applies to the position error,
    like the real servo; the velocity is the plant's (a real servo differentiates
    motor-side encoder counts at a high rate).
    """

    def __init__(
        self,
        plant: MultibodyPlant,
        params: ServoParams,
        joint_names: Sequence[str],
        period: float = 0.001,
        initial_q_cmd: Sequence[float] | None = None,
        off: Sequence[str] = (),
        extra_latency: float = 0.0,
        enable_port: bool = False,
        command_resolution: float = 0.0,
    ):
        super().__init__()
        if not (math.isfinite(command_resolution) and command_resolution >= 0):
            raise ValueError(
                "EmulatedPositionServo: command_resolution must be finite and >= 0, "
                f"got {command_resolution}"
            )
        self._command_resolution = command_resolution or None
        unknown = sorted(set(off) - set(SERVO_MECHANISMS))
        if unknown:
            raise ValueError(
                f"EmulatedPositionServo: unknown mechanism(s) {unknown} to switch off "
                f"(known: {list(SERVO_MECHANISMS)})"
            )
        self._indexing: JointIndexing = joint_indexing(plant, joint_names)
        if np.any(self._indexing.u < 0):
            missing = [n for n, u in zip(joint_names, self._indexing.u) if u < 0]
            raise ValueError(f"EmulatedPositionServo: joints without actuator: {missing}")
        if not period > 0:
            raise ValueError(f"EmulatedPositionServo: period must be > 0, got {period}")
        p, delays = _applied_parameters(params, joint_names, period, off, extra_latency)
        self._p = p
        self._delays = delays
        self._dahl = p["hysteresis_width"] > 0
        self._width = np.where(self._dahl, p["hysteresis_width"], 1.0)
        self._n = len(joint_names)
        self._declare_ports_and_state(plant, period, initial_q_cmd, enable_port)
        self._precompute_step_constants(plant)

    def _declare_ports_and_state(
        self,
        plant: MultibodyPlant,
        period: float,
        initial_q_cmd: Sequence[float] | None,
        enable_port: bool,
    ) -> None:
        """Declares the input ports, the discrete state with its events, and the
        actuation output (class docstring), in that order."""
        n = self._n
        self._q_cmd = self.DeclareVectorInputPort("q_cmd", n)
        self._state = self.DeclareVectorInputPort(
            "state", plant.num_positions() + plant.num_velocities()
        )
        self._enabled = None
        if enable_port:
            self._enabled = self.DeclareVectorInputPort("enabled", n)
        depth = int(self._delays.max())
        initial = np.zeros(n) if initial_q_cmd is None else np.asarray(initial_q_cmd, float)
        if initial.shape != (n,):
            raise ValueError(
                f"EmulatedPositionServo: initial_q_cmd has {initial.size} values, expected {n}"
            )
        self._depth = depth
        # One discrete state group (one read and one write per update): the direction
        # state s, the joint positions of the last update (the travel that moves s),
        # and the commands in transit, newest first (depth x n).
        initial_state = np.concatenate([np.zeros(2 * n), np.tile(initial, depth)])
        self._x = int(self.DeclareDiscreteState(initial_state))
        self._s_rows = slice(0, n)
        self._last_q_rows = slice(n, 2 * n)
        self._transit_rows = slice(2 * n, None)
        self.DeclareInitializationDiscreteUpdateEvent(self._initialize)
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._update)
        self.DeclareVectorOutputPort("actuation", plant.num_actuators(), self._calc)

    def _precompute_step_constants(self, plant: MultibodyPlant) -> None:
        """What the servo's law and state need per step, computed once.

        The servo runs at every plant step: the arithmetic is `joint_torques`' and
        `servo_torque`'s, operation for operation (tests/test_servo.py compares them bit
        for bit). Constants are arrays (numpy takes longer to broadcast a Python float
        than to read an array) and constant masks are index arrays (cheaper than where).
        """
        n, p, delays = self._n, self._p, self._delays
        self._state_q = self._indexing.q
        self._state_v = plant.num_positions() + self._indexing.v
        self._ones = np.ones(n)  # also the finite check: x·1 is finite iff every x_i is
        self._zeros = np.zeros(n)
        self._minus_i_max = -p["i_max"]
        self._minus_stall_current = -p["stall_current"]
        resolution = p["encoder_resolution"]
        quantized = resolution > 0
        self._unquantized = np.flatnonzero(~quantized)
        self._quantum_divisor = np.where(quantized, resolution, 1.0)
        self._dahl_joints = np.flatnonzero(self._dahl)
        self._dahl_width = self._width[self._dahl_joints]
        self._smooth_joints = np.flatnonzero(~self._dahl)
        # Applied command of joint j: the transit entry of row delays[j] - 1, or
        # q_cmd itself (delay 0).
        self._delayed = np.flatnonzero(delays > 0)
        self._transit_index = (2 * n + (delays - 1) * n + np.arange(n))[self._delayed]
        # Joint order -> actuation order (every actuator of the plant is a joint's).
        self._actuation_order = None
        if sorted(self._indexing.u) == list(range(plant.num_actuators())):
            self._actuation_order = np.argsort(self._indexing.u)
        self._num_actuators = plant.num_actuators()
    @property
    def joint_names(self) -> tuple[str, ...]:
        return self._indexing.names

    @property
    def latency_periods(self) -> np.ndarray:
        """Command latency of each joint in servo periods."""
        return self._delays.copy()

    def joint_torques(
        self,
        q_cmd: np.ndarray,
        q: np.ndarray,
        v: np.ndarray,
        s: np.ndarray | None = None,
        enabled: np.ndarray | None = None,
    ) -> np.ndarray:
        """The servo law (module docstring) on joint vectors; N·m.

        Args:
            q_cmd: the command the servo acts on (after the latency), rad.
            q, v: joint positions (rad) and velocities (rad/s).
            s: the direction state of the joints with hysteresis (ignored for the
                others, which use tanh(q̇ / v_s)); None: tanh for every joint.
            enabled: per joint, > 0.5 on, otherwise off (friction only); None: on.
        """
        p = self._p
        direction = np.tanh(v / p["v_coulomb"])
        if s is not None:
            direction[self._dahl_joints] = s[self._dahl_joints]
        return self._servo_torque(q_cmd - self.encoder(q), v, direction, enabled)

    def encoder(self, q: np.ndarray) -> np.ndarray:
        """What the servo's own encoder reads of the joint angles q (rad): q
        quantized at each joint's encoder_resolution (none where it is 0)."""
        # np.round(x) is np.rint(x) (half to even), without np.round's Python layer.
        q_encoder = np.rint(q / self._quantum_divisor) * self._p["encoder_resolution"]
        q_encoder[self._unquantized] = q[self._unquantized]
        return q_encoder

    def motor_current(
        self, q_cmd: np.ndarray, q: np.ndarray, v: np.ndarray,
        enabled: np.ndarray | None = None,
    ) -> np.ndarray:
        """The motor current i (A) the servo drives for the command it acts on
        (after the latency), as `joint_torques` computes it: what a servo reports as
        its present current."""
        return self._drive_current(q_cmd - self.encoder(q), v, enabled)

    def _servo_torque(
        self,
        error: np.ndarray,
        v: np.ndarray,
        direction: np.ndarray,
        enabled: np.ndarray | None = None,
    ) -> np.ndarray:
        """servo_torque(self's parameters, error, v, direction): the same operations
        on the same numbers, with array constants."""
        p, one = self._p, self._ones
        current = self._drive_current(error, v, enabled)
        drive = p["k1"] * (one + p["k1_asymmetry"] * direction) * current
        coulomb = p["k3"] + p["load_friction"] * np.abs(drive)
        return drive - p["k2"] * v - coulomb * direction

    def _drive_current(
        self, error: np.ndarray, v: np.ndarray, enabled: np.ndarray | None = None
    ) -> np.ndarray:
        """The motor current i (A) of the servo law (module docstring). np.clip(x, lo,
        hi) is written np.minimum(hi, np.maximum(lo, x)), which returns what clip
        returns (ties included), about 1 us less."""
        p, one = self._p, self._ones
        u = p["k4"] * error - p["k5"] * v
        current = np.sign(u) * np.maximum(np.abs(u) - p["i_deadzone"], self._zeros)
        back_emf = v / p["no_load_speed"]
        upper = np.minimum(p["i_max"], p["stall_current"] * (one - back_emf))
        lower = np.maximum(
            self._minus_i_max, self._minus_stall_current * (one + back_emf)
        )
        current = np.minimum(upper, np.maximum(lower, current))
        if enabled is not None:
            current = np.where(enabled > 0.5, current, self._zeros)
        return current

    def _joint_state(self, context: Context) -> tuple[np.ndarray, np.ndarray]:
        x = self._state.Eval(context)
        return x[self._state_q], x[self._state_v]

    def _checked_command(self, context: Context) -> np.ndarray:
        q_cmd = self._q_cmd.Eval(context)
        if not math.isfinite(q_cmd.dot(self._ones)):
            bad = [self.joint_names[i] for i in np.flatnonzero(~np.isfinite(q_cmd))]
            raise ValueError(f"EmulatedPositionServo: q_cmd is not finite for {bad}")
        if self._command_resolution is not None:
            return np.rint(q_cmd / self._command_resolution) * self._command_resolution
        return q_cmd

    def current(self, context: Context) -> np.ndarray:
        """The motor current (A) in `context` (this system's), as the servo drives it
        now: what a servo reports as its present current."""
        x = context.get_discrete_state(self._x).get_value()
        q_cmd = self._applied_command(self._checked_command(context), x)
        q, v = self._joint_state(context)
        enabled = None if self._enabled is None else self._enabled.Eval(context)
        return self.motor_current(q_cmd, q, v, enabled)

    def _applied_command(self, q_cmd: np.ndarray, x: np.ndarray) -> np.ndarray:
        """The command each joint acts on: q_cmd delayed by its latency (x: the
        discrete state)."""
        if self._depth:
            q_cmd = q_cmd.copy()
            q_cmd[self._delayed] = x[self._transit_index]
        return q_cmd

    def _initialize(self, context: Context, state: DiscreteValues) -> None:
        # (state holds the current discrete state on entry.)
        q, _ = self._joint_state(context)
        state.get_mutable_value(self._x)[self._last_q_rows] = q

    def _update(self, context: Context, state: DiscreteValues) -> None:
        # In place on `state`, which holds the current discrete state on entry.
        q, _ = self._joint_state(context)
        x = state.get_mutable_value(self._x)
        s = x[self._s_rows]
        travel = q - x[self._last_q_rows]
        dahl = self._dahl_joints
        s[dahl] = dahl_step(s[dahl], travel[dahl], self._dahl_width)
        s[self._smooth_joints] = 0.0
        x[self._last_q_rows] = q
        if self._depth:
            transit = x[self._transit_rows]
            transit[self._n :] = transit[: -self._n]  # overlapping: numpy copies first
            transit[: self._n] = self._checked_command(context)

    def _calc(self, context: Context, output: BasicVector) -> None:
        x = context.get_discrete_state(self._x).get_value()
        q_cmd = self._applied_command(self._checked_command(context), x)
        q, v = self._joint_state(context)
        enabled = None if self._enabled is None else self._enabled.Eval(context)
        tau = self.joint_torques(q_cmd, q, v, x[self._s_rows], enabled)
        if self._actuation_order is not None:
            output.set_value(tau[self._actuation_order])
            return
        actuation = np.zeros(self._num_actuators)
        actuation[self._indexing.u] = tau
        output.set_value(actuation)


def __getattr__(name: str):
    """The deprecated name `Hrp2ServoEmulation` (the class was renamed
    `EmulatedPositionServo`, which drives any robot): importing it warns once per
    place that imports it, and gives `EmulatedPositionServo` itself. It goes in the
    next release."""
    if name == "Hrp2ServoEmulation":
        warnings.warn(
            "hrp2_drake.robot.servo.Hrp2ServoEmulation is deprecated: use "
            "EmulatedPositionServo (the same class, renamed)",
            DeprecationWarning,
            stacklevel=2,
        )
        return EmulatedPositionServo
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
