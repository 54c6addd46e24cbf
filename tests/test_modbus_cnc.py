"""modbus_cnc: the register map from the config, per-register poll rates,
TCP and RTU against real pymodbus servers, writes only where declared."""
from __future__ import annotations

import asyncio
import dataclasses
import time
from collections import Counter

import pytest
import structlog

from lathed.bus import Bus, Sample
from lathed.command import Command
from lathed.config import ConfigError, Section
from lathed.driver import DriverContext
from lathed.sim.line import MILL_PROGRAM, SimCycleMachine
from lathed.sim.modbus_peer import ModbusPeer as SimPeer
from lathed.modbus_identity import decode_ascii
from lathed.sim.registers import CELL_IDENTITY, CELL_MAP, N_CELL_REGISTERS, SERIALS
from lathed.sim.serial_peer import NullModem
from lathed.supervisor import cancel_and_wait
from lathed_plugins.modbus_cnc import READ_ON_MIN_S, ModbusCNC, poll_groups
from tests.conftest import free_port

REGS = {"spindle_rpm_cmd": {"address": 0, "type": "float32", "writable": True},
        "spindle_rpm": {"address": 2, "type": "float32", "unit": "r/min"},
        "x_mm": {"address": 4, "type": "float32"},
        "part_count": {"address": 10, "type": "int32", "poll": "500ms"},
        "program_number": {"address": 15, "type": "uint16", "poll": "500ms"},
        "alarm_code": {"address": 16, "type": "uint16"}}


# every control lathed writes to says what it is (identity registers), and its driver names it
SERIAL, ID_AT = "TEST-CONTROL-1", 40
IDENT = {"identification": {"serial_number": SERIAL}, "identity": {"serial_number": {"address": ID_AT, "words": 8}}}


def ModbusPeer(host, port, regmap, size, on_write, serial=SERIAL, **kw):   # noqa: N802 (the peer it stands for)
    """A simulated control that serves its serial number at ID_AT."""
    return SimPeer(host, port, regmap, max(size, ID_AT + 8), on_write,
                   identity={"serial_number": ((ID_AT, 8), serial)}, **kw)


def driver(data: dict) -> ModbusCNC:
    data = {**IDENT, **data}
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
    # both passed: a key that is not a table was ignored, and a mistyped writable register
    # left the action without one
    ({"registers": {**REGS, "foo": 3}},
     "[machine.m.registers] foo: expected a table { address = ..., type = ... }, got 3"),
    ({"registers": {"spindle_rmp_cmd": {"address": 0, "type": "float32", "writable": True}}},
     "[machine.m.registers.spindle_rmp_cmd] writable: no action writes 'spindle_rmp_cmd'; writable registers: "
     "spindle_rpm_cmd, offset_x_um, spindle_override_pct, heartbeat"),
    # issue 35 case 3: a machine written to must say what it is before any write
    ({"registers": REGS, "identity": {}},
     "[machine.m] identity: m is written to (spindle_rpm): map the control's serial number"),
    ({"registers": REGS, "identity": {"serial": {"address": 40, "words": 8}}},
     "[machine.m.identity] serial: not an identification key; allowed: manufacturer, model, serial_number"),
    ({"registers": REGS, "identity": {"model": {"address": 40, "words": 8}}},
     "[machine.m.identity.model]: the peer's model is read, but [machine.m.identification] gives no model"),
    ({"registers": REGS, "identity": {"serial_number": {"address": 2, "words": 8}}},
     "[machine.m.identity.serial_number] address: overlaps register 'spindle_rpm' of the register map"),
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
            await cancel_and_wait([task])
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
    started = time.monotonic()        # before the connect: every read counted is after it

    async def check(d, events):
        # the model filled: both groups read once. Not "ten polls": on a loaded machine the slow
        # group's first read timed out (its answer came late, pymodbus dropped it) and the program
        # number was still unread after ten fast polls (failed twice on fresh clones)
        await until(lambda: d.model.live("spindle_rpm") is not None and d.model.live("program") is not None
                    and d.polls > 10, what="polls")
        snap = d.model.snapshot()
        assert snap["program"]["value"] == 2100 and snap["axes"]["x"]["stale"] is False
        # the slow group is read no more often than its period allows, and never more often than
        # the fast one (each due at once in a poll: checked fast first). Not a ratio of the two:
        # on a loaded machine a poll outlasting 50 ms reads the fast group once a poll, and the
        # ratio fell below the bound (failed once on a fresh clone)
        await until(lambda: d.reads[0.5] >= 3, what="slow group reads")
        slow, fast, elapsed = d.reads[0.5], d.reads[0.05], time.monotonic() - started
        assert slow <= elapsed / 0.5 + 1 and fast <= elapsed / 0.05 + 1, (d.reads, elapsed)
        assert fast >= slow, d.reads
        await d.execute(Command(machine="m", action="spindle_rpm", value=4200.0, reason="test", source="t"))
        await until(lambda: mill.rpm_override == 4200.0, what="write reached the controller")
        with pytest.raises(PermissionError, match="no writable register"):
            await d.execute(Command(machine="m", action="offset_x_um", value=5.0, reason="test", source="t"))
        mill.alarm_code = 77
        await until(lambda: d.model.state() == "alarm", what="alarm state")
        assert ("alarm_raised", {"kind": "mill", "alarm": "77"}) in events
    asyncio.run(asyncio.wait_for(_run_against(peer, mill, d, check), 30))


