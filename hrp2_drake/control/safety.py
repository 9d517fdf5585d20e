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
offset from q_position, q_position + α (q_torque − q_position)_last, until torque
control is wanted again: neither a NaN nor the chain's jump to its own fallback reaches
the robot, and q_cmd moves with the reference while the offset ramps away. Torque
control starts at start_time and resumes once every fault has been clear for
reentry_time (at most max_reentries times: then position control stays). The emergency
stop latches: the robot holds the pose measured when it was pressed (ramping down from
torque control) until `reset_emergency_stop`.

The arithmetic is `SafetySupervisorStep`'s (no Drake: a fused controller runs it as
is); `SafetySupervisor` is its LeafSystem shell.

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
from pydrake.systems.framework import BasicVector, Context, DiscreteValues, InputPort

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
            "force_limit", "torque_limit", "acceleration_limit",
            "angular_velocity_limit", "stale_time",
        )
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{where}.{name}: must be finite and > 0, got {value}")
        for name in ("start_time", "reentry_time"):
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
        if self.encoder_stale_samples < 2:
            raise ValueError(
                f"{where}.encoder_stale_samples: must be >= 2, "
                f"got {self.encoder_stale_samples}"
            )


#: The sensor kinds a supervisor monitors, and their sizes.
SENSOR_KINDS: dict[str, int] = {"wrench": 6, "acceleration": 3, "angular_velocity": 3}

# The scalar rows of the `memory` state: [time every fault has been clear (s), faults
# since start_time, torque wanted (ramping up or in torque), e-stop pressed].
_CLEAR_ROW, _FAULTS_ROW, _WANT_ROW, _PRESSED_ROW = range(4)


