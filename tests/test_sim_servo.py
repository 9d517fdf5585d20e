"""The emulated Dynamixel bus (hardware.sim_servo, hardware.protocol2), tested with
ROBOTIS' own client, dynamixel_sdk, as the host: no mock of the SDK. Each test serves
a pseudo-terminal and talks to it with PortHandler, PacketHandler(2.0),
GroupSyncRead/Write, GroupBulkRead/Write, and asserts what the SDK returns (its comm
result and the error byte of the status), and, where the emulator's side matters,
its control table and physics.

The lock-step emulators run in a thread of this process (deterministic, no timing);
the real-time one runs as the command does, in a subprocess (`run_sim_servo`), so
that the SDK's busy polling and the physics do not share one interpreter. Only lower
bounds are asserted on wall time: the machine may be slow and loaded.
"""

import json
import math
import re
import signal
import subprocess
import sys
import termios
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import dynamixel_sdk as sdk
import numpy as np
import pytest
import serial
from dynamixel_sdk import port_handler as sdk_port
from dynamixel_sdk.robotis_def import COMM_RX_CORRUPT, COMM_RX_TIMEOUT, COMM_SUCCESS

from hrp2_drake.description.bus import (
    dynamixel_model,
    status_bytes,
    sync_read_bytes,
    wire_time,
)
from hrp2_drake.hardware.protocol2 import (
    ALERT_BIT,
    Instruction,
    PacketParser,
    StatusError,
    crc16,
    encode_packet,
    encode_status,
    stuff,
    unstuff,
)
from hrp2_drake.hardware.sim_servo import (
    ServoBusEmulator,
    ServoFault,
    parse_fault,
    status_times,
)
from hrp2_drake.robot.bus_servos import SimulatedServos
from hrp2_drake.robot.station import StationConfig

REPO = Path(__file__).resolve().parents[1]
ROBOT = "xl330_pendulum"
XL330 = dynamixel_model("XL330-M288")
#: The XL330's items by name: (address, size).
ITEM = {name: (r.address, r.size) for name, r in XL330.registers.items()}
#: 0xFFFDFFFF: a Goal Position (extended position mode, -131073 pulses) whose bytes
#: (FF FF FD FF) hold the pattern byte stuffing breaks up.
STUFFED_GOAL = -131073


@pytest.fixture(autouse=True)
def sdk_timeout(monkeypatch):
    """The SDK's packet timeout: 2 x LATENCY_TIMER + 2 ms; 202 ms here (34 ms by
    default), so that a loaded machine does not turn a late reply into a timeout."""
    monkeypatch.setattr(sdk_port, "LATENCY_TIMER", 100)


# --------------------------------------------------------------------- helpers


class Bus:
    """A lock-step emulator served in a thread, and the SDK on its port."""

    def __init__(self, emulator: ServoBusEmulator):
        self.emulator = emulator
        self.summary: dict | None = None
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()
        self.port = sdk.PortHandler(emulator.port)
        assert self.port.openPort()
        self.sdk = sdk.PacketHandler(2.0)

    def _serve(self) -> None:
        self.summary = self.emulator.serve()

    def end(self) -> None:
        try:
            self.port.closePort()
        except Exception:
            pass
        self.emulator.stop()
        self.thread.join(30)
        self.emulator.close()

    def servo(self, servo_id: int):
        return next(s for s in self.emulator.servos if s.id == servo_id)

    def read(self, servo_id: int, item: str):
        """(counts, comm result, error byte) of a READ of `item` (signed items as
        such)."""
        address, size = ITEM[item]
        call = {
            1: self.sdk.read1ByteTxRx,
            2: self.sdk.read2ByteTxRx,
            4: self.sdk.read4ByteTxRx,
        }[size]
        value, result, error = call(self.port, servo_id, address)
        if XL330.registers[item].signed and value >= 1 << (8 * size - 1):
            value -= 1 << (8 * size)
        return value, result, error

    def write(self, servo_id: int, item: str, value: int, size: int | None = None):
        """(comm result, error byte) of a WRITE of `value` to `item` (`size`: the
        bytes written, default the item's)."""
        address, item_size = ITEM[item]
        size = size or item_size
        call = {
            1: self.sdk.write1ByteTxRx,
            2: self.sdk.write2ByteTxRx,
            4: self.sdk.write4ByteTxRx,
        }[size]
        return call(self.port, servo_id, address, value & ((1 << (8 * size)) - 1))

    def raw(self, data: bytes, packets: int = 0, settle: float = 0.2) -> bytes:
        """Writes `data` as is and returns what comes back: `packets` whole packets
        (waited for up to 10 s), then whatever else comes within `settle` s."""
        self.port.clearPort()
        self.port.writePort(data)
        received, parser, count = b"", PacketParser(), 0
        deadline = time.perf_counter() + 10
        while count < packets and time.perf_counter() < deadline:
            chunk = bytes(self.port.readPort(1024))
            received += chunk
            count += len(parser.feed(chunk))
            time.sleep(0.001)
        return received + self.collect(settle)

    def collect(self, seconds: float) -> bytes:
        received, deadline = b"", time.perf_counter() + seconds
        while time.perf_counter() < deadline:
            received += bytes(self.port.readPort(1024))
            time.sleep(0.001)
        return received

    def status(self):
        """The next status packet through the SDK: (packet, comm result)."""
        self.port.setPacketTimeout(11)
        return self.sdk.rxPacket(self.port, False)


