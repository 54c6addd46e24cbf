"""Whether the tool is in the cut, from every source a machine offers: the one owner of the cut
state (docs/chatter.md, "What a machine's configuration must provide").

``CutState`` takes the machine's samples (the cutting-feed signal, the axes, the depth register,
the spindle load) and the accelerometer's blocks, ORs the sources the configuration names
(lathed.analysis.cut.sources: the first to see the chip starts the cut, it ends when none does),
holds a dwell open while the axes stand, tells the chip's contact in a cut the feed started in
air, and says which of a block's samples are the cut's and where an impulse (a release, a knock,
a dwell's join) lies in them.  It returns what happened as ``CutEvent``s; the chatter analyzer
publishes them (``cutting``, ``dwell``, ``cut_contact``) and suppression and records read those.
Pure: no bus, no clock of its own, no asyncio.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lathed.analysis.cut.sources import SOURCES, FeedStop, LoadCutDetector, VibrationCutDetector
from lathed.analysis.device_rows import DeviceRows

# A vibration entry in a running cut whose frame jumps this much over the two before is an
# impulse (the tool's release, a knock), not chatter: the detector does not count it.
IMPULSE_JUMP = 2.0
# A polled machine source's "on" older than this many of its polls (and this many seconds), with
# the accelerometer in air, holds the cut no longer: a stalled poll would merge two passes into one.
# A driver that publishes only changes is never judged so (its silence is no age).
STALE_POLLS = 3
STALE_MIN_S = 0.25


# the machine's quantities that are cut sources, by source name
MACHINE_SOURCES = {"cutting_feed": "feed", "depth_of_cut_mm": "depth", "spindle_load_pct": "load"}


@dataclass
class CutEvent:
    kind: str                 # "start", "contact", "dwell", "dwell_over" or "end"
    t: float                  # when (an end: when the chip was last seen)
    source: str               # what said so (a source, "axes" or "dwell_max")
    held: bool = False        # an end: the cut was held in a dwell when it ended


@dataclass
class BlockCut:
    """What one accelerometer block means for the cut: the events it brought, the samples the
    detector takes (None: not the cut's: air, a dwell), and an impulse's offset in them."""
    events: list[CutEvent]
    data: np.ndarray | None
    impulse_at: int | None = None


class CutState:
    """The cut state of one machine and its accelerometer (see the module's docstring).

    ``cut_from``: the sources, of lathed.analysis.cut.sources.SOURCES.  ``dwell_axes``: the
    axes' position registers (with "feed"): a dwell holds the cut while they stand, for at most
    ``dwell_max`` seconds."""

    def __init__(self, cut_from: list[str], dwell_axes: list[str] | None = None, dwell_max: float = 2.0,
                 load_margin_pct: float = 5.0, contact_ratio: float = 1.3) -> None:
        bad = [c for c in cut_from if c not in SOURCES]
        if bad or not cut_from:
            raise ValueError(f"expected a non-empty list of {', '.join(SOURCES)}; got {cut_from!r}")
        if dwell_axes and "feed" not in cut_from:
            raise ValueError('a dwell is told from the cutting-feed signal: needs "feed" in cut_from')
        self.cut_from = list(cut_from)
        self.dwell_max = float(dwell_max)
        self.feed_stop = FeedStop(list(dwell_axes)) if dwell_axes else None
        # the machine's quantities machine() reads; another does nothing but time a dwell
        self.quantities = frozenset({"cutting_feed", "depth_of_cut_mm", "spindle_load_pct", *(dwell_axes or ())})
        self.load_cut = LoadCutDetector(load_margin_pct)
        self.contact_ratio = contact_ratio
        self.vib_cut: VibrationCutDetector | None = None
        self.seen = {c: False for c in self.cut_from}
        self.cutting = False
        self.cut_by: str | None = None         # the source that started the cut
        self.chip_by: str | None = None        # what saw the chip in a cut the feed started
        self.held: float | None = None         # a dwell: when the chip was last seen, the cut held
        self._held_clock = "machine"           # whose time stamps ``held`` is on: "machine" or "block"
        self._rejoin = False                   # the dwell over: the detector's next samples join it
        # a dwell rejoined before every axis was read in the feed's poll: (held, source, t) until then
        self._rejoined: tuple[float, str, float] | None = None
        self.dwells = 0
        self._read: dict[str, tuple[float, float | None]] = {}   # machine source -> (received, poll interval)
        self._last: dict[str, float] = {}       # each machine quantity's last value ...
        self._polled = False                   # ... one repeated: the driver polls, silence is age
        self._air_at: float | None = None      # when the vibration last said air (block clock)
        self._feed_at = -math.inf              # the feed's last reading (machine clock)
        # held because the feed's poll went stale in air: a dwell or the pass's end, the next
        # poll tells (the axes where the feed left them, or elsewhere); the chip alone does not
        self._stale_hold = False

    # -- the machine's samples -----------------------------------------------------------
    def machine(self, quantity: str, value: float, t: float, rpm: float | None,
                now: float | None = None) -> list[CutEvent]:
        """A sample of the machine (``rpm``: its speed now, for the load's no-chip level); one
        not in ``quantities`` only times a held dwell (``held``). ``now``: when it was received,
        on the clock ``block``'s ``now`` is on (None: its age is not judged)."""
        ev: list[CutEvent] = []
        if now is not None:
            self._received(quantity, value, now)
        if quantity == "cutting_feed":
            # the feed read again: the hold is judged as any feed stop's (the axes read in its poll)
            self._stale_hold = False
            self._feed_at = max(self._feed_at, t)
            if self.feed_stop is not None:
                self.feed_stop.feed(value != 0, t)
            if "feed" in self.seen:
                self._source("feed", value != 0, t, ev)
        elif self.feed_stop is not None and quantity in self.feed_stop.axes:
            self.feed_stop.position(quantity, value, t)
            if self._rejoined is not None and (self.feed_stop.away or not self.feed_stop.resuming):
                held, name, at = self._rejoined
                self._rejoined = None
                if self.feed_stop.away:         # read after the feed's sample: the next pass after all
                    self._end(held, "axes", ev)
                    self._source(name, True, at, ev)
        elif quantity == "depth_of_cut_mm":
            if "depth" in self.seen:
                self._source("depth", value > 0, t, ev)
        elif quantity == "spindle_load_pct":
            if "load" in self.seen:
                self._source("load", self.load_cut.update(value, rpm), t, ev)
        self._dwell_over(t, "machine", ev)
        return ev

    def cutting_load(self, load_pct: float, rpm: float | None) -> float | None:
        """The load the chip takes (above the no-chip load), or None under the margin."""
        return self.load_cut.cutting_load(load_pct, rpm)

    # -- the accelerometer's blocks -------------------------------------------------------
    def block(self, data: np.ndarray, rate_hz: float, t0: float, rows: DeviceRows | None = None,
              row: int = 0, now: float | None = None) -> BlockCut:
        """A block of the accelerometer starting at ``t0``: the vibration source, the chip's
        contact, and which of its samples the detector takes. ``rows``, ``row``: the device
        block ``data`` is a row of (Block.rows), whose frames the cut states of its channels
        make together. ``now``: when it was received (machine()'s clock): a machine source
        gone stale while the vibration says air ends the cut."""
        ev: list[CutEvent] = []
        impulse = None
        self._dwell_over(t0, "block", ev)
        if "vibration" in self.seen or "feed" in self.seen:
            if self.vib_cut is None or self.vib_cut.rate != rate_hz:
                self.vib_cut = VibrationCutDetector(rate_hz, contact_ratio=self.contact_ratio)
            vib = self.vib_cut
            at = vib.process(data, rows, row)
            if (at is not None and vib.cutting and self.cutting and self.chip_by is not None
                    and self.held is None and vib.entry_jump >= IMPULSE_JUMP):
                # in the cut already: the tool's release from a light chip (the feed or the load
                # still says cutting), or a knock; chatter grows into the vibration's entry level
                impulse = at
            if at is not None and "vibration" in self.seen:
                on = bool(vib.cutting)
                was, air = self.cutting, self.cutting and (self.chip_by is None or self.held is not None)
                self._source("vibration", on, t0 + at / rate_hz, ev)
                self._air_at = None if on else t0 + at / rate_hz
                if on and (not was or air):
                    data = data[at:]          # the revolution before the chip is air, not the cut
            elif self.cutting and self.chip_by is None and self.held is None:
                # the chip in a cut the feed started: a light one's step, or an entry's
                chip = vib.contact if at is None or not vib.cutting else at
                if chip is not None:
                    self._contact("vibration", t0 + chip / rate_hz, ev)
                    data = data[chip:]
        if (now is not None and self._polled and self.cutting and self.held is None
                and self.seen.get("vibration") is False):
            self._stale(now, t0, ev)
        if not self.cutting or self.held is not None or len(data) == 0:
            return BlockCut(ev, None)           # a dwell's blocks are not the cut's
        if self._rejoin:
            # the pass goes on after a dwell the detector did not see: its revolution difference
            # spans the join, and the chip's re-entry rings the structure
            self._rejoin, impulse = False, 0
        return BlockCut(ev, data, impulse)

    def _received(self, quantity: str, value: float, now: float) -> None:
        self._polled = self._polled or self._last.get(quantity) == value
        self._last[quantity] = value
        name = MACHINE_SOURCES.get(quantity)
        if name in self.seen:
            last = self._read.get(name)
            gap = None if last is None else now - last[0]
            if last is not None and last[1] is not None:
                gap = 0.8 * last[1] + 0.2 * gap    # smoothed: one late poll makes no reading stale
            self._read[name] = (now, gap)

    def _stale(self, now: float, t0: float, ev: list[CutEvent]) -> None:
        """The machine's sources still on with no reading for a few polls: taken as off, the
        chip last seen when the vibration went to air (a feed dwell: dwell_max on this clock)."""
        air = t0 if self._air_at is None else self._air_at
        for name, (at, gap) in self._read.items():
            if self.seen[name] and gap is not None and now - at > max(STALE_MIN_S, STALE_POLLS * gap):
                if name == "feed" and self.feed_stop is not None:
                    # a dwell's stop looks the same in air: the feed taken as stopped after its
                    # last reading, the cut held until the axes say where the tool went
                    self.feed_stop.stopped_unread(math.nextafter(self._feed_at, math.inf))
                    self.seen["feed"] = False
                    if not any(self.seen.values()):
                        self.held, self._held_clock, self._stale_hold = air, "block", True
                        self.dwells += 1
                        ev.append(CutEvent("dwell", air, "stale"))
                        return
                    continue
                self._source(name, False, air, ev)
                if self.held is not None:
                    self._held_clock = "block"
                if not self.cutting or self.held is not None:
                    return

    # -- the sources combined ----------------------------------------------------------------
    def _source(self, name: str, on: bool, t: float, ev: list[CutEvent]) -> None:
        """One source's verdict; the cut is on while any source sees the chip."""
        self.seen[name] = on
        cutting = any(self.seen.values())
        if self.held is not None:
            if not cutting or self._stale_hold:
                return
            if self.feed_stop.away:
                # the feed back with the tool elsewhere (retract, shift and approach within a
                # poll): the pass ended at the dwell, this is the next one
                self._end(self.held, "axes", ev)
            else:
                # the feed or the chip back with the tool where the feed left it: the same pass
                if self.feed_stop.resuming:     # an axis of this poll still to be read
                    self._rejoined = (self.held, name, t)
                self.held, self._rejoin = None, True
                ev.append(CutEvent("dwell_over", t, name))
                return
        if self.cutting and not cutting and self.feed_stop is not None and self.feed_stop.standing:
            # the feed stopped with the axes standing: a dwell, unless they move or it lasts
            self.held = t
            self._held_clock = "block" if name == "vibration" else "machine"
            self.dwells += 1
            ev.append(CutEvent("dwell", t, name))
            return
        if cutting and not self.cutting:
            self.cutting, self.cut_by = True, name
            self.chip_by = None if name == "feed" else name
            ev.append(CutEvent("start", t, name))
        elif self.cutting and not cutting:
            self._end(t, name, ev)
        elif self.cutting and on and name != "feed" and self.chip_by is None:
            self._contact(name, t, ev)

    def _end(self, t: float, source: str, ev: list[CutEvent]) -> None:
        """The cut is over: the chip was last seen at ``t``."""
        ev.append(CutEvent("end", t, source, held=self.held is not None))
        self._rejoined = None
        self.cut_by = self.chip_by = None
        self.held, self._rejoin, self._stale_hold = None, False, False
        self.cutting = False

    def _contact(self, by: str, t: float, ev: list[CutEvent]) -> None:
        """The chip, in a cut the feed started: what came before was the approach in air."""
        self.chip_by = by
        ev.append(CutEvent("contact", t, by))

    def _dwell_over(self, now: float, clock: str, ev: list[CutEvent]) -> None:
        """A held cut ends when an axis leaves the feed's path (the tool retracting) or after
        dwell_max (a feed hold left on), dated when the chip was last seen.  ``now`` is on the
        ``clock`` of the stream it came with: dwell_max is timed on the hold's own (the
        accelerometer's clock may be off the host's)."""
        if self.held is None:
            return
        if self.feed_stop.left:
            self._end(self.held, "axes", ev)
        elif clock == self._held_clock and now - self.held >= self.dwell_max:
            self._end(self.held, "dwell_max", ev)
