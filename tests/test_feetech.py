"""The emulated Feetech bus (hardware.sim_servo with hardware.feetech_protocol), tested
with Feetech's own client, scservo_sdk (PyPI feetech-servo-sdk, as LeRobot uses it), as
the host: no mock of the SDK. Each test serves the SO-101's six STS3215 on a
pseudo-terminal in lock step (a thread of this process: deterministic, no timing) and
talks to it with PortHandler, PacketHandler(0) (STS: little-endian), GroupSyncRead and
GroupSyncWrite, asserting what the SDK returns (its comm result and the status's
error byte) and, where the emulator's side matters, its table and physics.
"""

import threading
from contextlib import contextmanager

import numpy as np
import pytest
import scservo_sdk as scs
from pydrake.multibody.tree import JacobianWrtVariable
from scservo_sdk import port_handler as scs_port

from hrp2_drake.description import load_robot_description
from hrp2_drake.description.bus import (
    FRAMINGS,
    servo_model,
    status_bytes,
    sync_read_bytes,
    sync_write_bytes,
)
from hrp2_drake.hardware.feetech_protocol import (
    PacketParser,
    checksum,
    encode_packet,
    encode_status,
)
from hrp2_drake.hardware.protocol2 import StatusError
from hrp2_drake.hardware.sim_servo import ServoBusEmulator, parse_fault
from hrp2_drake.robot.bus_servos import SimulatedServos
from hrp2_drake.robot.station import StationConfig

ROBOT = "so101"
STS3215 = servo_model("feetech", "STS3215")
ITEM = {name: (r.address, r.size) for name, r in STS3215.registers.items()}
OK, TIMEOUT, CORRUPT = scs.COMM_SUCCESS, scs.COMM_RX_TIMEOUT, scs.COMM_RX_CORRUPT


@pytest.fixture(autouse=True)
def sdk_timeout(monkeypatch):
    """The SDK's packet timeout: 2 x LATENCY_TIMER + 2 ms; 202 ms here (34 ms by
    default), so that a loaded machine does not turn a late reply into a timeout."""
    monkeypatch.setattr(scs_port, "LATENCY_TIMER", 100)


class Bus:
    """A lock-step emulator served in a thread, and the SDK on its port."""

    def __init__(self, emulator: ServoBusEmulator):
        self.emulator = emulator
        self.thread = threading.Thread(target=emulator.serve, daemon=True)
        self.thread.start()
        self.port = scs.PortHandler(emulator.port)
        assert self.port.openPort()
        self.sdk = scs.PacketHandler(0)

    def end(self) -> None:
        self.port.closePort()
        self.emulator.stop()
        self.thread.join(30)
        self.emulator.close()

    def servo(self, servo_id: int):
        return next(s for s in self.emulator.servos if s.id == servo_id)

    def read(self, servo_id: int, item: str):
        """(counts, comm result, error byte) of a READ of `item`, decoded as the
        model says (sign-magnitude)."""
        address, size = ITEM[item]
        call = {1: self.sdk.read1ByteTxRx, 2: self.sdk.read2ByteTxRx}[size]
        raw, result, error = call(self.port, servo_id, address)
        return STS3215.registers[item].from_raw(raw), result, error

    def write(self, servo_id: int, item: str, value: int):
        """(comm result, error byte) of a WRITE of `item`."""
        address, size = ITEM[item]
        call = {1: self.sdk.write1ByteTxRx, 2: self.sdk.write2ByteTxRx}[size]
        raw = STS3215.registers[item].to_raw(value)
        return call(self.port, servo_id, address, raw)


@contextmanager
def bus(faults=(), **kwargs):
    emulator = ServoBusEmulator(
        SimulatedServos(StationConfig(robot=ROBOT, scenario="fixed_base")),
        lockstep=True,
        faults=faults,
        **kwargs,
    )
    b = Bus(emulator)
    try:
        yield b
    finally:
        b.end()


# --------------------------------------------------------------------- the wire


