"""The in-process sample bus: drivers publish, analyzers subscribe.

Publishing never blocks a driver. Each subscriber has its own bounded queue;
when an analyzer falls behind, what it missed is counted, per subscriber, in
``stats()`` (``lathectl status``), and its first miss is logged: never
silently dropped.

A tap is the other way to listen: a plain function the bus calls with each
message of a source as it is published, for work too small to deserve a task
and a queue (the push hub's rings: a reference kept per block). A tap must
return at once; one that raises is logged, removed and counted
(``tap_failures``), and publishing goes on.
"""
from __future__ import annotations

import asyncio
from collections import defaultdict, deque
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
import structlog

from lathed.analysis.device_rows import DeviceRows

log = structlog.get_logger("lathed.bus")


@dataclass(frozen=True)
class Sample:
    """One scalar reading: a temperature, a spindle speed, an axis position."""
    source: str          # instance name of the driver
    quantity: str        # e.g. "t_front_bearing", "spindle_rpm"
    value: float
    unit: str
    t: float             # wall-clock time of the measurement (s since epoch)

    def __init__(self, source: str, quantity: str, value: float, unit: str, t: float) -> None:
        # frozen all the same (no __setattr__); one dict update, not five object.__setattr__
        # calls: half the cost of the generated __init__, and thousands are made a second
        self.__dict__.update(source=source, quantity=quantity, value=value, unit=unit, t=t)


@dataclass(frozen=True)
class Block:
    """A block of a sampled waveform (vibration). A sensor that conditions several channels
    of one device together hands the block's ``rows`` (lathed.analysis.device_rows): ``data``
    is ``rows.ys[row]``, and the analyzers of the device's channels may work on all of them
    at once. None (a stream of its own): each analyzer works on ``data`` alone."""
    source: str
    quantity: str        # "acceleration"
    rate_hz: float
    t0: float            # time of the first sample (s since epoch)
    seq: int             # index of the first sample in the stream
    data: np.ndarray
    rpm: float | None = None   # spindle speed the stream reported for this block
    rows: DeviceRows | None = field(default=None, compare=False, repr=False)
    row: int = field(default=0, compare=False, repr=False)

    def __init__(self, source: str, quantity: str, rate_hz: float, t0: float, seq: int, data: np.ndarray,
                 rpm: float | None = None, rows: DeviceRows | None = None, row: int = 0) -> None:
        self.__dict__.update(source=source, quantity=quantity, rate_hz=rate_hz, t0=t0, seq=seq, data=data, rpm=rpm,
                             rows=rows, row=row)


Message = Sample | Block
Tap = Callable[[Message], None]


class Subscription:
    """One subscriber's bounded FIFO of messages: a deque and a waiter, not an
    asyncio.Queue, whose put and get are a handful of method calls each (the
    default config publishes ~1000 messages a second to its analyzers)."""

    def __init__(self, sources: frozenset[str], maxsize: int = 1024, name: str | None = None):
        self.sources = sources
        self.maxsize = maxsize
        self.name = name or "+".join(sorted(sources))    # who reads it, for status and the log
        self.dropped = 0
        self._items: deque[Message] = deque()
        self._waiter: asyncio.Future | None = None

    def put(self, msg: Message) -> None:
        """Queue a message, or count it dropped when ``maxsize`` wait already."""
        if len(self._items) >= self.maxsize:
            if not self.dropped:   # once: a subscriber behind stays behind for a while
                log.warning("bus_subscriber_behind", subscriber=self.name, sources=sorted(self.sources),
                            maxsize=self.maxsize)
            self.dropped += 1
            return
        self._items.append(msg)
        w = self._waiter
        if w is not None and not w.done():
            w.set_result(None)

    async def _wait(self) -> None:
        while not self._items:
            # one consumer per subscription; a cancelled wait takes nothing
            self._waiter = asyncio.get_running_loop().create_future()
            try:
                await self._waiter
            finally:
                self._waiter = None

    async def get(self) -> Message:
        if not self._items:
            await self._wait()
        return self._items.popleft()

    async def get_all(self) -> list[Message]:
        """Every message waiting (at least one), in order: one wait, not one coroutine and
        call a message, for a reader that handles each as it comes (the chatter analyzer:
        a block and the machine's registers every 20 ms, a channel)."""
        if not self._items:
            await self._wait()
        items = list(self._items)
        self._items.clear()
        return items


