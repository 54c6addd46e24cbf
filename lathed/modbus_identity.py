"""Identity registers of a Modbus control: what the peer says it is (docs/safety.md).

A control (or the PLC gateway in front of it) serves its serial number as ASCII in
holding registers, two characters a register, high byte first, padded with NULs or
spaces. The modbus_cnc driver reads them at every connect, and the framework compares
them with the machine's ``[identification]`` (lathed.identity)::

    [machine.lathe.identity]
    serial_number = { address = 36, words = 8 }

The simulated controls serve theirs the same way (lathed.sim.registers).
"""
from __future__ import annotations

import asyncio
from dataclasses import dataclass

from pymodbus.exceptions import ModbusException, ModbusIOException

from lathed.config import Section
from lathed.identity import KEYS

MAX_WORDS = 125      # one read request


@dataclass(frozen=True)
class IdentityRegister:
    key: str         # a key of [identification]: serial_number, model, manufacturer
    address: int
    words: int


def read_identity_map(sec: Section, taken: dict[int, str], identification: dict) -> dict[str, IdentityRegister]:
    """The [<machine>.identity] table: each key one of [identification]'s, read from ``words``
    registers at ``address``, clear of the register map (``taken``: address -> register)."""
    out = {}
    for key in sec.keys():
        if key not in KEYS:
            raise sec.error(key, f"not an identification key; allowed: {', '.join(KEYS)}")
        if not sec.has_section(key):
            raise sec.error(key, f"expected a table {{ address = ..., words = ... }}, got {sec.get(key)!r}")
    for sub in sec.subsections():
        reg = IdentityRegister(sub.name, sub.getint("address", minval=0, maxval=65535),
                               sub.getint("words", minval=1, maxval=MAX_WORDS))
        sub.check_unused()
        if reg.address + reg.words > 65536:
            raise sub.error("address", f"{reg.words} registers at {reg.address} run past register 65535")
        clash = next((taken[a] for a in range(reg.address, reg.address + reg.words) if a in taken), None)
        if clash is not None:
            raise sub.error("address", f"overlaps register {clash!r} of the register map")
        if reg.key not in identification:
            table = sec.table.rsplit(".", 1)[0] + ".identification"
            raise sub.error(None, f"the peer's {reg.key} is read, but [{table}] gives no {reg.key} to compare "
                                  "it with")
        out[reg.key] = reg
    return out


def decode_ascii(regs: list[int]) -> str:
    """Two characters a register, high byte first; NULs and spaces at the ends dropped."""
    raw = b"".join(int(r & 0xFFFF).to_bytes(2, "big") for r in regs)
    return raw.decode("ascii", errors="replace").strip("\0 ")


def encode_ascii(text: str, words: int) -> list[int]:
    raw = text.encode("ascii")[:2 * words].ljust(2 * words, b"\0")
    return [int.from_bytes(raw[i:i + 2], "big") for i in range(0, len(raw), 2)]


async def read_identity(client, identity: dict[str, IdentityRegister], unit: int, turn, timeout: float,
                        where: str) -> dict[str, str]:
    """Read each identity register from the control (``turn()``: the bus for one request)."""
    out = {}
    for key, reg in identity.items():
        try:
            async with turn(), asyncio.timeout(timeout + 1):
                rr = await client.read_holding_registers(reg.address, count=reg.words, device_id=unit)
        except (asyncio.TimeoutError, ModbusIOException) as e:
            raise TimeoutError(f"no answer from unit {unit} at {where} for its {key} "
                               f"(registers {reg.address}..{reg.address + reg.words - 1})") from e
        if rr.isError():
            raise ModbusException(f"unit {unit} at {where} refused the read of its {key} at {reg.address}: "
                                  f"{rr} (not the control the identity map is for?)")
        out[key] = decode_ascii(rr.registers)
    return out
