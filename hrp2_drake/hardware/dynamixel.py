"""A robot's Dynamixel bus from the controller's side, through ROBOTIS' own client
(`dynamixel_sdk`: PortHandler, PacketHandler 2.0, GroupSyncRead, GroupSyncWrite). No
protocol code of our own is on this side: packets, CRC and byte stuffing are the
SDK's. What the bus does is `hardware.bus_link.ServoBus`'s, for every kind; this
module names the SDK and reads Protocol 2.0's status error byte (bit 7: a hardware
alert, which the Hardware Error Status item details; bits 0-6: the error number).
"""

from hrp2_drake.hardware.servo_bus import ServoBus


class DynamixelBus(ServoBus):
    """The robot's Dynamixel servos on their bus (`ServoBus`), through
    `dynamixel_sdk`."""

    def _open_sdk(self):
        import dynamixel_sdk

        return dynamixel_sdk, dynamixel_sdk.PacketHandler(2.0)

    def _split_error(self, error: int) -> tuple[bool, int]:
        return bool(error & 0x80), error & 0x7F