def test_a_reading_is_stamped_when_the_controller_answered_not_when_the_poll_was_due():
    """A slow answer to a group's first block (a loaded host, a shared RTU bus): the poll's
    values are stamped between its first request and its last answer, one stamp for the poll
    (a dwell's axes are judged against the feed read with them); they were stamped with the
    time the poll was due, a slow answer's worth early."""
    port = free_port()
    mill = SimCycleMachine(MILL_PROGRAM)
    peer = ModbusPeer("127.0.0.1", port, CELL_MAP, N_CELL_REGISTERS, mill.write)
    d = driver(tcp(port))

    async def check(d, events):
        await until(lambda: d.polls > 3, what="polls")
        read, holding, gate = d.client.read_holding_registers, asyncio.Event(), asyncio.Event()

        async def slow_first_block(start, **kw):
            rr = await read(start, **kw)
            if start == 0 and not gate.is_set():
                holding.set()
                await gate.wait()
            return rr
        d.client.read_holding_registers = slow_first_block
        await holding.wait()
        sub = d.ctx.bus.subscribe("m")
        await asyncio.sleep(0.3)              # the controller's answer is this slow
        answered = time.time()
        gate.set()
        held = {}
        while len(held) < 2:                  # the held poll's samples, first of each
            m = await sub.get()
            if m.quantity in ("spindle_rpm", "alarm_code"):
                held.setdefault(m.quantity, m.t)
        assert held["alarm_code"] == held["spindle_rpm"]            # one poll, one stamp
        assert answered - 0.2 <= held["spindle_rpm"] <= answered   # midway, not when asked
    asyncio.run(asyncio.wait_for(_run_against(peer, mill, d, check), 30))


def test_a_thread_being_cut_interlocks_every_command():
    """The map's threading register (1 from a thread's first pass to its last): every command
    is refused while it is 1, and while it has not been read lately; a map without it has no
    interlock (the README says what a machine must provide)."""
    regs = {**REGS, "threading": {"address": 17, "type": "int16"}}
    d = driver({**tcp(502), "registers": regs})
    d.client = object()                       # connected
    speed = Command(machine="m", action="spindle_rpm", value=1500.0, reason="test", source="t")
    assert "threading signal not read yet" in d.interlock(speed)
    for on in (1, -1, 0.1, 8):                # a PLC's TRUE as -1, a scaled bit, F2's byte with THRD
        d.values["threading"] = (on, time.time())
        assert f"is cutting a thread (threading = {on:g})" in d.interlock(speed)
    assert "is cutting a thread" in d.interlock(dataclasses.replace(speed, value=1000.0))   # a release too
    d.values["threading"] = (0, time.time())
    assert d.interlock(speed) is None
    # two polls and an answer's wait (0.05 s, 0.3 s here): older, a thread may have begun since
    d.values["threading"] = (0, time.time() - 0.45)
    assert "not read within 0.4 s" in d.interlock(speed)
    assert driver(tcp(502)).interlock(speed) is None
    # asked again as the write takes the bus (a poll ahead of it on a shared RS-485 bus read it)
    d.values["threading"] = (1, time.time())
    d.values["spindle_rpm_cmd"] = (1400.0, time.time())
    with pytest.raises(PermissionError, match="is cutting a thread"):
        asyncio.run(d.execute(speed))
    slow = {**REGS, "threading": {"address": 17, "type": "uint16", "poll": "500ms"}}
    with pytest.raises(ConfigError, match=r"threading is polled every 0.5 s: poll it with the fastest group"):
        driver({**tcp(502), "registers": slow})


def test_simulated_controller_answers_as_a_real_one():
    """The simulator's server, seen from a plain Modbus client: it serves the
    machine's values, refuses writes to read-only registers and values the
    machine refuses (without storing them), passes accepted writes on, and
    answers only the holding-register function codes."""
    from pymodbus.client import AsyncModbusTcpClient
    from pymodbus.constants import ExcCodes

    from lathed.sim.modbus_peer import decode, encode

    writes = []

    def on_write(name, value):
        if value > 5000:
            raise ValueError(f"spindle speed {value} r/min beyond the drive's 0..5000")
        writes.append((name, value))

    port = free_port()
    (at, words), = CELL_IDENTITY.values()
    peer = SimPeer("127.0.0.1", port, CELL_MAP, N_CELL_REGISTERS, on_write,
                   identity={"serial_number": ((at, words), SERIALS["mill"])})
    peer.block.update({"spindle_rpm": 1234.0, "program_number": 2100})

    async def main():
        await peer.start()
        client = AsyncModbusTcpClient("127.0.0.1", port=port, timeout=2)
        try:
            assert await client.connect()

            async def read(address, count):
                rr = await client.read_holding_registers(address, count=count, device_id=1)
                assert not rr.isError(), rr
                return rr.registers

            regs = await read(0, N_CELL_REGISTERS)
            assert decode(regs[2:4], "float32") == 1234.0 and regs[15] == 2100
            # its serial number, as a control serves it, and read-only
            assert decode_ascii(regs[at:at + words]) == "SIM-MILL-0001"
            rr = await client.write_registers(at, [0x4142], device_id=1)
            assert rr.isError() and rr.exception_code == ExcCodes.ILLEGAL_ADDRESS
            rr = await client.write_registers(2, encode(9.0, "float32"), device_id=1)
            assert rr.isError() and rr.exception_code == ExcCodes.ILLEGAL_ADDRESS
            rr = await client.write_registers(0, encode(9999.0, "float32"), device_id=1)
            assert rr.isError() and rr.exception_code == ExcCodes.ILLEGAL_VALUE
            assert writes == [] and decode(await read(0, 2), "float32") == 0.0
            rr = await client.write_registers(0, encode(3000.0, "float32"), device_id=1)
            assert not rr.isError(), rr
            assert writes == [("spindle_rpm_cmd", 3000.0)] and decode(await read(0, 2), "float32") == 3000.0
            rr = await client.read_holding_registers(N_CELL_REGISTERS - 2, count=4, device_id=1)
            assert rr.isError() and rr.exception_code == ExcCodes.ILLEGAL_ADDRESS
            rr = await client.read_coils(0, count=8, device_id=1)
            assert rr.isError() and rr.exception_code == ExcCodes.ILLEGAL_FUNCTION
        finally:
            client.close()
            await peer.stop()
    asyncio.run(asyncio.wait_for(main(), 30))


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


