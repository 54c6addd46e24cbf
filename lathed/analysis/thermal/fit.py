"""Least squares on a run's terms, and its errors judged forward in time (see lathed.analysis.forward)."""
from __future__ import annotations

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
    in a column or two: the cross-products of every pair of columns up to each fold's origin are
    kept, so a design's forward errors cost a few small solves. Same algebra as
    ``forward_errors`` (the ridge on standardised columns is a ridge of ``_RIDGE * rows * var``
    on the raw ones, the variance over the fold's own rows)."""

    def __init__(self, data: ThermalData | ThermalRuns, folds: Sequence[Fold]):
        self.data = data
        y = data.displacement_um
        self.folds = list(folds)
        self.o = first_row(self.folds)
        self.origins = np.array([f.lo for f in self.folds])
        self.row_fold = np.repeat(np.arange(len(self.folds)), [f.hi - f.lo for f in self.folds])
        self.cols: dict[str, np.ndarray] = {"1": np.ones(len(y)), "y": y}
        self.sums: dict[tuple[str, str], np.ndarray] = {}
        self.by_id: dict[tuple[int, bool], tuple[Term, list[str]]] = {}
        self.rpm = data.rpm

    def _keys(self, term: Term, fit: bool) -> list[str]:
        hit = self.by_id.get((id(term), fit))
        if hit is not None and hit[0] is term:
            return hit[1]
        keys = self._make_keys(term, fit)
        self.by_id[(id(term), fit)] = (term, keys)     # the term held: its id is not reused
        return keys

    def _make_keys(self, term: Term, fit: bool) -> list[str]:
        k = repr(term)
        if fit and isinstance(term, LinearTerm) and not term.filtered:
            k, F = "fit:" + k, self.data.fit_rise(term.sensor)[:, None]
        else:
            F = None
        X = design(self.data, [term])        # per run for several runs: memory starts afresh in each
        keys = [f"{k}#{i}" for i in range(X.shape[1])]
        if keys[0] not in self.cols:
            F = X if F is None else F
            for i, key in enumerate(keys):
                self.cols[key] = np.ascontiguousarray(F[:, i])
        return keys

    def _pair(self, a: str, b: str) -> np.ndarray:
        """Sums of a*b over rows [0, origin) for each fold's origin."""
        key = (a, b) if a <= b else (b, a)
        out = self.sums.get(key)
        if out is None:
            cs = np.concatenate([[0.0], np.cumsum(self.cols[a] * self.cols[b])])
            out = self.sums[key] = cs[self.origins]
        return out

    def errors(self, terms: Sequence[Term]) -> np.ndarray:
        fk = [k for t in terms for k in self._keys(t, True)] + ["1"]
        pk = [k for t in terms for k in self._keys(t, False)]
        m = len(fk)
        S = np.empty((m, m, len(self.folds)))
        for i in range(m):
            for j in range(i, m):
                S[i, j] = S[j, i] = self._pair(fk[i], fk[j])
        Sy = np.array([self._pair(k, "y") for k in fk])
        nf = S[m - 1, m - 1]                       # rows each fold is fitted on
        var = S[np.arange(m), np.arange(m)] / nf - (S[:, m - 1] / nf) ** 2
        var = np.where(var > 0, var, 1.0)
        var[-1] = 0.0
        # every fold's fit in one batched solve, every row predicted by its fold's
        G = np.moveaxis(S, 2, 0).copy()
        G[:, np.arange(m), np.arange(m)] += _RIDGE * nf[:, None] * var.T
        coef = np.linalg.solve(G, Sy.T[:, :, None])[:, :, 0][self.row_fold]
        y = self.cols["y"][self.o:]
        P = np.column_stack([self.cols[k][self.o:] for k in pk]) if pk else np.empty((len(y), 0))
        return y - np.einsum("ij,ij->i", P, coef[:, :-1]) - coef[:, -1]


def cached_forward(data: ThermalData | ThermalRuns, terms: Sequence[Term], folds: Sequence[Fold]) -> np.ndarray:
    """Forward errors of least squares on ``terms`` (see ForwardCache), the cache kept on the data."""
    cache = data.__dict__.setdefault("_forward", {})
    key = tuple((f.lo, f.hi) for f in folds)
    fc = cache.get(key)
    if fc is None or fc.cols["y"] is not data.displacement_um or fc.rpm is not data.rpm:
        fc = cache[key] = ForwardCache(data, folds)
    return fc.errors(terms)