class SafetySupervisorStep(Step):
    """The supervisor's per-tick arithmetic (module docstring), without Drake.

    Args:
        num_joints: n, the size of q_torque, q_position, q_measured and q_cmd.
        sensors: name -> kind of each monitored sensor ("wrench" (6: torque then
            force), "acceleration" (3) or "angular_velocity" (3)); `step` reads
            them as one flat array, concatenated in this order.
        config: the SafetyConfig.
        num_sensor_stamps: the size of the `sensor_time` array (the time of each
            sensor's latest sample, s) when one is given.

    State (`Step`): `mode` (1, α), `fault` (1, the bits of the last period, see
    FAULT_BITS), `transition` (2, [time (s), bits] of the last switch: bits 0 for a
    ramp up), and `memory` (4 + 4 n + 2 s, s the sensors' total size): [time clear
    (s), faults since start_time, torque wanted, e-stop pressed; the e-stop's held
    pose (n, rad); q_torque − q_position of the last healthy period (n, rad); the
    last samples [q_measured (n); sensors (s)]; how many periods each has repeated
    (n + s); q_position when each encoder stopped (n, rad)].
    """

    def __init__(
        self,
        num_joints: int,
        sensors: dict[str, str],
        config: SafetyConfig,
        num_sensor_stamps: int = 0,
    ):
        super().__init__()
        config.validate()
        unknown = {k for k in sensors.values() if k not in SENSOR_KINDS}
        if unknown:
            raise ValueError(
                f"SafetySupervisor: unknown sensor kinds {sorted(unknown)}"
            )
        self._config = config
        self._n = n = num_joints
        self._sensor_size = sensor_size = sum(SENSOR_KINDS[k] for k in sensors.values())
        self._ramp_step = config.period / config.ramp_time
        # The range of every monitored entry, in input order.
        ranges = {
            "wrench": [config.torque_limit] * 3 + [config.force_limit] * 3,
            "acceleration": [config.acceleration_limit] * 3,
            "angular_velocity": [config.angular_velocity_limit] * 3,
        }
        self._sensor_limits = np.array(
            [limit for kind in sensors.values() for limit in ranges[kind]]
        )
        size = n + sensor_size  # the monitored samples, [q_measured; sensors]
        rows = _layout([0, 0, 0, 0, n, n, size, size, n])
        self._hold_rows, self._last_torque_rows = rows[4], rows[5]
        self._last_rows, self._count_rows, self._anchor_rows = rows[6:]
        self._declare("mode", 0.0)
        self._declare("fault", 0.0)
        self._declare("transition", np.zeros(2))
        self._declare("memory", np.zeros(self._anchor_rows.stop))
        # The thresholds as arrays (numpy compares two arrays faster than an array
        # and a Python float), and the per-tick work buffers (the ufuncs get them as
        # positional outputs, and count_nonzero tests a flag array: both about twice
        # as fast as `out=` and `.any()` on 30 entries).
        self._jump_limit = np.full(n, config.encoder_jump_speed * config.period)
        self._encoder_stale = np.full(n, float(config.encoder_stale_samples))
        self._encoder_motion = np.full(n, config.encoder_motion)
        self._stale_count = np.full(sensor_size, config.stale_samples - 1.0)
        self._stale_time = np.full(num_sensor_stamps, config.stale_time)
        self._ones_n = np.ones(n)
        self._ones_sensors = np.ones(sensor_size)
        self._ones_samples = np.ones(size)
        self._samples = np.zeros(size)
        self._q_values = self._samples[:n]
        self._sensor_values = self._samples[n:]
        self._same = np.zeros(size, dtype=bool)
        self._same_q = self._same[:n]
        self._diff_n = np.zeros(n)
        self._flag_n = np.zeros(n, dtype=bool)
        self._flag2_n = np.zeros(n, dtype=bool)
        self._abs_sensors = np.zeros(sensor_size)
        self._flag_sensors = np.zeros(sensor_size, dtype=bool)
        self._age = np.zeros(num_sensor_stamps)
        self._flag_age = np.zeros(num_sensor_stamps, dtype=bool)
        self._blend = np.zeros(n)
        self._finalize()

    def _views_changed(self) -> None:
        memory, n = self.memory, self._n
        self._hold = memory[self._hold_rows]
        self._last_torque = memory[self._last_torque_rows]
        self._last = memory[self._last_rows]
        self._count = memory[self._count_rows]
        self._anchor = memory[self._anchor_rows]
        self._last_q = self._last[:n]
        self._count_q = self._count[:n]
        self._count_sensors = self._count[n:]
        # (samples, last, count, same) over the finite rows, indexed by
        # 2 q_finite + sensors_finite: [q; sensors] (3), q (2), sensors (1), none.
        self._finite_views = [
            (self._samples[rows], self._last[rows], self._count[rows], self._same[rows])
            for rows in (slice(n, n), slice(n, None), slice(0, n), slice(None))
        ]

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
        place on the state.

        Args:
            q_torque, q_position, q_measured: n joint positions each (rad): the
                torque chain's command, the reference, the encoders.
            sensors: the monitored sensors' samples, one flat array in the order of
                the constructor's `sensors` (N, N·m, m/s², rad/s).
            e_stop, controller_fallback: 1-arrays (> 0: pressed, fallen back), or
                None when not connected.
            sensor_time: the time of each sensor's latest sample (s), or None
                (no stamps: the frozen-encoder heuristic instead).

        Returns:
            The fault bits when a fault starts this period (to be reported by the
            caller: the step never logs), else 0.
        """
        c = self._config
        memory = self.memory
        previous_bits = int(self.fault[0])
        alpha = self.mode[0]
        faults = memory[_FAULTS_ROW]
        bits = self._health(t, q_position, q_measured, sensors, sensor_time)
        if e_stop is not None and e_stop[0] > 0:
            bits |= 64
        if controller_fallback is not None and controller_fallback[0] > 0:
            bits |= 128
        torque_finite = math.isfinite(q_torque.dot(self._ones_n))
        if not torque_finite:
            bits |= 256
        self.fault[0] = bits
        clear = memory[_CLEAR_ROW] + c.period if bits == 0 else 0.0
        memory[_CLEAR_ROW] = clear
        # E-stop (latched): hold the pose measured when it was pressed (the last
        # finite one if this one is not).
        held = memory[_PRESSED_ROW] != 0
        if bits & 64 and not held:
            self._hold[:] = self._last_q if bits & 1 else q_measured
            memory[_PRESSED_ROW] = 1.0
            held = True
        # Mode: torque from start_time while healthy; after a fault, only once every
        # fault has been clear for reentry_time.
        running = t + 0.5 * c.period >= c.start_time
        if running and bits and not previous_bits:
            faults += 1
            memory[_FAULTS_ROW] = faults
        want_torque = (
            running
            and bits == 0
            and not held
            and faults <= c.max_reentries
            and (faults == 0 or clear >= c.reentry_time)
        )
        memory[_WANT_ROW] = float(want_torque)
        # The last command of a healthy torque chain in use: what a ramp down starts
        # from (once a fault is seen, the chain's own output is not trusted).
        if want_torque and torque_finite:
            np.subtract(q_torque, q_position, self._last_torque)
        ramp = self._ramp_step
        new_alpha = min(1.0, alpha + ramp) if want_torque else max(0.0, alpha - ramp)
        new_fault = 0
        if bits and not previous_bits:
            self.transition[0], self.transition[1] = t, float(bits)
            new_fault = bits
        elif want_torque and alpha == 0 and new_alpha > 0:
            self.transition[0], self.transition[1] = t, 0.0
        self.mode[0] = new_alpha
        return new_fault

    def _health(
        self,
        t: float,
        q_position: np.ndarray,
        q_measured: np.ndarray,
        sensors: np.ndarray,
        sensor_time: np.ndarray | None,
    ) -> int:
        """The sensors' fault bits of this period (1, 2, 4, 8, 16, 32); updates the
        sample memory (each row read before it is written)."""
        samples = self._samples
        self._q_values[:] = q_measured
        self._sensor_values[:] = sensors
        bits = 0
        # Which samples to remember: the finite parts ([q; sensors] at once when all
        # of it is, the usual case).
        if math.isfinite(samples.dot(self._ones_samples)):
            q_finite = sensors_finite = True
        else:
            q_finite = math.isfinite(self._q_values.dot(self._ones_n))
            sensors_finite = math.isfinite(self._sensor_values.dot(self._ones_sensors))
            bits |= (0 if q_finite else 1) | (0 if sensors_finite else 2)
        finite_samples, last, count, same = self._finite_views[
            2 * q_finite + sensors_finite
        ]
        if q_finite:
            np.subtract(self._q_values, self._last_q, self._diff_n)
            np.abs(self._diff_n, self._diff_n)
            np.greater(self._diff_n, self._jump_limit, self._flag_n)
            if np.count_nonzero(self._flag_n):
                bits |= 8
        # Each sample's count of identical consecutive samples:
        # count = where(same, count + 1, 0), in place.
        np.equal(finite_samples, last, same)
        np.multiply(count, same, count)
        np.add(count, same, count)
        if q_finite:
            bits |= self._frozen_encoders(q_position, sensor_time is None)
        if self._sensor_size and not bits & 2:
            np.abs(self._sensor_values, self._abs_sensors)
            flags = self._flag_sensors
            if np.count_nonzero(
                np.greater(self._abs_sensors, self._sensor_limits, flags)
            ):
                bits |= 4
            if self._config.stale_samples and np.count_nonzero(
                np.greater_equal(self._count_sensors, self._stale_count, flags)
            ):
                bits |= 16
        last[...] = finite_samples
        if sensor_time is not None:
            np.subtract(t, sensor_time, self._age)
            np.greater(self._age, self._stale_time, self._flag_age)
            if np.count_nonzero(self._flag_age):
                bits |= 16
        return bits

    def _frozen_encoders(self, q_position: np.ndarray, check: bool) -> int:
        """Moves each encoder's anchor to q_position (rad) where it changed; 32 when
        `check` and an encoder has not moved for encoder_stale_samples periods while
        its reference moved by more than encoder_motion, else 0."""
        anchor = self._anchor
        np.logical_not(self._same_q, self._flag_n)
        np.copyto(anchor, q_position, where=self._flag_n)
        # Only without the drivers' stamps: a joint starting to move from rest
        # (latency, dead zone, stiction) can stay on its count for several periods
        # while its reference moves away.
        if not check:
            return 0
        np.greater_equal(self._count_q, self._encoder_stale, self._flag_n)
        np.subtract(q_position, anchor, self._diff_n)
        np.abs(self._diff_n, self._diff_n)
        np.greater(self._diff_n, self._encoder_motion, self._flag2_n)
        np.logical_and(self._flag_n, self._flag2_n, self._flag_n)
        return 32 if np.count_nonzero(self._flag_n) else 0

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
        the e-stop's held pose replaces q_position. Returns `out`."""
        alpha = self.mode[0]
        memory = self.memory
        if memory[_PRESSED_ROW] > 0:
            q_position = self._hold
        if alpha <= 0.0:
            out[:] = q_position
            return out
        fault = self.fault[0] > 0
        fallback = controller_fallback is not None and controller_fallback[0] > 0
        wanted = memory[_WANT_ROW] > 0
        torque_finite = math.isfinite(q_torque.dot(self._ones_n))
        if fault or fallback or not wanted or not torque_finite:
            # The torque chain's last healthy offset from the reference, which the
            # ramp takes to zero: q_cmd moves with the reference, bumplessly.
            np.multiply(self._last_torque, alpha, out)
            np.add(out, q_position, out)
            return out
        np.multiply(q_torque, alpha, out)
        np.multiply(q_position, 1.0 - alpha, self._blend)
        np.add(out, self._blend, out)
        return out