def test_packets_are_feetech_framing_with_the_inverted_sum_checksum():
    # PING of ID 1: FF FF 01 02 01, checksum ~(1 + 2 + 1) = 0xFB.
    assert encode_packet(1, 1) == bytes.fromhex("ffff010201fb")
    # A status of ID 1 with the overload bit (32) and two bytes 0x00 0x08.
    status = encode_status(1, StatusError.NONE, 32, b"\x00\x08")
    assert status == bytes.fromhex("ffff010420") + b"\x00\x08" + bytes(
        (~(1 + 4 + 32 + 8) & 0xFF,)
    )
    assert checksum(status[2:-1]) == status[-1]
    # No status for a bad checksum or an unknown instruction (Feetech has no code).
    assert encode_status(1, StatusError.CRC, 0) == b""
    assert encode_status(1, StatusError.INSTRUCTION, 0) == b""
    # The parser: packets split anywhere, noise skipped, a bad checksum marked.
    parser = PacketParser()
    write = encode_packet(3, 3, bytes((42, 0x00, 0x08)))
    bad = bytearray(encode_packet(2, 1))
    bad[-1] ^= 0xFF
    stream = (
        b"\x00\x12" + write + bytes(bad) + encode_packet(0xFE, 0x82, b"\x38\x04\x01")
    )
    packets = parser.feed(stream[:5]) + parser.feed(stream[5:])
    assert [(p.id, p.instruction, p.crc_ok) for p in packets] == [
        (3, 3, True),
        (2, 1, False),
        (0xFE, 0x82, True),
    ]
    assert packets[0].params == bytes((42, 0x00, 0x08))
    assert (parser.skipped, parser.bad_crc) == (2, 1)


def test_the_wire_budget_counts_feetech_bytes():
    feetech = FRAMINGS["feetech"]
    # SYNC_READ of 6 IDs: FF FF FE LEN 82 addr len + 6 IDs + checksum = 14 bytes; a
    # status of 4 bytes: FF FF ID LEN ERR + 4 + checksum = 10; SYNC_WRITE of 2 bytes to
    # 6: FF FF FE LEN 83 addr len + 6 x 3 + checksum = 26.
    assert sync_read_bytes(6, feetech) == 14
    assert status_bytes(4, feetech) == 10
    assert sync_write_bytes(6, 2, feetech) == 26
    timing = load_robot_description(ROBOT).bus.timing()
    assert timing.read_instruction + timing.statuses == pytest.approx(740e-6)
    assert timing.cycle == pytest.approx(2.5e-3)


def test_sign_magnitude_encodings():
    position, load = (
        STS3215.registers["goal_position"],
        STS3215.registers["present_load"],
    )
    assert position.to_raw(-300) == 0x8000 | 300
    assert position.from_raw(0x8000 | 300) == -300
    assert STS3215.encode("goal_position", -300) == bytes((300 & 0xFF, 0x80 | 1))
    assert load.from_raw(0x400 | 16) == -16 and load.to_raw(-16) == 0x410
    assert STS3215.si("present_load", [0x410, 16]).tolist() == [-0.016, 0.016]
    assert position.counts_range() == (-32767, 32767)


# --------------------------------------------------------------------- the SDK


def test_ping_read_write_as_the_sdk_sees_them():
    with bus() as b:
        for servo_id in range(1, 7):
            model, result, error = b.sdk.ping(b.port, servo_id)
            assert (model, result, error) == (777, OK, 0)
        assert b.sdk.ping(b.port, 9)[1] == TIMEOUT  # nobody there
        assert b.read(2, "return_delay_time") == (0, OK, 0)
        assert b.read(2, "position_p_gain") == (32, OK, 0)
        assert b.read(2, "present_input_voltage") == (74, OK, 0)
        # A goal reaches the physics (pulse 2048: q = 0); outside the position
        # limits (0-4095 in position mode) it is refused.
        assert b.write(1, "torque_enable", 1) == (OK, 0)
        assert b.write(1, "goal_position", 2048 - 100) == (OK, 0)
        assert b.write(1, "goal_position", -5) == (OK, 0)
        assert b.read(1, "goal_position") == (1948, OK, 0)
        group = b.servo(1).group
        assert group.physics.goal[0] == pytest.approx(-100 * 2 * np.pi / 4096)
        # A negative value in sign-magnitude (the homing offset's bit 11) both ways.
        assert b.write(1, "torque_enable", 0) == (OK, 0)
        assert b.write(1, "homing_offset", -100) == (OK, 0)
        assert b.servo(1).table[31:33] == bytes((100, 0x08))
        assert b.read(1, "homing_offset") == (-100, OK, 0)
        # A 2-byte read over two 1-byte items, any bytes of the table.
        data, result, error = b.sdk.readTxRx(b.port, 3, 62, 2)
        assert (result, error) == (OK, 0) and data == [74, 30]


