"""Thermal error model of the spindle and the loop that finds what it lacks.

The paper (eq. 14) fits the nose growth as a static linear function of four
temperature rises. This module fits that regression by least squares, then
runs a residual loop: each *candidate effect* (sensor lag, temperature rate,
speed, nonlinearity, hysteresis, drift, or one a plugin supplies) proposes
extra terms; the one that most lowers the error on held-out contiguous time
blocks is added when the fall is both large enough to matter and
statistically significant; repeat. What is left is checked for structure
(autocorrelation, a periodicity) that no candidate explained.

The terms and candidate effects live in :mod:`lathed.analysis.thermal_terms`
(re-exported here). Pure numpy/scipy, no asyncio: the daemon's analyzer,
``lathectl analyze thermal`` and ``lathectl thermal refit`` all call the
same functions.

Units: temperatures °C, rises °C from the run's start, displacement µm,
time s, speed r/min.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

# The paper's printed eq. 14 (ΔN in mm per °C rise); we work in µm.
EQ14_COEF_MM_PER_C = {"t_front_bearing_c": -0.00911, "t_rear_bearing_c": 0.00606,
                      "t_motor_c": 0.009833, "t_room_c": 0.000548}
EQ14_INTERCEPT_MM = -0.22194

_REF_ROWS = 10        # rows in the line fitted for the starting temperature when rows are sparse
_REF_WINDOW_S = 300.0  # ... or the span of the quadratic fitted when they are dense (see _start_temp)
_REF_MIN_ROWS = 20
# spans tried for the local quadratic that takes sensor noise out of the fit (see smooth_rows)
_SMOOTH_SPANS_S = (120.0, 240.0, 480.0, 960.0, 1920.0)


def sensor_column(key: str) -> str:
    """``front_bearing``, ``t_front_bearing`` or ``t_front_bearing_c`` -> ``t_front_bearing_c``."""
    if key.startswith("t_"):
        return key if key.endswith("_c") else f"{key}_c"
    return f"t_{key}_c"


# -- data -----------------------------------------------------------------

def _start_temp(t_s: np.ndarray, x: np.ndarray) -> float:
    """Temperature at the first row, from a curve through the first rows: one
    DS18B20 reading is 1/16 °C coarse, and a plain mean would include the
    first minutes' warm-up in the reference. With dense rows, a quadratic
    over the first ``_REF_WINDOW_S`` (the warm-up bends within minutes);
    otherwise a line through the first ``_REF_ROWS`` rows. Every sensor's
    error here is an offset of the whole run's prediction."""
    dense = int(np.searchsorted(t_s, t_s[0] + _REF_WINDOW_S, side="right"))
    if dense >= _REF_MIN_ROWS:
        k, deg = dense, 2
    else:
        k, deg = min(_REF_ROWS, len(x)), 1
    if k < 3 or np.ptp(t_s[:k]) == 0:
        return float(x[0])
    return float(np.polyval(np.polyfit(t_s[:k] - t_s[0], x[:k], deg), 0.0))


