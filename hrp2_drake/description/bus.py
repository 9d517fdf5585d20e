"""A robot's servo bus, as its description holds it (`RobotDescription.bus`): plain
data, and the bus arithmetic that both ends of the wire need, written once.

A servo-bus robot's servos share one half-duplex serial line: Dynamixel's Protocol
2.0 (`kind: dynamixel`) or Feetech's STS/SMS protocol (`kind: feetech`, Dynamixel
Protocol 1.0's framing: `FF FF ID LEN INSTR params CHK`). The two differ in their
packets' bytes (`Framing`), their control tables and their value encodings (two's
complement or sign-magnitude, `Register`); the rest is common. Every
control period the host sends one SYNC_READ (one instruction for every ID), each
servo answers with a status packet in turn, the host computes, then sends one
SYNC_WRITE of the goal positions. Nothing else crosses the wire in a period, so the
period a bus can carry follows from the bytes (10 bits each on the wire: start, 8
data, stop), the baud rate, each servo's return delay and the USB adapter's latency
timer (`BusTiming`). A period shorter than that is refused with the budget
(`check_bus_period`).

Units are one equation each, used by the controller's link (`hardware.dynamixel`)
and by the emulated servos (`hardware.sim_servo`) alike: positions in pulses of the
servo's absolute encoder, `zero` pulses at q = 0, `direction` +1 or -1
(`BusDescription.to_pulses`, `to_radians`); the other registers in their e-manual
units (`ServoModel.si`).

The servo models' control tables are data, one file per kind beside this file
(`dynamixel_models.yaml` from ROBOTIS' e-manual, `feetech_models.yaml` from Feetech's
memory table, each model with its source): a model is added there.
"""

import functools
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from hrp2_drake.config import load_config

#: The bus kinds a description may name ("": no bus).
BUS_KINDS = ("dynamixel", "feetech")
#: Bits on the wire per byte: start bit, 8 data bits, stop bit (8N1).
BITS_PER_BYTE = 10
#: Bytes of a Protocol 2.0 packet around its parameters: header (3) + reserved (1)
#: + ID (1) + length (2) + instruction (1) + CRC (2).
PACKET_OVERHEAD = 10


@dataclass(frozen=True)
class Framing:
    """The bytes of a bus kind's packets (what `BusTiming` counts).

    Args:
        overhead: bytes of an instruction packet around its parameters.
        status_overhead: bytes of a status packet around its data.
        field: bytes of an address or a length in READ, SYNC_READ, SYNC_WRITE.
    """

    overhead: int
    status_overhead: int
    field: int


#: Per bus kind. Protocol 2.0: header, reserved, ID, length (2), instruction, CRC (2);
#: its status adds the error byte after the instruction (0x55). Feetech: FF FF, ID,
#: LEN, INSTR, checksum; its status has the error byte in the instruction's place.
FRAMINGS = {
    "dynamixel": Framing(overhead=PACKET_OVERHEAD, status_overhead=11, field=2),
    "feetech": Framing(overhead=6, status_overhead=6, field=1),
}
#: The broadcast ID (SYNC_READ, SYNC_WRITE, broadcast PING).
BROADCAST_ID = 0xFE
#: The highest servo ID (0xFD and 0xFF are header bytes).
MAX_ID = 0xFC