@contextmanager
def serving(ids=None, faults=(), robot=ROBOT):
    """A lock-step emulator of `robot` (one copy per group of `ids`) and the SDK."""
    config = StationConfig(robot=robot, scenario="fixed_base")
    joints = len(config.description().joints)
    copies = len(ids) // joints if ids else 1
    emulator = ServoBusEmulator(
        [SimulatedServos(config) for _ in range(copies)],
        ids=ids,
        lockstep=True,
        faults=faults,
    )
    bus = Bus(emulator)
    try:
        yield bus
    finally:
        bus.end()


def sdk_packet(servo_id: int, instruction: int, params=()) -> list[int]:
    """An instruction as the SDK's txPacket takes it (it fills header and CRC)."""
    length = len(params) + 3
    head = [0, 0, 0, 0, servo_id, length & 0xFF, length >> 8, instruction]
    return head + list(params) + [0, 0]


def status_ids(data: bytes) -> list[int]:
    """The IDs of the status packets in `data`, in order."""
    return [
        p.id for p in PacketParser().feed(data) if p.instruction == Instruction.STATUS
    ]


# --------------------------------------------------------------------- protocol 2.0


def test_crc_and_packets_match_the_e_manual_examples():
    # Protocol 2.0 e-manual: PING of ID 1, its status (XM430-W210: model 1030,
    # firmware 38), the SYNC_READ and BULK_WRITE examples.
    assert (
        encode_packet(1, Instruction.PING).hex(" ") == "ff ff fd 00 01 03 00 01 19 4e"
    )
    assert encode_status(1, 0, bytes((0x06, 0x04, 0x26)))[-2:] == bytes((0x65, 0x5D))
    sync_read = encode_packet(0xFE, Instruction.SYNC_READ, bytes((0x84, 0, 4, 0, 1, 2)))
    assert sync_read[-2:] == bytes((0xCE, 0xFA))
    bulk = bytes((1, 0x20, 0, 2, 0, 0xA0, 0, 2, 0x1F, 0, 1, 0, 0x50))
    assert encode_packet(0xFE, Instruction.BULK_WRITE, bulk)[-2:] == bytes((0xB7, 0x68))
    # And the SDK's own CRC (an independent implementation) on random bytes.
    rng = np.random.default_rng(0)
    handler = sdk.PacketHandler(2.0)
    for _ in range(50):
        data = rng.integers(0, 256, rng.integers(1, 40)).tolist()
        assert crc16(bytes(data)) == handler.updateCRC(0, data, len(data))


def test_byte_stuffing_round_trip():
    assert stuff(b"\x03\x74\x00\xff\xff\xfd\xff") == b"\x03\x74\x00\xff\xff\xfd\xfd\xff"
    assert unstuff(b"\xff\xff\xfd\xfd\xfd") == b"\xff\xff\xfd\xfd"
    rng = np.random.default_rng(1)
    for _ in range(500):
        body = bytes(rng.choice([0x00, 0xFD, 0xFF], rng.integers(0, 12)).tolist())
        stuffed = stuff(body)
        assert unstuff(stuffed) == body
        # Every FF FF FD of the stuffed body is followed by FD: no header inside.
        found = [
            i for i in range(len(stuffed) - 2) if stuffed[i : i + 3] == b"\xff\xff\xfd"
        ]
        assert all(stuffed[i + 3 : i + 4] == b"\xfd" for i in found)


def test_parser_resynchronises_on_the_header_and_reports_a_bad_crc():
    good = encode_packet(1, Instruction.WRITE, b"\x74\x00\xff\xff\xfd\xff")
    bad = bytearray(encode_packet(2, Instruction.PING))
    bad[-1] ^= 0x55
    stream = b"\x00\xff\xfd" + good + bytes(bad) + b"\xff\xff" + good
    parser = PacketParser()
    packets = [
        p for i in range(0, len(stream), 5) for p in parser.feed(stream[i : i + 5])
    ]
    assert [(p.id, p.crc_ok) for p in packets] == [(1, True), (2, False), (1, True)]
    assert packets[0].params == b"\x74\x00\xff\xff\xfd\xff"  # stuffing removed
    assert packets[0].size == len(good) and parser.bad_crc == 1 and parser.skipped == 5
    # A length field beyond any packet is noise: the next header is found.
    assert [
        p.id for p in PacketParser().feed(b"\xff\xff\xfd\x00\x01\xff\xff" + good)
    ] == [1]


