"""Whether an analyzer sees its sensor: blind while the sensor's driver is not connected
(a device gone, a link retrying) or has sent no block for ``stale_s``. An analyzer that is
blind says so instead of reporting a calm signal it does not have (docs/chatter.md).
"""
from __future__ import annotations

CHECK_EVERY_S = 0.25     # how often an analyzer looks at its sensor's state
STALE_S = 2.0            # a sensor connected but silent this long: blind all the same


class Sight:
    def __init__(self, source: str, stale_s: float = STALE_S) -> None:
        self.source, self.stale_s = source, stale_s
        self.blind: str | None = f"{source}: no block yet"    # why, while blind
        self.since: float | None = None                         # monotonic time it went blind
        self.seen = False                                       # a block ever came
        self._last: float | None = None

    def block(self, now: float) -> bool:
        """A block came at ``now``; True if that ends a blindness after sight (it came back)."""
        self._last = now
        back = self.blind is not None and self.seen
        self.blind, self.seen = None, True
        return back

    def check(self, status: dict | None, now: float) -> bool:
        """The sensor's driver state (Supervisor.machine_status); True if it just went blind
        after sight (the moment to say so)."""
        why = None
        if status is not None and status.get("state") != "connected":
            err = status.get("error")
            # an error: it failed, and is being tried again (connecting or waiting to)
            why = f"{self.source}: {err}, retrying" if err else f"{self.source} {status.get('describe')}"
        elif self._last is not None and now - self._last > self.stale_s:
            why = f"{self.source}: no signal for {now - self._last:.1f} s"
        if why is None:
            return False
        went = self.blind is None and self.seen
        if went:
            self.since = now
        self.blind = why
        return went
