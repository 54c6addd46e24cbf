"""The simulated Arduino: DS18B20 readings on a pseudo-terminal; and a null
modem of two pseudo-terminals for the grinder's Modbus RTU line.

The pty's slave end is what a real USB-serial Arduino would be
(/dev/ttyACM0); a symlink at a stable path points to it so the config
can name it. Lines carry the CRC-16 checksum (lathed.wire), as the current
firmware sends them.
"""
from __future__ import annotations

import asyncio
import os
import stat
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
        _symlink(self.link, name)
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


class NullModem:
    """Two pseudo-terminals joined back to back, as two RS-485 adapters on
    one cable: a server opens ``inner`` (the machine's port), the driver
    opens the symlink ``link`` (the PC's adapter). Needed because a serial
    Modbus server, like a client, wants a tty path of its own to open."""

    def __init__(self, link: Path):
        self.link = link
        self.fds: list[int] = []
        self.inner: str | None = None

    def open(self) -> str:
        ma, sa = os.openpty()
        mb, sb = os.openpty()
        for s in (sa, sb):
            tty.setraw(s)
        for m in (ma, mb):
            os.set_blocking(m, False)
        self.fds = [ma, sa, mb, sb]
        self.inner = os.ttyname(sa)
        loop = asyncio.get_running_loop()
        loop.add_reader(ma, self._pump, ma, mb)
        loop.add_reader(mb, self._pump, mb, ma)
        _symlink(self.link, os.ttyname(sb))
        return self.inner

    @staticmethod
    def _pump(src: int, dst: int) -> None:
        try:
            os.write(dst, os.read(src, 4096))
        except OSError:
            pass   # the far side is not open: bytes on a dead line are lost

    def close(self) -> None:
        if self.fds:
            loop = asyncio.get_running_loop()
            loop.remove_reader(self.fds[0])
            loop.remove_reader(self.fds[2])
            for fd in self.fds:
                os.close(fd)
        self.fds = []
        self.inner = None


def link_dir_problem(directory: Path, create: bool) -> str | None:
    """Why ``directory`` may not hold the simulator's tty links, or None. Whoever
    can write a directory can point a link in it at a tty of their own (fake
    temperatures to the daemon), so it must be ours and writable by us alone;
    with ``create`` a missing one is made 0700."""
    if create:
        try:
            directory.mkdir(parents=True, mode=0o700)
        except FileExistsError:
            pass
        except OSError as e:
            return f"cannot create {directory}: {e.strerror or e}"
    try:
        st = directory.lstat()
    except FileNotFoundError:
        return None            # made 0700 when the simulator starts
    except OSError as e:
        return f"cannot use {directory}: {e.strerror or e}"
    if not stat.S_ISDIR(st.st_mode):
        return f"{directory} is not a directory"
    if st.st_uid != os.geteuid():
        return f"{directory} belongs to uid {st.st_uid}, not to us (uid {os.geteuid()})"
    if stat.S_IMODE(st.st_mode) & 0o022:
        return f"{directory} is writable by others (mode {stat.S_IMODE(st.st_mode):04o})"
    return None


def _symlink(link: Path, target: str) -> None:
    problem = link_dir_problem(link.parent, create=True)
    if problem:
        raise PermissionError(f"refusing to put the tty link {link} there: {problem}")
    tmp = link.with_name(link.name + ".new")
    if tmp.is_symlink() or tmp.exists():
        tmp.unlink()
    tmp.symlink_to(target)
    tmp.replace(link)   # atomic: a reader never sees the link missing mid-swap
