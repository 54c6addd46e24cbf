"""ds18b20_serial: what the Arduino line carries, what is rejected and why,
and a real pty that is closed and reopened."""
from __future__ import annotations

import asyncio
import os
import time

import structlog

from lathed.bus import Bus
from lathed.config import Section
from lathed.driver import DriverContext
from lathed.sim.serial_peer import SerialPeer
from lathed.supervisor import Runner
from lathed.wire import format_temperature_line
from plugins.ds18b20_serial import DS18B20Serial


def sensor(port="/dev/null", stale_after="1s") -> DS18B20Serial:
    d = DS18B20Serial("temps", Section("t.toml", "sensor.temps", {"port": port, "stale_after": stale_after}))
    d.ctx = DriverContext(Bus(), structlog.get_logger(), lambda k, p=None: None)
    return d


def line(seq, uptime, **readings) -> bytes:
    return format_temperature_line(seq, uptime, readings)


def test_readings_rejected_by_reason():
    d = sensor()
    assert d.handle_line(line(0, 100, front=85.0, rear=-127.0, motor=130.0, room=20.5), 1.0) == 1
    assert dict(d.rejected) == {"power_on_85": 1, "disconnected_-127": 1, "out_of_range": 1}
    assert d.ctx.bus.latest[("temps", "t_room")].value == 20.5
    bad = line(1, 200, room=20.0).replace(b"20.0000", b"21.0000")      # checksum no longer matches
    assert d.handle_line(bad, 2.0) == 0 and "checksum mismatch" in d.last_line_error
    assert d.handle_line(b"T,2,300,room=20.0\r\n", 2.0) == 0 and "no '*' checksum" in d.last_line_error
    assert d.handle_line(b"\x00\xff garbage", 2.0) == 0         # no line end: cut off or overlong
    assert d.rejected["malformed"] == 3


def test_sequence_duplicates_gaps_and_restarts():
    d = sensor()
    d.handle_line(line(5, 1000, room=20.0), 1.0)
    assert d.handle_line(line(5, 1000, room=20.0), 1.1) == 0          # the same line again
    assert d.handle_line(line(4, 1100, room=20.0), 1.2) == 0          # seq back, clock not: not new
    assert d.rejected["duplicate"] == 2
    d.handle_line(line(9, 1600, room=20.0), 2.0)
    assert d.rejected["lost_lines"] == 3
    assert d.handle_line(line(0, 50, room=20.0), 3.0) == 1            # rebooted: uptime went back
    assert d.rejected["arduino_restarted"] == 1
    assert d.accepted == 3


def test_a_sensor_that_stops_reporting_goes_stale():
    d = sensor(stale_after="1s")
    now = time.time()
    d.ser = object()     # as if the port were open
    d.handle_line(line(0, 0, front=30.0, room=20.0), now - 5)
    d.handle_line(line(1, 6000, front=-127.0, room=20.1), now)       # front's wire came off
    st = d.status()["sensors"]
    assert st["front"]["stale"] and st["front"]["celsius"] == 30.0
    assert not st["room"]["stale"]


def test_pty_closed_and_reopened_with_garbage(tmp_path):
    link = tmp_path / "ttyACM0"

    async def main():
        peer = SerialPeer(link)
        peer.open()
        d = sensor(str(link), stale_after="1s")
        r = Runner("sensor", "temps", d, 0.1, 0.5, lambda *a: None)
        r.task = asyncio.create_task(r.loop())
        stop = asyncio.Event()

        async def arduino():
            while not stop.is_set():
                peer.send(int(time.monotonic() * 1000), {"room": 20.0})
                await asyncio.sleep(0.05)
        a = asyncio.create_task(arduino())

        async def until(pred, timeout, what):
            end = time.monotonic() + timeout
            while not pred():
                assert time.monotonic() < end, f"timed out waiting for {what}: {r.describe()}"
                await asyncio.sleep(0.02)
        try:
            await until(lambda: r.state == "connected" and d.accepted > 3, 5, "readings")
            os.write(peer.master, b"\x02\x7f#@!noise" * 30 + b"\n")
            n = d.accepted
            await until(lambda: d.accepted > n + 3 and d.rejected["malformed"] >= 1, 3, "readings after noise")
            assert r.failures == 0
            peer.close()                       # the cable pulled
            link.unlink()
            await until(lambda: r.state != "connected", 3, "the loss to be noticed")
            await asyncio.sleep(1.0)           # the outage itself, not a synchronisation
            peer.open()
            back = time.monotonic()
            n = d.accepted
            await until(lambda: r.state == "connected" and d.accepted > n, 5, "reconnected within 5 s")
            assert time.monotonic() - back < 5
            assert d.rejected["lost_lines"] > 0          # what the Arduino sent meanwhile is counted
            assert d.rejected.get("duplicate", 0) == 0
        finally:
            stop.set()
            await a
            r.task.cancel()
            await asyncio.gather(r.task, return_exceptions=True)
            peer.close()
    asyncio.run(asyncio.wait_for(main(), 30))