class SafetySupervisor(StepSystem):
    """The safety supervisor (module docstring): the LeafSystem shell of a
    `SafetySupervisorStep` (its arguments).

    Inputs: q_torque, q_position, q_measured (n each, rad), one port per monitored
    sensor (named after it), e_stop (1, optional), controller_fallback (1,
    optional), sensor_time (num_sensor_stamps, s; only if num_sensor_stamps > 0).
    Outputs: q_cmd (n, rad, direct feedthrough of q_torque, q_position and
    controller_fallback), and the state outputs mode, fault, transition.
    """

    def __init__(
        self,
        num_joints: int,
        sensors: dict[str, str],
        config: SafetyConfig,
        num_sensor_stamps: int = 0,
    ):
        super().__init__()
        step = SafetySupervisorStep(num_joints, sensors, config, num_sensor_stamps)
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

    def _update(self, context: Context, state: DiscreteValues) -> None:
        # (state holds the current discrete state on entry.)
        t = context.get_time()
        self._load(state)
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
        self._store(state)
        if new_fault:
            _logger.warning(
                "SafetySupervisor %s: fault at t = %.6g s (%s): to position control",
                self.GetSystemPathname(), t, describe_faults(new_fault),
            )

    # ----------------------------------------------------------------- output

    def _calc_q_cmd(self, context: Context, output: BasicVector) -> None:
        self._load_context(context)
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
