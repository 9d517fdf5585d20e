"""A robot's servo bus as data (hrp2_drake/description/bus.py): the control tables, the
units both ends of the wire share, the wire-time budget and its refusal, and what a
bus changes in the simulated robot (goals in pulses, samples ahead of the tick) and in
the controller's settings (the period's spans, Δq's saturation)."""

import copy
import math

import numpy as np
import pytest

from hrp2_drake.assembly.builders import JointReference
from hrp2_drake.assembly.torque_control import (
    DEFAULT_DELTA_Q_LIMIT,
    TorqueControlConfig,
    at_period,
    delta_q_limit,
)
from hrp2_drake.description import load_robot_description
from hrp2_drake.description.bus import (
    BusDescription,
    bus_for_period,
    check_bus_period,
    dynamixel_model,
    dynamixel_models,
    status_bytes,
    sync_read_bytes,
    sync_write_bytes,
    wire_time,
)


def _xl330(**changes) -> BusDescription:
    return BusDescription(
        **({"kind": "dynamixel", "ids": [1], "model": "XL330-M288"} | changes)
    )


def test_the_control_tables_hold_the_e_manuals_facts():
    xl330, xm430 = dynamixel_model("XL330-M288"), dynamixel_model("XM430-W350")
    assert (xl330.model_number, xm430.model_number) == (1200, 1020)
    for model in (xl330, xm430):
        assert (
            model.register("goal_position").address,
            model.register("goal_position").size,
        ) == (116, 4)
        assert model.register("present_position").address == 132
        assert model.register("return_delay_time").unit == 2e-6
        assert model.register("torque_enable").address == 64
        assert model.register("hardware_error_status").address == 70
        assert model.register("position_p_gain").address == 84
        # 0.229 rev/min per count.
        assert model.register("present_velocity").unit == pytest.approx(
            0.229 * 2 * math.pi / 60
        )
    assert xl330.register("present_current").unit == 0.001
    assert xm430.register("present_current").unit == 0.00269
    assert xl330.register("position_p_gain").initial == 400
    assert xm430.register("position_p_gain").initial == 800
    assert xm430.baud_rates[7] == 4_500_000 and len(xl330.baud_rates) == 7
    assert (
        xl330.describe_hardware_error(0b100101)
        == "input voltage error, overheating, overload"
    )
    # Signed items: two's complement over their size.
    assert xl330.si("present_velocity", 2**32 - 1) == pytest.approx(
        -0.229 * 2 * math.pi / 60
    )
    assert xl330.si("present_current", 2**16 - 5) == pytest.approx(-0.005)
    assert sorted(dynamixel_models()) == ["XL330-M288", "XM430-W350"]


def test_the_wire_time_budget_counts_every_byte():
    # One XL330 at 1 Mbit/s reading [velocity, position] (8 bytes): the instruction
    # 10 + 4 + 1 bytes, the status 10 + 1 + 8, the sync write 10 + 4 + 5.
    assert (sync_read_bytes(1), status_bytes(8), sync_write_bytes(1, 4)) == (15, 19, 19)
    bus = _xl330(
        read=["present_velocity", "present_position"],
        return_delay=20e-6,
        adapter_latency=0.001,
        compute_time=0.0005,
    )
    timing = bus.timing()
    assert bus.read_block() == (128, 8)
    assert timing.read_instruction == pytest.approx(150e-6)
    assert timing.statuses == pytest.approx(20e-6 + 190e-6)
    assert timing.write == pytest.approx(190e-6)
    assert timing.read_to_write == pytest.approx(210e-6 + 1e-3 + 0.5e-3 + 190e-6)
    assert timing.cycle == pytest.approx(150e-6 + timing.read_to_write)
    # Six servos at 4 Mbit/s with the factory's 500 µs return delay spend 3 ms on
    # return delays alone (DynamixelSDK issue 302: over 4 ms a sync read with USB).
    six = BusDescription(
        kind="dynamixel",
        ids=list(range(1, 7)),
        model="XL330-M288",
        baud=4_000_000,
        return_delay=500e-6,
    )
    assert six.timing().statuses == pytest.approx(6 * (500e-6 + wire_time(15, 4e6)))


def test_a_period_the_bus_cannot_carry_is_one_line_with_the_budget():
    bus = load_robot_description("xl330_pendulum").bus
    check_bus_period(bus, 0.005)
    with pytest.raises(ValueError) as error:
        check_bus_period(bus, 0.001)
    text = str(error.value)
    assert "\n" not in text and text.startswith("sensors.period: 1 ms (1000 Hz)")
    assert "adapter latency 1000 µs" in text and "at most 493 Hz" in text
    # The fastest bus its servos allow carries 1 kHz: 4 Mbit/s, no adapter latency.
    fast, note = bus_for_period(bus, 0.001)
    assert (fast.baud, fast.adapter_latency) == (4_000_000, 0.0) and "UART" in note
    assert bus_for_period(bus, 0.005) == (bus, "")
    with pytest.raises(ValueError, match="not even 1 XL330-M288 at 4 Mbit/s"):
        bus_for_period(bus, 0.0005)