def test_a_refused_write_has_no_error_bit_and_writes_nothing():
    with bus() as b:
        assert b.write(4, "torque_enable", 1) == (OK, 0)
        # The ID (EEPROM) with torque on: refused, answered without an error bit.
        assert b.write(4, "id", 9) == (OK, 0)
        assert b.read(4, "id") == (4, OK, 0)
        # A read-only item and an operating mode the physics cannot run: the same.
        assert b.write(4, "present_position", 7) == (OK, 0)
        assert b.write(4, "torque_enable", 0) == (OK, 0)
        assert b.write(4, "operating_mode", 2) == (OK, 0)
        assert b.read(4, "operating_mode") == (0, OK, 0)
        # With torque off the EEPROM takes it.
        assert b.write(4, "return_delay_time", 5) == (OK, 0)
        assert b.read(4, "return_delay_time") == (5, OK, 0)


def test_reg_write_acts_at_action():
    with bus() as b:
        address, _ = ITEM["goal_position"]
        result, error = b.sdk.regWriteTxRx(b.port, 5, address, 2, [0x10, 0x08])
        assert (result, error) == (OK, 0)
        assert b.read(5, "registered_instruction") == (1, OK, 0)
        assert b.read(5, "goal_position")[0] != 0x0810
        assert b.sdk.action(b.port, 5) == OK
        assert b.read(5, "goal_position") == (0x0810, OK, 0)
        assert b.read(5, "registered_instruction") == (0, OK, 0)


def test_sync_write_then_sync_read_one_status_per_servo():
    with bus() as b:
        goal = STS3215.registers["goal_position"]
        writer = scs.GroupSyncWrite(b.port, b.sdk, goal.address, goal.size)
        goals = {1: 2000, 2: 2100, 3: 10, 4: 2048, 5: 1500, 6: 2600}
        for servo_id, value in goals.items():
            assert writer.addParam(
                servo_id, list(STS3215.encode("goal_position", value))
            )
        assert writer.txPacket() == OK
        for servo_id, value in goals.items():
            assert b.read(servo_id, "goal_position") == (value, OK, 0)
        position = STS3215.registers["present_position"]
        reader = scs.GroupSyncRead(b.port, b.sdk, position.address, 4)
        for servo_id in goals:
            reader.addParam(servo_id)
        assert reader.txRxPacket() == OK
        present = b.emulator.groups[0].counts()["present_position"]
        for k, servo_id in enumerate(goals):
            raw = reader.getData(servo_id, position.address, 2)
            assert position.from_raw(raw) == present[k]
        assert b.emulator.summary()["packets"]["SYNC_READ"] == 1


def test_status_error_bits_are_the_servo_status():
    with bus(faults=["hardware:3@0:overload"]) as b:
        b.emulator._advance(0.0)  # the fault at robot time 0
        value, result, error = b.read(3, "hardware_error_status")
        assert (value, result, error) == (32, OK, 32)
        assert "Overload" in b.sdk.getRxPacketError(error)
        assert b.read(2, "hardware_error_status") == (0, OK, 0)
        # Unloading Condition (shutdown: 44 = temperature, current, overload): off.
        assert b.read(3, "torque_enable") == (0, OK, 32)
        assert b.write(3, "torque_enable", 1) == (OK, 32)
        assert b.read(3, "torque_enable")[0] == 0


def test_silent_servo_and_corrupt_statuses_and_bad_checksums():
    with bus(faults=["silent:4@0", "crc:2@0x2"]) as b:
        b.emulator._advance(0.0)
        assert b.sdk.ping(b.port, 4)[1] == TIMEOUT
        assert b.sdk.ping(b.port, 2)[1] == CORRUPT
        assert b.read(2, "id")[1] == CORRUPT
        assert b.read(2, "id") == (2, OK, 0)  # the burst is over
        # A sync read: servo 4 silent silences 5 and 6 after it (one status each,
        # back to back, in the list's order).
        position = STS3215.registers["present_position"]
        reader = scs.GroupSyncRead(b.port, b.sdk, position.address, 2)
        for servo_id in range(1, 7):
            reader.addParam(servo_id)
        assert reader.txPacket() == OK
        results = [b.sdk.readRx(b.port, i, 2)[1] for i in range(1, 7)]
        assert results == [OK, OK, OK, TIMEOUT, TIMEOUT, TIMEOUT]
        # The host's packet with a bad checksum: no status, counted.
        b.port.clearPort()
        bad = bytearray(encode_packet(1, 1))
        bad[-1] ^= 0x55
        b.port.writePort(bytes(bad))
        b.port.setPacketTimeoutMillis(100)
        assert b.sdk.rxPacket(b.port)[1] == TIMEOUT
        assert b.emulator.summary()["crc_errors"] == 1


