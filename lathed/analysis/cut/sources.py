"""Is the tool in the cut?  Decided from what a machine offers.

Real controls (Fanuc, Siemens, Heidenhain, Haas) report spindle speed,
spindle load, feed and program state, rarely the depth of cut.  Each source
here turns one of them into cutting / not cutting:

  depth      a depth-of-cut register > 0 (machines that have one; exact)
  load       spindle load above the spindle's own no-chip load by a margin
             (a standard register; polled, so the entry is seen one poll late)
  vibration  the accelerometer itself: a chip excites the structure, an air
             cut does not.  Frame rms (a few ms) against the air-cut floor
             learned while not cutting; sees the entry within the frame, so
             within one revolution at 3000 r/min.  Gain-invariant (a ratio).
  feed       the control's cutting-feed signal (Fanuc's CUT, a G01/G02/G03
             move that is not held): sees a light finishing cut that lifts
             neither the load nor the vibration much, but comes on before
             the chip, while the tool approaches the stock in air.  The chip's
             contact within it is a sustained step of the vibration over the
             air (``VibrationCutDetector.contact``), smaller than an entry.

The chatter analyzer ORs the sources a machine's config names: the first to
see the chip starts the cut, the cut ends when none sees it.  A dwell (G04)
with the tool in the work drops the feed, and the chip with it, so every
source says "not cutting" while the pass is not over: ``FeedStop`` tells it
from the pass's end by the axes' positions.  No asyncio here.
"""
from __future__ import annotations

import math

import numpy as np

from lathed.analysis.device_rows import DeviceRows
from lathed.analysis.quantile import SlidingQuantile

SOURCES = ("depth", "load", "vibration", "feed")


