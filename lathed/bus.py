"""The in-process sample bus: drivers publish, analyzers subscribe.

Publishing never blocks a driver. Each subscriber has its own bounded queue;
when an analyzer falls behind, what it missed is counted and shown in status
(never silently dropped).
"""
from __future__ import annotations

import asyncio
from collections import defaultdict, deque
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Sample:
    """One scalar reading: a temperature, a spindle speed, an axis position."""
    source: str          # instance name of the driver
    quantity: str        # e.g. "t_front_bearing", "spindle_rpm"
    value: float
    unit: str
    t: float             # wall-clock time of the measurement (s since epoch)


@dataclass(frozen=True)
class Block:
    """A block of a sampled waveform (vibration)."""
    source: str
    quantity: str        # "acceleration"
    rate_hz: float
    t0: float            # time of the first sample (s since epoch)
    seq: int             # index of the first sample in the stream
    data: np.ndarray
    rpm: float | None = None   # spindle speed the stream reported for this block


Message = Sample | Block


class Subscription:
    """One subscriber's bounded FIFO of messages: a deque and a waiter, not an
    asyncio.Queue, whose put and get are a handful of method calls each (the
    default config publishes ~1000 messages a second to its analyzers)."""

    def __init__(self, sources: frozenset[str], maxsize: int = 1024):
        self.sources = sources
        self.maxsize = maxsize
        self.dropped = 0
        self._items: deque[Message] = deque()
        self._waiter: asyncio.Future | None = None

    def put(self, msg: Message) -> None:
        """Queue a message, or count it dropped when ``maxsize`` wait already."""
        if len(self._items) >= self.maxsize:
            self.dropped += 1
            return
        self._items.append(msg)
        w = self._waiter
        if w is not None and not w.done():
            w.set_result(None)

    async def get(self) -> Message:
        while not self._items:
            # one consumer per subscription; a cancelled wait takes nothing
            self._waiter = asyncio.get_running_loop().create_future()
            try:
                await self._waiter
            finally:
                self._waiter = None
        return self._items.popleft()


class Bus:
    def __init__(self) -> None:
        self._subs: dict[str, list[Subscription]] = defaultdict(list)
        self.latest: dict[tuple[str, str], Sample] = {}
        self.published = 0

    def subscribe(self, *sources: str, maxsize: int = 1024) -> Subscription:
        sub = Subscription(frozenset(sources), maxsize)
        for s in sources:
            self._subs[s].append(sub)
        return sub

    def unsubscribe(self, sub: Subscription) -> None:
        for s in sub.sources:
            if sub in self._subs.get(s, []):
                self._subs[s].remove(sub)

    def publish(self, msg: Message) -> None:
        self.published += 1
        if isinstance(msg, Sample):
            self.latest[(msg.source, msg.quantity)] = msg
        for sub in self._subs.get(msg.source, ()):
            sub.put(msg)

    def forget(self, source: str, quantity: str) -> None:
        """A quantity its source no longer has (a sensor taken off the line)."""
        self.latest.pop((source, quantity), None)

    def latest_of(self, source: str) -> dict[str, Sample]:
        return {q: s for (src, q), s in self.latest.items() if src == source}

    def snapshot(self, source: str) -> dict[str, Any]:
        return {q: s.value for q, s in self.latest_of(source).items()}
