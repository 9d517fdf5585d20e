"""EmulatedPositionServo: a robot's emulated position servo (docs/architecture.md), a
current loop behind a position-error command as in closed-source servo boards (first
modelled on HRP-2's); its parameters come from the robot description's servo_file
(e.g. HRP-2: models/hrp2/servo.yaml; the iiwa: models/iiwa14/servo.yaml).

Per joint, with e = q_cmd(t - d) - q_encoder (paper eq. 5, plus what the paper and the
authors' measurements show of a real servo, Sec. 3.2; each robot's
models/<name>/README.md gives the source of every mechanism and number):

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
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.framework import BasicVector, Context, DiscreteValues

from hrp2_drake.config import load_config
from hrp2_drake.kernels import kernel
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
            "k2",
            "k3",
            "k5",
            "i_deadzone",
            "encoder_resolution",
            "latency",
            "hysteresis_width",
            "gain",
        )
        for name in non_negative:
            value = getattr(self, name)
            if not (value >= 0 and math.isfinite(value)):
                raise ValueError(
                    f"{where}.{name}: must be finite and >= 0, got {value}"
                )
        if math.isfinite(self.stall_current) != math.isfinite(self.no_load_speed):
            raise ValueError(
                f"{where}: stall_current and no_load_speed set the voltage limit "
                f"together (both finite, or both .inf), got {self.stall_current}, "
                f"{self.no_load_speed}"
            )
        if not 0 <= self.load_friction < 1:
            raise ValueError(
                f"{where}.load_friction: must be in [0, 1), got {self.load_friction}"
            )
        if not 0 <= self.k1_asymmetry < 1:
            raise ValueError(
                f"{where}.k1_asymmetry: must be in [0, 1), got {self.k1_asymmetry}"
            )


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


def load_servo_params(
    path: str | Path | None = None, robot: str | Path | None = None
) -> ServoParams:
    """Loads a servo data file: a path, a preset name ("ideal", "calibrated"), or None
    (the robot's calibrated servo), as `RobotDescription.servo_path` finds it (`robot`
    as `load_robot_description`: None for the default robot).

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


def save_servo_params(
    params: ServoParams, path: str | Path, header: Sequence[str]
) -> None:
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
        if math.isfinite(p["no_load_speed"][j]) and math.isfinite(
            p["stall_current"][j]
        ):
            cases.append(
                (0.0, k1_plus[j] * p["stall_current"][j] / p["no_load_speed"][j])
            )
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


# --- The per-step arithmetic: numba kernels (hrp2_drake.kernels) -------------------
#
# `servo_torque` above (and tests/test_servo.py's `dahl_step`) are the law in numpy,
# the reference; the kernels below are what the servo runs, operation for operation
# the same numbers (every operation is elementwise: no reduction, no fma;
# tests/test_servo.py compares them bit for bit). Two operations stay in numpy,
# outside the kernels: tanh and exp. numpy's float64 tanh is its own SIMD code (AVX2,
# AVX-512), which differs from the C library's (what a kernel calls) in the last bit
# for about a third of the arguments (measured on an AVX2 machine), and on AVX-512
# machines its float64 exp is its own too; so the servo computes tanh(q̇ / v_s) and
# the Dahl decay exp(-|Δq| / δ) with numpy, and the kernels take them as arrays.

# Rows of the servo's constants (`EmulatedPositionServo._constants`, one float64 row
# per parameter over the joints).
_K1, _ASYMMETRY, _K2, _K3, _K4, _K5 = 0, 1, 2, 3, 4, 5
_DEADZONE, _I_MAX, _STALL, _NO_LOAD, _LOAD_FRICTION = 6, 7, 8, 9, 10
_RESOLUTION, _WIDTH = 11, 12  # encoder quantum (0: none); hysteresis width (0: tanh)
# Rows of its index table (`EmulatedPositionServo._rows`, int64 over the joints).
_Q_ROW, _V_ROW = 0, 1  # q and v of the joint in the plant's state
_TRANSIT_ROW = 2  # its applied command in the discrete state (-1: no latency)
_U_ROW = 3  # its actuator in the plant's actuation vector


@kernel
def _np_sign(x):
    """np.sign of a float: 1, -1, 0.0 for either zero, NaN for NaN."""
    if x > 0.0:
        return 1.0
    if x < 0.0:
        return -1.0
    if x == 0.0:
        return 0.0
    return x


