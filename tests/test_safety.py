"""SafetySupervisor: each health check, the ramped transfer both ways, re-entry, the
latched emergency stop (the closed loop is in tests/test_faults.py)."""

import contextlib
import hashlib

import numpy as np
import pytest
from ticks import commit

from hrp2_drake import kernels
from hrp2_drake.control.safety import (
    FAULT_BITS,
    SafetyConfig,
    SafetySupervisor,
    SafetySupervisorStep,
    describe_faults,
    supervisor_sensors,
    with_sensor_ranges,
)
from hrp2_drake.description import load_robot_description
from hrp2_drake.description.sensors import SensorRanges

PERIOD = 0.001


class _Harness:
    """The supervisor alone, its inputs fixed, stepped like the simulator does.

    The timing rule (`hrp2_drake.step`): `step()` presents one sample and leaves the
    context where a Simulator's AdvanceTo to the next sampling instant leaves it: the
    outputs are the tick of that sample (direct feedthrough), its commit at the
    context's time, the next instant, still to come (it runs when the next sample is
    presented). So `h.context.get_time()` is the time of the next sample, as before
    one tick of sample to command.
    """

    def __init__(self, **config):
        defaults = {
            "start_time": 0.0,
            "ramp_time": 0.01,
            "reentry_time": 0.02,
            "force_limit": 2000.0,
            "torque_limit": 300.0,
            "acceleration_limit": 100.0,
        }
        config = SafetyConfig(**(defaults | config))
        self.system = SafetySupervisor(2, {"wrench_x": "wrench"}, config, PERIOD)
        self.context = self.system.CreateDefaultContext()
        self.rng = np.random.default_rng(0)
        self.inputs = dict(
            q_torque=np.array([0.1, 0.2]),
            q_position=np.array([0.0, 0.0]),
            q_measured=np.array([0.0, 0.0]),
        )
        self.fix()

    def fix(self, **changes):
        """Changes the inputs of the sample now held (its tick is recomputed)."""
        self.inputs |= changes
        for name, value in self.inputs.items():
            self.system.GetInputPort(name).FixValue(self.context, value)

    def step(self, n: int = 1, noisy: bool = True, **changes):
        """n periods, each a new sample (a fresh noisy F/T sample unless `wrench_x`
        given): the tick of the sample held is committed at the context's time (none
        is held at 0, the first commit is one period after), the new sample fixed,
        and the context's time the next sampling instant."""
        for _ in range(n):
            t = self.context.get_time()
            if t > 0:
                commit(self.system, self.context, t)
            if noisy and "wrench_x" not in changes:
                self.fix(wrench_x=self.rng.normal(0.0, 0.5, 6))
            if changes:
                self.fix(**changes)
            self.context.SetTime(t + PERIOD)
        return self

    def committed(self, name):
        """The committed state (the tick before the sample now held)."""
        group = self.system.step_group(name)
        return self.context.get_discrete_state(group).get_value().copy()

    def out(self, name):
        return self.system.GetOutputPort(name).Eval(self.context).copy()


def test_ramps_into_torque_control_without_a_step():
    h = _Harness()
    h.fix(wrench_x=np.zeros(6))
    modes, commands = [], []
    for _ in range(15):
        h.step()
        modes.append(h.out("mode")[0])
        commands.append(h.out("q_cmd"))
    assert modes[:3] == pytest.approx([0.1, 0.2, 0.3]) and modes[-1] == 1.0
    # q_cmd = α q_torque + (1 − α) q_position: steps of 0.1 * |q_torque − q_position|.
    steps = np.abs(np.diff(commands, axis=0)).max()
    assert steps == pytest.approx(0.1 * 0.2)
    np.testing.assert_allclose(commands[-1], [0.1, 0.2])


