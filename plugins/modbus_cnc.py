"""CNC machines (lathe, mill, grinder) over Modbus TCP or RTU, the register map in the config.

Registers are polled by period (``read_on`` reads one at once on a bus trigger); machines on
one RS-485 bus share one port and take turns. Only registers declared writable are written,
only by commands the safety guard passed, and only to a control whose serial number
(``[machine.X.identity]``) matches ``[identification]``. The CNC's commands and interlocks
(override as speed, release, threading) are lathed.cnc's. Keys: docs/configuration.md;
behaviour, heartbeat and overrides: docs/machines.md.
"""
from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections import Counter
from dataclasses import dataclass

from pymodbus import FramerType
from pymodbus.client import AsyncModbusSerialClient, AsyncModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException

from lathed import hookimpl
from lathed.bus import Sample
from lathed.cnc import ACTION_TARGETS, CncDriver
from lathed.command import Command
from lathed.config import Section
from lathed.modbus_identity import read_identity, read_identity_map
from lathed.plausible import Plausibility

DT = AsyncModbusTcpClient.DATATYPE
TYPES = {"int16": (DT.INT16, 1), "uint16": (DT.UINT16, 1), "int32": (DT.INT32, 2),
         "uint32": (DT.UINT32, 2), "float32": (DT.FLOAT32, 2)}
READ_ON_MIN_S = 0.05   # a trigger's reads at most this often: a flapping source costs 20 reads/s, deferred not lost
MAX_READ = 125   # registers per Modbus read request (protocol limit)


class SerialLink:
    """One RS-485 adapter, shared by every machine configured on it."""

    def __init__(self, device: str, settings: tuple):
        self.device, self.settings = device, settings
        self.client: AsyncModbusSerialClient | None = None    # None while the first machine opens it
        self.opened = asyncio.Event()
        self.lock = asyncio.Lock()
        self.users: set[str] = set()


_LINKS: dict[str, SerialLink] = {}     # device -> the link open on it now


def _settings_text(s: tuple) -> str:
    baud, parity, stop = s
    return f"{baud} baud 8{parity}{stop}"


@dataclass(frozen=True)
class Register:
    name: str
    address: int
    type: str
    word_order: str
    scale: float
    unit: str
    writable: bool
    poll: float
    read_on: tuple[str, ...] = ()     # "source.quantity" samples that, at 1, read it at once

    @property
    def count(self) -> int:
        return TYPES[self.type][1]

    def decode(self, regs: list[int]) -> float:
        raw = AsyncModbusTcpClient.convert_from_registers(regs, TYPES[self.type][0], word_order=self.word_order)
        return float(raw) * self.scale

    def encode(self, value: float) -> list[int]:
        raw = value / self.scale
        if self.type != "float32":
            # never further from zero than the value the guard checked (7.5 µm at a limit
            # of 7.5 rounded to 8 on a 1 µm register); a float's last bit is not a step
            raw = int(math.trunc(raw + math.copysign(1e-6, raw)))
        return AsyncModbusTcpClient.convert_to_registers(raw, TYPES[self.type][0], word_order=self.word_order)


# what lathed writes: an action's register, the override a speed is commanded by, the heartbeat
WRITABLE = (*ACTION_TARGETS.values(), "spindle_override_pct", "heartbeat")


