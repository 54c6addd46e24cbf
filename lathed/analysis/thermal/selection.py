"""Which temperature sensors the thermal model reads, chosen forward in time. See docs/thermal.md."""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from lathed.analysis.forward import Fold, fold_t, forward_folds, rmse
from lathed.analysis.thermal.data import ThermalData, ThermalRuns
from lathed.analysis.thermal.fit import cached_forward, design, fit_coefficients, fit_design, forward_errors
from lathed.analysis.thermal.report import SensorKept
from lathed.analysis.thermal.residual import spectral_line
from lathed.analysis.thermal.terms import LinearTerm, Term

COLLINEAR_R = 0.999

# Oscillations faster than this are a sensor's own, not heat the spindle's
# growth follows: four times the shortest lag the residual loop tries.
_FILTER_MAX_PERIOD_S = 4 * 300.0


def _filters(data: ThermalData | ThermalRuns, sensor: str) -> list[LinearTerm]:
    """The sensor's linear term as read, and, for a sensor that oscillates on
    its own (a spectral line in its rise), one through a notch at that
    period (``period_mean``). A plain sensor is not filtered: a lag there is
    a physical effect, for the residual loop to find and name."""
    cache = data.__dict__.setdefault("_smooth", {})     # shared with select(): same rows, same rises
    if ("filters", sensor) not in cache:
        # Any line that stands out, however small beside the warm-up; only a
        # fast one: a slow swing (the room's) is heat the growth follows.
        period, _ = spectral_line(data.time_s, data.rise(sensor), min_share=0.0)
        cache[("filters", sensor)] = ([LinearTerm(sensor)] if period is None or period > _FILTER_MAX_PERIOD_S
                                      else [LinearTerm(sensor), LinearTerm(sensor, notch_s=round(period, 1))])
    return list(cache[("filters", sensor)])


def usable_sensors(data: ThermalData | ThermalRuns, folds: Sequence[Fold]) -> tuple[list[str], list[str]]:
    """The temperature columns that can be fitted: not a sensor that never
    changed, nor one that moves in lock-step with another and adds nothing
    forward in time (two sensors reading the same heat; keeping both would
    split or, with noise, oppose their weights)."""
    notes: list[str] = []
    keep: list[str] = []
    for s in data.sensors:
        x = data.rise(s)
        if np.ptp(x) == 0:
            notes.append(f"{s} never changed ({x[0] + data.reference_c[s]:.2f} °C): left out of the fit")
            continue
        keep.append(s)
    if not keep:
        raise ValueError("no temperature column changed during the run: nothing to fit the growth to")
    y = data.displacement_um
    for s in list(keep[1:]):
        x = data.rise(s)
        twin = next((k for k in keep if k != s and abs(np.corrcoef(data.rise(k), x)[0, 1]) > COLLINEAR_R), None)
        if twin is None:
            continue
        r = np.corrcoef(data.rise(twin), x)[0, 1]
        if y is None:
            continue
        with_s = rmse(forward_errors(np.column_stack([data.rise(k) for k in keep]), y, folds))
        without = [k for k in keep if k != s]
        without_s = rmse(forward_errors(np.column_stack([data.rise(k) for k in without]), y, folds))
        if without_s <= 1.01 * with_s:
            keep = without
            notes.append(f"{s} moves with {twin} (r={r:.5f}): the two sensors read the same heat; "
                         f"fitted on {twin} only")
        else:
            notes.append(f"{s} moves with {twin} (r={r:.5f}) but still adds forward in time "
                         f"({without_s:.2f} -> {with_s:.2f} µm): both kept")
    return keep, notes


# One-sided level of the test a sensor passes to enter (see select_sensors).
SENSOR_ALPHA = 0.05


