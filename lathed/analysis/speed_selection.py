"""Spindle speed selection (SSS) against chatter, and the policy that decides
when to act.  Pure Python/numpy: the daemon's analyzer plugin, the
``lathectl suppress`` command and the benches all drive the same objects.

Strategies (each has ``select(rpm_now, chatter_frequency_hz, avoid) -> Decision``):

* ``FrequencySelection`` - no modal model: put the revolution frequency at the
  measured chatter frequency divided by an integer N, so the wave left on the
  surface is in phase with the one being cut and the regenerative chip
  variation vanishes; of the speeds 60*fc/N the machine can drive, the highest
  (largest removal rate).
* ``LobeSelection`` - a modal model is configured: the highest speed whose
  limiting depth exceeds the depth of cut by a margin, over a speed band wide
  enough to survive model error, that the spindle's torque and power allow.
* ``RatedSpeed`` - the paper's rule: drop to a configured rated speed.
* ``VariationSelection`` - keep the speed, modulate it (speed_variation.py).

When the lobes say every speed within reach chatters at the cut's depth,
moving only trades one chatter for another (the benchmark's closed loop:
such moves chattered again).  A policy set to hold
(``when_no_stable_speed = "hold"``) then keeps the speed and returns an
``Advice``: the model's limit depth here and at the best speed within reach,
i.e. what would cure it (a shallower cut, a stiffer set-up).

Removal rate in turning is depth * feed * cutting speed, so at fixed depth,
feed and diameter it scales with the spindle speed: the decision's
``removal_rate_ratio`` is rpm_after / rpm_before.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from typing import Protocol, Sequence

import numpy as np

from lathed.analysis.lobes import StabilityLobes
from lathed.analysis.speed_variation import SpeedVariation, ramp_time_s


@dataclass(frozen=True)
class SpindleLimits:
    """Spindle drive envelope.  Torque is flat up to ``base_rpm`` and falls as
    constant power above it (the MC4200: 35.8 N*m peak at 1500 r/min)."""
    max_rpm: float = 6000.0
    min_rpm: float = 100.0
    peak_torque_nm: float = 35.8
    base_rpm: float = 1500.0
    max_power_w: float | None = None      # default: peak torque at base speed
    accel_rpm_per_s: float = 2000.0

    @property
    def power_w(self) -> float:
        if self.max_power_w is not None:
            return self.max_power_w
        return self.peak_torque_nm * self.base_rpm * 2 * math.pi / 60

    def torque_available(self, rpm: np.ndarray | float) -> np.ndarray:
        n = np.asarray(rpm, dtype=float)
        omega = n * 2 * math.pi / 60
        with np.errstate(divide="ignore"):
            by_power = np.where(omega > 0, self.power_w / np.maximum(omega, 1e-12), np.inf)
        return np.minimum(self.peak_torque_nm, by_power)


@dataclass(frozen=True)
class Cut:
    """The programmed cut.  ``kt_n_per_m2`` is the tangential (cutting-force)
    coefficient: it sets the spindle torque; the chatter model's Kf is the
    force along the chip-thickness direction and lives in the lobes."""
    depth_m: float
    feed_m_per_rev: float
    diameter_m: float
    kt_n_per_m2: float

    @property
    def torque_nm(self) -> float:
        return self.kt_n_per_m2 * self.depth_m * self.feed_m_per_rev * self.diameter_m / 2

    def removal_rate_mm3_s(self, rpm: float) -> float:
        v = math.pi * self.diameter_m * rpm / 60          # cutting speed, m/s
        return self.depth_m * self.feed_m_per_rev * v * 1e9

    def drivable(self, rpm: np.ndarray | float, limits: SpindleLimits) -> np.ndarray:
        """Speeds within the speed range where the spindle has the torque."""
        n = np.asarray(rpm, dtype=float)
        return ((n >= limits.min_rpm) & (n <= limits.max_rpm)
                & (self.torque_nm <= limits.torque_available(n)))


@dataclass(frozen=True)
class Decision:
    strategy: str
    rpm_before: float
    rpm_after: float
    chatter_frequency_hz: float | None
    expected_b_lim_mm: float | None       # from the lobes, where known
    expected_stable: bool | None          # None: no model to say
    removal_rate_ratio: float
    reason: str
    variation: SpeedVariation | None = None
    chatter_index: float | None = None
    threshold: float | None = None

    def record(self) -> dict:
        """Critical values for the event store."""
        d = asdict(self)
        d["variation"] = None if self.variation is None else asdict(self.variation)
        return d


@dataclass(frozen=True)
class Advice:
    """No move: the model says every speed within reach chatters at this depth (its
    b_lim there is below the depth).  ``safe_depth_mm``: the depth the lobe rule would
    call stable at ``rpm`` (the worst b_lim within +-band over the margin)."""
    rpm: float
    depth_mm: float
    limit_mm: float               # the model's b_lim at ``rpm``
    best_rpm: float               # the speed within reach with the highest b_lim
    best_limit_mm: float
    safe_depth_mm: float
    min_rpm: float                # the reach: the spindle's range under the speed cap,
    max_rpm: float                # where the cut's torque is available
    chatter_frequency_hz: float | None = None
    chatter_index: float | None = None
    threshold: float | None = None

    @property
    def advice(self) -> str:
        # a cusp above the depth, narrower than the speed band, is no speed to move to
        cusp = " on a cusp narrower than the lobes' speed band" if self.best_limit_mm > self.depth_mm else ""
        return (f"no stable speed within {self.min_rpm:.0f}-{self.max_rpm:.0f} r/min at {self.depth_mm:.2f} mm: "
                f"the model's limit is {self.limit_mm:.2f} mm at {self.rpm:.0f} r/min, at best "
                f"{self.best_limit_mm:.2f} mm ({self.best_rpm:.0f} r/min){cusp}; speed held: reduce the depth of cut "
                f"below {self.safe_depth_mm:.2f} mm (stable here with the lobes' margin) or stiffen the set-up")

    def record(self) -> dict:
        return {**asdict(self), "advice": self.advice}


WHEN_NO_STABLE_SPEED = ("hold", "move")


class Strategy(Protocol):
    name: str

    def select(self, rpm_now: float, chatter_frequency_hz: float | None,
               avoid: Sequence[tuple[float, float]] = ()) -> Decision | None: ...


def _allowed(n: np.ndarray, avoid: Sequence[tuple[float, float]]) -> np.ndarray:
    ok = np.ones(n.shape, bool)
    for lo, hi in avoid:
        ok &= ~((n >= lo) & (n <= hi))
    return ok


@dataclass
class FrequencySelection:
    limits: SpindleLimits
    cut: Cut | None = None
    name: str = "sss_frequency"

    def select(self, rpm_now, chatter_frequency_hz, avoid=()):
        if chatter_frequency_hz is None or not chatter_frequency_hz > 0:
            return None          # nothing to tune to
        waves = np.arange(1, int(60 * chatter_frequency_hz / self.limits.min_rpm) + 1)
        n = 60 * chatter_frequency_hz / waves
        ok = (n >= self.limits.min_rpm) & (n <= self.limits.max_rpm) & _allowed(n, avoid)
        if self.cut is not None:
            ok &= self.cut.drivable(n, self.limits)
        if not ok.any():
            return None
        i = int(np.flatnonzero(ok)[0])             # highest speed that fits
        return Decision(self.name, rpm_now, float(n[i]), chatter_frequency_hz, None, None,
                        float(n[i]) / rpm_now,
                        f"revolution frequency = {chatter_frequency_hz:.1f} Hz / {waves[i]} waves")


def lobe_grid(lobes: StabilityLobes, limits: SpindleLimits, band: float = 0.03,
              resolution: int = 6000) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Speeds over the spindle's range, their b_lim, and the worst b_lim within
    +-band of each. It depends on the structure only, not on the cut, so a
    daemon computes it once (tens of ms) rather than at every alarm."""
    n = np.linspace(limits.min_rpm, limits.max_rpm, resolution)
    b, _ = lobes.b_lim_at(n)
    half = np.maximum(1, np.round(band * n / (n[1] - n[0])).astype(int))
    worst = np.array([b[max(0, i - h):i + h + 1].min() for i, h in enumerate(half)])
    return n, b, worst


