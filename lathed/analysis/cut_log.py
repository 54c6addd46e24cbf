"""One record per cut, and the cuts the stability refit reads from them.

A cut runs from entry to exit (the cut state the chatter analyzer and the
depth register give).  Within it the spindle may turn at several speeds: the
one it entered at, and each speed suppression moved it to.  Each such
stretch is its own evidence for the stability lobes, so the record keeps
them apart (``speeds``) with the verdict of each:

* ``chatter``: a chatter alarm in the stretch, counted from the end of the
  hold after the speed change (the spindle's ramp and ``settle_revs``
  revolutions: before that the old chatter marks are still being cut off);
* ``stable``: no alarm over at least MIN_JUDGE_REVS revolutions after it,
  and the detector's index not rising at its end (``rising``);
* ``null``: too short to tell (a speed left at once at entry, a cut that
  ended during the hold), the index still rising when it ended, or the
  speed was modulated: not evidence.

``cut_rows`` turns records into the rows of the cut-record CSV
(lathed.analysis.cuts) that ``lathectl cuts --csv`` writes and the
daemon's refit reads: one row per judged stretch with a known depth.
Numeric only, no asyncio.
"""
from __future__ import annotations

import math
import statistics
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from lathed.analysis.cuts import Cuts

# Revolutions without an alarm, once a stretch is judged, before it counts as
# stable: the detector's windows need a few revolutions each and chatter
# above the limit grows visible within ten or so (lathed.sim.lathe.VisibleChatter).
MIN_JUDGE_REVS = 20.0
# A stretch whose speed wandered more than this (a program changing speed
# mid-cut, constant surface speed) has no one speed to be evidence at.
MAX_SPREAD = 1.05
# A stretch whose judged chatter index rose by this much, from the first half of its last
# RISING_REVS judged revolutions to the second (medians), is not called stable: chatter a
# little above the limit, regrowing from the quiet a speed change leaves, takes longer than
# a cure's few judged revolutions to reach an alarm (the detector's baseline was learned over
# the entry's ring).  On the simulated lathe (the cures of two live programs, replayed) the
# stable ones' halves stayed within 15 % (0.5-1.05 x the limit), the entries' within 10 %;
# the cures at 1.10-1.25 x that no alarm caught rose 28-124 %.
RISING_RATIO = 1.2
RISING_REVS = 2 * MIN_JUDGE_REVS
RISING_MIN_WINDOWS = 3    # judged windows in each half, at least


@dataclass
class Stretch:
    """One speed within a cut."""
    trigger: str                 # "entry", or what moved the spindle here ("alarm", "predicted", ...)
    start_t: float
    judge_from_t: float          # alarms before this belong to the previous speed
    target_rpm: float | None     # the commanded speed (None: entry, or modulated)
    modulated: bool = False
    revs: float = 0.0
    judged_revs: float = 0.0
    rpms: list[float] = field(default_factory=list)   # speeds measured while judged
    alarm_t: float | None = None
    alarm_rev: float | None = None
    frequency_hz: float | None = None
    # (cut revolution, judged chatter index) over the stretch's last RISING_REVS judged revolutions
    indices: deque = field(default_factory=deque, repr=False)

    @property
    def rising(self) -> float | None:
        """The judged index's rise over the stretch's last RISING_REVS judged revolutions: the
        second half's median over the first's (None: too few windows to tell)."""
        if len(self.indices) < 2 * RISING_MIN_WINDOWS:
            return None
        mid = (self.indices[0][0] + self.indices[-1][0]) / 2
        first = [i for r, i in self.indices if r <= mid]
        last = [i for r, i in self.indices if r > mid]
        if len(first) < RISING_MIN_WINDOWS or len(last) < RISING_MIN_WINDOWS:
            return None
        low = statistics.median(first)
        return statistics.median(last) / low if low > 0 else None

    @property
    def rpm(self) -> float | None:
        if self.modulated:
            return None
        if self.target_rpm is not None:
            return self.target_rpm
        return statistics.median(self.rpms) if self.rpms else None

    @property
    def outcome(self) -> str | None:
        if self.modulated:
            return None
        if self.alarm_t is not None:
            return "chatter"
        if self.judged_revs < MIN_JUDGE_REVS:
            return None
        rising = self.rising
        return None if rising is not None and rising >= RISING_RATIO else "stable"

    def to_json(self, cut_start_t: float) -> dict:
        spread = max(self.rpms) / min(self.rpms) if self.rpms and min(self.rpms) > 0 else None
        return {"rpm": _r(self.rpm, 1), "trigger": self.trigger, "outcome": self.outcome,
                "start_s": _r(self.start_t - cut_start_t, 3), "revs": _r(self.revs, 1),
                "judged_revs": _r(self.judged_revs, 1),
                "rpm_min": _r(min(self.rpms), 1) if self.rpms else None,
                "rpm_max": _r(max(self.rpms), 1) if self.rpms else None,
                "steady": spread is not None and spread <= MAX_SPREAD,
                "first_alarm_s": None if self.alarm_t is None else _r(self.alarm_t - cut_start_t, 3),
                "chatter_frequency_hz": _r(self.frequency_hz, 1), "rising": _r(self.rising, 3)}