def _savgol_window(t_s: np.ndarray, span_s: float) -> int:
    """Rows (odd) in ``span_s``; 0 when under 7 rows, or when the span would
    reach over more than 1/20 of the run (sparse rows, such as one probe per
    part: neighbouring rows are then not repeat readings of one temperature)."""
    n = len(t_s)
    dt = float(np.median(np.diff(t_s))) if n > 1 else 0.0
    w = min(int(span_s / dt) if dt > 0 else 0, n // 20)
    w -= w % 2 == 0
    return w if w >= 7 else 0


def smooth_rows(t_s: np.ndarray, x: np.ndarray, span_s: float | None = None) -> np.ndarray:
    """Local quadratic (Savitzky-Golay) through the rows: the sensor noise
    (~0.03 °C a reading) taken out, the bends of a warm-up kept. The span is
    ``span_s`` when given, else the one of ``_SMOOTH_SPANS_S`` with the least
    leave-one-out error on this signal (a room sensor drifting over hours
    takes a longer span than a bearing that bends within minutes)."""
    from scipy.signal import savgol_coeffs, savgol_filter
    best = (math.inf, x)
    for sp in ((span_s,) if span_s is not None else _SMOOTH_SPANS_S):
        w = _savgol_window(t_s, sp)
        if not w:
            continue
        y = savgol_filter(x, w, 2, mode="interp")
        if span_s is not None:
            return y
        h0 = float(savgol_coeffs(w, 2)[w // 2])
        loo = float(np.mean(np.square((x - y) / (1.0 - h0))))
        if loo < best[0]:
            best = (loo, y)
    return best[1]


@dataclass
class ThermalData:
    """One contiguous run: time stamps, temperatures per column, speed, and
    the measured displacement (None when only predicting)."""
    time_s: np.ndarray
    temps_c: dict[str, np.ndarray]
    displacement_um: np.ndarray | None = None
    rpm: np.ndarray | None = None
    reference_c: dict[str, float] | None = None   # temperatures the rises start from
    t0_s: float | None = None                     # start of the run (drift clock)

    def __post_init__(self) -> None:
        self.time_s = np.asarray(self.time_s, dtype=float)
        self.temps_c = {k: np.asarray(v, dtype=float) for k, v in self.temps_c.items()}
        if self.displacement_um is not None:
            self.displacement_um = np.asarray(self.displacement_um, dtype=float)
        if self.rpm is not None:
            self.rpm = np.asarray(self.rpm, dtype=float)
        if len(self.time_s) == 0:
            raise ValueError("thermal data has no rows")
        if self.reference_c is None:
            self.reference_c = {k: _start_temp(self.time_s, v) for k, v in self.temps_c.items()}
        if self.t0_s is None:
            self.t0_s = float(self.time_s[0])

    def __len__(self) -> int:
        return len(self.time_s)

    @property
    def sensors(self) -> list[str]:
        return list(self.temps_c)

    def rise(self, column: str) -> np.ndarray:
        return self.temps_c[column] - self.reference_c[column]

    def smooth_rise(self, column: str) -> np.ndarray:
        """The rise with the sensor noise smoothed out, for fitting only."""
        cache = self.__dict__.setdefault("_smooth", {})
        if column not in cache:
            cache[column] = smooth_rows(self.time_s, self.rise(column))
        return cache[column]

    def slice(self, lo: int, hi: int) -> ThermalData:
        """Rows lo:hi, keeping this run's reference and start time."""
        return ThermalData(self.time_s[lo:hi], {k: v[lo:hi] for k, v in self.temps_c.items()},
                           None if self.displacement_um is None else self.displacement_um[lo:hi],
                           None if self.rpm is None else self.rpm[lo:hi],
                           dict(self.reference_c), self.t0_s)


class ThermalRuns:
    """Several runs, each from its own cold start (days of probe data): one
    set of rows for the fit, but each run keeps its own reference
    temperatures and drift clock, and terms with memory (lag, rate,
    hysteresis) start afresh in each. Behaves as a ThermalData for the
    residual loop; ``time_s`` is each row's time since its run's start."""

    def __init__(self, runs: Sequence[ThermalData]):
        self.runs = [r for r in runs if len(r)]
        if not self.runs:
            raise ValueError("thermal data has no rows")
        cols = [set(r.temps_c) for r in self.runs]
        if any(c != cols[0] for c in cols):
            raise ValueError("the runs do not have the same temperature columns")
        cat = np.concatenate
        self.time_s = cat([r.time_s - r.t0_s for r in self.runs])
        self.t0_s = 0.0
        self.temps_c = {k: cat([r.temps_c[k] for r in self.runs]) for k in self.runs[0].temps_c}
        self.displacement_um = (None if any(r.displacement_um is None for r in self.runs)
                                else cat([r.displacement_um for r in self.runs]))
        self.rpm = None if any(r.rpm is None for r in self.runs) else cat([r.rpm for r in self.runs])
        self.reference_c = self.runs[0].reference_c

    def __len__(self) -> int:
        return len(self.time_s)

    @property
    def sensors(self) -> list[str]:
        return self.runs[0].sensors

    def rise(self, column: str) -> np.ndarray:
        return np.concatenate([r.rise(column) for r in self.runs])

    def smooth_rise(self, column: str) -> np.ndarray:
        return np.concatenate([r.smooth_rise(column) for r in self.runs])

    def slice(self, lo: int, hi: int) -> ThermalRuns:
        out, start = [], 0
        for r in self.runs:
            a, b = max(lo - start, 0), min(hi - start, len(r))
            if a < b:
                out.append(r.slice(a, b))
            start += len(r)
        return ThermalRuns(out)


from lathed.analysis.thermal_terms import (  # noqa: F401  (re-exported: plugins import them from here)
    Candidate, DriftCandidate, DriftTerm, HysteresisCandidate, HysteresisTerm, LagCandidate, LagTerm,
    LinearTerm, NonlinearCandidate, NonlinearTerm, RateCandidate, RateTerm, SpeedCandidate, SpeedTerm,
    Term, builtin_candidates, lag_filter, play_operator)

# -- least squares --------------------------------------------------------

_RIDGE = 1e-6          # relative to n on standardised columns: only bites on exact collinearity
COLLINEAR_R = 0.999


def _design(data: ThermalData | ThermalRuns, terms: Sequence[Term]) -> np.ndarray:
    if isinstance(data, ThermalRuns):      # terms with memory start afresh in each run
        return np.vstack([_design(r, terms) for r in data.runs])
    cols = [np.asarray(t.features(data), dtype=float).reshape(len(data), -1) for t in terms]
    return np.hstack(cols) if cols else np.empty((len(data), 0))


def _fit_design(data: ThermalData, terms: Sequence[Term]) -> np.ndarray:
    """The design the coefficients are fitted on: as ``_design``, but the
    sensors' own (linear) columns with their reading noise smoothed out.

    The heated sensors move nearly in lock-step (rear bearing and motor warm
    with the same speed, r > 0.99), so what tells their weights apart is a
    few hundredths of a °C, the size of a DS18B20's noise: fitted on the raw
    readings the weights are biased along that direction (errors in
    variables), which costs nothing on the training run and a slow ramp of
    error on a run with another speed schedule. Predictions still use the
    raw readings."""
    if isinstance(data, ThermalRuns):
        return np.vstack([_fit_design(r, terms) for r in data.runs])
    cols = [data.smooth_rise(t.sensor)[:, None] if isinstance(t, LinearTerm)
            else np.asarray(t.features(data), dtype=float).reshape(len(data), -1) for t in terms]
    return np.hstack(cols) if cols else np.empty((len(data), 0))


class _Scaled:
    """Standardised design with an intercept; ridge on everything but the intercept."""

    def __init__(self, X: np.ndarray):
        self.mu = X.mean(axis=0)
        sd = X.std(axis=0)
        self.sd = np.where(sd > 0, sd, 1.0)

    def __call__(self, X: np.ndarray) -> np.ndarray:
        return np.hstack([(X - self.mu) / self.sd, np.ones((len(X), 1))])


def _solve(G: np.ndarray, b: np.ndarray, n: int) -> np.ndarray:
    reg = np.full(len(G), _RIDGE * max(n, 1))
    reg[-1] = 0.0
    return np.linalg.solve(G + np.diag(reg), b)


def fit_coefficients(X: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, float]:
    """Least squares y ≈ X·coef + intercept, in the raw units of X."""
    sc = _Scaled(X)
    Z = sc(X)
    beta = _solve(Z.T @ Z, Z.T @ y, len(y))
    coef = beta[:-1] / sc.sd
    return coef, float(beta[-1] - coef @ sc.mu)


def blocks(n: int, n_blocks: int) -> list[tuple[int, int]]:
    edges = np.linspace(0, n, n_blocks + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def heldout_errors(X: np.ndarray, y: np.ndarray, n_blocks: int = 5, gap: int = 10,
                   X_pred: np.ndarray | None = None) -> np.ndarray:
    """Error on each row when its contiguous time block is held out; the
    ``gap`` rows either side are left out of the fit too, since a thermal
    signal carries over from one row to the next. The fit is made on ``X``
    and the held-out rows predicted from ``X_pred`` (default ``X``; see
    ``_fit_design``)."""
    n = len(y)
    sc = _Scaled(X)
    Z = sc(X)
    P = Z if X_pred is None else sc(X_pred)
    G = Z.T @ Z
    b = Z.T @ y
    err = np.empty(n)
    for lo, hi in blocks(n, n_blocks):
        a, c = max(lo - gap, 0), min(hi + gap, n)
        Ze = Z[a:c]
        beta = _solve(G - Ze.T @ Ze, b - Ze.T @ y[a:c], n - (c - a))
        err[lo:hi] = y[lo:hi] - P[lo:hi] @ beta
    return err


def rmse(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(e))))


def improvement_z(e_old: np.ndarray, e_new: np.ndarray) -> float:
    """Diebold-Mariano statistic for the fall in squared error, with a
    Newey-West variance: neighbouring rows' errors are correlated, so a plain
    t-test would see significance everywhere."""
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


# -- the model ------------------------------------------------------------

@dataclass
class ThermalModel:
    """Displacement (µm) = Σ coef·column + intercept over the terms' columns."""
    terms: list[Term]
    coef: np.ndarray
    intercept_um: float
    notes: list[str] = field(default_factory=list)
    source: str = "fit"

    @property
    def names(self) -> list[str]:
        return [nm for t in self.terms for nm in t.names]

    @property
    def sensors(self) -> list[str]:
        return sorted({t.sensor for t in self.terms if t.sensor})

    def predict(self, data: ThermalData) -> np.ndarray:
        missing = [s for s in self.sensors if s not in data.temps_c]
        if missing:
            raise ValueError(f"the thermal model needs temperature column(s) {', '.join(missing)}")
        return _design(data, self.terms) @ self.coef + self.intercept_um

    def predictor(self, reference_c: Mapping[str, float] | None = None,
                  t0_s: float | None = None) -> ThermalPredictor:
        return ThermalPredictor(self, reference_c, t0_s)

    def to_dict(self) -> dict[str, Any]:
        terms = []
        i = 0
        for t in self.terms:
            k = len(t.names)
            d: dict[str, Any] = {"effect": t.effect, "params": dict(t.params),
                                 "coef": [float(c) for c in self.coef[i:i + k]]}
            if t.sensor:
                d["sensor"] = t.sensor
            terms.append(d)
            i += k
        return {"format": 1, "source": self.source, "intercept_um": float(self.intercept_um),
                "notes": list(self.notes), "terms": terms}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], candidates: Sequence[Candidate] = ()) -> ThermalModel:
        makers: dict[str, Any] = {c.name: c for c in [*builtin_candidates(), *candidates]}
        terms: list[Term] = []
        coef: list[float] = []
        for i, td in enumerate(d.get("terms", [])):
            eff = td.get("effect")
            if eff == "linear":
                term: Term = LinearTerm(td["sensor"])
            elif eff in makers:
                term = makers[eff].make_term(td.get("sensor"), td.get("params", {}))
            else:
                raise ValueError(f"thermal model term {i + 1} has effect {eff!r}, which no "
                                 f"candidate provides (known: linear, {', '.join(makers)})")
            if len(td.get("coef", [])) != len(term.names):
                raise ValueError(f"thermal model term {i + 1} ({eff}) needs {len(term.names)} "
                                 f"coefficient(s), has {len(td.get('coef', []))}")
            terms.append(term)
            coef += [float(c) for c in td["coef"]]
        return cls(terms, np.array(coef), float(d["intercept_um"]), list(d.get("notes", [])),
                   str(d.get("source", "fit")))


