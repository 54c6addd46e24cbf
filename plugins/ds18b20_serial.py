"""DS18B20 temperatures from an Arduino over a serial line (the line format: lathed.wire).

Each sensor becomes a ``t_<name>`` quantity in °C; bad lines and readings are refused and
counted by reason, the sequence resyncs by itself, and a silent port is re-opened with
backoff. Keys: docs/configuration.md; behaviour: docs/machines.md.
"""
from __future__ import annotations

import asyncio
import re
import time
from collections import Counter

import serial

from lathed import hookimpl
from lathed.bus import Sample
from lathed.config import Section
from lathed.driver import Driver
from lathed.wire import LineError, parse_temperature_line

POWER_ON_C = 85.0
DISCONNECTED_C = -127.0
MAX_LINE = 512   # bytes; a real line is < 100, so anything longer is noise
MIN_LINE = 10    # bytes of the shortest line, b"T,0,0*0000" less its end: bounds lines per second
NAME = re.compile(r"[A-Za-z0-9_]{1,24}")


def split_lines(buf: bytes, limit: int = MAX_LINE) -> tuple[list[bytes], bytes]:
    """The lines at the head of ``buf`` and the rest: each up to and with its newline,
    or its first ``limit`` bytes if it runs longer (an over-long line is cut, as
    readline(limit) cuts it, and its tail starts the next)."""
    lines = []
    start = 0
    while True:
        nl = buf.find(b"\n", start, start + limit)
        if nl >= 0:
            end = nl + 1
        elif len(buf) - start >= limit:
            end = start + limit
        else:
            return lines, buf[start:]
        lines.append(buf[start:end])
        start = end