@pytest.mark.parametrize(
    "changes, message",
    [
        (
            {"model": "XL999"},
            "bus.model: unknown servo model 'XL999' (known: ['XL330-M288', "
            "'XM430-W350'])",
        ),
        (
            {"baud": 4_500_000},
            "bus.baud: 4500000 bit/s is not a rate of the XL330-M288",
        ),
        ({"ids": [1, 1]}, "bus.ids: IDs listed twice [1]"),
        ({"ids": [253]}, "bus.ids: [253] are not servo IDs"),
        (
            {"return_delay": 3e-6},
            "bus.return_delay: 3e-06 s is not a whole number of 2 µs",
        ),
        (
            {"read": ["present_current"]},
            "bus.read: ['present_current'] must include present_position",
        ),
        (
            {"read": ["present_position", "goal_speed"]},
            "bus.read: 'goal_speed' is not an item",
        ),
        ({"direction": [2]}, "bus.direction: [2], each +1 or -1"),
        ({"kind": "can"}, "bus.kind: 'can', expected one of ('dynamixel', 'feetech')"),
    ],
)
def test_a_bad_bus_is_one_line_naming_the_field(changes, message):
    with pytest.raises(ValueError) as error:
        _xl330(**changes).validate(len(_xl330(**changes).ids))
    assert message in str(error.value) and "\n" not in str(error.value)


def test_a_robot_whose_gain_the_servos_cannot_take_is_refused():
    robot = copy.deepcopy(load_robot_description("xl330_pendulum"))
    robot.position_loop.gain = 400.5
    with pytest.raises(
        ValueError, match="position_loop.gain: 400.5, but a robot on a bus"
    ):
        robot.validate()
    robot.position_loop.gain = 400
    robot.sensors.period = 0.001
    with pytest.raises(ValueError, match="sensors.period: 1 ms"):
        robot.validate()


def test_positions_go_through_whole_pulses_as_the_servo_rounds_them():
    bus = _xl330(zero=[1000], direction=[-1])
    quantum = 2 * math.pi / 4096
    q = np.array([0.3])
    pulses = bus.to_pulses(q)
    assert pulses[0] == 1000 - round(0.3 / quantum)
    np.testing.assert_allclose(
        bus.to_radians(pulses), np.rint(q / quantum) * quantum, atol=1e-15
    )
    # The default zero is half a turn (BAM's XL330 logs: 0 rad at pulse 2048).
    assert _xl330().to_pulses(np.array([-quantum]))[0] == 2047
    # Rounding twice is rounding once.
    once = bus.quantized(np.array([0.123456]))
    np.testing.assert_array_equal(bus.quantized(once), once)


def test_the_simulated_servo_takes_its_goal_in_pulses():
    """A bus robot's station rounds q_cmd to whole pulses before its servo (the
    same torque for every command within half a pulse of one)."""
    from pydrake.systems.analysis import Simulator

    from hrp2_drake.robot.station import StationConfig, make_station

    station = make_station(StationConfig(robot="xl330_pendulum", scenario="fixed_base"))
    servo = station.GetSubsystemByName("servo")
    context = station.CreateDefaultContext()
    Simulator(station, context).Initialize()
    quantum = 2 * math.pi / 4096
    base = 65 * quantum
    torques = []
    for q_cmd in (
        base,
        base + 0.3 * quantum,
        base - 0.3 * quantum,
        base + 0.7 * quantum,
    ):
        station.GetInputPort("q_cmd").FixValue(context, [q_cmd])
        torques.append(
            servo.GetOutputPort("actuation").Eval(servo.GetMyContextFromRoot(context))[
                0
            ]
        )
    assert torques[0] == torques[1] == torques[2] != torques[3]


def test_settings_stated_at_1_khz_keep_their_spans_of_time():
    config = TorqueControlConfig()
    assert at_period(config, 0.001) is config
    slow = at_period(config, 0.005)
    assert slow.estimator.window == 16  # 80 samples at 1 kHz: 80 ms
    assert slow.supervisor.stale_time == pytest.approx(0.0125)
    assert slow.supervisor.stale_samples == config.supervisor.stale_samples
    tuned = TorqueControlConfig()
    tuned.estimator.windows = {"a": 21, "b": 8}
    windows = at_period(tuned, 0.004).estimator
    # 80 -> 20, 21 -> 5, 8 -> 5: each of the longest one's parity (even).
    assert (windows.window, windows.windows) == (20, {"a": 6, "b": 6})


def test_delta_q_saturates_where_the_servos_loop_does():
    xl330 = load_robot_description("xl330_pendulum")
    hrp2 = load_robot_description("hrp2")
    config = TorqueControlConfig()
    # duty = kp · e · output_per_gain saturates at 1: e = 1 / (400 · 2.87738e-3).
    assert delta_q_limit(xl330, config) == pytest.approx(1 / (400 * 2.87738e-3))
    assert delta_q_limit(hrp2, config) == DEFAULT_DELTA_Q_LIMIT == 0.1
    config.controller.delta_q_limit = 0.05
    assert delta_q_limit(xl330, config) == 0.05


def test_a_reference_starts_with_a_smooth_move_from_the_measured_pose():
    q0 = np.array([0.0, 1.0])
    reference = JointReference.hold(q0, 2.0)
    start = np.array([0.3, 1.0])
    moved = reference.after_approach(start, speed=0.5)
    assert moved.approach_time == pytest.approx(1.875 * 0.3 / 0.5)
    q, v, a = moved.at(0.0)
    np.testing.assert_allclose(q, start)
    np.testing.assert_allclose(v, 0.0, atol=1e-12)
    # Its fastest joint at the middle of the move: 15/8 of the mean speed, 0.5 rad/s.
    _, v_mid, _ = moved.at(moved.approach_time / 2)
    assert abs(v_mid[0]) == pytest.approx(0.5, rel=1e-3)
    np.testing.assert_allclose(moved.at(moved.approach_time + 1.0)[0], q0)
    assert moved.end_time() == pytest.approx(2.0 + moved.approach_time, abs=1e-3)
    # Within the tolerance (1 mrad): the reference itself.
    assert reference.after_approach(q0 + 5e-4) is reference