def test_machines_on_one_rs485_bus_share_the_port_and_take_turns(tmp_path):
    """Two controllers, units 1 and 2, on one RS-485 cable; the PC has one
    adapter. Both machines are configured on it: one port, one request at a
    time, no answer read by the wrong machine; unit 2 going silent costs
    unit 1 nothing but bus time; a third machine asking other serial settings
    is refused with the reason."""
    from pymodbus import FramerType
    from pymodbus.exceptions import NoSuchIdException
    from pymodbus.server import ModbusSerialServer

    from lathed.sim.modbus_peer import _Registers
    from lathed.supervisor import Runner
    from lathed_plugins import modbus_cnc

    link = tmp_path / "ttyBUS"
    nm = NullModem(link)
    (at, words), = CELL_IDENTITY.values()
    blocks = {u: _Registers(CELL_MAP, N_CELL_REGISTERS, lambda n, v: None,
                            identity={"serial_number": ((at, words), f"GRINDER-{u}")}) for u in (1, 2)}
    blocks[1].update({"spindle_rpm": 1111.0})
    blocks[2].update({"spindle_rpm": 2222.0})

    def machine(name, unit, baudrate=115200):
        sec = Section("t.toml", f"machine.{name}", {"kind": "grinder", "transport": "rtu", "device": str(link),
                                                    "baudrate": baudrate, "unit": unit, "poll": "50ms",
                                                    "timeout": "300ms", "registers": REGS,
                                                    "identification": {"serial_number": f"GRINDER-{unit}"},
                                                    "identity": {"serial_number": {"address": at, "words": words}}})
        d = ModbusCNC(name, sec)
        d.ctx = DriverContext(Bus(), structlog.get_logger(), lambda k, p=None: None)
        return d

    powered = {1: True, 2: True}

    def unit(u):
        # a controller switched off does not answer: the server, told to
        # ignore missing devices, stays silent for a unit that is not there
        async def action(*request):
            if not powered[u]:
                raise NoSuchIdException(f"unit {u} is switched off")
            return await blocks[u].action(*request)
        return dataclasses.replace(blocks[u].device(u), action=action)

    async def main():
        server = ModbusSerialServer([unit(1), unit(2)], framer=FramerType.RTU, port=nm.open(), baudrate=115200,
                                    ignore_missing_devices=True)
        await server.serve_forever(background=True)
        a, b = machine("grinder1", 1), machine("grinder2", 2)
        runners = [Runner("machine", d.name, d, 0.1, 0.5, lambda *x, **k: None) for d in (a, b)]
        for r in runners:
            r.task = asyncio.create_task(r.loop())
        try:
            await until(lambda: a.polls > 20 and b.polls > 20, 10, "both machines polled")
            assert a.link is b.link and a.client is b.client and a.link.users == {"grinder1", "grinder2"}
            # each machine reads its own controller
            assert a.values["spindle_rpm"][0] == 1111.0 and b.values["spindle_rpm"][0] == 2222.0
            assert a.errors == Counter() and b.errors == Counter()
            # unit 2 goes silent (powered off): grinder2 retries, grinder1 keeps its data fresh
            powered[2] = False
            await until(lambda: runners[1].state != "connected", 5, "grinder2 noticing")
            polls = a.polls
            t0 = time.monotonic()
            while time.monotonic() - t0 < 2.0:
                assert time.time() - a.values["spindle_rpm"][1] < 1.0, "grinder1 starved on the bus"
                await asyncio.sleep(0.05)
            assert a.polls - polls >= 10 and a.errors == Counter() and runners[0].state == "connected"
            assert b.errors["timeout"] >= 1
            # back on: grinder2 reconnects on the same open port
            powered[2] = True
            await until(lambda: runners[1].state == "connected" and b.values["spindle_rpm"][0] == 2222.0, 10,
                        "grinder2 back")
            assert a.link is b.link
            # one bus, one speed: a machine asking 9600 baud is refused with the reason
            c = machine("grinder3", 3, baudrate=9600)
            with pytest.raises(ConnectionError, match=r"ttyBUS is open at 115200 baud 8N1 for grinder1, grinder2; "
                                                      r"this machine asks 9600 baud 8N1"):
                await c.connect()
        finally:
            # as the daemon stops them: pymodbus's wait_for (Python 3.11) can swallow a cancellation
            # that lands as a read times out, and one cancel then leaves the runner polling (seen once)
            await cancel_and_wait([r.task for r in runners])
            await server.shutdown()
            nm.close()
        assert str(link) not in modbus_cnc._LINKS       # the last machine closed the port
    asyncio.run(asyncio.wait_for(main(), 60))