@pytest.mark.parametrize(
    "changes, bit",
    [
        (dict(q_measured=np.array([np.nan, 0.0])), 1),
        (dict(wrench_x=np.array([0, 0, 0, np.inf, 0, 0.0])), 2),
        (dict(wrench_x=np.array([0, 0, 0, 0, 0, 5000.0])), 4),
        (dict(q_measured=np.array([0.0, 0.05])), 8),  # 50 rad/s in one period
        (dict(q_torque=np.array([np.nan, 0.0])), 256),
    ],
    ids=[
        "encoder_nan",
        "sensor_inf",
        "force_out_of_range",
        "encoder_jump",
        "command_nan",
    ],
)
def test_each_fault_is_detected_in_the_tick_of_its_sample_and_ramps_down(changes, bit):
    """One tick from sample to command: the tick of the faulty sample reports the
    fault and commands the first period of the ramp down, before that tick is
    committed (it was one period later when the outputs were the committed state).
    (A range of one sample: `range_samples` has its own test.)"""
    h = _Harness(range_samples=1).step(20)
    assert h.out("mode")[0] == 1.0
    last = h.out("q_cmd")
    h.step(**changes)
    assert h.committed("fault")[0] == 0.0 and h.committed("mode")[0] == 1.0
    assert int(h.out("fault")[0]) & bit, describe_faults(h.out("fault")[0])
    assert h.out("transition")[1] == h.out("fault")[0]
    assert h.out("mode")[0] == pytest.approx(0.9)
    command = h.out("q_cmd")
    assert np.all(np.isfinite(command))  # a NaN q_torque is replaced by the last one
    assert np.abs(command - last).max() <= 0.1 * 0.2 + 1e-12


def test_a_landing_spike_is_not_out_of_range_a_reading_that_stays_is():
    """A force beyond force_limit for range_samples − 1 samples (a sole's landing:
    an impact spike) is no fault; for range_samples samples in a row it is, in the
    tick of the last one; an entry back in range starts its count anew."""
    spike = np.array([0, 0, 0, 0, 0, 5000.0])
    h = _Harness(range_samples=3).step(20)
    h.step(2, wrench_x=spike)
    assert h.out("fault")[0] == 0.0 and h.out("mode")[0] == 1.0
    h.step(1)  # back in range
    h.step(2, wrench_x=spike)
    assert h.out("fault")[0] == 0.0
    h.step(1, wrench_x=spike)  # the third in a row
    assert int(h.out("fault")[0]) == 4, describe_faults(h.out("fault")[0])
    assert SafetyConfig().range_samples == 3
    with pytest.raises(ValueError, match="SafetyConfig.range_samples: must be >= 1"):
        SafetyConfig(range_samples=0).validate()


def test_stale_sensor_within_stale_samples_and_not_when_disabled():
    h = _Harness(stale_samples=5).step(10)
    frozen = h.rng.normal(0.0, 0.5, 6)
    h.step(4, wrench_x=frozen)
    assert h.out("fault")[0] == 0.0
    h.step(1, wrench_x=frozen)  # the 5th identical sample
    assert int(h.out("fault")[0]) & 16
    h = _Harness(stale_samples=0).step(10)
    h.step(20, wrench_x=frozen)
    assert h.out("fault")[0] == 0.0


def test_frozen_encoder_is_caught_only_while_the_reference_moves():
    h = _Harness(encoder_stale_samples=10)
    h.step(30)  # at rest, the encoder never changes: no fault
    assert h.out("fault")[0] == 0.0
    # The reference moves 0.3 mrad per period, the encoder stays: caught after the
    # reference has moved 1 mrad and 10 periods have passed.
    for k in range(1, 12):
        h.step(q_position=np.array([3e-4 * k, 0.0]))
    assert int(h.out("fault")[0]) & 32


def test_reentry_waits_and_the_emergency_stop_latches():
    h = _Harness().step(20)
    h.step(q_measured=np.array([np.nan, 0.0]))
    h.step(q_measured=np.array([0.0, 0.0]))
    # Clear again: position control for reentry_time (20 ms), then the ramp up.
    modes = [h.step().out("mode")[0] for _ in range(40)]
    assert min(modes) == 0.0
    first_up = next(k for k, m in enumerate(modes) if k > 10 and m > 0)
    assert first_up >= 18 and modes[-1] == 1.0
    # Emergency stop: hold the measured pose, latched after the button is released.
    h.fix(q_measured=np.array([0.01, -0.02]))
    h.step(e_stop=np.array([1.0]))
    h.step(12, e_stop=np.array([0.0]))
    assert h.system.emergency_stopped(h.context)
    np.testing.assert_allclose(h.out("q_cmd"), [0.01, -0.02])
    assert h.out("mode")[0] == 0.0
    h.system.reset_emergency_stop(h.context)
    h.step(40)
    assert h.out("mode")[0] == 1.0


