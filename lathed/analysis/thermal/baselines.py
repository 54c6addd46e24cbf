"""Fitting a stage on the training rows, and the plain baselines every thermal report carries and
every choice must beat: least squares on all sensors, the same with the speed, and a ridge
regression on the temperatures and their first-order lags. See docs/thermal.md."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from lathed.analysis.forward import N_FOLDS, Fold, forward_folds, rmse
from lathed.analysis.thermal.data import ThermalData, ThermalRuns
from lathed.analysis.thermal.fit import _RIDGE, design, fit_coefficients, fit_design, forward_errors
from lathed.analysis.thermal.model import ThermalModel
from lathed.analysis.thermal.report import Stage
from lathed.analysis.thermal.terms import LagTerm, LinearTerm, SpeedTerm, Term

# The ridge baseline's lags: a quarter of an hour and an hour, the time scales of a spindle's
# housings; its penalty (relative to the rows, on standardised columns) from this grid.
RIDGE_LAGS_S = (900.0, 3600.0)
RIDGE_GRID = tuple(float(v) for v in 10.0 ** np.arange(-6.0, 1.01, 0.5))

Rows = ThermalData | ThermalRuns


def fit_stage(train: Rows, terms: Sequence[Term], test: Rows | None, cut: int, label: str,
              notes: Sequence[str] = (), *, raw: bool = False, source: str = "fit", ridge: float = _RIDGE,
              baseline: bool = False) -> Stage:
    """Least squares on ``terms``: fitted on the training rows before ``cut`` and judged on the
    rows after (its forward error), then fitted on every training row (the model), and judged on
    ``test`` (the forward error without one). ``raw``: fitted on the readings as read (the
    baselines), else on the smoothed rises where smoothing takes out only noise."""
    X = design(train, terms)
    Xf = X if raw else fit_design(train, terms)
    y = train.displacement_um
    c0, i0 = fit_coefficients(Xf[:cut], y[:cut], ridge)
    e_fw = y[cut:] - (X[cut:] @ c0 + i0)
    coef, icpt = fit_coefficients(Xf, y, ridge)
    model = ThermalModel(list(terms), coef, icpt, list(notes), source=source, rises_from=train.rises_from)
    test_rmse = rmse(test.displacement_um - model.predict(test)) if test is not None else rmse(e_fw)
    rolling = _rolling_rmse(X, Xf, y, ridge) if baseline else None
    return Stage(model, rmse(y - (X @ coef + icpt)), rmse(e_fw), test_rmse, label, baseline, e_fw, rolling)


def _rolling_rmse(X: np.ndarray, Xf: np.ndarray, y: np.ndarray, ridge: float) -> float:
    """Expanding-window error over the later half of every training row: a plain baseline is
    not searched, so it can be judged on all of them, and a choice between baselines made on
    one block of rows follows that block's chance (two within 1 % there can differ 25 % later)."""
    e = []
    for f in forward_folds(len(y), N_FOLDS):
        c, i = fit_coefficients(Xf[:f.lo], y[:f.lo], ridge)
        e.append(y[f.lo:f.hi] - (X[f.lo:f.hi] @ c + i))
    return rmse(np.concatenate(e))


def judged(model: ThermalModel, rows: Rows) -> float | None:
    """A fixed model's error on ``rows``; None when it needs a column they lack."""
    try:
        return rmse(rows.displacement_um - model.predict(rows))
    except ValueError:
        return None


def _sensors(train: Rows, test: Rows | None) -> list[str]:
    out = [s for s in train.sensors if np.ptp(train.rise(s)) > 0 and (test is None or s in test.temps_c)]
    if not out:
        raise ValueError("no temperature column changed during the run: nothing to fit the growth to")
    return out


def least_squares_stage(train: Rows, test: Rows | None, cut: int, folds: Sequence[Fold]) -> Stage:
    """Least squares on every sensor that changed, as read: no selection, no effect."""
    sensors = _sensors(train, test)
    return fit_stage(train, [LinearTerm(s) for s in sensors], test, cut,
                     f"least squares on {len(sensors)} sensor(s)",
                     [f"plain least squares on {len(sensors)} sensor(s)"], raw=True, source="least_squares",
                     baseline=True)


def speed_stage(train: Rows, test: Rows | None, cut: int, folds: Sequence[Fold]) -> Stage | None:
    """The same with the spindle speed (krpm) as a column; None without a speed that varies."""
    if train.rpm is None or np.ptp(train.rpm) == 0 or (test is not None and test.rpm is None):
        return None
    sensors = _sensors(train, test)
    return fit_stage(train, [*(LinearTerm(s) for s in sensors), SpeedTerm("n")], test, cut,
                     f"least squares on {len(sensors)} sensor(s) and the speed",
                     [f"plain least squares on {len(sensors)} sensor(s) and the speed"], raw=True,
                     source="least_squares_speed", baseline=True)


def ridge_lags_stage(train: Rows, test: Rows | None, cut: int, folds: Sequence[Fold]) -> Stage:
    """Ridge regression on every sensor's rise and its first-order lags (``RIDGE_LAGS_S``), the
    penalty the one of ``RIDGE_GRID`` with the least forward error."""
    sensors = _sensors(train, test)
    terms: list[Term] = [t for s in sensors for t in (LinearTerm(s), *(LagTerm(s, tau) for tau in RIDGE_LAGS_S))]
    X = design(train, terms)
    y = train.displacement_um
    # the penalty chosen on the forward folds of the rows before the cut only
    lam = min(RIDGE_GRID, key=lambda r: rmse(forward_errors(X[:cut], y[:cut], folds, ridge=r)))
    lags = " and ".join(f"{tau / 60:g} min" for tau in RIDGE_LAGS_S)
    return fit_stage(train, terms, test, cut, f"ridge on {len(sensors)} sensor(s) and their lags ({lags})",
                     [f"ridge regression on {len(sensors)} sensor(s) and their lags ({lags}), penalty {lam:g} "
                      f"chosen forward in time"], raw=True, source="ridge_lags", ridge=lam, baseline=True)


def baseline_stages(train: Rows, test: Rows | None, cut: int, folds: Sequence[Fold]) -> list[Stage]:
    """The plain baselines, least squares on all sensors first; ``folds`` are those of the rows
    before ``cut`` (see ``fit_stage``)."""
    out = [least_squares_stage(train, test, cut, folds), speed_stage(train, test, cut, folds),
           ridge_lags_stage(train, test, cut, folds)]
    return [s for s in out if s is not None]