def test_read_on_reads_a_register_at_once_when_its_trigger_says_1():
    """read_on: the spindle load at the chip's entry, not a poll later.  The register
    polled every 10 s is read as soon as the trigger sample says 1 (never at 0)."""
    port = free_port()
    mill = SimCycleMachine(MILL_PROGRAM)
    peer = ModbusPeer("127.0.0.1", port, CELL_MAP, N_CELL_REGISTERS, mill.write)
    regs = {**REGS, "x_mm": {"address": 4, "type": "float32", "poll": "10s",
                             "read_on": ["chatter.cutting", "chatter.cut_contact"]}}
    d = driver(tcp(port, registers=regs, stale_after="30s"))
    assert d.listens() == {"chatter": (".registers.x_mm", "read_on")}

    async def check(d, events):
        sub = d.ctx.bus.subscribe("m")
        await until(lambda: d.polls > 3, what="polls")
        first = d.reads_on.copy()
        d.ctx.bus.publish(Sample("chatter", "cutting", 0.0, "", time.time()))
        d.ctx.bus.publish(Sample("chatter", "chatter_index", 1.0, "", time.time()))
        await until(lambda: d.reads[0.05] >= 8, what="more fast polls")
        assert d.reads_on == first == Counter()
        sub._items.clear()
        d.ctx.bus.publish(Sample("chatter", "cut_contact", 1.0, "", time.time()))
        await until(lambda: d.reads_on["chatter.cut_contact"] == 1, what="the triggered read")
        assert d.reads[10.0] == 0      # not the poll: its first is 10 s off
        assert "x_mm" in {s.quantity for s in sub._items if isinstance(s, Sample)}
        assert d.status()["reads_on"] == {"chatter.cut_contact": 1}
        # a flapping trigger: many at once are one read, and the next waits READ_ON_MIN_S
        first_t = d._read_on_t["chatter.cut_contact"]
        for _ in range(10):
            d.ctx.bus.publish(Sample("chatter", "cut_contact", 1.0, "", time.time()))
        await until(lambda: d.reads_on["chatter.cut_contact"] == 2, what="the deferred read")
        assert d._read_on_t["chatter.cut_contact"] - first_t >= READ_ON_MIN_S
        await until(lambda: d.reads[0.05] >= 20, what="more fast polls")
        assert d.reads_on["chatter.cut_contact"] == 2
    asyncio.run(asyncio.wait_for(_run_against(peer, mill, d, check), 30))


def test_read_on_must_name_source_and_quantity():
    regs = {**REGS, "x_mm": {"address": 4, "type": "float32", "read_on": ["cutting"]}}
    with pytest.raises(ConfigError, match=r"read_on: 'cutting' is not source.quantity"):
        driver(tcp(502, registers=regs))


class OverrideControl:
    """A control that takes the spindle speed only as an override of its programmed 1500 r/min
    (50..150 %), as Fanuc's SOV through the PMC: the commanded speed follows it."""
    MAP = {"spindle_rpm_cmd": (0, "float32", False, "r/min"), "spindle_override_pct": (2, "float32", True, "%")}

    def __init__(self):
        self.program, self.override, self.writes = 1500.0, 100.0, []
        self.peer = ModbusPeer("127.0.0.1", free_port(), self.MAP, 4, self.write)
        self.publish()

    def write(self, name, value):
        if not 50 <= value <= 150:
            raise ValueError(f"override {value} beyond 50..150 %")
        self.override = value
        self.writes.append(value)
        self.publish()

    def publish(self):
        self.peer.block.update({"spindle_rpm_cmd": self.program * self.override / 100,
                                "spindle_override_pct": self.override})


def test_a_speed_is_written_as_an_override_rounded_towards_the_present_speed():
    ctl = OverrideControl()
    regs = {"spindle_rpm_cmd": {"address": 0, "type": "float32"},
            "spindle_override_pct": {"address": 2, "type": "float32", "writable": True}}
    d = driver({"kind": "lathe", "host": "127.0.0.1", "port": ctl.peer.port, "poll": "20ms",
                "registers": regs, "override_min_pct": 50.0, "override_max_pct": 150.0})
    assert d.speed_by_override and d.actions == ("spindle_rpm",)

    async def check(d, events):
        async def speed(rpm):
            n = len(ctl.writes)
            out = await d.execute(Command(machine="m", action="spindle_rpm", value=rpm, reason="t", source="t"))
            await until(lambda: len(ctl.writes) > n and d._fresh("spindle_override_pct") == ctl.override
                        and d.current("spindle_rpm") == ctl.program * ctl.override / 100, what="the write read back")
            return out
        await until(lambda: d.current("spindle_rpm") == 1500.0, what="polls")
        assert d.released("spindle_rpm") is None             # at 100 %: nothing to undo
        assert await speed(1650.0) == {"override_pct": 110.0, "rpm_effective": 1650.0}
        # 110.8 % asked, up from 110: the step below, between the present speed and the one asked
        assert (await speed(1662.0))["override_pct"] == 110.0
        assert (await speed(1000.0)) == {"override_pct": 67.0, "rpm_effective": 1005.0}   # 66.7 %: up to 67
        with pytest.raises(ValueError, match=r"2400 r/min is a spindle override of 160 % of the programmed "
                                             r"1500 r/min, beyond the control's 50\.\.150 %"):
            await d.execute(Command(machine="m", action="spindle_rpm", value=2400.0, reason="t", source="t"))
        assert ctl.override == 67.0
        assert d.released("spindle_rpm") == pytest.approx(1500.0)    # the programmed speed: 100 %
        assert (await speed(1500.0))["override_pct"] == 100.0
    asyncio.run(asyncio.wait_for(_run_against(ctl.peer, _NoPhysics(), d, check), 30))


