"""Least squares on a run's terms, and its errors judged forward in time (see lathed.analysis.forward)."""
from __future__ import annotations

from collections import OrderedDict
from typing import Sequence

import numpy as np

from lathed.analysis.forward import Fold, first_row
from lathed.analysis.thermal.data import ThermalData, ThermalRuns
from lathed.analysis.thermal.terms import LinearTerm, Term

_RIDGE = 1e-6          # relative to n on standardised columns: only bites on exact collinearity


def term_columns(data: ThermalData, term: Term) -> np.ndarray:
    """A term's columns on one run, kept: the loops ask for the same terms again and again as
    others come and go."""
    cache = data.__dict__.setdefault("_cols", {})
    key = repr(term)
    hit = cache.get(key)
    if hit is None or hit[0] is not data.rpm:      # rpm may be set or replaced after the run was built
        hit = cache[key] = (data.rpm, np.asarray(term.features(data), dtype=float).reshape(len(data), -1))
    return hit[1]


def design(data: ThermalData | ThermalRuns, terms: Sequence[Term]) -> np.ndarray:
    if isinstance(data, ThermalRuns):      # terms with memory start afresh in each run
        return np.vstack([design(r, terms) for r in data.runs])
    cols = [term_columns(data, t) for t in terms]
    return np.hstack(cols) if cols else np.empty((len(data), 0))


def fit_design(data: ThermalData | ThermalRuns, terms: Sequence[Term]) -> np.ndarray:
    """The design the coefficients are fitted on: as ``design``, but the unfiltered sensors' own
    (linear) columns with their reading noise smoothed out, where what is smoothed out is noise.

    Heated sensors move nearly in lock-step, so what tells their weights apart is a few
    hundredths of a °C, the size of a DS18B20's noise: fitted on raw readings the weights are
    biased along that direction (errors in variables). Predictions still use the raw readings.
    A sensor that oscillates on its own is fitted as it is predicted."""
    if isinstance(data, ThermalRuns):
        return np.vstack([fit_design(r, terms) for r in data.runs])
    cols = [data.fit_rise(t.sensor)[:, None] if isinstance(t, LinearTerm) and not t.filtered
            else term_columns(data, t) for t in terms]
    return np.hstack(cols) if cols else np.empty((len(data), 0))


class _Scaled:
    """Standardised design with an intercept; ridge on everything but the intercept."""

    def __init__(self, X: np.ndarray):
        self.mu = X.mean(axis=0)
        sd = X.std(axis=0)
        self.sd = np.where(sd > 0, sd, 1.0)

    def __call__(self, X: np.ndarray) -> np.ndarray:
        return np.hstack([(X - self.mu) / self.sd, np.ones((len(X), 1))])


def _solve(G: np.ndarray, b: np.ndarray, n: int, ridge: float = _RIDGE) -> np.ndarray:
    reg = np.full(len(G), ridge * max(n, 1))
    reg[-1] = 0.0
    return np.linalg.solve(G + np.diag(reg), b)


def fit_coefficients(X: np.ndarray, y: np.ndarray, ridge: float = _RIDGE) -> tuple[np.ndarray, float]:
    """Least squares y ≈ X·coef + intercept, in the raw units of X; ``ridge`` is the penalty on
    the standardised columns, relative to the rows."""
    sc = _Scaled(X)
    Z = sc(X)
    beta = _solve(Z.T @ Z, Z.T @ y, len(y), ridge)
    coef = beta[:-1] / sc.sd
    return coef, float(beta[-1] - coef @ sc.mu)


def forward_errors(X: np.ndarray, y: np.ndarray, folds: Sequence[Fold], X_pred: np.ndarray | None = None,
                   ridge: float = _RIDGE) -> np.ndarray:
    """Each fold fitted on the rows before it (on ``X``) and its rows predicted (from ``X_pred``,
    default ``X``; see ``fit_design``): the errors of rows [first_row(folds), n)."""
    P = X if X_pred is None else X_pred
    out = []
    for f in folds:
        coef, icpt = fit_coefficients(X[:f.lo], y[:f.lo], ridge)
        out.append(y[f.lo:f.hi] - (P[f.lo:f.hi] @ coef + icpt))
    return np.concatenate(out)