class DS18B20Serial(Driver):
    role = "sensor"
    kind = "temperature"

    def __init__(self, name: str, section: Section):
        super().__init__(name, section)
        self.port = section.getstr("port")
        self.baudrate = section.getint("baudrate", 115200, minval=300, maxval=4_000_000)
        self.stale_after = section.getduration("stale_after", 20.0, minval=0.1, maxval=3600)
        self.require_crc = section.getstr("checksum", "any", choices=("any", "crc16")) == "crc16"
        expected = section.getlist("sensors", None)
        if expected is not None:
            bad = [n for n in expected if not NAME.fullmatch(n)]
            if bad or not expected:
                raise section.error("sensors", f"{bad[0]!r} is not a sensor name (1-24 of A-Za-z0-9_)"
                                    if bad else "an empty list would refuse every sensor")
        self.expected = frozenset(expected) if expected is not None else None
        self.max_sensors = section.getint("max_sensors", 32, minval=1, maxval=256)
        self.forget_after = section.getduration("forget_after", 600.0, minval=1.0, maxval=30 * 86400)
        if self.forget_after <= self.stale_after:
            raise section.error("forget_after", f"must be longer than stale_after ({self.stale_after:g} s)")
        # lines per ms the link can carry at most: seq cannot advance faster
        self._lines_per_ms = self.baudrate / 10 / 1000 / MIN_LINE
        self.ser: serial.Serial | None = None
        self.rejected: Counter = Counter()
        self.accepted = 0
        self.lines = 0
        self.last_line_error: str | None = None
        self.readings: dict[str, tuple[float, float]] = {}   # sensor -> (celsius, t)
        self.checksums: Counter = Counter()                  # lines by checksum kind
        self.forgotten = 0
        self._last: tuple[int, int] | None = None            # (seq, uptime_ms) of the last line taken
        self._fresh = True                                   # no line taken since (re)connecting
        self._partial = b""

    async def connect(self) -> None:
        def opener() -> serial.Serial:
            s = serial.serial_for_url(self.port, baudrate=self.baudrate, timeout=0.25)
            s.reset_input_buffer()   # what queued while nobody listened is old news
            return s
        try:
            self.ser = await asyncio.to_thread(opener)
            self._partial = b""
            self._fresh = True   # another board may be on the port now: its numbering is taken as it comes
        except (serial.SerialException, OSError) as e:
            raise ConnectionError(f"cannot open {self.port}: {e} (Arduino unplugged?)") from None

    async def close(self) -> None:
        if self.ser is not None:
            s, self.ser = self.ser, None
            await asyncio.to_thread(s.close)

    def handle_line(self, raw: bytes, now: float) -> int:
        """Validate one line and publish its good readings; returns how many."""
        self.lines += 1
        if not raw.endswith(b"\n"):
            self.rejected["malformed"] += 1     # over-long or cut off by a timeout
            self.last_line_error = "line too long or not terminated (noise on the line?)"
            return 0
        try:
            seq, uptime, readings, checksum = parse_temperature_line(raw)
        except LineError as e:
            self.rejected["malformed"] += 1
            self.last_line_error = str(e)
            return 0
        if self.require_crc and checksum != "crc16":
            self.rejected["weak_checksum"] += 1
            self.last_line_error = "line has the legacy 8-bit XOR checksum; checksum = \"crc16\" requires CRC-16"
            return 0
        self.checksums[checksum] += 1
        if not self._sequence(seq, uptime):
            return 0
        self._forget_silent(now)
        good = 0
        for name, celsius in readings.items():
            if not NAME.fullmatch(name):
                self.rejected["bad_name"] += 1
                self.last_line_error = f"sensor name {name[:32]!r} is not 1-24 of A-Za-z0-9_"
            elif self.expected is not None and name not in self.expected:
                self.rejected["unknown_sensor"] += 1
                self.last_line_error = f"sensor {name!r} is not in sensors = [...]"
            elif name not in self.readings and self.expected is None and len(self.readings) >= self.max_sensors:
                self.rejected["too_many_sensors"] += 1
                self.last_line_error = f"new sensor {name!r} beyond max_sensors = {self.max_sensors}"
            elif celsius == POWER_ON_C:
                self.rejected["power_on_85"] += 1
            elif celsius == DISCONNECTED_C:
                self.rejected["disconnected_-127"] += 1
            elif not -55.0 <= celsius <= 125.0:
                self.rejected["out_of_range"] += 1
            elif self.ctx.bus.publish(Sample(self.name, f"t_{name}", celsius, "°C", now)):
                good += 1
                self.readings[name] = (celsius, now)
            else:
                self.rejected["implausible"] += 1
        self.accepted += good
        if good:
            self.mark_data()
        return good

    def _sequence(self, seq: int, uptime: int) -> bool:
        """Follow the Arduino's numbering; False only for a replay of the last line."""
        last, self._last = self._last, (seq, uptime)
        fresh, self._fresh = self._fresh, False
        if last is None:
            return True
        last_seq, last_uptime = last
        if (seq, uptime) == last and not fresh:
            self.rejected["duplicate"] += 1
            return False
        if uptime < last_uptime:
            self._restarted()
        elif seq <= last_seq or seq - last_seq > 2 + (uptime - last_uptime) * self._lines_per_ms:
            # a swapped board, or a line whose seq no link could have reached: take the new numbering
            # (after a reconnect that is simply where the numbering now is)
            if fresh:
                return True
            self.rejected["resync"] += 1
            self.ctx.log.warning("serial_resync", port=self.port, seq_from=last_seq, seq_to=seq,
                                 uptime_ms=uptime - last_uptime)
        elif seq > last_seq + 1:
            self.rejected["lost_lines"] += seq - last_seq - 1
        return True

    def _forget_silent(self, now: float) -> None:
        for name, (_, t) in list(self.readings.items()):
            if now - t > self.forget_after:
                del self.readings[name]
                self.ctx.bus.forget(self.name, f"t_{name}")
                self.forgotten += 1
                self.ctx.log.info("sensor_forgotten", port=self.port, sensor=name,
                                  silent_s=round(now - t))

    def _restarted(self) -> None:
        self.rejected["arduino_restarted"] += 1
        self.ctx.log.warning("arduino_restarted", port=self.port)

    def _read(self) -> bytes:
        """What has arrived (at least a byte; nothing after the port's timeout), in a
        read or two: the first byte of a line, then the rest that came with it. Not
        readline: pyserial's reads byte by byte, a select and a read per byte."""
        try:
            data = self.ser.read(max(1, self.ser.in_waiting))
            return data + self.ser.read(self.ser.in_waiting) if data else data
        except (serial.SerialException, OSError) as e:
            # a pty whose other end closed, or a USB adapter pulled, reads as EIO
            raise ConnectionError(f"{self.port} went away: {e} (USB cable pulled?)") from None

    async def run(self) -> None:
        last_valid = time.monotonic()
        while True:
            # a read timeout can cut a line in two: the head waits in _partial for its end
            lines, self._partial = split_lines(self._partial + await asyncio.to_thread(self._read))
            now = time.monotonic()
            for raw in lines:
                if self.handle_line(raw, time.time()):
                    last_valid = now
            if now - last_valid > self.stale_after:
                raise TimeoutError(f"no valid reading from {self.port} for {self.stale_after:g} s "
                                   "(Arduino hung or sensors disconnected?)")

    def quantities(self) -> frozenset[str] | None:
        # without a sensors list, a probe plugged in later is published under its own name
        return None if self.expected is None else frozenset(f"t_{n}" for n in self.expected)

    def status(self) -> dict:
        now = time.time()
        return {"accepted": self.accepted, "rejected": dict(self.rejected), "lines": self.lines,
                "checksums": dict(self.checksums), "forgotten": self.forgotten,
                "last_line_error": self.last_line_error, "port": self.port,
                "sensors": {n: {"celsius": v, "age_s": round(now - t, 3),
                                "stale": self.ser is None or now - t > self.stale_after}
                            for n, (v, t) in sorted(self.readings.items())}}


@hookimpl
def lathed_driver_types():
    return {"ds18b20_serial": DS18B20Serial}