class _NoPhysics:
    def step(self, dt):
        pass

    def registers(self):
        return {}


def test_an_override_needs_the_speed_it_is_a_percentage_of():
    with pytest.raises(ConfigError, match="a writable spindle_override_pct needs spindle_rpm_cmd"):
        driver({"host": "127.0.0.1", "registers": {"spindle_override_pct": {"address": 2, "type": "float32",
                                                                           "writable": True}}})


@pytest.mark.parametrize("value, word", [(7.5, 7), (-7.5, -7), (7.4, 7), (7.6, 7), (109.99999999, 110), (-3.0, -3)])
def test_an_integer_register_is_written_no_further_from_zero_than_the_value(value, word):
    # the guard checked the value: a half step rounded away from zero would pass its limit
    from lathed_plugins.modbus_cnc import Register
    reg = Register("offset_x_um", 10, "int16", "big", 1.0, "µm", True, 0.1)
    assert reg.decode(reg.encode(value)) == word


def test_an_override_needs_the_commanded_speed_not_the_measured_one():
    # the measured speed lags a write and a ramp: an override taken from it, just after a cure,
    # was 117 % for 1600 r/min asked (1755 on the control); and a G96 drift shows only in the
    # commanded speed
    with pytest.raises(ConfigError, match="a writable spindle_override_pct needs spindle_rpm_cmd"):
        driver({"host": "127.0.0.1", "registers": {
            "spindle_rpm": {"address": 0, "type": "float32"},
            "spindle_override_pct": {"address": 2, "type": "float32", "writable": True}}})


def test_an_override_step_finer_than_its_register_is_refused():
    # 103.5 % on the 0.5 % step, written to a whole-percent register as 104: past the speed checked
    regs = {"spindle_rpm_cmd": {"address": 0, "type": "float32"},
            "spindle_override_pct": {"address": 2, "type": "uint16", "writable": True}}
    with pytest.raises(ConfigError, match=r"override_step_pct: 0.5 % is not a whole number of the override "
                                          r"register's 1 % steps"):
        driver({"host": "127.0.0.1", "registers": regs, "override_step_pct": 0.5})
    assert driver({"host": "127.0.0.1", "registers": regs, "override_step_pct": 2.0}).override_step == 2.0


def test_a_release_is_100_percent_when_the_program_moved_on_before_it_was_written():
    """A cut ends, its cure is released as the programmed speed (1500), and before the write the
    control is already on the next pass's S word (2000): that release was written as 1500/2000 =
    75 % before (the other way round, 133 %), an override that held part after part. It is 100 %."""
    ctl = OverrideControl()
    regs = {"spindle_rpm_cmd": {"address": 0, "type": "float32"},
            "spindle_override_pct": {"address": 2, "type": "float32", "writable": True}}
    d = driver({"kind": "lathe", "host": "127.0.0.1", "port": ctl.peer.port, "poll": "20ms",
                "registers": regs, "override_min_pct": 50.0, "override_max_pct": 150.0})

    async def check(d, events):
        await until(lambda: d.current("spindle_rpm") == 1500.0, what="polls")
        await d.execute(Command(machine="m", action="spindle_rpm", value=1650.0, reason="t", source="t"))
        await until(lambda: d.current("spindle_rpm") == 1650.0, what="the override read back")
        back = d.released("spindle_rpm")
        assert back == pytest.approx(1500.0)
        ctl.program = 2000.0
        ctl.publish()
        await until(lambda: d.current("spindle_rpm") == 2200.0, what="the next S word read")
        out = await d.execute(Command(machine="m", action="spindle_rpm", value=back, reason="released", source="t"))
        assert out["override_pct"] == 100.0 and ctl.override == 100.0, out
    asyncio.run(asyncio.wait_for(_run_against(ctl.peer, _NoPhysics(), d, check), 30))


def test_an_override_the_control_took_but_answered_late_is_still_released():
    """The write reached the control, the answer did not (a timeout): the command failed, but
    the override on the control is lathed's, and released."""
    ctl = OverrideControl()
    d = driver({"kind": "lathe", "host": "127.0.0.1", "port": ctl.peer.port, "poll": "20ms",
                "registers": {"spindle_rpm_cmd": {"address": 0, "type": "float32"},
                              "spindle_override_pct": {"address": 2, "type": "float32", "writable": True}}})

    async def check(d, events):
        await until(lambda: d.current("spindle_rpm") == 1500.0, what="polls")
        write = d.client.write_registers

        async def lost_answer(*a, **k):
            await write(*a, **k)
            raise asyncio.TimeoutError
        d.client.write_registers = lost_answer
        with pytest.raises(asyncio.TimeoutError):
            await d.execute(Command(machine="m", action="spindle_rpm", value=1650.0, reason="t", source="t"))
        d.client.write_registers = write
        await until(lambda: d.current("spindle_rpm") == 1650.0, what="the override read back")
        assert d.released("spindle_rpm") == pytest.approx(1500.0)
    asyncio.run(asyncio.wait_for(_run_against(ctl.peer, _NoPhysics(), d, check), 30))


