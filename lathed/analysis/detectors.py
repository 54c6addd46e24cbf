"""Streaming chatter detectors behind one interface, and their registry.

Every detector works on windows a fixed number of spindle revolutions long,
hopping by a fraction of a revolution, with the same signal one revolution
earlier *in spindle angle* at hand (the angle is integrated from the ``rpm``
given with each block, so speed changes are followed).  Each window gives a
raw measure; the detector learns a baseline from the first ``learn_windows``
windows of a cut (median, so a cut-entry transient does not inflate it) or
from a reference recording (``learn_reference``), and reports

    index = raw / baseline

which does not depend on the signal's gain.  The alarm turns on after
``on_windows`` consecutive windows above ``threshold`` and off after
``off_windows`` consecutive windows below ``off_ratio * threshold``
(hysteresis).  While the speed ramps (by more than ``ramp_per_rev`` over a
revolution: a drive's acceleration) and for ``settle_revs`` revolutions
after, no alarm is raised (the revolution-to-revolution comparison is not
meaningful across a ramp); a slower drift, such as constant surface speed
(G96) following the diameter, is followed in angle and judged.  Nor does a window count whose
level (median |x|) steps by more than ``jump_ratio`` against the revolution
before, nor the falling ring after such a step: that is the tool entering or
leaving the work, where regenerative chatter grows over several revolutions.

Built-in detectors (``DETECTORS``):
  sync_residual      robust rms of x(theta) - x(theta - 2 pi): everything that
                     repeats every revolution (runout, a flat's ringing)
                     cancels; chatter does not.
  spectral_ratio     largest non-harmonic spectral peak over the band's
                     median level (chatter energy away from spindle harmonics).
  sync_cusum         sync_residual with the median of the learning windows
                     as baseline and a CUSUM beside the threshold (a
                     sustained rise below it adds up), the baseline raised
                     to the upper range of the cut's own calm windows
                     (follow_quantile): survives a real cut's slow wander,
                     catches mild chatter.
  chaos_sync         the paper's fractional-order Lorenz chaos-synchronisation
                     detector (lathed.analysis.chaos_sync).

Parameters (``make_detector(name, rate_hz, **params)``), with allowed ranges,
are listed in ``BASE_PARAMS`` and each class's ``PARAMS``:
``describe_params(name)`` returns name -> (default, min, max, meaning).

Use in a daemon: one detector per channel; call ``reset()`` when a cut
starts (the baseline is learned from the first windows after it, so feeding
air-cutting first would make the cut itself look like chatter), feed blocks
with the current speed, read ``Window``s.  Blocks below ``min_rpm`` are
dropped (``too_slow``); rpm <= 0 is a ValueError.  No asyncio and no pluggy
here: plugin detectors arrive as the ``extra`` dict.
"""
from __future__ import annotations

import math
import numbers
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from lathed.analysis.cut_state import SlidingQuantile

MIN_WINDOW_SAMPLES = 16
_HIST = 1 << 19   # most samples of history kept (10 s at 51.2 kS/s): sets the lowest speed followed
_HIST_START = 1 << 15   # history a detector starts with (0.6 s at 51.2 kS/s: 2 revolutions at 200 r/min);
                        # it grows to what a slower speed needs, up to _HIST (most cuts never need it)
LOAD_STEP = 1.3       # load_scaled: a level rising this much within a revolution waits for the load
LOAD_WAIT_S = 0.3     # ... for at most this long (a 100 ms poll and its jitter; a load that stops coming)
FOLLOW_WINDOWS = 256   # windows a follow_quantile baseline looks back over (128 revolutions at the default hop)
GROWTH_TAIL = 0.3      # growth: a window's second half at least this x its first's level (a release's: 0.2 x)
EYE_REVS = 4      # revolutions of a display eye (eye_views)
EYE_MEMORY = 64   # its GL filter's memory, samples
EYE_MAX_SAMPLES = 16384   # at most this many samples filtered per view (a slow spindle's 4 revolutions)


@dataclass
class Window:
    t_s: float                          # end of the window, seconds since reset
    index: float                        # raw / baseline (nan while nothing learned yet)
    threshold: float                    # index level that counts as chatter
    alarm: bool                         # alarm state after this window (hysteresis applied)
    chatter_frequency_hz: float | None = None   # only while alarm
    learning: bool = False              # window used to learn the baseline
    raised_by: str | None = None        # on the window that raises the alarm: "threshold" or
                                        # "sustained rise" (the CUSUM: index held above cusum_ratio)
    judged: bool = True                 # False: the index was not judged (learning, a speed change,
                                        # the tool entering or leaving the work, waiting for the load)


