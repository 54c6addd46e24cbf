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
                     detector (chaos_sync.py).

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
from typing import Any

import numpy as np

from lathed.analysis.chatter.eye import eye_of_difference
from lathed.analysis.chatter.rules import AlarmRules
from lathed.analysis.chatter.shape import SpectralShape
from lathed.analysis.chatter.spectrum import median, spectral_peak_hz
from lathed.analysis.chatter.windows import BASE_PARAMS, Window
from lathed.analysis.quantile import SlidingQuantile

FOLLOW_WINDOWS = 256   # windows a follow_quantile baseline looks back over (128 revolutions at the default hop)
MIN_WINDOW_SAMPLES = 16
_HIST = 1 << 19   # most samples of history kept (10 s at 51.2 kS/s): sets the lowest speed followed
_HIST_START = 1 << 15   # history a detector starts with (0.6 s at 51.2 kS/s: 2 revolutions at 200 r/min);
                        # it grows to what a slower speed needs, up to _HIST (most cuts never need it)
EYE_REVS = 4      # revolutions of a display eye (eye_views)
EYE_MEMORY = 64   # its GL filter's memory, samples
EYE_MAX_SAMPLES = 16384   # at most this many samples filtered per view (a slow spindle's 4 revolutions)


class RevolutionDetector(AlarmRules):
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
        # the angle of each sample (_th) is made only when a speed change asks for it (_delayed):
        # _th[:_th_ok] is made, and each block after it waits as (buffer start, samples, angle
        # step, angle before it)
        self._th_ok = 0
        self._th_todo: list[tuple[int, int, float, float]] = []
        self._total = 0             # samples seen since reset
        self._theta = 0.0
        self._next_end: int | None = None
        self._rpm: float | None = None
        self._since_idx = 0
        self._settle_until = 0
        self._speeds: deque[tuple[int, float]] = deque()   # (sample since reset, r/min) of recent blocks
        self._step_until = 0        # no alarm counted before this sample (a level step)
        self._step_before = 0       # ... as it stood before the window being judged (_level_step)
        self._impulse = (0, 0)      # windows ending in this span do not count (impulse())
        self._levels: deque[tuple[int, float]] = deque(maxlen=8)   # (window end, median |x|)
        self._pair: tuple = ()      # the last window's pair of levels (_level_pair): sample counts restart
        self._raw_hist: deque[tuple[int, float]] = deque(maxlen=8)     # (window end, raw measure)
        self._raw_now = 0.0
        self._learn: list[float] = []
        self._sh_until = 0          # a shoulder's span ends at this sample (0: none; _shoulder)
        self._sh_raws: list = []    # (raw, bands) of its windows
        self._sh_steady = 0         # windows in a row without a rise: a rise after enough is a step
        self._sh_grown = 0
        self._sh_start = 0          # its first window's end
        self._sh_jump = False       # its span began with a jump (a level over jump_ratio x)
        self._sh_from = 0.0         # the level before its step
        self._sh_level = 0.0        # its last window's level (a ring falls from it, chatter rises)
        self._sh_over = self._sh_over_before = 0   # windows in a row over the sum's allowance
        self._prev_raw = 0.0
        self._recent_from = -1      # the growth look-back counts from this window (a shoulder's)
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
        if self._fixed_baseline is None or not hasattr(self, "_shape"):   # a reference's shape is kept
            self._shape = SpectralShape(self.rate, self.params["fmin_hz"], self.params["fmax_hz"])
        self.shape = math.nan               # the last window's shape index (SpectralShape), nan unless the
                                            # shape gate looked at it (_shape_now)
        self._span: tuple[int, int] = (0, 0)     # the window being judged (buffer indices)
        self._wb: np.ndarray | None = None       # its band powers, once made (_bands)
        self._made = False                       # its shape index made (_shape_now)
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
            for name, buf in self._history().items():
                if name != "_th":
                    buf[:keep] = buf[cut:self._n]
            if self._th_ok > cut:
                self._th[:self._th_ok - cut] = self._th[cut:self._th_ok]
            self._th_ok = max(self._th_ok - cut, 0)
            # the blocks whose angle waits move with the buffer (those now before it are gone)
            self._th_todo = [(n0 - cut, n, dth, th0) for n0, n, dth, th0 in self._th_todo if n0 + n > cut]
            self._n = keep
            self._since_idx = max(self._since_idx - cut, -1)
        dth = 2 * np.pi * rpm / 60.0 / self.rate
        n0 = self._n
        self._x[n0:n0 + k] = x
        self._th_todo.append((n0, k, dth, self._theta))
        self._theta += dth * k
        self._n += k
        self._total += k
        d = self._d[n0:self._n]
        self._delayed(n0, self._n, d)
        np.subtract(self._x[n0:self._n], d, out=d)
        self._new_samples(n0, self._n)

    _steps = np.empty(0)

    def _angles(self) -> None:
        """Make _th up to the last sample: theta + dth * (1..k) for each block that waits (its
        part still in the buffer), without temporaries, as each block's was made at once."""
        th = self._th
        for n0, k, dth, th0 in self._th_todo:
            if len(self._steps) < k:
                self._steps = np.arange(1, k + 1, dtype=np.float64)     # sample steps, made once
            j0 = max(0, -n0)           # a block the last trim cut into: its part still kept
            out = th[n0 + j0:n0 + k]
            np.multiply(self._steps[j0:k], dth, out=out)
            out += th0
        self._th_todo.clear()
        self._th_ok = self._n

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
        # a 1-D array is cast as _append copies it in (a float32 block: no float64 copy first)
        x = block if type(block) is np.ndarray and block.ndim == 1 else np.asarray(block, dtype=float).ravel()
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
            self._n = self._th_ok = 0
            self._th_todo.clear()
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

    def _delayed(self, start: int, end: int, out: np.ndarray) -> None:
        """The signal one revolution earlier (in angle) for samples start..end, into ``out``."""
        spr = self.rate * 60.0 / self._rpm
        di = int(spr)
        first = start - di - 1
        if first >= 0 and first >= self._since_idx:
            # constant speed over the span: a fixed fractional delay, two slices (the products
            # and their sum made in ``out``, without temporaries: the same numbers)
            fr = spr - di
            np.multiply(self._x[start - di:end - di], 1.0 - fr, out=out)
            out += np.multiply(self._x[start - di - 1:end - di - 1], fr)
            return
        if self._th_todo:
            self._angles()
        q = self._th[start:end] - 2 * np.pi
        lo = int(np.searchsorted(self._th[:start], q[0])) - 1
        lo = max(lo, 0)
        # before any history: no difference (windows never reach back there)
        out[:] = np.interp(q, self._th[lo:end], self._x[lo:end], left=np.nan)

    def _window(self, start: int, end: int, rpm: float) -> Window:
        raw = float(self._measure(start, end, rpm))
        t_s = self._next_end / self.rate
        settling = self._next_end < self._settle_until
        if self._collect is not None:
            self._collect.append(raw)
            self._shape.learn(self._shape.bands(self._d[start:end]))
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
        # the window's band powers and shape index, made when first needed (_bands, _shape_now)
        self._span, self._wb, self._made, self.shape = (start, end), None, False, math.nan
        if self.baseline is None:
            if not settling:
                self._learn.append(raw)
                self._shape.learn(self._bands())
            if len(self._learn) >= self.params["learn_windows"]:
                self.baseline = max(float(np.quantile(self._learn, self.params["learn_quantile"])), 1e-300)
                self._on_learned()
                self._learned_baseline = self.baseline
            # np.median bit for bit, without its wrappers (every learning window)
            med = median(np.array(self._learn, dtype=float)) if self._learn else float("nan")
            return Window(t_s, raw / med if med > 0 else float("nan"), self.threshold, False, None, True,
                          judged=False)
        index = raw / self.baseline
        self._raw_now = raw
        self._raw_hist.append((self._next_end, raw))
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
            # a deeper pass: its span is not judged but for growth beyond a stable echo's (not
            # a step's: the tool leaving, whose release may fall late in the span's first window)
            shoulder, grew_out = self._shoulder(start, end, rpm, raw, other, stepped)
            index = raw / self.baseline         # the deeper pass may have its own baseline now
            settling = other or stepped or shoulder
            # a level alone is not chatter: the threshold and the CUSUM need the spectrum's shape
            # changed (but against a reference, which vouches for the level)
            gated = bool(p["shape_min"]) and self._fixed_baseline is None
            self._on = self._on + 1 if (index > self.threshold and not settling
                                        and (not gated or self._shape_now() >= p["shape_min"])) else 0
            # (a deeper pass's jump too: a stable one's level falls back within a revolution, but
            # near the limit its echo rises for 2-3 revolutions first: not before rules.ECHO_REVS)
            jumped = shoulder and self._sh_jump
            if (self._rising_from_step(start, end, index, stepped, other or (shoulder and not jumped))
                    and not (stepped or (shoulder and not jumped)) and not (shoulder and not self._past_echo(rpm))):
                self._on = max(self._on, p["on_windows"])
            grew = self._growth(start, end, rpm, raw, settling and not shoulder)
            grew = (grew and not shoulder) or grew_out
            if self._on >= p["on_windows"]:
                raised_by = "threshold"
            elif grew:
                raised_by = "growth"
            elif self._cusum_says(index, settling) and (not gated or self._shape_now() >= p["shape_min"]):
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
            self._shape.learn(self._bands())
        freq = self._chatter_frequency(start, end, rpm) if self.alarm else None
        return Window(t_s, index, self.threshold, self.alarm, freq, raised_by=raised_by,
                      judged=self.alarm or not settling, shape=self.shape)

    def _on_learned(self) -> None:
        pass

    def _bands(self) -> np.ndarray:
        """This window's band powers (SpectralShape.bands), made once when first needed: by the
        shape gate, the shape's baseline learning, a deeper pass's span; an alarm's windows and
        those the gate does not reach never need them (an FFT a window saved)."""
        if self._wb is None:
            start, end = self._span
            self._wb = self._shape.bands(self._d[start:end])
        return self._wb

    def _shape_now(self) -> float:
        """This window's shape index (``shape``), against the baseline's bands as they were when
        the window began: made before anything in the window learns them (_shoulder's end)."""
        if not self._made:
            self.shape, self._made = self._shape.index(self._bands()), True
        return self.shape

    # -- the chaos eye, for display -------------------------------------------------
    def eye_views(self) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray] | None]:
        """The paper's chaos eye drawn from this detector's revolution difference
        (the last EYE_REVS revolutions, and the cut's first counted window as the
        baseline, both scaled by that window's error): for the operator's screen only,
        computed when asked; the alarm is this detector's own.  chaos_sync draws
        its own eye from its windows."""
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