@kernel
def _np_maximum(a, b):
    """np.maximum(a, b) of floats: NaN if either is, b on a tie (its zero's sign)."""
    if a > b or math.isnan(a):
        return a
    return b


@kernel
def _np_minimum(a, b):
    """np.minimum(a, b) of floats: NaN if either is, b on a tie (its zero's sign)."""
    if a < b or math.isnan(a):
        return a
    return b


@kernel
def _encoder_reading(c, j, q):
    """What joint j's encoder reads of angle q: rint(q / quantum) · quantum (rint:
    half to even), q itself without quantization."""
    quantum = c[_RESOLUTION, j]
    if quantum > 0.0:
        return np.rint(q / quantum) * quantum
    return q


@kernel
def _joint_current(c, j, error, v, on):
    """servo_torque's current i (A) of joint j: position error `error` (rad), velocity
    v, driver on (`on`) or off (0)."""
    u = c[_K4, j] * error - c[_K5, j] * v
    current = _np_sign(u) * _np_maximum(abs(u) - c[_DEADZONE, j], 0.0)
    back_emf = v / c[_NO_LOAD, j]
    upper = _np_minimum(c[_I_MAX, j], c[_STALL, j] * (1.0 - back_emf))
    lower = _np_maximum(-c[_I_MAX, j], -c[_STALL, j] * (1.0 + back_emf))
    current = _np_minimum(upper, _np_maximum(lower, current))  # np.clip's numbers
    if not on:
        return 0.0
    return current


@kernel
def _joint_torque(c, j, current, v, direction):
    """servo_torque's τ (N·m) of joint j driving `current` at velocity v, in the
    direction state `direction`."""
    drive = c[_K1, j] * (1.0 + c[_ASYMMETRY, j] * direction) * current
    coulomb = c[_K3, j] + c[_LOAD_FRICTION, j] * abs(drive)
    return drive - c[_K2, j] * v - coulomb * direction


@kernel
def _servo_law(c, q_cmd, q, v, direction, enabled, torque, out):
    """The law on joint vectors (`joint_torques`, `motor_current`): out[j] = τ_j
    (`torque`) or i_j for the command q_cmd (after the latency), the joint angles q
    (through the encoder; a zero-length q: q_cmd is the position error itself), the
    velocities v and the direction states; `enabled` > 0.5 on (zero-length: all on)."""
    error_given = q.shape[0] == 0
    all_on = enabled.shape[0] == 0
    for j in range(out.shape[0]):
        error = q_cmd[j] if error_given else q_cmd[j] - _encoder_reading(c, j, q[j])
        on = all_on or enabled[j] > 0.5
        current = _joint_current(c, j, error, v[j], on)
        if torque:
            out[j] = _joint_torque(c, j, current, v[j], direction[j])
        else:
            out[j] = current


@kernel
def _encoder_readings(c, q, out):
    """out[j]: what joint j's encoder reads of q[j]
    (`EmulatedPositionServo.encoder`)."""
    for j in range(out.shape[0]):
        out[j] = _encoder_reading(c, j, q[j])


@kernel
def _command_finite(q_cmd):
    """Whether every entry of q_cmd is finite."""
    for j in range(q_cmd.shape[0]):
        if not math.isfinite(q_cmd[j]):
            return False
    return True


@kernel
def _servo_output(
    c, rows, x, q_cmd, servo_state, tanh_v, enabled, quantum, torque, out
):
    """The servo's output now (`EmulatedPositionServo._calc`, `current`): with
    `torque`, the actuation (out: the plant's actuation vector, zero where no joint
    of the servo drives), else the motor current of each joint (out: joint order).

    x: the plant's state; q_cmd: the command input; servo_state: the discrete state
    (direction states, last positions, commands in transit); tanh_v: tanh(q̇ / v_s) of
    each joint (read for the joints without hysteresis); enabled: as `_servo_law`;
    quantum: the goal's quantum (0: none). Returns False, computing nothing, if q_cmd
    is not finite."""
    if not _command_finite(q_cmd):
        return False
    if torque:
        out[:] = 0.0
    for j in range(c.shape[1]):
        command = q_cmd[j]
        if quantum > 0.0:
            command = np.rint(command / quantum) * quantum
        transit = rows[_TRANSIT_ROW, j]
        if transit >= 0:
            command = servo_state[transit]
        v = x[rows[_V_ROW, j]]
        error = command - _encoder_reading(c, j, x[rows[_Q_ROW, j]])
        on = enabled.shape[0] == 0 or enabled[j] > 0.5
        current = _joint_current(c, j, error, v, on)
        if torque:
            direction = servo_state[j] if c[_WIDTH, j] > 0.0 else tanh_v[j]
            out[rows[_U_ROW, j]] = _joint_torque(c, j, current, v, direction)
        else:
            out[j] = current
    return True


