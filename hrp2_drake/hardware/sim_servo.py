"""Emulated bus servos on a pseudo-terminal: the far end of a servo bus, whose
physics is the robot's simulation (`hrp2-drake sim-servo`). One emulator, two
protocols: Dynamixel's Protocol 2.0 and Feetech's STS/SMS protocol, as the robot's
`bus.kind` says (`WireProtocol`: the packets of `hardware.protocol2` or
`hardware.feetech_protocol`; the servos, their tables, the timing and the faults are
the same code).

`ServoBusEmulator` opens a pseudo-terminal (`os.openpty`) and serves its slave
(`port`) as the robot's bus: behind it, every servo ID of the robot's
description (`BusDescription.ids`, or an `ids` override) is an `EmulatedServo`
whose joint is the robot's simulated station (`robot.bus_servos.SimulatedServos`:
for the XL330, its digital twin). A controller talks to it through ROBOTIS' own
client, `dynamixel_sdk` (a Feetech bus: Feetech's `scservo_sdk`), exactly as to a USB
adapter: it is a real test of the client's path.

Feetech's differences (its protocol manual and memory table; `feetech_protocol`):
addresses and lengths of one byte; a status's error byte is the servo's Status bits
(no protocol error codes: a bad checksum or an unknown instruction gets no status, a
refused write a status without error bits; ours, undocumented by Feetech); PING
answers no parameters (the client reads the model number at address 3); Response
Status Level 0 answers PING and reads, 1 everything; position control is Operating
Mode 0; no REBOOT or BULK instructions; values sign-magnitude (`Register.sign_bit`).

The servos
----------
Each `EmulatedServo` holds its control table as bytes (the model's table, from
`dynamixel_models.yaml`), initialised from the model's initial values and from the
description (ID, baud rate and return delay as configured; the P gain, the goal
and the torque the physics has). It answers PING, READ, WRITE, REG_WRITE, ACTION,
REBOOT, SYNC_READ, SYNC_WRITE, BULK_READ and BULK_WRITE as the e-manual states them:

- status errors: access error (an address outside the table or between its items,
  writing a read-only item, an EEPROM item with torque on), data length error (a
  write that covers part of an item, a parameter block of the wrong size), data
  range error (outside the item's range), data limit error (outside the limit
  another item sets: Goal Position within the Min/Max Position Limit in position
  control mode, Goal PWM/Current/Velocity within their limits), result fail (torque
  on after a shutdown; an operating mode or a P gain of 0 the physics cannot run),
  instruction error (an instruction it does not implement, ACTION without
  REG_WRITE), CRC error; bit 7 (alert) while its Hardware Error Status is not 0;
- a write is checked whole before any byte is written; it may span several items
  (never part of one); a read may span any bytes of the table (0 between items);
- broadcast: READ and WRITE to 0xFE get no status; PING to 0xFE gets one per servo,
  in ID order; Status Return Level 0 answers PING only, 1 also the reads (READ,
  SYNC_READ, BULK_READ), 2 every instruction; the level and the ID are the ones the
  servo had when the instruction came (a WRITE of the ID is answered from the old
  one, a WRITE of the level as before it);
- REBOOT: the RAM items back to their initial values (torque off, hardware error
  cleared), the goal at the present position; REG_WRITE is checked when it comes
  and written at ACTION; a servo with a wrong baud rate hears nothing;
- SYNC_READ and BULK_READ: the servos answer in the order of the instruction's
  list, each after the previous one's status; a listed servo that does not answer
  (absent, silent) silences the ones after it (ROBOTIS, DynamixelSDK issue #364:
  "if one device does not respond in the middle, all IDs do not respond after
  that"; issue #331, the same on a logic analyser).

What reaches the physics: Goal Position (pulses to rad with `BusDescription.
to_radians`, then `SimulatedServos.set_goal` of the whole vector), Torque Enable
(`set_enabled`), Position P Gain (`set_gain`: the physics has one gain for all the
servos of a robot, so a gain is applied when every servo of the robot agrees; until
then the registers differ and the physics keeps the last agreed gain), Return Delay
Time (the reply's timing). Operating Mode takes 3 (position) and 4 (extended
position): the physics is a position servo. The other items are stored and read
back, without effect. Reads of Present Position/Velocity/Current/PWM/Input
Voltage/Temperature convert `SimulatedServos.present()` at the time of the read
with the item's unit (positions with `BusDescription.to_pulses`), two's complement
for signed items; Realtime Tick is the robot's time in ms modulo 32768; Moving is
|velocity| above the Moving Threshold.

An `ids` override serves other IDs than the description's: their number must be a
multiple of the robot's joints, each group of that many IDs (in joint order) driving
its own copy of the robot (`SimulatedServos`). The XL330 pendulum served as IDs
1, 2, 3 is three pendulums on one bus: a multi-servo bus for tests.

Timing
------
Real time (default, `rate` 1): robot time = rate x (wall time since `serve`).
Between packets the physics keeps up with the clock (each time it is found more
than a period behind counts as a late period). A packet's bytes arrive on the pty
at once; on the emulated wire the instruction of n bytes ends `wire_time(n, baud)`
after it was written, or after the bus's previous replies if they end later (the
bus is half-duplex: one talker at a time). The servos act at the instruction's end
(the physics is advanced there: their sample, their new goal); each status starts
after the previous status (or the instruction) ends plus this servo's own Return
Delay Time, takes its wire time, and reaches the host the description's
`adapter_latency` later (`status_times`): it is written to the pty at that wall
time (`time.sleep`, then a spin of the last 100 µs). A status written more than a
period after that time counts as a late status. The physics costs CPU in
proportion to robot time (about 0.2 s per robot second per copy of the XL330
pendulum): a `rate` below 1 lets a slow or loaded machine keep up.

Lock-step (`lockstep=True`), for deterministic tests on any machine: robot time does
not follow the wall clock, and replies go out at once, after the physics took what
the instruction wrote (in real time the statuses go first, since a new gain costs
a station rebuild; the physics takes the writes at the instruction's time all the
same). The contract, which the controller's in-process twin
(`hardware.in_process.run_on_bus_in_process`) reproduces call for call:

- the k-th SYNC_READ (k = 0, 1, ...) whose block contains Present Position is
  control period k: `advance_to(k*T)`, then `present()` (T: the description's
  `sensors.period`);
- the first SYNC_WRITE after it acts at k*T + d (d: `bus.timing().read_to_write`):
  `advance_to(k*T + d)`, then the registers are written and `set_goal(...)` is
  called with every servo's goal;
- everything else (PING, READ, WRITE, another SYNC_WRITE, ...) acts at the current
  robot time, without advancing it.

Faults (`ServoFault`, parsed from one word by `parse_fault`), at robot time:
`silent:ID@T` (the servo answers nothing from T on; it still hears and acts),
`crc:ID@T[xN]` (its next N statuses from T on have a corrupted CRC),
`hardware:ID@T:ERROR` (its Hardware Error Status gets ERROR's bit, one of the model's
`hardware_errors` with spaces written `_`; every later status has the alert bit;
if the Shutdown item (63) selects that error, torque goes off, as a real X-series
servo does, and only REBOOT lets it on again), `close@T` (the emulator closes the
pty and stops: the host sees its port vanish), `push:ID@T:TAU` (from T on, an
external torque of TAU N·m on the joint of servo ID, as a hand pushing it; 0 lets
go: `SimulatedServos.set_external_torque`), `push-force:BODY@T:FX,FY,FZ` (from T on,
a force in N, world frame, on the origin of the model's body BODY, through every
joint at once; 0,0,0 lets go: `SimulatedServos.set_external_force`), and at
start-up `wrong_model:ID:MODEL`
(the servo reports MODEL's model number).

The emulator keeps its own slave fd open (raw mode), so the host may close and
reopen the port between commands. It runs until a duration (robot time), SIGTERM or
SIGINT (in the main thread), a `close` fault or `stop()`, and returns a summary
(packets per instruction, CRC errors received, bytes, late periods, faults, and
why it stopped: `stopped`, "port closed ..." when the host lost its port).
`run_sim_servo` is the command: it builds the physics, prints one line with the
port, serves and writes a short report.
"""

