"""Feetech's STS/SMS serial protocol as a device speaks it: the emulated servos' side
of a Feetech bus (`hardware.sim_servo`). The controller's side is Feetech's own
client (`scservo_sdk`, `hardware.feetech`): nothing here is used there, so the two
ends are written independently, from the same specification.

Facts from Feetech's communication protocol manual (FT-SCS protocol, doc.feetech.cn;
the same framing as Dynamixel's Protocol 1.0):

- a packet is the header FF FF, the ID (0xFE: broadcast), the length LEN (the bytes
  that follow it: instruction, parameters and checksum, so parameters + 2), the
  instruction, the parameters, and a one-byte checksum: the bitwise inverse of the
  sum of ID, LEN, instruction and parameters, low byte (`checksum`);
- a status packet has the same framing with the servo's error byte in the
  instruction's place: the bits of its Status item (voltage, angle sensor,
  temperature, current, -, overload: `ServoModel.hardware_errors`); Feetech defines
  no protocol error codes (Protocol 1.0's checksum and instruction bits are Feetech's
  current and reserved bits);
- instructions PING 1, READ 2, WRITE 3, REG_WRITE 4, ACTION 5, SYNC_READ 0x82 (STS
  and SMS: one status per listed servo, back to back, in the list's order),
  SYNC_WRITE 0x83; addresses and lengths are one byte each, words little-endian
  on STS/SMS.

`PacketParser` takes the bytes as they come and returns whole packets (the same
`Packet` as Protocol 2.0's parser): it looks for FF FF, reads LEN's worth of bytes,
checks the checksum. A packet whose checksum does not match is returned marked so
(a servo ignores it) and its bytes dropped; bytes outside a packet are skipped and
counted: the parser resynchronises on the next header.

`PROTOCOL` is what the emulator needs of Feetech's wire (`sim_servo.WireProtocol`).
"""

from hrp2_drake.hardware import protocol2
from hrp2_drake.hardware.protocol2 import Instruction, Packet, StatusError

#: The header that opens every packet.
HEADER = b"\xff\xff"
#: Bytes before the instruction: header (2), ID, LEN.
PREFIX_BYTES = 4
#: The instructions an STS/SMS servo implements (Feetech's protocol manual).
INSTRUCTIONS = frozenset(
    {
        Instruction.PING,
        Instruction.READ,
        Instruction.WRITE,
        Instruction.REG_WRITE,
        Instruction.ACTION,
        Instruction.SYNC_READ,
        Instruction.SYNC_WRITE,
    }
)


def checksum(body: bytes) -> int:
    """The checksum of `body` (ID, LEN, instruction or error, parameters)."""
    return ~sum(body) & 0xFF


def encode_packet(packet_id: int, instruction: int, params: bytes = b"") -> bytes:
    """A whole packet: FF FF, ID, LEN, `instruction` (a status: the error byte),
    `params`, checksum. A ValueError for an ID or instruction outside a byte, or more
    parameters than LEN holds."""
    if not (0 <= packet_id <= 0xFF and 0 <= instruction <= 0xFF):
        raise ValueError(
            f"feetech packet: ID {packet_id} and instruction {instruction} must be "
            "bytes (0 to 255)"
        )
    length = len(params) + 2
    if length > 0xFF:
        raise ValueError(f"feetech packet: {len(params)} parameters (at most 253)")
    body = bytes((packet_id, length, instruction)) + bytes(params)
    return HEADER + body + bytes((checksum(body),))


def encode_status(
    packet_id: int, error: int, hardware: int, params: bytes = b""
) -> bytes:
    """Servo `packet_id`'s status: its error byte is its Status bits (`hardware`).
    Feetech has no protocol errors: an instruction the servo does not implement or
    one whose checksum is wrong gets no status (empty bytes); any other `error`
    (`StatusError`: a write the servo refuses) is answered without an error bit, and
    nothing was written (the host sees it by reading back). These two choices are
    ours: Feetech documents no error code for them."""
    if error in (StatusError.CRC, StatusError.INSTRUCTION):
        return b""
    return encode_packet(packet_id, int(hardware) & 0xFF, params)


class PacketParser(protocol2.PacketParser):
    """Whole packets from a byte stream, whatever the chunks (module docstring): the
    buffer, `feed`, `drop_pending` and the counters (`skipped`, `bad_crc`,
    `dropped`) are Protocol 2.0's parser's; what makes a packet is Feetech's
    (`_next`)."""

    def _next(self) -> Packet | None:
        buffer = self._buffer
        while True:
            start = buffer.find(HEADER)
            if start < 0:
                keep = 1 if buffer.endswith(HEADER[:1]) else 0
                self._skip(len(buffer) - keep)
                return None
            if start:
                self._skip(start)
            if len(buffer) < PREFIX_BYTES:
                return None
            packet_id, length = buffer[2], buffer[3]
            if packet_id == 0xFF or length < 2:
                self._skip(1)  # FF FF FF ...: the header starts a byte later
                continue
            total = PREFIX_BYTES + length
            if len(buffer) < total:
                return None
            raw = bytes(buffer[:total])
            del buffer[:total]
            ok = checksum(raw[2:-1]) == raw[-1]
            self.bad_crc += not ok
            return Packet(
                id=packet_id,
                instruction=raw[4],
                params=raw[5:-1],
                size=total,
                crc_ok=ok,
            )