def select_sensors(data: ThermalData | ThermalRuns, folds: Sequence[Fold] | None = None, max_sensors: int = 8,
                   min_gain: float = 0.005, alpha: float = SENSOR_ALPHA, *,
                   start: Sequence[LinearTerm] | None = None,
                   fixed: Sequence[Term] = (), prune: bool = True, filters: bool = True
                   ) -> tuple[list[LinearTerm], list[str], list[SensorKept]]:
    """Choice of sensors (each with the filter of ``_filters`` that suits it), judged forward in
    time, at most ``max_sensors``. Sixteen sensors on one spindle mostly read the same few heats:
    all of them in one regression fit their noise and oscillations, not the growth.

    A floating search (sequential floating forward selection): for each number of sensors the
    set with the least forward error found so far; after a sensor enters, swaps and removals are
    taken while they beat the best set of their size (a decoy that stands in for two true sensors
    would otherwise keep them out). The search goes to the cap, and the smallest set that no
    larger one beats significantly is kept: a forward error lower by ``min_gain`` (relative) and
    consistently so across the folds (``fold_t`` at one-sided level ``alpha``).

    With no more usable sensors than ``max_sensors`` all enter, each with its best filter beside
    ``fixed`` (as read without ``filters``): a missing effect may hide a sensor's share, and the
    loop decides once effects are in. ``start`` are sensors already chosen, ``fixed`` effect
    terms fitted beside them; the residual loop calls this again as effects enter, and last
    with ``prune``."""
    folds = forward_folds(len(data)) if folds is None else folds
    keep, notes = usable_sensors(data, folds)
    y = data.displacement_um
    if y is None:
        return [LinearTerm(s) for s in keep], notes, []
    fixed = list(fixed)
    few = len(keep) <= max_sensors
    if few:
        # each sensor through the filter that suits it, chosen beside the effects in: a notch
        # delays a sensor by half its period and stands in for a lag the loop has not found yet
        start = [LinearTerm(s) for s in keep] if start is None else [t for t in start if t.sensor in keep]
        for i, t0 in enumerate(start if filters else ()):
            grid = _filters(data, t0.sensor)
            if len(grid) > 1:
                start[i] = min(grid, key=lambda t: rmse(
                    cached_forward(data, [*start[:i], t, *start[i + 1:], *fixed], folds)))
    cands = [] if few else [t for s in keep for t in _filters(data, s)]
    scored: dict[tuple[str, ...], tuple[float, np.ndarray]] = {}

    def score(ts: Sequence[LinearTerm]) -> tuple[float, np.ndarray]:
        key = tuple(sorted(repr(t) for t in ts))
        if key not in scored:
            e = (cached_forward(data, [*ts, *fixed], folds) if ts or fixed
                 else forward_errors(np.empty((len(y), 0)), y, folds))
            scored[key] = (rmse(e), e)
        return scored[key]

    from scipy.special import stdtrit      # Student's t quantile (scipy.stats costs a second to import)
    t_crit = float(stdtrit(len(folds) - 1, 1 - alpha)) if len(folds) > 1 else math.inf

    def significant(small: Sequence[LinearTerm], big: Sequence[LinearTerm]) -> bool:
        (r0, e0), (r1, e1) = score(small), score(big)
        return 1 - r1 / r0 >= min_gain and fold_t(e0, e1, folds) >= t_crit

    def free(c: LinearTerm, ts: Sequence[LinearTerm]) -> bool:
        return all(t.sensor != c.sensor for t in ts)

    chosen: list[LinearTerm] = [t for t in (start or ()) if t.sensor in keep]
    best: dict[int, list[LinearTerm]] = {len(chosen): chosen}

    def better(ts: list[LinearTerm]) -> bool:
        """Is ``ts`` the best set of its size yet? (kept if so)"""
        k = len(ts)
        if k in best and score(ts)[0] >= score(best[k])[0] - 1e-12:
            return False
        best[k] = ts
        return True

    def float_(ts: list[LinearTerm]) -> list[LinearTerm]:
        while True:
            swaps = [[*ts[:i], c, *ts[i + 1:]] for i in range(len(ts)) for c in cands
                     if repr(c) != repr(ts[i]) and free(c, ts[:i] + ts[i + 1:])]
            sw = min(swaps, key=lambda m: score(m)[0], default=None)
            if sw is not None and better(sw):
                ts = sw
                continue
            # a smaller set only against the best of its size met on the way up
            drops = [ts[:i] + ts[i + 1:] for i in range(len(ts))] if len(ts) - 1 in best else []
            dr = min(drops, key=lambda m: score(m)[0], default=None)
            if dr is not None and better(dr):
                ts = dr
                continue
            return ts

    if not few:
        # Every size up to the cap, then the smallest set no larger one beats
        # significantly: a plain "stop at the first step that is not
        # significant" would stop where a decoy blocks the way (two true
        # sensors in place of one decoy show only one size further on).
        lo = len(chosen)
        ts = float_(chosen) if chosen else chosen
        if prune:      # sizes below the start: let go of sensors made redundant
            while len(ts) > 1:
                dr = min((ts[:i] + ts[i + 1:] for i in range(len(ts))), key=lambda m: score(m)[0])
                better(dr)
                ts = float_(best[len(dr)])
            lo = 1
        ts = best[len(chosen)]
        while len(ts) < max_sensors:
            adds = [[*ts, c] for c in cands if free(c, ts)]
            if not adds:
                break
            nxt = min(adds, key=lambda m: score(m)[0])
            better(nxt)
            ts = float_(best[len(nxt)])
        sizes = sorted(k for k in best if k >= max(lo, 1))
        # the first always enters: the growth is fitted to something
        k = next(k for k in sizes if not any(significant(best[k], best[j]) for j in sizes if j > k))
        chosen = best[k]
    # Few sensors all enter; one leaves only when the forward error is lower without it, as
    # consistently as a sensor must lower it to enter. "Adds nothing" is no reason: the folds
    # cover the later half of the rows, where a sensor (the room's) may hardly have moved, and a
    # sensor left out is missed on the next day whose room moves.
    for t in list(chosen if prune and few else ()):
        rest = [o for o in chosen if o is not t]
        if rest and significant(chosen, rest):
            chosen = rest
    e_cur = score(chosen)[1]
    left = [s for s in keep if all(t.sensor != s for t in chosen)]
    if left:
        notes.append(f"sensor selection kept {len(chosen)} of {len(keep)}: "
                     f"{', '.join(left)} added nothing forward in time")
    coef, _ = fit_coefficients(fit_design(data, [*chosen, *fixed]), y)
    kept = []
    for i, t in enumerate(chosen):
        rest = [o for o in chosen if o is not t]
        without = rmse(cached_forward(data, [*rest, *fixed], folds) if rest or fixed
                       else forward_errors(np.empty((len(y), 0)), y, folds))
        kept.append(SensorKept(t.sensor, t.smooth_s, without - rmse(e_cur),
                               float(abs(coef[i]) * np.ptp(design(data, [t]))), t.notch_s))
    return chosen, notes, kept
