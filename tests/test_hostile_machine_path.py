"""Issue 35, the machine path: the second hostile probe's cases replayed against real peers on
loopback (a pymodbus control, the Arduino's line on a pty, a real store), in one process. What
each must show: no wrong value on the machine, no command without its record."""
from __future__ import annotations

import asyncio
import json
import os
import socket
import subprocess
import time
import types
from pathlib import Path

import numpy as np

from lathed.audit import AuditReserve
from lathed.bus import Bus
from lathed.command import Command
from lathed.config import Instance, Section
from lathed.driver import Driver
from lathed.safety import Limits
from lathed.sim.modbus_peer import ModbusPeer
from lathed.sim.registers import LATHE_IDENTITY, LATHE_MAP, N_REGISTERS, SERIALS
from lathed.sim.serial_peer import SerialPeer
from lathed.store import Store
from lathed.supervisor import Plan, Supervisor, cancel_and_wait
from lathed.wire import format_temperature_line
from lathed_plugins.ds18b20_serial import DS18B20Serial
from lathed_plugins.modbus_cnc import ModbusCNC
from lathed_plugins.thermal import ThermalAnalyzer
from tests.conftest import BIN, disk_free, disk_full, free_port, sim_config

FAST = {"retry_initial": "100ms", "retry_max": "300ms"}
RIGHT = {"front_bearing": 30.0, "rear_bearing": 28.0, "motor": 32.0, "room": 20.0}
COLDER = {k: v - 10.0 for k, v in RIGHT.items()}     # eq. 14 on these: 73 µm less growth


def lathe_data(port: int, serial: str = SERIALS["lathe"]) -> dict:
    regs = {n: {"address": a, "type": t, "writable": w, **({"unit": u} if u else {})}
            for n, (a, t, w, u) in LATHE_MAP.items()}
    (at, words), = LATHE_IDENTITY.values()
    return {"kind": "lathe", "host": "127.0.0.1", "port": port, "poll": "50ms", "timeout": "500ms",
            "registers": regs, "identification": {"serial_number": serial},
            "identity": {"serial_number": {"address": at, "words": words}}}


class Control:
    """The simulated lathe's control: its register map, serving ``serial``; every write kept."""

    def __init__(self, serial: str = SERIALS["lathe"]):
        self.writes: list[tuple[str, float]] = []
        (at, words), = LATHE_IDENTITY.values()
        self.peer = ModbusPeer("127.0.0.1", free_port(), LATHE_MAP, N_REGISTERS,
                               lambda n, v: self.writes.append((n, v)),
                               identity={"serial_number": ((at, words), serial)})
        self.peer.block.update({"spindle_rpm_cmd": 2000.0, "spindle_rpm": 2000.0, "spindle_override_pct": 100.0})

    def written(self, name: str) -> list[float]:
        return [v for n, v in self.writes if n == name]


class Cell:
    """A supervisor over real drivers and analyzers, with a real store, in this process."""

    def __init__(self, tmp: Path, drivers: dict, analyzers: dict | None = None, limits: dict | None = None,
                 reserve: AuditReserve | None = None):
        self.store = Store(tmp / "lathed.db")
        plan = Plan(limits=limits or {})
        for name, (category, plugin, obj) in drivers.items():
            plan.drivers[name] = (Instance(category, name, plugin, Section("t.toml", name, {}),
                                           Section("t.toml", name, dict(FAST))), obj)
        for name, obj in (analyzers or {}).items():
            plan.analyzers[name] = (Instance("analyzer", name, name, Section("t.toml", name, {}),
                                             Section("t.toml", name, dict(FAST))), obj)
        cfg = types.SimpleNamespace(path=tmp / "lathed.toml")
        self.sup = Supervisor(cfg, plan, Bus(), self.store, lambda *a: None, reserve)

    async def __aenter__(self):
        self.sup.start_draining()
        self.sup.start()
        return self

    async def __aexit__(self, *exc):
        await self.sup.stop()
        await asyncio.to_thread(self.store.close)

    def events(self, kind: str) -> list[dict]:
        return [json.loads(r["payload"]) for r in
                self.store.query("SELECT payload FROM events WHERE kind = ? ORDER BY id", (kind,))]


async def until(pred, timeout: float = 15.0, what: str = "condition"):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = pred()
        if v:
            return v
        await asyncio.sleep(0.02)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def run(coro, timeout: float = 90.0):
    return asyncio.run(asyncio.wait_for(coro, timeout))


