"""The simulated control's PMC watchdog on the heartbeat register: an override held by a
client whose count stopped (the daemon died, the link is down) goes back to 100 %."""
from __future__ import annotations

import asyncio
import time

from pymodbus.client import AsyncModbusTcpClient

from lathed.sim.__main__ import Simulator, parse_args
from lathed.sim.modbus_peer import decode, encode
from lathed.sim.registers import HEARTBEAT_TIMEOUT_S, LATHE_MAP
from tests.conftest import free_port

OVR, BEAT = LATHE_MAP["spindle_override_pct"][0], LATHE_MAP["heartbeat"][0]


def test_a_held_override_goes_back_to_100_when_the_heartbeat_stops(tmp_path):
    async def go():
        sim = Simulator(parse_args(["--modbus-port", str(free_port()), "--vibration-port", str(free_port()),
                                    "--serial-link", str(tmp_path / "tty")]))
        task = asyncio.create_task(sim.run())
        client = AsyncModbusTcpClient("127.0.0.1", port=sim.args.modbus_port, timeout=1)
        try:
            while not sim.modbus.up:
                await asyncio.sleep(0.02)
            assert await client.connect()

            async def override():
                rr = await client.read_holding_registers(OVR, count=2, device_id=1)
                return decode(rr.registers, "float32")

            async def beat(n):
                assert not (await client.write_registers(BEAT, encode(n, "uint16"), device_id=1)).isError()

            # no heartbeat yet: the watchdog is not armed, a held override stays
            assert not (await client.write_registers(OVR, encode(110.0, "float32"), device_id=1)).isError()
            n, end = 1, time.monotonic() + HEARTBEAT_TIMEOUT_S + 0.5
            while time.monotonic() < end:
                assert await override() == 110.0
                await asyncio.sleep(0.1)
            # beating: held past the timeout. The simulator runs in this loop: a stall of it longer
            # than the timeout (a loaded machine) stops the count as a dead client's would, and a
            # reset then is right: the override is written again and the beating goes on
            end = time.monotonic() + HEARTBEAT_TIMEOUT_S + 0.5
            changed = time.monotonic()
            while time.monotonic() < end:
                before = changed
                await beat(n)
                changed = time.monotonic()      # the control has the new count: its last change
                n += 1
                if await override() != 110.0:
                    assert changed - before > HEARTBEAT_TIMEOUT_S, "reset while the count was changing"
                    assert not (await client.write_registers(OVR, encode(110.0, "float32"), device_id=1)).isError()
                    end = time.monotonic() + HEARTBEAT_TIMEOUT_S + 0.5
                await asyncio.sleep(0.1)
            # a count that repeats is a stopped count, from its last change (not from the end of
            # the loop: a loaded loop's 0.1 s sleep took 0.9 s, and the reset looked early)
            n -= 1
            stopped, resets = changed, len(sim.watchdog_resets)
            while await override() != 100.0:
                await beat(n)
                assert time.monotonic() - stopped < HEARTBEAT_TIMEOUT_S + 10.0, "override still held"
                await asyncio.sleep(0.05)
            assert time.monotonic() - stopped >= HEARTBEAT_TIMEOUT_S - 0.1
            (reset,) = sim.watchdog_resets[resets:]
            assert reset["override_pct"] == 110.0 and reset["silent_s"] > HEARTBEAT_TIMEOUT_S
        finally:
            client.close()
            sim._stop.set()
            await asyncio.wait_for(task, 10)
    asyncio.run(asyncio.wait_for(go(), 60))


def test_the_watchdog_waits_for_a_threads_end(tmp_path):
    # a thread's passes run at one speed: the PMC takes the override back after the thread
    from lathed.sim.program import parse_cut
    sim = Simulator(parse_args(["--modbus-port", str(free_port()), "--vibration-port", str(free_port()),
                                "--serial-link", str(tmp_path / "tty"), "--cut", "2000,0.3,1.5,20,thread=1.5",
                                "--cut", "2000,1.0,0.3,20"]))
    assert sim.lathe.part == parse_cut("2000,0.3,1.5,20,thread=1.5")
    sim.lathe.override_pct, sim._beat_wall = 110.0, time.time() - 2 * HEARTBEAT_TIMEOUT_S
    sim._pmc_watchdog()
    assert sim.lathe.override_pct == 110.0 and sim.watchdog_resets == []
    while sim.lathe.part.thread:              # the thread's cycle ends
        sim.lathe.step(4096)
    sim._pmc_watchdog()
    assert sim.lathe.override_pct == 100.0 and len(sim.watchdog_resets) == 1
