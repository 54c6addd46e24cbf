"""What counts towards a chatter alarm beyond the index over its threshold: the tool entering or
leaving (a level step) and the ring after it, chatter rising out of a step, growth whatever the
baseline, a sustained rise (CUSUM), the baseline following a stable cut's wander, and waiting for
the load (docs/chatter.md).  A mixin of RevolutionDetector: these methods read its buffers."""
from __future__ import annotations

import math

import numpy as np

from lathed.analysis.chatter.spectrum import median_abs

LOAD_STEP = 1.3       # load_scaled: a level rising this much within a revolution waits for the load
LOAD_WAIT_S = 0.3     # ... for at most this long (a 100 ms poll and its jitter; a load that stops coming)
GROWTH_TAIL = 0.3      # growth: a window's second half at least this x its first's level (a release's: 0.2 x)
# a level is the median |x| of a few hundred samples (_level), good to ~7 % (its standard error
# 1.17 / sqrt(n)): two of them on a plateau differ by ~10 % by chance, where a release's ring falls
# by 2 x or more a revolution; so a level "falls" (a ring decaying) only when it is under this x
# the one it is compared with (at 1.0, chatter's plateau read as a ring by a 0.2 % dip)
LEVEL_FALL = 0.9
# a stable shoulder's regenerative echo near the limit (0.8-0.9 x) rises for 2-3 revolutions after
# the step before it decays (at 4500 r/min its revolution difference 3-14 x the pre-step level at
# 2-3.5 revolutions: bench/step_bound.py's drawn shoulders, seeds from 30000): growth out of a
# step is judged from this many revolutions after the span's first window (0.4-1 after the step)
ECHO_REVS = 2.5