def lathe(ctl: Control, serial: str = SERIALS["lathe"]) -> ModbusCNC:
    sec = Section("t.toml", "machine.lathe", lathe_data(ctl.peer.port, serial))
    d = ModbusCNC("lathe", sec)
    sec.check_unused()
    return d


LIMITS = Limits(rpm_min=300.0, rpm_max=6000.0, rpm_step_max=3000.0, offset_max_um=60.0,
                offset_rate_max_um_s=25.0, offset_step_max_um=10.0)


# -- case 1 --------------------------------------------------------------------------------------
class Board:
    """The Arduino on the temperature line: its own numbering; closed, the USB cable pulled."""

    def __init__(self, link: Path, readings: dict):
        self.peer, self.readings, self.seq = SerialPeer(link), dict(readings), 0
        self.t0 = time.monotonic()

    def line(self) -> None:
        self.peer.write(format_temperature_line(self.seq, int((time.monotonic() - self.t0) * 1000), self.readings))
        self.seq += 1


def test_case_1_stale_and_implausible_temperatures_move_no_offset(tmp_path):
    """The board's link drops; another on the same port sends readings 10 °C colder for 6 lines
    and drops too. Before: the first line after the reconnect was taken (the gap credited any
    change), eq. 14 predicted 73 µm less growth in one line, and with the sensor gone the
    analyzer phased the offset on to +60 µm. Now: the reading back after the reconnect is
    confirmed first (a rebase), the growth step it makes is refused, stale readings hold the
    offset, and compensation goes on when the right board is back."""
    link = tmp_path / "ttyARDUINO"
    ctl = Control()
    temps = DS18B20Serial("temps", Section("t.toml", "sensor.temps", {"port": str(link), "stale_after": "400ms"}))
    thermal = ThermalAnalyzer("thermal", Section("t.toml", "analyzer.thermal", {
        "input": "temps", "machine": "lathe", "step": "100ms", "rate_um_s": 20.0, "stale_after": "1s"}))
    board = Board(link, RIGHT)
    board.peer.open()

    async def lines(stop: asyncio.Event):
        while not stop.is_set():
            board.line()
            await asyncio.sleep(0.05)

    async def main():
        await ctl.peer.start()
        stop = asyncio.Event()
        feeding = asyncio.create_task(lines(stop))
        try:
            async with Cell(tmp_path, {"lathe": ("machine", "modbus_cnc", lathe(ctl)),
                                       "temps": ("sensor", "ds18b20_serial", temps)},
                            {"thermal": thermal}, {"lathe": LIMITS}) as cell:
                await until(lambda: thermal.touchoff is not None and thermal.applied is not None
                            and thermal.prediction is not None, what="the touch-off and a prediction")
                # the link drops, and another board answers on the same port, colder
                stop.set()
                await feeding
                board.peer.close()
                link.unlink()
                await until(lambda: cell.sup.runners["temps"].state != "connected", what="the sensor down")
                other = Board(link, COLDER)
                other.peer.open()
                await until(lambda: cell.sup.runners["temps"].state == "connected", what="the other board")
                for _ in range(6):
                    other.line()
                    await asyncio.sleep(0.05)
                await asyncio.sleep(0.3)
                other.peer.close()
                link.unlink()
                # ... and is gone, its readings going stale: 2 s watched, 20 steps the analyzer could write
                await until(lambda: cell.sup.runners["temps"].state != "connected", what="the other board gone")
                await asyncio.sleep(2.0)
                offsets = ctl.written("offset_x_um")
                assert all(abs(v) <= 2.5 for v in offsets), offsets
                assert thermal.held and "stale" in thermal.held, thermal.held
                held = await until(lambda: cell.events("thermal_held"), what="the hold recorded")
                assert "predicted growth moved" in held[0]["why"] and "stale" in held[-1]["why"], held
                # the right board is back: its level is confirmed again, and compensation goes on
                board.peer.open()
                stop.clear()
                feeding = asyncio.create_task(lines(stop))
                await until(lambda: thermal.held is None, what="the compensation resumed")
                await until(lambda: cell.events("thermal_resumed"), what="the resumption recorded")
                assert temps.plausible.rebased, "the readings after each reconnect were confirmed, not credited"
                await asyncio.sleep(0.5)
                assert all(abs(v) <= 2.5 for v in ctl.written("offset_x_um")), ctl.writes
        finally:
            stop.set()
            await asyncio.gather(feeding, return_exceptions=True)
            board.peer.close()
            await ctl.peer.stop()
    run(main())