def read_register_map(sec: Section, default_poll: float, plausible: Plausibility | None = None) -> dict[str, Register]:
    regs = {}
    for key in sec.keys():   # subsections() passes over the rest: `foo = 3` was silently ignored
        if not sec.has_section(key):
            raise sec.error(key, f"expected a table {{ address = ..., type = ... }}, got {sec.get(key)!r}")
    for sub in sec.subsections():
        reg = Register(
            name=sub.name,
            address=sub.getint("address", minval=0, maxval=65535),
            type=sub.getstr("type", choices=tuple(TYPES)),
            word_order=sub.getstr("word_order", "big", choices=("big", "little")),
            scale=sub.getfloat("scale", 1.0),
            unit=sub.getstr("unit", ""),
            writable=sub.getbool("writable", False),
            poll=sub.getduration("poll", default_poll, minval=0.01, maxval=3600),
            read_on=tuple(sub.getlist("read_on", [])),
        )
        bad = [t for t in reg.read_on if t.count(".") != 1 or not all(t.split("."))]
        if bad:
            raise sub.error("read_on", f"{bad[0]!r} is not source.quantity (e.g. \"chatter.cut_contact\")")
        if plausible is not None and (why := plausible.unit_problem(reg.name, reg.unit,
                                                                     sec.table.rsplit(".", 1)[0] + ".plausible")):
            raise sub.error("unit", why)
        if reg.scale == 0:
            raise sub.error("scale", "must not be 0")
        if reg.address + reg.count > 65536:
            raise sub.error("address", f"a {reg.type} at {reg.address} runs past register 65535")
        if reg.writable and reg.name not in WRITABLE:   # a typo would leave the action without its register
            raise sub.error("writable", f"no action writes {reg.name!r}; writable registers: {', '.join(WRITABLE)}")
        sub.check_unused()
        regs[reg.name] = reg
    if not regs:
        raise sec.error(None, "no registers declared; add [<table>.NAME] tables with address and type")
    taken: dict[int, str] = {}
    for r in regs.values():
        for a in range(r.address, r.address + r.count):
            if a in taken:
                raise sec.error(r.name, f"register {a} overlaps {taken[a]!r}")
            taken[a] = r.name
    return regs


def read_plan(regs) -> list[tuple[int, int, list[Register]]]:
    """Group registers into as few contiguous read requests as the protocol allows."""
    plan: list[tuple[int, int, list[Register]]] = []
    for r in sorted(regs, key=lambda r: r.address):
        if plan and r.address + r.count - plan[-1][0] <= MAX_READ and r.address - (plan[-1][0] + plan[-1][1]) <= 8:
            start, _, members = plan[-1]
            plan[-1] = (start, r.address + r.count - start, members + [r])
        else:
            plan.append((r.address, r.count, [r]))
    return plan


def poll_groups(regs: dict[str, Register]) -> dict[float, list[tuple[int, int, list[Register]]]]:
    """One read plan per poll period."""
    periods = sorted({r.poll for r in regs.values()})
    return {p: read_plan([r for r in regs.values() if r.poll == p]) for p in periods}