@dataclass
class LobeSelection:
    lobes: StabilityLobes
    cut: Cut
    limits: SpindleLimits
    margin: float = 1.15         # depth must stay this far below b_lim
    band: float = 0.03           # ... over +-3 % of speed (model error, speed ripple)
    resolution: int = 6000
    name: str = "sss_lobes"
    grid: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None   # from lobe_grid(), shared

    def select(self, rpm_now, chatter_frequency_hz, avoid=()):
        if self.grid is None:
            self.grid = lobe_grid(self.lobes, self.limits, self.band, self.resolution)
        n, b, worst = self.grid
        ok = self.cut.drivable(n, self.limits) & _allowed(n, avoid)
        stable = ok & (worst >= self.margin * self.cut.depth_m)
        if stable.any():
            i = int(np.flatnonzero(stable)[-1])
            reason = (f"highest speed with b_lim >= {self.margin:g} x depth over "
                      f"+-{self.band:.0%} of speed")
            ok_stable = True
        elif ok.any():
            # no stable speed the machine can drive: the most stable one
            i = int(np.flatnonzero(ok)[np.argmax(worst[ok])])
            reason = "no stable speed within the spindle limits; most stable drivable speed"
            ok_stable = False
        else:
            return None
        return Decision(self.name, rpm_now, float(n[i]), chatter_frequency_hz,
                        float(b[i] * 1e3), ok_stable, float(n[i]) / rpm_now, reason)

    def limit_mm(self, rpm: float) -> float:
        """The worst b_lim within +-band of ``rpm``, mm: the limit this rule judges a speed by."""
        if self.grid is None:
            self.grid = lobe_grid(self.lobes, self.limits, self.band, self.resolution)
        n, _, worst = self.grid
        return float(np.interp(rpm, n, worst)) * 1e3

    def advise(self, rpm_now: float, chatter_frequency_hz: float | None = None,
               avoid: Sequence[tuple[float, float]] = ()) -> Advice | None:
        """When the model says the speed this rule would move to chatters at the cut's depth
        (its b_lim below it), what would cure it; None when that speed's b_lim is above the
        depth (if not by the margin, a move there is the bet the margin leaves open) or
        nothing is drivable.  The speed it would move to is the most stable one over the band
        among those not in ``avoid``: a peak of b_lim above the depth narrower than the band is
        not where it goes, so it does not stand against the hold."""
        robust_mm = self.limit_mm(rpm_now)     # builds the grid when not yet there
        n, b, worst = self.grid
        ok = self.cut.drivable(n, self.limits)
        if not ok.any():
            return None
        i = int(np.flatnonzero(ok)[np.argmax(b[ok])])
        left = ok & _allowed(n, avoid)
        if left.any() and b[int(np.flatnonzero(left)[np.argmax(worst[left])])] > self.cut.depth_m:
            return None
        return Advice(rpm_now, self.cut.depth_m * 1e3, float(np.interp(rpm_now, n, b)) * 1e3, float(n[i]),
                      float(b[i]) * 1e3, robust_mm / self.margin, float(n[ok][0]), float(n[ok][-1]),
                      chatter_frequency_hz)