def _r(x, d):
    return None if x is None or not math.isfinite(x) else round(float(x), d)


class CutTracker:
    """Builds one cut's record from what the daemon sees during it."""

    def __init__(self, machine: str, tool: str | None, material: str | None):
        self.machine, self.tool, self.material = machine, tool or None, material or None
        self.start_t: float | None = None
        self.stretches: list[Stretch] = []
        self.actions: list[dict] = []
        self._last: tuple[float, float] | None = None   # (t, rpm) of the last speed sample
        self.revs = 0.0
        self.alarm = False
        self.alarms = 0
        self.frequency_hz: float | None = None
        self.first_alarm: tuple[float, float, float | None] | None = None   # t, rev, frequency
        self.depth_mm: float | None = None
        self.depth_from: str | None = None
        self.feed_mm_rev: float | None = None
        self.tool_number: int | None = None   # the machine's tool register (set by the owner)
        self.advice: str | None = None     # suppression held the speed: why, what would cure it
        self._dwell = False                # the feed stopped mid-pass: no chip, nothing judged

    @property
    def active(self) -> bool:
        return self.start_t is not None

    def start(self, t: float, rpm: float | None) -> None:
        self.start_t = t
        self.stretches = [Stretch("entry", t, t, None)]
        self.actions, self.revs, self.alarms, self.first_alarm = [], 0.0, 0, None
        self.alarm = False
        self.advice = None
        self._dwell = False
        self._last = None if rpm is None else (t, rpm)

    def contact(self, t: float) -> None:
        """The chip, in a cut the cutting-feed signal started while the tool approached in
        air: the record counts from here (an approach that saw an action keeps its start)."""
        if self.active and not self.actions and not self.alarms and t > self.start_t:
            self.start(t, None if self._last is None else self._last[1])

    def speed(self, t: float, rpm: float) -> None:
        if not self.active:
            return
        if self._last is not None and t > self._last[0]:
            t0, n0 = self._last
            s = self.stretches[-1]
            d = (t - t0) * n0 / 60.0
            self.revs += d
            s.revs += d
            if t0 >= s.judge_from_t and not self._dwell:
                s.judged_revs += d
        if t >= self.stretches[-1].judge_from_t:
            self.stretches[-1].rpms.append(rpm)
        self._last = (t, rpm)

    def dwell(self, t: float, on: bool) -> None:
        """The feed stopped mid-pass (a dwell: no chip, no windows), or went on: revolutions
        without a chip judge no speed stable, and remembered cures are learned from stable ones."""
        if self._last is not None:
            self.speed(t, self._last[1])      # the revolutions up to now, as they were
        self._dwell = on

    def chatter(self, t: float, alarm: bool, frequency_hz: float | None) -> None:
        if not self.active:
            return
        if alarm and frequency_hz:
            self.frequency_hz = frequency_hz
        if alarm and not self.alarm:
            self.alarms += 1
            if self.first_alarm is None:
                self.first_alarm = (t, self._rev_at(t), frequency_hz)
        self.alarm = alarm
        s = self.stretches[-1]
        if alarm and t >= s.judge_from_t and s.alarm_t is None:
            s.alarm_t, s.alarm_rev, s.frequency_hz = t, self._rev_at(t), frequency_hz

    def index(self, t: float, value: float) -> None:
        """A window's chatter index the detector judged (``chatter_index_judged``): whether the
        stretch was still rising when it ended."""
        s = self.stretches[-1] if self.active else None
        if s is None or t < s.judge_from_t or self._dwell or not math.isfinite(value) or value <= 0:
            return
        rev = self._rev_at(t)
        s.indices.append((rev, value))
        while s.indices[0][0] < rev - RISING_REVS:
            s.indices.popleft()

    def _rev_at(self, t: float) -> float:
        if self._last is None:
            return self.revs
        return self.revs + max(0.0, t - self._last[0]) * self._last[1] / 60.0

    def action(self, t: float, payload: dict, judge_from_t: float) -> None:
        """A suppression decision acted on (or refused) in this cut."""
        if not self.active:
            return
        self.actions.append({k: payload.get(k) for k in ("trigger", "strategy", "rpm_before", "rpm_after",
                                                         "sent", "by")} | {"at_s": round(t - self.start_t, 3)})
        if not payload.get("sent"):
            return
        modulated = payload.get("variation") is not None
        self.stretches.append(Stretch(payload.get("trigger") or "alarm", t, judge_from_t,
                                      None if modulated else payload.get("rpm_after"), modulated))

    def advised(self, text: str) -> None:
        """Suppression held the speed (no stable speed within reach): the cut says so."""
        if self.active:
            self.advice = text

    def end(self, t: float) -> dict:
        """The cut's record; the tracker is then idle until the next start."""
        if self._last is not None:
            self.speed(t, self._last[1])      # the revolutions since the last speed sample
        st = self.start_t
        stretches = self.stretches
        chattered = self.alarms > 0
        last = stretches[-1]
        if chattered:
            outcome = "chatter"
        elif any(s.outcome == "stable" for s in stretches):
            outcome = "stable"
        else:
            outcome = None          # too short to judge
        fa = self.first_alarm
        rec = {"machine": self.machine, "tool": self.tool, "material": self.material,
               "tool_number": self.tool_number,
               "start_t": round(st, 3), "end_t": round(t, 3), "duration_s": round(t - st, 3),
               "revs": round(self.revs, 1),
               "rpm_start": _r(stretches[0].rpm, 1), "rpm_end": _r(self._last[1] if self._last else None, 1),
               "speeds": [s.to_json(st) for s in stretches],
               "depth_mm": _r(self.depth_mm, 4), "depth_from": self.depth_from,
               "feed_mm_rev": _r(self.feed_mm_rev, 4),
               "outcome": outcome,
               "first_alarm_s": None if fa is None else round(fa[0] - st, 3),
               "first_alarm_rev": None if fa is None else round(fa[1], 1),
               "chatter_frequency_hz": None if fa is None else _r(fa[2] or self.frequency_hz, 1),
               "alarms": self.alarms,
               "actions": self.actions,
               "advice": self.advice,
               "cured": (last.outcome == "stable" and not self.alarm) if chattered and self.actions else
                        (False if chattered else None)}
        self.start_t = None
        return rec


