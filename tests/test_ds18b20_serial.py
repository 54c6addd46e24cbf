"""ds18b20_serial: what the Arduino line carries, what is rejected and why,
and a real pty that is closed and reopened."""
from __future__ import annotations

import asyncio
import io
import os
import random
import time

import structlog

from lathed.bus import Bus
from lathed.config import Section
from lathed.driver import DriverContext
from lathed.sim.serial_peer import SerialPeer
from lathed.supervisor import Runner
from lathed.wire import crc16, format_temperature_line, xor_checksum
from lathed_plugins.ds18b20_serial import MAX_LINE, DS18B20Serial, split_lines


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
    assert d.rejected["duplicate"] == 1
    d.handle_line(line(9, 1600, room=20.0), 2.0)
    assert d.rejected["lost_lines"] == 3
    assert d.handle_line(line(0, 50, room=20.0), 3.0) == 1            # rebooted: uptime went back
    assert d.rejected["arduino_restarted"] == 1
    assert d.accepted == 3


def test_one_line_with_a_huge_seq_does_not_lock_out_the_temperatures():
    """issue 18 D4: seq 10**12 with uptime 0 made every later line a duplicate, until restart."""
    d = sensor()
    d.handle_line(line(5, 30_000, room=20.0), 1.0)
    assert d.handle_line(line(10**12, 0, room=20.0), 2.0) == 1         # uptime back: taken as a reboot
    assert d.handle_line(line(6, 36_000, room=20.1), 7.0) == 1        # seq back, uptime on: resync
    assert d.handle_line(line(7, 42_000, room=20.2), 13.0) == 1
    assert d.rejected["resync"] == 1 and "duplicate" not in d.rejected
    # a jump no 115200 baud line could carry in 6 s of uptime: resync, not a billion lost lines
    assert d.handle_line(line(10**9, 48_000, room=20.3), 19.0) == 1
    assert d.handle_line(line(9, 54_000, room=20.3), 25.0) == 1
    assert d.rejected["resync"] == 3 and d.rejected.get("lost_lines", 0) == 0


def test_a_board_swapped_for_one_with_a_lower_seq_is_followed():
    d = sensor()
    d.handle_line(line(500, 3_000_000, room=20.0), 1.0)
    assert d.handle_line(line(3, 3_006_000, room=20.1), 7.0) == 1
    assert d.handle_line(line(4, 3_012_000, room=20.1), 13.0) == 1
    assert d.rejected["resync"] == 1


def test_reconnect_starts_the_sequence_afresh(tmp_path):
    link = tmp_path / "tty"
    peer = SerialPeer(link)
    peer.open()
    try:
        d = sensor(str(link))
        d.handle_line(line(0, 1000, room=20.0), 1.0)
        d.handle_line(line(10**12, 5000, room=20.0), 1.0)
        asyncio.run(d.connect())
        assert d.handle_line(line(10**12, 5000, room=20.0), 2.0) == 1     # not a duplicate after a reconnect
        assert d.handle_line(line(2, 6000, room=20.0), 3.0) == 1
        assert d.rejected == {"resync": 2}     # before the reconnect, and the one after the stale seq
        asyncio.run(d.close())
    finally:
        peer.close()


def test_crc16_lines_and_legacy_xor():
    d = sensor()
    assert line(0, 0, room=20.0).endswith(b"*%04X\r\n" % crc16(b"T,0,0,room=20.0000"))
    # two flips in one bit column pass the XOR; the CRC catches them
    good = format_temperature_line(1, 6000, {"room": 20.0}, checksum="xor8")
    flipped = good.replace(b"room=20", b"room=31")   # '2'^'3' == '0'^'1': the XOR is unchanged
    assert xor_checksum(good[:good.index(b"*")]) == xor_checksum(flipped[:flipped.index(b"*")])
    assert d.handle_line(good, 1.0) == 1 and d.checksums == {"xor8": 1}
    crc_flipped = line(2, 12000, room=20.0).replace(b"room=20", b"room=31")
    assert d.handle_line(crc_flipped, 2.0) == 0 and "crc16 checksum mismatch" in d.last_line_error
    strict = DS18B20Serial("temps", Section("t.toml", "sensor.temps", {"port": "/dev/null", "checksum": "crc16"}))
    strict.ctx = d.ctx
    assert strict.handle_line(good, 3.0) == 0 and strict.rejected == {"weak_checksum": 1}