# name -> (default, min, max, meaning)
BASE_PARAMS: dict[str, tuple[float, float, float, str]] = {
    "window_revs": (1.0, 0.25, 16.0, "window length in spindle revolutions"),
    "hop_revs": (0.5, 0.1, 4.0, "hop between windows in revolutions"),
    "min_window_s": (0.02, 0.002, 1.0, "window never shorter than this (high speeds)"),
    "min_hop_s": (0.01, 0.001, 1.0, "hop never shorter than this (bounds the cost)"),
    "learn_windows": (4, 2, 1000, "windows at the start of a cut used to learn the baseline"),
    "learn_quantile": (0.25, 0.0, 1.0, "quantile of the learning windows taken as baseline "
                       "(low: ignores the cut-entry transient and chatter already growing)"),
    "threshold": (2.0, 1.05, 1000.0, "index above which a window counts as chatter"),
    "on_windows": (2, 1, 50, "consecutive windows above threshold to raise the alarm"),
    "off_windows": (4, 1, 1000, "consecutive windows below off_ratio*threshold to clear it"),
    "off_ratio": (0.7, 0.1, 1.0, "hysteresis: clear level as a fraction of threshold"),
    "settle_revs": (2.0, 0.0, 50.0, "no new alarm this many revolutions after a speed change"),
    "ramp_per_rev": (0.01, 0.0, 1.0, "a speed change counts (settle_revs) when the speed moved by more than this "
                     "share over the last revolution: a drive's ramp (2-8 % a revolution), not a slow drift "
                     "such as constant surface speed (G96), under which chatter is still judged"),
    "cusum_ratio": (0.0, 0.0, 100.0, "0: off; else a cumulative sum of log(index / cusum_ratio) "
                    "also raises the alarm past on_windows x log(threshold / cusum_ratio): a "
                    "sustained rise below the threshold adds up (1 < cusum_ratio < threshold)"),
    "follow_quantile": (0.0, 0.0, 0.99, "0: off; else, with cusum_ratio set, the baseline rises to this "
                        "quantile of the cut's last 256 windows below the allowance, once there are "
                        "2 x learn_windows of them: the sustained-rise test learns how far the stable "
                        "cut wanders (never below the learned baseline)"),
    "load_scaled": (0.0, 0.0, 1.0, "1: the index is divided by the cutting load's ratio to its value "
                    "when the baseline was set (set_load: the spindle load above its no-chip load), so "
                    "a deeper stable pass in the same cut (a shoulder) is not chatter; an upward level "
                    "step then waits for the next load reading (0: off)"),
    "growth_ratio": (0.0, 0.0, 100.0, "0: off; else on_windows windows in a row whose raw measure is this many "
                     "times the lowest of the growth_revs revolutions before raise the alarm (raised_by "
                     "'growth'): chatter growing, whatever the baseline; a window whose second half is "
                     "quieter than its first (the ring of the tool's release) does not count"),
    "growth_revs": (4.0, 1.0, 64.0, "revolutions the growth test looks back over (counted once a cut, a "
                    "speed change or a level step has that many behind it)"),
    "jump_ratio": (3.0, 1.5, 1000.0, "a window whose level (median |x|) is above jump_ratio x, or below "
                   "1/jump_ratio x, the level one revolution earlier does not count towards "
                   "the alarm (the tool entering or leaving the work, not chatter)"),
    "fmin_hz": (50.0, 0.0, 20000.0, "lower edge of the chatter band"),
    "fmax_hz": (5000.0, 10.0, 25600.0, "upper edge of the chatter band"),
}


