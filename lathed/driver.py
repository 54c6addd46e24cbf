"""The base of every machine and sensor driver.

A driver's constructor only reads and validates its config table (no I/O),
so ``lathed --check-config`` can build every driver without touching the
plant. The supervisor then runs ``connect()`` and ``run()`` in a supervised
task; any exception puts the driver in its safe state (``close()``, no
commands) and it is retried with capped backoff.
"""
from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any, ClassVar

from lathed.config import Section

if TYPE_CHECKING:
    import structlog

    from lathed.bus import Bus
    from lathed.command import Command


class DriverContext:
    """What the supervisor hands a driver: the bus, a logger and the store."""

    def __init__(self, bus: Bus, log: structlog.typing.FilteringBoundLogger, record):
        self.bus = bus
        self.log = log
        self.record = record   # record(kind, payload) -> None, durable, never raises


class Driver:
    role: ClassVar[str] = "sensor"        # "machine" or "sensor"
    kind: ClassVar[str] = "sensor"        # lathe | mill | grinder | robot_arm | sensor
    # Actions (lathed.command.ACTIONS) this driver can carry out.
    actions: ClassVar[tuple[str, ...]] = ()

    def __init__(self, name: str, section: Section):
        self.name = name
        self.ctx: DriverContext | None = None
        self.last_data_t: float | None = None

    async def connect(self) -> None:
        """Open the link; raise on failure."""

    async def run(self) -> None:
        """Read until the link fails (raise) or the task is cancelled."""
        raise NotImplementedError

    async def close(self) -> None:
        """Release the link. Must not raise; called on every failure."""

    async def execute(self, cmd: Command) -> None:
        """Carry out a command the safety guard has passed."""
        raise NotImplementedError(f"{type(self).__name__} takes no commands")

    def current(self, action: str) -> float | None:
        """The machine's present value of what ``action`` commands, if known."""
        return None

    def status(self) -> dict[str, Any]:
        """Extra fields for ``lathectl status``."""
        return {}

    def mark_data(self) -> None:
        self.last_data_t = time.time()