@dataclass
class RatedSpeed:
    rated_rpm: float
    lobes: StabilityLobes | None = None
    cut: Cut | None = None
    name: str = "rated_speed"
    limits: SpindleLimits | None = None   # with the cut: no rated speed the spindle cannot drive it at

    def select(self, rpm_now, chatter_frequency_hz, avoid=()):
        if not _allowed(np.array([self.rated_rpm]), avoid)[0]:
            return None
        if self.cut is not None and self.limits is not None and not self.cut.drivable(self.rated_rpm, self.limits):
            return None
        b_mm = stable = None
        if self.lobes is not None:
            b_mm = float(self.lobes.b_lim_at(self.rated_rpm)[0][0] * 1e3)
            if self.cut is not None:
                stable = bool(self.cut.depth_m * 1e3 < b_mm)     # not numpy's bool: `is False` holds
        return Decision(self.name, rpm_now, self.rated_rpm, chatter_frequency_hz, b_mm, stable,
                        self.rated_rpm / rpm_now, "paper's rule: drop to the rated speed")


@dataclass
class VariationSelection:
    variation: SpeedVariation
    name: str = "ssv"

    def select(self, rpm_now, chatter_frequency_hz, avoid=()):
        return Decision(self.name, rpm_now, rpm_now, chatter_frequency_hz, None, None, 1.0,
                        f"{self.variation.kind} modulation, RVA "
                        f"{self.variation.achieved_amplitude_ratio(rpm_now):.3f}, "
                        f"period {self.variation.period_s:g} s", variation=self.variation)