def _supervised(ctl, rpm_max, act, **limits):
    """A supervisor with one machine on ``ctl``: ``act(sup, d)`` runs once it is connected,
    then the supervisor stops. Returns act's result and the records."""
    from lathed.config import Instance
    from lathed.safety import Limits
    from lathed.supervisor import Plan, Supervisor
    from tests.test_plausible import FakeStore
    regs = {"spindle_rpm_cmd": {"address": 0, "type": "float32"},
            "spindle_override_pct": {"address": 2, "type": "float32", "writable": True}}
    data = {"kind": "lathe", "host": "127.0.0.1", "port": ctl.peer.port, "poll": "20ms", "registers": regs}

    async def go():
        d = driver(data)
        inst = Instance("machine", "m", "modbus_cnc", Section("t.toml", "machine.m", data),
                        Section("t.toml", "machine.m", {}))
        store = FakeStore()
        lim = Limits(rpm_min=100.0, rpm_max=rpm_max, **limits)
        sup = Supervisor(None, Plan(drivers={"m": (inst, d)}, limits={"m": lim}),
                         Bus(), store, lambda *a: None)
        await ctl.peer.start()
        sup.start_drivers()
        try:
            await until(lambda: sup.runners["m"].state == "connected" and d.current("spindle_rpm") is not None,
                        what="connected")
            return await act(sup, d), store.records
        finally:
            await sup.stop()
            await ctl.peer.stop()
    return asyncio.run(asyncio.wait_for(go(), 30))


def _speed(rpm, reason="t"):
    return Command(machine="m", action="spindle_rpm", value=rpm, reason=reason, source="suppress")


def test_a_release_the_interlock_refused_is_sent_when_it_clears():
    """An override cured before a thread began, its release refused mid-thread: held back, not
    dropped (it would hold for the parts after), and sent as soon as the thread ends."""
    async def released_after_the_thread(sup, d):
        threading_on = [False]
        d.interlock = lambda cmd: "cutting a thread (threading = 1)" if threading_on[0] else None
        assert (await sup.command(_speed(1650.0)))["sent"]
        threading_on[0] = True
        r = await sup.release("m", "spindle_rpm", "suppress")
        assert not r["sent"] and r["interlock"] and ("m", "spindle_rpm") in sup._owed
        assert ctl.override == 110.0 and sup.held() == ["m spindle_rpm"]
        threading_on[0] = False
        await until(lambda: ctl.override == 100.0 and not sup.held(), what="the release, the thread over")
        return sup.held()
    ctl = OverrideControl()
    held, records = _supervised(ctl, 3000.0, released_after_the_thread)
    assert held == []
    said = [(k, p.get("override_pct")) for k, _, p in records if k.startswith("command_")]
    assert said == [("command_sent", 110.0), ("command_refused", None), ("command_sent", 100.0)], said


def test_an_interlock_that_fails_refuses_the_command():
    """A driver whose interlock raises (a plugin's bug) cannot vouch for its machine's state:
    the command is refused and recorded with the cause, never sent."""
    async def broken_interlock(sup, d):
        def interlock(cmd):
            raise KeyError("threading")
        d.interlock = interlock
        return await sup.command(_speed(1650.0))
    ctl = OverrideControl()
    r, records = _supervised(ctl, 2000.0, broken_interlock)
    assert not r["sent"] and r["reason"].startswith("machine m's interlock could not be read: KeyError: 'threading'")
    assert [k for k, _, _ in records if k.startswith("command_")] == ["command_refused"]
    assert ctl.override == 100.0


def test_a_release_passes_the_guard_as_any_command():
    """The supervisor's release: the programmed speed, through the guard. A programmed speed
    above spindle_rpm_max is refused (suppression then records speed_not_released), within
    it the override goes back to 100 %. Only an override lathed wrote is released: one the
    control or its operator set is not lathed's to undo."""
    async def cured_then_released(sup, d):
        await sup.command(_speed(1350.0))                         # 90 %
        await until(lambda: d.current("spindle_rpm") == 1350.0, what="the override read back")
        return await sup.release("m", "spindle_rpm", "suppress")

    ctl = OverrideControl()
    refused, records = _supervised(ctl, 1400.0, cured_then_released)
    assert refused == {"sent": False, "reason": "spindle speed 1500 r/min outside [100, 1400]"}
    assert ctl.override == 90.0
    assert [k for k, _, _ in records if k.startswith("command")] == ["command_sent", "command_refused",
                                                                     "command_refused"]   # the stop's too
    ctl = OverrideControl()
    sent, records = _supervised(ctl, 2000.0, cured_then_released)
    assert sent == {"sent": True, "reason": None, "override_pct": 100.0, "rpm_effective": 1500.0}
    assert ctl.override == 100.0
    payload = [p for k, _, p in records if k == "command_sent"][-1]
    assert payload["reason"] == "released: back to the programmed speed" and payload["override_pct"] == 100.0

    async def operators(sup, d):
        await until(lambda: d.current("spindle_rpm") == 1350.0, what="polls")
        return await sup.release("m", "spindle_rpm", "suppress")
    ctl = OverrideControl()
    ctl.override = 90.0          # set on the control's panel (or by an earlier run), not by lathed
    ctl.publish()
    released, records = _supervised(ctl, 2000.0, operators)
    assert released is None and ctl.override == 90.0
    # said once, when the link came up
    assert [(k, p) for k, _, p in records] == [("override_found_held", {"machine": "m", "override_pct": 90.0})]