def test_config_errors_name_the_field():
    with pytest.raises(ValueError, match="ramp_time"):
        SafetyConfig(ramp_time=0.0).validate()
    with pytest.raises(ValueError, match="stale_samples"):
        SafetyConfig(stale_samples=1).validate()
    with pytest.raises(ValueError, match="unknown sensor kinds"):
        SafetySupervisor(2, {"x": "thermometer"}, SafetyConfig(), PERIOD)


def test_the_ranges_are_the_robots():
    """A range left 0 is the robot's (its description's sensor_ranges); one the
    config sets wins; a monitored sensor without a range is one line naming the
    description's field, and a supervisor built on an unfilled range refuses."""
    monitored = supervisor_sensors(["right_foot"])
    ranges = load_robot_description("hrp2").sensor_ranges
    config = with_sensor_ranges(SafetyConfig(torque_limit=50.0), monitored, ranges)
    assert (config.force_limit, config.torque_limit) == (ranges.force, 50.0)
    assert (config.acceleration_limit, config.angular_velocity_limit) == (
        ranges.acceleration,
        ranges.angular_velocity,
    )
    wrench = {"wrench_wrist": "wrench"}
    message = r"^r.yaml: sensor_ranges.force: not given .* \['wrench_wrist'\]"
    with pytest.raises(ValueError, match=message):
        with_sensor_ranges(SafetyConfig(), wrench, SensorRanges(), where="r.yaml")
    # Only what is monitored needs a range: an arm without IMU.
    arm = with_sensor_ranges(SafetyConfig(), wrench, SensorRanges(force=1, torque=1))
    assert arm.acceleration_limit == 0.0
    with pytest.raises(ValueError, match="SafetyConfig.torque_limit: 0 .the robot's"):
        SafetySupervisor(2, wrench, SafetyConfig(), PERIOD)


def test_stale_stamps_are_caught_within_three_periods():
    """With the drivers' time stamps (`sensor_time`), a sensor that stops sending is
    stale once its latest sample is older than stale_time (2.5 periods)."""
    h = _Harness()
    h.system = SafetySupervisor(2, {"wrench_x": "wrench"}, h.system.config(), PERIOD, 2)
    h.context = h.system.CreateDefaultContext()
    h.fix()
    for _ in range(10):
        h.step(sensor_time=np.full(2, h.context.get_time() - PERIOD))
    assert h.out("fault")[0] == 0.0
    frozen = h.context.get_time() - PERIOD
    faults = []
    for _ in range(4):
        h.step(sensor_time=np.array([h.context.get_time() - PERIOD, frozen]))
        faults.append(int(h.out("fault")[0]) & 16)
    assert faults[0] == 0 and faults[2] == 16


def test_a_controller_that_keeps_faulting_is_not_retried_forever():
    h = _Harness(max_reentries=2).step(20)
    modes = []
    for _ in range(3):
        h.step(q_measured=np.array([np.nan, 0.0]))
        h.step(q_measured=np.array([0.0, 0.0]))
        h.step(40)
        modes.append(h.out("mode")[0])
    assert modes == [1.0, 1.0, 0.0]  # resumed twice, then position control stays
    h.step(100)
    assert h.out("mode")[0] == 0.0


def _step_and_system(num_stamps: int = 0):
    """A SafetySupervisorStep and the harness's SafetySupervisor, same arguments."""
    h = _Harness()
    sensors = {"imu_linear_acceleration": "acceleration", "wrench_x": "wrench"}
    h.system = SafetySupervisor(2, sensors, h.system.config(), PERIOD, num_stamps)
    h.context = h.system.CreateDefaultContext()
    h.fix(imu_linear_acceleration=np.zeros(3), wrench_x=np.zeros(6))
    step = SafetySupervisorStep(2, sensors, h.system.config(), PERIOD, num_stamps)
    return step, h


