"""SafetySupervisor: between the torque-control chain and the robot, it watches the
sensors and decides, every control period, how much of the torque chain's command the
robot gets; on any fault it hands the robot back to its position servo, bumplessly.

Sensor health (each a bit of the `fault` output, `FAULT_BITS`):
  - a NaN or infinite sample (encoders, IMU, F/T) or torque-chain command;
  - a value out of range (F/T force and torque, accelerometer, gyroscope) for
    `range_samples` consecutive samples (a sole landing gives its F/T sensor an
    impact spike of a sample or two: not a sensor's fault);
  - an encoder jump no joint can make in one period (a glitch);
  - a stale sensor: its latest sample older than `stale_time` (the `sensor_time`
    input: the stamps or sequence counters a driver sends); a noisy sensor (IMU, F/T)
    repeating its sample exactly for `stale_samples` periods (a stuck or zeroed
    reading: a live noisy sensor never repeats); without stamps, also an encoder that
    does not move for `encoder_stale_samples` periods while the reference moved (a
    heuristic: a joint at rest cannot be told from a frozen encoder, and a joint
    starting from rest can lag its reference that long);
  - the emergency stop input, and the torque controller's own fallback.

Mode: α in [0, 1] (0: position control, the robot's servo tracks q_position; 1: torque
control, the servo gets q_torque). q_cmd = α q_torque + (1 − α) q_position, computed
from the live inputs (no extra delay). α ramps at 1/ramp_time per second both ways, so
no mode switch makes a step in q_cmd: from the first period of a fault (or of the
controller's own fallback) on, q_torque is replaced by the torque chain's last healthy
offset from q_position, q_position + α (q_torque − q_position)_last, until torque
control is wanted again: neither a NaN nor the chain's jump to its own fallback reaches
the robot, and q_cmd moves with the reference while the offset ramps away. Torque
control starts at start_time and resumes once every fault has been clear for
reentry_time (at most max_reentries times: then position control stays). The emergency
stop latches: the robot holds the pose measured when it was pressed (ramping down from
torque control) until `reset_emergency_stop`.

The arithmetic is `SafetySupervisorStep`'s (no Drake: a fused controller runs it as
is), two numba kernels (`hrp2_drake.kernels`): `_supervise` (its `step`) and
`_command` (its `q_cmd`); `SafetySupervisor` is its LeafSystem shell.

.. code-block:: text

                          ┌──────────────────┐
    q_torque ────────────►│                  ├──► q_cmd
    q_position ──────────►│                  ├──► mode (α)
    q_measured ──────────►│ SafetySupervisor ├──► fault (bits)
    <sensor> (each) ─────►│                  ├──► transition ([time, bits])
    sensor_time (opt.) ──►│                  │
    e_stop (optional) ───►│                  │
    controller_fallback ─►│                  │
      (optional)          └──────────────────┘
"""

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from pydrake.systems.framework import BasicVector, Context, DiscreteValues, InputPort

from hrp2_drake.config import check_finite, moved_keys
from hrp2_drake.description.sensors import RANGE_QUANTITIES, SensorRanges
from hrp2_drake.kernels import kernel
from hrp2_drake.step import Step, StepSystem

_logger = logging.getLogger(__name__)

#: The bits of the `fault` output and of a transition's reason.
FAULT_BITS: dict[int, str] = {
    1: "encoder not finite",
    2: "sensor not finite",
    4: "sensor out of range",
    8: "encoder jump",
    16: "stale sensor",
    32: "stale encoder",
    64: "emergency stop",
    128: "torque controller fallback",
    256: "torque command not finite",
}


def describe_faults(bits: int) -> str:
    """The names of the faults in a bitmask, or "none"."""
    names = [name for bit, name in FAULT_BITS.items() if int(bits) & bit]
    return ", ".join(names) or "none"