def eq14_model(path: str | Path | None = None) -> ThermalModel:
    """The paper's printed regression, in µm; from its TOML table when given."""
    coef_mm, icpt_mm = EQ14_COEF_MM_PER_C, EQ14_INTERCEPT_MM
    if path is not None:
        import tomllib
        with open(path, "rb") as f:
            t = tomllib.load(f)
        coef_mm = {sensor_column(k): float(v) for k, v in t["coefficients_mm_per_degc"].items()}
        icpt_mm = float(t["intercept_mm"])
    terms = [LinearTerm(s) for s in coef_mm]
    return ThermalModel(terms, np.array([coef_mm[s] * 1000.0 for s in coef_mm]), icpt_mm * 1000.0,
                        ["paper eq. 14 (printed mm, here µm)"], source="eq14")


def save_model(model: ThermalModel, path: str | Path, meta: Mapping[str, Any] | None = None) -> None:
    import tomli_w
    d = model.to_dict()
    if meta:
        d["meta"] = dict(meta)
    from lathed.atomic import write_atomic
    write_atomic(path, tomli_w.dumps(d).encode())


def load_model(path: str | Path, candidates: Sequence[Candidate] = ()) -> ThermalModel:
    import tomllib
    with open(path, "rb") as f:
        return ThermalModel.from_dict(tomllib.load(f), candidates)