@dataclass
class SuppressionPolicy:
    """When to act on chatter alarms.  Feed it one judgement per analysis
    window (``observe``); it returns a Decision when the speed must change.

    Rules (these are what keeps it from oscillating):

    1. Act only after ``confirm`` consecutive alarm windows.
    2. After a change, hold: alarms are ignored until the spindle has reached
       the new speed (ramp at the spindle's acceleration) and then turned
       ``settle_revs`` revolutions at it - old chatter marks are still being
       cut off and the vibration must decay before it can be judged.
    3. A speed left because of chatter is banned, +-``ban_band``, for the rest
       of the part; no strategy may pick a banned speed.  So no speed is
       visited twice and A -> B -> A cannot happen.
    4. The speed is never raised back because alarms stopped; only ``reset``
       (next part) clears the bans.
    5. At most ``max_changes`` changes per part; when the strategy has no
       admissible speed or the budget is spent, the ``fallback`` (the paper's
       rated speed) is taken once; after that the policy holds and reports.
    6. ``when_no_stable_speed = "hold"`` (lobe strategy): when the lobes say
       the speed it would move to chatters at this depth (its b_lim below the
       depth, LobeSelection.advise), and the fallback too,
       the speed is kept and ``observe`` returns an Advice, once: the policy
       is then exhausted for this part, unless the cut gets shallower
       (``lift_advice``).  Where that speed's limit is above the
       depth but not by the margin, it still moves there (the margin is for
       model error; such moves cure most such cuts).  A fallback the lobes
       say chatters is not taken either (the budget spent, say): the policy
       is exhausted.  Moves to speeds the model itself called chattering
       re-chattered five times in six in the closed loop from zero.  "move"
       takes the most stable speed and then the fallback, as the paper's rule
       would.
    """
    strategy: Strategy
    limits: SpindleLimits
    fallback: Strategy | None = None
    settle_revs: float = 20.0
    confirm: int = 1
    ban_band: float = 0.04
    max_changes: int = 3
    when_no_stable_speed: str = "move"
    changes: list[Decision] = field(default_factory=list)
    banned: list[tuple[float, float]] = field(default_factory=list)
    _streak: int = 0
    _hold_until_s: float = -math.inf
    exhausted: bool = False
    advice: Advice | None = None

    def __post_init__(self) -> None:
        if self.when_no_stable_speed not in WHEN_NO_STABLE_SPEED:
            raise ValueError(f"when_no_stable_speed {self.when_no_stable_speed!r} is not one of "
                             f"{', '.join(WHEN_NO_STABLE_SPEED)}")

    def reset(self) -> None:
        self.changes.clear()
        self.banned.clear()
        self._streak = 0
        self._hold_until_s = -math.inf
        self.exhausted = False
        self.advice = None

    @property
    def holding(self) -> bool:
        return bool(self.changes)

    def hold_until(self) -> float:
        return self._hold_until_s

    def lift_advice(self) -> Advice | None:
        """The cut no longer is what the advice judged (it got shallower): the next alarm is
        decided afresh, with this part's bans and budget.  Returns the advice lifted."""
        a = self.advice
        if a is not None:
            self.advice, self.exhausted = None, False
        return a

    def ban(self, rpm: float) -> None:
        """No speed within ban_band of ``rpm`` is chosen again for this part."""
        self.banned.append((rpm * (1 - self.ban_band), rpm * (1 + self.ban_band)))

    def _admissible(self, d: Decision | None) -> Decision | None:
        # enforced here, not trusted to the strategy: a banned target, or one outside the
        # envelope (the speed cap; a rated_rpm configured beyond it), is refused
        if d is None:
            return d
        if d.variation is not None:     # the modulation's whole swing
            a = d.variation.achieved_amplitude_ratio(d.rpm_before)
            ok = self.limits.min_rpm <= d.rpm_before * (1 - a) and d.rpm_before * (1 + a) <= self.limits.max_rpm
            return d if ok else None
        if not _allowed(np.array([d.rpm_after]), self.banned)[0]:
            return None
        if not self.limits.min_rpm <= d.rpm_after <= self.limits.max_rpm:
            return None
        return d

    def take(self, t_s: float, rpm: float, decision: Decision) -> Decision | None:
        """A decision made from evidence other than this part's alarms (a remembered cure),
        under the same rules: within the envelope, never a banned speed, within the budget,
        then the speed left is banned and the hold begins.  None when it is not admissible."""
        if (t_s < self._hold_until_s or self.exhausted or len(self.changes) >= self.max_changes
                or self._admissible(decision) is None):
            return None
        self.ban(rpm)
        self.changes.append(decision)
        self._hold_until_s = (t_s + ramp_time_s(rpm, decision.rpm_after, self.limits.accel_rpm_per_s)
                              + self.settle_revs * 60 / decision.rpm_after)
        return decision

    def settling(self, t_s: float) -> bool:
        """In a change's ramp and settle, or with nothing left to try: an alarm decides nothing."""
        return t_s < self._hold_until_s or self.exhausted

    def observe(self, t_s: float, rpm: float, alarm: bool,
                chatter_frequency_hz: float | None = None,
                chatter_index: float | None = None,
                threshold: float | None = None) -> Decision | Advice | None:
        if t_s < self._hold_until_s:
            self._streak = 0
            return None
        self._streak = self._streak + 1 if alarm else 0
        if self._streak < self.confirm or self.exhausted:
            return None
        self._streak = 0
        self.ban(rpm)
        decision = None
        fallback_left = self.fallback is not None and not any(d.strategy == self.fallback.name
                                                              for d in self.changes)
        if len(self.changes) < self.max_changes:
            decision = self._admissible(self.strategy.select(rpm, chatter_frequency_hz, self.banned))
            if (decision is not None and decision.expected_stable is False and self.when_no_stable_speed == "hold"
                    and isinstance(self.strategy, LobeSelection)):
                advice = self.strategy.advise(rpm, chatter_frequency_hz, self.banned)
                fb = self._admissible(self.fallback.select(rpm, chatter_frequency_hz, self.banned)) \
                    if fallback_left and advice is not None else None
                if fb is not None and fb.expected_stable is not False:
                    decision = fb          # the model says the fallback will not chatter
                elif advice is not None:
                    # the model says every speed within reach chatters: a move would only trade chatter
                    self.exhausted = True
                    self.advice = replace(advice, chatter_index=chatter_index, threshold=threshold)
                    return self.advice
                # else a speed within reach is above the depth, not by the margin: the most stable one
        if decision is None and fallback_left:
            decision = self._admissible(self.fallback.select(rpm, chatter_frequency_hz, self.banned))
            if (decision is not None and decision.expected_stable is False and self.when_no_stable_speed == "hold"
                    and isinstance(self.strategy, LobeSelection)):
                decision = None        # the lobes say the fallback chatters too: no move to trade chatter
        if decision is None:
            self.exhausted = True
            return None
        decision = Decision(**{**decision.__dict__, "chatter_index": chatter_index,
                               "threshold": threshold})
        self.changes.append(decision)
        target = decision.rpm_after
        self._hold_until_s = (t_s + ramp_time_s(rpm, target, self.limits.accel_rpm_per_s)
                              + self.settle_revs * 60 / target)
        if decision.variation is not None:
            # modulating: there is nothing further to select for this part
            self.exhausted = True
        return decision