import errno
import json
import math
import os
import re
import select
import signal
import threading
import time
import tty
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hrp2_drake.description.bus import (
    BROADCAST_ID,
    MAX_ID,
    BusDescription,
    Register,
    ServoModel,
    servo_model,
    wire_time,
)
from hrp2_drake.hardware import feetech_protocol, protocol2
from hrp2_drake.hardware.protocol2 import Instruction, Packet, StatusError
from hrp2_drake.report import markdown_table
from hrp2_drake.robot.bus_servos import SimulatedServos

#: The Goal Position's range in extended position control mode (pulses, ±256
#: turns; e-manual, X-series "Goal Position(116)").
EXTENDED_POSITION_RANGE = 1_048_575
#: Items whose value another item bounds (data limit error): Goal Position within
#: [Min, Max] Position Limit (position control mode only); Goal PWM, Current and
#: Velocity within ± their limit (e-manual, X-series control tables).
LIMITED_BY = {
    "goal_position": ("min_position_limit", "max_position_limit"),
    "goal_pwm": ("pwm_limit",),
    "goal_current": ("current_limit",),
    "goal_velocity": ("velocity_limit",),
}
#: Items computed from the physics at the time of a read.
COMPUTED = (
    "present_pwm",
    "present_load",
    "present_current",
    "present_velocity",
    "present_position",
    "present_input_voltage",
    "present_temperature",
    "realtime_tick",
    "moving",
)
#: Realtime Tick wraps at this many ms.
TICK_MODULO = 32768
#: The last part of a wait spent spinning instead of sleeping (s).
SPIN = 100e-6
#: Lock-step: how long the loop waits for bytes before it looks at its stop flag (s).
IDLE_POLL = 0.05
#: Real time: the physics is brought up to the clock at least this often (robot s):
#: a packet then finds it at most this far behind, and its replies are not late for
#: the simulation of a whole period (one plant step: 1 ms).
KEEP_UP = 0.001
#: An unfinished packet is dropped after this long without bytes (wall s): a real
#: device's receive timeout.
PARTIAL_TIMEOUT = 0.1


@dataclass(frozen=True)
class WireProtocol:
    """What the emulator needs of a bus kind's wire (module docstring).

    Args:
        name: the protocol's name, for reports.
        parser: a new packet parser (`feed(bytes) -> [Packet]`).
        field: bytes of an address or a length in an instruction's parameters.
        instructions: the instructions its servos implement (others: an
            instruction error).
        answered_at_level: the lowest Status Return Level that answers each
            instruction; `default_level` for the others.
        status: (ID, `StatusError`, Hardware Error Status bits, parameters) -> the
            status packet's bytes (empty: no status).
        ping_params: whether PING's status carries the model number and firmware.
    """

    name: str
    parser: Callable
    field: int
    instructions: frozenset
    answered_at_level: dict
    default_level: int
    status: Callable[[int, int, int, bytes], bytes]
    ping_params: bool


#: Per bus kind. Protocol 2.0's Status Return Level (e-manual, item 68): 0 PING,
#: 1 also the reads, 2 every instruction. Feetech's Response Status Level (item 8):
#: 0 PING and READ (and SYNC_READ), 1 every instruction.
PROTOCOLS = {
    "dynamixel": WireProtocol(
        name="Protocol 2.0",
        parser=protocol2.PacketParser,
        field=2,
        instructions=frozenset(Instruction) - {Instruction.STATUS},
        answered_at_level={
            Instruction.PING: 0,
            Instruction.READ: 1,
            Instruction.SYNC_READ: 1,
            Instruction.BULK_READ: 1,
        },
        default_level=2,
        status=lambda servo_id, error, hardware, params: protocol2.encode_status(
            servo_id, error, params, alert=hardware != 0
        ),
        ping_params=True,
    ),
    "feetech": WireProtocol(
        name="Feetech STS/SMS",
        parser=feetech_protocol.PacketParser,
        field=1,
        instructions=feetech_protocol.INSTRUCTIONS,
        answered_at_level={
            Instruction.PING: 0,
            Instruction.READ: 0,
            Instruction.SYNC_READ: 0,
        },
        default_level=1,
        status=feetech_protocol.encode_status,
        ping_params=False,
    ),
}


# --------------------------------------------------------------------- faults


@dataclass
class ServoFault:
    """A fault injected on the bus (module docstring; `parse_fault`).

    Args:
        kind: "silent", "crc", "hardware", "close", "push", "push-force" or
            "wrong_model".
        servo_id: the servo it hits (-1: none, for "close" and "push-force").
        at: robot time it starts (s); 0 for "wrong_model" (at start-up).
        count: "crc": how many statuses are corrupted.
        detail: "hardware": the error's name ("overload"); "wrong_model": the
            model whose model number the servo reports ("XM430-W350"); "push": the
            torque (N·m, "-0.2"); "push-force": the force (N, "0,0,-1.5").
        body: "push-force": the pushed body of the robot's model.
    """

    kind: str
    servo_id: int = -1
    at: float = 0.0
    count: int = 1
    detail: str = ""
    body: str = ""

    def spec(self) -> str:
        """The fault as `parse_fault` reads it."""
        if self.kind == "push-force":
            return f"push-force:{self.body}@{self.at:g}:{self.detail}"
        if self.kind == "close":
            return f"close@{self.at:g}"
        if self.kind == "wrong_model":
            return f"wrong_model:{self.servo_id}:{self.detail}"
        spec = f"{self.kind}:{self.servo_id}@{self.at:g}"
        if self.kind == "crc" and self.count != 1:
            spec += f"x{self.count}"
        if self.kind in ("hardware", "push"):
            spec += f":{self.detail.replace(' ', '_')}"
        return spec


FAULT_SYNTAX = (
    "silent:ID@T, crc:ID@T[xN], hardware:ID@T:ERROR, close@T, wrong_model:ID:MODEL, "
    "push:ID@T:TAU, push-force:BODY@T:FX,FY,FZ"
)
_PUSH_FORCE = re.compile(r"push-force:(?P<body>[^@:]+)@(?P<at>[^:]+):(?P<force>.*)")
_FAULT = re.compile(
    r"(?P<kind>[a-z_]+)(?::(?P<id>\d+))?(?:@(?P<at>[0-9.eE+-]+?)(?:x(?P<count>\d+))?)?"
    r"(?::(?P<detail>[A-Za-z0-9_.-]+))?"
)
#: Per kind: the parts a spec must have and the parts it may have.
_FAULT_PARTS = {
    "silent": ({"id", "at"}, set()),
    "crc": ({"id", "at"}, {"count"}),
    "hardware": ({"id", "at", "detail"}, set()),
    "close": ({"at"}, set()),
    "wrong_model": ({"id", "detail"}, set()),
    "push": ({"id", "at", "detail"}, set()),
}