# --------------------------------------------------------------------- faults


def test_fault_specs():
    cases = {
        "silent:1@2.0": ServoFault("silent", 1, 2.0),
        "crc:1@1.5x20": ServoFault("crc", 1, 1.5, 20),
        "hardware:1@2.0:overload": ServoFault("hardware", 1, 2.0, detail="overload"),
        "hardware:3@0.5:input_voltage_error": ServoFault(
            "hardware", 3, 0.5, detail="input voltage error"
        ),
        "close@3.0": ServoFault("close", -1, 3.0),
        "wrong_model:1:XM430-W350": ServoFault("wrong_model", 1, detail="XM430-W350"),
    }
    for spec, fault in cases.items():
        assert parse_fault(spec) == fault
        assert parse_fault(fault.spec()) == fault
    for bad in (
        "silent:1",
        "crc@1.0",
        "close:1@2",
        "hardware:1@2",
        "loud:1@2",
        "silent:1@-1",
        "crc:1@1x0",
        "wrong_model:1@2:XL330-M288",
        "silent:x@1",
    ):
        with pytest.raises(ValueError, match=re.escape(f"fault '{bad}'")) as error:
            parse_fault(bad)
        assert "\n" not in str(error.value)


def test_bad_ids_and_faults_are_one_line_errors():
    servos = SimulatedServos(StationConfig(robot=ROBOT, scenario="fixed_base"))
    for kwargs, message in (
        ({"ids": [1, 2]}, "2 IDs for 1 copy"),
        ({"ids": [253]}, "each one 0 to 252"),
        ({"faults": ["hardware:1@1:cold"]}, "'cold' is not a hardware error"),
        ({"faults": ["silent:9@1"]}, "no servo with ID 9"),
        ({"faults": ["wrong_model:1:XX-1"]}, "unknown servo model 'XX-1'"),
    ):
        with pytest.raises(ValueError, match=message) as error:
            ServoBusEmulator(servos, **kwargs)
        assert "\n" not in str(error.value)


# --------------------------------------------------------------------- the SDK


def test_ping_read_and_write_through_the_sdk():
    with serving() as bus:
        model, result, error = bus.sdk.ping(bus.port, 1)
        assert (model, result, error) == (1200, COMM_SUCCESS, 0)
        assert bus.sdk.ping(bus.port, 2)[1] == COMM_RX_TIMEOUT  # nobody has ID 2
        assert bus.read(1, "model_number") == (1200, COMM_SUCCESS, 0)
        assert bus.read(1, "firmware_version")[0] == XL330.firmware
        assert bus.read(1, "present_input_voltage")[0] == 74  # 7.4 V supply
        assert bus.read(1, "present_position")[0] == 2048  # hanging, q = 0
        # One write across two items (Torque Enable, LED): both written.
        assert bus.sdk.write2ByteTxRx(
            bus.port, 1, ITEM["torque_enable"][0], 0x0101
        ) == (COMM_SUCCESS, 0)
        assert bus.read(1, "torque_enable")[0] == 1 and bus.read(1, "led")[0] == 1
        assert bus.write(1, "goal_position", 2548) == (COMM_SUCCESS, 0)
        assert bus.read(1, "goal_position")[0] == 2548
        physics = bus.emulator.groups[0].physics
        bus_description = bus.emulator.bus
        np.testing.assert_array_equal(physics.goal, bus_description.to_radians([2548]))
        np.testing.assert_array_equal(physics.enabled, [1.0])
        # A read over several items, and over the bytes between them (0).
        data, result, error = bus.sdk.readTxRx(bus.port, 1, ITEM["torque_enable"][0], 4)
        assert (list(data), result, error) == ([1, 1, 0, 0], COMM_SUCCESS, 0)