def test_an_s_word_is_held_to_the_range_at_the_speed_the_operators_override_gives():
    """The control multiplies the S word by the panel's spindle override: at 120 %, 2800 r/min
    runs at 3360, beyond spindle_rpm_max 3000, and is refused; 2400 (2880) is sent."""
    from lathed.config import Instance
    from lathed.safety import Limits
    from lathed.supervisor import Plan, Supervisor
    from tests.test_plausible import FakeStore
    written = []
    peer = ModbusPeer("127.0.0.1", free_port(), {"spindle_rpm_cmd": (0, "float32", True, "r/min"),
                                                 "spindle_override_pct": (2, "float32", False, "%")}, 4,
                      lambda n, v: written.append(v))
    peer.block.update({"spindle_rpm_cmd": 2000.0, "spindle_override_pct": 120.0})
    data = {"kind": "lathe", "host": "127.0.0.1", "port": peer.port, "poll": "20ms",
            "registers": {"spindle_rpm_cmd": {"address": 0, "type": "float32", "writable": True},
                          "spindle_override_pct": {"address": 2, "type": "float32"}}}

    async def go():
        d = driver(data)
        inst = Instance("machine", "m", "modbus_cnc", Section("t.toml", "machine.m", data),
                        Section("t.toml", "machine.m", {}))
        sup = Supervisor(None, Plan(drivers={"m": (inst, d)}, limits={"m": Limits(rpm_min=100.0, rpm_max=3000.0)}),
                         Bus(), FakeStore(), lambda *a: None)
        await peer.start()
        sup.start_drivers()
        try:
            await until(lambda: d._fresh("spindle_override_pct") == 120.0, what="the override read")
            return await sup.command(_speed(2800.0)), await sup.command(_speed(2400.0))
        finally:
            await sup.stop()
            await peer.stop()
    refused, sent = asyncio.run(asyncio.wait_for(go(), 30))
    assert refused == {"sent": False, "reason": "spindle speed 2800 r/min runs at 3360 with the control's "
                                                "spindle override at 120 %, outside [100, 3000]"}
    assert sent["sent"] and written == [2400.0]


def test_a_command_whose_asker_is_cancelled_mid_write_is_finished_and_recorded():
    """A speed variation stopped at the cut's end, or the daemon stopping, cancels the task that
    asked for a speed while its write is on the wire: the control takes it, so it is recorded
    (and paced, and released) as any command sent."""
    async def cancelled_mid_write(sup, d):
        answer, on_wire = asyncio.Event(), asyncio.Event()
        write = d.client.write_registers

        async def slow_answer(*a, **k):
            r = await write(*a, **k)          # on the control
            on_wire.set()
            await answer.wait()               # ... the answer still on its way
            return r
        d.client.write_registers = slow_answer
        asker = asyncio.create_task(sup.command(_speed(1650.0)))
        await on_wire.wait()
        asker.cancel()
        answer.set()
        with pytest.raises(asyncio.CancelledError):
            await asker
        d.client.write_registers = write
    ctl = OverrideControl()
    _, records = _supervised(ctl, 2000.0, cancelled_mid_write)
    sent = [p for k, _, p in records if k == "command_sent"]
    assert [p["override_pct"] for p in sent] == [110.0, 100.0], sent      # the cure, then the stop's release
    assert ctl.override == 100.0


@pytest.mark.parametrize("limits", [{"rpm_step_max": 100.0}, {"rpm_rate_max": 100.0}])
def test_a_release_is_bounded_by_the_range_not_the_step_or_pace(limits):
    """Two steps of 90 and 60 r/min lead to 110 %; the way back is one of 150, and it may come
    at once (a cut that ends just after the cure): refused, the override would hold over the
    next parts (a program's S1900 run at 2090 r/min)."""
    async def cured_then_released(sup, d):
        for rpm in ((1590.0, 1650.0) if "rpm_step_max" in limits else (1590.0,)):
            assert (await sup.command(_speed(rpm)))["sent"]
            await until(lambda: d.current("spindle_rpm") == rpm, what="the override read back")
        return await sup.release("m", "spindle_rpm", "suppress")
    ctl = OverrideControl()
    if "rpm_rate_max" in limits:
        ctl.program = 1500.0
    released, _ = _supervised(ctl, 2000.0, cured_then_released, **limits)
    assert released["sent"] and released["override_pct"] == 100.0 and ctl.override == 100.0


def test_an_override_lathed_left_is_released_when_the_daemon_stops():
    """Supervisor.stop puts back what lathed's commands left held (an override holds part
    after part), through the guard; an override the operator moved since is theirs."""
    async def cured(sup, d):
        await sup.command(_speed(1650.0))                         # 110 %
        await until(lambda: d.current("spindle_rpm") == 1650.0, what="the override read back")
    ctl = OverrideControl()
    _, records = _supervised(ctl, 2000.0, cured)
    assert ctl.writes == [110.0, 100.0]
    payload = [p for k, _, p in records if k == "command_sent"][-1]
    assert payload["reason"] == "released: the daemon is stopping" and payload["override_pct"] == 100.0

    async def then_the_operator(sup, d):
        await cured(sup, d)
        ctl.write("spindle_override_pct", 80.0)
        await until(lambda: d.current("spindle_rpm") == 1200.0, what="the operator's override read back")
    ctl = OverrideControl()
    _, records = _supervised(ctl, 2000.0, then_the_operator)
    assert ctl.writes == [110.0, 80.0] and ctl.override == 80.0
    assert [k for k, _, _ in records if k.startswith("command")] == ["command_sent"]