class Bus:
    def __init__(self) -> None:
        self._subs: dict[str, list[Subscription]] = defaultdict(list)
        # subscriptions that take only the Blocks of a source (an analyzer of the waveform,
        # not of its rms): a queue's put and get, and a dispatch, fewer per block
        self._block_subs: dict[str, list[Subscription]] = defaultdict(list)
        self.latest: dict[tuple[str, str], Sample] = {}
        self.published = 0
        self._taps: dict[str, list[Tap]] = {}
        self.tap_failures = 0
        self.last_tap_failure: str | None = None
        self._dropped_gone: dict[str, int] = defaultdict(int)   # by unsubscribed subscriptions, by name

    def subscribe(self, *sources: str, maxsize: int = 1024, name: str | None = None,
                  blocks_only: tuple[str, ...] = ()) -> Subscription:
        """Every message of ``sources``; of those also in ``blocks_only``, their Blocks alone."""
        sub = Subscription(frozenset(sources), maxsize, name)
        for s in sources:
            (self._block_subs if s in blocks_only else self._subs)[s].append(sub)
        return sub

    def unsubscribe(self, sub: Subscription) -> None:
        subscribed = False
        for s in sub.sources:
            for subs in (self._subs, self._block_subs):
                if sub in subs.get(s, []):
                    subs[s].remove(sub)
                    subscribed = True
        if subscribed and sub.dropped:    # a restarted analyzer subscribes again: its count goes on
            self._dropped_gone[sub.name] += sub.dropped

    def tap(self, source: str, fn: Tap) -> None:
        """Call ``fn(msg)`` with each message ``source`` publishes, in publish."""
        self._taps.setdefault(source, []).append(fn)

    def untap(self, source: str, fn: Tap) -> None:
        taps = self._taps.get(source)
        if taps and fn in taps:
            taps.remove(fn)
            if not taps:
                del self._taps[source]

    def publish(self, msg: Message) -> None:
        self.published += 1
        if isinstance(msg, Sample):
            self.latest[(msg.source, msg.quantity)] = msg
        else:
            for sub in self._block_subs.get(msg.source, ()):
                sub.put(msg)
        for sub in self._subs.get(msg.source, ()):
            sub.put(msg)
        taps = self._taps.get(msg.source)
        if taps:
            failed = None
            for fn in taps:
                try:
                    fn(msg)
                except Exception as e:   # a listener's bug is its own: the driver keeps publishing
                    failed = (failed or []) + [(fn, e)]
            for fn, e in failed or ():
                self.untap(msg.source, fn)
                self.tap_failures += 1
                self.last_tap_failure = f"{msg.source}: {getattr(fn, '__qualname__', fn)}: {type(e).__name__}: {e}"
                log.error("bus_tap_failed", source=msg.source, tap=getattr(fn, "__qualname__", repr(fn)),
                          error=f"{type(e).__name__}: {e}", removed=True)

    def stats(self) -> dict:
        dropped = dict(self._dropped_gone)
        for sub in {id(sub): sub for by in (self._subs, self._block_subs) for subs in by.values()
                    for sub in subs}.values():
            if sub.dropped:
                dropped[sub.name] = dropped.get(sub.name, 0) + sub.dropped
        return {"published": self.published, "taps": sum(map(len, self._taps.values())),
                "tap_failures": self.tap_failures, "last_tap_failure": self.last_tap_failure,
                "dropped": dropped}

    def forget(self, source: str, quantity: str) -> None:
        """A quantity its source no longer has (a sensor taken off the line)."""
        self.latest.pop((source, quantity), None)

    def latest_of(self, source: str) -> dict[str, Sample]:
        return {q: s for (src, q), s in self.latest.items() if src == source}

    def snapshot(self, source: str) -> dict[str, Any]:
        return {q: s.value for q, s in self.latest_of(source).items()}