# -- records -> cut rows ----------------------------------------------------------

def cut_rows(records: list[dict]) -> tuple[Cuts | None, dict[str, int]]:
    """Cut records (payloads of ``cut`` events, oldest first) as the refit's
    cuts: one row per judged, steady stretch with a known depth.  Also how
    many stretches were left out, by reason (nothing is dropped unsaid)."""
    rows: list[tuple] = []
    skipped: dict[str, int] = {}

    def skip(why: str) -> None:
        skipped[why] = skipped.get(why, 0) + 1
    for r in records:
        for s in r.get("speeds") or []:
            if s.get("outcome") is None and (s.get("rising") or 0) >= RISING_RATIO:
                skip("chatter index still rising when the speed ended")
            elif s.get("outcome") is None:
                skip("too short to judge or speed modulated")
            elif r.get("depth_mm") is None:
                skip("no depth of cut known (no depth register, no programmed depth_mm)")
            elif not r.get("feed_mm_rev"):
                skip("no feed known (no feed_mm_rev register)")
            elif s.get("rpm") is None or not s.get("steady", False):
                skip("speed not steady")
            else:
                f = s.get("chatter_frequency_hz") if s["outcome"] == "chatter" else None
                rows.append((r["machine"], r.get("tool") or "-", r.get("material") or "-", float(s["rpm"]),
                             float(r["depth_mm"]), float(r["feed_mm_rev"]),
                             s["outcome"] == "chatter", math.nan if f is None else float(f)))
    if not rows:
        return None, skipped
    m, tl, mat, rpm, d, feed, ch, f = zip(*rows)
    return Cuts(list(m), list(tl), list(mat), np.array(rpm), np.array(d), np.array(feed), np.array(ch, bool),
                np.array(f, float), np.arange(2, len(rows) + 2), "daemon cut records"), skipped