def test_the_step_on_plain_arrays_is_the_system():
    """The step driven by plain arrays (no Context) gives the LeafSystem's outputs,
    bit for bit, through a ramp up, a NaN encoder, the fallback and re-entry; and it
    reports a new fault once, when it starts."""
    step, h = _step_and_system(num_stamps=3)
    rng = np.random.default_rng(1)
    h.fix(sensor_time=np.zeros(3))
    h.system.ExecuteInitializationEvents(h.context)
    step.initialize(h.inputs["q_measured"], h.inputs["q_position"], np.zeros(9))
    q_cmd, returned, modes = np.zeros(2), [], []
    for k in range(80):
        t = h.context.get_time()
        q_measured = np.array([np.nan if k == 20 else 1e-4 * k, 0.0])
        fallback = np.array([1.0 if 40 <= k < 42 else 0.0])
        sensors = rng.normal(0.0, 0.5, 9)
        stamps = np.full(3, t - PERIOD)
        returned.append(
            step.step(
                t,
                h.inputs["q_torque"],
                h.inputs["q_position"],
                q_measured,
                sensors,
                None,
                fallback,
                stamps,
            )
        )
        h.step(
            noisy=False,
            q_measured=q_measured,
            controller_fallback=fallback,
            imu_linear_acceleration=sensors[:3],
            wrench_x=sensors[3:],
            sensor_time=stamps,
        )
        step.q_cmd(h.inputs["q_torque"], h.inputs["q_position"], fallback, q_cmd)
        for name in ("mode", "fault", "transition"):
            np.testing.assert_array_equal(getattr(step, name), h.out(name))
        np.testing.assert_array_equal(q_cmd, h.out("q_cmd"))
        modes.append(step.mode[0])
    # Up in 10 periods; the NaN at 20 ms and the fallback at 40 ms, each reported
    # once (bits 1 and 128); back up after reentry_time.
    assert modes[9] == pytest.approx(1.0) and modes[20] == pytest.approx(0.9)
    reported = [(k, bits) for k, bits in enumerate(returned) if bits]
    assert reported == [(20, 1), (40, 128)]
    # Clear from 42 ms on: the ramp up starts 20 ms later.
    assert modes[60] == 0.0 and modes[61] == pytest.approx(0.1)
    assert step.transition == pytest.approx([0.061, 0.0])
    assert modes[-1] == 1.0
    np.testing.assert_array_equal(q_cmd, [0.1, 0.2])


def test_the_step_runs_on_a_bound_buffer_and_holds_the_e_stop_pose():
    """A fused controller's use: the state in its buffer, no sensor_time, e_stop and
    controller_fallback as 1-arrays; q_cmd holds the pose measured at the press."""
    step, _ = _step_and_system()
    buffer = np.zeros(step.state_size + 4)
    step.bind(buffer[2:-2])
    assert np.shares_memory(step.memory, buffer)
    q_torque, q_position, q_cmd = np.array([0.1, 0.2]), np.zeros(2), np.zeros(2)
    sensors = np.zeros(9)
    e_stop, fallback = np.zeros(1), np.zeros(1)
    step.initialize(np.zeros(2), q_position, sensors)
    for k in range(15):
        sensors[:] = 0.01 * (k + 1)  # a live (changing) sensor
        q_measured = np.array([0.005, -0.008]) if k >= 12 else np.zeros(2)
        e_stop[0] = 1.0 if k == 12 else 0.0
        t = k * PERIOD
        step.step(t, q_torque, q_position, q_measured, sensors, e_stop, fallback)
    assert step.emergency_stopped()
    assert step.mode[0] == pytest.approx(0.7)  # 1.0, then 3 periods down (12-14)
    assert buffer[2 + step.rows("mode").start] == step.mode[0]
    # q_cmd: the held pose plus α × the last healthy offset (0.1, 0.2).
    step.q_cmd(q_torque, q_position, fallback, q_cmd)
    np.testing.assert_allclose(q_cmd, [0.005 + 0.07, -0.008 + 0.14], rtol=0, atol=1e-15)
    step.reset_emergency_stop()
    assert not step.emergency_stopped()


