"""The in-process sample bus: drivers publish, analyzers subscribe.

Publishing never blocks a driver. Each subscriber has its own bounded queue;
when an analyzer falls behind, what it missed is counted and shown in status
(never silently dropped).
"""
from __future__ import annotations

import asyncio
from collections import defaultdict
from dataclasses import dataclass, field
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


@dataclass
class Subscription:
    sources: frozenset[str]
    queue: asyncio.Queue = field(default_factory=lambda: asyncio.Queue(maxsize=1024))
    dropped: int = 0

    async def get(self) -> Message:
        return await self.queue.get()


class Bus:
    def __init__(self) -> None:
        self._subs: dict[str, list[Subscription]] = defaultdict(list)
        self.latest: dict[tuple[str, str], Sample] = {}
        self.published = 0

    def subscribe(self, *sources: str, maxsize: int = 1024) -> Subscription:
        sub = Subscription(frozenset(sources), asyncio.Queue(maxsize=maxsize))
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
            try:
                sub.queue.put_nowait(msg)
            except asyncio.QueueFull:
                sub.dropped += 1

    def forget(self, source: str, quantity: str) -> None:
        """A quantity its source no longer has (a sensor taken off the line)."""
        self.latest.pop((source, quantity), None)

    def latest_of(self, source: str) -> dict[str, Sample]:
        return {q: s for (src, q), s in self.latest.items() if src == source}

    def snapshot(self, source: str) -> dict[str, Any]:
        return {q: s.value for q, s in self.latest_of(source).items()}