def test_response_status_level_and_unknown_instructions():
    with bus() as b:
        assert b.write(6, "status_return_level", 0) == (OK, 0)  # answered as before
        # Level 0: a WRITE gets no status, READ and PING still do.
        assert b.sdk.write1ByteTxRx(b.port, 6, ITEM["lock"][0], 0)[0] == TIMEOUT
        assert b.read(6, "lock") == (0, OK, 0)
        assert b.sdk.ping(b.port, 6)[1] == OK
        # Protocol 2.0's REBOOT (8) is not an STS instruction: no status.
        b.port.clearPort()
        b.port.writePort(encode_packet(1, 8))
        b.port.setPacketTimeoutMillis(100)
        assert b.sdk.rxPacket(b.port)[1] == TIMEOUT
        assert b.emulator.summary()["packets"]["REBOOT"] == 1


def test_a_push_moves_the_joint_the_servo_holds_by_its_stiffness():
    """`push:ID@T:TAU`: an external torque on servo ID's joint from T on (a hand);
    the servo holding the arm (P 32: 17.8 N m/rad, K_tau = 0.0562 rad/(N m)) gives
    way by TAU K_tau, to the encoder's pulse."""
    with pytest.raises(ValueError, match="not a torque"):
        parse_fault("push:1@1.0:hard")
    assert parse_fault("push:2@1.5:-0.2").spec() == "push:2@1.5:-0.2"
    with bus(faults=["push:1@0.5:0.2"]) as b:
        physics = b.emulator.groups[0].physics
        physics.set_goal(physics.present().position)
        physics.set_enabled(np.ones(6))
        b.emulator._advance(0.5)
        before = physics.present().position.copy()
        assert physics.external_torque.tolist() == [0.2, 0, 0, 0, 0, 0]
        b.emulator._advance(1.5)
        moved = physics.present().position - before
        assert moved[0] == pytest.approx(0.2 * 0.0561887, abs=2 * np.pi / 4096)


@pytest.mark.parametrize(
    "spec, message",
    [
        ("push-force:gripper_frame_link@1.0:0,0", "not a force in N"),
        ("push-force:gripper_frame_link@1.0:0,0,nan", "not a force in N"),
        ("push-force:gripper_frame_link@-1:0,0,1", "not a time in seconds"),
        ("push-force:gripper_frame_link:0,0,1", "push-force:BODY@T:FX,FY,FZ"),
    ],
)
def test_a_bad_push_force_is_one_line(spec, message):
    with pytest.raises(ValueError, match=message) as error:
        parse_fault(spec)
    assert "\n" not in str(error.value)


def test_a_push_force_on_a_body_the_model_lacks_is_refused_at_start():
    with pytest.raises(ValueError, match="no body 'hand' in so101's model") as error:
        with bus(faults=["push-force:hand@1.0:0,0,1"]):
            pass
    assert "gripper_frame_link" in str(error.value) and "\n" not in str(error.value)


def test_a_push_force_at_the_gripper_moves_every_joint_by_jt_f():
    """`push-force:BODY@T:FX,FY,FZ`: a force on the body's origin (world frame) from
    T on, through every joint at once; the servos holding (17.8 N m/rad each) give
    way by K_tau Jᵀ F (J the body origin's translational Jacobian at the pose held,
    from a second plant), to the encoder's pulse and the few % the pose's change of
    gravity torque adds; 0,0,0 lets go."""
    spec = "push-force:gripper_frame_link@0.5:0.3,-0.4,-1"
    assert parse_fault(spec).spec() == spec
    with bus(faults=[spec, "push-force:gripper_frame_link@2.0:0,0,0"]) as b:
        physics = b.emulator.groups[0].physics
        physics.set_goal(physics.present().position)
        physics.set_enabled(np.ones(6))
        b.emulator._advance(0.5)
        before = physics.present().position.copy()
        b.emulator._advance(1.5)
        assert physics.external_forces["gripper_frame_link"].tolist() == [0.3, -0.4, -1]
        moved = physics.present().position - before
        b.emulator._advance(2.0)
        assert physics.external_forces["gripper_frame_link"].tolist() == [0, 0, 0]
    plant = load_robot_description(ROBOT).make_plant(weld_base=True)
    context = plant.CreateDefaultContext()
    plant.SetPositions(context, before)
    frame = plant.GetBodyByName("gripper_frame_link").body_frame()
    world = plant.world_frame()
    J = plant.CalcJacobianTranslationalVelocity(
        context, JacobianWrtVariable.kV, frame, np.zeros(3), world, world
    )
    expected = 0.0561887 * J.T @ np.array([0.3, -0.4, -1.0])
    assert np.abs(expected[:3]).min() > 5 * 2 * np.pi / 4096  # pulses to measure
    np.testing.assert_allclose(moved, expected, rtol=0.05, atol=1.5 * 2 * np.pi / 4096)