def parse_fault(spec: str) -> ServoFault:
    """A `ServoFault` from one word (`FAULT_SYNTAX`: "silent:1@2.0", "crc:1@1.5x20",
    "hardware:1@2.0:overload", "close@3.0", "wrong_model:1:XM430-W350"); a ServoFault
    is returned as is. Raises ValueError naming the spec and the syntax."""
    if isinstance(spec, ServoFault):
        return spec
    if str(spec).strip().startswith("push-force"):
        return _parse_push_force(str(spec).strip())
    match = _FAULT.fullmatch(str(spec).strip())
    where = f"fault '{spec}'"
    if not match or match["kind"] not in _FAULT_PARTS:
        raise ValueError(f"{where}: expected one of {FAULT_SYNTAX}")
    kind = match["kind"]
    required, optional = _FAULT_PARTS[kind]
    given = {
        part for part in ("id", "at", "count", "detail") if match[part] is not None
    }
    if not required <= given <= required | optional:
        example = FAULT_SYNTAX.split(", ")[list(_FAULT_PARTS).index(kind)]
        raise ValueError(f"{where}: a {kind} fault is written {example}")
    try:
        at = float(match["at"]) if match["at"] is not None else 0.0
    except ValueError:
        raise ValueError(f"{where}: '{match['at']}' is not a time in seconds") from None
    servo_id = int(match["id"]) if match["id"] is not None else -1
    count = int(match["count"]) if match["count"] is not None else 1
    if not (math.isfinite(at) and at >= 0) or servo_id > MAX_ID or count < 1:
        raise ValueError(
            f"{where}: the time must be >= 0 s, the ID 0 to {MAX_ID}, the count >= 1"
        )
    detail = match["detail"] or ""
    if kind == "hardware":
        detail = detail.replace("_", " ").replace("-", " ").lower()
    if kind == "push":
        if not math.isfinite(_number(detail)):
            raise ValueError(f"{where}: '{detail}' is not a torque in N·m")
    return ServoFault(kind, servo_id, at, count, detail)


def _parse_push_force(spec: str) -> ServoFault:
    """`push-force:BODY@T:FX,FY,FZ` (`parse_fault`); the body is checked against
    the model when the emulator starts."""
    where = f"fault '{spec}'"
    match = _PUSH_FORCE.fullmatch(spec)
    if not match:
        raise ValueError(
            f"{where}: a push-force fault is written push-force:BODY@T:FX,FY,FZ"
        )
    at = _number(match["at"])
    if not (math.isfinite(at) and at >= 0):
        raise ValueError(f"{where}: '{match['at']}' is not a time in seconds (>= 0)")
    force = [_number(x) for x in match["force"].split(",")]
    if len(force) != 3 or not all(math.isfinite(f) for f in force):
        raise ValueError(
            f"{where}: '{match['force']}' is not a force in N (FX,FY,FZ: 3 numbers)"
        )
    return ServoFault("push-force", -1, at, 1, match["force"], body=match["body"])


def _number(text: str) -> float:
    """`text` as a float; NaN if it is not a number (the caller's one-line error)."""
    try:
        return float(text)
    except ValueError:
        return math.nan


def parse_faults(specs: Sequence) -> list[ServoFault]:
    """`parse_fault` of each spec."""
    return [parse_fault(spec) for spec in specs]


# --------------------------------------------------------------------- the servos


def _counts_range(register: Register) -> tuple[int, int]:
    """The counts an item's bytes can hold."""
    return register.counts_range()


class ServoGroup:
    """The servos of one copy of the robot and its physics: what maps their
    registers onto `SimulatedServos` (module docstring, "What reaches the physics").

    Args:
        physics: the robot's simulated servos.
        bus: the robot's bus description (its units: `to_pulses`, `to_radians`).
    """

    def __init__(self, physics: SimulatedServos, bus: BusDescription):
        self.physics = physics
        self.bus = bus
        self.model = bus.servo_model()
        self.protocol = PROTOCOLS[bus.kind]
        self.members: list[EmulatedServo] = []
        self.gain_disagreements = 0
        self._counts: dict[str, np.ndarray] | None = None
        self._counts_time = -1.0

    def counts(self) -> dict[str, np.ndarray]:
        """The computed items' counts (`COMPUTED`) of every joint, from
        `SimulatedServos.present()` now (cached until the time or a register
        changes)."""
        t = self.physics.time
        if self._counts is not None and self._counts_time == t:
            return self._counts
        readings = self.physics.present()
        counts = {"present_position": self.bus.to_pulses(readings.position)}
        for name, value in (
            ("present_velocity", readings.velocity),
            ("present_current", readings.current),
            ("present_pwm", readings.pwm),
            ("present_load", readings.pwm),
            ("present_input_voltage", readings.voltage),
            ("present_temperature", readings.temperature),
        ):
            if name in self.model.registers:
                unit = self.model.registers[name].unit or 1.0
                counts[name] = np.rint(np.asarray(value, float) / unit).astype(np.int64)
        if "realtime_tick" in self.model.registers:
            unit = self.model.registers["realtime_tick"].unit or 0.001
            tick = math.floor(t / unit + 1e-6) % TICK_MODULO
            counts["realtime_tick"] = np.full(len(self.members), tick, dtype=np.int64)
        self._counts, self._counts_time = counts, t
        return counts

    def apply(self, names: set[str]) -> None:
        """Carries the written items `names` over to the physics, at its time."""
        physics = self.physics
        if "goal_position" in names:
            pulses = np.array(
                [m.get("goal_position") for m in self.members], dtype=np.int64
            )
            physics.set_goal(self.bus.to_radians(pulses))
        if "torque_enable" in names:
            physics.set_enabled(
                np.array([float(m.get("torque_enable")) for m in self.members])
            )
        if "position_p_gain" in names:
            gains = {m.get("position_p_gain") for m in self.members}
            if len(gains) == 1:
                physics.set_gain(float(gains.pop()))
            else:
                self.gain_disagreements += 1
        self._counts = None