def test_every_status_error_through_the_sdk():
    with serving() as bus:

        def error_of(*write):
            result, error = bus.write(*write)
            assert result == COMM_SUCCESS
            return error

        # Access: read-only, between items, beyond the table, EEPROM with torque on.
        assert error_of(1, "present_position", 0) == StatusError.ACCESS
        assert bus.sdk.write1ByteTxRx(bus.port, 1, 66, 0) == (
            COMM_SUCCESS,
            StatusError.ACCESS,
        )
        assert bus.sdk.read1ByteTxRx(bus.port, 1, 1000)[1:] == (
            COMM_SUCCESS,
            StatusError.ACCESS,
        )
        assert error_of(1, "torque_enable", 1) == 0
        assert error_of(1, "return_delay_time", 0) == StatusError.ACCESS
        assert error_of(1, "torque_enable", 0) == 0
        assert error_of(1, "return_delay_time", 0) == 0
        # Data length: 2 bytes of the 4-byte Goal Position; a write from its middle.
        assert error_of(1, "goal_position", 100, 2) == StatusError.DATA_LENGTH
        assert bus.sdk.write1ByteTxRx(bus.port, 1, 117, 0) == (
            COMM_SUCCESS,
            StatusError.DATA_LENGTH,
        )
        # Data range: outside the item's range; nothing written.
        assert error_of(1, "torque_enable", 2) == StatusError.DATA_RANGE
        assert error_of(1, "goal_position", 5000) == StatusError.DATA_RANGE
        assert bus.read(1, "goal_position")[0] == 2048
        # Data limit: the Goal Position beyond the Max Position Limit.
        assert error_of(1, "max_position_limit", 3000) == 0
        assert error_of(1, "goal_position", 3500) == StatusError.DATA_LIMIT
        assert error_of(1, "goal_position", 2900) == 0
        # Result fail: what the physics cannot run (PWM control mode, a P gain of 0).
        assert error_of(1, "operating_mode", 16) == StatusError.RESULT_FAIL
        assert error_of(1, "position_p_gain", 0) == StatusError.RESULT_FAIL
        # Instruction error: an undefined instruction; ACTION without REG_WRITE.
        _, result, error = bus.sdk.txRxPacket(bus.port, sdk_packet(1, 0x42))
        assert (result, error) == (COMM_SUCCESS, StatusError.INSTRUCTION)
        assert (
            bus.sdk.txPacket(bus.port, sdk_packet(1, Instruction.ACTION))
            == COMM_SUCCESS
        )
        packet, result = bus.status()
        assert (result, packet[8]) == (COMM_SUCCESS, StatusError.INSTRUCTION)
        # CRC error: an instruction whose CRC does not match, written raw.
        bad = bytearray(encode_packet(1, Instruction.READ, bytes((132, 0, 4, 0))))
        bad[-2] ^= 0x01
        bus.port.clearPort()
        bus.port.writePort(bytes(bad))
        packet, result = bus.status()
        assert (result, packet[4], packet[8]) == (COMM_SUCCESS, 1, StatusError.CRC)
    assert bus.summary["crc_errors"] == 1 and bus.summary["packets"]["bad CRC"] == 1


def test_broadcast_reg_write_action_and_status_return_level():
    with serving(ids=[1, 2, 3]) as bus:
        models, result = bus.sdk.broadcastPing(bus.port)
        assert result == COMM_SUCCESS
        assert models == {i: [1200, XL330.firmware] for i in (1, 2, 3)}
        # Broadcast WRITE: every servo writes, none answers.
        assert bus.write(0xFE, "led", 1) == (COMM_SUCCESS, 0)
        assert bus.collect(0.2) == b""
        assert [bus.read(i, "led")[0] for i in (1, 2, 3)] == [1, 1, 1]
        # Broadcast READ: no status either.
        assert (
            bus.raw(encode_packet(0xFE, Instruction.READ, bytes((65, 0, 1, 0)))) == b""
        )
        # REG_WRITE waits for ACTION.
        address = ITEM["goal_position"][0]
        assert bus.sdk.regWriteTxRx(bus.port, 2, address, 4, [0x10, 0x09, 0, 0]) == (
            COMM_SUCCESS,
            0,
        )
        assert bus.read(2, "registered_instruction")[0] == 1
        assert bus.read(2, "goal_position")[0] == 2048
        assert bus.sdk.action(bus.port, 0xFE) == COMM_SUCCESS
        assert bus.collect(0.2) == b""  # broadcast ACTION: no status
        assert bus.read(2, "goal_position")[0] == 0x0910
        assert bus.read(2, "registered_instruction")[0] == 0
        np.testing.assert_array_equal(
            bus.emulator.groups[1].physics.goal, bus.emulator.bus.to_radians([0x0910])
        )
        # Status Return Level 1: READ and PING answered, WRITE not (but done).
        assert bus.write(3, "status_return_level", 1) == (COMM_SUCCESS, 0)
        assert bus.write(3, "led", 0)[0] == COMM_RX_TIMEOUT
        assert bus.read(3, "led") == (0, COMM_SUCCESS, 0)
        assert bus.write(3, "status_return_level", 0)[0] == COMM_RX_TIMEOUT
        assert bus.read(3, "led")[1] == COMM_RX_TIMEOUT  # level 0: PING only
        assert bus.sdk.ping(bus.port, 3)[:2] == (1200, COMM_SUCCESS)