# ------------------------------------------------------------- the numba kernels


def _scripted_run():
    """The step through every fault (bits 1 to 256; a NaN encoder, an infinite and an
    out-of-range F/T entry, a frozen encoder while the reference moves, a jump, a NaN
    command, all samples NaN, a stuck sensor, the e-stop held and reset, the
    controller's fallback, a stale stamp), re-entries until max_reentries, absent and
    connected optional inputs in turn; returns [(returned bits, state, q_cmd)] of every
    period and the union of the fault bits."""
    config = SafetyConfig(
        start_time=0.005,
        ramp_time=0.004,
        reentry_time=0.006,
        stale_samples=4,
        encoder_stale_samples=3,
        max_reentries=10,
        range_samples=1,
        force_limit=2000.0,
        torque_limit=300.0,
        acceleration_limit=100.0,
    )
    sensors = {"imu_linear_acceleration": "acceleration", "wrench_x": "wrench"}
    step = SafetySupervisorStep(3, sensors, config, PERIOD, 2)
    n, s = 3, 9
    q_torque, q_cmd = np.zeros(n), np.zeros(n)
    q_position, q_measured, values = np.zeros(n), np.zeros(n), np.zeros(s)
    e_stop, fallback, stamps = np.zeros(1), np.zeros(1), np.zeros(2)
    step.initialize(q_measured, q_position, values)
    trace, bits_seen = [], 0
    for k in range(220):
        t = k * 0.001
        frozen = q_measured[0]
        for j in range(n):
            q_position[j] = min(k % 46, 46 - k % 46) * 1e-3 * (j + 1)  # a triangle
            q_measured[j] = q_position[j] + ((k * 31 + j * 7) % 5) * 1e-5
            q_torque[j] = q_position[j] + 0.01 * (j + 1)
        if 60 <= k < 70:
            q_measured[0] = frozen  # a frozen encoder, its reference moving
        for j in range(s):  # a noisy sensor, exact arithmetic (no RNG, no libm)
            values[j] = ((k * 7919 + j * 104729) % 1000) / 1000 - 0.5
        if 100 <= k < 106:
            values[:] = 0.25  # a stuck sensor
        if k == 30:
            q_measured[1] = np.nan
        if k == 40:
            values[4] = np.inf
        if k == 50:
            values[8] = 5000.0  # force beyond force_limit
        if k == 80:
            q_measured[2] += 0.05  # a jump
        if k == 90:
            q_torque[0] = np.nan
        if k == 95:
            q_measured[:] = np.nan
            values[:] = np.nan
        e_stop[0] = 1.0 if k == 120 else 0.0
        if k == 150:
            step.reset_emergency_stop()
        fallback[0] = 1.0 if 130 <= k < 133 else 0.0
        stamps[:] = t - 0.001
        if k == 175:
            stamps[1] = t - 0.01
        returned = step.step(
            t,
            q_torque,
            q_position,
            q_measured,
            values,
            None if k % 2 else e_stop,
            None if k % 3 == 0 else fallback,
            stamps if k >= 150 else None,
        )
        bits_seen |= int(step.fault[0])
        step.q_cmd(q_torque, q_position, None if k % 5 == 0 else fallback, q_cmd)
        trace.append((returned, step.state.copy(), q_cmd.copy()))
    return trace, bits_seen


def _digest(trace, extra_rows: int = 9) -> str:
    """The digest of every return, state and q_cmd; the state without its last
    `extra_rows` (the counts of samples out of range, issue 35: the scripted run's
    9 sensor entries), which the numpy step did not have."""
    digest = hashlib.sha256()
    for returned, state, q_cmd in trace:
        digest.update(np.int64(returned).tobytes())
        digest.update(state[: state.size - extra_rows].tobytes())
        digest.update(q_cmd.tobytes())
    return digest.hexdigest()


