"""Event-loop lag: how late a task that asks to wake every 50 ms really wakes.

A blocked loop (a handler doing heavy work in place, a flood of requests)
delays every timer: vibration blocks, thermal writes, status replies. The
daemon runs ``watch()`` and shows ``LagStats.summary()`` in ``status``
(``daemon.loop_lag_ms``): p50/p99/max over the last ``window_s``, and a
histogram since start, so a benchmark can take the exact distribution over
any interval by subtracting two of them.
"""
from __future__ import annotations

import asyncio
import bisect
import math
from collections import deque

INTERVAL_S = 0.05
WINDOW_S = 10.0
# histogram bin upper edges, ms; the last bin is everything above the last edge
EDGES_MS = (1, 2, 5, 10, 20, 30, 50, 75, 100, 200, 500, 1000, 2000, 5000, 10000, 30000)
MAX_BACKFILL = 100_000    # swallowed wakes counted per stall (83 min at 50 ms)


class LagStats:
    """Wake-up delays (numeric only): a rolling window and a histogram since start."""

    def __init__(self, window_s: float = WINDOW_S):
        self.window_s = window_s
        self._recent: deque[tuple[float, float]] = deque()   # (t, lag_ms)
        self.counts = [0] * (len(EDGES_MS) + 1)
        self.n = 0
        self.max_ms = 0.0

    def add(self, t: float, lag_ms: float, interval_ms: float = 0.0) -> None:
        """One wake ``lag_ms`` late. With the wake-up interval, a stall also
        counts the wakes it swallowed (each as late as it would have been):
        otherwise a 20 s freeze weighs as one sample among thousands."""
        self._one(t, lag_ms)
        if interval_ms > 0:
            missed = lag_ms - interval_ms
            for _ in range(MAX_BACKFILL):
                if missed < interval_ms:
                    break
                self._one(t, missed)
                missed -= interval_ms
        while self._recent and self._recent[0][0] < t - self.window_s:
            self._recent.popleft()

    def _one(self, t: float, lag_ms: float) -> None:
        self._recent.append((t, lag_ms))
        self.counts[bisect.bisect_left(EDGES_MS, lag_ms)] += 1
        self.n += 1
        self.max_ms = max(self.max_ms, lag_ms)

    def summary(self) -> dict:
        lags = sorted(v for _, v in self._recent)
        return {"window_s": self.window_s, "n": len(lags), "p50": _pct(lags, 50), "p99": _pct(lags, 99),
                "max": round(lags[-1], 3) if lags else None,
                "since_start": {"n": self.n, "max": round(self.max_ms, 3), "edges_ms": list(EDGES_MS),
                                "counts": list(self.counts)}}


def _pct(xs: list[float], p: float) -> float | None:
    if not xs:
        return None
    return round(xs[min(len(xs) - 1, math.ceil(p / 100 * len(xs)) - 1)], 3)


async def watch(stats: LagStats, interval: float = INTERVAL_S) -> None:
    loop = asyncio.get_running_loop()
    while True:
        due = loop.time() + interval
        await asyncio.sleep(interval)
        now = loop.time()
        stats.add(now, max(0.0, (now - due) * 1000.0), interval * 1000.0)
