"""A robot's servo bus from the controller's side (`ServoBus`), written once for
every bus kind: `hardware.dynamixel.DynamixelBus` names ROBOTIS' `dynamixel_sdk`,
`hardware.feetech.FeetechBus` Feetech's `scservo_sdk`; `hardware.bus_link` makes the
robot's (`servo_bus`) and runs the control loop's link over it (`BusLink`). No
protocol code of our own is on this side: packets, checksums and byte stuffing are
the SDKs'.

The two SDKs share one shape (PortHandler, PacketHandler, GroupSyncRead,
GroupSyncWrite, `readRx`, `ping`, `readNByteTxRx`, `writeNByteTxRx`), so what the
bus does is written once; a subclass names its SDK and reads its status error byte.
`ServoBus` is what the control loop and `hrp2-drake record` need of the servos:

- `start()`: open the port at the description's baud rate; ping every ID and check
  its model number; with torque off, set and read back the return delay, the
  position control mode (the model's) and the position P gain (`position_loop.gain`,
  the gain the motor model and the twin are stated at); read the present pose, make
  it the goal, torque on: the servos hold where they are.
- `read()`: one SYNC_READ of the description's `read` block (`BusDescription.read`),
  each servo's status taken with its error byte (the SDK's `readRx`: its
  `GroupSyncRead.rxPacket` drops it and stops at the first failure): positions in
  rad, and what went wrong per servo (no status, a corrupt one, a hardware alert).
- `write(q)`: one SYNC_WRITE of the goal positions (pulses, `BusDescription.to_pulses`,
  in the item's encoding: `ServoModel.encode`).
- `hardware_error(k)`: the Hardware Error Status of servo k, in words.

Every problem at start-up is one ValueError naming the port, the servo ID and its
joint; a port that disappears mid-run (the adapter unplugged, the emulator killed)
raises `BusClosed`.
"""

import termios
from dataclasses import dataclass, field

import numpy as np
import serial

from hrp2_drake.description import RobotDescription
from hrp2_drake.description.bus import servo_models
from hrp2_drake.hardware.link import LinkClosed

#: How long start-up waits for each status beyond its bytes' wire time (s): a servo
#: silent this long is absent. Generous: start-up is not timed, and a loaded host or
#: emulator may be late by more than the SDKs' own 34 ms.
STARTUP_WAIT = 0.5
#: What each servo's status in a period was (`BusRead.status`).
STATUS_OK, STATUS_SILENT, STATUS_CORRUPT = 0, 1, 2


class BusClosed(LinkClosed):
    """The serial port is gone (unplugged, closed by the other end)."""


@dataclass
class BusRead:
    """One period's sync read.

    Attributes:
        position: joint angles (rad, joint order); a servo that did not answer keeps
            its previous value.
        values: each `read` item of each servo in SI units ({item: array}), the same
            way.
        status: per servo, STATUS_OK, STATUS_SILENT (no status) or STATUS_CORRUPT
            (a status with a bad CRC or length).
        alert: per servo, the hardware alert bit of its status (bit 7 of the error
            byte: a hardware error; `ServoBus.hardware_error` says which).
        error: per servo, the status's error number (bits 0-6: 0 none).
    """

    position: np.ndarray
    values: dict[str, np.ndarray]
    status: np.ndarray
    alert: np.ndarray
    error: np.ndarray
    complete: bool = field(default=False)