class ForwardCache:
    """``forward_errors`` for the selection loops, which score thousands of designs that differ
    in a column or two. Every column met is kept once, and the sums of products of each pair of
    columns met together, up to each fold's origin; a design's forward errors then cost one
    gather and a few small solves. Same algebra as ``forward_errors`` (the ridge on standardised
    columns is a ridge of ``_RIDGE * rows * var`` on the raw ones, the variance over the fold's
    own rows). Columns are kept less their mean (the intercept takes it up): sums of products of
    raw rises lose digits to their common part."""

    SEEN = 2048         # designs whose errors are kept (a few tens of MB on a long real run)

    def __init__(self, data: ThermalData | ThermalRuns, folds: Sequence[Fold]):
        self.data = data
        y = data.displacement_um
        self.folds = list(folds)
        self.o = first_row(self.folds)
        self.row_fold = np.repeat(np.arange(len(self.folds)), [f.hi - f.lo for f in self.folds])
        # rows [edges[i], edges[i + 1]) add to the sums of fold i and every later one
        self.edges = [0, *(f.lo for f in self.folds)]
        self.n = len(y)
        self.X = np.empty((64, self.n))                     # the columns (a row each), less their mean
        self.shift = np.empty(64)                           # ... which is this
        self.G = np.empty((len(self.folds), 64, 64))        # sums of products up to each origin
        self.have = np.zeros((64, 64), dtype=bool)          # which pairs G holds
        self.index: dict[str, int] = {}
        self.by_repr: dict[tuple[str, bool], list[int]] = {}
        self.by_id: dict[tuple[int, bool], tuple[Term, list[int]]] = {}
        self.seen: OrderedDict[tuple, np.ndarray] = OrderedDict()    # the newest designs' errors
        self.one, self.iy = self._add("1", np.ones(self.n)), self._add("y", y)
        self.rpm = data.rpm
        self.y = y

    def _add(self, key: str, col: np.ndarray) -> int:
        k = len(self.index)
        if k == self.X.shape[0]:                            # room for twice as many
            X, G, have = np.empty((2 * k, self.n)), np.empty((len(self.folds), 2 * k, 2 * k)), \
                np.zeros((2 * k, 2 * k), dtype=bool)
            X[:k], G[:, :k, :k], have[:k, :k] = self.X, self.G, self.have
            self.X, self.G, self.have, self.shift = X, G, have, np.concatenate([self.shift, np.empty(k)])
        c = 0.0 if key == "1" else float(np.mean(col))
        self.shift[k] = c
        self.X[k] = col - c
        self.index[key] = k
        return k

    def _products(self, keys: np.ndarray) -> None:
        """Fill in the sums of products G lacks among ``keys``."""
        missing = ~self.have[keys[:, None], keys]
        if not missing.any():
            return
        for i in np.flatnonzero(missing.any(axis=1)):
            js = keys[missing[i]]
            if len(js) == 0:
                continue
            k = keys[i]
            seg = np.stack([self.X[js, a:b] @ self.X[k, a:b] for a, b in zip(self.edges[:-1], self.edges[1:])])
            sums = np.cumsum(seg, axis=0)
            self.G[:, k, js] = sums
            self.G[:, js, k] = sums
            self.have[k, js] = self.have[js, k] = True
            missing[:, i] = False       # the pairs just filled, seen from the other side

    def _keys(self, term: Term, fit: bool) -> list[int]:
        held = self.by_id.get((id(term), fit))
        if held is not None and held[0] is term:
            return held[1]
        r = repr(term)
        hit = self.by_repr.get((r, fit))
        if hit is None:
            hit = self.by_repr[(r, fit)] = self._make_keys(term, r, fit)
        self.by_id[(id(term), fit)] = (term, hit)       # the term held: its id is not reused
        return hit

    def _make_keys(self, term: Term, r: str, fit: bool) -> list[int]:
        if fit and isinstance(term, LinearTerm) and not term.filtered:
            r, F = "fit:" + r, self.data.fit_rise(term.sensor)[:, None]
        else:
            F = design(self.data, [term])        # per run for several runs: memory starts afresh in each
        keys = [f"{r}#{i}" for i in range(F.shape[1])]
        return [self.index[key] if key in self.index else self._add(key, np.asarray(F[:, i], dtype=float))
                for i, key in enumerate(keys)]

    def errors(self, terms: Sequence[Term]) -> np.ndarray:
        fk = [k for t in terms for k in self._keys(t, True)]
        pk = [k for t in terms for k in self._keys(t, False)]
        seen = (tuple(fk), tuple(pk))
        hit = self.seen.get(seen)
        if hit is not None:         # the searches score many a design again
            self.seen.move_to_end(seen)
            return hit
        e = self._errors(np.array([*fk, self.one]), pk)
        e.flags.writeable = False
        self.seen[seen] = e
        if len(self.seen) > self.SEEN:
            self.seen.popitem(last=False)
        return e

    def _errors(self, fk: np.ndarray, pk: list[int]) -> np.ndarray:
        self._products(np.append(fk, self.iy))
        m = len(fk)
        S = self.G[:, fk[:, None], fk]                      # folds x m x m, a copy
        Sy = self.G[:, fk, self.iy]                         # folds x m
        nf = S[:, -1, -1]                                   # rows each fold is fitted on
        diag = S.reshape(len(S), m * m)[:, ::m + 1]         # a view: the ridge goes on it
        var = diag / nf[:, None] - (S[:, :, -1] / nf[:, None]) ** 2
        var[var <= 0] = 1.0
        var[:, -1] = 0.0
        # every fold's fit in one batched solve, every row predicted by its fold's
        diag += _RIDGE * nf[:, None] * var
        coef = np.linalg.solve(S, Sy[:, :, None])[:, :, 0]
        # fitted on columns less their means, predicted from other columns (raw rises for
        # smoothed ones) less theirs: the difference of the means moves the intercept
        icpt = coef[:, -1] + coef[:, :-1] @ (self.shift[pk] - self.shift[fk[:-1]]) if pk else coef[:, -1]
        e = self.X[self.iy, self.o:] - icpt[self.row_fold]
        if pk:
            # each fold's rows by its own coefficients: a product per fold, not a row-by-row gather
            for i, f in enumerate(self.folds):
                e[f.lo - self.o:f.hi - self.o] -= coef[i, :-1] @ self.X[pk, f.lo:f.hi]
        return e


def cached_forward(data: ThermalData | ThermalRuns, terms: Sequence[Term], folds: Sequence[Fold]) -> np.ndarray:
    """Forward errors of least squares on ``terms`` (see ForwardCache), the cache kept on the data."""
    cache = data.__dict__.setdefault("_forward", {})
    key = tuple((f.lo, f.hi) for f in folds)
    fc = cache.get(key)
    if fc is None or fc.y is not data.displacement_um or fc.rpm is not data.rpm:
        fc = cache[key] = ForwardCache(data, folds)
    return fc.errors(terms)