class AlarmRules:
    """The rules RevolutionDetector._window applies to each window (state kept on the detector)."""

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
        # ... or reaches back to a shoulder's step (_shoulder): a look-back from a steady level
        full = full or (bool(self._recent) and self._recent[0][0] == self._recent_from)
        low = min(v for _, v in self._recent) if full else None
        self._low = low or 0.0
        self._recent.append((self._next_end, raw))
        grows = low is not None and raw > r * low and self._tail(start, end) >= GROWTH_TAIL
        self._grown = self._grown + 1 if grows else 0
        return self._grown >= p["on_windows"]

    def _shoulder(self, start: int, end: int, rpm: float, raw: float, other: bool,
                  stepped: bool = False) -> tuple[bool, bool]:
        """A deeper pass (a shoulder, a step in the stock): (this window is in its span, chatter
        grew out of it).  rise_ratio: a window whose level is that many times the level a
        revolution earlier, from a cut at its own steady level, is the chip thickening.  Its
        first revolutions look the same whether the deeper pass is stable or not: the level
        steps with the chip, and a stable cut near its limit then rises further, its regenerative
        echo dying over several revolutions (2-5 x the level before on the simulated shoulders
        to 0.87 x the limit).  So the span whose revolution difference still sees the step
        (window_revs + 1 revolutions) is not judged, but for growth beyond rise_growth x its
        lowest window: a stable echo is smaller every revolution than the one before, so two
        revolutions on it stays under 3 x the first, while chatter's grows.  At the span's end a
        level still rising is judged as it is, against the baseline before the step; a level that
        has settled is the deeper pass's own: the baseline (and the spectrum's shape) is learned
        again there, and chatter must rise from it.  Not within the cut's first revolutions
        (chatter from the entry grows in steps too) nor from out of the cut (a gap's re-entry).
        Off with a reference baseline, which vouches for the level (docs/chatter.md).

        The tool leaving the work at the pass's end starts a span too when the release falls late
        in a window (its level then rises 1.5-3 x, not the jump it is): the ring's windows after
        it are 3-5 x that first one, as chatter's would be.  But the ring jumps (``stepped``: a
        level step by jump_ratio, the tool entering or leaving) and then falls window after
        window, where chatter keeps rising: neither counts as growth.  (Which windows a release
        straddles depends on where it falls on the window grid: in the live daemon on a loaded
        host, on when a cure's speed reached the machine; 11 of the 40 pass ends of
        test_no_alarm_wherever_a_stable_pass_ends_on_the_window_grid alarmed.)"""
        p = self.params
        r = p["rise_ratio"]
        if not r or self._fixed_baseline is not None:
            return False, False
        _, now, before = self._level_pair(start, end, rpm)
        up = now > r * before
        prev, self._prev_raw = self._prev_raw, raw
        # windows in a row before this one over the sum's allowance
        over, self._sh_over = self._sh_over, (self._sh_over + 1 if p["cusum_ratio"] and raw > p["cusum_ratio"]
                                              * self.baseline else 0)
        self._sh_over_before = over
        if self._sh_until:
            # growing beyond the echo's bound, not a knock's or the release's ring: a jump, then a
            # level falling from one window to the next (and within the window: the growth test's
            # tail); the span's last window too, before its level is taken as the deeper pass's
            low = min(v for v, _ in self._sh_raws)
            grows = (p["growth_ratio"] > 0 and raw > p["rise_growth"] * low and not stepped
                     and now >= LEVEL_FALL * max(before, self._sh_level)
                     and self._tail(start, end) >= GROWTH_TAIL)
            self._sh_level = now
            self._sh_grown = self._sh_grown + 1 if grows else 0
            if self._sh_grown >= p["on_windows"] and self._past_echo(rpm, raw):
                self._sh_until = 0
                return True, True
            # (a window grown past the bound at the span's end is followed one more: where the span
            # ends is the window grid's, not the chatter's; a stable echo falls back there)
            if self._next_end < self._sh_until or self._sh_grown:
                self._sh_raws.append((raw, self._bands()))
                return True, False
            self._sh_until = 0
            self._grown = 0                 # growth within the span was judged against its bound
            if not up and now >= math.sqrt(r) * self._sh_from:
                # the level held up where the step took it: a deeper pass (one fallen back is a
                # swell, as a flat's impacts beat with chatter; one still rising is growth: both
                # judged as they are); growth from the deeper pass's own level on
                self._recent.clear()
                self._recent_from = self._next_end
                last = self._sh_raws[-2:]
                level = float(np.median([v for v, _ in last]))
                self.baseline = max(self.baseline, level)
                self._learned_baseline = max(self._learned_baseline or 0.0, level)
                self._cusum = 0.0
                self._shape_now()               # this window's gate reads the shape before the step
                self._shape.reset()
                for _, b in last:
                    self._shape.learn(b)
            return False, False
        if not up:
            # a step from a cut at its own level: growth_revs revolutions without a rise (chatter
            # growing, or beating with a flat's impacts, rises again within a few)
            self._sh_steady += 1
            return False, False
        steady, self._sh_steady = self._sh_steady, 0
        # a step up by more than jump_ratio from a cut at its own level (not a release's impulse,
        # nor within an earlier step's ring) is a deeper pass too: a stable 0.5 -> 1.3 mm shoulder
        # at 1000 r/min lifts the level 3.6 x in a window; taken as the tool's entry, its deeper
        # level was judged against the shallower pass's baseline once its ring stopped falling
        jump_up = (stepped and now > p["jump_ratio"] * before and self._next_end >= self._step_before
                   and not self._impulse[0] < self._next_end <= self._impulse[1])
        other = other or (stepped and not jump_up)
        if (other or steady < 2 * p["growth_revs"] / p["hop_revs"] or self._windows <= 2 * p["learn_windows"]
                or self._next_end < self._step_before
                or prev < self._learned_baseline / p["jump_ratio"] ** 2
                or self._sh_over_before >= p["on_windows"]):
            # (a level already held over the sum's allowance is rising, not a cut at its own level)
            return False, False
        self._sh_until = self._next_end + int((p["window_revs"] + 1.0) * self.rate * 60.0 / rpm)
        self._sh_start = self._next_end
        self._sh_jump = jump_up             # chatter rising through a jump still counts (_rising_from_step)
        self._sh_raws = [(raw, self._bands())]
        self._sh_from = before              # the level before the step
        self._sh_level = now                # the span's last window's level
        self._sh_grown = 0
        self._recent.clear()            # growth is looked for from the step on, not across it
        self._grown = 0
        self._recent_from = self._next_end
        return True, False

    def _past_echo(self, rpm: float, raw: float | None = None) -> bool:
        """A deeper pass's growth counts only once a stable echo would have peaked (ECHO_REVS
        after the span's first window) and, given ``raw``, while the measure still rises over
        the revolution before by more than a level's chance spread (1 / LEVEL_FALL): a stable
        echo near the limit grows 2-5 x for 2-3 revolutions, as chatter does, then falls;
        chatter keeps rising."""
        spr = self.rate * 60.0 / rpm
        if self._next_end < self._sh_start + ECHO_REVS * spr:
            return False
        if raw is None:
            return True
        # the last window at least a revolution before (a hop over half a revolution, above
        # 6000 r/min, puts none exactly there)
        at = self._next_end - int(spr) + 2
        prev = None
        for t, v in self._raw_hist:
            if t <= at:
                prev = v
        return prev is not None and raw * LEVEL_FALL >= prev

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
        self._step_before = self._step_until     # the span of a step before this window's
        di, now, before = self._level_pair(start, end, rpm)
        r = self.params["jump_ratio"]
        stepped = not before / r <= now <= before * r
        # the vibration falling as the revolution difference rises is the tool leaving an
        # interrupted cut (its impacts repeat every revolution and cancel, until the air a
        # revolution later meets them), not chatter, which adds to the vibration
        # the revolution difference outgrowing the vibration itself by jump_ratio within a
        # revolution: the revolution before holds what the cut no longer makes (the tool leaving
        # an interrupted cut, whose impacts cancelled while they repeated; its ring keeps the
        # level up), not chatter, which grows into the vibration as into its revolution difference
        if before > 0 and self.params.get("rise_ratio"):
            at = self._next_end - di          # the window a revolution before's raw measure
            raw_before = next((v for t, v in self._raw_hist if abs(t - at) <= 2), None)
            if raw_before:
                stepped = stepped or (self._raw_now / raw_before) / (now / before) >= r
        ringing = self._next_end < self._step_until and now < LEVEL_FALL * before
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
        """(samples a revolution, this window's level, the level a revolution earlier); kept for
        the window (the level step, the shoulder and the load's wait each ask for it)."""
        key = (self._next_end, start, end, rpm)
        if self._pair[:4] == key:
            return self._pair[4]
        di = int(self.rate * 60.0 / rpm)
        pair = (di, self._level(start, end, self._next_end), self._level(start - di, end - di, self._next_end - di))
        self._pair = (*key, pair)
        return pair

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
        a.partition(len(a) // 2)               # in place: np.partition's copy and wrapper spared
        lv = float(a[len(a) // 2])
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