def test_sensor_names_checked_capped_and_forgotten():
    d = sensor()
    d.max_sensors = 3
    junk = {"room": 20.0, "a b": 20.0, "x" * 40: 20.0, "s1": 20.0, "s2": 20.0, "s3": 20.0}
    assert d.handle_line(line(0, 0, **junk), 1.0) == 3
    assert d.rejected == {"bad_name": 2, "too_many_sensors": 1}
    assert sorted(d.status()["sensors"]) == ["room", "s1", "s2"]
    # a name silent for forget_after is forgotten, from status and the bus, freeing its place
    d.handle_line(line(1, 6000, room=20.0, s1=20.0), 1.0 + d.forget_after / 2)
    d.handle_line(line(2, 12000, room=20.0, s3=20.0), 2.0 + d.forget_after)
    assert sorted(d.status()["sensors"]) == ["room", "s1", "s3"] and d.forgotten == 1
    assert ("temps", "t_s2") not in d.ctx.bus.latest


def test_expected_sensors_listed():
    d = DS18B20Serial("temps", Section("t.toml", "sensor.temps", {"port": "/dev/null",
                                                                  "sensors": ["room", "motor"]}))
    d.ctx = DriverContext(Bus(), structlog.get_logger(), lambda k, p=None: None)
    assert d.handle_line(line(0, 0, room=20.0, motor=30.0, junk=1.0), 1.0) == 2
    assert d.rejected == {"unknown_sensor": 1}


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


def test_lines_split_from_chunks_as_readline_cut_them():
    # the port is read in chunks of whatever has arrived, not byte by byte (pyserial's readline:
    # a select and a read per byte); the lines must come out as readline(MAX_LINE - partial) gave them
    rng = random.Random(5)
    stream = b"".join(rng.choice([line(i, 1000 * i, room=20.5), b"\x02garbage" * rng.randint(1, 80) + b"\n",
                                  b"x" * rng.choice([MAX_LINE - 1, MAX_LINE, MAX_LINE + 1, 3 * MAX_LINE]) + b"\n",
                                  b"\n", b"no end"]) for i in range(300))
    want, partial, f = [], b"", io.BytesIO(stream)
    while chunk := f.readline(MAX_LINE - len(partial)):
        partial += chunk
        if partial.endswith(b"\n") or len(partial) >= MAX_LINE:
            want.append(partial)
            partial = b""
    got, rest, i = [], b"", 0
    while i < len(stream):
        n = rng.choice([1, 2, 7, 100, 511, 512, 513, 4096])
        lines, rest = split_lines(rest + stream[i:i + n])
        got += lines
        i += n
    assert got == want and rest == partial
    assert any(len(x) == MAX_LINE and not x.endswith(b"\n") for x in got)     # over-long lines were cut


def test_a_line_is_read_in_one_worker_call_in_a_read_or_two():
    class Port:
        """A line arrives while the driver waits: its first byte wakes the read, the rest is waiting."""
        def __init__(self, line):
            self.line, self.waiting, self.reads = line, b"", 0

        @property
        def in_waiting(self):
            return len(self.waiting)

        def read(self, n):
            self.reads += 1
            if self.line:
                self.waiting, self.line = self.line, b""
            out, self.waiting = self.waiting[:n], self.waiting[n:]
            return out
    d = sensor()
    d.ser = Port(line(1, 1000, room=20.0) + line(2, 2000, room=20.1))
    assert split_lines(d._read()) == ([line(1, 1000, room=20.0), line(2, 2000, room=20.1)], b"")
    assert d.ser.reads == 2
    assert d._read() == b"" and d.ser.reads == 3          # the port's timeout: nothing, one read