@dataclass
class Register:
    """One item of a servo's control table (ROBOTIS e-manual).

    Args:
        address: its address (bytes from 0).
        size: its size (1, 2 or 4 bytes, little-endian).
        access: "R" (read only) or "RW".
        initial: its value at power-up (a count); for read-only items the emulator
            computes, a typical value.
        low, high: the range a WRITE may set (counts; both 0: the size's range).
        unit: SI units per count (rad, rad/s, A, V, °C, s, or a fraction for a PWM
            duty); 0: a plain count (an ID, a mode, a gain).
        signed: two's complement over `size` bytes (velocities, currents, positions).
        sign_bit: sign-magnitude instead (Feetech): the bit that holds the sign, the
            bits below it the magnitude (15 for positions and speeds, 10 for the
            load); 0: none.
        eeprom: in the EEPROM area: writable only with torque off.
    """

    address: int = 0
    size: int = 1
    access: str = "R"
    initial: int = 0
    low: int = 0
    high: int = 0
    unit: float = 0.0
    signed: bool = False
    sign_bit: int = 0
    eeprom: bool = False

    def limits(self) -> tuple[int, int]:
        """(low, high): the counts a WRITE may set."""
        if self.low or self.high:
            return self.low, self.high
        return self.counts_range()

    def counts_range(self) -> tuple[int, int]:
        """(low, high): the counts the item's bytes can hold."""
        bits = 8 * self.size
        if self.sign_bit:
            return -((1 << self.sign_bit) - 1), (1 << self.sign_bit) - 1
        if self.signed:
            return -(1 << (bits - 1)), (1 << (bits - 1)) - 1
        return 0, (1 << bits) - 1

    def from_raw(self, raw: int) -> int:
        """The counts an unsigned word of the item's size holds (its encoding:
        two's complement, sign-magnitude or none)."""
        raw = int(raw)
        if self.sign_bit:
            magnitude = raw & ((1 << self.sign_bit) - 1)
            return -magnitude if raw >> self.sign_bit & 1 else magnitude
        bits = 8 * self.size
        if self.signed and raw >= 1 << (bits - 1):
            return raw - (1 << bits)
        return raw

    def to_raw(self, value: int) -> int:
        """The unsigned word of the item's size that holds `value` counts (within
        `counts_range`)."""
        value = int(value)
        if self.sign_bit:
            return -value | 1 << self.sign_bit if value < 0 else value
        return value & ((1 << (8 * self.size)) - 1)


@dataclass
class ServoModel:
    """A bus servo model: its model number, its control table and its facts.

    The item names are snake_case and shared by the kinds where the item is the
    same thing (Feetech's P Coefficient is `position_p_gain`, its Status
    `hardware_error_status`, its Unloading Condition `shutdown`): what the link and
    the emulator do with an item is written once.

    Args:
        model_number: what the Model Number item returns (and Protocol 2.0's PING).
        firmware: the firmware version the emulator reports.
        source: where the numbers come from.
        pulses_per_turn: the absolute encoder's resolution.
        byte_order: "little" (Dynamixel, Feetech STS/SMS) or "big" (Feetech SCS).
        position_modes: the Operating Mode values that are position control (the
            first: what the link sets).
        baud_rates: bit/s by value of the Baud Rate item: 0, 1, ...
        hardware_errors: what each bit of the Hardware Error Status item means, by
            bit: 0, 1, ... ("" for an unused bit).
        registers: the control table by snake_case name.
    """

    model_number: int = 0
    firmware: int = 0
    source: str = ""
    pulses_per_turn: int = 4096
    byte_order: str = "little"
    position_modes: list[int] = field(default_factory=lambda: [3, 4])
    baud_rates: list[int] = field(default_factory=list)
    hardware_errors: list[str] = field(default_factory=list)
    registers: dict[str, Register] = field(default_factory=dict)

    def decode(self, name: str, data: bytes) -> int:
        """Item `name`'s counts from its bytes."""
        return self.registers[name].from_raw(int.from_bytes(data, self.byte_order))

    def encode(self, name: str, value: int) -> bytes:
        """Item `name`'s bytes for `value` counts."""
        register = self.registers[name]
        return register.to_raw(value).to_bytes(register.size, self.byte_order)

    def register(self, name: str, where: str = "") -> Register:
        """The item `name`; a ValueError naming `where` and the known items."""
        if name not in self.registers:
            raise ValueError(
                f"{where or 'bus'}: '{name}' is not an item of the control table "
                f"(known: {sorted(self.registers)})"
            )
        return self.registers[name]

    def table_size(self) -> int:
        """Bytes of the control table (its last item's end)."""
        return max(r.address + r.size for r in self.registers.values())

    def si(self, name: str, counts):
        """The item's counts in SI units (its `unit`); signed items as such."""
        register = self.registers[name]
        counts = np.asarray(counts, dtype=np.int64)
        if register.sign_bit:
            magnitude = counts & ((1 << register.sign_bit) - 1)
            counts = np.where(counts >> register.sign_bit & 1, -magnitude, magnitude)
        elif register.signed:
            bits = 8 * register.size
            counts = np.where(counts >= 1 << (bits - 1), counts - (1 << bits), counts)
        return counts * (register.unit or 1.0)

    def describe_hardware_error(self, bits: int) -> str:
        """The Hardware Error Status bits in words ("overload, overheating")."""
        names = [
            text
            for bit, text in enumerate(self.hardware_errors)
            if text and bits >> bit & 1
        ]
        return ", ".join(names) or f"status 0x{bits:02x}"

    def validate(self, name: str = "") -> None:
        where = f"servo model {name}"
        if not self.model_number:
            raise ValueError(f"{where}: model_number missing")
        needed = (
            "model_number",
            "id",
            "return_delay_time",
            "operating_mode",
            "torque_enable",
            "hardware_error_status",
            "position_p_gain",
            "goal_position",
            "present_position",
        )
        missing = [item for item in needed if item not in self.registers]
        if missing:
            raise ValueError(f"{where}: registers {missing} missing")
        for item, register in self.registers.items():
            if register.size not in (1, 2, 4) or register.access not in ("R", "RW"):
                raise ValueError(
                    f"{where}: register {item}: size 1, 2 or 4 and access R or RW"
                )
            if register.sign_bit and not 0 < register.sign_bit < 8 * register.size:
                raise ValueError(f"{where}: register {item}: sign_bit inside its bytes")
        if self.byte_order not in ("little", "big") or not self.position_modes:
            raise ValueError(f"{where}: byte_order little or big, position_modes set")


