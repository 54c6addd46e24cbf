"""The simulated CNCs' Modbus servers (real pymodbus servers): TCP on loopback,
or RTU on a null-modem pseudo-terminal pair (lathed.sim.serial_peer.NullModem)."""
from __future__ import annotations

import asyncio
import logging
import socket
from typing import Callable

from pymodbus.client import AsyncModbusTcpClient
from pymodbus.constants import ExcCodes
from pymodbus import FramerType
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from lathed.modbus_identity import encode_ascii
from lathed.sim.serial_peer import NullModem

log = logging.getLogger("lathed.sim.modbus")
DT = AsyncModbusTcpClient.DATATYPE
HOLDING = {3, 6, 16, 22, 23}     # function codes on holding registers
TYPES = {"int16": DT.INT16, "uint16": DT.UINT16, "int32": DT.INT32, "uint32": DT.UINT32, "float32": DT.FLOAT32}


def encode(value: float, typ: str) -> list[int]:
    dt = TYPES[typ]
    if typ != "float32":
        value = int(round(value))
    return AsyncModbusTcpClient.convert_to_registers(value, dt, word_order="big")


def decode(regs: list[int], typ: str) -> float:
    return float(AsyncModbusTcpClient.convert_from_registers(regs, TYPES[typ], word_order="big"))


class _Registers:
    """A controller's holding registers, served through pymodbus's SimDevice:
    the machine's values live here, each request first copies them into the
    server's memory; writes to read-only addresses are refused and accepted
    writes pass to the machine, which may refuse the value."""

    def __init__(self, regmap: dict, size: int, on_write: Callable[[str, float], None],
                 identity: dict[str, tuple[tuple[int, int], str]] | None = None):
        self.regmap = regmap
        self.on_write = on_write
        self.regs = [0] * size
        # what the control says it is: key -> ((address, words), text), read-only
        for (addr, words), text in (identity or {}).values():
            self.regs[addr:addr + words] = encode_ascii(text, words)
        self._owner = {}
        for name, (addr, typ, writable, _unit) in regmap.items():
            for a in range(addr, addr + len(encode(0, typ))):
                self._owner[a] = (name, writable)

    def device(self, unit: int = 0) -> SimDevice:
        """The server-side device; unit 0 answers every unit address."""
        return SimDevice(unit, simdata=SimData(0, values=[0] * len(self.regs), datatype=DataType.REGISTERS),
                         action=self.action)

    def update(self, values: dict[str, float]) -> None:
        for name, v in values.items():
            addr, typ, _, _ = self.regmap[name]
            regs = encode(v, typ)
            self.regs[addr:addr + len(regs)] = regs

    def _value(self, regs: list[int], name: str) -> float:
        addr, typ, _, _ = self.regmap[name]
        return decode(regs[addr:addr + len(encode(0, typ))], typ)

    async def action(self, function_code: int, start_address: int, address: int, count: int,
                     registers: list[int], set_values: list[int] | None) -> ExcCodes | None:
        if function_code not in HOLDING:
            return ExcCodes.ILLEGAL_FUNCTION       # the controller has holding registers only
        if address < 0 or address + count > len(self.regs):
            return ExcCodes.ILLEGAL_ADDRESS
        if set_values is not None:
            touched = {self._owner.get(a, (None, False)) for a in range(address, address + count)}
            if any(not writable for _, writable in touched):
                return ExcCodes.ILLEGAL_ADDRESS
            new = list(self.regs)
            new[address:address + count] = set_values
            for name, _ in touched:
                try:
                    self.on_write(name, self._value(new, name))
                except (ValueError, KeyError) as e:
                    log.warning("write refused by the machine: %s", e)
                    return ExcCodes.ILLEGAL_VALUE
            # the written words over what the machine made of them (a commanded speed that
            # follows a new override), not over a copy from before the write
            self.regs[address:address + count] = set_values
        first = address - start_address
        registers[first:first + count] = self.regs[address:address + count]
        return None


class ModbusPeer:
    def __init__(self, host: str, port: int, regmap: dict, size: int, on_write,
                 null_modem: NullModem | None = None, baudrate: int = 115200,
                 identity: dict[str, tuple[tuple[int, int], str]] | None = None):
        self.host, self.port = host, port
        self.null_modem, self.baudrate = null_modem, baudrate
        self.block = _Registers(regmap, size, on_write, identity)
        self.server: ModbusTcpServer | ModbusSerialServer | None = None
        self.up = False

    async def start(self) -> None:
        if self.null_modem is not None:
            inner = self.null_modem.open()
            self.server = ModbusSerialServer(self.block.device(), framer=FramerType.RTU, port=inner,
                                             baudrate=self.baudrate)
        else:
            self.server = ModbusTcpServer(self.block.device(), address=(self.host, self.port))
        try:
            await self.server.serve_forever(background=True)
        except RuntimeError:
            # pymodbus logs the cause and raises a generic error: the daemon is to say why
            if self.null_modem is None:
                with socket.socket() as probe:
                    try:
                        probe.bind((self.host, self.port))
                    except OSError as e:
                        raise OSError(e.errno, f"cannot serve Modbus TCP on {self.host}:{self.port}: "
                                               f"{e.strerror}") from None
            raise
        self.up = True

    async def stop(self) -> None:
        if self.server is not None:
            await self.server.shutdown()
            self.server = None
        if self.null_modem is not None:
            self.null_modem.close()      # the RS-485 cable pulled
        self.up = False

    async def outage(self, seconds: float) -> None:
        """Go away as a crashed controller does, then come back."""
        await self.stop()
        await asyncio.sleep(seconds)
        await self.start()