# -- case 2 --------------------------------------------------------------------------------------
def test_case_2_a_release_claimed_by_a_plugin_is_bounded_as_any_command(tmp_path):
    """Releases of 6000 then 300 r/min, 1 s apart, swung the lathe 2000 -> 6000 -> 300 against
    spindle_rpm_step_max 3000. A caller's claim of a release (the flag, where Command still had
    one) buys nothing: 6000 is a 4000 r/min step from the commanded 2000 and is refused."""
    claim = {"release": True} if "release" in Command.__dataclass_fields__ else {}
    ctl = Control()

    async def main():
        await ctl.peer.start()
        try:
            async with Cell(tmp_path, {"lathe": ("machine", "modbus_cnc", lathe(ctl))}, limits={"lathe": LIMITS}) as cell:
                d = cell.sup.runners["lathe"].obj
                await until(lambda: cell.sup.runners["lathe"].state == "connected"
                            and d.current("spindle_rpm") == 2000.0, what="the lathe")
                r = await cell.sup.command(Command("lathe", "spindle_rpm", 6000.0, "plugin", reason="release", **claim))
                assert not r["sent"] and r["reason"] == "spindle speed step 4000 r/min exceeds 3000", r
                assert ctl.written("spindle_rpm_cmd") == []
        finally:
            await ctl.peer.stop()
    run(main())


# -- case 3 --------------------------------------------------------------------------------------
def test_case_3_another_machine_at_the_address_is_never_commanded(tmp_path):
    """Another lathe answers at the configured address (a second simulator on the port, a
    controller swapped on the plant network): refused as a link fault, naming what it says it
    is; no command, and not even the heartbeat, reaches it."""
    other = Control(serial="SIM-LATHE-0002")

    async def main():
        await other.peer.start()
        try:
            async with Cell(tmp_path, {"lathe": ("machine", "modbus_cnc", lathe(other))},
                            limits={"lathe": LIMITS}) as cell:
                r = cell.sup.runners["lathe"]
                await until(lambda: r.failures >= 2, what="the connect refused")
                assert r.state != "connected" and "SIM-LATHE-0002" in r.last_error, r.last_error
                assert "not 'SIM-LATHE-0001'" in r.last_error
                sent = await cell.sup.command(Command("lathe", "offset_x_um", 2.0, "thermal"))
                assert not sent["sent"]
                status = cell.sup.status()["machines"][0]
                assert status["identity"].startswith("not confirmed")
                faults = await until(lambda: cell.events("machine_fault"), what="the fault recorded")
                assert "another machine answers at this address" in faults[0]["error"]
            assert other.writes == []
        finally:
            await other.peer.stop()
    run(main())


class Anonymous(ModbusCNC):
    """A machine driver that cannot ask its peer what it is (a third-party driver)."""

    async def identify(self):
        return None


def test_case_3_a_machine_not_confirmed_takes_no_command(tmp_path):
    ctl = Control()

    async def main():
        await ctl.peer.start()
        try:
            sec = Section("t.toml", "machine.lathe", lathe_data(ctl.peer.port))
            async with Cell(tmp_path, {"lathe": ("machine", "anon", Anonymous("lathe", sec))},
                            limits={"lathe": LIMITS}) as cell:
                await until(lambda: cell.sup.runners["lathe"].state == "connected", what="connected")
                r = await cell.sup.command(Command("lathe", "spindle_rpm", 2100.0, "suppress"))
                assert not r["sent"] and "not confirmed to be this machine" in r["reason"], r
                assert "cannot ask the peer" in r["reason"]
            assert ctl.written("spindle_rpm_cmd") == []
        finally:
            await ctl.peer.stop()
    run(main())


def test_case_3_a_simulator_that_fails_to_start_stops_the_daemon_saying_why(tmp_path):
    """Its port taken (by another simulator): the daemon logged simulator_failed without a reason,
    went on and commanded the other lathe. Now it stops, with one line naming the cause."""
    cfg, paths = sim_config(tmp_path)
    taken = socket.socket()
    taken.bind(("127.0.0.1", paths["modbus_port"]))
    taken.listen()
    try:
        r = subprocess.run([str(BIN / "lathed"), "--config", str(cfg)], capture_output=True, text=True, timeout=60)
    finally:
        taken.close()
    assert r.returncode == 69, (r.returncode, r.stderr[-2000:])
    said = [ln for ln in r.stderr.splitlines() if ln.startswith("lathed: ")]
    assert said == [f"lathed: {cfg}: [simulator] the simulator did not start: [Errno 98] cannot serve Modbus TCP "
                    f"on 127.0.0.1:{paths['modbus_port']}: Address already in use"], r.stderr[-2000:]
    db = sqlite3_rows(paths["state"] / "lathed.db", "SELECT kind FROM events")
    assert "simulator_failed" in db and "command_sent" not in db


