"""The base of every analyzer: reads the bus, decides, asks for commands.

Analyzers never talk to hardware: every command goes through
``ctx.command()``, i.e. the safety guard and the machine's driver.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Awaitable, Callable, ClassVar

from lathed.config import Section

if TYPE_CHECKING:
    import structlog

    from lathed.bus import Bus
    from lathed.command import Command


class AnalyzerContext:
    def __init__(self, bus: Bus, log: structlog.typing.FilteringBoundLogger, record,
                 command: Callable[[Command], Awaitable[dict]],
                 register_control: Callable[[str, Callable[[dict], Awaitable[Any]]], None],
                 store, machine_status: Callable[[str], dict | None], config_dir, plugins=None,
                 release: Callable[[str, str, str], Awaitable[dict | None]] | None = None,
                 interlock: Callable[[str, str], str | None] | None = None):
        self.bus = bus
        self.log = log
        self.record = record                  # record(kind, payload) -> None
        self.command = command                # await command(Command) -> {"sent": bool, "reason": ...}
        self.register_control = register_control  # expose a control-socket command
        self.store = store
        self.machine_status = machine_status
        self.config_dir = config_dir
        self.plugins = plugins                # the PluginLoader: plugin-supplied detectors, candidates
        # await release(machine, action, source): the action back to what the machine's program
        # sets, where a command's effect outlasts the cut (a spindle override); None: nothing to do
        self.release = release or _no_release
        # interlock(machine, action): why the machine takes no such command now (a thread being
        # cut), else None; an analysis asks so as not to ask in vain (the guard refuses anyway)
        self.interlock = interlock or (lambda machine, action: None)


async def _no_release(machine: str, action: str, source: str) -> None:
    return None


class Analyzer:
    """Every method has a default: an analyzer overrides what it uses (docs/plugins.md)."""

    # it forwards the store's records elsewhere (a sink): retention waits for its progress
    forwards_records: ClassVar[bool] = False
    # keys of its table a configuration reload (SIGHUP) may change without a restart
    LIVE_KEYS: ClassVar[frozenset[str]] = frozenset()
    # the machine it works on, if one (lathectl status)
    machine: str | None = None

    def __init__(self, name: str, section: Section):
        self.name = name
        self.ctx: AnalyzerContext | None = None

    def inputs(self) -> list[str]:
        """Instance names of the drivers this analyzer reads (checked at start)."""
        return []

    def machines(self) -> list[str]:
        """Instance names of the machines this analyzer may command."""
        return []

    def refers(self) -> dict[str, tuple[str, str, str | None]]:
        """Keys of this analyzer's table that name another instance: key -> (name, category,
        need). Category is "analyzer", "machine" or "sensor"; need is, for a sensor, the kind
        it must be ("accelerometer"; a plugin sensor of the unspecified kind "sensor" passes),
        for a machine an action it must take ("spindle_rpm"). The supervisor refuses a key
        naming no such instance, naming the key (inputs() and machines() only say it exists)."""
        return {}

    def recording_context(self, source: str) -> dict[str, Any] | None:
        """What an analyst needs beside a recording of sensor ``source`` (``lathectl record``),
        if this analyzer reads it: its machine (whose speed and tool are recorded too), tool,
        material, detector and its parameters. It must publish ``cutting`` (1/0) for a
        recording of the next N cuts. None: it does not read ``source``."""
        return None

    def offset_pace(self) -> tuple[float, float] | None:
        """(µm a write, µm/s) at most, for an analyzer that phases in an offset: the
        supervisor refuses a config whose machine's guard would refuse such writes."""
        return None

    def live_view(self) -> dict | None:
        """What the operator page and lathectl's live views draw for it (a snapshot, pushed
        to subscribers); None: nothing to draw."""
        return None

    async def run(self) -> None:
        """Analyse until cancelled; an exception is reported and the analyzer restarted."""
        raise NotImplementedError

    def status(self) -> dict[str, Any]:
        return {}