class VibrationCutDetector:
    """Air cut vs chip from the vibration signal.

    Frames of ``frame_s``; the air-cut floor is a slow running low level of
    the frame rms while not cutting (so a gain change or a warmer spindle is
    followed).  Entry: a frame ``on_ratio`` x above the floor.  Exit: frames
    below ``off_ratio`` x the floor for ``off_s`` (longer than a flat's gap in
    an interrupted cut, so the cut does not end at every revolution).  Until
    an air cut has been seen the floor is unknown and the state is None.

    ``contact``: a run of frames ``contact_ratio`` x above the floor lasting
    ``contact_s`` while not cutting (a chip too light for ``on_ratio``: a
    finishing pass, a face at a fine feed) sets it to the run's first sample
    in the block (0 if it began in an earlier one); None otherwise.  The air's
    frames spread a few per cent; a knock rings down within the run.

    ``entry_jump``: at an entry, its frame's rms over the lower of the two
    frames' before.  An impulse (the tool's release from a light cut, a
    knock) jumps within one frame; chatter grows by a few per cent a frame.
    """

    def __init__(self, rate_hz: float, frame_s: float = 0.004, on_ratio: float = 4.0,
                 off_ratio: float = 2.0, off_s: float = 0.15, floor_s: float = 0.2,
                 contact_ratio: float = 1.3, contact_s: float = 0.02) -> None:
        if not rate_hz > 0:
            raise ValueError(f"sample rate must be > 0 Hz, got {rate_hz}")
        if not 1.0 < off_ratio < on_ratio:
            raise ValueError(f"vibration cut detection needs 1 < off_ratio < on_ratio, "
                             f"got {off_ratio:g} and {on_ratio:g}")
        self.rate = float(rate_hz)
        self.frame = max(8, int(frame_s * rate_hz))
        self.on_ratio, self.off_ratio = on_ratio, off_ratio
        if not 1.0 < contact_ratio <= on_ratio:
            raise ValueError(f"contact_ratio must be in (1, on_ratio = {on_ratio:g}], got {contact_ratio:g}")
        self.contact_ratio = contact_ratio
        self.contact_frames = max(1, int(round(contact_s * rate_hz / self.frame)))
        self.contact: int | None = None
        self._run = 0                        # frames in a row over contact_ratio x the floor
        self.entry_jump = 0.0                # the entry frame's rms over the two frames before's
        self._last_rms = (0.0, 0.0)
        self.off_frames = max(1, int(off_s * rate_hz / self.frame))
        self.floor_frames = max(4, int(floor_s * rate_hz / self.frame))
        self.floor: float | None = None
        self.cutting: bool | None = None
        self._air = SlidingQuantile(0.25, self.floor_frames)   # the air-cut frames' rms
        self._quiet = 0
        self._rest = np.empty(0)
        self._after: tuple[DeviceRows, int] | None = None    # the device block and row fed last

    def process(self, x: np.ndarray, rows: DeviceRows | None = None, row: int = 0) -> int | None:
        """Feed samples; returns the sample offset in ``x`` where the state changed
        (the last change in this block), or None. ``rows``: the device block ``x`` is row
        ``row`` of (Block.rows): when this detector was fed the same row of the block before, its
        frames are made with the rows framed alike, at once (the same numbers as alone)."""
        frame, k = self.frame, len(self._rest)
        r = None
        if rows is not None:
            after, self._after = self._after, (rows, row)
            if after is not None and rows.prev is after[0] and row == after[1]:
                r = rows.frame_rms(frame, k, row)
                if r is not None:
                    self._rest = x[len(r) * frame - k:]
        else:
            self._after = None
        if r is None:
            x = x.ravel() if type(x) is np.ndarray else np.ravel(x)    # the method: np.ravel's wrapper spared
            buf = np.concatenate((self._rest, x), dtype=float)     # the cast and the join in one pass
            nf = len(buf) // frame
            self._rest = buf[nf * frame:]
            if nf == 0:
                if rows is not None:
                    rows.ask(frame, len(self._rest), row)
                return None
            frames = buf[:nf * frame].reshape(nf, frame)
            # np.mean's sum and division without its Python wrapper, the deviations squared and the
            # root in place (the same numbers, bit for bit; a block's few frames are a handful of
            # numpy calls, each costing more than its arithmetic)
            dev = frames - np.add.reduce(frames, axis=1, keepdims=True) / frame
            np.multiply(dev, dev, out=dev)
            ms = np.add.reduce(dev, axis=1)
            ms /= frame
            r = np.sqrt(ms, out=ms).tolist()
        if rows is not None:
            rows.ask(frame, len(self._rest), row)     # the next block frames this row with the others
        nf = len(r)
        offset0 = -k                         # buffer index 0 in x's coordinates
        self.contact = None
        if self.cutting:
            exit_level = self.off_ratio * self.floor
            if not any([v < exit_level for v in r]):
                # in the cut, every frame over the exit's level (a block's usual case): no frame
                # counts towards the exit, nothing changes but the two last frames' rms
                self._quiet = 0
                self._last_rms = (self._last_rms[1], r[0]) if nf == 1 else (r[-2], r[-1])
                return None
        return self._frames(r, offset0)

    def _frames(self, rms: list[float], offset0: int) -> int | None:
        """The frames one by one: the floor follows the air frame by frame."""
        changed = None
        frame, floor, last = self.frame, self.floor, self._last_rms
        air = self._air
        enough = min(4, self.floor_frames)
        for i, r in enumerate(rms):
            if not self.cutting:
                if floor is not None and r > self.on_ratio * floor:
                    self.cutting, self._quiet, self._run = True, 0, 0
                    # the lower of the two frames before: an impulse mid-frame lifts the first
                    self.entry_jump = r / max(min(last), 1e-300)
                    last = (last[1], r)
                    changed = max(0, offset0 + i * frame)
                    continue
                last = (last[1], r)
                self._run = self._run + 1 if floor is not None and r > self.contact_ratio * floor else 0
                if self._run == self.contact_frames:
                    self.contact = max(0, offset0 + (i + 1 - self._run) * frame)
                air.push(r)
                if len(air) >= enough:
                    # a low quantile: a knock or a ramp's ringing does not lift it
                    floor = self.floor = max(air.value(), 1e-300)
                    if self.cutting is None:
                        self.cutting = False
            else:
                last = (last[1], r)
                self._quiet = self._quiet + 1 if r < self.off_ratio * floor else 0
                if self._quiet >= self.off_frames:
                    self.cutting = False
                    self._air.clear()
                    changed = max(0, offset0 + (i + 1) * frame)
        self._last_rms = last
        return changed


