"""CNC machines (lathe, mill, grinder) over Modbus TCP, with the register map in the config.

    [machine.lathe]
    plugin = "modbus_cnc"
    kind = "lathe"                  # lathe | mill | grinder
    host = "127.0.0.1"
    port = 502
    unit = 1                        # Modbus unit (device) id
    poll = "100ms"                  # how often the map is read
    timeout = "1s"
    stale_after = "2s"              # a value older than this is shown as stale
    [machine.lathe.registers]
    spindle_rpm = { address = 2, type = "float32", unit = "r/min" }
    spindle_rpm_cmd = { address = 0, type = "float32", writable = true }

A register entry: ``address`` (0-65535), ``type`` (int16 | uint16 | int32 |
uint32 | float32), ``word_order`` ("big": high word first, or "little"),
``scale`` (value = raw * scale), ``unit``, ``writable`` (default false).
Commands write only to writable registers: the ``spindle_rpm`` action writes
``spindle_rpm_cmd``, the ``offset_x_um`` action writes ``offset_x_um``.
"""
from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass

from pymodbus.client import AsyncModbusTcpClient
from pymodbus.exceptions import ModbusException

from lathed import hookimpl
from lathed.bus import Sample
from lathed.command import Command
from lathed.config import Section
from lathed.driver import Driver

DT = AsyncModbusTcpClient.DATATYPE
TYPES = {"int16": (DT.INT16, 1), "uint16": (DT.UINT16, 1), "int32": (DT.INT32, 2),
         "uint32": (DT.UINT32, 2), "float32": (DT.FLOAT32, 2)}
ACTION_REGISTERS = {"spindle_rpm": "spindle_rpm_cmd", "offset_x_um": "offset_x_um"}
MAX_READ = 125   # registers per Modbus read request (protocol limit)


@dataclass(frozen=True)
class Register:
    name: str
    address: int
    type: str
    word_order: str
    scale: float
    unit: str
    writable: bool

    @property
    def count(self) -> int:
        return TYPES[self.type][1]

    def decode(self, regs: list[int]) -> float:
        raw = AsyncModbusTcpClient.convert_from_registers(regs, TYPES[self.type][0], word_order=self.word_order)
        return float(raw) * self.scale

    def encode(self, value: float) -> list[int]:
        raw = value / self.scale
        if self.type != "float32":
            raw = int(round(raw))
        return AsyncModbusTcpClient.convert_to_registers(raw, TYPES[self.type][0], word_order=self.word_order)


def read_register_map(sec: Section) -> dict[str, Register]:
    regs = {}
    for sub in sec.subsections():
        reg = Register(
            name=sub.name,
            address=sub.getint("address", minval=0, maxval=65535),
            type=sub.getstr("type", choices=tuple(TYPES)),
            word_order=sub.getstr("word_order", "big", choices=("big", "little")),
            scale=sub.getfloat("scale", 1.0),
            unit=sub.getstr("unit", ""),
            writable=sub.getbool("writable", False),
        )
        if reg.scale == 0:
            raise sub.error("scale", "must not be 0")
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


def read_plan(regs: dict[str, Register]) -> list[tuple[int, int, list[Register]]]:
    """Group registers into as few contiguous read requests as the protocol allows."""
    plan: list[tuple[int, int, list[Register]]] = []
    for r in sorted(regs.values(), key=lambda r: r.address):
        if plan and r.address + r.count - plan[-1][0] <= MAX_READ and r.address - (plan[-1][0] + plan[-1][1]) <= 8:
            start, _, members = plan[-1]
            plan[-1] = (start, r.address + r.count - start, members + [r])
        else:
            plan.append((r.address, r.count, [r]))
    return plan


class ModbusCNC(Driver):
    role = "machine"
    STATES = {0: "idle", 1: "running", 2: "alarm"}

    def __init__(self, name: str, section: Section):
        super().__init__(name, section)
        self.kind = section.getstr("kind", "lathe", choices=("lathe", "mill", "grinder"))
        self.host = section.getstr("host")
        self.port = section.getint("port", 502, minval=1, maxval=65535)
        self.unit = section.getint("unit", 1, minval=0, maxval=247)
        self.poll = section.getduration("poll", 0.1, minval=0.01, maxval=60)
        self.timeout = section.getduration("timeout", 1.0, minval=0.05, maxval=60)
        self.stale_after = section.getduration("stale_after", max(2.0, 5 * self.poll), minval=0.05)
        self.registers = read_register_map(section.getsection("registers"))
        self.plan = read_plan(self.registers)
        self.actions = tuple(a for a, reg in ACTION_REGISTERS.items()
                             if reg in self.registers and self.registers[reg].writable)
        self.client: AsyncModbusTcpClient | None = None
        self.values: dict[str, tuple[float, float]] = {}     # name -> (value, t)
        self.polls = 0
        self.errors = 0

    async def connect(self) -> None:
        # pymodbus's own reconnect is off: the supervisor owns retries and backoff
        self.client = AsyncModbusTcpClient(self.host, port=self.port, timeout=self.timeout, retries=0,
                                           reconnect_delay=0)
        if not await self.client.connect():
            raise ConnectionError(f"no Modbus server at {self.host}:{self.port} (machine off or network down?)")

    async def close(self) -> None:
        if self.client is not None:
            self.client.close()
            self.client = None

    async def _read_all(self) -> None:
        now = time.time()
        for start, count, members in self.plan:
            rr = await self.client.read_holding_registers(start, count=count, device_id=self.unit)
            if rr.isError():
                raise ModbusException(f"read of registers {start}..{start + count - 1} refused: {rr}")
            for r in members:
                off = r.address - start
                v = r.decode(rr.registers[off:off + r.count])
                self.values[r.name] = (v, now)
                self.ctx.bus.publish(Sample(self.name, r.name, v, r.unit, now))
        self.polls += 1
        self.mark_data()

    async def run(self) -> None:
        while True:
            t0 = time.monotonic()
            await self._read_all()
            await asyncio.sleep(max(0.0, self.poll - (time.monotonic() - t0)))

    async def execute(self, cmd: Command) -> None:
        reg = self.registers[ACTION_REGISTERS[cmd.action]]
        if not reg.writable:   # belt and braces: actions only list writable registers
            raise PermissionError(f"register {reg.name} is read-only")
        if self.client is None:
            raise ConnectionError("not connected")
        rr = await self.client.write_registers(reg.address, reg.encode(cmd.value), device_id=self.unit)
        if rr.isError():
            raise ModbusException(f"controller refused write of {cmd.value:g} to {reg.name}: {rr}")
        self.values[reg.name] = (float(cmd.value), time.time())

    def _fresh(self, name: str) -> float | None:
        v = self.values.get(name)
        if v is None or time.time() - v[1] > self.stale_after:
            return None
        return v[0]

    def current(self, action: str) -> float | None:
        if action == "spindle_rpm":
            return self._fresh("spindle_rpm_cmd") if "spindle_rpm_cmd" in self.registers else None
        if action == "offset_x_um":
            return self._fresh("offset_x_um")
        return None

    def status(self) -> dict:
        now = time.time()
        values = {n: {"value": v, "unit": self.registers[n].unit, "age_s": round(now - t, 3),
                      "stale": now - t > self.stale_after} for n, (v, t) in self.values.items()}
        spindle = self._fresh("spindle_rpm")
        state = self._fresh("program_state")
        return {"spindle_rpm": spindle,
                "machine_state": None if state is None else self.STATES.get(int(state), f"code {int(state)}"),
                "values": values, "polls": self.polls}


@hookimpl
def lathed_driver_types():
    return {"modbus_cnc": ModbusCNC}