class RevolutionDetector:
    """Windowing, revolution delay, baseline, hysteresis; subclasses give ``_measure``."""

    name = "base"
    PARAMS: dict[str, tuple[float, float, float, str]] = {}
    OWN_EYE = False   # True: the detector computes the chaos eye itself (chaos_sync)
    RAW_POWER = 1.0   # the raw measure grows as the vibration's amplitude to this power (load_scaled)

    def __init__(self, rate_hz: float, **params: Any) -> None:
        if not rate_hz > 0:
            raise ValueError(f"sample rate must be > 0 Hz, got {rate_hz}")
        self.rate = float(rate_hz)
        spec = {**BASE_PARAMS, **self.PARAMS}
        unknown = sorted(set(params) - set(spec))
        if unknown:
            raise ValueError(f"detector {self.name!r}: unknown parameter(s) {', '.join(unknown)}; "
                             f"allowed: {', '.join(sorted(spec))}")
        self.params: dict[str, float] = {}
        for key, (default, lo, hi, _) in spec.items():
            v = params.get(key, default)
            # float() took "2" and true (as 1) from the config: a number must be written as one
            if isinstance(v, bool) or not isinstance(v, numbers.Real):
                raise ValueError(f"detector {self.name!r}: {key}: expected a number, got {v!r}")
            v = float(v)
            # a count (an integer default) is used whole: 4.7 windows would silently be 4 or 5
            if isinstance(default, int) and math.isfinite(v) and not v.is_integer():
                raise ValueError(f"detector {self.name!r}: {key}: expected a whole number (a count), got {v:g}")
            if not lo <= v <= hi:
                raise ValueError(f"detector {self.name!r}: {key} = {v:g} is outside [{lo:g}, {hi:g}]")
            self.params[key] = v
        cr = self.params["cusum_ratio"]
        if cr and not 1.0 < cr < self.params["threshold"]:
            raise ValueError(f"detector {self.name!r}: cusum_ratio = {cr:g} must be 0 (off) or between 1 "
                             f"and the threshold {self.params['threshold']:g}")
        if self.params["fmin_hz"] >= self.params["fmax_hz"]:
            raise ValueError(f"detector {self.name!r}: fmin_hz must be below fmax_hz")
        # the shortest window and hop must hold samples, or a window is empty
        # (division by zero) and a hop of 0 never advances (issue 18 D5)
        short = min(self.params["min_window_s"] / MIN_WINDOW_SAMPLES, self.params["min_hop_s"])
        if short * self.rate < 1.0:
            raise ValueError(f"sample rate {self.rate:g} Hz is too low for the {self.name} detector: it needs "
                             f"at least {1.0 / short:g} Hz ({MIN_WINDOW_SAMPLES} samples per "
                             f"{self.params['min_window_s']:g} s window)")
        self.threshold = self.params["threshold"]
        self._x = np.empty(_HIST_START)
        self._th = np.empty(_HIST_START)
        self._d = np.empty(_HIST_START)     # revolution difference x(theta) - x(theta - 2 pi)
        self._fixed_baseline: float | None = None
        self.reset()

    # -- state --------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the cut (history, alarm, learned baseline unless fixed by a reference)."""
        self.too_slow = False
        self._n = 0                 # valid samples in the buffer
        self._total = 0             # samples seen since reset
        self._theta = 0.0
        self._next_end: int | None = None
        self._rpm: float | None = None
        self._since_idx = 0
        self._settle_until = 0
        self._speeds: deque[tuple[int, float]] = deque()   # (sample since reset, r/min) of recent blocks
        self._step_until = 0        # no alarm counted before this sample (a level step)
        self._impulse = (0, 0)      # windows ending in this span do not count (impulse())
        self._levels: deque[tuple[int, float]] = deque(maxlen=8)   # (window end, median |x|)
        self._learn: list[float] = []
        self.baseline = self._fixed_baseline
        self._learned_baseline = self.baseline
        q = self.params["follow_quantile"]
        self._calm = SlidingQuantile(q, FOLLOW_WINDOWS) if q and self.params["cusum_ratio"] else None
        self._chattered = False     # the cut has alarmed: its calm windows since are chatter's tail
        self._load: float | None = None       # the cutting load now (set_load), and the sample it came at
        self._load_at = -1
        self._load_ref: float | None = None   # the load the baseline stands for
        self._load_wait: int | None = None    # a level step waits for a load reading after this sample
        self._load_waited = 0                 # no new wait before this sample (growth, not a new depth)
        self.alarm = False
        self._on = 0
        self._off = 0
        self._cusum = 0.0
        self._windows = 0           # windows since reset
        self._recent: deque[tuple[int, float]] = deque()   # (window end, raw) for the growth test
        self._grown = 0             # windows in a row that passed the growth test
        self._rising: list[tuple[float, float]] = []   # (index, level) of windows rising from a level step
        self._low = 0.0             # the lowest raw measure the growth test looked back at
        self._hold_raw = 0.0        # an alarm raised by growth holds while raw is above this
        self._eye_base_d: np.ndarray | None = None   # the cut's first counted window's d, for the eye
        self._eye_base: tuple[np.ndarray, np.ndarray, float] | None = None   # its eye, made once
        self._reset_extra()

    def _reset_extra(self) -> None:
        pass

    @property
    def learned(self) -> bool:
        return self.baseline is not None

    def set_baseline(self, raw: float) -> None:
        """Fix the baseline raw measure (e.g. stored from an earlier stable cut)."""
        if not raw > 0:
            raise ValueError(f"baseline must be > 0, got {raw}")
        self._fixed_baseline = self.baseline = float(raw)

    def set_load(self, load: float | None) -> None:
        """The cutting load now (the spindle load above its no-chip load, in any unit: only
        ratios count); used with ``load_scaled``.  None or <= 0 (no chip by the load, a
        light cut under the register's margin) is ignored: the last reading stands."""
        if load is not None and load > 0:
            self._load, self._load_at = float(load), self._total

    def learn_reference(self, signal: np.ndarray, rpm: float, block: int = 4096) -> float:
        """Learn the baseline from a recording of a stable cut at ``rpm``; it is
        then kept across ``reset``.  Returns the baseline raw measure."""
        self._fixed_baseline = None
        self.reset()
        raws: list[float] = []
        self._collect = raws
        try:
            sig = np.asarray(signal, dtype=float)
            for i in range(0, len(sig), block):
                self.process(sig[i:i + block], rpm)
        finally:
            self._collect = None
        if not raws:
            raise ValueError("reference recording is shorter than one window plus one revolution")
        self.set_baseline(float(np.median(raws)))
        self._ref_hook()
        self.reset()
        return self.baseline

    _collect: list[float] | None = None

    def _ref_hook(self) -> None:
        pass

    # -- streaming ----------------------------------------------------------------
    def _append(self, x: np.ndarray, rpm: float) -> None:
        k = len(x)
        if self._n + k > len(self._x):
            keep = min(self._n, len(self._x) // 2)
            cut = self._n - keep
            for buf in self._history().values():
                buf[:keep] = buf[cut:self._n]
            self._n = keep
            self._since_idx = max(self._since_idx - cut, -1)
        dth = 2 * np.pi * rpm / 60.0 / self.rate
        n0 = self._n
        self._x[n0:n0 + k] = x
        self._th[n0:n0 + k] = self._theta + dth * np.arange(1, k + 1)
        self._theta += dth * k
        self._n += k
        self._total += k
        self._d[n0:self._n] = self._x[n0:self._n] - self._delayed(n0, self._n)
        self._new_samples(n0, self._n)

    def _history(self) -> dict[str, np.ndarray]:
        """Per-sample history arrays kept aligned, by attribute (subclasses add theirs)."""
        return {"_x": self._x, "_th": self._th, "_d": self._d}

    def _grow(self, size: int) -> None:
        """Room for ``size`` samples of history, the valid ones kept (a slower speed's windows)."""
        for name, buf in self._history().items():
            new = np.empty(size)
            new[:self._n] = buf[:self._n]
            setattr(self, name, new)

    def _new_samples(self, start: int, end: int) -> None:
        """Hook: samples start..end (buffer indices) were appended, with ``_d``."""

    def process(self, block: np.ndarray, rpm: float) -> list[Window]:
        """Feed consecutive samples at spindle speed ``rpm``; returns the windows completed."""
        if not rpm > 0:
            raise ValueError(f"spindle speed must be > 0 r/min, got {rpm}")
        x = np.asarray(block, dtype=float).ravel()
        spr = self.rate * 60.0 / rpm
        if self._ramping(rpm, spr):
            # the speed may change all through the block: settle_revs from its end
            self._settle_until = self._total + len(x) + int(self.params["settle_revs"] * spr)
        if self._rpm is None or rpm != self._rpm:
            self._since_idx = self._n   # buffer index of the first sample at this speed
        self._rpm = rpm
        p = self.params
        w_len = int(max(p["window_revs"] * spr, p["min_window_s"] * self.rate))
        hop = int(max(p["hop_revs"] * spr, p["min_hop_s"] * self.rate))
        need = w_len + int(spr) + 2 + self._lead()
        if need > _HIST // 2:
            # too slow for a window plus a revolution of history (spindle
            # spinning up or down): drop the stream, keep baseline and alarm
            self.too_slow = True
            self._n = 0
            self._next_end = None
            self._rpm = None
            return []
        self.too_slow = False
        # history for two windows and their revolution, and the block: a trim keeps half
        room = min(_HIST, 1 << (2 * (need + len(x)) - 1).bit_length())
        if room > len(self._x):
            self._grow(room)
        self._append(x, rpm)
        if self._next_end is None:
            self._next_end = need
        out: list[Window] = []
        while self._next_end <= self._total:
            end = self._n - (self._total - self._next_end)
            start = end - w_len
            if start - int(spr) - 2 - self._lead() < 0:   # history trimmed: restart the count
                self._next_end += hop
                continue
            out.append(self._window(start, end, rpm))
            self._next_end += hop
        return out

    def _ramping(self, rpm: float, spr: float) -> bool:
        """The speed moved by more than ramp_per_rev over the last revolution (blocks of any
        size, a polled speed that steps every 100 ms): a ramp, whose forced response differs
        between revolutions; a slower drift (constant surface speed) is followed, not waited out."""
        q, now = self._speeds, self._total
        q.append((now, rpm))
        while len(q) > 1 and q[1][0] <= now - spr:
            q.popleft()                 # keep the newest block at least a revolution old
        revs = max((now - q[0][0]) / spr, 1.0)    # blocks longer than a revolution: per revolution
        return abs(rpm - q[0][1]) > self.params["ramp_per_rev"] * rpm * revs

    @property
    def min_rpm(self) -> float:
        """Lowest speed this detector can follow (below it blocks are dropped)."""
        p = self.params
        return self.rate * 60.0 * (p["window_revs"] + 1.0) / (_HIST // 2 - self._lead() - 4)

    def _lead(self) -> int:
        """Extra samples before the window a subclass needs (filter warm-up)."""
        return 0

    def _delayed(self, start: int, end: int) -> np.ndarray:
        """The signal one revolution earlier (in angle) for samples start..end."""
        spr = self.rate * 60.0 / self._rpm
        di = int(spr)
        first = start - di - 1
        if first >= 0 and first >= self._since_idx:
            # constant speed over the span: a fixed fractional delay, two slices
            fr = spr - di
            return (1.0 - fr) * self._x[start - di:end - di] + fr * self._x[start - di - 1:end - di - 1]
        q = self._th[start:end] - 2 * np.pi
        lo = int(np.searchsorted(self._th[:start], q[0])) - 1
        lo = max(lo, 0)
        # before any history: no difference (windows never reach back there)
        return np.interp(q, self._th[lo:end], self._x[lo:end], left=np.nan)

    def _window(self, start: int, end: int, rpm: float) -> Window:
        raw = float(self._measure(start, end, rpm))
        t_s = self._next_end / self.rate
        settling = self._next_end < self._settle_until
        if self._collect is not None:
            self._collect.append(raw)
            return Window(t_s, float("nan"), self.threshold, False, None, True, judged=False)
        self._windows += 1
        if self.params["load_scaled"] and self._load is not None:
            # the residual of a stable cut scales with the cutting force: the index is read
            # at the load the baseline was learned at (the first reading of the cut)
            if self._load_ref is None:
                self._load_ref = self._load
            raw /= (self._load / self._load_ref) ** self.RAW_POWER
        if self._eye_base_d is None and not settling and not self.OWN_EYE:
            self._eye_base_d = self._d[max(start - EYE_MEMORY, 0):end].copy()
        if self.baseline is None:
            if not settling:
                self._learn.append(raw)
            if len(self._learn) >= self.params["learn_windows"]:
                self.baseline = max(float(np.quantile(self._learn, self.params["learn_quantile"])), 1e-300)
                self._on_learned()
                self._learned_baseline = self.baseline
            med = float(np.median(self._learn)) if self._learn else float("nan")
            return Window(t_s, raw / med if med > 0 else float("nan"), self.threshold, False, None, True,
                          judged=False)
        index = raw / self.baseline
        p = self.params
        # a reference baseline skips the learning windows, not the entry's ring: the
        # cut's first learn_windows windows raise no alarm either way
        settling = settling or self._windows <= p["learn_windows"]
        raised_by = None
        if not self.alarm:
            # a step in the level within one revolution is the tool entering or leaving
            # the work, not regenerative chatter (which grows over several revolutions):
            # it, and the ring after it, do not count
            stepped = (self._level_step(start, end, rpm)
                       or self._impulse[0] < self._next_end <= self._impulse[1])
            other = settling or self._waiting_for_load(start, end, rpm)
            settling = other or stepped
            self._on = self._on + 1 if (index > self.threshold and not settling) else 0
            if self._rising_from_step(start, end, index, stepped, other) and not stepped:
                self._on = max(self._on, p["on_windows"])
            grew = self._growth(start, end, rpm, raw, settling)
            if self._on >= p["on_windows"]:
                raised_by = "threshold"
            elif grew:
                raised_by = "growth"
            elif self._cusum_says(index, settling):
                raised_by = "sustained rise"
            if raised_by:
                self.alarm, self._off = True, 0
                # an alarm raised by growth holds while the measure stays well above where the
                # growth started (the index may still be below the clear level when the
                # baseline was learned over the entry's ring)
                grew_from = self._low if raised_by == "growth" else 0.0
                self._hold_raw = p["off_ratio"] * p["growth_ratio"] * grew_from
                self._recent.clear()     # growth is looked for afresh once the alarm clears
                self._grown = 0
        else:
            # with a CUSUM, chatter held just above its allowance is still chatter
            clear = p["off_ratio"] * self.threshold
            if p["cusum_ratio"]:
                clear = min(clear, p["cusum_ratio"])
            held = self._hold_raw and raw > self._hold_raw    # a growth alarm's measure still up
            self._off = self._off + 1 if (index < clear and not held) else 0
            if self._off >= p["off_windows"]:
                self.alarm, self._on, self._cusum = False, 0, 0.0
        if self.alarm:
            self._chattered = True
        elif (self._calm is not None and not self._chattered and not settling
              and 0 < index < p["cusum_ratio"]):
            self._follow(raw)
        freq = self._chatter_frequency(start, end, rpm) if self.alarm else None
        return Window(t_s, index, self.threshold, self.alarm, freq, raised_by=raised_by,
                      judged=self.alarm or not settling)

    def _rising_from_step(self, start: int, end: int, index: float, stepped: bool, other: bool) -> bool:
        """A level step's windows do not count (their revolution difference spans the step),
        but chatter that starts with a deeper pass keeps rising through them: when a window
        at a step is over the threshold and each window after it is higher in index and in
        level (median |x|), the on_windows-th after it counts for the threshold rule, once
        its revolution difference is clear of the step.  A shoulder holds its level; the tool's
        entry or release rings down within two windows."""
        level = self._level(start, end, self._next_end)    # kept from _level_step: no new median
        chain = self._rising
        if other or index <= self.threshold:
            chain.clear()
        elif chain and (index <= chain[-1][0] or level <= chain[-1][1]):
            chain[:] = [(index, level)] if stepped else []
        elif chain or stepped:
            chain.append((index, level))
        return len(chain) > self.params["on_windows"]

    def _growth(self, start: int, end: int, rpm: float, raw: float, settling: bool) -> bool:
        """growth_ratio: on_windows windows in a row whose raw measure is growth_ratio x the
        lowest of the growth_revs revolutions before.  Regenerative chatter grows by that
        within a few revolutions whatever the baseline (one learned over the entry's ring sits
        2-5 x above the steady level); a stable cut's wander moves it by less than 2 x.  The
        look-back restarts at every settling window (entry, speed change, level step), and
        counts once it spans growth_revs revolutions.  The tool's release rings the structure
        and lifts the revolution difference as chatter does, but the ring decays within the
        window: a window whose second half is quieter than GROWTH_TAIL x its first does not count."""
        p = self.params
        r = p["growth_ratio"]
        if not r:
            return False
        if settling:
            self._recent.clear()
            self._grown = 0
            return False
        spr = self.rate * 60.0 / rpm
        span = int(p["growth_revs"] * spr)
        while self._recent and self._recent[0][0] < self._next_end - span:
            self._recent.popleft()
        # counted once the look-back spans growth_revs (to within a hop) of counted windows
        full = bool(self._recent) and self._recent[0][0] <= self._next_end - span + p["hop_revs"] * spr
        low = min(v for _, v in self._recent) if full else None
        self._low = low or 0.0
        self._recent.append((self._next_end, raw))
        grows = low is not None and raw > r * low and self._tail(start, end) >= GROWTH_TAIL
        self._grown = self._grown + 1 if grows else 0
        return self._grown >= p["on_windows"]

    def _tail(self, start: int, end: int) -> float:
        """The window's second half's level over its first half's (median |x|, a few hundred
        samples): a ring decaying within the window reads well below 1, growth above."""
        mid, step = (start + end) // 2, max(1, (end - start) // 256)
        first = median_abs(self._x[start:mid:step])
        return median_abs(self._x[mid:end:step]) / first if first > 0 else math.inf

    def _follow(self, raw: float) -> None:
        """A window below the CUSUM's allowance is the stable cut's own: the baseline rises to
        follow_quantile of the last FOLLOW_WINDOWS such windows.  Learned in the first
        revolutions, the baseline knows nothing of the cut's wander (+-20 % over tens of
        revolutions), and the allowance would sit inside it; where the entry's ring set it
        high, it stays (only ever raised), so chatter from entry is not learned away.  Not
        after the cut's first alarm: the windows below the allowance then are the chatter's
        decaying tail at the new speed, and following them would hide its return."""
        self._calm.push(raw)
        if len(self._calm) >= 2 * self.params["learn_windows"]:
            self.baseline = max(self._learned_baseline, self._calm.value())

    def impulse(self, at: int, rpm: float) -> None:
        """The cut state saw an impulse ``at`` samples into the next block fed (the tool's
        release ringing the structure, a knock): the windows whose revolution difference spans
        it do not count, as a level step's.  The release from a light cut rings it 5 x, but
        lifts a window's median |x| less than jump_ratio: _level_step cannot see it."""
        a = self._total + at
        self._impulse = (a, a + int((self.params["window_revs"] + 1.0) * self.rate * 60.0 / rpm))
        self._step_until = max(self._step_until, self._impulse[1])   # and its ring, as it decays

    def _level_step(self, start: int, end: int, rpm: float) -> bool:
        """True for a window whose median |x| is over jump_ratio x, or under 1/jump_ratio x,
        that of the revolution before it, and, within window_revs + 1 revolutions of such a
        window (the span whose revolution difference still sees the step), for every window
        whose level is below the revolution before's: the structure's ring after the tool's
        release decays for several revolutions and keeps that span open; chatter after a
        step (a deeper pass) grows, and counts at once."""
        di, now, before = self._level_pair(start, end, rpm)
        r = self.params["jump_ratio"]
        stepped = not before / r <= now <= before * r
        ringing = self._next_end < self._step_until and now < before
        if stepped or ringing:
            self._step_until = self._next_end + int((self.params["window_revs"] + 1.0) * di)
        return stepped or ringing

    def _waiting_for_load(self, start: int, end: int, rpm: float) -> bool:
        """With load_scaled, a level that rises by LOAD_STEP within a revolution may be a
        deeper pass whose load the polled register has not shown yet: the window does not
        count until a load reading newer than the step has come (at most LOAD_WAIT_S).
        A rise soon after such a wait is growth, not a new depth, and does not wait."""
        if not self.params["load_scaled"] or self._load_ref is None:
            return False
        if self._load_wait is not None:
            if self._load_at > self._load_wait or self._next_end > self._load_wait + LOAD_WAIT_S * self.rate:
                self._load_wait = None
                self._load_waited = self._next_end + int((self.params["window_revs"] + 1.0)
                                                         * self.rate * 60.0 / rpm)
                return False
            return True
        if self._next_end < self._load_waited:
            return False
        _, now, before = self._level_pair(start, end, rpm)
        if now > LOAD_STEP * before:
            self._load_wait = self._next_end - (end - start)   # the step is within this window
            return True
        return False

    def _level_pair(self, start: int, end: int, rpm: float) -> tuple[int, float, float]:
        """(samples a revolution, this window's level, the level a revolution earlier)."""
        di = int(self.rate * 60.0 / rpm)
        return (di, self._level(start, end, self._next_end),
                self._level(start - di, end - di, self._next_end - di))

    def _level(self, start: int, end: int, at: int) -> float:
        """Median |x| over buffer samples start..end, which end at sample ``at`` since reset.
        A window's level is kept: the window a revolution later compares with it (two hops
        of half a revolution), so each window costs one median, not two; a window ending
        within 2 samples of ``at`` (the revolution rounded to whole hops) is the same."""
        # the detector's cost per window was doubled by two full medians (5 ms CPU per
        # second of signal at 2000 r/min, as much as the rest of sync_cusum)
        for t, lv in self._levels:
            if abs(t - at) <= 2:
                return lv
        # a few hundred samples tell a level to a few %, enough against a ratio of 1.5 or more
        a = np.abs(self._x[start:end:max(1, (end - start) // 256)])
        lv = float(np.partition(a, len(a) // 2)[len(a) // 2])
        self._levels.append((at, lv))
        return lv

    def _cusum_says(self, index: float, settling: bool) -> bool:
        """Page's CUSUM on log(index): each window adds its log rise over the allowance
        cusum_ratio, at most log(threshold / cusum_ratio) (the sum never goes below 0);
        past on_windows x that (the evidence of on_windows windows at the threshold)
        it alarms, so it needs more than on_windows windows, each above the allowance.
        In log terms a gain change cancels; restarted while the speed settles and
        over a cut's entry."""
        r = self.params["cusum_ratio"]
        if not r or settling or not index > 0:
            self._cusum = 0.0
            return False
        # a window adds at most a threshold-high window's evidence: one spike (a chip
        # striking, a speed change's last ring) never alarms alone
        step = math.log(self.threshold / r)
        self._cusum = max(0.0, self._cusum + min(math.log(index / r), step))
        if self._cusum > self.params["on_windows"] * step:
            self._cusum = 0.0
            return True
        return False

    def _on_learned(self) -> None:
        pass

    # -- the chaos eye, for display -------------------------------------------------
    def eye_views(self) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray] | None]:
        """The paper's chaos eye drawn from this detector's revolution difference
        (the last EYE_REVS revolutions, and the cut's first counted window as the
        baseline, both scaled by that window's error): for the operator's screen only,
        computed when asked; the alarm is this detector's own.  chaos_sync draws
        its own eye from its windows."""
        from lathed.analysis.chaos_sync import eye_of_difference
        if self._eye_base_d is None or self._rpm is None or self._n == 0:
            return (np.empty(0), np.empty(0)), None
        if self._eye_base is None:     # the baseline's scale and points, once per cut
            self._eye_base = eye_of_difference(self._eye_base_d, memory=EYE_MEMORY)
        b1, b2, sigma = self._eye_base
        n = min(self._n, int(EYE_REVS * self.rate * 60.0 / self._rpm) + EYE_MEMORY, EYE_MAX_SAMPLES)
        p1, p2, _ = eye_of_difference(self._d[self._n - n:self._n], sigma, memory=EYE_MEMORY)
        return (p1, p2), (b1, b2)

    def _measure(self, start: int, end: int, rpm: float) -> float:
        raise NotImplementedError

    def _chatter_frequency(self, start: int, end: int, rpm: float) -> float | None:
        """Strongest peak of the non-synchronous part, refined by a parabola."""
        d = self._d[start:end]
        return spectral_peak_hz(d, self.rate, self.params["fmin_hz"], self.params["fmax_hz"])


class JudgedIndex:
    """The index of the windows a detector judged (``Window.judged``), one window late: the
    window where the tool leaves the work is judged before the next one shows the level step,
    so a judged window followed by one not judged is dropped.  What a part's record keeps."""

    def __init__(self) -> None:
        self._held: tuple[float, float] | None = None

    def reset(self) -> None:
        self._held = None

    def push(self, w: Window, t: float) -> tuple[float, float] | None:
        """This window; returns the (index, t) of the one before it if that one stands."""
        judged = getattr(w, "judged", True) and not math.isnan(w.index)   # a plugin's may lack it
        out = self._held if judged else None
        self._held = (w.index, t) if judged else None
        return out


def median_abs(x: np.ndarray) -> float:
    """np.median(np.abs(x)), bit for bit, without np.median's checks and copies: the
    windowed detectors' largest cost (a third of sync_cusum's time went to its wrappers)."""
    a = np.abs(x)
    n = len(a)
    k = n // 2
    if n % 2:
        a.partition(k)
        return float(a[k])
    a.partition((k - 1, k))
    return float((a[k - 1] + a[k]) / 2)


def spectral_peak_hz(x: np.ndarray, rate: float, fmin: float, fmax: float) -> float | None:
    n = len(x)
    if n < 8:
        return None
    nf = fast_len(n)
    spec = np.abs(np.fft.rfft(x * np.hanning(n), nf))
    f = np.arange(len(spec)) * rate / nf
    band = np.flatnonzero((f >= fmin) & (f <= min(fmax, rate / 2)))
    if band.size < 3:
        return None
    i = int(band[np.argmax(spec[band])])
    if 0 < i < len(spec) - 1:
        a, b, c = np.log(spec[i - 1:i + 2] + 1e-300)
        den = a - 2 * b + c
        off = 0.5 * (a - c) / den if den < 0 else 0.0
        return float((i + off) * rate / nf)
    return float(f[i])


class SyncResidualDetector(RevolutionDetector):
    """Robust rms (1.4826 * median |d|) of the revolution difference
    d = x(theta) - x(theta - 2 pi).  The median ignores a short burst such as
    the ringing at cut entry; continuous chatter moves it."""

    name = "sync_residual"

    def _measure(self, start: int, end: int, rpm: float) -> float:
        return 1.4826 * median_abs(self._d[start:end])


class SyncCusumDetector(SyncResidualDetector):
    """sync_residual with a CUSUM beside its threshold, and the median of the
    learning windows as baseline.  The robust rms is linear in the vibration
    amplitude, so a real stable cut's slow level wander (regen.Wander: the
    cutting force's random part wanders +-20 %) moves it by as much, where
    chaos_sync's bilinear eye grows with its square; a sustained rise of 20 %
    over the baseline then adds up to an alarm over tens of windows (mild
    chatter held by a worn flank), and a rise to the threshold alarms as
    fast as the threshold alone.  Allowance 1.2 and threshold 1.6 chosen on
    the simulated corpus (bench/bench_chatter.py, seed bases 100/1000/2000;
    3000/4000 held out), then checked once on the real recordings.

    Learned from steady cutting (a recording, a baseline re-learned after a
    speed change) rather than from a cut's entry, whose ring lifts it, the
    allowance sat inside the cut's own wander: 19 of 24 simulated 10 s stable
    cuts alarmed (bench_chatter.py's mid-cut table).  So the baseline rises
    to the 0.9 quantile of the cut's windows below the allowance
    (follow_quantile): 5 of 24 there (0.9 and the 256 windows were chosen on
    other seeds, where it went from 14 to 2 of 24).

    The baseline learned over the entry's ring sits 2-5 x above the steady
    level, so chatter starting mid-cut had to grow 4-8 x before the
    threshold saw it; the growth test (growth_ratio 2.5 over 4 revolutions)
    sees it at 2.5 x whatever the baseline: corpus median 3.6 -> 2.2
    revolutions, no new false alarm or miss (seed bases 100-4000; 5000 and
    6000, drawn after: 3.4 -> 3.0 and 2.5 -> 2.5); with the rising step
    (RevolutionDetector._rising_from_step) 2.0."""

    name = "sync_cusum"
    PARAMS = {
        "learn_quantile": (0.5, 0.0, 1.0, "quantile of the learning windows taken as baseline "
                           "(the median: a low quantile of a wandering start sets the baseline low)"),
        "cusum_ratio": (1.2, 0.0, 100.0, "0: off; else the CUSUM allowance as an index ratio "
                        "(1 < cusum_ratio < threshold): a sustained rise above it adds up to an alarm"),
        "threshold": (1.6, 1.05, 1000.0, "index above which a window counts as chatter; with "
                      "on_windows it also sets the CUSUM's decision level"),
        "follow_quantile": (0.9, 0.0, 0.99, "0: off; else the baseline rises to this quantile of the cut's "
                            "last 256 windows below the allowance (once there are 2 x learn_windows): "
                            "the CUSUM learns how far the stable cut wanders"),
        "growth_ratio": (2.5, 0.0, 100.0, "0: off; else on_windows windows in a row whose raw measure is this "
                         "many times the lowest of the growth_revs revolutions before raise the alarm: "
                         "chatter growing, whatever the baseline"),
        "min_hop_s": (0.005, 0.001, 1.0, "hop never shorter than this (above 3000 r/min the hop stays half a "
                      "revolution down to 6000: growth is seen as soon as at lower speeds)"),
    }


class SpectralRatioDetector(RevolutionDetector):
    """Largest spectral peak away from the spindle harmonics, over the median
    level of the band.  Needs several revolutions per window so that bins lie
    between the harmonics."""

    name = "spectral_ratio"
    RAW_POWER = 0.0   # a peak over the band's own median: the level cancels
    PARAMS = {
        "window_revs": (4.0, 2.0, 16.0, "window length in revolutions (>= 2 to resolve harmonics)"),
        "hop_revs": (1.0, 0.1, 4.0, "hop between windows in revolutions"),
        "min_window_s": (0.05, 0.01, 1.0, "window never shorter than this"),
        "harmonic_halfwidth_bins": (1.5, 0.5, 10.0, "bins masked either side of each spindle harmonic"),
        "threshold": (3.0, 1.05, 1000.0, "peak-ratio index above which a window counts as chatter"),
    }

    def _measure(self, start: int, end: int, rpm: float) -> float:
        x = self._x[start:end]
        n = len(x)
        nf = fast_len(n)
        ps = np.abs(np.fft.rfft((x - x.mean()) * np.hanning(n), nf)) ** 2
        df = self.rate / nf
        f = np.arange(len(ps)) * df
        frot = rpm / 60.0
        band = (f >= self.params["fmin_hz"]) & (f <= min(self.params["fmax_hz"], self.rate / 2))
        harm = np.abs(f / frot - np.round(f / frot)) * frot <= self.params["harmonic_halfwidth_bins"] * df
        sel = band & ~harm
        if not sel.any():
            return 0.0
        floor = float(np.median(ps[band])) or 1e-300
        self._last_peak = float(f[sel][np.argmax(ps[sel])])
        return float(ps[sel].max()) / floor

    def _chatter_frequency(self, start: int, end: int, rpm: float) -> float | None:
        return getattr(self, "_last_peak", None)


def fast_len(n: int) -> int:
    """The smallest 2^a 3^b 5^c >= n: an FFT length numpy's pocketfft does fast
    (scipy.fft would do, but costs the daemon a quarter second to import)."""
    best = 1 << max(n - 1, 0).bit_length()
    p5 = 1
    while p5 < best:
        p35 = p5
        while p35 < best:
            m = p35
            while m < n:
                m *= 2
            best = min(best, m)
            p35 *= 3
        p5 *= 5
    return best


Factory = Callable[..., Any]


def _chaos(rate_hz: float, **params: Any):
    from lathed.analysis.chaos_sync import ChaosSyncDetector
    return ChaosSyncDetector(rate_hz, **params)


DETECTORS: dict[str, Factory] = {
    "sync_residual": SyncResidualDetector,
    "sync_cusum": SyncCusumDetector,
    "spectral_ratio": SpectralRatioDetector,
    "chaos_sync": _chaos,
}

# Chosen from bench/bench_chatter.py on stable cutting that wanders as a real
# cut does (regen.Wander): sync_cusum misses none of the 20 chatter cases
# (chaos_sync misses 3 mild ones) and alarms on no stable or trap case
# (chaos_sync on one trap), median delay 2.0 revolutions (chaos_sync 5.9);
# on the real recordings it finds both chatter files and no stable one; in
# the closed loop (bench/bench_loop.py) it alarms 5.9-7.3 revolutions after
# chatter is visible, chaos_sync 13.6-25.4.  Its false alarms in the closed
# loop came at the end of stable cuts whose baseline was learned after a
# speed change at entry (the tool's release rings the structure: jump_ratio).
# See docs/benchmarks.md, chatter detectors.
DEFAULT_DETECTOR = "sync_cusum"


def make_detector(name: str, rate_hz: float, extra: dict[str, Factory] | None = None, **params: Any):
    """Build detector ``name``; ``extra`` (from the lathed_chatter_detectors
    hook) is merged over the built-ins."""
    table = {**DETECTORS, **(extra or {})}
    if name not in table:
        raise ValueError(f"unknown chatter detector {name!r}; allowed: {', '.join(sorted(table))}")
    return table[name](rate_hz, **params)


def describe_params(name: str) -> dict[str, tuple[float, float, float, str]]:
    """Parameters of a built-in detector: name -> (default, min, max, meaning)."""
    if name == "chaos_sync":
        from lathed.analysis.chaos_sync import ChaosSyncDetector as cls
    elif name in DETECTORS:
        cls = DETECTORS[name]
    else:
        raise ValueError(f"unknown chatter detector {name!r}; allowed: {', '.join(sorted(DETECTORS))}")
    return {**BASE_PARAMS, **cls.PARAMS}