class ThermalPredictor:
    """Live prediction: feed temperatures as they arrive, get the growth.

    Temperatures may be keyed ``front_bearing`` or ``t_front_bearing_c``.
    Rises are taken from ``reference_c`` (the cold-start temperatures), or
    from the first reading when none is given; the drift clock runs from
    ``t0_s``, or from the first update. Terms with memory (lag, rate,
    hysteresis) keep their state here, so call ``update`` in time order; they
    start settled at the first reading.
    """

    def __init__(self, model: ThermalModel, reference_c: Mapping[str, float] | None = None,
                 t0_s: float | None = None):
        self.model = model
        self.reference_c = None if reference_c is None else {sensor_column(k): float(v)
                                                             for k, v in reference_c.items()}
        self._streams = [t.stream() for t in model.terms]
        self._t0 = t0_s
        self.prediction_um: float | None = None

    def update(self, temps_c: Mapping[str, float], rpm: float | None = None,
               t_s: float | None = None) -> float:
        temps = {sensor_column(k): float(v) for k, v in temps_c.items()}
        missing = [s for s in self.model.sensors if s not in temps]
        if missing:
            raise ValueError(f"no reading from {', '.join(missing)}: the thermal model needs it")
        if self.reference_c is None:
            self.reference_c = {s: temps[s] for s in self.model.sensors}
        t = 0.0 if t_s is None else float(t_s)
        if self._t0 is None:
            self._t0 = t
        unreferenced = [s for s in self.model.sensors if s not in self.reference_c]
        if unreferenced:
            raise ValueError(f"no reference temperature for {', '.join(unreferenced)}: "
                             f"the rises cannot be taken")
        rises = {s: temps[s] - self.reference_c[s] for s in self.model.sensors}
        vals: list[float] = []
        for term, f in zip(self.model.terms, self._streams):
            if f is None:      # drift: hours on the predictor's clock
                vals.append(float(term.hours((t - self._t0) / 3600.0)))
            else:
                vals.extend(float(v) for v in f(t, rises, rpm))
        self.prediction_um = float(np.dot(self.model.coef, vals) + self.model.intercept_um)
        return self.prediction_um