def sqlite3_rows(db: Path, sql: str) -> list:
    import sqlite3
    con = sqlite3.connect(db)
    try:
        return [r[0] for r in con.execute(sql)]
    finally:
        con.close()


# -- cases 9, 10, 11 -----------------------------------------------------------------------------
def test_case_9_no_command_without_its_record_on_a_full_disk(tmp_path):
    """While commits failed, 21 command_sent records were lost and the lathe kept being
    commanded. Now each command's record has room claimed before the write: refused by the
    store, it is kept in the audit reserve and stored once there is space; with the reserve
    full, nothing more is sent."""
    ctl = Control()
    reserve = AuditReserve(tmp_path / "audit-reserve", size=2000)

    async def main():
        await ctl.peer.start()
        try:
            async with Cell(tmp_path, {"lathe": ("machine", "modbus_cnc", lathe(ctl))},
                            limits={"lathe": Limits(rpm_min=300.0, rpm_max=6000.0)}, reserve=reserve) as cell:
                await until(lambda: cell.sup.runners["lathe"].state == "connected", what="connected")
                disk_full(cell.store, "events")
                results = []
                for rpm in (2100.0, 2200.0, 2300.0, 2400.0, 2500.0, 2600.0, 2700.0, 2800.0, 2900.0):
                    results.append(await cell.sup.command(Command("lathe", "spindle_rpm", rpm, "suppress")))
                    await until(lambda: reserve.stats()["claimed_bytes"] == 0, what="the record settled")
                sent = [r for r in results if r["sent"]]
                refused = [r for r in results if not r["sent"]]
                assert sent and refused, results
                assert all("no room to record it" in r["reason"] for r in refused)
                assert len(ctl.written("spindle_rpm_cmd")) == len(sent)
                kept_n, kept = reserve.kept()
                assert [r["payload"]["value"] for r in kept] == ctl.written("spindle_rpm_cmd")
                # space again: the kept records reach the store, each with the time it was sent
                await asyncio.wrap_future(disk_free(cell.store))
                await until(lambda: reserve.kept()[0] == 0, what="the reserve drained")
                stored = [p["value"] for p in cell.events("command_sent")]
                assert stored == ctl.written("spindle_rpm_cmd")
                assert [r["t"] for r in kept] == [r["t"] for r in cell.store.query(
                    "SELECT t FROM events WHERE kind = 'command_sent' ORDER BY id")]
        finally:
            await ctl.peer.stop()
    run(main())


def test_case_9_the_reserve_survives_a_stop_and_is_stored_at_the_next_start(tmp_path):
    line = AuditReserve.line("command_sent", "suppress", {"machine": "lathe", "value": 2100.0}, 1234.5)
    r = AuditReserve(tmp_path / "audit-reserve", size=4096)
    assert r.claim(len(line))
    r.settle(len(line), line)
    r.close()
    again = AuditReserve(tmp_path / "audit-reserve", size=4096)
    n, kept = again.kept()
    assert n == len(line) and kept == [{"kind": "command_sent", "source": "suppress", "t": 1234.5,
                                        "payload": {"machine": "lathe", "value": 2100.0}}]
    assert os.stat(tmp_path / "audit-reserve").st_size == 4096      # its room taken when made
    again.drop(n)
    assert again.kept() == (0, [])


def test_case_10_a_commands_context_cannot_stand_for_its_recorded_fields(tmp_path):
    """The lathe got 2000 r/min while its record said machine=mill value=1."""
    ctl = Control()

    async def main():
        await ctl.peer.start()
        try:
            async with Cell(tmp_path, {"lathe": ("machine", "modbus_cnc", lathe(ctl))}, limits={"lathe": LIMITS}) as cell:
                await until(lambda: cell.sup.runners["lathe"].state == "connected", what="connected")
                forged = {"machine": "mill", "value": 1, "action": "offset_x_um", "by": "operator", "reason": "x"}
                r = await cell.sup.command(Command("lathe", "spindle_rpm", 2200.0, "plugin", reason="cure",
                                                   context=forged))
                assert r["sent"]
                await until(lambda: cell.events("command_sent"), what="the record")
                p, = cell.events("command_sent")
                assert (p["machine"], p["action"], p["value"], p["by"], p["reason"]) == \
                    ("lathe", "spindle_rpm", 2200.0, "plugin", "cure")
                assert p["context"] == forged
        finally:
            await ctl.peer.stop()
    run(main())


