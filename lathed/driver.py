"""The base of every machine and sensor driver.

A driver's constructor only reads and validates its config table (no I/O),
so ``lathed --check-config`` can build every driver without touching the
plant. The supervisor then runs ``connect()`` and ``run()`` in a supervised
task; any exception puts the driver in its safe state (``close()``, no
commands) and it is retried with capped backoff.
"""
from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Any, ClassVar

from lathed.bus import Block, Bus, Message, Sample
from lathed.config import Section
from lathed.plausible import Plausibility

if TYPE_CHECKING:
    import structlog

    from lathed.command import Command

class LinkDown(ConnectionError):
    """A link or device that is down (a sensor unplugged, an audio server gone): the driver's
    state, not a bug, so status and log say its message alone, without type or source line."""


REPORT_EVERY_S = 60.0    # an implausible value is logged and recorded at most this often per quantity and reason


class GatedBus:
    """The bus as a driver sees it: every value is checked for being finite and
    physically plausible (lathed.plausible) before it is published, so no
    analyzer, machine model or guard reference ever holds one that is not.
    ``publish`` says whether the value went out; a refused one is counted in
    status, logged and recorded (rate-limited), never silently dropped."""

    def __init__(self, bus: Bus, plausible: Plausibility, log, record, clock=time.monotonic):
        self._bus, self.plausible, self._log, self._record, self._clock = bus, plausible, log, record, clock
        self._reported: dict[tuple[str, str], tuple[float, int]] = {}   # (quantity, reason) -> (t, suppressed)

    def publish(self, msg: Message) -> bool:
        if isinstance(msg, Sample):
            bad = self.plausible.check(msg.quantity, msg.unit, msg.value, msg.t)
            value = msg.value
        elif isinstance(msg, Block):
            # a device's rows come with their extremes, reduced for all channels at once
            rows = msg.rows
            bad = self.plausible.check_block(msg.quantity, "m/s²" if msg.quantity == "acceleration" else "",
                                             msg.data, msg.rate_hz, msg.rpm,
                                             None if rows is None else rows.extremes(msg.row, msg.data))
            value = None
        else:
            bad = None
        if bad is None:
            self._bus.publish(msg)
            return True
        self.report(msg.quantity, value, *bad)
        return False

    def report(self, quantity: str, value, reason: str, why: str) -> None:
        """Log and record a refused value, at most once per REPORT_EVERY_S per quantity and reason."""
        now = self._clock()
        last, suppressed = self._reported.get((quantity, reason), (None, 0))
        if last is not None and now - last < REPORT_EVERY_S:
            self._reported[(quantity, reason)] = (last, suppressed + 1)
            return
        self._reported[(quantity, reason)] = (now, 0)
        self._log.warning("implausible_value", quantity=quantity, reason=reason, why=why,
                          suppressed_since_last=suppressed)
        self._record("implausible_value", {"quantity": quantity, "value": value if value is None or
                                           math.isfinite(value) else repr(value), "reason": reason, "why": why,
                                           "suppressed_since_last": suppressed})

    def forget(self, source: str, quantity: str) -> None:
        self.plausible.forget(quantity)
        self._bus.forget(source, quantity)

    def link_lost(self) -> None:
        """The driver's link failed: the time until it is back vouches for no rate of change."""
        self.plausible.link_lost()

    def __getattr__(self, name: str):
        return getattr(self._bus, name)


class DriverContext:
    """What the supervisor hands a driver: the (gated) bus, a logger and the store."""

    def __init__(self, bus: Bus, log: structlog.typing.FilteringBoundLogger, record,
                 plausible: Plausibility | None = None):
        self.bus = GatedBus(bus, plausible or Plausibility(), log, record)
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
        # bounds of what a peer may plausibly send ([<table>.plausible]), checked by the framework
        self.plausible = Plausibility.from_section(section.getsection("plausible", required=False))
        # a machine's nameplate ([machine.NAME.identification]), for plant systems (lathed-opcua)
        self.identification: dict[str, Any] = {}
        if self.role == "machine":
            ident = section.getsection("identification", required=False)
            for key in ("manufacturer", "model", "serial_number"):
                if key in ident:
                    self.identification[key] = ident.getstr(key)
            if "year_of_construction" in ident:
                self.identification["year_of_construction"] = ident.getint("year_of_construction", minval=1900,
                                                                           maxval=2200)
            ident.check_unused()

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

    async def identify(self) -> dict[str, Any] | None:
        """What the peer on the link just opened says it is, under the keys of
        [identification] (serial_number, model, manufacturer), read from the peer itself
        (an identity register, the agent's device description); None where the protocol or
        the config gives no way to ask. Called after every ``connect()``: a peer that says it
        is another machine is refused as a link failure, and a machine whose peer is not
        confirmed to be the configured one (serial_number) takes no command."""
        return None

    def released(self, action: str) -> float | None:
        """The value ``action`` goes back to when lathed is done with it, read from the machine:
        what its program runs without lathed, where a command of lathed's holds beyond the cut
        (a spindle override); None where nothing of lathed's holds. The guard takes a command
        of this value as a release (bounded by the range, not the step or pace)."""
        return None

    def runs_at(self, cmd: Command) -> tuple[float, str] | None:
        """(the speed the machine will run for ``cmd``, why it differs from its value), where the
        machine scales what is written (the operator's override); None: it runs the value."""
        return None

    def interlock(self, cmd: Command) -> str | None:
        """Why the machine must not take ``cmd`` now, from its own state (the safety guard
        refuses it then); None: nothing the driver knows of stands against it."""
        return None

    def quantities(self) -> frozenset[str] | None:
        """Every quantity it can publish as a sample, where its config fixes them (a register
        map), so ``watch`` can refuse one that would never come; None: any may appear."""
        return None

    def status(self) -> dict[str, Any]:
        """Extra fields for ``lathectl status``."""
        return {}

    def listens(self) -> dict[str, tuple[str, str]]:
        """Instances whose bus samples this driver taps (``ctx.bus.tap``), each with the
        table and key of its config that names it: the supervisor refuses a config that
        names one not configured (a tap on it would wait forever)."""
        return {}

    def mark_data(self) -> None:
        self.last_data_t = time.time()