class LoadCutDetector:
    """Cutting while the spindle load is ``margin_pct`` above its no-chip load.

    The no-chip load (bearings, seals; it rises with speed) is the lowest load
    seen at the current speed band while the spindle turns; in a band not yet
    seen, the nearest band's (under constant surface speed the spindle runs
    through new bands while it cuts, and the cut must not end there), or
    ``idle_pct`` until one is seen."""

    def __init__(self, margin_pct: float = 5.0, idle_pct: float = 5.0) -> None:
        self.margin = float(margin_pct)
        self.idle_default = float(idle_pct)
        self._idle: dict[int, float] = {}
        self.cutting = False

    @staticmethod
    def _band(rpm: float | None) -> int:
        return -1 if not rpm or rpm <= 0 else int(round(math.log(rpm) / math.log(1.1)))

    def _idle_at(self, band: int) -> float:
        if band in self._idle:
            return self._idle[band]
        if not self._idle:
            return self.idle_default
        return self._idle[min(self._idle, key=lambda b: (abs(b - band), b))]

    def cutting_load(self, load_pct: float, rpm: float | None) -> float | None:
        """The load the chip takes (above the no-chip load at this speed band), or None
        under the margin: a measure of the static cutting force (chatter barely moves it)."""
        extra = load_pct - self._idle_at(self._band(rpm))
        return extra if extra >= self.margin else None

    def update(self, load_pct: float, rpm: float | None) -> bool:
        band = self._band(rpm)
        idle = self._idle_at(band)
        if rpm and rpm > 0 and load_pct < idle + self.margin:
            self._idle[band] = min(idle, load_pct) if band in self._idle else min(self.idle_default,
                                                                                  load_pct)
            idle = self._idle[band]
        self.cutting = load_pct >= idle + self.margin
        return self.cutting


# An axis this far off where the cutting feed left it has left the work: a retract clears the
# stock by 0.5 mm or more, while a standing axis's reading moves by microns (servo lag, a
# thermal offset's step of at most 10 um).
AXIS_TOL_MM = 0.1
# A poll's time stamp is when it was asked for, not when each register was read: under load
# tens of ms apart, which at a feed of 10 mm/s is more than AXIS_TOL_MM along the feed's way
POLL_JITTER_S = 0.05