@kernel
def _dahl_exponents(c, rows, x, servo_state, out):
    """out[j] = -|q_j - q_j(last update)| / δ_j, the Dahl decay's exponent, for the
    joints with hysteresis (the others: 0)."""
    n = c.shape[1]
    for j in range(n):
        width = c[_WIDTH, j]
        if width > 0.0:
            out[j] = -abs(x[rows[_Q_ROW, j]] - servo_state[n + j]) / width
        else:
            out[j] = 0.0


@kernel
def _servo_update(c, rows, x, q_cmd, servo_state, decay, quantum, depth):
    """The servo's periodic update, in place on its discrete state (`servo_state`):
    the direction states (tests/test_servo.py's `dahl_step`'s numbers with decay =
    exp of `_dahl_exponents`; 0 without hysteresis), the last positions, and, with a
    latency (`depth` periods), the commands in transit shifted by one period with
    q_cmd (quantized to `quantum`, 0: none) entering. Returns False, changing
    nothing, if there is a latency and q_cmd is not finite."""
    n = c.shape[1]
    if depth > 0 and not _command_finite(q_cmd):
        return False
    for j in range(n):
        q = x[rows[_Q_ROW, j]]
        if c[_WIDTH, j] > 0.0:
            travel = q - servo_state[n + j]
            if travel != 0.0:  # dq == 0 (or NaN != 0: NaN, as np.where gives)
                target = _np_sign(travel)
                servo_state[j] = target + (servo_state[j] - target) * decay[j]
        else:
            servo_state[j] = 0.0
        servo_state[n + j] = q
    if depth > 0:
        # Newest first: each row moves one period back (from the oldest).
        for i in range(servo_state.shape[0] - 1, 3 * n - 1, -1):
            servo_state[i] = servo_state[i - n]
        for j in range(n):
            command = q_cmd[j]
            if quantum > 0.0:
                command = np.rint(command / quantum) * quantum
            servo_state[2 * n + j] = command
    return True


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
            "EmulatedPositionServo: extra_latency must be finite and >= 0, got "
            f"{extra_latency}"
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

    Per plant step (the output, then the update) the arithmetic is numba kernels
    (`_servo_output`, `_dahl_exponents` and `_servo_update`, on the ports' values and
    the discrete state as they are: no copy, no gather in Python), with numpy's tanh
    and exp between them; `servo_torque`'s numbers bit for bit (the comment above the
    kernels). The constructor compiles them, or loads them from numba's cache
    (`warm_up`).
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
            raise ValueError(
                f"EmulatedPositionServo: joints without actuator: {missing}"
            )
        if not period > 0:
            raise ValueError(f"EmulatedPositionServo: period must be > 0, got {period}")
        p, delays = _applied_parameters(params, joint_names, period, off, extra_latency)
        self._p = p
        self._delays = delays
        self._dahl = p["hysteresis_width"] > 0
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
        initial = (
            np.zeros(n) if initial_q_cmd is None else np.asarray(initial_q_cmd, float)
        )
        if initial.shape != (n,):
            raise ValueError(
                f"EmulatedPositionServo: initial_q_cmd has {initial.size} values, "
                f"expected {n}"
            )
        self._depth = depth
        # One discrete state group (one read and one write per update): the direction
        # state s, the joint positions of the last update (the travel that moves s),
        # and the commands in transit, newest first (depth x n).
        initial_state = np.concatenate([np.zeros(2 * n), np.tile(initial, depth)])
        self._x = int(self.DeclareDiscreteState(initial_state))
        self._last_q_rows = slice(n, 2 * n)
        self.DeclareInitializationDiscreteUpdateEvent(self._initialize)
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._update)
        self.DeclareVectorOutputPort("actuation", plant.num_actuators(), self._calc)

    def _precompute_step_constants(self, plant: MultibodyPlant) -> None:
        """What the servo's kernels need per step, packed once: one float64 array of
        the parameters (a row each, `_K1`..`_WIDTH`), one int64 table of where each
        joint's values are (`_Q_ROW`..`_U_ROW`), and the buffers of the two numpy
        operations (module comment above the kernels: tanh, exp)."""
        n, p, delays = self._n, self._p, self._delays
        constants = np.zeros((_WIDTH + 1, n))
        for row, name in (
            (_K1, "k1"),
            (_ASYMMETRY, "k1_asymmetry"),
            (_K2, "k2"),
            (_K3, "k3"),
            (_K4, "k4"),
            (_K5, "k5"),
            (_DEADZONE, "i_deadzone"),
            (_I_MAX, "i_max"),
            (_STALL, "stall_current"),
            (_NO_LOAD, "no_load_speed"),
            (_LOAD_FRICTION, "load_friction"),
            (_RESOLUTION, "encoder_resolution"),
        ):
            constants[row] = p[name]
        constants[_WIDTH] = np.where(self._dahl, p["hysteresis_width"], 0.0)
        self._constants = constants
        rows = np.zeros((_U_ROW + 1, n), dtype=np.int64)
        rows[_Q_ROW] = self._indexing.q
        rows[_V_ROW] = plant.num_positions() + self._indexing.v
        # Applied command of joint j: the transit entry of row delays[j] - 1, or
        # q_cmd itself (delay 0).
        rows[_TRANSIT_ROW] = np.where(
            delays > 0, 2 * n + (delays - 1) * n + np.arange(n), -1
        )
        rows[_U_ROW] = self._indexing.u
        self._rows = rows
        self._state_q = self._indexing.q
        self._state_v = plant.num_positions() + self._indexing.v
        self._dahl_joints = np.flatnonzero(self._dahl)
        self._any_smooth = bool(np.any(~self._dahl))
        self._any_dahl = bool(np.any(self._dahl))
        self._v_coulomb = p["v_coulomb"]
        self._tanh_v = np.zeros(n)  # tanh(q̇ / v_s) of every joint, per step
        self._decay = np.zeros(n)  # the Dahl decay of the joints with hysteresis
        # A zero-length vector: no `enabled` input (every joint on), no q (q_cmd is
        # the position error), no command (no latency), for the kernels.
        self._empty = np.zeros(0)
        self._quantum = float(self._command_resolution or 0.0)
        self._num_actuators = plant.num_actuators()
        self.warm_up()

    def warm_up(self) -> None:
        """Compiles (or loads from numba's cache) every kernel the servo calls, on
        arrays of a step's types and layouts (1-D C-contiguous float64: the inputs'
        values, the output's, the discrete state writable in an update and read-only
        in an output calc), so that `hrp2_drake.kernels.freeze()` can follow. The
        constructor calls it: the servo runs in the processes of loops that freeze
        (the in-process and bus runs), which warm their own steps only."""
        n, c = self._n, self._constants
        # The scalar kernels the others call (compiled into them, but a kernel loaded
        # from the cache leaves them uncompiled: `freeze` needs each compiled).
        _np_sign(0.0)
        _np_maximum(0.0, 0.0)
        _np_minimum(0.0, 0.0)
        _encoder_reading(c, 0, 0.0)
        _joint_current(c, 0, 0.0, 0.0, True)
        _joint_torque(c, 0, 0.0, 0.0, 0.0)
        _command_finite(np.zeros(n))
        x = np.zeros(int(self._rows[: _V_ROW + 1].max(initial=-1)) + 1)
        q_cmd = np.zeros(n)
        servo_state = np.zeros(2 * n + self._depth * n)
        read_only = servo_state.copy()
        read_only.flags.writeable = False
        out = np.zeros(self._num_actuators)
        for enabled in (self._empty, np.ones(n)):
            _servo_output(
                c,
                self._rows,
                x,
                q_cmd,
                read_only,
                self._tanh_v,
                enabled,
                0.0,
                True,
                out,
            )
            _servo_law(c, q_cmd, q_cmd, q_cmd, q_cmd, enabled, True, np.zeros(n))
        _dahl_exponents(c, self._rows, x, servo_state, np.zeros(n))
        _servo_update(c, self._rows, x, q_cmd, servo_state, np.zeros(n), 0.0, 0)
        _encoder_readings(c, q_cmd, np.zeros(n))

    @property
    def joint_names(self) -> tuple[str, ...]:
        return self._indexing.names

    def _vector(self, values) -> np.ndarray:
        """`values` (one per joint, or one for all) as a new float64 joint vector:
        the type the kernels are compiled for."""
        return np.array(np.broadcast_to(np.asarray(values, dtype=float), (self._n,)))

    def _enabled_vector(self, enabled: np.ndarray | None) -> np.ndarray:
        return self._empty if enabled is None else self._vector(enabled)

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
        v = self._vector(v)
        direction = np.tanh(v / self._v_coulomb)
        if s is not None:
            direction[self._dahl_joints] = self._vector(s)[self._dahl_joints]
        tau = np.empty(self._n)
        _servo_law(
            self._constants,
            self._vector(q_cmd),
            self._vector(q),
            v,
            direction,
            self._enabled_vector(enabled),
            True,
            tau,
        )
        return tau

    def encoder(self, q: np.ndarray) -> np.ndarray:
        """What the servo's own encoder reads of the joint angles q (rad): q
        quantized at each joint's encoder_resolution (none where it is 0)."""
        q_encoder = np.empty(self._n)
        _encoder_readings(self._constants, self._vector(q), q_encoder)
        return q_encoder

    def motor_current(
        self,
        q_cmd: np.ndarray,
        q: np.ndarray,
        v: np.ndarray,
        enabled: np.ndarray | None = None,
    ) -> np.ndarray:
        """The motor current i (A) the servo drives for the command it acts on
        (after the latency), as `joint_torques` computes it: what a servo reports as
        its present current."""
        v = self._vector(v)
        current = np.empty(self._n)
        _servo_law(
            self._constants,
            self._vector(q_cmd),
            self._vector(q),
            v,
            v,
            self._enabled_vector(enabled),
            False,
            current,
        )
        return current

    def _joint_state(self, context: Context) -> tuple[np.ndarray, np.ndarray]:
        x = self._state.Eval(context)
        return x[self._state_q], x[self._state_v]

    def _raise_not_finite(self, q_cmd: np.ndarray) -> None:
        bad = [self.joint_names[i] for i in np.flatnonzero(~np.isfinite(q_cmd))]
        raise ValueError(f"EmulatedPositionServo: q_cmd is not finite for {bad}")

    def _enabled_input(self, context: Context) -> np.ndarray:
        if self._enabled is None:
            return self._empty
        return self._enabled.Eval(context)

    def current(self, context: Context) -> np.ndarray:
        """The motor current (A) in `context` (this system's), as the servo drives it
        now: what a servo reports as its present current."""
        q_cmd = self._q_cmd.Eval(context)
        current = np.empty(self._n)
        if not _servo_output(
            self._constants,
            self._rows,
            self._state.Eval(context),
            q_cmd,
            context.get_discrete_state(self._x).get_value(),
            self._tanh_v,
            self._enabled_input(context),
            self._quantum,
            False,
            current,
        ):
            self._raise_not_finite(q_cmd)
        return current

    def _initialize(self, context: Context, state: DiscreteValues) -> None:
        # (state holds the current discrete state on entry.)
        q, _ = self._joint_state(context)
        state.get_mutable_value(self._x)[self._last_q_rows] = q

    def _update(self, context: Context, state: DiscreteValues) -> None:
        # In place on `state`, which holds the current discrete state on entry.
        x = self._state.Eval(context)
        servo_state = state.get_mutable_value(self._x)
        if self._any_dahl:
            decay = self._decay
            _dahl_exponents(self._constants, self._rows, x, servo_state, decay)
            np.exp(decay, decay)
        q_cmd = self._q_cmd.Eval(context) if self._depth else self._empty
        if not _servo_update(
            self._constants,
            self._rows,
            x,
            q_cmd,
            servo_state,
            self._decay,
            self._quantum,
            self._depth,
        ):
            self._raise_not_finite(q_cmd)

    def _calc(self, context: Context, output: BasicVector) -> None:
        x = self._state.Eval(context)
        if self._any_smooth:  # (positional out: faster than out=)
            np.tanh(x.take(self._state_v) / self._v_coulomb, self._tanh_v)
        q_cmd = self._q_cmd.Eval(context)
        if not _servo_output(
            self._constants,
            self._rows,
            x,
            q_cmd,
            context.get_discrete_state(self._x).get_value(),
            self._tanh_v,
            self._enabled_input(context),
            self._quantum,
            True,
            output.get_mutable_value(),
        ):
            self._raise_not_finite(q_cmd)