#: `_digest(_scripted_run()[0])` with the numpy step before the numba kernels (every
#: return, state and q_cmd bit for bit; a range of one sample, as it had).
_NUMPY_DIGEST = "0bddd23d56a17714de1748131447284e58ecce1e1fd45e1b3eb7a92f1da8f708"


def test_kernels_compiled_interpreted_and_numpy_are_bitwise_equal():
    """The kernels compiled, the same source interpreted, and the numpy step they
    replaced give the same returns, states and commands, bit for bit, through every
    fault."""
    compiled, bits_seen = _scripted_run()
    # (With NUMBA_DISABLE_JIT=1 both runs are the Python source.)
    with kernels.interpreted() if kernels.jit_enabled() else contextlib.nullcontext():
        interpreted, _ = _scripted_run()
    assert bits_seen == sum(FAULT_BITS)
    reported = [bits for bits, _, _ in compiled if bits]
    assert reported == [1, 2, 4, 32, 8, 256, 3, 16, 64, 128, 16]
    for (r1, s1, c1), (r2, s2, c2) in zip(compiled, interpreted):
        assert r1 == r2
        np.testing.assert_array_equal(s1.view(np.int64), s2.view(np.int64))
        np.testing.assert_array_equal(c1.view(np.int64), c2.view(np.int64))
    assert _digest(compiled) == _NUMPY_DIGEST
    assert compiled[-1][1][0] == 0.0  # the 11th fault: position control stays


def test_warm_up_then_frozen_a_tick_runs_and_a_new_signature_raises():
    """warm_up compiles both kernels without touching the state; frozen, a real step
    (the fused controller's bound buffer, a LeafSystem's arrays) runs, and a float32
    array raises instead of compiling."""
    step, _ = _step_and_system(num_stamps=3)
    buffer = np.zeros(step.state_size + 3)
    step.bind(buffer[1:-2])
    step.initialize(np.zeros(2), np.zeros(2), np.zeros(9))
    step.memory[0] = 0.25  # some state to keep
    before = buffer.copy()
    step.warm_up()
    np.testing.assert_array_equal(buffer, before)
    q_torque, q_cmd = np.array([0.1, 0.2]), np.zeros(2)
    try:
        kernels.freeze()
        assert (
            step.step(
                0.0,
                q_torque,
                np.zeros(2),
                np.zeros(2),
                np.ones(9),
                np.zeros(1),
                np.zeros(1),
                np.zeros(3),
            )
            == 0
        )
        step.step(0.001, q_torque, np.zeros(2), np.zeros(2), np.zeros(9))
        step.q_cmd(q_torque, np.zeros(2), None, q_cmd)
        h = _Harness().step(5)  # the LeafSystem shell (Drake's arrays)
        assert h.out("mode")[0] == pytest.approx(0.5)
        if kernels.jit_enabled():
            with pytest.raises(TypeError):
                step.step(
                    0.002,
                    q_torque.astype(np.float32),
                    np.zeros(2),
                    np.zeros(2),
                    np.zeros(9),
                )
            with pytest.raises(TypeError):
                step.q_cmd(q_torque, np.zeros(4)[::2], None, q_cmd)
    finally:
        kernels.thaw()
    assert step.mode[0] == pytest.approx(0.2)


def test_inputs_of_the_wrong_size_raise():
    step, _ = _step_and_system(num_stamps=3)
    z = np.zeros(2)
    with pytest.raises(ValueError, match="wrong size"):
        step.step(0.0, z, z, z, np.zeros(8))
    with pytest.raises(ValueError, match="wrong size"):
        step.step(0.0, z, z, z, np.zeros(9), None, None, np.zeros(2))
    with pytest.raises(ValueError, match="wrong size"):
        step.step(0.0, np.zeros(3), z, z, np.zeros(9))
    with pytest.raises(ValueError, match="wrong size"):
        step.q_cmd(z, z, None, np.zeros(3))