def test_the_heartbeat_counts_while_the_link_is_up():
    """A writable heartbeat register gets a count every heartbeat_every (the control's PMC
    takes a held override back when it stops); a read-only one is a config error."""
    ctl = OverrideControl()
    beats = []
    ctl.MAP = {**OverrideControl.MAP, "heartbeat": (4, "uint16", True, "")}
    ctl.peer = ModbusPeer("127.0.0.1", free_port(), ctl.MAP, 5,
                          lambda n, v: beats.append(v) if n == "heartbeat" else ctl.write(n, v))
    ctl.publish()
    regs = {"spindle_rpm_cmd": {"address": 0, "type": "float32"},
            "heartbeat": {"address": 4, "type": "uint16", "writable": True}}
    d = driver({"kind": "lathe", "host": "127.0.0.1", "port": ctl.peer.port, "poll": "20ms",
                "heartbeat_every": "50ms", "registers": regs})

    async def check(d, events):
        await until(lambda: len(beats) >= 4, what="four beats")
        hb = d.status()["heartbeat"]
        assert hb["every_s"] == 0.05 and abs(hb["count"] - len(beats)) <= 1     # one may be in flight
    asyncio.run(asyncio.wait_for(_run_against(ctl.peer, _NoPhysics(), d, check), 30))
    assert beats[:4] == [1.0, 2.0, 3.0, 4.0]          # the first at connect
    with pytest.raises(ConfigError, match="heartbeat must be writable"):
        driver({"host": "127.0.0.1", "registers": {"heartbeat": {"address": 4, "type": "uint16"}}})


def test_no_override_under_constant_surface_speed():
    """Under G96 the programmed speed moves on its own, and an override would carry the spindle
    past the speed the guard checked: refused, seen from css_active where mapped, else from the
    commanded speed changing at every poll. Back to 100 % (a release) is always written."""
    ctl = OverrideControl()
    ctl.peer = ModbusPeer("127.0.0.1", free_port(), {**OverrideControl.MAP, "css_active": (4, "uint16", False, "")},
                          5, ctl.write)
    ctl.css = 0

    def publish():
        ctl.peer.block.update({"spindle_rpm_cmd": ctl.program * ctl.override / 100,
                               "spindle_override_pct": ctl.override, "css_active": ctl.css})
    ctl.publish = publish
    ctl.publish()
    base = {"spindle_rpm_cmd": {"address": 0, "type": "float32"},
            "spindle_override_pct": {"address": 2, "type": "float32", "writable": True}}

    async def check_css(d, events):
        await until(lambda: d.current("spindle_rpm") == 1500.0, what="polls")
        await d.execute(Command(machine="m", action="spindle_rpm", value=1650.0, reason="t", source="t"))
        ctl.css = 1
        ctl.publish()
        await until(lambda: d._fresh("css_active") == 1, what="G96 seen")
        with pytest.raises(ValueError, match="constant surface speed, G96"):
            await d.execute(Command(machine="m", action="spindle_rpm", value=1800.0, reason="t", source="t"))
        assert ctl.override == 110.0
        assert (await d.execute(Command(machine="m", action="spindle_rpm", value=d.released("spindle_rpm"),
                                        reason="released", source="t")))["override_pct"] == 100.0

    d = driver({"kind": "lathe", "host": "127.0.0.1", "port": ctl.peer.port, "poll": "20ms",
                "registers": {**base, "css_active": {"address": 4, "type": "uint16"}}})
    asyncio.run(asyncio.wait_for(_run_against(ctl.peer, _NoPhysics(), d, check_css), 30))

    class Facing:       # no css_active register: the commanded speed rises at every poll
        def step(self, dt):
            ctl.program += 30.0
            ctl.publish()

        def registers(self):
            return {}

    async def check_drift(d, events):
        def moving():      # three polls in a row, each with the speed moved (a stalled loop may repeat one)
            seen = list(d._cmd_seen)[-3:]
            return len(seen) == 3 and all(a[1] == b[1] == 100.0 and b[0] > a[0] for a, b in zip(seen, seen[1:]))
        await until(moving, what="the speed moving at each poll")
        with pytest.raises(ValueError, match="moving on its own"):
            await d.execute(Command(machine="m", action="spindle_rpm", value=ctl.program * 1.1, reason="t",
                                    source="t"))
    ctl.program, ctl.override, ctl.css = 1500.0, 100.0, 0
    ctl.peer = ModbusPeer("127.0.0.1", free_port(), OverrideControl.MAP, 4, ctl.write)
    ctl.publish = lambda: ctl.peer.block.update({"spindle_rpm_cmd": ctl.program * ctl.override / 100,
                                                 "spindle_override_pct": ctl.override})
    ctl.publish()
    # polled slower than the facing's 20 ms steps: each poll sees the speed moved
    d = driver({"kind": "lathe", "host": "127.0.0.1", "port": ctl.peer.port, "poll": "60ms", "registers": base})
    asyncio.run(asyncio.wait_for(_run_against(ctl.peer, Facing(), d, check_drift), 30))
