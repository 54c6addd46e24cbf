"""The simulated CNCs' Modbus servers (real pymodbus servers): TCP on loopback,
or RTU on a null-modem pseudo-terminal pair (lathed.sim.serial_peer.NullModem)."""
from __future__ import annotations

import asyncio
import logging
from typing import Callable

from pymodbus.client import AsyncModbusTcpClient
from pymodbus.constants import ExcCodes
from pymodbus.datastore import ModbusDeviceContext, ModbusSequentialDataBlock, ModbusServerContext
from pymodbus import FramerType
from pymodbus.server import ModbusSerialServer, ModbusTcpServer

from lathed.sim.serial_peer import NullModem

log = logging.getLogger("lathed.sim.modbus")
DT = AsyncModbusTcpClient.DATATYPE
TYPES = {"int16": DT.INT16, "uint16": DT.UINT16, "int32": DT.INT32, "uint32": DT.UINT32, "float32": DT.FLOAT32}


def encode(value: float, typ: str) -> list[int]:
    dt = TYPES[typ]
    if typ != "float32":
        value = int(round(value))
    return AsyncModbusTcpClient.convert_to_registers(value, dt, word_order="big")


def decode(regs: list[int], typ: str) -> float:
    return float(AsyncModbusTcpClient.convert_from_registers(regs, TYPES[typ], word_order="big"))


class _Registers(ModbusSequentialDataBlock):
    """Holding registers that refuse writes to read-only addresses and pass
    accepted writes to the machine."""

    def __init__(self, regmap: dict, size: int, on_write: Callable[[str, float], None]):
        super().__init__(1, [0] * size)      # pymodbus adds 1 to protocol addresses
        self.regmap = regmap
        self.on_write = on_write
        self._owner = {}
        for name, (addr, typ, writable, _unit) in regmap.items():
            for a in range(addr, addr + len(encode(0, typ))):
                self._owner[a] = (name, writable)

    def update(self, values: dict[str, float]) -> None:
        for name, v in values.items():
            addr, typ, _, _ = self.regmap[name]
            super().setValues(addr + 1, encode(v, typ))

    def setValues(self, address, values):
        values = values if isinstance(values, list) else [values]
        proto = address - 1
        touched = {self._owner.get(a, (None, False)) for a in range(proto, proto + len(values))}
        if any(not writable for _, writable in touched):
            return ExcCodes.ILLEGAL_ADDRESS
        result = super().setValues(address, values)
        for name, _ in touched:
            addr, typ, _, _ = self.regmap[name]
            regs = self.getValues(addr + 1, len(encode(0, typ)))
            try:
                self.on_write(name, decode(regs, typ))
            except (ValueError, KeyError) as e:
                log.warning("write refused by the machine: %s", e)
                return ExcCodes.ILLEGAL_VALUE
        return result


class ModbusPeer:
    def __init__(self, host: str, port: int, regmap: dict, size: int, on_write,
                 null_modem: NullModem | None = None, baudrate: int = 115200):
        self.host, self.port = host, port
        self.null_modem, self.baudrate = null_modem, baudrate
        self.block = _Registers(regmap, size, on_write)
        self.context = ModbusServerContext(devices=ModbusDeviceContext(hr=self.block), single=True)
        self.server: ModbusTcpServer | ModbusSerialServer | None = None
        self.up = False

    async def start(self) -> None:
        if self.null_modem is not None:
            inner = self.null_modem.open()
            self.server = ModbusSerialServer(self.context, framer=FramerType.RTU, port=inner,
                                             baudrate=self.baudrate)
        else:
            self.server = ModbusTcpServer(self.context, address=(self.host, self.port))
        await self.server.serve_forever(background=True)
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
