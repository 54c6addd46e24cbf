"""modbus_cnc: the register map from the config, per-register poll rates,
TCP and RTU against real pymodbus servers, writes only where declared."""
from __future__ import annotations

import asyncio
import time

import pytest
import structlog

from lathed.bus import Bus
from lathed.command import Command
from lathed.config import ConfigError, Section
from lathed.driver import DriverContext
from lathed.sim.line import MILL_PROGRAM, SimCycleMachine
from lathed.sim.modbus_peer import ModbusPeer
from lathed.sim.registers import CELL_MAP, N_CELL_REGISTERS
from lathed.sim.serial_peer import NullModem
from plugins.modbus_cnc import ModbusCNC, poll_groups
from tests.conftest import free_port

REGS = {"spindle_rpm_cmd": {"address": 0, "type": "float32", "writable": True},
        "spindle_rpm": {"address": 2, "type": "float32", "unit": "r/min"},
        "x_mm": {"address": 4, "type": "float32"},
        "part_count": {"address": 10, "type": "int32", "poll": "500ms"},
        "program_number": {"address": 15, "type": "uint16", "poll": "500ms"},
        "alarm_code": {"address": 16, "type": "uint16"}}


def driver(data: dict) -> ModbusCNC:
    sec = Section("t.toml", "machine.m", data)
    d = ModbusCNC("m", sec)
    sec.check_unused()
    return d


def tcp(port: int, **kw) -> dict:
    return {"kind": "mill", "host": "127.0.0.1", "port": port, "poll": "50ms", "timeout": "300ms",
            "registers": REGS, **kw}


@pytest.mark.parametrize("data, problem", [
    ({"registers": {"a": {"address": 0, "type": "float32"}, "b": {"address": 1, "type": "uint16"}}},
     "register 1 overlaps 'a'"),
    ({"registers": {"a": {"address": 0, "type": "float64"}}}, "allowed: int16, uint16"),
    ({"registers": {"a": {"address": 0, "type": "int16", "scale": 0}}}, "must not be 0"),
    ({"registers": {"a": {"address": 0, "type": "int16", "poll": "2s"}}, "stale_after": "1s"},
     "longer than the slowest poll"),
    ({"transport": "rtu", "registers": REGS}, "[machine.m] device: missing required key"),
    ({"transport": "rtu", "device": "/dev/ttyUSB0", "host": "x", "registers": REGS}, "host: unknown key"),
])
def test_config_errors_name_the_key(data, problem):
    data = {"host": "127.0.0.1", **data} if data.get("transport") != "rtu" else data
    with pytest.raises(ConfigError) as e:
        driver(data)
    assert problem in str(e.value) and str(e.value).startswith("t.toml: [machine.m")


def test_registers_grouped_by_poll_period():
    d = driver(tcp(502))
    groups = poll_groups(d.registers)
    assert sorted(groups) == [0.05, 0.5]
    # one request per contiguous run: 0..5 and 16 are fast, 10..11 and 15 slow
    assert [(s, n) for s, n, _ in groups[0.05]] == [(0, 6), (16, 1)]
    assert [(s, n) for s, n, _ in groups[0.5]] == [(10, 6)]
    assert d.actions == ("spindle_rpm",)


async def _run_against(peer: ModbusPeer, machine: SimCycleMachine, d: ModbusCNC, check) -> None:
    events = []
    d.ctx = DriverContext(Bus(), structlog.get_logger(), lambda k, p=None: events.append((k, p)))
    await peer.start()
    stop = asyncio.Event()

    async def physics():
        while not stop.is_set():
            machine.step(0.05)
            peer.block.update(machine.registers())
            await asyncio.sleep(0.02)
    ph = asyncio.create_task(physics())
    try:
        await d.connect()
        task = asyncio.create_task(d.run())
        try:
            await check(d, events)
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
            await d.close()
    finally:
        stop.set()
        await ph
        await peer.stop()


async def until(pred, timeout=5.0, what="condition"):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return
        await asyncio.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what}")


def test_tcp_fills_the_model_and_writes_only_declared_registers():
    port = free_port()
    mill = SimCycleMachine(MILL_PROGRAM)
    peer = ModbusPeer("127.0.0.1", port, CELL_MAP, N_CELL_REGISTERS, mill.write)
    d = driver(tcp(port))

    async def check(d, events):
        await until(lambda: d.model.live("spindle_rpm") is not None and d.polls > 10, what="polls")
        snap = d.model.snapshot()
        assert snap["program"]["value"] == 2100 and snap["axes"]["x"]["stale"] is False
        # the slow group is read about ten times less often than the fast one
        await until(lambda: d.reads[0.5] >= 3, what="slow group reads")
        ratio = d.reads[0.05] / d.reads[0.5]
        assert 5 <= ratio <= 14, d.reads
        await d.execute(Command(machine="m", action="spindle_rpm", value=4200.0, reason="test", source="t"))
        await until(lambda: mill.rpm_override == 4200.0, what="write reached the controller")
        with pytest.raises(PermissionError, match="no writable register"):
            await d.execute(Command(machine="m", action="offset_x_um", value=5.0, reason="test", source="t"))
        mill.alarm_code = 77
        await until(lambda: d.model.state() == "alarm", what="alarm state")
        assert ("alarm_raised", {"kind": "mill", "alarm": "77"}) in events
    asyncio.run(asyncio.wait_for(_run_against(peer, mill, d, check), 30))


def test_rtu_over_a_null_modem(tmp_path):
    grinder = SimCycleMachine(MILL_PROGRAM)
    peer = ModbusPeer("127.0.0.1", 0, CELL_MAP, N_CELL_REGISTERS, grinder.write,
                      null_modem=NullModem(tmp_path / "ttyRS485"))
    d = driver({"kind": "grinder", "transport": "rtu", "device": str(tmp_path / "ttyRS485"), "baudrate": 115200,
                "poll": "50ms", "timeout": "300ms", "registers": REGS})

    async def check(d, events):
        await until(lambda: d.polls > 5 and d.model.live("program") == 2100, what="RTU polls")
        assert d.status()["link"] == {"transport": "rtu", "where": str(tmp_path / "ttyRS485"), "errors": {}}
    asyncio.run(asyncio.wait_for(_run_against(peer, grinder, d, check), 30))


def test_no_server_is_a_clear_connection_error():
    d = driver(tcp(free_port()))
    d.ctx = DriverContext(Bus(), structlog.get_logger(), lambda k, p=None: None)
    with pytest.raises(ConnectionError, match=r"no Modbus TCP link to 127.0.0.1:\d+ \(machine off or network down\?\)"):
        asyncio.run(d.connect())