def test_byte_stuffing_both_ways_through_the_sdk():
    with serving() as bus:
        assert bus.write(1, "operating_mode", 4) == (
            COMM_SUCCESS,
            0,
        )  # extended position
        # The SDK (4.1.0) writes this packet without stuffing (its addStuffing's
        # result is dropped); its CRC covers the bytes as sent, so a device takes it.
        assert bus.write(1, "goal_position", STUFFED_GOAL) == (COMM_SUCCESS, 0)
        assert bus.servo(1).get("goal_position") == STUFFED_GOAL
        np.testing.assert_array_equal(
            bus.emulator.groups[0].physics.goal,
            bus.emulator.bus.to_radians([STUFFED_GOAL]),
        )
        # Read back: the status needs stuffing, and the SDK removes it.
        assert bus.read(1, "goal_position") == (STUFFED_GOAL, COMM_SUCCESS, 0)
        read = encode_packet(
            1, Instruction.READ, bytes((ITEM["goal_position"][0], 0, 4, 0))
        )
        raw = bus.raw(read, packets=1)
        assert b"\xff\xff\xfd\xfd" in raw and len(raw) == 16  # 15 bytes + 1 of stuffing
        assert raw[5] | raw[6] << 8 == 9  # the length counts it
        # A stuffed instruction, as the e-manual has the host send it.
        assert bus.write(1, "goal_position", 0) == (COMM_SUCCESS, 0)
        data = ITEM["goal_position"][0].to_bytes(2, "little") + (
            STUFFED_GOAL & 0xFFFFFFFF
        ).to_bytes(4, "little")
        write = encode_packet(1, Instruction.WRITE, data)
        assert b"\xff\xff\xfd\xfd" in write
        bus.port.clearPort()
        bus.port.writePort(write)
        packet, result = bus.status()
        assert (result, packet[8]) == (COMM_SUCCESS, 0)
        assert bus.read(1, "goal_position") == (STUFFED_GOAL, COMM_SUCCESS, 0)


def test_corrupted_status_is_rx_corrupt():
    with serving(ids=[1, 2], faults=["crc:2@0x2"]) as bus:
        assert bus.sdk.ping(bus.port, 2)[1] == COMM_RX_CORRUPT
        reader = sdk.GroupSyncRead(bus.port, bus.sdk, *bus.emulator.bus.read_block())
        for servo_id in (1, 2):
            reader.addParam(servo_id)
        assert reader.txRxPacket() == COMM_RX_CORRUPT
        assert bus.sdk.ping(bus.port, 2)[:2] == (
            1200,
            COMM_SUCCESS,
        )  # the fault is over
        assert reader.txRxPacket() == COMM_SUCCESS


def test_silent_servo_times_out_and_silences_the_rest_of_a_sync_read():
    with serving(ids=[1, 2, 3], faults=["silent:2@0.01"]) as bus:
        address, length = bus.emulator.bus.read_block()
        reader = sdk.GroupSyncRead(bus.port, bus.sdk, address, length)
        for servo_id in (1, 2, 3):
            reader.addParam(servo_id)
        assert [reader.txRxPacket() for _ in range(2)] == [COMM_SUCCESS] * 2  # t = 0, T
        assert reader.txRxPacket() == COMM_RX_TIMEOUT  # t = 2T = 0.01 s: ID 2 is silent
        # On the wire: ID 1 answers; ID 3 waits for ID 2's status, which never comes.
        sync_read = encode_packet(
            0xFE, Instruction.SYNC_READ, bytes((address, 0, length, 0, 1, 2, 3))
        )
        assert status_ids(bus.raw(sync_read, packets=1)) == [1]
        assert bus.sdk.ping(bus.port, 2)[1] == COMM_RX_TIMEOUT
        assert bus.sdk.ping(bus.port, 3)[:2] == (1200, COMM_SUCCESS)
        # It still hears: a write without a status is done (the PING after it
        # returns once the emulator has handled both, in order).
        assert bus.write(2, "led", 1)[0] == COMM_RX_TIMEOUT
        assert bus.sdk.ping(bus.port, 1)[1] == COMM_SUCCESS
        assert bus.servo(2).get("led") == 1
    assert bus.summary["faults"] == [{"fault": "silent:2@0.01", "time": 0.01}]