@moved_keys(period="the robot's sensors.period (the control period)")
@dataclass
class SafetyConfig:
    """Configuration of the SafetySupervisor (its period is the control period, an
    argument of `SafetySupervisorStep`).

    Args:
        start_time: torque control may start from then (s).
        ramp_time: duration of a full position <-> torque transfer (s).
        reentry_time: how long every fault must stay clear before torque control
            resumes (s); covers the estimation window's memory of a bad sample.
        stale_samples: identical consecutive samples of a noisy sensor that mean stale
            (0: no check, for noiseless simulated sensors).
        encoder_stale_samples: periods an encoder may not move while the reference
            moves by more than encoder_motion (rad).
        encoder_motion: reference motion over encoder_stale_samples that an encoder
            must follow (rad).
        encoder_jump_speed: a joint moving faster than this between two samples is a
            glitch (rad/s).
        force_limit, torque_limit: F/T range (N, N·m, per axis); 0: the robot's
            (its description's `sensor_ranges`, `with_sensor_ranges`).
        range_samples: consecutive samples out of its range that make a sensor's
            entry faulty (1: any one sample). A sole's landing is an impact: its
            F/T sensor's reading spikes for a sample or two.
        acceleration_limit: accelerometer range (m/s², per axis); 0: the robot's.
        angular_velocity_limit: gyroscope range (rad/s, per axis); 0: the robot's.
        stale_time: a sensor whose latest sample is older than this is stale (s; the
            `sensor_time` input, the stamps a driver sends).
        max_reentries: torque control resumes after at most this many faults; the
            next one leaves the robot in position control for good (a controller that
            keeps faulting is not retried forever).
    """

    start_time: float = 0.5
    ramp_time: float = 0.05
    reentry_time: float = 0.2
    stale_samples: int = 5
    encoder_stale_samples: int = 10
    encoder_motion: float = 0.001
    encoder_jump_speed: float = 10.0
    force_limit: float = 0.0
    range_samples: int = 3
    torque_limit: float = 0.0
    acceleration_limit: float = 0.0
    angular_velocity_limit: float = 0.0
    stale_time: float = 0.0025
    max_reentries: int = 3

    def validate(self) -> None:
        where = "SafetyConfig"
        positive = (
            "ramp_time",
            "encoder_motion",
            "encoder_jump_speed",
            "stale_time",
        )
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{where}.{name}: must be finite and > 0, got {value}")
        for name in ("start_time", "reentry_time", *RANGE_LIMITS.values()):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(
                    f"{where}.{name}: must be finite and >= 0, got {value}"
                )
        if self.stale_samples == 1 or self.stale_samples < 0:
            raise ValueError(
                f"{where}.stale_samples: must be 0 or >= 2, got {self.stale_samples}"
            )
        if self.max_reentries < 0:
            raise ValueError(
                f"{where}.max_reentries: must be >= 0, got {self.max_reentries}"
            )
        if self.range_samples < 1:
            raise ValueError(
                f"{where}.range_samples: must be >= 1, got {self.range_samples}"
            )
        if self.encoder_stale_samples < 2:
            raise ValueError(
                f"{where}.encoder_stale_samples: must be >= 2, "
                f"got {self.encoder_stale_samples}"
            )


#: The sensor kinds a supervisor monitors, and their sizes.
SENSOR_KINDS: dict[str, int] = {"wrench": 6, "acceleration": 3, "angular_velocity": 3}

#: SafetyConfig's range of each quantity (`description.sensors.SensorRanges`'s
#: fields), by quantity.
RANGE_LIMITS: dict[str, str] = {
    "force": "force_limit",
    "torque": "torque_limit",
    "acceleration": "acceleration_limit",
    "angular_velocity": "angular_velocity_limit",
}
#: The quantities each sensor kind's entries measure, in entry order.
_KIND_QUANTITIES: dict[str, tuple[str, ...]] = {
    "wrench": ("torque",) * 3 + ("force",) * 3,
    "acceleration": ("acceleration",) * 3,
    "angular_velocity": ("angular_velocity",) * 3,
}


def with_sensor_ranges(
    config: SafetyConfig,
    sensors: dict[str, str],
    ranges: SensorRanges,
    where: str = "",
) -> SafetyConfig:
    """`config` with its ranges left 0 taken from the robot's (`ranges`: its
    description's `sensor_ranges`), a copy.

    Raises:
        ValueError: one line naming `sensor_ranges.<quantity>` (prefixed by
            `where`, the description's file) for a quantity a monitored sensor
            (`sensors`: {port: kind}) measures whose range neither gives.
    """
    filled = {}
    needed = {q for kind in sensors.values() for q in _KIND_QUANTITIES.get(kind, ())}
    for quantity, name in RANGE_LIMITS.items():
        if getattr(config, name) > 0:
            continue
        value = getattr(ranges, quantity)
        if value > 0:
            filled[name] = value
        elif quantity in needed:
            ports = sorted(
                p for p, k in sensors.items() if quantity in _KIND_QUANTITIES[k]
            )
            prefix = f"{where}: " if where else ""
            raise ValueError(
                f"{prefix}sensor_ranges.{quantity}: not given (nor "
                f"SafetyConfig.{name}), but the supervisor monitors {ports}: give "
                f"the sensors' rated range, {RANGE_QUANTITIES[quantity]}"
            )
    return replace(config, **filled)


