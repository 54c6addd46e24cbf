"""DS18B20 temperatures from an Arduino over a serial line (format: lathed.wire).

    [sensor.temps]
    plugin = "ds18b20_serial"
    port = "/dev/ttyACM0"
    baudrate = 115200
    stale_after = "20s"     # a sensor with no valid reading for this long is stale;
                            # no valid reading from any: the port is re-opened

The Arduino sends one line per read cycle of all its sensors, every 6 s:

    T,<seq>,<uptime_ms>,<name>=<celsius>[,<name>=<celsius>...]*<XX>\\r\\n

``seq`` counts read cycles since the Arduino booted, ``XX`` is the XOR of
every byte from ``T`` up to ``*`` in hex. Each sensor name becomes a
quantity ``t_<name>`` in °C.

What is rejected, and counted by reason in ``lathectl status``:
``power_on_85`` (the DS18B20's 85.0 before its first conversion),
``disconnected_-127`` (its reading when the wire is off), ``out_of_range``
(outside the part's -55..125 °C), ``malformed`` (no checksum, bad checksum,
bad fields, over-long garbage), ``duplicate`` (a line whose seq was already
seen, e.g. replayed after a reconnect). ``lost_lines`` counts the gaps in
seq (lines sent while nobody listened), ``arduino_restarted`` the times its
uptime went back. A sensor that stops giving valid readings goes stale
(its last value kept, marked stale); when none gives one for
``stale_after`` or the port disappears (USB cable pulled), the port is
closed and re-opened with backoff until it is back.
"""
from __future__ import annotations

import asyncio
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


class DS18B20Serial(Driver):
    role = "sensor"
    kind = "temperature"

    def __init__(self, name: str, section: Section):
        super().__init__(name, section)
        self.port = section.getstr("port")
        self.baudrate = section.getint("baudrate", 115200, minval=300, maxval=4_000_000)
        self.stale_after = section.getduration("stale_after", 20.0, minval=0.1, maxval=3600)
        self.ser: serial.Serial | None = None
        self.rejected: Counter = Counter()
        self.accepted = 0
        self.lines = 0
        self.last_line_error: str | None = None
        self.readings: dict[str, tuple[float, float]] = {}   # sensor -> (celsius, t)
        self._last_seq: int | None = None
        self._last_uptime: int | None = None
        self._partial = b""

    async def connect(self) -> None:
        def opener() -> serial.Serial:
            s = serial.serial_for_url(self.port, baudrate=self.baudrate, timeout=0.25)
            s.reset_input_buffer()   # what queued while nobody listened is old news
            return s
        try:
            self.ser = await asyncio.to_thread(opener)
            self._partial = b""
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
            seq, uptime, readings = parse_temperature_line(raw)
        except LineError as e:
            self.rejected["malformed"] += 1
            self.last_line_error = str(e)
            return 0
        if self._last_seq is not None:
            if self._last_uptime is not None and uptime < self._last_uptime:
                self._restarted()
            elif seq <= self._last_seq:
                self.rejected["duplicate"] += 1
                return 0
            elif seq > self._last_seq + 1:
                self.rejected["lost_lines"] += seq - self._last_seq - 1
        self._last_seq, self._last_uptime = seq, uptime
        good = 0
        for name, celsius in readings.items():
            if celsius == POWER_ON_C:
                self.rejected["power_on_85"] += 1
            elif celsius == DISCONNECTED_C:
                self.rejected["disconnected_-127"] += 1
            elif not -55.0 <= celsius <= 125.0:
                self.rejected["out_of_range"] += 1
            elif self.ctx.bus.publish(Sample(self.name, f"t_{name}", celsius, "°C", now)):
                good += 1
                self.readings[name] = (celsius, now)
        self.accepted += good
        if good:
            self.mark_data()
        return good

    def _restarted(self) -> None:
        self.rejected["arduino_restarted"] += 1
        self.ctx.log.warning("arduino_restarted", port=self.port)

    def _readline(self) -> bytes:
        try:
            return self.ser.readline(MAX_LINE - len(self._partial))
        except (serial.SerialException, OSError) as e:
            # a pty whose other end closed, or a USB adapter pulled, reads as EIO
            raise ConnectionError(f"{self.port} went away: {e} (USB cable pulled?)") from None

    async def run(self) -> None:
        last_valid = time.monotonic()
        while True:
            self._partial += await asyncio.to_thread(self._readline)
            now = time.monotonic()
            # a read timeout can cut a line in two: keep the head until its end comes
            if self._partial.endswith(b"\n") or len(self._partial) >= MAX_LINE:
                raw, self._partial = self._partial, b""
                if self.handle_line(raw, time.time()):
                    last_valid = now
            if now - last_valid > self.stale_after:
                raise TimeoutError(f"no valid reading from {self.port} for {self.stale_after:g} s "
                                   "(Arduino hung or sensors disconnected?)")

    def status(self) -> dict:
        now = time.time()
        return {"accepted": self.accepted, "rejected": dict(self.rejected), "lines": self.lines,
                "last_line_error": self.last_line_error, "port": self.port,
                "sensors": {n: {"celsius": v, "age_s": round(now - t, 3),
                                "stale": self.ser is None or now - t > self.stale_after}
                            for n, (v, t) in sorted(self.readings.items())}}


@hookimpl
def lathed_driver_types():
    return {"ds18b20_serial": DS18B20Serial}
