"""Judging a fitted model forward in time, as it will be used: folds, tests, the side-by-side report.

Shared by the loops that fit models on time series (the thermal loop; the stability loop's
earlier/later split is the one-fold case). See docs/thermal.md, "Judged forward in time".
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

# Folds cover the later half of the rows: a fit on less than half a run has seen too little of
# the machine to say much about how a model fitted on all of it will do.
FIRST_ORIGIN = 0.5
N_FOLDS = 5
# The newest share of the rows, kept from every choice a search makes on the folds before it:
# a search that tries thousands of variants on the same folds finds one that fits them by
# chance, and only rows it never saw say whether it beats a plain baseline.
CONFIRM_SHARE = 0.2


@dataclass(frozen=True)
class Fold:
    """Fit on rows [0, lo), predict rows [lo, hi)."""
    lo: int
    hi: int


def forward_folds(n: int, n_folds: int = N_FOLDS, first: float = FIRST_ORIGIN) -> list[Fold]:
    """Expanding-window folds over ``n`` rows in time order: each fits on everything before its
    origin and predicts up to the next origin. The folds tile rows [first * n, n)."""
    if n_folds < 1:
        raise ValueError(f"need at least one fold, got {n_folds}")
    edges = np.linspace(first * n, n, n_folds + 1).round().astype(int)
    folds = [Fold(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]
    if not folds or folds[0].lo < 1:
        raise ValueError(f"{n} rows are too few for {n_folds} forward folds")
    return folds


def first_row(folds: Sequence[Fold]) -> int:
    """The first row a fold predicts: forward errors are for rows [first_row, n)."""
    return folds[0].lo


def rmse(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(e)))) if len(e) else math.nan


def fold_t(e_old: np.ndarray, e_new: np.ndarray, folds: Sequence[Fold]) -> float:
    """Paired t of the fall in squared error across the folds (log of each fold's mean squared
    error before over after; NaN with one fold). A fold's errors come from one fit and are
    correlated throughout, so the fold, not the row, is the unit of evidence. ``e_*`` are the
    forward errors (rows from ``first_row(folds)`` on)."""
    o = first_row(folds)
    lr = np.array([np.log(np.mean(e_old[f.lo - o:f.hi - o] ** 2) / max(np.mean(e_new[f.lo - o:f.hi - o] ** 2),
                                                                        1e-300)) for f in folds])
    if len(lr) < 2:
        return math.nan
    sd = float(lr.std(ddof=1))
    return math.copysign(math.inf, lr.mean()) if sd == 0 else float(lr.mean() / (sd / math.sqrt(len(lr))))


def blocks(n: int, n_blocks: int = N_FOLDS) -> list[Fold]:
    """``n`` rows cut into contiguous blocks (as folds, for ``fold_t``)."""
    edges = np.linspace(0, n, n_blocks + 1).round().astype(int)
    return [Fold(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]


# One-sided level at which a fall in error counts as consistent across folds or blocks.
ALPHA = 0.05


def t_critical(n_blocks: int, alpha: float = ALPHA) -> float:
    """Student's t quantile for ``fold_t`` over ``n_blocks``."""
    from scipy.special import stdtrit      # scipy.stats costs a second to import
    return float(stdtrit(n_blocks - 1, 1 - alpha)) if n_blocks > 1 else math.inf


@dataclass
class Verdict:
    """Does a new model beat an old one on the same later rows: by ``min_gain`` (relative) and
    consistently across blocks of them (``fold_t`` at one-sided ``alpha``)?"""
    better: bool
    gain: float
    t: float
    t_crit: float

    def why(self) -> str:
        return f"{100 * self.gain:.0f} % lower error, t = {self.t:.2f} across blocks of the rows (needs {self.t_crit:.2f})"


def beats(e_old: np.ndarray, e_new: np.ndarray, min_gain: float, n_blocks: int = N_FOLDS,
          alpha: float = ALPHA) -> Verdict:
    """Judge ``e_new`` against ``e_old`` (errors on the same later rows, in time order)."""
    bl = blocks(len(e_old), n_blocks)
    gain = 1.0 - rmse(e_new) / rmse(e_old) if rmse(e_old) > 0 else 0.0
    t, tc = fold_t(e_old, e_new, bl), t_critical(len(bl), alpha)
    return Verdict(bool(gain >= min_gain and t >= tc), gain, t, tc)


def improvement_z(e_old: np.ndarray, e_new: np.ndarray) -> float:
    """Diebold-Mariano statistic for the fall in squared error, with a Newey-West variance:
    neighbouring rows' errors are correlated, so a plain t-test would see significance
    everywhere."""
    d = e_old ** 2 - e_new ** 2
    n = len(d)
    dc = d - d.mean()
    lags = max(1, int(math.sqrt(n)))
    var = dc @ dc / n
    for k in range(1, min(lags, n - 1) + 1):
        var += 2 * (1 - k / (lags + 1)) * (dc[k:] @ dc[:-k]) / n
    if var <= 0:
        return math.inf if d.mean() > 0 else 0.0
    return float(d.mean() / math.sqrt(var / n))


@dataclass
class Scored:
    """One model of a side-by-side report: its forward error on the training rows (what the
    choice is made on) and its error on later rows (what the report judges on), either may be
    missing. ``baseline`` marks the plain models every report carries."""
    label: str
    forward: float | None
    later: float | None = None
    baseline: bool = False
    note: str = ""
    rolling: float | None = None     # a baseline's error over the later half of the training rows

    def to_json(self) -> dict[str, Any]:
        r = (lambda v: None if v is None else round(v, 4))
        return {"model": self.label, "forward_rmse_um": r(self.forward), "rmse_um": r(self.later),
                "baseline": self.baseline, **({"note": self.note} if self.note else {}),
                **({"rolling_rmse_um": r(self.rolling)} if self.rolling is not None else {})}


def best(rows: Sequence[Scored], on: str = "forward", baseline: bool | None = None) -> Scored | None:
    """The row with the least error ``on`` ("forward" or "later"), among baselines only or
    non-baselines only when ``baseline`` is given; rows without that error are skipped. A tie
    goes to the row listed first."""
    pool = [r for r in rows if (baseline is None or r.baseline == baseline)
            and getattr(r, on) is not None and math.isfinite(getattr(r, on))]
    return min(pool, key=lambda r: getattr(r, on), default=None)