# The scalar rows of the `memory` state: [time every fault has been clear (s), faults
# since start_time, torque wanted (ramping up or in torque), e-stop pressed].
_CLEAR_ROW, _FAULTS_ROW, _WANT_ROW, _PRESSED_ROW = range(4)

# Where the step's named arrays start in its flat state (their declaration order in
# `SafetySupervisorStep.__init__`, checked there): mode, fault, transition (2), memory.
# The memory's blocks follow its 4 scalar rows: the held pose (n), the last healthy
# offset (n), the last samples (n + s), their repeat counts (n + s), the anchors (n),
# the sensors' consecutive samples out of range (s).
_MODE, _FAULT, _TRANSITION, _MEMORY = 0, 1, 2, 4
_HOLD = _MEMORY + 4

# The rows of the step's constants (`SafetySupervisorStep._constants`, packed once at
# construction), then the range of each monitored sensor entry (s rows).
(
    _C_PERIOD,
    _C_RAMP,
    _C_START,
    _C_REENTRY,
    _C_MAX_REENTRIES,
    _C_STALE_SAMPLES,
    _C_STALE_COUNT,
    _C_JUMP,
    _C_ENCODER_STALE,
    _C_ENCODER_MOTION,
    _C_STALE_TIME,
    _C_STAMPS,
    _C_RANGE_SAMPLES,
    _C_LIMITS,
) = range(14)

#: What a kernel gets for an input that is not connected (None): no entries.
_ABSENT = np.zeros(0)


