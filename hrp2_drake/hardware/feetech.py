"""A robot's Feetech bus (STS/SMS servos: the SO-101's STS3215) from the controller's
side, through Feetech's own client, `scservo_sdk` (PyPI `feetech-servo-sdk`, the
package LeRobot pins: PortHandler, PacketHandler, GroupSyncRead, GroupSyncWrite). No
protocol code of our own is on this side: packets and checksums are the SDK's. What
the bus does is `hardware.bus_link.ServoBus`'s, for every kind; this module names the
SDK and reads Feetech's status error byte.

Feetech's error byte is the servo's Status bits (voltage, angle sensor, temperature,
current, -, overload: `ServoModel.hardware_errors`), not an error number: any bit set
is a hardware alert. The SDK's pitfalls, handled where every bus handles them
(`ServoBus`): its packet timeout (`BusDescription.status_timeout`), a status later
than it (dropped before the next sync read, counted), a bad status on a sync read (a
corrupt status, counted per servo; three periods in a row end torque control).
`PacketHandler(0)`: STS/SMS words are little-endian (1: the SCS series, big-endian);
the SDK keeps it in a module global.
"""

from hrp2_drake.hardware.servo_bus import ServoBus


class FeetechBus(ServoBus):
    """The robot's Feetech servos on their bus (`ServoBus`), through `scservo_sdk`."""

    def _open_sdk(self):
        import scservo_sdk

        end = 0 if self.model.byte_order == "little" else 1
        return scservo_sdk, scservo_sdk.PacketHandler(end)

    def _split_error(self, error: int) -> tuple[bool, int]:
        return error != 0, 0