class FeedStop:
    """Where the cutting feed stopped: in the work (a dwell, G04, at a groove's bottom or a
    shoulder; a feed hold), every axis standing where the feed left it, or at the pass's end,
    the tool moving away (a rapid retract).  From the cutting-feed signal and the axes'
    position registers, read in the same polls (one time stamp a poll, in any order).

    While the feed is on, an axis's last two readings give its rate under feed.  Its first
    reading after the feed stopped must lie on the way the feed was taking it (between its
    last reading under feed and where the feed would have taken it by then, give or take
    ``tol_mm``), each later one within ``tol_mm`` of that: ``standing``.  An axis read
    otherwise, or not read under feed (no path to judge by), is the tool leaving: ``left``,
    until the feed comes on again, once the feed's reading of that poll (or a later poll)
    says it is still off: the axes move when the feed goes on again too."""

    def __init__(self, axes: list[str], tol_mm: float = AXIS_TOL_MM) -> None:
        self.axes = list(axes)
        self.tol = float(tol_mm)
        self.off_t: float | None = None        # the first reading of the feed off after it was on
        self._moved_t: float | None = None     # the first reading off the feed's path
        self._feed_t = self._last_t = -math.inf   # the feed's last reading (off), any last reading
        self._on = False
        self._recent: dict[str, list[tuple[float, float]]] = {a: [] for a in self.axes}
        self._path: dict[str, list[tuple[float, float]]] = {}    # the last two readings under feed
        self._rest: dict[str, float] = {}                        # where each axis stood after
        # the feed back on after a stop: each axis's first reading of that poll must be where it
        # stood, or on the feed's way on from there; else the tool went elsewhere between polls
        # (retract, shift, re-approach faster than a poll): the next pass, not the same one
        self._resume_t: float | None = None
        self._resume_from: dict[str, tuple[float, float, float]] = {}   # axis: (stood, rate, since)
        self.away = False
        self._unread = False                   # the stop taken from a stale poll: not read standing

    def stopped_unread(self, t: float) -> None:
        """The feed's poll went stale: taken as stopped just after its last reading. Where the axes
        stood meanwhile was not read, so a first reading off the feed's path is the tool gone
        elsewhere, not where it stands."""
        self.feed(False, t)
        self._unread = True

    @property
    def left(self) -> bool:
        """An axis moved off the feed's path with the feed off in that poll or after."""
        m = self._moved_t
        return m is not None and (self._feed_t >= m or self._last_t > m)

    @property
    def standing(self) -> bool:
        """The feed stopped in this pass and no axis has moved off its path since."""
        return self.off_t is not None and not self.left

    @property
    def resuming(self) -> bool:
        """The feed is back on and an axis has not been read in that poll yet."""
        return self._resume_t is not None

    def feed(self, on: bool, t: float) -> None:
        self._last_t = max(self._last_t, t)
        if on:
            if not self._on:                    # a new move under feed: its own path
                self._resume_t, self.away, self._resume_from = None, False, {}
                if self.off_t is not None:
                    self._resume_t = t
                    for axis in self.axes:
                        path = self._path.get(axis, [])
                        rate = ((path[-1][1] - path[0][1]) / (path[-1][0] - path[0][0])
                                if len(path) == 2 and path[-1][0] > path[0][0] else 0.0)
                        stood = self._rest.get(axis, path[-1][1] if path else None)
                        if stood is not None:
                            self._resume_from[axis] = (stood, rate, self._feed_t)
                self.off_t, self._moved_t = None, None
                self._path.clear()
                self._rest.clear()
                # a reading of the same poll that came before the feed's is under feed
                self._recent = {a: [r for r in rs if r[0] >= t] for a, rs in self._recent.items()}
                for axis, readings in self._recent.items():
                    for r in readings:
                        self._judge_resume(axis, *r)
                if not self._resume_from:
                    self._resume_t = None
            self._on, self._unread = True, False
        else:
            self._feed_t = t
            if not self._on:
                return
            self._on, self.off_t = False, t
            self.away, self._resume_t, self._resume_from = False, None, {}    # a new stop: judged anew
            for axis, readings in self._recent.items():
                # a reading of the same poll that came before the feed's is after the stop
                self._path[axis] = [r for r in readings if r[0] < t][-2:]
                if not self._path[axis]:
                    self._moved(t)              # never read under feed: nothing to judge by
                for r in readings:
                    if r[0] >= t:
                        self._judge(axis, *r)

    def position(self, axis: str, value: float, t: float) -> None:
        if axis not in self._recent:
            return
        self._last_t = max(self._last_t, t)
        self._recent[axis] = (self._recent[axis] + [(t, value)])[-3:]
        if self.off_t is not None:
            self._judge(axis, t, value)
        elif self._resume_t is not None and t >= self._resume_t:
            self._judge_resume(axis, t, value)

    def _judge_resume(self, axis: str, t: float, value: float) -> None:
        if axis not in self._resume_from:
            return
        stood, rate, since = self._resume_from.pop(axis)
        reach = stood + rate * max(0.0, t - since)     # the feed resumed after its last reading off
        slack = self.tol + abs(rate) * POLL_JITTER_S
        if not min(stood, reach) - slack <= value <= max(stood, reach) + slack:
            self.away = True
        if not self._resume_from:
            self._resume_t = None

    def _judge(self, axis: str, t: float, value: float) -> None:
        if axis in self._rest:
            moved = abs(value - self._rest[axis]) > self.tol
        else:
            path = self._path.get(axis, [])
            if not path:
                moved = True
            else:
                t1, v1 = path[-1]
                rate = (v1 - path[0][1]) / (t1 - path[0][0]) if len(path) == 2 and t1 > path[0][0] else 0.0
                reach = v1 + rate * max(0.0, t - t1)
                slack = self.tol + abs(rate) * POLL_JITTER_S
                moved = not min(v1, reach) - slack <= value <= max(v1, reach) + slack
            if not (moved and self._unread):
                self._rest[axis] = value
        if moved:
            self._moved(t)

    def _moved(self, t: float) -> None:
        if self._moved_t is None:
            self._moved_t = t
