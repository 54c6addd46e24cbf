"""Log lines a flood could multiply, at most one per key per period, with counts.

A client that connects 5,000 times a second must not write 5,000 log lines a
second (issue 35: 106 MB of accept errors in 40 s). ``Limited`` is for our own
structlog events; ``LimitFilter`` does the same for a library's standard-library
logger (aiohttp's "Error handling request", asyncio's accept errors). The first
line of a kind goes out at once; the next after ``every`` seconds, saying how
many like it were held back meanwhile.
"""
from __future__ import annotations

import logging
import time
from collections import OrderedDict
from typing import Any, Callable

KEYS_KEPT = 1000       # kinds remembered; the oldest is forgotten (a flood of distinct keys stays bounded)


class _Window:
    def __init__(self, every: float, clock: Callable[[], float]):
        self.every, self.clock = every, clock
        self.keys: OrderedDict[Any, list] = OrderedDict()     # key -> [last line's time, held back since]

    def admit(self, key: Any) -> int | None:
        """None: hold this one back; else the number held back since the last line of this key."""
        now = self.clock()
        slot = self.keys.get(key)
        if slot is not None and now - slot[0] < self.every:
            slot[1] += 1
            return None
        held = slot[1] if slot is not None else 0
        self.keys[key] = [now, 0]
        self.keys.move_to_end(key)
        while len(self.keys) > KEYS_KEPT:
            self.keys.popitem(last=False)
        return held

    def pending(self) -> list[tuple[Any, int]]:
        return [(k, s[1]) for k, s in self.keys.items() if s[1]]


class Limited:
    """``lim.warning("login_failed", key=client, **fields)``: logged, or counted into the next line."""

    def __init__(self, logger: Any, every: float = 10.0, clock: Callable[[], float] = time.monotonic):
        self.log = logger
        self._w = _Window(every, clock)

    def _emit(self, level: str, event: str, key: Any = None, **kw: Any) -> bool:
        held = self._w.admit((level, event, key))
        if held is None:
            return False
        if held:
            kw["held_back"] = held
        getattr(self.log, level)(event, **kw)
        return True

    def info(self, event: str, key: Any = None, **kw: Any) -> bool:
        return self._emit("info", event, key, **kw)

    def warning(self, event: str, key: Any = None, **kw: Any) -> bool:
        return self._emit("warning", event, key, **kw)

    def error(self, event: str, key: Any = None, **kw: Any) -> bool:
        return self._emit("error", event, key, **kw)

    def flush(self) -> None:
        """At a stop: the counts still held back, one line each."""
        for (level, event, key), n in self._w.pending():
            getattr(self.log, level)(event, held_back=n, **({"key": key} if key is not None else {}))
        self._w.keys.clear()


class LimitFilter(logging.Filter):
    """On a library's logger: one record per (logger, message template) per ``every`` seconds."""

    def __init__(self, every: float = 10.0, clock: Callable[[], float] = time.monotonic):
        super().__init__()
        self._w = _Window(every, clock)

    def filter(self, record: logging.LogRecord) -> bool:
        held = self._w.admit((record.name, record.msg if isinstance(record.msg, str) else type(record.msg)))
        if held is None:
            return False
        if held:
            record.msg = f"{record.msg} ({held} more like this held back in the last {self._w.every:g} s)"
        return True


def limit_library_logs(names: tuple[str, ...] = ("aiohttp.server", "aiohttp.access", "aiohttp.web", "asyncio"),
                       every: float = 10.0) -> LimitFilter:
    """Rate-limit these standard-library loggers (their handlers are the root's: lathed.log)."""
    f = LimitFilter(every)
    for name in names:
        lg = logging.getLogger(name)
        lg.filters = [x for x in lg.filters if not isinstance(x, LimitFilter)]
        lg.addFilter(f)
    return f