class ServoBus:
    """The robot's servos on their bus (module docstring), through the maintainers'
    SDK that a subclass names (`_open_sdk`): `hardware.dynamixel.DynamixelBus`,
    `hardware.feetech.FeetechBus`.

    Args:
        robot: the robot description (its `bus`, joints, `position_loop.gain`).
        port: the serial port (e.g. /dev/ttyUSB0, or the emulator's pseudo-terminal).
    """

    def _open_sdk(self):
        """(the SDK's module, its PacketHandler) for this bus kind."""
        raise NotImplementedError

    def _split_error(self, error: int) -> tuple[bool, int]:
        """(hardware alert, error number) of a status's error byte."""
        raise NotImplementedError

    def _error_text(self, k: int, error: int) -> str:
        """A status's error in words (its error number's), for servo k."""
        return self._packet.getRxPacketError(error)

    def _before_sync_read(self) -> None:
        """Drops what came in since the last period (a status later than the SDK's
        packet timeout), counted in `stale_bytes`: both SDKs' `clearPort` flushes
        the output only, and `readRx` takes the first status with the ID it waits
        for, so a late status would pass for this period's, and every period after
        it would read the one before."""
        waiting = self._call(self._port.getBytesAvailable)
        if waiting:
            self._call(self._port.readPort, waiting)
            self.stale_bytes += waiting

    def __init__(self, robot: RobotDescription, port: str):
        self.robot = robot
        self.bus = bus = robot.bus
        if not bus.active:
            raise ValueError(f"robot '{robot.name}': its description has no bus")
        self.port_name = port
        self.model = bus.servo_model()
        self.ids = list(bus.ids)
        self._sdk, self._packet = self._open_sdk()
        self._port = _port_handler(self._sdk)(port)
        self.stale_bytes = 0
        self._address, self._length = bus.read_block()
        self._items = [
            (
                item,
                self.model.register(item).address - self._address,
                self.model.register(item).size,
            )
            for item in bus.read
        ]
        goal = self.model.register("goal_position")
        self._writer = self._sdk.GroupSyncWrite(
            self._port, self._packet, goal.address, goal.size
        )
        self._reader = self._sdk.GroupSyncRead(
            self._port, self._packet, self._address, self._length
        )
        for servo in self.ids:
            self._reader.addParam(servo)
        n = len(self.ids)
        self._last = BusRead(
            position=np.zeros(n),
            values={item: np.zeros(n) for item in bus.read},
            status=np.zeros(n, dtype=int),
            alert=np.zeros(n, dtype=bool),
            error=np.zeros(n, dtype=int),
        )
        self._raw = {item: np.zeros(n, dtype=np.int64) for item in bus.read}
        self.is_open = False

    # ---------------------------------------------------------------- naming

    def name(self, k: int) -> str:
        """Servo k as a person finds it: "servo ID 11 (joint1)"."""
        return f"servo ID {self.ids[k]} ({self.robot.joints[k]})"

    def _where(self, k: int | None = None) -> str:
        return f"{self.port_name}: " + (f"{self.name(k)}: " if k is not None else "")

    # ---------------------------------------------------------------- start-up

    def open(self) -> None:
        """Opens the port at the bus's baud rate; a ValueError naming it if it cannot
        be opened."""
        try:
            opened = self._port.openPort() and self._port.setBaudRate(self.bus.baud)
        except Exception as error:  # pyserial: SerialException, OSError
            raise ValueError(
                f"{self.port_name}: cannot open the port ({error})"
            ) from None
        if not opened:
            raise ValueError(
                f"{self.port_name}: cannot open the port at {self.bus.baud} bit/s"
            )
        self.is_open = True

    def start(self, gain: float | None = None) -> np.ndarray:
        """The start-up (module docstring), with the position P gain `gain` (the
        servo's units; None: the description's `position_loop.gain`); the present
        pose (rad), which the servos now hold with torque on."""
        gain = self.robot.position_loop.gain if gain is None else gain
        self._port.wait = STARTUP_WAIT
        if not self.is_open:
            self.open()
        for k in range(len(self.ids)):
            self._check_model(k)
        for k in range(len(self.ids)):
            self._write_checked(k, "torque_enable", 0)
            delay = self.model.register("return_delay_time")
            self._write_checked(
                k, "return_delay_time", round(self.bus.return_delay / delay.unit)
            )
            self._write_checked(k, "operating_mode", self.model.position_modes[0])
            self._write_checked(k, "position_p_gain", int(gain))
        # One READ and one WRITE per servo, not the periods' sync read and write: a
        # lock-step robot counts those as its periods.
        present = np.array(
            [self._read_checked(k, "present_position") for k in range(len(self.ids))]
        )
        q = self.bus.to_radians(present)
        goal = self.bus.to_pulses(q)
        for k in range(len(self.ids)):
            self._write_checked(k, "goal_position", int(goal[k]))
            self._write_checked(k, "torque_enable", 1)
        self._last.position[:] = q
        self.set_status_wait(self.bus.status_timeout or None)
        return q

    def set_status_wait(self, wait: float | None) -> None:
        """How long to wait for a status beyond its bytes' wire time (s; None: the
        SDK's own packet timeout)."""
        self._port.wait = wait

    def _check_model(self, k: int) -> None:
        servo = self.ids[k]
        number, result, error = self._call(self._packet.ping, self._port, servo)
        if result != self._sdk.COMM_SUCCESS:
            raise ValueError(
                f"{self._where(k)}no answer to PING "
                f"({self._packet.getTxRxResult(result)}): check its ID, the baud rate "
                f"({self.bus.baud} bit/s) and its power"
            )
        if number != self.model.model_number:
            models = servo_models(self.bus.kind)
            known = {m.model_number: name for name, m in models.items()}
            other = known.get(number, "a model this package does not know")
            raise ValueError(
                f"{self._where(k)}model number {number} ({other}), but the description "
                f"says {self.bus.model} ({self.model.model_number})"
            )

    def _write_checked(self, k: int, item: str, value: int) -> None:
        """Writes `item` of servo k and reads it back; a ValueError if either fails."""
        register = self.model.register(item)
        write = {
            1: self._packet.write1ByteTxRx,
            2: self._packet.write2ByteTxRx,
            4: self._packet.write4ByteTxRx,
        }[register.size]
        unsigned = register.to_raw(value)
        result, error = self._call(
            write, self._port, self.ids[k], register.address, unsigned
        )
        self._check_result(k, f"writing {item} = {value}", result, error)
        back = self._read_checked(k, item, "reading it back")
        if back != value:
            raise ValueError(f"{self._where(k)}{item}: wrote {value}, read back {back}")

    def _read_checked(self, k: int, item: str, what: str = "") -> int:
        """`item` of servo k (signed items as such); a ValueError if the read fails."""
        register = self.model.register(item)
        read = {
            1: self._packet.read1ByteTxRx,
            2: self._packet.read2ByteTxRx,
            4: self._packet.read4ByteTxRx,
        }[register.size]
        value, result, error = self._call(
            read, self._port, self.ids[k], register.address
        )
        self._check_result(k, what or f"reading {item}", result, error)
        return register.from_raw(value)

    def _check_result(self, k: int, what: str, result: int, error: int) -> None:
        if result != self._sdk.COMM_SUCCESS:
            raise ValueError(
                f"{self._where(k)}{what}: {self._packet.getTxRxResult(result)}"
            )
        alert, number = self._split_error(error)
        if alert:
            raise ValueError(
                f"{self._where(k)}{what}: hardware error: {self.hardware_error(k)}"
            )
        if number:
            raise ValueError(f"{self._where(k)}{what}: {self._error_text(k, number)}")

    def _call(self, function, *args):
        """An SDK call; a vanished port (pyserial's OSError or SerialException, or
        termios.error from a hung-up terminal) is `BusClosed`."""
        try:
            return function(*args)
        except (OSError, termios.error, serial.SerialException) as error:
            raise BusClosed(f"{self.port_name}: {error}") from None

    # ---------------------------------------------------------------- periods

    def read(self) -> BusRead:
        """One SYNC_READ (`BusRead`; the object is reused: copy what you keep)."""
        sdk, packet, port = self._sdk, self._packet, self._port
        last = self._last
        self._before_sync_read()
        result = self._call(self._reader.txPacket)
        if result != sdk.COMM_SUCCESS:
            raise BusClosed(
                f"{self.port_name}: sync read not sent ({packet.getTxRxResult(result)})"
            )
        status, alert, errors = last.status, last.alert, last.error
        for k, servo in enumerate(self.ids):
            data, result, error = self._call(packet.readRx, port, servo, self._length)
            if result != sdk.COMM_SUCCESS or len(data) != self._length:
                status[k] = (
                    STATUS_SILENT if result == sdk.COMM_RX_TIMEOUT else STATUS_CORRUPT
                )
                continue
            status[k] = STATUS_OK
            alert[k], errors[k] = self._split_error(error)
            for item, offset, size in self._items:
                self._raw[item][k] = self.model.decode(
                    item, bytes(data[offset : offset + size])
                )
        ok = status == STATUS_OK
        last.position[ok] = self.bus.to_radians(self._raw["present_position"])[ok]
        for item in self.bus.read:
            register = self.model.registers[item]
            last.values[item][ok] = (self._raw[item] * (register.unit or 1.0))[ok]
        last.values["present_position"][:] = last.position
        last.complete = bool(ok.all())
        return last

    def write(self, q: np.ndarray) -> None:
        """One SYNC_WRITE of the goal positions q (rad, joint order)."""
        pulses = self.bus.to_pulses(q)
        writer, encode = self._writer, self.model.encode
        writer.clearParam()
        for servo, value in zip(self.ids, pulses):
            writer.addParam(servo, list(encode("goal_position", int(value))))
        result = self._call(writer.txPacket)
        if result != self._sdk.COMM_SUCCESS:
            raise BusClosed(
                f"{self.port_name}: sync write not sent "
                f"({self._packet.getTxRxResult(result)})"
            )

    def hardware_error(self, k: int) -> str:
        """Servo k's Hardware Error Status in words (or why it could not be read)."""
        register = self.model.register("hardware_error_status")
        bits, result, _ = self._call(
            self._packet.read1ByteTxRx, self._port, self.ids[k], register.address
        )
        if result != self._sdk.COMM_SUCCESS:
            return (
                "its hardware error status could not be read "
                f"({self._packet.getTxRxResult(result)})"
            )
        return self.model.describe_hardware_error(bits)

    def torque(self, on: bool) -> None:
        """Torque enable of every servo (no read-back: used at the end of a run)."""
        register = self.model.register("torque_enable")
        for servo in self.ids:
            self._call(
                self._packet.write1ByteTxRx,
                self._port,
                servo,
                register.address,
                int(on),
            )

    def close(self) -> None:
        if self.is_open:
            try:
                self._port.closePort()
            except Exception:  # already gone
                pass
            self.is_open = False


def _port_handler(sdk):
    """The SDK's PortHandler class with the wait for a status set by the bus: its
    `wait` (s; None: the SDK's own: 2 x 16 ms + 2 ms with dynamixel-sdk and
    feetech-servo-sdk 1.0, 50 ms with ftservo-python-sdk; LeRobot patches the
    latter's timeout into the former). Each SDK computes its packet timeout in
    `setPacketTimeout(bytes)` after sending an instruction: the bytes' wire time
    plus a fixed wait, which this subclass sets (the same fields in both SDKs)."""

    class PortHandler(sdk.PortHandler):
        wait: float | None = None

        def setPacketTimeout(self, packet_length):  # noqa: N802 (the SDK's name)
            if self.wait is None:
                return super().setPacketTimeout(packet_length)
            self.packet_start_time = self.getCurrentTime()
            self.packet_timeout = (
                self.tx_time_per_byte * packet_length + self.wait * 1e3
            )

    return PortHandler
