"""Taguchi analysis of designed cutting experiments: S/N ratios, main effects,
recommended levels.

Each trial is one measured part of an orthogonal-array run (e.g. L9 over
speed, feed and depth of cut): its factor levels and its responses. Trials
with the same levels are replicates of one run. Per objective the S/N ratio
of every run is averaged per factor level (main effects); the level with
the highest mean S/N is recommended:

    precision   |diameter error|  smaller-the-better  S/N = -10 log10(mean(y^2))
    surface     Ra                smaller-the-better
    efficiency  removal rate      larger-the-better   S/N = -10 log10(mean(1/y^2))

Pure numpy, no I/O: the daemon and offline tools share it.
"""
from __future__ import annotations

from typing import Any, Iterable

import numpy as np

# The standard L9(3^4) array (levels numbered from 1).
L9 = np.array([[1, 1, 1, 1], [1, 2, 2, 2], [1, 3, 3, 3],
               [2, 1, 2, 3], [2, 2, 3, 1], [2, 3, 1, 2],
               [3, 1, 3, 2], [3, 2, 1, 3], [3, 3, 2, 1]])

# objective -> (response key, kind)
OBJECTIVES = {"precision": ("diameter_error_um", "smaller"),
              "surface": ("ra_um", "smaller"),
              "efficiency": ("removal_rate", "larger")}
TIE_DB = 1e-6   # dB; levels this close are reported as a tie
# Bounds of what one analysis takes. Levels number an orthogonal array's
# settings of a factor (2 to 5 in the common arrays, 9 in L81): the main
# effects count per level, so a level of 3e8 would allocate per level value.
MAX_LEVEL = 27
MAX_FACTORS = 64
MAX_TRIALS = 10_000


def sn_smaller(y: Iterable[float]) -> float:
    y = np.asarray(list(y), dtype=float)
    return float(-10.0 * np.log10(np.mean(y ** 2)))


def sn_larger(y: Iterable[float]) -> float:
    y = np.asarray(list(y), dtype=float)
    if np.any(y <= 0):
        raise ValueError("larger-the-better S/N needs positive responses")
    return float(-10.0 * np.log10(np.mean(1.0 / y ** 2)))


def main_effects(levels: np.ndarray, sn: np.ndarray) -> list[dict[int, float]]:
    """Mean S/N at each level of each factor: ``levels`` is (runs, factors)."""
    levels, sn = np.asarray(levels), np.asarray(sn, dtype=float)
    return [{int(lv): float(sn[levels[:, j] == lv].mean()) for lv in np.unique(levels[:, j])}
            for j in range(levels.shape[1])]


def analyse(levels: np.ndarray, sn: np.ndarray, factors: list[str]) -> dict[str, Any]:
    """Main effects, best level(s) per factor (ties kept), factor ranking by
    range, and the additive-model prediction of the S/N at the optimum."""
    effects = main_effects(levels, sn)
    mean = float(np.mean(sn))
    best, delta = {}, {}
    for f, eff in zip(factors, effects):
        top = max(eff.values())
        best[f] = [lv for lv, v in eff.items() if v >= top - TIE_DB]
        delta[f] = top - min(eff.values())
    balanced = all(len(set(np.bincount(levels[:, j])[1:]) - {0}) <= 1 for j in range(levels.shape[1]))
    return {"mean_sn_db": mean,
            "effects": {f: eff for f, eff in zip(factors, effects)},
            "best": best,
            "delta_db": delta,
            "rank": sorted(factors, key=lambda f: -delta[f]),
            "predicted_sn_db": mean + sum(effects[j][best[f][0]] - mean for j, f in enumerate(factors)),
            "balanced": balanced}


def recommend(trials: list[dict[str, Any]]) -> dict[str, Any]:
    """Recommendations from experiment trials.

    A trial: ``levels`` {factor: level}, optional ``settings`` {factor: value},
    and any of ``diameter_error_um``, ``ra_um``, ``removal_rate``.
    """
    if not trials:
        raise ValueError("no experiment trials recorded")
    if len(trials) > MAX_TRIALS:
        raise ValueError(f"{len(trials)} trials; one analysis takes at most {MAX_TRIALS}")
    factors = sorted(trials[0]["levels"])
    if len(factors) > MAX_FACTORS:
        raise ValueError(f"{len(factors)} factors; at most {MAX_FACTORS}")
    for t in trials:
        if sorted(t["levels"]) != factors:
            raise ValueError(f"trials disagree on the factors: {factors} vs {sorted(t['levels'])}")
        for f, lv in t["levels"].items():
            if isinstance(lv, bool) or not isinstance(lv, int) or not 1 <= lv <= MAX_LEVEL:
                raise ValueError(f"factor {f} has level {lv!r}; levels are numbered 1 to {MAX_LEVEL}")
    settings: dict[str, dict[int, Any]] = {f: {} for f in factors}
    for t in trials:
        for f, v in (t.get("settings") or {}).items():
            if f in settings:
                settings[f].setdefault(int(t["levels"][f]), v)
    out: dict[str, Any] = {"factors": factors, "trials": len(trials), "objectives": {}}
    for obj, (key, kind) in OBJECTIVES.items():
        runs: dict[tuple, list[float]] = {}
        for t in trials:
            if t.get(key) is not None:
                y = abs(float(t[key])) if obj == "precision" else float(t[key])
                runs.setdefault(tuple(int(t["levels"][f]) for f in factors), []).append(y)
        if not runs:
            out["objectives"][obj] = None
            continue
        keys = sorted(runs)
        sn_fn = sn_smaller if kind == "smaller" else sn_larger
        sn = np.array([sn_fn(runs[k]) for k in keys])
        res = analyse(np.array(keys), sn, factors)
        res.update({"response": key, "sn": f"{kind}-the-better", "runs": len(keys),
                    "best_settings": {f: [settings[f].get(lv) for lv in res["best"][f]] for f in factors}})
        out["objectives"][obj] = res
    return out