def test_hardware_error_alert_shutdown_and_reboot():
    with serving(faults=["hardware:1@0.01:overload"]) as bus:
        assert bus.write(1, "torque_enable", 1) == (COMM_SUCCESS, 0)
        address, length = bus.emulator.bus.read_block()
        reader = sdk.GroupSyncRead(bus.port, bus.sdk, address, length)
        reader.addParam(1)
        errors = []
        for _ in range(3):  # t = 0, T, 2T = 0.01 s
            assert reader.txPacket() == COMM_SUCCESS
            errors.append(bus.sdk.readRx(bus.port, 1, length)[2])
        assert errors == [0, 0, ALERT_BIT]
        overload = 1 << XL330.hardware_errors.index("overload")
        assert bus.read(1, "hardware_error_status") == (
            overload,
            COMM_SUCCESS,
            ALERT_BIT,
        )
        # The Shutdown item (53: overload among its bits) switched torque off.
        assert bus.read(1, "torque_enable")[0] == 0
        np.testing.assert_array_equal(bus.emulator.groups[0].physics.enabled, [0.0])
        assert bus.write(1, "torque_enable", 1) == (
            COMM_SUCCESS,
            ALERT_BIT | StatusError.RESULT_FAIL,
        )
        # REBOOT is the only way back.
        assert bus.sdk.reboot(bus.port, 1)[0] == COMM_SUCCESS
        assert bus.read(1, "hardware_error_status") == (0, COMM_SUCCESS, 0)
        assert bus.write(1, "torque_enable", 1) == (COMM_SUCCESS, 0)
        np.testing.assert_array_equal(bus.emulator.groups[0].physics.enabled, [1.0])


def test_sync_and_bulk_read_and_write_of_several_servos():
    with serving(ids=[1, 2, 3]) as bus:
        goal_address, goal_size = ITEM["goal_position"]
        torque = sdk.GroupSyncWrite(bus.port, bus.sdk, ITEM["torque_enable"][0], 1)
        goals = sdk.GroupSyncWrite(bus.port, bus.sdk, goal_address, goal_size)
        for servo_id, goal in ((1, 2448), (2, 2048), (3, 1648)):
            torque.addParam(servo_id, [1])
            goals.addParam(servo_id, list(goal.to_bytes(4, "little")))
        assert torque.txPacket() == COMM_SUCCESS
        address, length = bus.emulator.bus.read_block()
        reader = sdk.GroupSyncRead(bus.port, bus.sdk, address, length)
        for servo_id in (1, 2, 3):
            reader.addParam(servo_id)
        for _ in range(40):  # 0.2 s: three pendulums, three goals
            assert reader.txRxPacket() == COMM_SUCCESS
            assert goals.txPacket() == COMM_SUCCESS
        position = [reader.getData(i, *ITEM["present_position"]) for i in (1, 2, 3)]
        assert position[0] > 2048 + 100 and abs(position[1] - 2048) <= 2
        assert position[2] < 2048 - 100
        # BULK_READ: another item per servo; BULK_WRITE likewise.
        bulk = sdk.GroupBulkRead(bus.port, bus.sdk)
        for servo_id, item in (
            (1, "present_position"),
            (2, "torque_enable"),
            (3, "present_input_voltage"),
        ):
            assert bulk.addParam(servo_id, *ITEM[item])
        assert bulk.txRxPacket() == COMM_SUCCESS
        assert bulk.getData(1, *ITEM["present_position"]) > 2048 + 100
        assert bulk.getData(2, *ITEM["torque_enable"]) == 1
        assert bulk.getData(3, *ITEM["present_input_voltage"]) == 74
        writer = sdk.GroupBulkWrite(bus.port, bus.sdk)
        writer.addParam(1, ITEM["led"][0], 1, [1])
        writer.addParam(3, goal_address, goal_size, list((2000).to_bytes(4, "little")))
        assert writer.txPacket() == COMM_SUCCESS
        assert bus.read(1, "led")[0] == 1 and bus.read(3, "goal_position")[0] == 2000