@dataclass
class _Models:
    models: dict[str, ServoModel] = field(default_factory=dict)


#: The control tables of each bus kind.
MODELS_FILES = {
    "dynamixel": Path(__file__).with_name("dynamixel_models.yaml"),
    "feetech": Path(__file__).with_name("feetech_models.yaml"),
}


@functools.cache
def servo_models(kind: str = "dynamixel") -> dict[str, ServoModel]:
    """The servo models this package knows on a bus of `kind`, by name."""
    models = load_config(_Models, filename=MODELS_FILES[kind]).models
    for name, model in models.items():
        model.validate(name)
    return models


def servo_model(kind: str, name: str, where: str = "bus.model") -> ServoModel:
    """The servo model `name` of bus kind `kind`; a ValueError naming `where` and
    the known models."""
    models = servo_models(kind)
    if name not in models:
        raise ValueError(
            f"{where}: unknown servo model '{name}' (known: {sorted(models)})"
        )
    return models[name]


def dynamixel_models() -> dict[str, ServoModel]:
    """The Dynamixel models (dynamixel_models.yaml), by name."""
    return servo_models("dynamixel")


def dynamixel_model(name: str, where: str = "bus.model") -> ServoModel:
    """The Dynamixel model `name` ("XL330-M288")."""
    return servo_model("dynamixel", name, where)


def wire_time(num_bytes: int, baud: float) -> float:
    """Seconds `num_bytes` take on a serial line at `baud` bit/s (8N1)."""
    return num_bytes * BITS_PER_BYTE / baud


_DYNAMIXEL = FRAMINGS["dynamixel"]


def sync_read_bytes(num_servos: int, framing: Framing = _DYNAMIXEL) -> int:
    """Bytes of a SYNC_READ instruction for `num_servos` IDs (before byte stuffing):
    the packet's overhead, address, length, one byte per ID."""
    return framing.overhead + 2 * framing.field + num_servos


