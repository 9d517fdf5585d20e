"""SafetySupervisor: between the torque-control chain and the robot, it watches the
sensors and decides, every control period, how much of the torque chain's command the
robot gets; on any fault it hands the robot back to its position servo, bumplessly.

Sensor health (each a bit of the `fault` output, `FAULT_BITS`):
  - a NaN or infinite sample (encoders, IMU, F/T) or torque-chain command;
  - a value out of range (F/T force and torque, accelerometer, gyroscope);
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
offset from q_position, q_position + α (q_torque − q_position)_last, until torque control
is wanted again: neither a NaN nor the chain's jump to its own fallback reaches the
robot, and q_cmd moves with the reference while the offset ramps away. Torque control starts at start_time and resumes once every
fault has been clear for reentry_time (at most max_reentries times: then position
control stays). The emergency stop latches: the robot holds the pose
measured when it was pressed (ramping down from torque control) until
`reset_emergency_stop`.

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
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from pydrake.systems.framework import BasicVector, Context, DiscreteValues

from hrp2_drake.simulation import WitnessFreeLeafSystem

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


@dataclass
class SafetyConfig:
    """Configuration of the SafetySupervisor.

    Args:
        period: control period (s).
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
        force_limit, torque_limit: F/T range (N, N·m).
        acceleration_limit: accelerometer range (m/s²).
        angular_velocity_limit: gyroscope range (rad/s).
        stale_time: a sensor whose latest sample is older than this is stale (s; the
            `sensor_time` input, the stamps a driver sends).
        max_reentries: torque control resumes after at most this many faults; the
            next one leaves the robot in position control for good (a controller that
            keeps faulting is not retried forever).
    """

    period: float = 0.001
    start_time: float = 0.5
    ramp_time: float = 0.05
    reentry_time: float = 0.2
    stale_samples: int = 5
    encoder_stale_samples: int = 10
    encoder_motion: float = 0.001
    encoder_jump_speed: float = 10.0
    force_limit: float = 2000.0
    torque_limit: float = 300.0
    acceleration_limit: float = 100.0
    angular_velocity_limit: float = 20.0
    stale_time: float = 0.0025
    max_reentries: int = 3

    def validate(self) -> None:
        where = "SafetyConfig"
        positive = (
            "period", "ramp_time", "encoder_motion", "encoder_jump_speed",
            "force_limit", "torque_limit", "acceleration_limit", "angular_velocity_limit",
            "stale_time",
        )
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{where}.{name}: must be finite and > 0, got {value}")
        for name in ("start_time", "reentry_time"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{where}.{name}: must be finite and >= 0, got {value}")
        if self.stale_samples == 1 or self.stale_samples < 0:
            raise ValueError(f"{where}.stale_samples: must be 0 or >= 2, got {self.stale_samples}")
        if self.max_reentries < 0:
            raise ValueError(f"{where}.max_reentries: must be >= 0, got {self.max_reentries}")
        if self.encoder_stale_samples < 2:
            raise ValueError(
                f"{where}.encoder_stale_samples: must be >= 2, got {self.encoder_stale_samples}"
            )


class SafetySupervisor(WitnessFreeLeafSystem):
    """The safety supervisor (module docstring).

    Args:
        num_joints: n, the size of q_torque, q_position, q_measured and q_cmd.
        sensors: name -> kind of each monitored sensor input ("wrench" (6: torque then
            force), "acceleration" (3) or "angular_velocity" (3)); the input ports are
            named after them.
        config: the SafetyConfig.
        num_sensor_stamps: the size of the optional `sensor_time` input (the time of
            each sensor's latest sample); 0: no such input.
    """

    _KINDS = {"wrench": 6, "acceleration": 3, "angular_velocity": 3}

    def __init__(
        self,
        num_joints: int,
        sensors: dict[str, str],
        config: SafetyConfig,
        num_sensor_stamps: int = 0,
    ):
        super().__init__()
        config.validate()
        unknown = {k for k in sensors.values() if k not in self._KINDS}
        if unknown:
            raise ValueError(f"SafetySupervisor: unknown sensor kinds {sorted(unknown)}")
        self._config = config
        self._n = n = num_joints
        self._q_torque = self.DeclareVectorInputPort("q_torque", n)
        self._q_position = self.DeclareVectorInputPort("q_position", n)
        self._q_measured = self.DeclareVectorInputPort("q_measured", n)
        self._sensors = [
            (name, kind, self.DeclareVectorInputPort(name, self._KINDS[kind]))
            for name, kind in sensors.items()
        ]
        self._e_stop = self.DeclareVectorInputPort("e_stop", 1)
        self._controller_fallback = self.DeclareVectorInputPort("controller_fallback", 1)
        self._sensor_time = (
            self.DeclareVectorInputPort("sensor_time", num_sensor_stamps)
            if num_sensor_stamps
            else None
        )
        sensor_size = sum(self._KINDS[k] for k in sensors.values())
        # The range of every monitored entry, in input order.
        ranges = {
            "wrench": [config.torque_limit] * 3 + [config.force_limit] * 3,
            "acceleration": [config.acceleration_limit] * 3,
            "angular_velocity": [config.angular_velocity_limit] * 3,
        }
        self._sensor_limits = np.array(
            [limit for kind in sensors.values() for limit in ranges[kind]]
        )
        # State: the three outputs, and one group for everything else (one accessor
        # per update, views on its rows): [clear time, faults since start_time,
        # torque wanted (ramping up or in torque), e-stop pressed; the e-stop's held
        # pose (n); q_torque − q_position of the last healthy period (n); the last
        # samples [q_measured (n); monitored sensors]; how many periods each has
        # repeated (same layout); q_position when each encoder stopped (n)].
        self._alpha = self.DeclareDiscreteState(1)
        self._fault = self.DeclareDiscreteState(1)
        self._transition = self.DeclareDiscreteState(2)
        size = n + sensor_size  # the monitored samples, [q_measured; sensors]
        (
            self._clear_row,
            self._faults_row,
            self._want_row,
            self._pressed_row,
            self._hold_rows,
            self._last_torque_rows,
            self._last_rows,
            self._count_rows,
            self._anchor_rows,
        ) = _layout([0, 0, 0, 0, n, n, size, size, n])
        self._memory = self.DeclareDiscreteState(self._anchor_rows.stop)
        self.DeclareInitializationDiscreteUpdateEvent(self._initialize)
        self.DeclarePeriodicDiscreteUpdateEvent(config.period, 0.0, self._update)
        self.DeclareVectorOutputPort(
            "q_cmd", n, self._calc_q_cmd,
            prerequisites_of_calc={
                self.xd_ticket(),
                self._q_torque.ticket(),
                self._q_position.ticket(),
                self._controller_fallback.ticket(),
            },
        )
        self.DeclareStateOutputPort("mode", self._alpha)
        self.DeclareStateOutputPort("fault", self._fault)
        self.DeclareStateOutputPort("transition", self._transition)
        # Per period: plain ints for DiscreteValues (its cheapest accessors), and one
        # buffer for the monitored samples, [q_measured; sensors in input order].
        self._alpha_group = int(self._alpha)
        self._fault_group = int(self._fault)
        self._transition_group = int(self._transition)
        self._memory_group = int(self._memory)
        self._samples = np.zeros(size)
        self._q_values = self._samples[:n]
        self._sensor_values = self._samples[n:]
        ends = n + np.cumsum([self._KINDS[kind] for kind in sensors.values()])
        self._sensor_rows = [
            (port, self._samples[end - self._KINDS[kind] : end])
            for (_, kind, port), end in zip(self._sensors, ends)
        ]
        self._ones_n = np.ones(n)
        self._ones_sensors = np.ones(sensor_size)
        self._ones_samples = np.ones(size)
        # The thresholds as arrays (numpy compares two arrays faster than an array
        # and a Python float).
        self._jump_limit = np.full(n, config.encoder_jump_speed * config.period)
        self._stale_count = np.full(sensor_size, config.stale_samples - 1.0)
        self._stale_time = np.full(num_sensor_stamps, config.stale_time)

    def config(self) -> SafetyConfig:
        return self._config

    def mode(self, context: Context) -> float:
        return float(context.get_discrete_state(self._alpha).get_value()[0])

    def emergency_stopped(self, context: Context) -> bool:
        """True once the emergency stop was pressed (it latches)."""
        memory = context.get_discrete_state(self._memory).get_value()
        return bool(memory[self._pressed_row] > 0)

    def reset_emergency_stop(self, context: Context) -> None:
        """Releases a latched emergency stop: a deliberate act (the position command
        returns from the held pose to q_position at once); torque control may resume
        after reentry_time."""
        memory = context.get_mutable_discrete_state(self._memory).get_mutable_value()
        memory[self._pressed_row] = 0.0

    # ---------------------------------------------------------------- updates

    def _initialize(self, context: Context, state: DiscreteValues) -> None:
        # (state holds the current discrete state on entry.)
        memory = state.get_mutable_value(self._memory_group)
        n = self._n
        memory[self._last_rows][:n] = self._q_measured.Eval(context)
        memory[self._anchor_rows] = self._q_position.Eval(context)
        for port, row in self._sensor_rows:
            row[:] = port.Eval(context)
        memory[self._last_rows][n:] = self._sensor_values

    def _health(
        self, context: Context, memory: np.ndarray, q_position: np.ndarray
    ) -> int:
        """The fault bits of this period; updates the sample memory (rows of `memory`,
        the state being updated, read before they are written)."""
        c = self._config
        n = self._n
        bits = 0
        samples = self._samples
        self._q_values[:] = self._q_measured.Eval(context)
        for port, row in self._sensor_rows:
            row[:] = port.Eval(context)
        last = memory[self._last_rows]
        stamped = self._sensor_time is not None and self._sensor_time.HasValue(context)
        # Which samples to remember: the finite parts ([q; sensors] at once when all
        # of it is, the usual case).
        if math.isfinite(samples.dot(self._ones_samples)):
            rows = slice(None)
        else:
            q_finite = math.isfinite(self._q_values.dot(self._ones_n))
            sensors_finite = math.isfinite(self._sensor_values.dot(self._ones_sensors))
            bits |= (0 if q_finite else 1) | (0 if sensors_finite else 2)
            rows = slice(0 if q_finite else n, None if sensors_finite else n)
        q_finite = not bits & 1
        if q_finite and np.count_nonzero(
            np.abs(self._q_values - last[:n]) > self._jump_limit
        ):
            bits |= 8
        # Each sample's count of identical consecutive samples:
        # count = where(same, count + 1, 0), in place.
        same = samples[rows] == last[rows]
        count = memory[self._count_rows][rows]
        count *= same
        count += same
        if q_finite:
            # Frozen encoder: unchanged while the reference moved.
            anchor = memory[self._anchor_rows]
            anchor[:] = np.where(same[:n], anchor, q_position)
            # Only without the drivers' stamps: a joint starting to move from rest
            # (latency, dead zone, stiction) can stay on its count for several periods
            # while its reference moves away.
            if not stamped and np.count_nonzero(
                (memory[self._count_rows][:n] >= c.encoder_stale_samples)
                & (np.abs(q_position - anchor) > c.encoder_motion)
            ):
                bits |= 32
        if self._sensors and not bits & 2:
            if np.count_nonzero(np.abs(self._sensor_values) > self._sensor_limits):
                bits |= 4
            if c.stale_samples and np.count_nonzero(
                memory[self._count_rows][n:] >= self._stale_count
            ):
                bits |= 16
        last[rows] = samples[rows]
        if stamped:
            age = context.get_time() - self._sensor_time.Eval(context)
            if np.count_nonzero(age > self._stale_time):
                bits |= 16
        if self._e_stop.HasValue(context) and self._e_stop.Eval(context)[0] > 0:
            bits |= 64
        if (
            self._controller_fallback.HasValue(context)
            and self._controller_fallback.Eval(context)[0] > 0
        ):
            bits |= 128
        return bits

    def _update(self, context: Context, state: DiscreteValues) -> None:
        # In place on `state`, which holds the current discrete state on entry: each
        # value is read before it is written.
        c = self._config
        t = context.get_time()
        memory = state.get_mutable_value(self._memory_group)
        fault = state.get_mutable_value(self._fault_group)
        alpha_value = state.get_mutable_value(self._alpha_group)
        previous_bits = int(fault[0])
        alpha = alpha_value[0]
        faults = memory[self._faults_row]
        q_position = self._q_position.Eval(context)
        q_torque = self._q_torque.Eval(context)
        bits = self._health(context, memory, q_position)
        torque_finite = math.isfinite(q_torque.dot(self._ones_n))
        if not torque_finite:
            bits |= 256
        fault[0] = bits
        clear = memory[self._clear_row] + c.period if bits == 0 else 0.0
        memory[self._clear_row] = clear
        # E-stop (latched): hold the pose measured when it was pressed.
        held = memory[self._pressed_row] != 0
        if bits & 64 and not held:
            q = self._q_measured.Eval(context)
            if not math.isfinite(q.sum()):
                previous = context.get_discrete_state(self._memory).get_value()
                q = previous[self._last_rows][: self._n]
            memory[self._hold_rows] = q
            memory[self._pressed_row] = 1.0
            held = True
        # Mode: torque from start_time while healthy; after a fault, only once every
        # fault has been clear for reentry_time.
        running = t + 0.5 * c.period >= c.start_time
        if running and bits and not previous_bits:
            faults += 1
            memory[self._faults_row] = faults
        want_torque = (
            running
            and bits == 0
            and not held
            and faults <= c.max_reentries
            and (faults == 0 or clear >= c.reentry_time)
        )
        memory[self._want_row] = float(want_torque)
        # The last command of a healthy torque chain in use: what a ramp down starts
        # from (once a fault is seen, the chain's own output is not trusted).
        if want_torque and torque_finite:
            np.subtract(q_torque, q_position, out=memory[self._last_torque_rows])
        step = c.period / c.ramp_time
        new_alpha = min(1.0, alpha + step) if want_torque else max(0.0, alpha - step)
        if bits and not previous_bits:
            _logger.warning(
                "SafetySupervisor %s: fault at t = %.6g s (%s): to position control",
                self.GetSystemPathname(), t, describe_faults(bits),
            )
            state.set_value(self._transition_group, [t, float(bits)])
        elif want_torque and alpha == 0 and new_alpha > 0:
            state.set_value(self._transition_group, [t, 0.0])
        alpha_value[0] = new_alpha

    # ----------------------------------------------------------------- output

    def _calc_q_cmd(self, context: Context, output: BasicVector) -> None:
        xd = context.get_discrete_state()
        alpha = xd.get_value(self._alpha_group)[0]
        memory = xd.get_value(self._memory_group)
        q_position = self._q_position.Eval(context)
        if memory[self._pressed_row] > 0:
            q_position = memory[self._hold_rows]
        if alpha <= 0.0:
            output.set_value(q_position)
            return
        q_torque = self._q_torque.Eval(context)
        fault = xd.get_value(self._fault_group)[0] > 0
        fallback = (
            self._controller_fallback.HasValue(context)
            and self._controller_fallback.Eval(context)[0] > 0
        )
        wanted = memory[self._want_row] > 0
        torque_finite = math.isfinite(q_torque.dot(self._ones_n))
        if fault or fallback or not wanted or not torque_finite:
            # The torque chain's last healthy offset from the reference, which the
            # ramp takes to zero: q_cmd moves with the reference, bumplessly.
            offset = memory[self._last_torque_rows]
            output.set_value(q_position + alpha * offset)
            return
        output.set_value(alpha * q_torque + (1.0 - alpha) * q_position)


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
        out = {"imu_linear_acceleration": "acceleration", "imu_angular_velocity": "angular_velocity"}
    out |= {f"wrench_{name}": "wrench" for name in wrenches}
    return out
