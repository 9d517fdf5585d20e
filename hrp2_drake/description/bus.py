"""A robot's servo bus, as its description holds it (`RobotDescription.bus`): plain
data, and the bus arithmetic that both ends of the wire need, written once.

A Dynamixel robot's servos share one half-duplex serial line (Protocol 2.0). Every
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
units (`DynamixelModel.si`).

The servo models' control tables are data (`dynamixel_models.yaml` beside this file,
transcribed from ROBOTIS' e-manual, each with its source): a model is added there.
"""

import functools
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from hrp2_drake.config import load_config

#: The bus kinds a description may name ("": no bus).
BUS_KINDS = ("dynamixel",)
#: Bits on the wire per byte: start bit, 8 data bits, stop bit (8N1).
BITS_PER_BYTE = 10
#: Bytes of a Protocol 2.0 packet around its parameters: header (3) + reserved (1)
#: + ID (1) + length (2) + instruction (1) + CRC (2).
PACKET_OVERHEAD = 10
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
    eeprom: bool = False

    def limits(self) -> tuple[int, int]:
        """(low, high): the counts a WRITE may set."""
        if self.low or self.high:
            return self.low, self.high
        bits = 8 * self.size
        if self.signed:
            return -(1 << (bits - 1)), (1 << (bits - 1)) - 1
        return 0, (1 << bits) - 1


@dataclass
class DynamixelModel:
    """A Dynamixel servo model: its model number, its control table and its facts.

    Args:
        model_number: what PING and the Model Number item (address 0) return.
        firmware: the firmware version the emulator reports.
        source: where the numbers come from.
        pulses_per_turn: the absolute encoder's resolution.
        baud_rates: bit/s by value of the Baud Rate item (address 8): 0, 1, ...
        hardware_errors: what each bit of the Hardware Error Status item (address
            70) means, by bit: 0, 1, ... ("" for an unused bit).
        registers: the control table by snake_case name.
    """

    model_number: int = 0
    firmware: int = 0
    source: str = ""
    pulses_per_turn: int = 4096
    baud_rates: list[int] = field(default_factory=list)
    hardware_errors: list[str] = field(default_factory=list)
    registers: dict[str, Register] = field(default_factory=dict)

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
        if register.signed:
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
        where = f"dynamixel model {name}"
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


@dataclass
class _Models:
    models: dict[str, DynamixelModel] = field(default_factory=dict)


MODELS_FILE = Path(__file__).with_name("dynamixel_models.yaml")


@functools.lru_cache(maxsize=1)
def dynamixel_models() -> dict[str, DynamixelModel]:
    """The servo models this package knows (dynamixel_models.yaml), by name."""
    models = load_config(_Models, filename=MODELS_FILE).models
    for name, model in models.items():
        model.validate(name)
    return models


def dynamixel_model(name: str, where: str = "bus.model") -> DynamixelModel:
    """The servo model `name` ("XL330-M288"); a ValueError naming `where` and the
    known models."""
    models = dynamixel_models()
    if name not in models:
        raise ValueError(
            f"{where}: unknown servo model '{name}' (known: {sorted(models)})"
        )
    return models[name]


def wire_time(num_bytes: int, baud: float) -> float:
    """Seconds `num_bytes` take on a serial line at `baud` bit/s (8N1)."""
    return num_bytes * BITS_PER_BYTE / baud


def sync_read_bytes(num_servos: int) -> int:
    """Bytes of a SYNC_READ instruction for `num_servos` IDs (before byte stuffing):
    the packet's overhead, address (2), length (2), one byte per ID."""
    return PACKET_OVERHEAD + 4 + num_servos


def status_bytes(data_length: int) -> int:
    """Bytes of a status packet carrying `data_length` bytes: overhead, error (1)."""
    return PACKET_OVERHEAD + 1 + data_length


def sync_write_bytes(num_servos: int, data_length: int) -> int:
    """Bytes of a SYNC_WRITE of `data_length` bytes to each of `num_servos` IDs."""
    return PACKET_OVERHEAD + 4 + num_servos * (1 + data_length)


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
        kind: "dynamixel" (Protocol 2.0), or empty for a robot without a bus.
        protocol: the protocol version (2.0).
        baud: the line's rate (bit/s), as set in every servo.
        ids: the servo IDs, in the description's `joints` order.
        model: the servo model (`dynamixel_models.yaml`), e.g. "XL330-M288".
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

    @property
    def active(self) -> bool:
        """Whether the robot has a bus."""
        return bool(self.kind)

    def servo_model(self) -> DynamixelModel:
        return dynamixel_model(self.model)

    def validate(self, num_joints: int | None = None) -> None:
        """Raises ValueError naming the field (`num_joints`: how many the robot has)."""
        if not self.kind:
            return
        if self.kind not in BUS_KINDS:
            raise ValueError(f"bus.kind: '{self.kind}', expected one of {BUS_KINDS}")
        if self.protocol != 2.0:
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
        for name in ("adapter_latency", "compute_time", "supply_voltage"):
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
        status = wire_time(status_bytes(length), self.baud)
        return BusTiming(
            read_instruction=wire_time(sync_read_bytes(n), self.baud),
            statuses=n * (self.return_delay + status),
            adapter=self.adapter_latency,
            compute=self.compute_time if compute_time is None else compute_time,
            write=wire_time(sync_write_bytes(n, goal.size), self.baud),
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