# Whole: one compiled pass on the tick's arrays; a split costs calls (scripts/bench.py)
@kernel
def _supervise(
    t,
    state,
    constants,
    q_torque,
    q_position,
    q_measured,
    sensors,
    e_stop,
    controller_fallback,
    sensor_time,
    stamped,
):
    """`SafetySupervisorStep.step`'s arithmetic, in place on `state` (the step's flat
    state): the health checks, the mode and the memory; returns the fault bits when a
    fault starts this period, else 0. `e_stop`, `controller_fallback`: 1-arrays, or no
    entries when not connected; `stamped`: whether `sensor_time` was given.

    Every value is computed as the numpy code before it did, operation for operation
    (bit for bit). A finiteness test is, as before, that of a sum (any NaN or inf, or
    finite entries whose sum overflows, |x| ~ 1e308): a loop here, BLAS's dot before,
    which can differ in order only at that overflow edge."""
    n = q_measured.shape[0]
    s = sensors.shape[0]
    if (
        q_torque.shape[0] != n
        or q_position.shape[0] != n
        or state.shape[0] != _HOLD + 5 * n + 3 * s
        or constants.shape[0] != _C_LIMITS + s
        or (stamped and sensor_time.shape[0] != int(constants[_C_STAMPS]))
    ):
        raise ValueError("SafetySupervisorStep.step: an input of the wrong size")
    last_torque = _HOLD + n
    last = last_torque + n  # [q_measured (n); sensors (s)]
    count = last + n + s
    anchor = count + n + s
    outside = anchor + n  # (s)
    period = constants[_C_PERIOD]
    previous_bits = int(state[_FAULT])
    alpha = state[_MODE]
    faults = state[_MEMORY + _FAULTS_ROW]
    # ---- Sensor health (bits 1, 2, 4, 8, 16, 32); each memory row read before it
    # is written. Which samples are finite: [q; sensors] at once, the usual case.
    bits = 0
    q_sum = 0.0
    for i in range(n):
        q_sum += q_measured[i]
    total = q_sum
    for j in range(s):
        total += sensors[j]
    q_finite = True
    sensors_finite = True
    if not math.isfinite(total):
        sensors_sum = 0.0
        for j in range(s):
            sensors_sum += sensors[j]
        q_finite = math.isfinite(q_sum)
        sensors_finite = math.isfinite(sensors_sum)
        if not q_finite:
            bits |= 1
        if not sensors_finite:
            bits |= 2
    if q_finite:
        # Jumps; each encoder's count of identical consecutive samples (count + 1 or
        # 0: count·same + same before) and its anchor (q_position where it changed);
        # without the drivers' stamps, a frozen encoder (the reference moved by more
        # than encoder_motion while the encoder stayed for encoder_stale_samples).
        jump = constants[_C_JUMP]
        encoder_stale = constants[_C_ENCODER_STALE]
        motion = constants[_C_ENCODER_MOTION]
        for i in range(n):
            q = q_measured[i]
            previous = state[last + i]
            if abs(q - previous) > jump:
                bits |= 8
            if q == previous:
                repeats = state[count + i] + 1.0
            else:
                repeats = 0.0
                state[anchor + i] = q_position[i]
            state[count + i] = repeats
            if (
                not stamped
                and repeats >= encoder_stale
                and abs(q_position[i] - state[anchor + i]) > motion
            ):
                bits |= 32
            state[last + i] = q
    if sensors_finite:
        # Range (for range_samples samples in a row), and a noisy sensor repeating
        # its sample (stale_samples; 0: no check).
        stale_check = constants[_C_STALE_SAMPLES] != 0
        stale_count = constants[_C_STALE_COUNT]
        range_samples = constants[_C_RANGE_SAMPLES]
        for j in range(s):
            value = sensors[j]
            row = last + n + j
            if value == state[row]:
                repeats = state[count + n + j] + 1.0
            else:
                repeats = 0.0
            state[count + n + j] = repeats
            if abs(value) > constants[_C_LIMITS + j]:
                over = state[outside + j] + 1.0
            else:
                over = 0.0
            state[outside + j] = over
            if over >= range_samples:
                bits |= 4
            if stale_check and repeats >= stale_count:
                bits |= 16
            state[row] = value
    if stamped:
        stale_time = constants[_C_STALE_TIME]
        for k in range(sensor_time.shape[0]):
            if t - sensor_time[k] > stale_time:
                bits |= 16
    # ---- The e-stop, the controller's fallback, the torque chain's command.
    if e_stop.shape[0] > 0 and e_stop[0] > 0:
        bits |= 64
    if controller_fallback.shape[0] > 0 and controller_fallback[0] > 0:
        bits |= 128
    torque_sum = 0.0
    for i in range(n):
        torque_sum += q_torque[i]
    torque_finite = math.isfinite(torque_sum)
    if not torque_finite:
        bits |= 256
    state[_FAULT] = float(bits)
    clear = state[_MEMORY + _CLEAR_ROW] + period if bits == 0 else 0.0
    state[_MEMORY + _CLEAR_ROW] = clear
    # E-stop (latched): hold the pose measured when it was pressed (the last finite
    # one if this one is not).
    held = state[_MEMORY + _PRESSED_ROW] != 0
    if bits & 64 and not held:
        if bits & 1:
            for i in range(n):
                state[_HOLD + i] = state[last + i]
        else:
            for i in range(n):
                state[_HOLD + i] = q_measured[i]
        state[_MEMORY + _PRESSED_ROW] = 1.0
        held = True
    # Mode: torque from start_time while healthy; after a fault, only once every fault
    # has been clear for reentry_time.
    running = t + 0.5 * period >= constants[_C_START]
    if running and bits != 0 and previous_bits == 0:
        faults += 1.0
        state[_MEMORY + _FAULTS_ROW] = faults
    want_torque = (
        running
        and bits == 0
        and not held
        and faults <= constants[_C_MAX_REENTRIES]
        and (faults == 0 or clear >= constants[_C_REENTRY])
    )
    state[_MEMORY + _WANT_ROW] = 1.0 if want_torque else 0.0
    # The last command of a healthy torque chain in use: what a ramp down starts from
    # (once a fault is seen, the chain's own output is not trusted).
    if want_torque and torque_finite:
        for i in range(n):
            state[last_torque + i] = q_torque[i] - q_position[i]
    ramp = constants[_C_RAMP]
    if want_torque:
        new_alpha = alpha + ramp
        if not new_alpha < 1.0:  # min(1.0, α + ramp)
            new_alpha = 1.0
    else:
        new_alpha = alpha - ramp
        if not new_alpha > 0.0:  # max(0.0, α − ramp)
            new_alpha = 0.0
    new_fault = 0
    if bits != 0 and previous_bits == 0:
        state[_TRANSITION] = t
        state[_TRANSITION + 1] = float(bits)
        new_fault = bits
    elif want_torque and alpha == 0 and new_alpha > 0:
        state[_TRANSITION] = t
        state[_TRANSITION + 1] = 0.0
    state[_MODE] = new_alpha
    return new_fault