def reach(limits: SpindleLimits, rpm_programmed: float | None, max_speed_ratio: float) -> SpindleLimits:
    """The spindle's envelope under the speed cap: never more than ``max_speed_ratio`` x the
    programmed speed (the cutting speed the tool and material were programmed for)."""
    if not rpm_programmed:
        return limits
    return replace(limits, max_rpm=min(limits.max_rpm, max_speed_ratio * rpm_programmed))


def lobe_policy(lobes: StabilityLobes, cut: Cut, limits: SpindleLimits, rpm_programmed: float | None,
                max_speed_ratio: float, rated_rpm: float, grid=None, settle_revs: float = 20.0,
                when_no_stable_speed: str = "hold") -> SuppressionPolicy:
    """One cut's policy as the daemon's suppression composes it for strategy "lobes": LobeSelection
    within reach, the rated speed as the fallback (the benchmark's closed loop runs this too)."""
    within = reach(limits, rpm_programmed, max_speed_ratio)
    return SuppressionPolicy(LobeSelection(lobes, cut, within, grid=grid), within,
                             fallback=RatedSpeed(rated_rpm, lobes, cut, limits=within), settle_revs=settle_revs,
                             when_no_stable_speed=when_no_stable_speed)


def model_free_policy(cut: Cut, limits: SpindleLimits, rpm_programmed: float | None, max_speed_ratio: float,
                      rated_rpm: float, settle_revs: float = 20.0) -> SuppressionPolicy:
    """One cut's policy with no model for it (another turret tool; a model not learned yet, or
    not trusted): the frequency rule within reach, the rated speed as its fallback."""
    within = reach(limits, rpm_programmed, max_speed_ratio)
    return SuppressionPolicy(FrequencySelection(within, cut), within,
                             fallback=RatedSpeed(rated_rpm, None, cut, limits=within), settle_revs=settle_revs)
