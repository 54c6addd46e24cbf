"""The simulated Arduino: DS18B20 readings on a pseudo-terminal.

The pty's slave end is what a real USB-serial Arduino would be
(/dev/ttyACM0); a symlink at a stable path points to it so the config
can name it.
"""
from __future__ import annotations

import os
import tty
from pathlib import Path

from lathed.wire import format_temperature_line


class SerialPeer:
    def __init__(self, link: Path):
        self.link = link
        self.master: int | None = None
        self._slave: int | None = None
        self.seq = 0
        self.sent = 0
        self.dropped = 0

    def open(self) -> str:
        self.master, self._slave = os.openpty()
        tty.setraw(self._slave)              # a serial port does no line editing or echo
        os.set_blocking(self.master, False)  # an Arduino never waits for its reader
        name = os.ttyname(self._slave)
        self.link.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.link.with_name(self.link.name + ".new")
        if tmp.is_symlink() or tmp.exists():
            tmp.unlink()
        tmp.symlink_to(name)
        tmp.replace(self.link)
        return name

    def close(self) -> None:
        for fd in (self.master, self._slave):
            if fd is not None:
                os.close(fd)
        self.master = self._slave = None

    def send(self, uptime_ms: int, readings: dict[str, float]) -> None:
        self.write(format_temperature_line(self.seq, uptime_ms, readings))
        self.seq += 1

    def write(self, data: bytes) -> None:
        if self.master is None:
            return
        try:
            os.write(self.master, data)
            self.sent += 1
        except (BlockingIOError, OSError):
            # nobody reading and the tty buffer is full: a real Arduino's
            # bytes are lost the same way
            self.dropped += 1