@kernel
def _command(state, q_torque, q_position, controller_fallback, out):
    """`SafetySupervisorStep.q_cmd`'s arithmetic into `out` (elementwise, bit for bit
    the numpy code's; the finiteness of q_torque tested on its sum, as in
    `_supervise`). `controller_fallback`: a 1-array, or no entries when not
    connected."""
    n = q_torque.shape[0]
    if q_position.shape[0] != n or out.shape[0] != n or state.shape[0] < _HOLD + 2 * n:
        raise ValueError("SafetySupervisorStep.q_cmd: an input of the wrong size")
    last_torque = _HOLD + n
    alpha = state[_MODE]
    pressed = state[_MEMORY + _PRESSED_ROW] > 0
    if alpha <= 0.0:
        if pressed:
            for i in range(n):
                out[i] = state[_HOLD + i]
        else:
            for i in range(n):
                out[i] = q_position[i]
        return
    fault = state[_FAULT] > 0
    fallback = controller_fallback.shape[0] > 0 and controller_fallback[0] > 0
    wanted = state[_MEMORY + _WANT_ROW] > 0
    torque_sum = 0.0
    for i in range(n):
        torque_sum += q_torque[i]
    if fault or fallback or not wanted or not math.isfinite(torque_sum):
        # The torque chain's last healthy offset from the reference, which the ramp
        # takes to zero: q_cmd moves with the reference, bumplessly.
        for i in range(n):
            position = state[_HOLD + i] if pressed else q_position[i]
            out[i] = state[last_torque + i] * alpha + position
        return
    rest = 1.0 - alpha
    for i in range(n):
        position = state[_HOLD + i] if pressed else q_position[i]
        out[i] = q_torque[i] * alpha + position * rest