class EmulatedServo:
    """One Protocol 2.0 device: its control table and the instructions' semantics
    (module docstring, "The servos").

    Args:
        servo_id: its ID.
        group: the robot copy it belongs to (`ServoGroup`: model, bus, physics).
        joint: its joint's index in the robot's joint order.
        model_number: the model number it reports (None: its model's).
        id_taken: whether another device of the bus has an ID (refuses a new ID
            that would collide).
    """

    def __init__(
        self,
        servo_id: int,
        group: ServoGroup,
        joint: int,
        model_number: int | None = None,
        id_taken: Callable[[int], bool] | None = None,
    ):
        self.group = group
        self.model: ServoModel = group.model
        self.protocol = group.protocol
        self.joint = joint
        self._id_taken = id_taken or (lambda other: False)
        self._registers = self.model.registers
        size = self.model.table_size()
        self.table = bytearray(size)
        self._owner: list[str | None] = [None] * size
        for name, register in self._registers.items():
            for address in range(register.address, register.address + register.size):
                self._owner[address] = name
        self._computed = [
            (name, self._registers[name])
            for name in COMPUTED
            if name in self._registers
        ]
        self._computed_span = (
            min((r.address for _, r in self._computed), default=size),
            max((r.address + r.size for _, r in self._computed), default=0),
        )
        self._power_up(servo_id, model_number)
        self.silent = False
        self.corrupt_left = 0
        self.registered: tuple[int, bytes] | None = None
        group.members.append(self)

    def _power_up(self, servo_id: int, model_number: int | None) -> None:
        """The table at power-up: the model's initial values, the bus's EEPROM
        settings, and the physics' goal, torque and gain."""
        for name, register in self._registers.items():
            self.put(name, register.initial)
        bus, physics = self.group.bus, self.group.physics
        self.put("model_number", model_number or self.model.model_number)
        if "firmware_version" in self._registers:
            self.put("firmware_version", self.model.firmware)
        self.put("id", servo_id)
        if "baud_rate" in self._registers:
            self.put("baud_rate", self.model.baud_rates.index(bus.baud))
        delay = self._registers["return_delay_time"]
        self.put("return_delay_time", round(bus.return_delay / delay.unit))
        self.put("position_p_gain", round(physics.gain))
        self.put("goal_position", int(bus.to_pulses(physics.goal)[self.joint]))
        self.put("torque_enable", int(physics.enabled[self.joint] > 0.5))

    # ---------------------------------------------------------------- the table

    def get(self, name: str) -> int:
        """Item `name` in counts (signed items as such)."""
        register = self._registers[name]
        data = self.table[register.address : register.address + register.size]
        return self.model.decode(name, data)

    def put(self, name: str, value: int) -> None:
        """Writes item `name` (counts, clipped to what its bytes hold)."""
        register = self._registers[name]
        low, high = _counts_range(register)
        value = min(max(int(value), low), high)
        self.table[register.address : register.address + register.size] = (
            self.model.encode(name, value)
        )

    @property
    def id(self) -> int:
        return self.get("id")

    @property
    def return_delay(self) -> float:
        """Its Return Delay Time (s)."""
        return self.get("return_delay_time") * self._registers["return_delay_time"].unit

    @property
    def listening(self) -> bool:
        """Whether its baud rate is the bus's (else it hears only noise)."""
        if "baud_rate" not in self._registers:
            return True
        return self.model.baud_rates[self.get("baud_rate")] == self.group.bus.baud

    @property
    def shut_down(self) -> bool:
        """Whether a hardware error its Shutdown item selects has switched it off."""
        shutdown = self.get("shutdown") if "shutdown" in self._registers else 0xFF
        return bool(self.get("hardware_error_status") & shutdown)

    def answers(self, instruction: int) -> bool:
        """Whether its Status Return Level sends a status for `instruction`."""
        protocol = self.protocol
        level = (
            self.get("status_return_level")
            if "status_return_level" in self._registers
            else protocol.default_level
        )
        return level >= protocol.answered_at_level.get(
            instruction, protocol.default_level
        )

    def status(
        self, error: int, params: bytes = b"", reply_id: int | None = None
    ) -> bytes:
        """Its status packet (from `reply_id`, default its ID): the alert bit while
        it has a hardware error, and a corrupted CRC while a `crc` fault lasts."""
        packet = self.protocol.status(
            self.id if reply_id is None else reply_id,
            error,
            self.get("hardware_error_status"),
            params,
        )
        if packet and self.corrupt_left > 0:
            self.corrupt_left -= 1
            packet = packet[:-1] + bytes((packet[-1] ^ 0xFF,))
        return packet

    # ---------------------------------------------------------------- instructions

    def ping(self) -> bytes:
        """PING's parameters: model number (2 bytes), firmware version (Feetech:
        none)."""
        if not self.protocol.ping_params:
            return b""
        firmware = (
            self.get("firmware_version") if "firmware_version" in self._registers else 0
        )
        return self.get("model_number").to_bytes(2, "little") + bytes((firmware,))

    def read(self, address: int, length: int) -> tuple[int, bytes]:
        """(error, data) of a READ of `length` bytes from `address`: any bytes of the
        table (0 between items), the computed items as the physics is now."""
        if length < 1:
            return StatusError.DATA_LENGTH, b""
        if address + length > len(self.table):
            return StatusError.ACCESS, b""
        low, high = self._computed_span
        if address < high and address + length > low:
            self._refresh()
        return StatusError.NONE, bytes(self.table[address : address + length])

    def _refresh(self) -> None:
        """The computed items from the physics now."""
        counts = self.group.counts()
        for name, _ in self._computed:
            if name in counts:
                self.put(name, counts[name][self.joint])
        if "moving" in self._registers and "present_velocity" in counts:
            threshold = (
                self.get("moving_threshold")
                if "moving_threshold" in self._registers
                else 0
            )
            moving = abs(int(counts["present_velocity"][self.joint])) > threshold
            self.put("moving", int(moving))

    def write(self, address: int, data: bytes) -> tuple[int, set[str]]:
        """(error, items written) of a WRITE of `data` at `address`: checked whole
        (`check_write`), then written; nothing is written on an error."""
        error, values = self.check_write(address, data)
        if error:
            return error, set()
        for name, value in values.items():
            self.put(name, value)
        return StatusError.NONE, set(values)

    def check_write(self, address: int, data: bytes) -> tuple[int, dict[str, int]]:
        """(error, {item: value}) of a write of `data` at `address`, in the order a
        device finds them: where the bytes go (access, length), each item's range,
        the limits other items set, then what the physics can do (result fail)."""
        error, values = self._items_written(address, data)
        if error:
            return error, {}
        for name, value in values.items():
            low, high = self._range(name)
            if not low <= value <= high:
                return StatusError.DATA_RANGE, {}
        merged = lambda item: values.get(item, self.get(item))  # noqa: E731
        for name, value in values.items():
            low, high = self._limit(name, merged)
            if not low <= value <= high:
                return StatusError.DATA_LIMIT, {}
        if not self._can_run(values):
            return StatusError.RESULT_FAIL, {}
        return StatusError.NONE, values

    def _items_written(self, address: int, data: bytes) -> tuple[int, dict[str, int]]:
        """The items `data` at `address` covers, whole, writable now; or the access
        or data length error."""
        end = address + len(data)
        if not data:
            return StatusError.DATA_LENGTH, {}
        if end > len(self.table):
            return StatusError.ACCESS, {}
        torque_on = self.get("torque_enable") != 0
        values, position = {}, address
        while position < end:
            name = self._owner[position]
            if name is None:
                return StatusError.ACCESS, {}
            register = self._registers[name]
            if register.address != position or position + register.size > end:
                return StatusError.DATA_LENGTH, {}
            if register.access != "RW" or (register.eeprom and torque_on):
                return StatusError.ACCESS, {}
            chunk = data[position - address : position - address + register.size]
            values[name] = self.model.decode(name, chunk)
            position += register.size
        return StatusError.NONE, values

    def _range(self, name: str) -> tuple[int, int]:
        """The counts item `name` takes (its range; the Goal Position's in extended
        position control mode)."""
        if name == "goal_position" and self._extended(self.get("operating_mode")):
            return -EXTENDED_POSITION_RANGE, EXTENDED_POSITION_RANGE
        return self._registers[name].limits()

    def _limit(self, name: str, value_of: Callable[[str], int]) -> tuple[float, float]:
        """The bounds other items set on item `name` (`LIMITED_BY`; none: ±inf)."""
        bounds = [item for item in LIMITED_BY.get(name, ()) if item in self._registers]
        position_control = self.model.position_modes[0]
        if not bounds or (
            name == "goal_position" and value_of("operating_mode") != position_control
        ):
            return -math.inf, math.inf
        if len(bounds) == 2:
            return value_of(bounds[0]), value_of(bounds[1])
        return -value_of(bounds[0]), value_of(bounds[0])

    def _can_run(self, values: dict[str, int]) -> bool:
        """Whether the physics can do what `values` ask (else: result fail)."""
        if values.get("torque_enable") == 1 and self.shut_down:
            return False  # e-manual: only REBOOT turns torque on after a shutdown
        if (
            "operating_mode" in values
            and values["operating_mode"] not in self.model.position_modes
        ):
            return False
        if values.get("position_p_gain", 1) <= 0:
            return False  # the twin's law is stated at a gain > 0
        new_id = values.get("id", self.id)
        return new_id == self.id or not self._id_taken(new_id)

    def _extended(self, mode: int) -> bool:
        """Whether Operating Mode `mode` is extended (multi-turn) position control:
        the model's second position mode (Dynamixel's 4)."""
        return mode in self.model.position_modes[1:]

    def hardware_error(self, name: str) -> bool:
        """Raises the hardware error `name` (one of the model's `hardware_errors`);
        torque goes off if the Shutdown item selects it. Returns whether torque went
        off."""
        bit = self.model.hardware_errors.index(name)
        self.put("hardware_error_status", self.get("hardware_error_status") | 1 << bit)
        if self.shut_down and self.get("torque_enable"):
            self.put("torque_enable", 0)
            return True
        return False

    def reboot(self) -> set[str]:
        """REBOOT: the RAM items back to their initial values (torque off, no
        hardware error, nothing registered), the goal at the present position.
        Returns the items the physics must take."""
        present = int(self.group.counts()["present_position"][self.joint])
        for name, register in self._registers.items():
            if not register.eeprom and name not in COMPUTED:
                self.put(name, register.initial)
        self.put("goal_position", present)
        self.registered = None
        return {"torque_enable", "goal_position", "position_p_gain"}