def status_bytes(data_length: int, framing: Framing = _DYNAMIXEL) -> int:
    """Bytes of a status packet carrying `data_length` bytes (error byte included)."""
    return framing.status_overhead + data_length


def sync_write_bytes(
    num_servos: int, data_length: int, framing: Framing = _DYNAMIXEL
) -> int:
    """Bytes of a SYNC_WRITE of `data_length` bytes to each of `num_servos` IDs."""
    return framing.overhead + 2 * framing.field + num_servos * (1 + data_length)


@dataclass
class BusTiming:
    """One control period on the bus (s), from the bytes that cross it.

    The servos sample when the SYNC_READ ends (`read_instruction`); each answers in
    turn after its return delay (`statuses`); the host sees the last status after the
    adapter's latency timer (`adapter`), computes (`compute`), and the goal positions
    arrive when the SYNC_WRITE ends (`write`).

    Attributes:
        read_instruction, statuses, adapter, compute, write: the parts (s).
        read: instruction + statuses + adapter: what a sync read costs the host.
        read_to_write: from the servos' sample to their new goal (s): the delay the
            controller's command sees, inside the period.
        cycle: the whole period's traffic and compute: the shortest period.
    """

    read_instruction: float
    statuses: float
    adapter: float
    compute: float
    write: float

    @property
    def read(self) -> float:
        return self.read_instruction + self.statuses + self.adapter

    @property
    def read_to_write(self) -> float:
        return self.statuses + self.adapter + self.compute + self.write

    @property
    def cycle(self) -> float:
        return self.read_instruction + self.read_to_write

    def describe(self) -> str:
        """The budget in one line (µs)."""
        us = lambda s: f"{s * 1e6:.0f} µs"  # noqa: E731
        return (
            f"sync read {us(self.read_instruction)} + statuses {us(self.statuses)} + "
            f"adapter latency {us(self.adapter)} + compute {us(self.compute)} + sync "
            f"write {us(self.write)} = {us(self.cycle)}"
        )