# -- the residual loop ----------------------------------------------------

@dataclass
class Stage:
    model: ThermalModel
    rmse_um: float          # in-sample on the training data
    heldout_rmse_um: float  # held-out time blocks of the training data
    test_rmse_um: float     # on the test run, or held-out blocks without one

    def to_json(self) -> dict[str, Any]:
        return {"terms": self.model.names, "rmse_um": round(self.rmse_um, 4),
                "test_rmse_um": round(self.test_rmse_um, 4)}


@dataclass
class EffectFound:
    term: Term
    stage: Stage
    gain: float     # relative fall of the held-out error when added
    z: float        # its significance

    def to_json(self) -> dict[str, Any]:
        i = self.stage.model.names.index(self.term.names[0])
        coef = self.stage.model.coef[i:i + len(self.term.names)]
        params = dict(self.term.params)
        params["coef"] = [round(float(c), 6) for c in coef] if len(coef) > 1 else round(float(coef[0]), 6)
        return {"effect": self.term.effect, "sensor": self.term.sensor, "params": params,
                "test_rmse_um": round(self.stage.test_rmse_um, 4)}


@dataclass
class ResidualReport:
    structured: bool
    note: str
    noise_um: float
    lag1: float
    period_s: float | None = None


@dataclass
class Analysis:
    baseline: Stage
    effects: list[EffectFound]
    final: Stage
    residual: ResidualReport
    notes: list[str]

    @property
    def model(self) -> ThermalModel:
        return self.final.model

    def to_json(self) -> dict[str, Any]:
        return {"baseline": self.baseline.to_json(), "effects": [e.to_json() for e in self.effects],
                "final": self.final.to_json(),
                "residual": {"structured": self.residual.structured, "note": self.residual.note},
                "notes": self.notes}


