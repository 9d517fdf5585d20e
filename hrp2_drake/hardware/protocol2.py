"""Dynamixel Protocol 2.0 as a device speaks it: the emulated servos' side of the wire
(`hardware.sim_servo`). The controller's side is ROBOTIS' own client
(`dynamixel_sdk`, `hardware.dynamixel`): nothing here is used there, so that the two
ends are written independently, from the same specification.

Facts from ROBOTIS' e-manual, "Protocol 2.0" (emanual.robotis.com/docs/en/dxl/
protocol2/; ROBOTIS-GIT/emanual docs/en/dxl/protocol2.md) and "CRC calculation"
(docs/en/dxl/crc/):

- a packet is the header FF FF FD, a reserved byte 00, the ID, the length (2 bytes,
  little-endian: the bytes that follow it, instruction to CRC), the instruction, the
  parameters and a CRC-16 (2 bytes, little-endian) of everything before it; a status
  packet's instruction is 0x55 and its first parameter is the error byte (bit 7:
  hardware alert, bits 0-6: the error number, `StatusError`);
- byte stuffing: the sender writes FF FF FD FD wherever FF FF FD appears from the
  instruction to the last parameter, and counts the added bytes in the length and
  the CRC; the receiver checks the CRC over the bytes as received, then removes the
  stuffing. So a real header (FF FF FD followed by the reserved 00) never appears
  inside a packet;
- the CRC is CRC-16 with polynomial 0x8005 (x^16 + x^15 + x^2 + 1), initial value 0,
  bits not reflected, no final XOR (the e-manual's table, which `_crc_table` builds
  from the polynomial).

`PacketParser` takes the bytes as they come and returns whole packets: it looks for
the header, reads the length's worth of bytes, checks the CRC. A packet with a bad
CRC is returned marked so (a servo answers it with a CRC error) and its bytes are
dropped; bytes outside any packet are skipped and counted: the parser resynchronises
on the next header.
"""

from dataclasses import dataclass
from enum import IntEnum

from hrp2_drake.description.bus import BROADCAST_ID

#: The header and the reserved byte that open every packet.
HEADER = b"\xff\xff\xfd\x00"
#: The pattern byte stuffing breaks up, and what it becomes.
STUFFING_PATTERN = b"\xff\xff\xfd"
STUFFED_PATTERN = b"\xff\xff\xfd\xfd"
#: Bytes before the instruction: header (4), ID (1), length (2).
PREFIX_BYTES = 7
#: The CRC's polynomial (CRC-16, as the e-manual's table).
CRC_POLYNOMIAL = 0x8005
#: Bit 7 of a status's error byte: the device has a hardware error (its Hardware
#: Error Status item says which).
ALERT_BIT = 0x80
#: The longest length field the parser accepts (bytes after the length field): a
#: longer one is taken for noise. The SDK's own buffers are 1 KiB.
MAX_LENGTH = 1024

__all__ = [
    "ALERT_BIT",
    "BROADCAST_ID",
    "HEADER",
    "Instruction",
    "Packet",
    "PacketParser",
    "StatusError",
    "crc16",
    "encode_packet",
    "encode_status",
    "instruction_name",
    "stuff",
    "unstuff",
]


class Instruction(IntEnum):
    """Protocol 2.0 instructions (e-manual, "Instruction")."""

    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    REG_WRITE = 0x04
    ACTION = 0x05
    FACTORY_RESET = 0x06
    REBOOT = 0x08
    CLEAR = 0x10
    STATUS = 0x55
    SYNC_READ = 0x82
    SYNC_WRITE = 0x83
    FAST_SYNC_READ = 0x8A
    BULK_READ = 0x92
    BULK_WRITE = 0x93
    FAST_BULK_READ = 0x9A


def instruction_name(code: int) -> str:
    """The instruction's name ("SYNC_READ"), or its code in hex ("0x42")."""
    try:
        return Instruction(code).name
    except ValueError:
        return f"0x{code:02X}"


class StatusError(IntEnum):
    """The error number of a status packet (bits 0-6 of its error byte; e-manual,
    "Status Packet", "Error")."""

    NONE = 0x00
    RESULT_FAIL = 0x01  # failed to process the instruction
    INSTRUCTION = 0x02  # undefined instruction, or ACTION without REG_WRITE
    CRC = 0x03  # the instruction's CRC does not match
    DATA_RANGE = 0x04  # the value is outside the item's range
    DATA_LENGTH = 0x05  # fewer bytes than the item's size (e.g. 2 of a 4-byte item)
    DATA_LIMIT = 0x06  # the value is outside the limit another item sets
    ACCESS = 0x07  # read-only, undefined, or EEPROM while torque is on


# ------------------------------------------------------------------------- CRC


def _crc_table(polynomial: int = CRC_POLYNOMIAL) -> tuple[int, ...]:
    """The 256 remainders of a most-significant-bit-first CRC-16 with `polynomial`:
    entry i is the CRC of the byte i shifted into a zero register."""
    table = []
    for byte in range(256):
        remainder = byte << 8
        for _ in range(8):
            remainder <<= 1
            if remainder & 0x10000:
                remainder ^= 0x10000 | polynomial
        table.append(remainder & 0xFFFF)
    return tuple(table)


_CRC_TABLE = _crc_table()


