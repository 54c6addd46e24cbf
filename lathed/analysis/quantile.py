"""A sliding-window quantile, kept sorted as values come (the chatter detector's and the cut
state's running baselines)."""
from __future__ import annotations

import math
from bisect import bisect_left, insort
from collections import deque


class SlidingQuantile:
    """The ``q`` quantile of the last ``size`` values pushed, equal to
    ``np.quantile(values, q)`` (its default, linear method) bit for bit.

    The values are kept sorted as they come (a bisect and a shift of at most
    ``size``), so a new quantile costs a few float operations rather than
    np.quantile's list conversion and partition: ~1 us, not tens of us, at every frame.
    A NaN is counted, not sorted: while one is in the window the quantile is
    NaN, as numpy's is."""

    def __init__(self, q: float, size: int) -> None:
        if not 0.0 <= q <= 1.0:
            raise ValueError(f"quantile must be in [0, 1], got {q}")
        if size < 1:
            raise ValueError(f"window must hold at least 1 value, got {size}")
        self.q, self.size = float(q), int(size)
        self._order: deque[float] = deque()
        self._sorted: list[float] = []
        self._nans = 0

    def __len__(self) -> int:
        return len(self._order)

    def clear(self) -> None:
        self._order.clear()
        self._sorted.clear()
        self._nans = 0

    def push(self, x: float) -> None:
        x = float(x)
        order = self._order
        order.append(x)
        if x != x:                      # NaN (math.isnan, without the call)
            self._nans += 1
        else:
            insort(self._sorted, x)
        if len(order) > self.size:
            old = order.popleft()
            if old != old:
                self._nans -= 1
            else:
                del self._sorted[bisect_left(self._sorted, old)]

    def value(self) -> float:
        if not self._order:
            raise ValueError("quantile of no values")
        if self._nans:
            return math.nan
        s = self._sorted
        # numpy's linear method, operation for operation (numpy.lib._function_base_impl:
        # virtual index (n-1) q, then _lerp's two formulas either side of 0.5)
        virtual = (len(s) - 1) * self.q
        lo = math.floor(virtual)
        hi = min(lo + 1, len(s) - 1)
        t = virtual - lo
        a, b = s[lo], s[hi]
        diff = b - a
        return b - diff * (1 - t) if t >= 0.5 else a + diff * t