def test_lockstep_contract_matches_the_in_process_calls():
    """Period k: the SYNC_READ samples at k*T, the SYNC_WRITE acts at k*T + d; the
    same calls on a second SimulatedServos give the same numbers, bit for bit."""
    config = StationConfig(robot=ROBOT, scenario="fixed_base")
    twin = SimulatedServos(config)
    with serving() as bus:
        description = bus.emulator.bus
        period = bus.emulator.robot.sensors.period
        delay = description.timing().read_to_write
        physics = bus.emulator.groups[0].physics
        assert bus.write(1, "torque_enable", 1) == (COMM_SUCCESS, 0)
        twin.set_enabled(np.ones(1))
        address, length = description.read_block()
        reader = sdk.GroupSyncRead(bus.port, bus.sdk, address, length)
        reader.addParam(1)
        writer = sdk.GroupSyncWrite(bus.port, bus.sdk, *ITEM["goal_position"])
        velocity_unit = XL330.registers["present_velocity"].unit
        positions = []
        for k in range(30):
            assert reader.txRxPacket() == COMM_SUCCESS
            assert physics.time == pytest.approx(k * period, abs=1e-12)
            tick = bus.read(1, "realtime_tick")[0]
            assert tick == math.floor(k * period * 1000 + 1e-6)
            twin.advance_to(k * period)
            present = twin.present()
            position = reader.getData(1, *ITEM["present_position"])
            velocity = reader.getData(1, *ITEM["present_velocity"])
            velocity -= (velocity >= 1 << 31) << 32
            assert position == description.to_pulses(present.position)[0]
            assert velocity == round(present.velocity[0] / velocity_unit)
            positions.append(position)
            goal = 2048 + round(600 * math.sin(2 * math.pi * k / 30))
            writer.clearParam()
            writer.addParam(1, list(goal.to_bytes(4, "little")))
            assert writer.txPacket() == COMM_SUCCESS
            # The PING's status comes once the write is handled: time has moved.
            assert bus.sdk.ping(bus.port, 1)[1] == COMM_SUCCESS
            assert physics.time == pytest.approx(k * period + delay, abs=1e-12)
            twin.advance_to(k * period + delay)
            twin.set_goal(description.to_radians([goal]))
            np.testing.assert_array_equal(physics.goal, twin.goal)
        assert max(positions) - min(positions) > 50  # the pendulum moved
    assert bus.summary["periods"] == 30 and bus.summary["mode"] == "lock-step"


def test_id_change_port_reopen_and_wrong_model():
    with serving(ids=[1, 2], faults=["wrong_model:2:XM430-W350"]) as bus:
        assert bus.sdk.ping(bus.port, 2)[:2] == (1020, COMM_SUCCESS)
        assert bus.read(2, "model_number")[0] == 1020
        assert bus.write(1, "id", 2) == (COMM_SUCCESS, StatusError.RESULT_FAIL)  # taken
        assert bus.write(1, "id", 7) == (COMM_SUCCESS, 0)  # answered from ID 1
        assert bus.sdk.ping(bus.port, 1)[1] == COMM_RX_TIMEOUT
        assert bus.sdk.ping(bus.port, 7)[:2] == (1200, COMM_SUCCESS)
        # The host closes its port and opens it again: the bus is still there.
        bus.port.closePort()
        bus.port = sdk.PortHandler(bus.emulator.port)
        assert bus.port.openPort()
        assert bus.sdk.ping(bus.port, 7)[:2] == (1200, COMM_SUCCESS)


def test_close_fault_takes_the_port_away():
    with serving(faults=["close@0.01"]) as bus:
        reader = sdk.GroupSyncRead(bus.port, bus.sdk, *bus.emulator.bus.read_block())
        reader.addParam(1)
        assert [reader.txRxPacket() for _ in range(2)] == [COMM_SUCCESS] * 2
        # The third sync read (t = 0.01 s) closes the port: the SDK's next call on
        # it fails, with pyserial's SerialException (reading, writing) or termios'
        # error (flushing), depending on where the hang-up finds it.
        with pytest.raises((serial.SerialException, termios.error)):
            for _ in range(100):
                reader.txRxPacket()
        bus.thread.join(30)
    assert bus.summary["stopped"] == "port closed by the fault close@0.01"
    assert bus.summary["periods"] == 3


def test_gain_applies_when_all_servos_of_a_robot_agree():
    robot = "open_manipulator_x"
    description = StationConfig(robot=robot, scenario="fixed_base").description()
    with serving(robot=robot) as bus:
        ids = list(description.bus.ids)
        physics = bus.emulator.groups[0].physics
        reader = sdk.GroupSyncRead(bus.port, bus.sdk, *description.bus.read_block())
        for servo_id in ids:
            assert bus.sdk.ping(bus.port, servo_id)[:2] == (1020, COMM_SUCCESS)
            reader.addParam(servo_id)
        assert reader.txRxPacket() == COMM_SUCCESS
        before = physics.gain
        for servo_id in ids[:-1]:
            assert bus.write(servo_id, "position_p_gain", 900) == (COMM_SUCCESS, 0)
            assert physics.gain == before  # the servos disagree: the physics waits
        assert bus.write(ids[-1], "position_p_gain", 900) == (COMM_SUCCESS, 0)
        assert physics.gain == 900
    assert bus.summary["gain_disagreements"] == len(ids) - 1


# --------------------------------------------------------------------- real time