class ModbusCNC(CncDriver):
    STATES = {0: "idle", 1: "running", 2: "alarm"}

    def __init__(self, name: str, section: Section):
        super().__init__(name, section)
        self.kind = section.getstr("kind", "lathe", choices=("lathe", "mill", "grinder"))
        self.transport = section.getstr("transport", "tcp", choices=("tcp", "rtu"))
        if self.transport == "tcp":
            self.host = section.getstr("host")
            self.port = section.getint("port", 502, minval=1, maxval=65535)
            self.where = f"{self.host}:{self.port}"
        else:
            self.device = section.getstr("device")
            self.baudrate = section.getint("baudrate", 19200, minval=300, maxval=4_000_000)
            self.parity = section.getstr("parity", "N", choices=("N", "E", "O"))
            self.stopbits = section.getint("stopbits", 1, minval=1, maxval=2)
            self.where = self.device
        self.unit = section.getint("unit", 1, minval=0, maxval=247)
        self.poll = section.getduration("poll", 0.1, minval=0.01, maxval=60)
        self.timeout = section.getduration("timeout", 1.0, minval=0.05, maxval=60)
        self.registers = read_register_map(section.getsection("registers"), self.poll, self.plausible)
        slowest = max(r.poll for r in self.registers.values())
        stale_after = section.getduration("stale_after", max(2.0, 3 * slowest), minval=0.05)
        if stale_after <= slowest:
            raise section.error("stale_after", f"must be longer than the slowest poll ({slowest:g} s), "
                                               "or every value of that group is always stale")
        thr = self.registers.get("threading")
        fastest = min(r.poll for r in self.registers.values())
        if thr is not None and thr.poll > fastest:
            # a thread begun between two slow readings would take commands for up to a poll
            raise section.error("registers", f"threading is polled every {thr.poll:g} s: poll it with the "
                                             f"fastest group ({fastest:g} s), it holds every command back")
        # how old a threading reading may be for a command to pass: two polls and an answer's wait
        self.setup_cnc(section, set(self.registers), {n for n, r in self.registers.items() if r.writable},
                       "registers", stale_after, threading_max_age=2 * fastest + self.timeout)
        self.groups = poll_groups(self.registers)
        # trigger -> the read plan of the registers it reads at once
        self.read_on = {t: read_plan([r for r in self.registers.values() if t in r.read_on])
                        for t in sorted({t for r in self.registers.values() for t in r.read_on})}
        self._triggered: list[str] = []        # triggers seen since the last read (in order, once each)
        self._wake = asyncio.Event()
        self.reads_on: Counter = Counter()     # trigger -> reads it caused
        self._read_on_t: dict[str, float] = {}  # trigger -> monotonic time of its last read
        ovr = self.registers.get("spindle_override_pct")
        if self.speed_by_override:
            res = ovr.scale if ovr.type != "float32" else 0.0
            if res and abs(self.override_step / res - round(self.override_step / res)) > 1e-6:
                raise section.error("override_step_pct", f"{self.override_step:g} % is not a whole number of "
                                                         f"the override register's {res:g} % steps: the control "
                                                         "would round it past the speed the guard checked")
        taken = {a: r.name for r in self.registers.values() for a in range(r.address, r.address + r.count)}
        self.identity_map = read_identity_map(section.getsection("identity", required=False), taken,
                                              self.identification)
        writes = [*self.actions, *(["heartbeat"] if "heartbeat" in self.registers else [])]
        if writes and "serial_number" not in self.identity_map:
            # whatever answers at the address would be commanded (another machine, a simulator)
            raise section.error("identity", f"{self.name} is written to ({', '.join(writes)}): map the "
                                            "control's serial number (serial_number = { address = ..., words = ... }) "
                                            f"and give it as [{section.table}.identification] serial_number, so that "
                                            "the peer is confirmed to be this machine before any command")
        hb = self.registers.get("heartbeat")
        if hb is not None and not hb.writable:
            raise section.error("registers", "heartbeat must be writable: lathed writes it, the control's "
                                             "PMC watches it")
        # read only with the register: given without it, it is an unknown key
        self.heartbeat_every = (section.getduration("heartbeat_every", 0.5, minval=0.05, maxval=10.0)
                                if hb is not None else None)
        self.beats = 0
        self.client: AsyncModbusTcpClient | AsyncModbusSerialClient | None = None
        self.link: SerialLink | None = None
        self.polls = 0
        self.reads: Counter = Counter()    # poll period -> reads of that group
        self.errors: Counter = Counter()

    async def connect(self) -> None:
        # pymodbus's own reconnect is off: the supervisor owns retries and backoff
        if self.transport == "tcp":
            self.client = AsyncModbusTcpClient(self.host, port=self.port, timeout=self.timeout, retries=0,
                                               reconnect_delay=0)
            await self._open(self.client)
        else:
            await self._join_link()
        # the first read proves the controller answers: an open port is not a machine. Nothing
        # is written before run(): the supervisor first confirms the peer is this machine
        await self._read_group(self.groups[min(self.groups)])
        self.held_at_connect()
        self.model.link_up()

    async def identify(self) -> dict[str, str]:
        """The identity registers ([<machine>.identity]) as the control serves them now."""
        return await read_identity(self.client, self.identity_map, self.unit, self._turn, self.timeout, self.where)

    async def _open(self, client) -> None:
        try:
            async with asyncio.timeout(self.timeout + 1):     # not wait_for: see _read_group
                ok = await client.connect()
        except asyncio.TimeoutError:
            ok = False
        if not ok:
            self.errors["connect"] += 1
            hint = "machine off or network down?" if self.transport == "tcp" else "adapter unplugged?"
            raise ConnectionError(f"no Modbus {self.transport.upper()} link to {self.where} ({hint})")

    async def _join_link(self) -> None:
        settings = (self.baudrate, self.parity, self.stopbits)
        link = _LINKS.get(self.device)
        if link is not None and link.settings != settings:
            raise ConnectionError(
                f"{self.device} is open at {_settings_text(link.settings)} for {', '.join(sorted(link.users))}; "
                f"this machine asks {_settings_text(settings)}: the machines on one RS-485 bus must agree")
        if link is None:
            # registered before opening, so machines starting together open the port once
            link = _LINKS[self.device] = SerialLink(self.device, settings)
            link.users.add(self.name)
            client = AsyncModbusSerialClient(self.device, framer=FramerType.RTU, baudrate=self.baudrate,
                                             parity=self.parity, stopbits=self.stopbits,
                                             timeout=self.timeout, retries=0, reconnect_delay=0)
            try:
                await self._open(client)
            except BaseException:
                link.users.discard(self.name)
                if _LINKS.get(self.device) is link:
                    del _LINKS[self.device]
                link.opened.set()         # the others waiting see no client and fail too
                raise
            link.client = client
            link.opened.set()
        else:
            link.users.add(self.name)
            await link.opened.wait()
            if link.client is None:
                link.users.discard(self.name)
                self.errors["connect"] += 1
                raise ConnectionError(f"no Modbus RTU link to {self.where} (adapter unplugged?)")
        self.link, self.client = link, link.client

    async def close(self) -> None:
        self.model.link_down()
        link, self.link = self.link, None
        if link is not None:
            link.users.discard(self.name)
            if not link.users:
                if _LINKS.get(link.device) is link:
                    del _LINKS[link.device]
                if link.client is not None:
                    link.client.close()
        elif self.client is not None:
            self.client.close()
        self.client = None

    def linked(self) -> bool:
        return self.client is not None

    def _turn(self):
        """The bus for one request: RTU machines on one adapter take turns."""
        return self.link.lock if self.link is not None else contextlib.nullcontext()

    def _link_lost(self) -> None:
        # the adapter itself is gone: the next machine to connect opens it afresh
        if self.link is not None and _LINKS.get(self.link.device) is self.link:
            del _LINKS[self.link.device]

    async def _read_group(self, plan) -> None:
        read, asked = [], None
        for start, count, members in plan:
            try:
                # asyncio.timeout, not wait_for: on 3.11 wait_for can swallow a
                # cancellation that lands as the read completes, and the poll goes on
                async with self._turn(), asyncio.timeout(self.timeout + 1):
                    asked = asked or time.time()
                    rr = await self.client.read_holding_registers(start, count=count, device_id=self.unit)
            except (asyncio.TimeoutError, ModbusIOException) as e:
                self.errors["timeout"] += 1
                raise TimeoutError(f"no answer from unit {self.unit} at {self.where} within {self.timeout:g} s "
                                   f"(controller hung, wrong unit id or cable?)") from e
            except ConnectionException as e:
                self.errors["connection"] += 1
                self._link_lost()
                raise ConnectionError(f"Modbus link to {self.where} lost: {e}") from e
            if rr.isError():
                self.errors["refused"] += 1
                raise ModbusException(f"read of registers {start}..{start + count - 1} refused by unit "
                                      f"{self.unit}: {rr} (register map wrong for this controller?)")
            read.append((start, members, rr))
        # the controller read them between the first request and the last answer: stamped
        # then, not when the poll was due (a loaded host, a shared RTU bus put up to a poll's
        # worth of time in between); one stamp a poll, whose readings go together (a dwell's
        # axes against the feed's state)
        now = (asked + time.time()) / 2
        for start, members, rr in read:
            for r in members:
                off = r.address - start
                v = r.decode(rr.registers[off:off + r.count])
                # a float32 NaN or an implausible speed must reach neither the
                # machine model nor current() (the guard's step reference)
                self.take(r.name, v, r.unit, now)
        self.polls += 1
        self.mark_data()

    def listens(self) -> dict[str, tuple[str, str]]:
        """The instances whose samples read_on waits for, each with the table and key that
        name it (the supervisor checks they exist)."""
        return {t.split(".")[0]: (f".registers.{r.name}", "read_on") for r in self.registers.values()
                for t in r.read_on}

    def _trigger(self, msg) -> None:
        """A bus tap (in publish: no I/O here): a read_on sample at 1 wakes the poll loop."""
        if not isinstance(msg, Sample) or msg.value != 1.0:
            return
        key = f"{msg.source}.{msg.quantity}"
        if key in self.read_on and key not in self._triggered:
            self._triggered.append(key)
            self._wake.set()

    async def run(self) -> None:
        sources = sorted(self.listens())
        self._triggered.clear()       # a trigger seen before a reconnect: the poll reads it anyway
        for src in sources:
            self.ctx.bus.tap(src, self._trigger)
        try:
            await self._beat()        # the control's watchdog is armed as soon as the peer is confirmed
            await self._poll()
        finally:
            for src in sources:
                self.ctx.bus.untap(src, self._trigger)

    async def _beat(self) -> None:
        """One heartbeat, where mapped: the count the control's PMC watches (a held override
        goes back to 100 % when it stops).  A refused write is a link fault, as a failed read."""
        reg = self.registers.get("heartbeat")
        if reg is None or self.client is None:
            return
        n = self.beats % 32767 + 1
        async with self._turn():
            rr = await self.client.write_registers(reg.address, reg.encode(n), device_id=self.unit)
        if rr.isError():
            self.errors["heartbeat"] += 1
            raise ModbusException(f"controller refused the heartbeat write to register {reg.address}: {rr}")
        self.beats = n

    async def _poll(self) -> None:
        due = {p: time.monotonic() + p for p in self.groups}
        if "heartbeat" in self.registers:
            due["heartbeat"] = time.monotonic() + self.heartbeat_every
        while True:
            for key in list(self._triggered):
                if time.monotonic() - self._read_on_t.get(key, -math.inf) >= READ_ON_MIN_S:
                    self._triggered.remove(key)
                    await self._read_group(self.read_on[key])
                    self._read_on_t[key] = time.monotonic()
                    self.reads_on[key] += 1
            for p, plan in self.groups.items():
                now = time.monotonic()
                if now >= due[p]:
                    await self._read_group(plan)
                    self.reads[p] += 1
                    due[p] = max(due[p] + p, now)   # after a stall: no burst of catch-up reads
            if time.monotonic() >= due.get("heartbeat", math.inf):
                await self._beat()
                due["heartbeat"] = time.monotonic() + self.heartbeat_every
            self._wake.clear()
            wake_at = min([*due.values(), *(self._read_on_t.get(k, -math.inf) + READ_ON_MIN_S for k in self._triggered)])
            with contextlib.suppress(asyncio.TimeoutError):
                async with asyncio.timeout(max(0.0, wake_at - time.monotonic())):
                    await self._wake.wait()

    async def execute(self, cmd: Command) -> dict | None:
        detail = None
        if cmd.action == "spindle_rpm" and self.speed_by_override:
            value, rpm = self.override_for(float(cmd.value))
            reg = self.registers["spindle_override_pct"]
            detail = {"override_pct": value, "rpm_effective": round(rpm, 1)}
        else:
            value, reg = float(cmd.value), self.registers.get(ACTION_TARGETS.get(cmd.action, ""))
            if cmd.action not in self.actions or reg is None or not reg.writable:
                # only the supervisor calls this, after the guard; anything else is a bug
                raise PermissionError(f"{self.name}: no writable register for action {cmd.action!r}")
        if self.client is None:
            raise ConnectionError("not connected")
        async with self._turn():
            # asked again with the bus ours: on a shared RS-485 bus a poll ahead of this write
            # may have read a thread begun since the guard passed it
            why = self.interlock(cmd)
            if why is not None:
                raise PermissionError(why)
            if detail is not None:
                self.override_written(value, None, pending=True)   # applied but answered late: still ours
            rr = await self.client.write_registers(reg.address, reg.encode(value), device_id=self.unit)
        if rr.isError():
            raise ModbusException(f"controller refused write of {value:g} to {reg.name}: {rr}")
        if detail is not None:
            self.override_written(value, rpm)
        else:
            self.values[reg.name] = (value, time.time())
        return detail

    def status(self) -> dict:
        values = self.value_status({n: r.unit for n, r in self.registers.items()})
        return {"spindle_rpm": self.model.live("spindle_rpm"), "machine_state": self.model.state(),
                "model": self.model.snapshot(), "values": values, "polls": self.polls,
                "reads_by_period_s": {f"{p:g}": n for p, n in sorted(self.reads.items())},
                "reads_on": dict(self.reads_on),
                **({"heartbeat": {"every_s": self.heartbeat_every, "count": self.beats}}
                   if "heartbeat" in self.registers else {}),
                "link": {"transport": self.transport, "where": self.where, "errors": dict(self.errors)}}


@hookimpl
def lathed_driver_types():
    return {"modbus_cnc": ModbusCNC}
