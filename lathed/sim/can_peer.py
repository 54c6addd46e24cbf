"""The simulated robot arm's CAN adapter: a serial-line CAN (slcan, as on a
CANable or other USB-CAN adapter) on a pseudo-terminal.

The frames are packed here with struct, independently of the DBC file the
driver decodes them with (etc/robot_arm.dbc), so a mistake in either shows
up as a wrong value rather than cancelling out. Layout: see plugins/can_robot.py.
"""
from __future__ import annotations

import asyncio
import os
import struct
from pathlib import Path

from lathed.sim.line import SimRobotArm
from lathed.sim.serial_peer import SerialPeer

JOINTS_A, JOINTS_B, TOOL, STATUS = 0x100, 0x101, 0x102, 0x103


def robot_frames(arm: SimRobotArm, counter: int) -> list[tuple[int, bytes]]:
    j = [int(round(a * 100)) for a in arm.joints]
    x, y, z = (int(round(v * 10)) for v in arm.tool_mm())
    c = counter % 256
    return [(JOINTS_A, struct.pack("<hhhBx", j[0], j[1], j[2], c)),
            (JOINTS_B, struct.pack("<hhhBx", j[3], j[4], j[5], c)),
            (TOOL, struct.pack("<hhhBx", x, y, z, c)),
            (STATUS, struct.pack("<BBHHBB", arm.state, arm.gripper, arm.alarm_code, arm.cycle_count,
                                 arm.program, c))]


def slcan_line(can_id: int, data: bytes) -> bytes:
    """One standard-id data frame in the slcan text protocol: t<iii><l><dd..>\\r."""
    return b"t%03X%d%s\r" % (can_id, len(data), data.hex().upper().encode())


class CanPeer(SerialPeer):
    def __init__(self, link: Path):
        super().__init__(link)
        self.counter = 0

    def open(self) -> str:
        name = super().open()
        # the driver sends adapter commands (O, C, S6); read and drop them so
        # its writes never block on a full tty buffer
        asyncio.get_running_loop().add_reader(self.master, self._drain, self.master)
        return name

    def _drain(self, fd: int) -> None:
        try:
            os.read(fd, 4096)
        except OSError:
            pass   # nobody has the other end open (EIO): nothing to drop

    def close(self) -> None:
        if self.master is not None:
            asyncio.get_running_loop().remove_reader(self.master)
        super().close()

    def send_arm(self, arm: SimRobotArm) -> None:
        self.write(b"".join(slcan_line(i, d) for i, d in robot_frames(arm, self.counter)))
        self.counter += 1