# --------------------------------------------------------------------- the bus


@dataclass
class _Reply:
    """A status on its way: the servo and its bytes."""

    servo: EmulatedServo
    data: bytes


def _word(data: bytes, offset: int, size: int = 2) -> int:
    """The little-endian field of `size` bytes (1 or 2) at `offset`."""
    return data[offset] | (data[offset + 1] << 8 if size == 2 else 0)


def status_times(
    end: float, statuses: Sequence[tuple[float, int]], baud: float, latency: float
) -> list[tuple[float, float]]:
    """When the statuses of one instruction end on the wire and reach the host (s).

    The bus is half-duplex: each status starts when the one before it (the first:
    the instruction) has ended, plus its servo's Return Delay Time, takes its bytes'
    wire time, and reaches the host `latency` (the USB adapter's) after it ends.

    Args:
        end: when the instruction ends on the wire (s).
        statuses: (return delay (s), bytes) of each status, in bus order.
        baud: the line's rate (bit/s).
        latency: the adapter's latency (s).

    Returns:
        (end on the wire, arrival at the host) of each status (s).
    """
    times = []
    for delay, size in statuses:
        end = end + delay + wire_time(size, baud)
        times.append((end, end + latency))
    return times


class ServoBusEmulator:
    """A robot's servos behind a pseudo-terminal (module docstring).

    Args:
        servos: the robot's simulated servos, or one copy per group of IDs (an
            `ids` override with k times the robot's joints needs k copies).
        ids: the IDs served, joint order, copy after copy (None: the description's
            `bus.ids`).
        lockstep: lock-step timing (module docstring) instead of real time.
        rate: real time: robot seconds per wall second.
        faults: `ServoFault`s or their specs (`parse_fault`).
    """

    def __init__(
        self,
        servos: SimulatedServos | Sequence[SimulatedServos],
        ids: Sequence[int] | None = None,
        lockstep: bool = False,
        rate: float = 1.0,
        faults: Sequence = (),
    ):
        copies = [servos] if isinstance(servos, SimulatedServos) else list(servos)
        if not copies:
            raise ValueError("sim-servo: no simulated servos to serve")
        self.robot = copies[0].robot
        self.bus = self.robot.bus
        self.model = self.bus.servo_model()
        self.protocol = PROTOCOLS[self.bus.kind]
        self._f = self.protocol.field
        self.ids = self._check_ids(ids, len(copies))
        if not (math.isfinite(rate) and rate > 0):
            raise ValueError(f"sim-servo: rate {rate}, must be finite and > 0")
        self.lockstep, self.rate = bool(lockstep), float(rate)
        self.period = self.robot.sensors.period
        self.read_to_write = self.bus.timing().read_to_write
        self.groups = [ServoGroup(physics, self.bus) for physics in copies]
        n = len(self.robot.joints)
        self.servos = [
            EmulatedServo(servo_id, self.groups[k // n], k % n, id_taken=self._id_taken)
            for k, servo_id in enumerate(self.ids)
        ]
        self.applied_faults: list[dict] = []
        self._timed = self._prepare_faults(parse_faults(faults))
        self._open_pty()
        self._parser = self.protocol.parser()
        self._dirty: dict[int, set[str]] = {}
        self._stop = threading.Event()
        self.stopped = ""
        self._periods = 0
        self._write_time: float | None = None
        self._bus_free = 0.0
        self._t0 = self._last_bytes = time.perf_counter()
        self.counters = Counter()
        self.packets: Counter = Counter()
        self.max_lag = 0.0
        self.wall_time = 0.0  # of the last `serve`

    # ---------------------------------------------------------------- set-up

    def _check_ids(self, ids: Sequence[int] | None, copies: int) -> list[int]:
        ids = [int(i) for i in (ids if ids else self.bus.ids)]
        n = len(self.robot.joints)
        if len(ids) != n * copies:
            raise ValueError(
                f"sim-servo: {len(ids)} IDs for {copies} "
                f"cop{'y' if copies == 1 else 'ies'} "
                f"of '{self.robot.name}' ({n} joint(s) each): expected {n * copies}"
            )
        bad = [i for i in ids if not 0 <= i <= MAX_ID]
        twice = sorted({i for i in ids if ids.count(i) > 1})
        if bad or twice:
            raise ValueError(
                f"sim-servo: ids {ids}: each one 0 to {MAX_ID}, once "
                f"(bad {bad}, twice {twice})"
            )
        return ids

    def _id_taken(self, servo_id: int) -> bool:
        return any(servo.id == servo_id for servo in self.servos)

    def _servo(self, servo_id: int, where: str) -> EmulatedServo:
        for servo in self.servos:
            if servo.id == servo_id:
                return servo
        raise ValueError(
            f"{where}: no servo with ID {servo_id} on the bus (ids {self.ids})"
        )

    def _prepare_faults(self, faults: list[ServoFault]) -> list[ServoFault]:
        """Applies the start-up faults, checks the others against the bus; the
        timed faults in time order."""
        timed = []
        for fault in faults:
            where = f"fault '{fault.spec()}'"
            if fault.kind in ("close", "push-force"):
                if fault.kind == "push-force":
                    self.groups[0].physics.check_body(fault.body, where)
                timed.append(fault)
                continue
            servo = self._servo(fault.servo_id, where)
            if fault.kind == "wrong_model":
                servo.put(
                    "model_number",
                    servo_model(self.bus.kind, fault.detail, where).model_number,
                )
                self.applied_faults.append({"fault": fault.spec(), "time": 0.0})
                continue
            if (
                fault.kind == "hardware"
                and fault.detail not in self.model.hardware_errors
            ):
                known = [e.replace(" ", "_") for e in self.model.hardware_errors if e]
                raise ValueError(
                    f"{where}: '{fault.detail}' is not a hardware error of the "
                    f"{self.bus.model} (known: {known})"
                )
            timed.append(fault)
        return sorted(timed, key=lambda f: f.at)

    def _open_pty(self) -> None:
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.port = os.ttyname(self._slave)

    def close(self) -> None:
        """Closes the pseudo-terminal (both ends): the host's port is gone."""
        for name in ("_master", "_slave"):
            fd = getattr(self, name, -1)
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
                setattr(self, name, -1)

    def __enter__(self) -> "ServoBusEmulator":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def stop(self) -> None:
        """Ends `serve` (from another thread) at its next look at the clock."""
        self._stop.set()

    # ---------------------------------------------------------------- time

    @property
    def time(self) -> float:
        """The robot's time (s): the physics' in lock-step, the clock's in real time."""
        if self.lockstep:
            return self.groups[0].physics.time
        return self.rate * (time.perf_counter() - self._t0)

    def _wall(self, robot_time: float) -> float:
        return self._t0 + robot_time / self.rate

    def _advance(self, t: float) -> None:
        """The physics to robot time `t`, applying the faults due on the way."""
        while self._timed and self._timed[0].at <= t:
            fault = self._timed.pop(0)
            for group in self.groups:
                group.physics.advance_to(fault.at)
            self._apply_fault(fault)
        for group in self.groups:
            group.physics.advance_to(t)

    def _apply_fault(self, fault: ServoFault) -> None:
        self.applied_faults.append({"fault": fault.spec(), "time": float(fault.at)})
        if fault.kind == "close":
            self.stopped = f"port closed by the fault {fault.spec()}"
            return
        if fault.kind == "push-force":
            force = [float(x) for x in fault.detail.split(",")]
            for group in self.groups:
                group.physics.set_external_force(fault.body, force)
            return
        servo = self._servo(fault.servo_id, f"fault '{fault.spec()}'")
        if fault.kind == "silent":
            servo.silent = True
        elif fault.kind == "crc":
            servo.corrupt_left += fault.count
        elif fault.kind == "hardware" and servo.hardware_error(fault.detail):
            servo.group.apply({"torque_enable"})
        elif fault.kind == "push":
            group = servo.group
            torque = group.physics.external_torque
            torque[servo.joint] = float(fault.detail)
            group.physics.set_external_torque(torque)

    def _sleep_until(self, wall: float) -> None:
        """Sleeps until perf_counter() reaches `wall`, spinning the last `SPIN`."""
        while True:
            left = wall - time.perf_counter()
            if left <= 0:
                return
            if left > SPIN:
                time.sleep(left - SPIN)

    # ---------------------------------------------------------------- the loop

    def serve(self, duration: float = math.inf) -> dict:
        """Serves the bus until robot time `duration` (s), SIGTERM/SIGINT (when run
        in the main thread), a `close` fault or `stop()`. Returns `summary()`."""
        previous = {}
        if threading.current_thread() is threading.main_thread():

            def on_signal(signum, frame):
                self.stopped = self.stopped or f"signal {signal.Signals(signum).name}"

            previous = {
                s: signal.signal(s, on_signal) for s in (signal.SIGTERM, signal.SIGINT)
            }
        self._t0 = self._last_bytes = time.perf_counter()
        try:
            while not self.stopped:
                if self._stop.is_set():
                    self.stopped = "stop requested"
                elif self.time >= duration:
                    self.stopped = f"duration {duration:g} s"
                else:
                    self._step(duration)
        finally:
            for s, handler in previous.items():
                signal.signal(s, handler)
            self.wall_time = time.perf_counter() - self._t0
            if self.stopped.startswith("port closed"):
                self.close()
        return self.summary()

    def _step(self, duration: float) -> None:
        """Keeps the physics up with the clock, waits for bytes (at most a period),
        and handles the packets they complete."""
        if self.lockstep:
            timeout = IDLE_POLL
        else:
            now = self.time
            lag = now - self.groups[0].physics.time
            if lag > self.period:
                self.counters["late_periods"] += 1
                self.max_lag = max(self.max_lag, lag)
            if lag > 0:
                self._advance(now)
            if self.stopped:
                return
            timeout = min(KEEP_UP, self.period, max(duration - now, 0.0)) / self.rate
        ready, _, _ = select.select([self._master], [], [], timeout)
        if not ready:
            if (
                self._parser.pending
                and time.perf_counter() - self._last_bytes > PARTIAL_TIMEOUT
            ):
                self._parser.drop_pending()
            return
        try:
            data = os.read(self._master, 4096)
        except OSError as error:
            if error.errno in (errno.EAGAIN, errno.EINTR):
                return
            self.stopped = f"port closed: the pseudo-terminal failed ({error})"
            return
        arrival = self.time
        self._last_bytes = time.perf_counter()
        self.counters["bytes_in"] += len(data)
        for packet in self._parser.feed(data):
            self._handle(packet, arrival)
            if self.stopped:
                return

    def _handle(self, packet: Packet, arrival: float) -> None:
        """One instruction: the servos act at its time (module docstring, "Timing"),
        the physics takes what was written and their statuses go out. In real time
        the statuses go first (a new gain rebuilds the station: 5-10 ms), the physics
        still at the instruction's time."""
        self.packets[packet.name if packet.crc_ok else "bad CRC"] += 1
        t = self._act_time(packet, arrival)
        self._advance(t)
        if self.stopped:
            return
        replies = [reply for reply in self._dispatch(packet) if reply.data]
        if not self.lockstep:
            self._send(replies, t)
        for index, names in self._dirty.items():
            self.groups[index].apply(names)
        self._dirty.clear()
        if self.lockstep:
            self._send(replies, t)

    def _act_time(self, packet: Packet, arrival: float) -> float:
        """The robot time the instruction acts at (module docstring, "Timing")."""
        period = (
            packet.crc_ok
            and packet.instruction == Instruction.SYNC_READ
            and (self._is_period(packet.params))
        )
        if not self.lockstep:
            self._periods += bool(period)
            start = max(arrival, self._bus_free)
            end = start + wire_time(packet.size, self.bus.baud)
            self._bus_free = end
            return end
        now = self.groups[0].physics.time
        if period:
            t = self._periods * self.period
            self._periods += 1
            self._write_time = t + self.read_to_write
            return max(t, now)
        if (
            packet.crc_ok
            and packet.instruction == Instruction.SYNC_WRITE
            and (self._write_time is not None)
        ):
            t, self._write_time = self._write_time, None
            return max(t, now)
        return now

    def _is_period(self, params: bytes) -> bool:
        """Whether a SYNC_READ's block contains Present Position."""
        f = self._f
        if len(params) < 2 * f:
            return False
        address, length = _word(params, 0, f), _word(params, f, f)
        position = self.model.registers["present_position"]
        return (
            address <= position.address
            and position.address + position.size <= address + length
        )

    def _send(self, replies: list[_Reply], t: float) -> None:
        """Writes the statuses: at once in lock-step; in real time, each when it
        reaches the host (`status_times`)."""
        if self.lockstep:
            times = [(t, t)] * len(replies)
        else:
            times = status_times(
                t,
                [(r.servo.return_delay, len(r.data)) for r in replies],
                self.bus.baud,
                self.bus.adapter_latency,
            )
        for reply, (end, arrival) in zip(replies, times):
            if not self.lockstep:
                due = self._wall(arrival)
                self._sleep_until(due)
                if time.perf_counter() - due > self.period / self.rate:
                    self.counters["late_statuses"] += 1
                self._bus_free = max(self._bus_free, end)
            self._write(reply.data)
            self.counters["statuses"] += 1

    def _write(self, data: bytes) -> None:
        try:
            written = os.write(self._master, data)
        except BlockingIOError:
            written = 0  # nobody reads the port: its buffer is full
        except OSError as error:
            self.stopped = f"port closed: the pseudo-terminal failed ({error})"
            return
        self.counters["bytes_out"] += written
        self.counters["bytes_dropped"] += len(data) - written

    # ---------------------------------------------------------------- instructions

    def _dispatch(self, packet: Packet) -> list[_Reply]:
        """The statuses of the servos the packet addresses, in bus order; what they
        write is noted for the physics (`_dirty`)."""
        if not packet.crc_ok:
            self.counters["crc_errors"] += 1
            return self._unicast(packet, StatusError.CRC)
        handler = {
            Instruction.PING: self._ping,
            Instruction.READ: self._read,
            Instruction.WRITE: self._write_instruction,
            Instruction.REG_WRITE: self._reg_write,
            Instruction.ACTION: self._action,
            Instruction.REBOOT: self._reboot,
            Instruction.SYNC_READ: self._sync_read,
            Instruction.SYNC_WRITE: self._sync_write,
            Instruction.BULK_READ: self._bulk_read,
            Instruction.BULK_WRITE: self._bulk_write,
            Instruction.STATUS: lambda packet: [],  # another device's status
        }.get(packet.instruction)
        if handler is None or (
            packet.instruction != Instruction.STATUS
            and packet.instruction not in self.protocol.instructions
        ):
            return self._unicast(packet, StatusError.INSTRUCTION)
        return handler(packet)

    def _listening(self) -> dict[int, EmulatedServo]:
        return {servo.id: servo for servo in self.servos if servo.listening}

    def _reply(
        self, servo: EmulatedServo, instruction: int, error: int, params: bytes = b""
    ) -> list[_Reply]:
        """The servo's status, if it answers `instruction` and is not silent."""
        if servo.silent or not servo.answers(instruction):
            return []
        return [_Reply(servo, servo.status(error, params))]

    def _unicast(self, packet: Packet, error: int) -> list[_Reply]:
        """An error status from the addressed servo (none for a broadcast)."""
        servo = self._listening().get(packet.id)
        if servo is None:
            return []
        return self._reply(servo, packet.instruction if packet.crc_ok else -1, error)

    def _written(self, servo: EmulatedServo, names: set[str]) -> None:
        if names:
            index = self.groups.index(servo.group)
            self._dirty.setdefault(index, set()).update(names)

    def _ping(self, packet: Packet) -> list[_Reply]:
        servos = self._listening()
        if packet.id == BROADCAST_ID:
            replies = []
            for servo_id in sorted(servos):
                replies += self._reply(
                    servos[servo_id], Instruction.PING, 0, servos[servo_id].ping()
                )
            return replies
        servo = servos.get(packet.id)
        return self._reply(servo, Instruction.PING, 0, servo.ping()) if servo else []

    def _read(self, packet: Packet) -> list[_Reply]:
        servo = self._listening().get(packet.id)
        if servo is None:  # broadcast READ: no status (e-manual)
            return []
        f = self._f
        if len(packet.params) != 2 * f:
            return self._reply(servo, Instruction.READ, StatusError.DATA_LENGTH)
        error, data = servo.read(_word(packet.params, 0, f), _word(packet.params, f, f))
        return self._reply(servo, Instruction.READ, error, data)

    def _each(
        self, packet: Packet, act: Callable[[EmulatedServo], int]
    ) -> list[_Reply]:
        """WRITE, REG_WRITE, ACTION, REBOOT: `act` on the addressed servo (or every
        one, for the broadcast ID), which returns its error; a status for a unicast
        only, from the ID it was addressed by (even if the write changed it), if its
        Status Return Level when the instruction came asks for one."""
        servos = self._listening()
        if packet.id == BROADCAST_ID:
            for servo in servos.values():
                act(servo)
            return []
        servo = servos.get(packet.id)
        if servo is None:
            return []
        answering = not servo.silent and servo.answers(packet.instruction)
        error = act(servo)
        return (
            [_Reply(servo, servo.status(error, reply_id=packet.id))]
            if answering
            else []
        )

    def _write_instruction(self, packet: Packet) -> list[_Reply]:
        def write(servo: EmulatedServo) -> int:
            f = self._f
            if len(packet.params) < f + 1:
                return StatusError.DATA_LENGTH
            error, names = servo.write(_word(packet.params, 0, f), packet.params[f:])
            self._written(servo, names)
            return error

        return self._each(packet, write)

    def _reg_write(self, packet: Packet) -> list[_Reply]:
        def register(servo: EmulatedServo) -> int:
            f = self._f
            if len(packet.params) < f + 1:
                return StatusError.DATA_LENGTH
            address, data = _word(packet.params, 0, f), bytes(packet.params[f:])
            error, _ = servo.check_write(address, data)
            if not error:
                servo.registered = (address, data)
                servo.put("registered_instruction", 1)
            return error

        return self._each(packet, register)

    def _action(self, packet: Packet) -> list[_Reply]:
        def action(servo: EmulatedServo) -> int:
            if servo.registered is None:
                return StatusError.INSTRUCTION  # ACTION without REG_WRITE
            error, names = servo.write(*servo.registered)
            servo.registered = None
            servo.put("registered_instruction", 0)
            self._written(servo, names)
            return error

        return self._each(packet, action)

    def _reboot(self, packet: Packet) -> list[_Reply]:
        def reboot(servo: EmulatedServo) -> int:
            self._written(servo, servo.reboot())
            return StatusError.NONE

        return self._each(packet, reboot)

    def _sync_read(self, packet: Packet) -> list[_Reply]:
        params, f = packet.params, self._f
        if packet.id != BROADCAST_ID or len(params) < 2 * f + 1:
            self.counters["malformed"] += 1
            return []
        address, length = _word(params, 0, f), _word(params, f, f)
        return self._chain(
            [(servo_id, address, length) for servo_id in params[2 * f :]],
            Instruction.SYNC_READ,
        )

    def _bulk_read(self, packet: Packet) -> list[_Reply]:
        params = packet.params
        if packet.id != BROADCAST_ID or not params or len(params) % 5:
            self.counters["malformed"] += 1
            return []
        requests = [
            (params[i], _word(params, i + 1), _word(params, i + 3))
            for i in range(0, len(params), 5)
        ]
        return self._chain(requests, Instruction.BULK_READ)

    def _chain(
        self, requests: list[tuple[int, int, int]], instruction: int
    ) -> list[_Reply]:
        """The statuses of a SYNC_READ or BULK_READ, in the list's order: each
        servo answers after the one before it; one that does not answer (absent,
        silent, a status return level of 0) silences the rest (module docstring)."""
        servos = self._listening()
        replies = []
        for servo_id, address, length in requests:
            servo = servos.get(servo_id)
            if servo is None or servo.silent or not servo.answers(instruction):
                break
            error, data = servo.read(address, length)
            replies.append(_Reply(servo, servo.status(error, data)))
        return replies

    def _sync_write(self, packet: Packet) -> list[_Reply]:
        params, f = packet.params, self._f
        if packet.id != BROADCAST_ID or len(params) < 2 * f:
            self.counters["malformed"] += 1
            return []
        address, length = _word(params, 0, f), _word(params, f, f)
        blocks = params[2 * f :]
        if length < 1 or len(blocks) % (1 + length):
            self.counters["malformed"] += 1
            return []
        writes = [
            (blocks[i], address, blocks[i + 1 : i + 1 + length])
            for i in range(0, len(blocks), 1 + length)
        ]
        return self._write_each(writes)

    def _bulk_write(self, packet: Packet) -> list[_Reply]:
        params, writes, i = packet.params, [], 0
        while packet.id == BROADCAST_ID and i + 5 <= len(params):
            length = _word(params, i + 3)
            writes.append(
                (params[i], _word(params, i + 1), params[i + 5 : i + 5 + length])
            )
            i += 5 + length
        if packet.id != BROADCAST_ID or i != len(params) or not writes:
            self.counters["malformed"] += 1
            return []
        return self._write_each(writes)

    def _write_each(self, writes: list[tuple[int, int, bytes]]) -> list[_Reply]:
        """SYNC_WRITE and BULK_WRITE: each listed servo writes its block; no status
        (an error is only counted)."""
        servos = self._listening()
        for servo_id, address, data in writes:
            servo = servos.get(servo_id)
            if servo is None:
                continue
            error, names = servo.write(address, bytes(data))
            self.counters["sync_write_errors"] += bool(error)
            self._written(servo, names)
        return []

    # ---------------------------------------------------------------- summary

    def summary(self) -> dict:
        """What the emulator did (counts, times, faults)."""
        parser = self._parser
        return {
            "robot": self.robot.name,
            "port": self.port,
            "mode": "lock-step" if self.lockstep else "real time",
            "rate": self.rate,
            "ids": list(self.ids),
            "baud": self.bus.baud,
            "robot_time": float(self.groups[0].physics.time),
            "wall_time": float(self.wall_time),
            "stopped": self.stopped,
            "periods": int(self._periods),
            "packets": dict(sorted(self.packets.items())),
            "crc_errors": int(self.counters["crc_errors"]),
            "statuses": int(self.counters["statuses"]),
            "bytes_in": int(self.counters["bytes_in"]),
            "bytes_out": int(self.counters["bytes_out"]),
            "bytes_dropped": int(self.counters["bytes_dropped"]),
            "bytes_skipped": int(parser.skipped + parser.dropped),
            "malformed": int(self.counters["malformed"]),
            "sync_write_errors": int(self.counters["sync_write_errors"]),
            "late_periods": int(self.counters["late_periods"]),
            "late_statuses": int(self.counters["late_statuses"]),
            "max_lag": float(self.max_lag),
            "gain_disagreements": int(sum(g.gain_disagreements for g in self.groups)),
            "faults": list(self.applied_faults),
        }


# --------------------------------------------------------------------- the command


def run_sim_servo(
    robot: str,
    lockstep: bool = False,
    rate: float = 1.0,
    duration: float = math.inf,
    faults: Sequence = (),
    ids: Sequence[int] | None = None,
    out: str = "",
) -> dict:
    """`hrp2-drake sim-servo`: the robot's servos on a pseudo-terminal.

    Builds `SimulatedServos` for `StationConfig(robot=robot, scenario="fixed_base")`
    (one copy per group of IDs), prints one line
    `sim-servo: <robot> on <port> (<n> servos, ids ..., <baud> bit/s, <mode>)`
    (mode: "real time" or "lock-step")
    on stdout, serves (`ServoBusEmulator.serve`) and returns the summary.

    Args:
        robot: the robot's name in models/ or its robot.yaml (its description must
            have a `bus`).
        lockstep: lock-step timing instead of real time.
        rate: real time: robot seconds per wall second.
        duration: robot seconds to serve (inf: until a signal or a close fault).
        faults: fault specs (`parse_fault`).
        ids: IDs to serve instead of the description's (a multiple of its joints).
        out: a folder for the report (sim_servo.md) and the summary (sim_servo.json);
            empty: none.
    """
    from hrp2_drake.robot.station import StationConfig

    faults = parse_faults(faults)
    try:
        duration = float(duration)
    except (TypeError, ValueError):
        raise ValueError(f"sim-servo: duration '{duration}' is not seconds") from None
    if not duration > 0:
        raise ValueError(f"sim-servo: duration {duration} s, must be > 0")
    config = StationConfig(robot=robot, scenario="fixed_base")
    description = config.description()
    if not description.bus.active:
        raise ValueError(
            f"sim-servo: robot '{description.name}' has no bus in its description"
        )
    n = len(description.joints)
    copies = max(1, -(-len(ids) // n)) if ids else 1
    servos = [SimulatedServos(config) for _ in range(copies)]
    with ServoBusEmulator(
        servos, ids=ids, lockstep=lockstep, rate=rate, faults=faults
    ) as emulator:
        served = ", ".join(str(i) for i in emulator.ids)
        print(
            f"sim-servo: {description.name} on {emulator.port} "
            f"({len(emulator.ids)} servos, "
            f"ids {served}, {emulator.bus.baud} bit/s, "
            f"{'lock-step' if lockstep else 'real time'})",
            flush=True,
        )
        summary = emulator.serve(duration)
    if out:
        write_report(summary, Path(out))
    return summary


def write_report(summary: dict, folder: Path) -> None:
    """The summary as sim_servo.json and a short sim_servo.md in `folder`."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "sim_servo.json").write_text(json.dumps(summary, indent=2) + "\n")
    rows = [[name, str(count)] for name, count in summary["packets"].items()]
    counts = [
        [key.replace("_", " "), f"{summary[key]:g}"]
        for key in (
            "periods",
            "statuses",
            "crc_errors",
            "bytes_in",
            "bytes_out",
            "bytes_dropped",
            "bytes_skipped",
            "malformed",
            "sync_write_errors",
            "late_periods",
            "late_statuses",
            "max_lag",
            "gain_disagreements",
        )
    ]
    faults = [[f["fault"], f"{f['time']:g}"] for f in summary["faults"]]
    lines = [
        f"# sim-servo: {summary['robot']}",
        "",
        f"{len(summary['ids'])} servo(s), ids {summary['ids']}, "
        f"{summary['baud']} bit/s, "
        f"{summary['mode']} (rate {summary['rate']:g}), on {summary['port']}: "
        f"{summary['robot_time']:.3f} s of robot time in {summary['wall_time']:.3f} s, "
        f"ended by {summary['stopped'] or 'nothing'}.",
        "",
        "## Packets received",
        "",
        *markdown_table(["instruction", "packets"], rows or [["none", "0"]]),
        "",
        "## Counts",
        "",
        *markdown_table(["what", "count"], counts),
        "",
        "## Faults applied",
        "",
        *markdown_table(["fault", "robot time (s)"], faults or [["none", ""]]),
        "",
    ]
    (folder / "sim_servo.md").write_text("\n".join(lines))


__all__ = [
    "EmulatedServo",
    "FAULT_SYNTAX",
    "ServoBusEmulator",
    "ServoFault",
    "ServoGroup",
    "parse_fault",
    "parse_faults",
    "run_sim_servo",
    "status_times",
    "write_report",
]