def test_status_times_follow_the_wire_and_the_return_delays():
    # Three statuses of 19 bytes at 1 Mbit/s (190 µs each), return delays 500, 0
    # and 20 µs, after an instruction that ends at 1 ms; a 1 ms adapter latency.
    times = status_times(1e-3, [(500e-6, 19), (0.0, 19), (20e-6, 19)], 1e6, 1e-3)
    ends = [1e-3 + 500e-6 + 190e-6, 1e-3 + 500e-6 + 380e-6, 1e-3 + 520e-6 + 570e-6]
    np.testing.assert_allclose([e for e, _ in times], ends, rtol=0, atol=1e-12)
    np.testing.assert_allclose([a for _, a in times], np.add(ends, 1e-3), atol=1e-12)
    # The register the host writes is the delay the emulator waits.
    with serving() as bus:
        delay = XL330.registers["return_delay_time"]
        assert bus.write(1, "return_delay_time", 250) == (COMM_SUCCESS, 0)
        assert bus.servo(1).return_delay == pytest.approx(250 * delay.unit)


#: Robot seconds per wall second of the real-time test: three simulated pendulums
#: cost about 0.7 s of a core per robot second, the SDK's busy polling takes a core,
#: and the machine may be loaded: at 0.1 the emulator keeps up with a fraction of a
#: core.
RATE = 0.1
REAL_TIME_SCRIPT = """
import sys
from hrp2_drake.hardware.sim_servo import run_sim_servo
run_sim_servo("xl330_pendulum", ids=[1, 2, 3], faults=["wrong_model:3:XM430-W350"],
              rate=float(sys.argv[2]), out=sys.argv[1])
"""


def test_real_time_command_budget_clock_and_sigterm(tmp_path, monkeypatch):
    # A real-time emulator on a loaded machine may fall behind the clock (it counts
    # it): 2 s before the SDK gives up on a status.
    monkeypatch.setattr(sdk_port, "LATENCY_TIMER", 1000)
    process = subprocess.Popen(
        [sys.executable, "-c", REAL_TIME_SCRIPT, str(tmp_path), str(RATE)],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        line = process.stdout.readline()
        match = re.fullmatch(
            r"sim-servo: xl330_pendulum on (/dev/\S+) \(3 servos, ids 1, 2, 3, "
            r"1000000 bit/s, real time\)\n",
            line,
        )
        assert match, (
            line,
            process.stderr.read() if process.poll() is not None else "",
        )
        port = sdk.PortHandler(match[1])
        assert port.openPort()
        handler = sdk.PacketHandler(2.0)
        assert handler.ping(port, 3)[:2] == (1020, COMM_SUCCESS)
        delay = XL330.registers["return_delay_time"]
        for servo_id in (1, 2, 3):  # 500 µs each
            assert handler.write1ByteTxRx(port, servo_id, delay.address, 250) == (
                COMM_SUCCESS,
                0,
            )
        description = (
            StationConfig(robot=ROBOT, scenario="fixed_base").description().bus
        )
        address, length = description.read_block()
        budget = (
            wire_time(sync_read_bytes(3), description.baud)
            + 3 * (250 * delay.unit + wire_time(status_bytes(length), description.baud))
            + description.adapter_latency
        )
        reader = sdk.GroupSyncRead(port, handler, address, length)
        for servo_id in (1, 2, 3):
            reader.addParam(servo_id)
        elapsed = []
        for _ in range(20):
            start = time.perf_counter()
            result = reader.txRxPacket()
            elapsed.append(time.perf_counter() - start)
            assert result == COMM_SUCCESS
        assert min(elapsed) >= budget / RATE  # a lower bound only
        # Robot time follows the wall clock (x RATE): the tick grows at least as the
        # time from one reply's arrival to the next instruction's sending.
        tick_unit = XL330.registers["realtime_tick"].unit
        first = handler.read2ByteTxRx(port, 1, ITEM["realtime_tick"][0])
        received = time.perf_counter()
        time.sleep(0.2)
        sent = time.perf_counter()
        second = handler.read2ByteTxRx(port, 1, ITEM["realtime_tick"][0])
        assert first[1] == second[1] == COMM_SUCCESS
        assert (
            second[0] - first[0] >= math.floor(RATE * (sent - received) / tick_unit) - 1
        )
        assert second[0] - first[0] > 0
        port.closePort()
    finally:
        process.send_signal(signal.SIGTERM)
        process.communicate(timeout=60)
    assert process.returncode == 0
    summary = json.loads((tmp_path / "sim_servo.json").read_text())
    assert summary["stopped"] == "signal SIGTERM" and summary["mode"] == "real time"
    assert summary["rate"] == RATE
    assert summary["packets"]["SYNC_READ"] == summary["periods"] == 20
    assert summary["faults"] == [{"fault": "wrong_model:3:XM430-W350", "time": 0.0}]
    assert "| SYNC_READ | 20 |" in (tmp_path / "sim_servo.md").read_text()
