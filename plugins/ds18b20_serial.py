"""DS18B20 temperatures from an Arduino over a serial line (format: lathed.wire).

    [sensor.temps]
    plugin = "ds18b20_serial"
    port = "/dev/ttyACM0"
    baudrate = 115200
    stale_after = "20s"     # no valid reading for this long: the link is re-opened

Each sensor name in the line becomes a quantity ``t_<name>`` in °C. The
DS18B20's power-on value 85.0 and its disconnect value -127.0 are rejected
and counted, as are readings outside the part's -55..125 °C range,
malformed lines, bad checksums and gaps in the sequence number.
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
        self._last_seq: int | None = None

    async def connect(self) -> None:
        def opener() -> serial.Serial:
            s = serial.serial_for_url(self.port, baudrate=self.baudrate, timeout=0.25)
            s.reset_input_buffer()   # what queued while nobody listened is old news
            return s
        try:
            self.ser = await asyncio.to_thread(opener)
        except serial.SerialException as e:
            raise ConnectionError(f"cannot open {self.port}: {e} (Arduino unplugged?)") from None

    async def close(self) -> None:
        if self.ser is not None:
            s, self.ser = self.ser, None
            await asyncio.to_thread(s.close)

    def handle_line(self, raw: bytes, now: float) -> None:
        self.lines += 1
        try:
            seq, _uptime, readings = parse_temperature_line(raw)
        except LineError:
            self.rejected["malformed"] += 1
            return
        if self._last_seq is not None and seq != self._last_seq + 1:
            if seq > self._last_seq:
                self.rejected["lost_lines"] += seq - self._last_seq - 1
            else:
                self.rejected["arduino_restarted"] += 1
        self._last_seq = seq
        fresh = False
        for name, celsius in readings.items():
            if celsius == POWER_ON_C:
                self.rejected["power_on_85"] += 1
            elif celsius == DISCONNECTED_C:
                self.rejected["disconnected_-127"] += 1
            elif not -55.0 <= celsius <= 125.0:
                self.rejected["out_of_range"] += 1
            else:
                self.accepted += 1
                fresh = True
                self.ctx.bus.publish(Sample(self.name, f"t_{name}", celsius, "°C", now))
        if fresh:
            self.mark_data()

    async def run(self) -> None:
        last_valid = time.monotonic()
        while True:
            raw = await asyncio.to_thread(self.ser.readline)
            now = time.monotonic()
            if raw:
                before = self.accepted
                self.handle_line(raw, time.time())
                if self.accepted > before:
                    last_valid = now
            if now - last_valid > self.stale_after:
                raise TimeoutError(f"no valid reading from {self.port} for {self.stale_after:g} s "
                                   "(Arduino hung or sensors disconnected?)")

    def status(self) -> dict:
        return {"accepted": self.accepted, "rejected": dict(self.rejected), "port": self.port}


@hookimpl
def lathed_driver_types():
    return {"ds18b20_serial": DS18B20Serial}