def test_case_11_command_never_raises_and_takes_numpy_numbers(tmp_path):
    """ctx.command(10**400) raised OverflowError and recorded nothing; numpy's float32 and
    int64 were refused as not finite numbers."""
    ctl = Control()

    async def main():
        await ctl.peer.start()
        try:
            async with Cell(tmp_path, {"lathe": ("machine", "modbus_cnc", lathe(ctl))}, limits={"lathe": LIMITS}) as cell:
                await until(lambda: cell.sup.runners["lathe"].state == "connected", what="connected")
                huge = await cell.sup.command(Command("lathe", "spindle_rpm", 10**400, "plugin"))
                assert not huge["sent"] and huge["reason"].endswith("is not a finite number"), huge
                for v in (np.float32(2100.0), np.int64(2200)):
                    r = await cell.sup.command(Command("lathe", "spindle_rpm", v, "plugin"))
                    assert r["sent"], r
                await until(lambda: len(cell.events("command_sent")) == 2, what="the records")
                refused, = cell.events("command_refused")
                assert refused["value"].startswith("1000000") and "not a finite number" in refused["refused"]
                assert [p["value"] for p in cell.events("command_sent")] == [2100.0, 2200.0]
                assert ctl.written("spindle_rpm_cmd") == [2100.0, 2200.0]
        finally:
            await ctl.peer.stop()
    run(main())


# -- case 14 -------------------------------------------------------------------------------------
class SwitchedOff(Driver):
    """A machine that does not answer until switched on."""
    role, kind = "machine", "lathe"

    def __init__(self):
        super().__init__("mill", Section("t.toml", "machine.mill", {}))
        self.on = False

    async def connect(self):
        if not self.on:
            raise ConnectionError("no Modbus TCP link to 10.0.4.21:502 (machine off or network down?)")

    async def run(self):
        await asyncio.Event().wait()


def test_case_14_a_switched_off_machine_is_one_fault_a_summary_and_one_recovery():
    """46-48 machine_fault records per 90 s (~44,000 a day, to every sink): now one when it goes
    down, a summary with the count while it stays down, one when it is back."""
    from lathed.runner import Runner
    records = []
    m = SwitchedOff()
    r = Runner("machine", "mill", m, 0.01, 0.01, lambda k, s, p=None: records.append((k, p)), summary_every=0.5)

    async def main():
        t0 = time.monotonic()
        r.task = asyncio.create_task(r.loop())
        await until(lambda: r.failures >= 60 and time.monotonic() - t0 > 1.2, what="sixty tries")
        m.on = True
        down_s = time.monotonic() - t0
        await until(lambda: any(k == "machine_recovered" for k, _ in records), what="recovered")
        await cancel_and_wait([r.task])
        return down_s
    down_s = run(main())
    kinds = [k for k, _ in records]
    assert kinds[0] == "machine_fault" and kinds[-1] == "machine_recovered" and kinds.count("machine_recovered") == 1
    # the first, then at most one summary per summary_every
    assert 2 <= kinds.count("machine_fault") <= 1 + down_s / 0.5 + 1, (kinds, down_s)
    summaries = [p for k, p in records if k == "machine_fault" and p.get("still_down")]
    assert sum(p["failures"] for p in summaries) <= r.failures - 1
    assert records[-1][1]["after_failures"] == r.failures, (records[-1], r.failures)


def test_case_14_an_analyzer_failing_at_each_start_is_not_a_fault_and_recovery_pair_per_try():
    """An unreachable MQTT broker: the sink starts (no link to open), fails, and was recorded as
    recovered at each start: a fault/recovered pair per retry."""
    from lathed.runner import Runner
    records = []

    class Sink:
        async def run(self):
            raise ConnectionError("MQTT broker 10.0.4.9:1883 unreachable")
    r = Runner("analyzer", "mqtt", Sink(), 0.01, 0.05, lambda k, s, p=None: records.append(k), summary_every=3600)

    async def main():
        r.task = asyncio.create_task(r.loop())
        await until(lambda: r.failures >= 30, what="thirty tries")
        await cancel_and_wait([r.task])
    run(main())
    assert records == ["analyzer_fault"], records