class SafetySupervisorStep(Step):
    """The supervisor's per-tick arithmetic (module docstring), without Drake: the
    numba kernels `_supervise` (`step`) and `_command` (`q_cmd`) on the step's flat
    state and its constants, packed once here.

    Args:
        num_joints: n, the size of q_torque, q_position, q_measured and q_cmd.
        sensors: name -> kind of each monitored sensor ("wrench" (6: torque then
            force), "acceleration" (3) or "angular_velocity" (3)); `step` reads
            them as one flat array, concatenated in this order.
        config: the SafetyConfig.
        period: the control period (s): one `step` per period.
        num_sensor_stamps: the size of the `sensor_time` array (the time of each
            sensor's latest sample, s) when one is given.

    State (`Step`): `mode` (1, α), `fault` (1, the bits of the last period, see
    FAULT_BITS), `transition` (2, [time (s), bits] of the last switch: bits 0 for a
    ramp up), and `memory` (4 + 5 n + 3 s, s the sensors' total size): [time clear
    (s), faults since start_time, torque wanted, e-stop pressed; the e-stop's held
    pose (n, rad); q_torque − q_position of the last healthy period (n, rad); the
    last samples [q_measured (n); sensors (s)]; how many periods each has repeated
    (n + s); q_position when each encoder stopped (n, rad); how many samples in a row
    each sensor entry has been out of its range (s)].
    """

    def __init__(
        self,
        num_joints: int,
        sensors: dict[str, str],
        config: SafetyConfig,
        period: float,
        num_sensor_stamps: int = 0,
    ):
        super().__init__()
        config.validate()
        check_finite(period, "SafetySupervisor: period (s)", 0.0)
        unknown = {k for k in sensors.values() if k not in SENSOR_KINDS}
        if unknown:
            raise ValueError(
                f"SafetySupervisor: unknown sensor kinds {sorted(unknown)}"
            )
        self._config = config
        self._n = n = num_joints
        self._sensor_size = sensor_size = sum(SENSOR_KINDS[k] for k in sensors.values())
        self._num_stamps = num_sensor_stamps
        # The range of every monitored entry, in input order (0: the robot's, not
        # filled in: `with_sensor_ranges`).
        for kind in dict.fromkeys(sensors.values()):
            for quantity in dict.fromkeys(_KIND_QUANTITIES[kind]):
                name = RANGE_LIMITS[quantity]
                if not getattr(config, name) > 0:
                    raise ValueError(
                        f"SafetyConfig.{name}: 0 (the robot's range) but not filled "
                        "in: give it, or the robot's sensor_ranges "
                        "(with_sensor_ranges)"
                    )
        limits = [
            getattr(config, RANGE_LIMITS[quantity])
            for kind in sensors.values()
            for quantity in _KIND_QUANTITIES[kind]
        ]
        # The kernel's constants, in the rows _C_* name (the products and quotients as
        # the numpy code formed them).
        constants = np.zeros(_C_LIMITS + sensor_size)
        constants[_C_PERIOD] = period
        constants[_C_RAMP] = period / config.ramp_time
        constants[_C_START] = config.start_time
        constants[_C_REENTRY] = config.reentry_time
        constants[_C_MAX_REENTRIES] = config.max_reentries
        constants[_C_STALE_SAMPLES] = config.stale_samples
        constants[_C_STALE_COUNT] = config.stale_samples - 1.0
        constants[_C_JUMP] = config.encoder_jump_speed * period
        constants[_C_ENCODER_STALE] = float(config.encoder_stale_samples)
        constants[_C_ENCODER_MOTION] = config.encoder_motion
        constants[_C_STALE_TIME] = config.stale_time
        constants[_C_STAMPS] = num_sensor_stamps
        constants[_C_RANGE_SAMPLES] = float(config.range_samples)
        constants[_C_LIMITS:] = limits
        self._constants = constants
        size = n + sensor_size  # the monitored samples, [q_measured; sensors]
        rows = _layout([0, 0, 0, 0, n, n, size, size, n])
        self._hold_rows, self._last_torque_rows = rows[4], rows[5]
        self._last_rows, self._count_rows, self._anchor_rows = rows[6:]
        end = self._anchor_rows.stop
        self._outside_rows = slice(end, end + sensor_size)
        self._declare("mode", 0.0)
        self._declare("fault", 0.0)
        self._declare("transition", np.zeros(2))
        self._declare("memory", np.zeros(self._outside_rows.stop))
        self._finalize()
        # The kernels' layout of the state (_MODE, ...): the declarations above.
        names = ("mode", "fault", "transition", "memory")
        starts = [self.rows(name).start for name in names]
        if (
            starts != [_MODE, _FAULT, _TRANSITION, _MEMORY]
            or self._hold_rows.start != 4
        ):
            raise AssertionError("SafetySupervisorStep: the state layout changed")

    def _views_changed(self) -> None:
        memory, n = self.memory, self._n
        self._hold = memory[self._hold_rows]
        self._last_torque = memory[self._last_torque_rows]
        self._last = memory[self._last_rows]
        self._count = memory[self._count_rows]
        self._anchor = memory[self._anchor_rows]
        self._last_q = self._last[:n]

    def config(self) -> SafetyConfig:
        return self._config

    @property
    def num_joints(self) -> int:
        return self._n

    @property
    def sensor_size(self) -> int:
        """The size of the flat `sensors` array (the monitored sensors' sizes)."""
        return self._sensor_size

    def emergency_stopped(self) -> bool:
        """True once the emergency stop was pressed (it latches)."""
        return bool(self.memory[_PRESSED_ROW] > 0)

    def reset_emergency_stop(self) -> None:
        """Releases a latched emergency stop (see SafetySupervisor's)."""
        self.memory[_PRESSED_ROW] = 0.0

    def initialize(
        self, q_measured: np.ndarray, q_position: np.ndarray, sensors: np.ndarray
    ) -> None:
        """At start-up: the first samples (q_measured (n, rad), the flat `sensors`)
        and the reference (q_position (n, rad)) become the memory's last samples and
        encoder anchors (no jump, no repeat counted against them)."""
        self._last_q[:] = q_measured
        self._anchor[:] = q_position
        self._last[self._n :] = sensors

    def warm_up(self) -> None:
        """Compiles (or loads from numba's cache) `_supervise` and `_command` on arrays
        of a tick's types (1-D C-contiguous float64: a state vector's copy, zero
        inputs), the state left as it was."""
        state = self._state.copy()
        zeros = np.zeros(self._n)
        _supervise(
            0.0,
            state,
            self._constants,
            zeros,
            zeros,
            zeros,
            np.zeros(self._sensor_size),
            np.zeros(1),
            np.zeros(1),
            np.zeros(self._num_stamps),
            True,
        )
        _command(state, zeros, zeros, np.zeros(1), np.zeros(self._n))

    def step(
        self,
        t: float,
        q_torque: np.ndarray,
        q_position: np.ndarray,
        q_measured: np.ndarray,
        sensors: np.ndarray,
        e_stop: np.ndarray | None = None,
        controller_fallback: np.ndarray | None = None,
        sensor_time: np.ndarray | None = None,
    ) -> int:
        """One control period at time t (s): the health checks, mode and memory, in
        place on the state (the kernel `_supervise`).

        Args:
            q_torque, q_position, q_measured: n joint positions each (rad): the
                torque chain's command, the reference, the encoders.
            sensors: the monitored sensors' samples, one flat array in the order of
                the constructor's `sensors` (N, N·m, m/s², rad/s).
            e_stop, controller_fallback: 1-arrays (> 0: pressed, fallen back), or
                None when not connected.
            sensor_time: the time of each sensor's latest sample (s), or None
                (no stamps: the frozen-encoder heuristic instead).

        Every array is a 1-D float64 array (C-contiguous: what `warm_up` compiles
        for).

        Returns:
            The fault bits when a fault starts this period (to be reported by the
            caller: the step never logs), else 0.
        """
        return _supervise(
            t,
            self._state,
            self._constants,
            q_torque,
            q_position,
            q_measured,
            sensors,
            _ABSENT if e_stop is None else e_stop,
            _ABSENT if controller_fallback is None else controller_fallback,
            _ABSENT if sensor_time is None else sensor_time,
            sensor_time is not None,
        )

    def q_cmd(
        self,
        q_torque: np.ndarray,
        q_position: np.ndarray,
        controller_fallback: np.ndarray | None,
        out: np.ndarray,
    ) -> np.ndarray:
        """The position command (n, rad) into `out` (not one of the inputs), from the
        state and the live inputs (no extra delay): α q_torque + (1 − α) q_position,
        or, while torque control is not wanted (a fault, the controller's fallback, a
        non-finite q_torque, a ramp down), q_position + α × the last healthy offset;
        the e-stop's held pose replaces q_position (the kernel `_command`). Returns
        `out`."""
        _command(
            self._state,
            q_torque,
            q_position,
            _ABSENT if controller_fallback is None else controller_fallback,
            out,
        )
        return out


