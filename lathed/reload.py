"""What a configuration reload (SIGHUP) may change in a running daemon.

Live: ``[daemon] log_level`` and ``stop_wait``, ``[store] keep_days`` and ``prune_every``, a
machine's ``[*.limits]``, and an analyzer's keys it lists in ``LIVE_KEYS``
(applied by its ``reconfigure(section)``). Anything else that differs — a
machine, sensor or analyzer added, removed or of another plugin, a driver's
address, the simulator — is structural: the whole reload is refused, naming
each with "(restart lathed to apply)", and the running configuration stays as it is.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from lathed.config import Config

LIVE_DAEMON = {"log_level", "stop_wait"}
RESTART = "(restart lathed to apply)"   # what the refusal of a structural change asks of the reader
LIVE_STORE = {"keep_days", "prune_every"}


@dataclass
class Changes:
    daemon: dict[str, Any] = field(default_factory=dict)
    store: dict[str, Any] = field(default_factory=dict)
    limits: list[str] = field(default_factory=list)      # machines whose limits changed
    analyzers: list[str] = field(default_factory=list)   # analyzers whose live keys changed
    refused: list[str] = field(default_factory=list)     # structural: each named

    def summary(self) -> list[str]:
        return ([f"[daemon] {k}" for k in self.daemon] + [f"[store] {k}" for k in self.store]
                + [f"[machine.{m}.limits]" for m in self.limits] + [f"[analyzer.{a}]" for a in self.analyzers])


def _changed(old: dict, new: dict) -> list[str]:
    return sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))


def diff(old: Config, new: Config, live_keys: dict[str, set[str]]) -> Changes:
    """``live_keys``: analyzer name -> the keys of its table it can take live."""
    ch = Changes()
    for table, live, out in (("daemon", LIVE_DAEMON, ch.daemon), ("store", LIVE_STORE, ch.store)):
        o, n = getattr(old, table).raw(), getattr(new, table).raw()
        for k in _changed(o, n):
            if k in live:
                out[k] = n.get(k)
            else:
                ch.refused.append(f"[{table}] {k} changed {RESTART}")
    if (old.simulator and old.simulator.raw()) != (new.simulator and new.simulator.raw()):
        ch.refused.append(f"[simulator] changed {RESTART}")
    olds = {(i.category, i.name): i for i in old.instances}
    news = {(i.category, i.name): i for i in new.instances}
    for key in sorted(set(olds) - set(news)):
        ch.refused.append(f"[{key[0]}.{key[1]}] removed {RESTART}")
    for key in sorted(set(news) - set(olds)):
        ch.refused.append(f"[{key[0]}.{key[1]}] added {RESTART}")
    for key in sorted(set(olds) & set(news)):
        o, n = olds[key], news[key]
        where = f"[{key[0]}.{key[1]}]"
        if o.plugin != n.plugin:
            ch.refused.append(f"{where} plugin changed from {o.plugin!r} to {n.plugin!r} {RESTART}")
            continue
        fw = _changed(o.framework.raw(), n.framework.raw())
        if "limits" in fw and key[0] == "machine":
            ch.limits.append(key[1])
        ch.refused += [f"{where} {k} changed {RESTART}" for k in fw if k != "limits"]
        sec = _changed(o.section.raw(), n.section.raw())
        live = live_keys.get(key[1], set()) if key[0] == "analyzer" else set()
        if any(k in live for k in sec):
            ch.analyzers.append(key[1])
        ch.refused += [f"{where} {k} changed {RESTART}" for k in sec if k not in live]
    return ch