def crc16(data: bytes, crc: int = 0) -> int:
    """The Protocol 2.0 CRC of `data` (everything from the header to the last
    parameter, stuffing included), continuing from `crc`."""
    table = _CRC_TABLE
    for byte in data:
        crc = ((crc << 8) & 0xFFFF) ^ table[((crc >> 8) ^ byte) & 0xFF]
    return crc


# ------------------------------------------------------------------------- stuffing


def stuff(body: bytes) -> bytes:
    """`body` (instruction and parameters) with FF FF FD FD wherever FF FF FD was.

    The pattern cannot overlap itself (no suffix of FF FF FD is a prefix of it), so
    a left-to-right replacement finds every occurrence."""
    return bytes(body).replace(STUFFING_PATTERN, STUFFED_PATTERN)


def unstuff(body: bytes) -> bytes:
    """`body` as sent before stuffing: each FF FF FD FD back to FF FF FD (FF FF FD
    FD cannot overlap itself either)."""
    return bytes(body).replace(STUFFED_PATTERN, STUFFING_PATTERN)


# ------------------------------------------------------------------------- packets


def encode_packet(packet_id: int, instruction: int, params: bytes = b"") -> bytes:
    """A whole packet: header, `packet_id`, length, `instruction` and `params`
    stuffed, CRC. Raises ValueError for an ID or instruction outside a byte."""
    if not (0 <= packet_id <= 0xFF and 0 <= instruction <= 0xFF):
        raise ValueError(
            f"protocol 2.0 packet: ID {packet_id} and instruction {instruction} "
            "must be bytes (0 to 255)"
        )
    body = stuff(bytes((instruction,)) + bytes(params))
    length = len(body) + 2
    if length > 0xFFFF:
        raise ValueError(f"protocol 2.0 packet: {length} bytes after the length field")
    head = HEADER + bytes((packet_id, length & 0xFF, length >> 8))
    packet = head + body
    crc = crc16(packet)
    return packet + bytes((crc & 0xFF, crc >> 8))


def encode_status(
    packet_id: int, error: int, params: bytes = b"", alert: bool = False
) -> bytes:
    """A status packet (instruction 0x55) of device `packet_id`: the error byte
    (`error`, with bit 7 set if `alert`), then `params`."""
    error_byte = (int(error) & 0x7F) | (ALERT_BIT if alert else 0)
    return encode_packet(
        packet_id, Instruction.STATUS, bytes((error_byte,)) + bytes(params)
    )


@dataclass
class Packet:
    """One packet as received.

    Attributes:
        id: its ID (0xFE: broadcast).
        instruction: its instruction byte.
        params: its parameters, stuffing removed (for a status packet, the error
            byte first).
        size: its bytes on the wire (header to CRC, stuffing included).
        crc_ok: whether its CRC matched (if not, `params` are as received).
    """

    id: int
    instruction: int
    params: bytes
    size: int
    crc_ok: bool = True

    @property
    def name(self) -> str:
        return instruction_name(self.instruction)


class PacketParser:
    """Whole packets from a byte stream, whatever the chunks (module docstring).

    `feed(data)` returns the packets completed by `data`, in order. Counters:
    `skipped` (bytes outside any packet: noise, or what follows a packet whose
    length field lied), `bad_crc` (packets whose CRC did not match), `dropped`
    (bytes of an unfinished packet thrown away by `drop_pending`).

    Args:
        max_length: the longest length field taken for a packet (bytes after it).
    """

    def __init__(self, max_length: int = MAX_LENGTH):
        self._buffer = bytearray()
        self._max_length = max_length
        self.skipped = 0
        self.bad_crc = 0
        self.dropped = 0

    @property
    def pending(self) -> int:
        """Bytes held, waiting for the rest of a packet."""
        return len(self._buffer)

    def drop_pending(self) -> None:
        """Forgets an unfinished packet (its sender went quiet: a real device's
        receive timeout)."""
        self.dropped += len(self._buffer)
        self._buffer.clear()

    def feed(self, data: bytes) -> list[Packet]:
        """The packets `data` completes (see the class docstring)."""
        self._buffer += data
        packets = []
        while True:
            packet = self._next()
            if packet is None:
                return packets
            packets.append(packet)

    def _skip(self, count: int) -> None:
        self.skipped += count
        del self._buffer[:count]

    def _next(self) -> Packet | None:
        """The next whole packet in the buffer (and its bytes removed), or None if
        the buffer holds none yet."""
        buffer = self._buffer
        while True:
            start = buffer.find(HEADER)
            if start < 0:
                # Keep what may be the beginning of a header split across chunks.
                keep = next((k for k in (3, 2, 1) if buffer.endswith(HEADER[:k])), 0)
                self._skip(len(buffer) - keep)
                return None
            if start:
                self._skip(start)
            if len(buffer) < PREFIX_BYTES:
                return None
            length = buffer[5] | buffer[6] << 8
            if length < 3 or length > self._max_length:
                self._skip(1)  # not a packet: look for the next header
                continue
            total = PREFIX_BYTES + length
            if len(buffer) < total:
                return None
            raw = bytes(buffer[:total])
            del buffer[:total]
            crc_ok = crc16(raw[:-2]) == (raw[-2] | raw[-1] << 8)
            body = unstuff(raw[PREFIX_BYTES:-2]) if crc_ok else raw[PREFIX_BYTES:-2]
            if not crc_ok:
                self.bad_crc += 1
            return Packet(
                id=raw[4],
                instruction=body[0],
                params=body[1:],
                size=total,
                crc_ok=crc_ok,
            )