@dataclass
class BusDescription:
    """A robot's servo bus (a robot description's `bus`; `kind` empty: none).

    A robot on a bus runs at the bus's rate: its `sensors.period` is the bus period
    (one sync read and one sync write per period), which the bus must carry
    (`check_bus_period`). The position P gain the host sets is the description's
    `position_loop.gain`: the gain its motor model and twin are stated at.

    Args:
        kind: "dynamixel" (Protocol 2.0), "feetech" (STS/SMS), or empty for a robot
            without a bus.
        protocol: the Dynamixel protocol version (2.0; not read for Feetech).
        baud: the line's rate (bit/s), as set in every servo.
        ids: the servo IDs, in the description's `joints` order.
        model: the servo model (`dynamixel_models.yaml`, `feetech_models.yaml`),
            e.g. "XL330-M288", "STS3215".
        return_delay: each servo's Return Delay Time (s; written in units of the
            model's register, 2 µs; the factory value is 500 µs).
        read: the items read every period, one contiguous block per servo (its
            first item to its last); `present_position` must be among them.
        zero: per joint, the position in pulses at q = 0 (empty: half a turn, 2048
            on a 4096-pulse encoder).
        direction: per joint, +1 if q grows with the pulses, -1 if not (empty: +1).
        adapter_latency: the USB adapter's latency timer (s): an FTDI chip holds
            received bytes up to this long (1 ms with `setserial low_latency`, 16 ms
            without). 0 for a pseudo-terminal.
        compute_time: the host's time from the last status to the sync write (s):
            one controller tick and the packet's encoding.
        supply_voltage: the servos' supply (V): what the emulated servos report as
            their input voltage.
        silent_periods: a servo that answers no sync read for this many periods in a
            row ends torque control (a ramp to position control).
        status_timeout: how long the host waits for a status in a period, beyond
            its bytes' wire time (s; the SDK's packet timeout); 0: the SDK's own
            (34 ms with dynamixel-sdk and feetech-servo-sdk 1.0).
    """

    kind: str = ""
    protocol: float = 2.0
    baud: int = 1_000_000
    ids: list[int] = field(default_factory=list)
    model: str = ""
    return_delay: float = 0.0
    read: list[str] = field(default_factory=lambda: ["present_position"])
    zero: list[int] = field(default_factory=list)
    direction: list[int] = field(default_factory=list)
    adapter_latency: float = 0.001
    compute_time: float = 0.0005
    supply_voltage: float = 5.0
    silent_periods: int = 3
    status_timeout: float = 0.0

    @property
    def active(self) -> bool:
        """Whether the robot has a bus."""
        return bool(self.kind)

    def servo_model(self) -> ServoModel:
        return servo_model(self.kind, self.model)

    @property
    def framing(self) -> Framing:
        """The bytes of this bus's packets."""
        return FRAMINGS[self.kind]

    def validate(self, num_joints: int | None = None) -> None:
        """Raises ValueError naming the field (`num_joints`: how many the robot has)."""
        if not self.kind:
            return
        if self.kind not in BUS_KINDS:
            raise ValueError(f"bus.kind: '{self.kind}', expected one of {BUS_KINDS}")
        if self.kind == "dynamixel" and self.protocol != 2.0:
            raise ValueError(
                f"bus.protocol: {self.protocol}, only Protocol 2.0 is supported"
            )
        model = self.servo_model()
        if self.baud not in model.baud_rates:
            raise ValueError(
                f"bus.baud: {self.baud} bit/s is not a rate of the {self.model} "
                f"(its Baud Rate item's: {model.baud_rates})"
            )
        if not self.ids:
            raise ValueError("bus.ids: empty, expected one servo ID per joint")
        bad = [i for i in self.ids if not (isinstance(i, int) and 0 <= i <= MAX_ID)]
        if bad:
            raise ValueError(f"bus.ids: {bad} are not servo IDs (0 to {MAX_ID})")
        twice = sorted({i for i in self.ids if self.ids.count(i) > 1})
        if twice:
            raise ValueError(f"bus.ids: IDs listed twice {twice}")
        if num_joints is not None and len(self.ids) != num_joints:
            raise ValueError(
                f"bus.ids: {len(self.ids)} IDs for {num_joints} joints (one per joint, "
                "in the order of `joints`)"
            )
        n = len(self.ids)
        for name in ("zero", "direction"):
            values = getattr(self, name)
            if values and len(values) != n:
                raise ValueError(f"bus.{name}: {len(values)} values for {n} servos")
        if any(d not in (1, -1) for d in self.direction):
            raise ValueError(f"bus.direction: {self.direction}, each +1 or -1")
        delay = model.register("return_delay_time", "bus.return_delay")
        counts = self.return_delay / delay.unit
        if not (
            0 <= counts <= delay.limits()[1] and abs(counts - round(counts)) < 1e-6
        ):
            raise ValueError(
                f"bus.return_delay: {self.return_delay} s is not a whole number of "
                f"{delay.unit * 1e6:g} µs from 0 to "
                f"{delay.limits()[1] * delay.unit * 1e6:g} µs"
            )
        if "present_position" not in self.read:
            raise ValueError(f"bus.read: {self.read} must include present_position")
        for item in self.read:
            model.register(item, "bus.read")
        for name in (
            "adapter_latency",
            "compute_time",
            "supply_voltage",
            "status_timeout",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"bus.{name}: {value} must be finite and >= 0")
        if not (isinstance(self.silent_periods, int) and self.silent_periods >= 1):
            raise ValueError(
                f"bus.silent_periods: {self.silent_periods!r}, an integer >= 1"
            )

    # ---------------------------------------------------------------- units

    def quantum(self) -> float:
        """One pulse of the position items (rad)."""
        return 2 * math.pi / self.servo_model().pulses_per_turn

    def _zero(self) -> np.ndarray:
        return np.array(
            self.zero or [self.servo_model().pulses_per_turn // 2] * len(self.ids)
        )

    def _direction(self) -> np.ndarray:
        return np.array(self.direction or [1] * len(self.ids), dtype=float)

    def to_pulses(self, q: np.ndarray) -> np.ndarray:
        """Joint angles (rad, joint order) as goal positions (pulses, int64): the
        nearest pulse (half to even)."""
        pulses = np.rint(np.asarray(q, float) * self._direction() / self.quantum())
        return pulses.astype(np.int64) + self._zero()

    def to_radians(self, pulses: np.ndarray) -> np.ndarray:
        """Positions (pulses, signed, joint order) as joint angles (rad)."""
        offset = np.asarray(pulses, dtype=np.int64) - self._zero()
        return offset * self._direction() * self.quantum()

    def quantized(self, q: np.ndarray) -> np.ndarray:
        """q (rad) as the servo takes it: through the goal position's pulses."""
        return self.to_radians(self.to_pulses(q))

    # ---------------------------------------------------------------- traffic

    def read_block(self) -> tuple[int, int]:
        """(address, length): the block each servo returns per sync read, from the
        first of the `read` items to the end of the last."""
        model = self.servo_model()
        registers = [model.register(item, "bus.read") for item in self.read]
        start = min(r.address for r in registers)
        end = max(r.address + r.size for r in registers)
        return start, end - start

    def timing(self, compute_time: float | None = None) -> BusTiming:
        """One period's traffic on this bus (`BusTiming`); `compute_time` (s) instead
        of the description's."""
        n = len(self.ids)
        _, length = self.read_block()
        goal = self.servo_model().register("goal_position")
        framing = self.framing
        status = wire_time(status_bytes(length, framing), self.baud)
        return BusTiming(
            read_instruction=wire_time(sync_read_bytes(n, framing), self.baud),
            statuses=n * (self.return_delay + status),
            adapter=self.adapter_latency,
            compute=self.compute_time if compute_time is None else compute_time,
            write=wire_time(sync_write_bytes(n, goal.size, framing), self.baud),
        )


def bus_for_period(bus: BusDescription, period: float) -> tuple[BusDescription, str]:
    """A bus that carries `period` (s): `bus` itself if it does; otherwise the same
    servos at their model's fastest baud rate with no adapter latency (a UART on the
    host or a microcontroller as bus master: a USB adapter's 1 ms latency timer
    alone rules out 1 kHz), with a note saying so. A ValueError if even that bus
    cannot."""
    if bus.timing().cycle <= period * (1 + 1e-9):
        return bus, ""
    fastest = replace(bus, baud=max(bus.servo_model().baud_rates), adapter_latency=0.0)
    if fastest.timing().cycle > period * (1 + 1e-9):
        raise ValueError(
            f"{1 / period:.0f} Hz: not even {len(bus.ids)} {bus.model} at "
            f"{fastest.baud / 1e6:g} Mbit/s without adapter latency carry it: "
            f"{fastest.timing().describe()}"
        )
    note = (
        f"the bus as described needs {bus.timing().cycle * 1e3:.2f} ms per period; at "
        f"{fastest.baud / 1e6:g} Mbit/s without adapter latency (a UART bus master), "
        f"{fastest.timing().cycle * 1e3:.2f} ms"
    )
    return fastest, note


def check_bus_period(
    bus: BusDescription, period: float, where: str = "sensors.period"
) -> None:
    """Raises ValueError naming `where` if `period` (s) is shorter than one period's
    traffic on `bus` (`BusTiming.cycle`), with the budget."""
    if not bus.active:
        return
    timing = bus.timing()
    if period < timing.cycle * (1 - 1e-9):
        raise ValueError(
            f"{where}: {period * 1e3:g} ms ({1 / period:.0f} Hz) is shorter than what "
            f"{len(bus.ids)} {bus.model} servo(s) at {bus.baud / 1e6:g} Mbit/s need "
            f"per period: {timing.describe()} (at most {1 / timing.cycle:.0f} Hz)"
        )
