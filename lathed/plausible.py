"""Is a value from a peer physically plausible? Judged before it reaches the bus.

Every value a driver publishes passes this check (lathed.driver.GatedBus), so
analyzers, the machine model and the safety guard never see a NaN, a value
outside what the quantity can physically be, or a jump faster than it can
physically change (a 124.99 °C bearing 0.3 s after 30 °C is a bit error, not
heat). Numeric only, no asyncio.

Bounds per quantity come from the instance's ``plausible`` sub-table, by exact
quantity name or a glob, else from the defaults of the value's unit::

    [sensor.temps.plausible]
    confirm = 3                                    # consistent readings that confirm a jump
    t_front_bearing = { min = 10, max = 90, rate = 1.0 }
    "t_*" = { rate = 2.0, tol = 0.5 }              # °C per s; tol: change always allowed

``rate`` is judged against the last ACCEPTED value and the time since it, while
the value was watched: after the driver's link failed (a reconnect, another
board on the port) or a quantity was forgotten (a sensor off its wire), the
time unwatched vouches for nothing, and the first value back must lie within
``tol`` of the last one. A jump faster than ``rate`` is refused, unless
``confirm`` readings in a row agree with one another at that rate: then the
new level is real (a sensor moved, or the first value accepted was the wrong
one) and it is accepted and counted as ``rebased``. A single spike is never
accepted; a wrong level cannot hold the sensor out forever, and what acts on
such a level (thermal compensation) judges its own step (docs/safety.md).
"""
from __future__ import annotations

import fnmatch
import math
from collections import Counter
from dataclasses import dataclass, replace

import numpy as np

from lathed.config import Section

INF = math.inf


@dataclass(frozen=True)
class Bounds:
    lo: float = -INF
    hi: float = INF
    rate: float = INF     # largest change per second between accepted values
    tol: float = 0.0      # a change always allowed (resolution, noise)


# What the quantity can physically be, by unit. A unit not listed: finite only.
UNIT_DEFAULTS: dict[str, Bounds] = {
    # a machine structure or motor: DS18B20 range, and no spindle warms 2 °C in a second
    "°C": Bounds(-55.0, 150.0, rate=2.0, tol=0.5),
    "r/min": Bounds(0.0, 100_000.0),
    "mm": Bounds(-100_000.0, 100_000.0),          # no machine axis travels 100 m
    "µm": Bounds(-100_000.0, 100_000.0),
    "deg": Bounds(-1e7, 1e7),                     # rotary axes count whole turns
    "m/s²": Bounds(-1e6, 1e6),                    # 100 000 g: beyond any shock accelerometer
    "%": Bounds(-1000.0, 1000.0),
    "s": Bounds(0.0, 1e9),
}
# Units lathed knows that bound nothing: a count, code or flag (no unit), a feed, a frequency.
# A unit in neither (a typo, "rpm" for "r/min") would leave its quantity finite-only without
# a word, so a driver whose units come from the config refuses it (unit_problem).
UNBOUNDED_UNITS = ("", "mm/rev", "Hz")
KNOWN_UNITS = (*UNIT_DEFAULTS, *UNBOUNDED_UNITS)
CONFIRM = 3