def baseline_terms(data: ThermalData, n_blocks: int = 5, gap: int = 10) -> tuple[list[Term], list[str]]:
    """One linear term per temperature column, less those that cannot be
    fitted: a sensor that never changed, or one that moves in lock-step with
    another and adds nothing on held-out blocks (two sensors reading the same
    heat; keeping both would split or, with noise, oppose their weights)."""
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
        with_s = rmse(heldout_errors(np.column_stack([data.rise(k) for k in keep]), y, n_blocks, gap))
        without = [k for k in keep if k != s]
        without_s = rmse(heldout_errors(np.column_stack([data.rise(k) for k in without]), y, n_blocks, gap))
        if without_s <= 1.01 * with_s:
            keep = without
            notes.append(f"{s} moves with {twin} (r={r:.5f}): the two sensors read the same heat; "
                         f"fitted on {twin} only")
        else:
            notes.append(f"{s} moves with {twin} (r={r:.5f}) but still adds on held-out blocks "
                         f"({without_s:.2f} -> {with_s:.2f} µm): both kept")
    return [LinearTerm(s) for s in keep], notes


def _stage(train: ThermalData, terms: list[Term], test: ThermalData | None,
           n_blocks: int, gap: int, notes: list[str]) -> tuple[Stage, np.ndarray]:
    X = _design(train, terms)
    Xf = _fit_design(train, terms)
    y = train.displacement_um
    coef, icpt = fit_coefficients(Xf, y)
    model = ThermalModel(list(terms), coef, icpt, list(notes))
    e_cv = heldout_errors(Xf, y, n_blocks, gap, X)
    fit_rmse = rmse(y - (X @ coef + icpt))
    test_rmse = rmse(test.displacement_um - model.predict(test)) if test is not None else rmse(e_cv)
    return Stage(model, fit_rmse, rmse(e_cv), test_rmse), e_cv


def residual_structure(t_s: np.ndarray, e: np.ndarray) -> ResidualReport:
    """Is there more in the residual than noise? Compares its rms with the
    sample-to-sample scatter (which smooth structure does not inflate) and
    looks for a spectral line."""
    e = np.asarray(e, float) - np.mean(e)
    n = len(e)
    if n < 16:
        return ResidualReport(False, f"only {n} rows: too few to judge the residual", rmse(e), 0.0)
    d = np.diff(e)
    noise = float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2))
    total = rmse(e)
    lag1 = float((e[1:] @ e[:-1]) / (e @ e)) if total > 0 else 0.0
    # Periodogram on an even grid (the median step); linear trend removed.
    dt = float(np.median(np.diff(t_s)))
    tt = np.arange(n) * dt
    det = e - np.polyval(np.polyfit(tt, e, 1), tt)
    p = np.abs(np.fft.rfft(det)) ** 2
    f = np.fft.rfftfreq(n, dt)
    period = None
    share = 0.0
    if len(p) > 8:
        k = 3 + int(np.argmax(p[3:]))        # skip the slowest bins: trend, not a period
        band = p[max(k - 1, 1):k + 2].sum()
        share = float(band / p[1:].sum())
        if share > 0.2 and p[k] > 20 * np.median(p[1:]):
            period = 1.0 / f[k]
    ratio = total / noise if noise > 0 else (1.0 if total < 1e-12 else math.inf)
    structured = ratio > 1.3 or period is not None
    if not structured:
        note = (f"residual looks like measurement noise: rms {total:.2f} µm vs {noise:.2f} µm "
                f"sample-to-sample, lag-1 autocorrelation {lag1:.2f}")
    else:
        note = (f"structure left that no candidate explains: residual rms {total:.2f} µm is "
                f"{ratio:.1f}x the sample-to-sample noise ({noise:.2f} µm), lag-1 autocorrelation {lag1:.2f}")
        if period is not None:
            note += f"; a periodicity of {period / 60:.1f} min carries {100 * share:.0f}% of its variance"
    return ResidualReport(structured, note, noise, lag1, period)