class SafetySupervisor(StepSystem):
    """The safety supervisor (module docstring): the LeafSystem shell of a
    `SafetySupervisorStep` (its arguments).

    Inputs: q_torque, q_position, q_measured (n each, rad), one port per monitored
    sensor (named after it), e_stop (1, optional), controller_fallback (1,
    optional), sensor_time (num_sensor_stamps, s; only if num_sensor_stamps > 0).
    Outputs: q_cmd (n, rad), mode, fault, transition: this tick's (direct
    feedthrough, `StepSystem`).
    """

    def __init__(
        self,
        num_joints: int,
        sensors: dict[str, str],
        config: SafetyConfig,
        period: float,
        num_sensor_stamps: int = 0,
        lead: float = 0.0,
    ):
        """The arguments of `SafetySupervisorStep`; `lead`: the samples arrive this
        long (s) before each multiple of the period (`StepSystem`: the commits follow
        the sampler)."""
        super().__init__()
        step = SafetySupervisorStep(
            num_joints, sensors, config, period, num_sensor_stamps
        )
        n = num_joints
        self._q_torque = self.DeclareVectorInputPort("q_torque", n)
        self._q_position = self.DeclareVectorInputPort("q_position", n)
        self._q_measured = self.DeclareVectorInputPort("q_measured", n)
        sensor_ports = [
            self.DeclareVectorInputPort(name, SENSOR_KINDS[kind])
            for name, kind in sensors.items()
        ]
        self._e_stop = self.DeclareVectorInputPort("e_stop", 1)
        self._controller_fallback = self.DeclareVectorInputPort(
            "controller_fallback", 1
        )
        self._sensor_time = (
            self.DeclareVectorInputPort("sensor_time", num_sensor_stamps)
            if num_sensor_stamps
            else None
        )
        self._declare_step_state(step)
        self.DeclareInitializationDiscreteUpdateEvent(self._initialize)
        self._declare_commit(period, lead)
        self.DeclareVectorOutputPort(
            "q_cmd",
            n,
            self._calc_q_cmd,
            prerequisites_of_calc={
                self._ticked.ticket(),
                self._q_torque.ticket(),
                self._q_position.ticket(),
                self._controller_fallback.ticket(),
            },
        )
        for name in ("mode", "fault", "transition"):
            self._declare_step_output(name)
        # The monitored sensors' samples, gathered from their ports every period
        # (the step's flat `sensors`), and a row of it per port.
        self._sensor_values = np.zeros(step.sensor_size)
        ends = np.cumsum([SENSOR_KINDS[kind] for kind in sensors.values()])
        self._sensor_rows = [
            (port, self._sensor_values[end - port.size() : end])
            for port, end in zip(sensor_ports, ends)
        ]
        self._mode_group = self.step_group("mode")
        self._memory_group = self.step_group("memory")

    def config(self) -> SafetyConfig:
        return self._step.config()

    def mode(self, context: Context) -> float:
        """α (0: position control, 1: torque control)."""
        return float(context.get_discrete_state(self._mode_group).get_value()[0])

    def emergency_stopped(self, context: Context) -> bool:
        """True once the emergency stop was pressed (it latches)."""
        memory = context.get_discrete_state(self._memory_group).get_value()
        return bool(memory[_PRESSED_ROW] > 0)

    def reset_emergency_stop(self, context: Context) -> None:
        """Releases a latched emergency stop: a deliberate act (the position command
        returns from the held pose to q_position at once); torque control may resume
        after reentry_time."""
        memory = context.get_mutable_discrete_state(self._memory_group)
        memory.get_mutable_value()[_PRESSED_ROW] = 0.0

    # ---------------------------------------------------------------- updates

    def _gather_sensors(self, context: Context) -> np.ndarray:
        for port, row in self._sensor_rows:
            row[:] = port.Eval(context)
        return self._sensor_values

    def _initialize(self, context: Context, state: DiscreteValues) -> None:
        # (state holds the current discrete state on entry.)
        self._load(state)
        self._step.initialize(
            self._q_measured.Eval(context),
            self._q_position.Eval(context),
            self._gather_sensors(context),
        )
        self._store(state)

    def _tick(self, context: Context, t: float) -> None:
        new_fault = self._step.step(
            t,
            self._q_torque.Eval(context),
            self._q_position.Eval(context),
            self._q_measured.Eval(context),
            self._gather_sensors(context),
            _optional(self._e_stop, context),
            _optional(self._controller_fallback, context),
            _optional(self._sensor_time, context),
        )
        if new_fault:
            _logger.warning(
                "SafetySupervisor %s: fault at t = %.6g s (%s): to position control",
                self.GetSystemPathname(),
                t,
                describe_faults(new_fault),
            )

    # ----------------------------------------------------------------- output

    def _calc_q_cmd(self, context: Context, output: BasicVector) -> None:
        # The command of this tick: from the state after it.
        self._step.state[:] = self.ticked(context)
        self._step.q_cmd(
            self._q_torque.Eval(context),
            self._q_position.Eval(context),
            _optional(self._controller_fallback, context),
            output.get_mutable_value(),
        )


def _optional(port: InputPort | None, context: Context) -> np.ndarray | None:
    """The value of an optional input port, None when absent or not connected."""
    if port is None or not port.HasValue(context):
        return None
    return port.Eval(context)


def _layout(sizes: Sequence[int]) -> list[int | slice]:
    """Consecutive rows of a vector: an index for each size 0 (a scalar), a slice of
    that many rows for the others."""
    out, start = [], 0
    for size in sizes:
        out.append(start if size == 0 else slice(start, start + size))
        start += max(size, 1)
    return out


def supervisor_sensors(wrenches: Sequence[str], imu: bool = True) -> dict[str, str]:
    """The station's monitored sensor ports: the IMU (if any) and the given F/T
    sensors."""
    out = {}
    if imu:
        out = {
            "imu_linear_acceleration": "acceleration",
            "imu_angular_velocity": "angular_velocity",
        }
    out |= {f"wrench_{name}": "wrench" for name in wrenches}
    return out