class Plausibility:
    """The bounds of one driver's quantities and the state the rate check needs."""

    def __init__(self, rules: dict[str, Bounds] | None = None, confirm: int = CONFIRM):
        self.rules = dict(rules or {})
        self._bounds: dict[tuple[str, str], Bounds | None] = {}
        self.confirm = confirm
        self._last: dict[str, tuple[float, float]] = {}          # quantity -> last accepted (value, t)
        self._chain: dict[str, tuple[float, float, int]] = {}    # quantity -> (value, t, n) of a jump
        self._unwatched: set[str] = set()      # quantities whose link failed since their last value
        self.rejected: dict[str, Counter] = {}                   # quantity -> reason -> count
        self.rebased: Counter = Counter()

    @classmethod
    def from_section(cls, sec: Section) -> Plausibility:
        confirm = sec.getint("confirm", CONFIRM, minval=1, maxval=100)
        rules = {}
        for sub in sec.subsections():
            b = Bounds(sub.getfloat("min", -INF), sub.getfloat("max", INF),
                       sub.getfloat("rate", INF, above=0.0), sub.getfloat("tol", 0.0, minval=0.0))
            if b.lo > b.hi:
                raise sub.error("min", f"{b.lo:g} is above max {b.hi:g}")
            sub.check_unused()
            rules[sub.name] = b
        sec.check_unused()
        return cls(rules, confirm)

    def rule(self, quantity: str) -> Bounds | None:
        """The quantity's own rule: exact name, then the first glob that matches."""
        rule = self.rules.get(quantity)
        if rule is None:
            rule = next((b for pat, b in self.rules.items() if fnmatch.fnmatchcase(quantity, pat)), None)
        return rule

    def unit_problem(self, quantity: str, unit: str, table: str) -> str | None:
        """Why a configured unit cannot be taken (None: it can): one lathed does not know
        gets no bounds, unless the quantity's rule (in [``table``]) gives its min and max."""
        rule = self.rule(quantity)
        if unit in KNOWN_UNITS or rule is not None and rule.lo > -INF and rule.hi < INF:
            return None
        return (f"{unit!r} is not a unit lathed knows, so {quantity} would be checked only for being finite; "
                f"known: {', '.join(u for u in KNOWN_UNITS if u)} or none (or give {quantity} its min and max "
                f"in [{table}])")

    def bounds(self, quantity: str, unit: str) -> Bounds | None:
        """The quantity's rule (exact name, then the first glob that matches) merged
        over its unit's defaults; None: no bounds, finite is enough. Worked out once per
        quantity and unit (the rules are fixed): every sample is checked."""
        key = (quantity, unit)
        if key not in self._bounds:
            self._bounds[key] = self._bounds_of(quantity, unit)
        return self._bounds[key]

    def _bounds_of(self, quantity: str, unit: str) -> Bounds | None:
        base = UNIT_DEFAULTS.get(unit)
        rule = self.rule(quantity)
        if rule is None:
            return base
        if base is None:
            return rule
        # keys the rule leaves out keep the unit's default
        return replace(base, **{k: getattr(rule, k) for k in ("lo", "hi", "rate", "tol")
                                if getattr(rule, k) != getattr(Bounds(), k)})

    def check(self, quantity: str, unit: str, value: float, t: float) -> tuple[str, str] | None:
        """None: accept (and remember) the value; else (reason, one-line why)."""
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            return self._refuse(quantity, "not_finite", f"{quantity} = {value!r} is not a finite number")
        b = self.bounds(quantity, unit)
        if b is not None:
            if not b.lo <= value <= b.hi:
                return self._refuse(quantity, "out_of_range",
                                    f"{quantity} = {value:g} {unit} outside the plausible [{b.lo:g}, {b.hi:g}]")
            last = self._last.get(quantity)
            if last is not None and quantity in self._unwatched:
                last = (last[0], max(last[1], t))     # no credit for the time nobody watched
            if last is not None and not _within(b, last, value, t):
                chain = self._chain.get(quantity)
                n = chain[2] + 1 if chain is not None and _within(b, chain[:2], value, t) else 1
                if n < self.confirm:
                    self._chain[quantity] = (value, t, n)
                    dt = t - last[1]
                    return self._refuse(quantity, "rate",
                                        f"{quantity} jumped {value - last[0]:+g} {unit} in {dt:.3g} s from "
                                        f"{last[0]:g}; faster than the plausible {b.rate:g} {unit}/s")
                self.rebased[quantity] += 1
        self._chain.pop(quantity, None)
        self._unwatched.discard(quantity)
        self._last[quantity] = (float(value), t)
        return None

    def check_block(self, quantity: str, unit: str, data: np.ndarray, rate_hz: float = 1.0,
                    rpm: float | None = None, extremes: tuple[float, float] | None = None) -> tuple[str, str] | None:
        """A waveform block: a finite positive rate, a spindle speed within the r/min
        range (if given), every sample finite and within its unit's range. ``extremes``: the
        block's (lowest, highest) sample, when already made (DeviceRows.extremes)."""
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            return self._refuse(quantity, "rate", f"{quantity}: sample rate {rate_hz!r} Hz is not a finite rate > 0")
        if rpm is not None:
            b = UNIT_DEFAULTS["r/min"]
            if not (math.isfinite(rpm) and b.lo <= rpm <= b.hi):
                return self._refuse(quantity, "rpm", f"{quantity}: spindle speed {rpm!r} r/min is not "
                                                     f"in {b.lo:g}..{b.hi:g}")
        if data.size == 0:
            return None
        if extremes is not None:
            lo, hi = extremes
        else:           # the ufuncs' reductions: the methods' (and np.min's) wrappers cost as much again
            lo, hi = float(np.minimum.reduce(data, axis=None)), float(np.maximum.reduce(data, axis=None))
        if not (math.isfinite(lo) and math.isfinite(hi)):
            bad = int(np.count_nonzero(~np.isfinite(data)))
            return self._refuse(quantity, "not_finite", f"{quantity}: {bad} of {data.size} samples not finite")
        b = self.bounds(quantity, unit)
        if b is not None and (lo < b.lo or hi > b.hi):
            return self._refuse(quantity, "out_of_range", f"{quantity}: samples {lo:g}..{hi:g} {unit} outside "
                                                          f"the plausible [{b.lo:g}, {b.hi:g}]")
        return None

    def forget(self, quantity: str) -> None:
        """A quantity its source no longer has (a sensor off its wire): should it come back,
        its first value is judged against its last, with no credit for the time away."""
        self._chain.pop(quantity, None)
        if quantity in self._last:
            self._unwatched.add(quantity)

    def link_lost(self) -> None:
        """The link to the peer failed: whoever answers next (the same board, another on the
        same port) gets no credit for the time until then."""
        self._chain.clear()
        self._unwatched.update(self._last)

    def _refuse(self, quantity: str, reason: str, why: str) -> tuple[str, str]:
        self.rejected.setdefault(quantity, Counter())[reason] += 1
        return reason, why

    def status(self) -> dict:
        out = {}
        if self.rejected:
            out["implausible"] = {q: dict(c) for q, c in sorted(self.rejected.items())}
        if self.rebased:
            out["implausible_rebased"] = dict(self.rebased)
        return out


def _within(b: Bounds, last: tuple[float, float], value: float, t: float) -> bool:
    if b.rate == INF:
        return True                 # no rate bound (inf x 0 s would be NaN, and refuse)
    dt = max(t - last[1], 0.0)      # a clock step back allows no more than tol
    return abs(value - last[0]) <= b.tol + b.rate * dt