def analyze(train: ThermalData, test: ThermalData | None = None, *,
            candidates: Sequence[Candidate] | None = None, extra_candidates: Sequence[Candidate] = (),
            max_effects: int = 4, n_blocks: int = 5, gap_rows: int = 10,
            min_gain: float = 0.05, min_z: float = 2.0) -> Analysis:
    """Fit the linear baseline on ``train``, then add candidate effects while
    one lowers the held-out error by at least ``min_gain`` (relative) with a
    Diebold-Mariano z of at least ``min_z``. Effects are chosen on held-out
    blocks of ``train`` only; ``test`` (another run) is only reported on."""
    if train.displacement_um is None:
        raise ValueError("training data has no displacement_um to fit")
    if len(train) < 10 * n_blocks:
        raise ValueError(f"{len(train)} rows are too few for {n_blocks} held-out blocks "
                         f"(need at least {10 * n_blocks})")
    cands = list(builtin_candidates() if candidates is None else candidates) + list(extra_candidates)
    gap = min(gap_rows, len(train) // (4 * n_blocks))
    terms, notes = baseline_terms(train, n_blocks, gap)
    base, e_cur = _stage(train, terms, test, n_blocks, gap, notes)
    stage = base
    found: list[EffectFound] = []
    y = train.displacement_um
    while len(found) < max_effects:
        X = _design(train, stage.model.terms)
        Xf = _fit_design(train, stage.model.terms)
        have = {(t.effect, t.sensor) for t in stage.model.terms}
        best = None

        def consider(term, cand):
            nonlocal best
            if (term.effect, term.sensor) in have:
                return
            if test is not None and (term.sensor and term.sensor not in test.temps_c
                                     or isinstance(term, SpeedTerm) and test.rpm is None):
                return       # could not be evaluated on the test run
            F = _design(train, [term])
            if not np.all(np.isfinite(F)) or np.all(np.ptp(F, axis=0) == 0):
                return
            e = heldout_errors(np.hstack([Xf, F]), y, n_blocks, gap, np.hstack([X, F]))
            r = rmse(e)
            if best is None or r < best[0]:
                best = (r, term, e, cand)

        for cand in cands:
            for term in cand.propose(train):
                consider(term, cand)
        if best is None:
            break
        # A parameter on a coarse grid leaves a misfit that a second, spurious
        # term would soak up: refine it where the candidate knows how.
        refine = getattr(best[3], "refine", None)
        if refine is not None:
            for term in refine(best[1]):
                consider(term, best[3])
        r, term, e, _ = best
        gain = 1.0 - r / rmse(e_cur)
        z = improvement_z(e_cur, e)
        if gain < min_gain or z < min_z:
            break
        stage, e_cur = _stage(train, [*stage.model.terms, term], test, n_blocks, gap, notes)
        found.append(EffectFound(term, stage, gain, z))
    if test is not None:
        res = residual_structure(test.time_s, test.displacement_um - stage.model.predict(test))
    else:
        res = residual_structure(train.time_s, e_cur)
    return Analysis(base, found, stage, res, notes)


# -- refit for the daemon -------------------------------------------------

@dataclass
class RefitResult:
    model: ThermalModel            # the model to use from now on
    candidate: ThermalModel        # what the loop fitted
    before_rmse_um: float          # current model on the held-out tail
    after_rmse_um: float           # new model on the same tail
    better: bool
    analysis: Analysis


def refit(data: ThermalData, current: ThermalModel | None = None, *, holdout_fraction: float = 0.2,
          min_gain: float = 0.05, extra_candidates: Sequence[Candidate] = ()) -> RefitResult:
    """Run the residual loop on all but the most recent ``holdout_fraction``
    of ``data`` and keep the new model only if it beats ``current`` (default
    eq. 14) on that recent tail by at least ``min_gain``."""
    if data.displacement_um is None:
        raise ValueError("refit needs measured displacements")
    if not 0 < holdout_fraction < 1:
        raise ValueError(f"holdout_fraction must be in (0, 1), got {holdout_fraction}")
    n = len(data)
    cut = int(round(n * (1 - holdout_fraction)))
    current = current or eq14_model()
    a = analyze(data.slice(0, cut), extra_candidates=extra_candidates)
    tail = slice(cut, n)
    y = data.displacement_um[tail]
    before = rmse(y - current.predict(data)[tail])
    after = rmse(y - a.model.predict(data)[tail])
    better = after < (1 - min_gain) * before
    return RefitResult(a.model if better else current, a.model, before, after, better, a)
