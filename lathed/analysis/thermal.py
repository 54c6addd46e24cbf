"""Thermal error model of the spindle and the loop that finds what it lacks.

The paper (eq. 14) fits the nose growth as a static linear function of four
temperature rises. This module selects the sensors (any number; a floating
stepwise search on held-out time, capped, each kept sensor lowering the
error consistently across the held-out blocks; a sensor that oscillates on
its own is filtered the same way at fit and at prediction), fits that
regression by least squares,
then runs a residual loop: each *candidate effect* (sensor lag, temperature
rate, speed, nonlinearity, hysteresis, drift, lag of speed, speed x
temperature, lag of T - ambient, or one a plugin supplies) proposes extra
terms; the set with one more that most lowers the error on held-out
contiguous time blocks, every parameter re-chosen jointly, is taken when the
fall is both large enough to matter and statistically significant; terms
made redundant leave; repeat. Structure left in the residual becomes a term
where it has a form one can fit (steps at speed levels, a periodic term at a
spectral line); what cannot be modelled is said. Plain least squares on all
sensors is fitted beside it, reported on the same rows, and is the model
when the selection does worse on held-out time.

The terms and candidate effects live in :mod:`lathed.analysis.thermal_terms`
(re-exported here). Pure numpy/scipy, no asyncio: the daemon's analyzer,
``lathectl analyze thermal`` and ``lathectl thermal refit`` all call the
same functions.

Units: temperatures °C, rises °C from the run's start, displacement µm,
time s, speed r/min.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
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
# Rows further apart than this: a run that starts at speed has warmed by its
# first row, so rises are taken from the room's start temperature (a cold
# machine is at the room's), fitted over the first ``_ROOM_REF_S``.
ROOM_REF_MIN_DT_S = 15.0
_ROOM_REF_S = 3600.0


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


def room_column(columns: Sequence[str]) -> str | None:
    """The column that reads the room (``t_room_c``, ``t_ambient_c``), if any."""
    return next((k for k in columns if "room" in k or "ambient" in k), None)


def _room_start(t_s: np.ndarray, x: np.ndarray) -> float:
    """The room's temperature at the first row, from a line through its first
    hour: one reading's error would go into every heated sensor's rise."""
    k = int(np.searchsorted(t_s, t_s[0] + _ROOM_REF_S, side="right"))
    if k < 3 or np.ptp(t_s[:k]) == 0:
        return float(x[0])
    return float(np.polyval(np.polyfit(t_s[:k] - t_s[0], x[:k], 1), 0.0))


def rises_from_room(t_s: np.ndarray, columns: Sequence[str]) -> str | None:
    """The room column rises are taken from for rows this far apart, or None
    (each sensor from its own start)."""
    room = room_column(columns)
    if room is None or len(t_s) < 2 or float(np.median(np.diff(t_s))) <= ROOM_REF_MIN_DT_S:
        return None
    return room


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
    rises_from: str | None = None                 # the room column every rise starts from (see rises_from_room)

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
            self.rises_from = rises_from_room(self.time_s, list(self.temps_c))
            if self.rises_from is not None:
                r0 = _room_start(self.time_s, self.temps_c[self.rises_from])
                self.reference_c = {k: r0 for k in self.temps_c}
            else:
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

    def rises_as(self, rises_from: str | None) -> ThermalData:
        """The same rows with rises taken as a model fitted with ``rises_from``
        takes them: every sensor from the room's reference, or each from its
        own start."""
        if rises_from == self.rises_from:
            return self
        if rises_from is None:
            ref = {k: _start_temp(self.time_s, v) for k, v in self.temps_c.items()}
        elif rises_from in self.temps_c:
            r0 = self.reference_c[rises_from] if self.rises_from is None else \
                _room_start(self.time_s, self.temps_c[rises_from])
            ref = {k: r0 for k in self.temps_c}
        else:
            raise ValueError(f"the thermal model takes its rises from {rises_from}, which the data lacks")
        return ThermalData(self.time_s, self.temps_c, self.displacement_um, self.rpm, ref, self.t0_s, rises_from)

    def smooth_rise(self, column: str) -> np.ndarray:
        """The rise with the sensor noise smoothed out, for fitting only."""
        cache = self.__dict__.setdefault("_smooth", {})
        if column not in cache:
            cache[column] = smooth_rows(self.time_s, self.rise(column))
        return cache[column]

    def fit_rise(self, column: str) -> np.ndarray:
        """The rise a linear term is fitted on (see ``_fit_design``): smoothed
        where what smoothing takes out is noise, else as read."""
        cache = self.__dict__.setdefault("_smooth", {})
        if ("fit", column) not in cache:
            sm, x = self.smooth_rise(column), self.rise(column)
            cache[("fit", column)] = sm if _noise_only(x - sm) else x
        return cache[("fit", column)]

    def select(self, columns: Sequence[str]) -> ThermalData:
        """The same rows with only ``columns`` of the temperatures."""
        out = ThermalData(self.time_s, {k: self.temps_c[k] for k in columns}, self.displacement_um, self.rpm,
                          {k: self.reference_c[k] for k in columns}, self.t0_s, self.rises_from)
        out.__dict__["_smooth"] = self.__dict__.setdefault("_smooth", {})
        out.__dict__["_cols"] = self.__dict__.setdefault("_cols", {})
        return out

    def slice(self, lo: int, hi: int) -> ThermalData:
        """Rows lo:hi, keeping this run's reference and start time."""
        return ThermalData(self.time_s[lo:hi], {k: v[lo:hi] for k, v in self.temps_c.items()},
                           None if self.displacement_um is None else self.displacement_um[lo:hi],
                           None if self.rpm is None else self.rpm[lo:hi],
                           dict(self.reference_c), self.t0_s, self.rises_from)


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
        self.rises_from = self.runs[0].rises_from

    def __len__(self) -> int:
        return len(self.time_s)

    @property
    def sensors(self) -> list[str]:
        return self.runs[0].sensors

    def rise(self, column: str) -> np.ndarray:
        return np.concatenate([r.rise(column) for r in self.runs])

    def smooth_rise(self, column: str) -> np.ndarray:
        return np.concatenate([r.smooth_rise(column) for r in self.runs])

    def fit_rise(self, column: str) -> np.ndarray:
        return np.concatenate([r.fit_rise(column) for r in self.runs])

    def select(self, columns: Sequence[str]) -> ThermalRuns:
        return ThermalRuns([r.select(columns) for r in self.runs])

    def rises_as(self, rises_from: str | None) -> ThermalRuns:
        return self if rises_from == self.rises_from else ThermalRuns([r.rises_as(rises_from) for r in self.runs])

    def slice(self, lo: int, hi: int) -> ThermalRuns:
        out, start = [], 0
        for r in self.runs:
            a, b = max(lo - start, 0), min(hi - start, len(r))
            if a < b:
                out.append(r.slice(a, b))
            start += len(r)
        return ThermalRuns(out)


from lathed.analysis.thermal_terms import (  # noqa: F401  (re-exported: plugins import them from here)
    AmbientLagTerm, Candidate, DriftCandidate, DriftTerm, HysteresisCandidate, HysteresisTerm, LagCandidate,
    LagTerm, LinearTerm, NonlinearCandidate, NonlinearTerm, PeriodicTerm, RateCandidate, RateTerm,
    SpeedCandidate, SpeedLagTerm, SpeedStepCandidate, SpeedStepTerm, SpeedTempTerm, SpeedTerm, Term,
    builtin_candidates, lag_filter, play_operator)

# -- least squares --------------------------------------------------------

_RIDGE = 1e-6          # relative to n on standardised columns: only bites on exact collinearity
COLLINEAR_R = 0.999


def _cols(data: ThermalData, term: Term) -> np.ndarray:
    """A term's columns on one run, kept: the loops below ask for the same
    terms again and again as others come and go."""
    cache = data.__dict__.setdefault("_cols", {})
    key = repr(term)
    hit = cache.get(key)
    if hit is None or hit[0] is not data.rpm:      # rpm may be set or replaced after the run was built
        hit = cache[key] = (data.rpm, np.asarray(term.features(data), dtype=float).reshape(len(data), -1))
    return hit[1]


def _design(data: ThermalData | ThermalRuns, terms: Sequence[Term]) -> np.ndarray:
    if isinstance(data, ThermalRuns):      # terms with memory start afresh in each run
        return np.vstack([_design(r, terms) for r in data.runs])
    cols = [_cols(data, t) for t in terms]
    return np.hstack(cols) if cols else np.empty((len(data), 0))


def _noise_only(x: np.ndarray) -> bool:
    """Is ``x`` (what smoothing takes out of a sensor) reading noise? Noise
    spreads over the whole spectrum; a sensor's own oscillation (coolant past
    it, a fan cycling) puts a line in it that holds a large share."""
    if len(x) < 64:
        return True
    p = np.abs(np.fft.rfft(x - x.mean()))[1:] ** 2
    if p.sum() <= 0:
        return True
    band = np.convolve(p, np.ones(3), "same")
    return float(band.max() / p.sum()) < 0.1


def _fit_design(data: ThermalData, terms: Sequence[Term]) -> np.ndarray:
    """The design the coefficients are fitted on: as ``_design``, but the
    unfiltered sensors' own (linear) columns with their reading noise
    smoothed out, where what is smoothed out is noise.

    The heated sensors move nearly in lock-step (rear bearing and motor warm
    with the same speed, r > 0.99), so what tells their weights apart is a
    few hundredths of a °C, the size of a DS18B20's noise: fitted on the raw
    readings the weights are biased along that direction (errors in
    variables), which costs nothing on the training run and a slow ramp of
    error on a run with another speed schedule. Predictions still use the
    raw readings: right for noise, wrong for a sensor that oscillates on its
    own, whose oscillation the fit would never see and the prediction would
    carry straight into the growth. Such a sensor is fitted as it is
    predicted (raw, or through its notch or lag)."""
    if isinstance(data, ThermalRuns):
        return np.vstack([_fit_design(r, terms) for r in data.runs])
    cols = [data.fit_rise(t.sensor)[:, None] if isinstance(t, LinearTerm) and not t.filtered
            else _cols(data, t) for t in terms]
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
    # the room column every rise is taken from (rows far apart, see rises_from_room), else None
    rises_from: str | None = None

    @property
    def names(self) -> list[str]:
        return [nm for t in self.terms for nm in t.names]

    @property
    def sensors(self) -> list[str]:
        # a term may read more than its own sensor (a lag of T - ambient reads the room too)
        return sorted({s for t in self.terms for s in getattr(t, "sensors", (t.sensor,)) if s}
                      | ({self.rises_from} if self.rises_from else set()))

    def predict(self, data: ThermalData) -> np.ndarray:
        missing = [s for s in self.sensors if s not in data.temps_c]
        if missing:
            raise ValueError(f"the thermal model needs temperature column(s) {', '.join(missing)}")
        return _design(data.rises_as(self.rises_from), self.terms) @ self.coef + self.intercept_um

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
                "notes": list(self.notes), "terms": terms,
                **({"rises_from": self.rises_from} if self.rises_from else {})}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], candidates: Sequence[Candidate] = ()) -> ThermalModel:
        """The inverse of to_dict; ValueError naming the key of a malformed one (a hand edit, a
        damaged file: AttributeError, a bare KeyError 'sensor' and nan coefficients got through)."""
        fmt = d.get("format", 1)
        if fmt != 1 or isinstance(fmt, bool):
            raise ValueError(f"format: {fmt!r} is not a thermal model format this lathed reads (1)")
        if "intercept_um" not in d:
            raise ValueError("intercept_um: missing key")
        makers: dict[str, Any] = {c.name: c for c in [*builtin_candidates(), *candidates]}
        terms: list[Term] = []
        coef: list[float] = []
        tds = d.get("terms", [])
        if not isinstance(tds, list):
            raise ValueError(f"terms: expected a list of tables, got {tds!r}")
        for i, td in enumerate(tds):
            if not isinstance(td, dict):
                raise ValueError(f"term {i + 1}: expected a table, got {td!r}")
            eff = td.get("effect")
            p = td.get("params", {})
            if not isinstance(p, dict):
                raise ValueError(f"term {i + 1} ({eff}) params: expected a table, got {p!r}")
            for k, v in p.items():
                if isinstance(v, float) and not math.isfinite(v):
                    raise ValueError(f"term {i + 1} ({eff}) params.{k}: expected a finite number, got {v!r}")
            if "sensor" in td and not isinstance(td["sensor"], str):
                raise ValueError(f"term {i + 1} ({eff}) sensor: expected a string, got {td['sensor']!r}")
            if eff != "linear" and eff not in makers:
                raise ValueError(f"thermal model term {i + 1} has effect {eff!r}, which no "
                                 f"candidate provides (known: linear, {', '.join(makers)})")
            try:
                if eff == "linear":
                    if "sensor" not in td:
                        raise KeyError("sensor")
                    term: Term = LinearTerm(td["sensor"], float(p.get("smooth_s", 0.0)),
                                            notch_s=float(p.get("notch_s", 0.0)))
                else:
                    term = makers[eff].make_term(td.get("sensor"), p)
            except KeyError as e:
                raise ValueError(f"term {i + 1} ({eff}): missing key {e}") from None
            except (TypeError, ValueError) as e:
                raise ValueError(f"term {i + 1} ({eff}): {e}") from None
            tc = td.get("coef", [])
            if not isinstance(tc, list) or len(tc) != len(term.names):
                raise ValueError(f"thermal model term {i + 1} ({eff}) needs {len(term.names)} "
                                 f"coefficient(s), has {len(tc) if isinstance(tc, list) else repr(tc)}")
            terms.append(term)
            coef += [_finite(c, f"term {i + 1} ({eff}) coef[{j}]") for j, c in enumerate(tc)]
        notes, rises_from = d.get("notes", []), d.get("rises_from") or None
        if not isinstance(notes, list):
            raise ValueError(f"notes: expected a list, got {notes!r}")
        if rises_from is not None and not isinstance(rises_from, str):
            raise ValueError(f"rises_from: expected a sensor name, got {rises_from!r}")
        return cls(terms, np.array(coef), _finite(d["intercept_um"], "intercept_um"), list(notes),
                   str(d.get("source", "fit")), rises_from)


def _finite(v: Any, key: str) -> float:
    from lathed.config import finite   # an int past a float's range too
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not finite(v):
        raise ValueError(f"{key}: expected a finite number, got {v!r}")
    return float(v)


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
    from the first reading when none is given; for a model fitted with
    ``rises_from`` (rows far apart), every rise from the room's reference, as
    in the fit. The drift clock runs from
    ``t0_s``, or from the first update. Terms with memory (lag, rate,
    hysteresis) keep their state here, so call ``update`` in time order; they
    start settled at the first reading.
    """

    def __init__(self, model: ThermalModel, reference_c: Mapping[str, float] | None = None,
                 t0_s: float | None = None):
        self.model = model
        self.reference_c = None if reference_c is None else {sensor_column(k): float(v)
                                                             for k, v in reference_c.items()}
        if self.reference_c is not None:
            self._room_reference()
        self._streams = [t.stream() for t in model.terms]
        self._t0 = t0_s
        self.prediction_um: float | None = None

    def _room_reference(self) -> None:
        """A model fitted with ``rises_from`` takes every rise from the room's reference, as the fit did."""
        room = self.model.rises_from
        if room is not None and room in self.reference_c:
            self.reference_c = {s: self.reference_c[room] for s in self.model.sensors}

    def update(self, temps_c: Mapping[str, float], rpm: float | None = None,
               t_s: float | None = None) -> float:
        temps = {sensor_column(k): float(v) for k, v in temps_c.items()}
        missing = [s for s in self.model.sensors if s not in temps]
        if missing:
            raise ValueError(f"no reading from {', '.join(missing)}: the thermal model needs it")
        if self.reference_c is None:
            self.reference_c = {s: temps[s] for s in self.model.sensors}
            self._room_reference()
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
            if f is None:      # drift, periodic: on the run's clock, from the cold start
                vals.extend(term.run_clock(t - self._t0))
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
    sensor: str | None = None       # an input sensor oscillating at that period
    steps_h: list[float] = field(default_factory=list)   # sudden steps in the residual (h into the run)


@dataclass
class Comparison:
    """One model's error on the rows every model of the report is judged on."""
    label: str
    rmse_um: float | None
    note: str = ""

    def to_json(self) -> dict[str, Any]:
        return {"model": self.label, "rmse_um": None if self.rmse_um is None else round(self.rmse_um, 4),
                **({"note": self.note} if self.note else {})}


@dataclass
class SensorKept:
    """A sensor the selection kept, and what it carries."""
    sensor: str
    smooth_s: float
    heldout_gain_um: float   # held-out error without it less with it
    span_um: float           # its weight times the span of its rise: growth it accounts for
    notch_s: float = 0.0

    def to_json(self) -> dict[str, Any]:
        return {"sensor": self.sensor, "smooth_s": self.smooth_s, "notch_s": self.notch_s,
                "heldout_gain_um": round(self.heldout_gain_um, 4), "span_um": round(self.span_um, 3)}


@dataclass
class Analysis:
    baseline: Stage
    effects: list[EffectFound]
    final: Stage
    residual: ResidualReport
    notes: list[str]
    least_squares: Stage | None = None
    comparison: list[Comparison] = field(default_factory=list)
    sensors: list[SensorKept] = field(default_factory=list)
    judged_on: str = ""

    @property
    def model(self) -> ThermalModel:
        return self.final.model

    def to_json(self) -> dict[str, Any]:
        return {"baseline": self.baseline.to_json(), "effects": [e.to_json() for e in self.effects],
                "final": self.final.to_json(),
                "least_squares": None if self.least_squares is None else self.least_squares.to_json(),
                "comparison": {"rows": self.judged_on, "models": [c.to_json() for c in self.comparison]},
                "sensors": [k.to_json() for k in self.sensors],
                "residual": {"structured": self.residual.structured, "note": self.residual.note,
                             **({"period_s": round(self.residual.period_s, 1)} if self.residual.period_s else {}),
                             **({"matches_sensor": self.residual.sensor} if self.residual.sensor else {})},
                "notes": self.notes}


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
        period, _ = _line(data.time_s, data.rise(sensor), min_share=0.0)
        cache[("filters", sensor)] = ([LinearTerm(sensor)] if period is None or period > _FILTER_MAX_PERIOD_S
                                      else [LinearTerm(sensor), LinearTerm(sensor, notch_s=round(period, 1))])
    return list(cache[("filters", sensor)])


class _HeldoutCache:
    """``heldout_errors`` for the selection loops, which score thousands of
    designs that differ in a column or two: the cross-products of every pair
    of columns over the whole run and over each held-out stretch are kept,
    so a design's held-out errors cost a few small solves. Same algebra as
    ``heldout_errors`` (the ridge on standardised columns is a ridge of
    ``_RIDGE * rows * var`` on the raw ones)."""

    def __init__(self, data: ThermalData | ThermalRuns, n_blocks: int, gap: int):
        self.data = data
        y = data.displacement_um
        n = len(y)
        self.blocks = blocks(n, n_blocks)
        self.segs = [(max(lo - gap, 0), min(hi + gap, n)) for lo, hi in self.blocks]
        self.row_block = np.repeat(np.arange(len(self.blocks)), [hi - lo for lo, hi in self.blocks])
        self.fit_rows = np.array([max(n - (c - a), 1) for a, c in self.segs], dtype=float)
        self.cols: dict[str, np.ndarray] = {"1": np.ones(n), "y": y}
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
        X = _design(self.data, [term])        # per run for several runs: memory starts afresh in each
        keys = [f"{k}#{i}" for i in range(X.shape[1])]
        if keys[0] not in self.cols:
            F = X if F is None else F
            for i, key in enumerate(keys):
                self.cols[key] = np.ascontiguousarray(F[:, i])
        return keys

    def _pair(self, a: str, b: str) -> np.ndarray:
        key = (a, b) if a <= b else (b, a)
        out = self.sums.get(key)
        if out is None:
            cs = np.concatenate([[0.0], np.cumsum(self.cols[a] * self.cols[b])])
            out = self.sums[key] = np.array([cs[-1], *(cs[c] - cs[s] for s, c in self.segs)])
        return out

    def errors(self, terms: Sequence[Term]) -> np.ndarray:
        fk = [k for t in terms for k in self._keys(t, True)] + ["1"]
        pk = [k for t in terms for k in self._keys(t, False)]
        m = len(fk)
        S = np.empty((m, m, len(self.segs) + 1))
        for i in range(m):
            for j in range(i, m):
                S[i, j] = S[j, i] = self._pair(fk[i], fk[j])
        Sy = np.array([self._pair(k, "y") for k in fk])
        y = self.cols["y"]
        n = len(y)
        var = S[np.arange(m), np.arange(m), 0] / n - (S[:, m - 1, 0] / n) ** 2
        var = np.where(var > 0, var, 1.0)
        var[-1] = 0.0
        # every block's fit in one batched solve, every row predicted by its block's
        G = np.moveaxis(S[:, :, :1] - S[:, :, 1:], 2, 0)
        G[:, np.arange(m), np.arange(m)] += _RIDGE * self.fit_rows[:, None] * var
        coef = np.linalg.solve(G, (Sy[:, :1] - Sy[:, 1:]).T[:, :, None])[:, :, 0][self.row_block]
        P = np.column_stack([self.cols[k] for k in pk]) if pk else np.empty((n, 0))
        return y - np.einsum("ij,ij->i", P, coef[:, :-1]) - coef[:, -1]


def _heldout(data: ThermalData | ThermalRuns, terms: Sequence[Term], n_blocks: int, gap: int) -> np.ndarray:
    cache = data.__dict__.setdefault("_heldout", {})
    hc = cache.get((n_blocks, gap))
    if hc is None or hc.cols["y"] is not data.displacement_um or hc.rpm is not data.rpm:
        hc = cache[(n_blocks, gap)] = _HeldoutCache(data, n_blocks, gap)
    return hc.errors(terms)


def _usable_sensors(data: ThermalData, n_blocks: int, gap: int) -> tuple[list[str], list[str]]:
    """The temperature columns that can be fitted: not a sensor that never
    changed, nor one that moves in lock-step with another and adds nothing on
    held-out blocks (two sensors reading the same heat; keeping both would
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
    return keep, notes


def block_t(e_old: np.ndarray, e_new: np.ndarray, n_blocks: int) -> float:
    """Paired t of the fall in held-out error across the held-out blocks (the
    log of each block's mean squared error before over after; NaN with one
    block). A block's held-out errors all come from one fit, so they are
    correlated over the whole block: the block, not the row, is the unit of
    evidence. The Diebold-Mariano z with its Newey-West window of sqrt(rows)
    counts a 100-row block as several independent pieces, and called sensors
    significant that fitted one run's course only."""
    lr = np.array([np.log(np.mean(e_old[a:b] ** 2) / max(np.mean(e_new[a:b] ** 2), 1e-300))
                   for a, b in blocks(len(e_old), n_blocks)])
    if len(lr) < 2:
        return math.nan
    sd = float(lr.std(ddof=1))
    return math.copysign(math.inf, lr.mean()) if sd == 0 else float(lr.mean() / (sd / math.sqrt(len(lr))))


# One-sided level of the test a sensor passes to enter (see select_sensors).
SENSOR_ALPHA = 0.05


def select_sensors(data: ThermalData | ThermalRuns, n_blocks: int = 5, gap: int = 10, max_sensors: int = 8,
                   min_gain: float = 0.005, alpha: float = SENSOR_ALPHA, *,
                   start: Sequence[LinearTerm] | None = None,
                   fixed: Sequence[Term] = (), prune: bool = True
                   ) -> tuple[list[LinearTerm], list[str], list[SensorKept]]:
    """Choice of sensors (each with the filter of ``_filters`` that suits
    it) on held-out time blocks, at most ``max_sensors``. Sixteen sensors on
    one spindle mostly read the same few heats: all of them in one
    regression fit their noise and oscillations, not the growth.

    The search floats (sequential floating forward selection): for each
    number of sensors it keeps the set with the least held-out error found
    so far; after a sensor enters, swaps of one sensor (or its filter) for
    another and removals are taken while they beat the best set of their
    size. A plain forward pass is led astray by decoys: a sensor on a part
    that lags a heated one (a housing further out) stands in for two true
    sensors at once and, once in, keeps them out. The search goes to the
    cap, and the smallest set that no larger one beats significantly is
    kept: beating means a held-out error lower by ``min_gain`` (relative)
    and consistently so across the held-out blocks (``block_t`` at one-sided
    level ``alpha``, Student's t with blocks - 1 degrees of freedom). Among
    some thirty sensor-filter candidates the best one always lowers the
    held-out error a little, by chance or by a slow wander that fits within
    one run and not on the next; the old test (a Diebold-Mariano z of 1 on
    rows) took such sensors in.

    With no more usable sensors than ``max_sensors`` and no ``start``, all
    enter (each with its best filter): on a few sensors a missing effect
    hides a sensor's share, and the loop decides once effects are in.
    ``start`` are sensors already chosen, ``fixed`` effect terms fitted
    beside them: the residual loop calls this again as effects enter, and
    last with ``prune`` to let go of those that add nothing."""
    keep, notes = _usable_sensors(data, n_blocks, gap)
    y = data.displacement_um
    if y is None:
        return [LinearTerm(s) for s in keep], notes, []
    fixed = list(fixed)
    few = len(keep) <= max_sensors
    if start is None and few:
        start = [LinearTerm(s) for s in keep]
        for i, s in enumerate(keep):
            grid = _filters(data, s)
            if len(grid) > 1:
                start[i] = min(grid, key=lambda t: rmse(
                    _heldout(data, [*start[:i], t, *start[i + 1:], *fixed], n_blocks, gap)))
    cands = [] if few else [t for s in keep for t in _filters(data, s)]
    scored: dict[tuple[str, ...], tuple[float, np.ndarray]] = {}

    def score(ts: Sequence[LinearTerm]) -> tuple[float, np.ndarray]:
        key = tuple(sorted(repr(t) for t in ts))
        if key not in scored:
            e = (_heldout(data, [*ts, *fixed], n_blocks, gap) if ts or fixed
                 else heldout_errors(np.empty((len(y), 0)), y, n_blocks, gap))
            scored[key] = (rmse(e), e)
        return scored[key]

    from scipy.special import stdtrit      # Student's t quantile (scipy.stats costs a second to import)
    t_crit = float(stdtrit(n_blocks - 1, 1 - alpha)) if n_blocks > 1 else math.inf

    def significant(small: Sequence[LinearTerm], big: Sequence[LinearTerm]) -> bool:
        (r0, e0), (r1, e1) = score(small), score(big)
        return 1 - r1 / r0 >= min_gain and block_t(e0, e1, n_blocks) >= t_crit

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
    e_cur = score(chosen)[1]
    for t in list(chosen if prune and few else ()):     # few sensors: only those that add next to nothing go
        rest = [o for o in chosen if o is not t]
        if not rest:
            break
        e = _heldout(data, [*rest, *fixed], n_blocks, gap)
        if 1 - rmse(e_cur) / rmse(e) < min_gain / 2:
            chosen, e_cur = rest, e
    left = [s for s in keep if all(t.sensor != s for t in chosen)]
    if left:
        notes.append(f"sensor selection kept {len(chosen)} of {len(keep)}: "
                     f"{', '.join(left)} added nothing on held-out time")
    coef, _ = fit_coefficients(_fit_design(data, [*chosen, *fixed]), y)
    kept = []
    for i, t in enumerate(chosen):
        rest = [o for o in chosen if o is not t]
        without = rmse(_heldout(data, [*rest, *fixed], n_blocks, gap)) if rest or fixed else rmse(y - y.mean())
        kept.append(SensorKept(t.sensor, t.smooth_s, without - rmse(e_cur),
                               float(abs(coef[i]) * np.ptp(_design(data, [t]))), t.notch_s))
    return chosen, notes, kept


def baseline_terms(data: ThermalData, n_blocks: int = 5, gap: int = 10) -> tuple[list[Term], list[str]]:
    """The linear terms the residual loop starts from: the selected sensors."""
    terms, notes, _ = select_sensors(data, n_blocks, gap)
    return list(terms), notes


def _stage(train: ThermalData, terms: list[Term], test: ThermalData | None,
           n_blocks: int, gap: int, notes: list[str], raw: bool = False,
           source: str = "fit") -> tuple[Stage, np.ndarray]:
    X = _design(train, terms)
    Xf = X if raw else _fit_design(train, terms)
    y = train.displacement_um
    coef, icpt = fit_coefficients(Xf, y)
    model = ThermalModel(list(terms), coef, icpt, list(notes), source=source, rises_from=train.rises_from)
    e_cv = heldout_errors(Xf, y, n_blocks, gap, X)
    fit_rmse = rmse(y - (X @ coef + icpt))
    test_rmse = rmse(test.displacement_um - model.predict(test)) if test is not None else rmse(e_cv)
    return Stage(model, fit_rmse, rmse(e_cv), test_rmse), e_cv


def least_squares_stage(train: ThermalData, test: ThermalData | None = None, n_blocks: int = 5,
                        gap: int = 10) -> tuple[Stage, np.ndarray]:
    """The plain baseline every report carries: least squares on every
    sensor that changed, as read, no selection, no effect."""
    sensors = [s for s in train.sensors if np.ptp(train.rise(s)) > 0
               and (test is None or s in test.temps_c)]
    if not sensors:
        raise ValueError("no temperature column changed during the run: nothing to fit the growth to")
    return _stage(train, [LinearTerm(s) for s in sensors], test, n_blocks, gap,
                  [f"plain least squares on {len(sensors)} sensor(s)"], raw=True, source="least_squares")


def _line(t_s: np.ndarray, x: np.ndarray, min_share: float = 0.2) -> tuple[float | None, float]:
    """The period of a spectral line in ``x`` (sampled at ``t_s``) and the
    share of the variance it carries; None when there is none. A line stands
    above the bins either side of it; a slow trend's spectrum only falls
    from the slowest bin, so it is never taken for a period (it used to be
    called one of a third of the run)."""
    x = np.asarray(x, float)
    n = len(x)
    if n < 32:
        return None, 0.0
    dt = float(np.median(np.diff(t_s)))
    tt = np.arange(n) * dt
    # A quadratic off: a warm-up's curve is trend, not a cycle.
    det = x - np.polyval(np.polyfit(tt / tt[-1], x, 2), tt / tt[-1])
    p = np.abs(np.fft.rfft(det * np.hanning(n))) ** 2
    f = np.fft.rfftfreq(n, dt)
    if len(p) < 12 or p[1:].sum() <= 0:
        return None, 0.0
    def stands_out(k: int) -> bool:
        sides = np.r_[p[max(k - 5, 1):k - 2], p[k + 3:k + 6]]
        return bool(len(sides) and p[k] > 10 * sides.max() and p[k] > 20 * np.median(p[1:]))

    if min_share > 0:
        k = 4 + int(np.argmax(p[4:]))           # four cycles in the run at least
    else:   # any line, however small beside the rest: the strongest that stands out
        peaks = [k for k in range(4, len(p) - 1) if p[k] >= p[k - 1] and p[k] >= p[k + 1] and stands_out(k)]
        k = max(peaks, key=lambda j: p[j]) if peaks else 4
    band = p[k - 1:k + 2].sum()
    share = float(band / p[1:].sum())
    if share > min_share and stands_out(k):
        # the peak between bins: a parabola through the log power
        a, b, c = np.log(p[k - 1:k + 2] + 1e-300)
        off = 0.5 * (a - c) / (a - 2 * b + c) if (a - 2 * b + c) != 0 else 0.0
        return 1.0 / ((k + float(np.clip(off, -0.5, 0.5))) * (f[1] - f[0])), share
    return None, share


def residual_structure(t_s: np.ndarray, e: np.ndarray, data: ThermalData | None = None) -> ResidualReport:
    """Is there more in the residual than noise? Compares its rms with the
    sample-to-sample scatter (which smooth structure does not inflate) and
    looks for a spectral line; with ``data``, says which input sensor
    oscillates at the same period, if one does."""
    e = np.asarray(e, float) - np.mean(e)
    n = len(e)
    if n < 16:
        return ResidualReport(False, f"only {n} rows: too few to judge the residual", rmse(e), 0.0)
    d = np.diff(e)
    noise = float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2))
    total = rmse(e)
    lag1 = float((e[1:] @ e[:-1]) / (e @ e)) if total > 0 else 0.0
    period, share = _line(t_s, e)
    sensor = None
    if period is not None and data is not None:
        span = float(t_s[-1] - t_s[0]) or 1.0
        for s in data.sensors:
            ps, _ = _line(data.time_s, data.rise(s))
            if ps is not None and abs(1 / ps - 1 / period) * span <= 1.5:   # within 1.5 bins
                sensor = s
                break
    steps = _steps(t_s, e, noise)
    ratio = total / noise if noise > 0 else (1.0 if total < 1e-12 else math.inf)
    structured = ratio > 1.3 or period is not None or bool(steps)
    if not structured:
        note = (f"residual looks like measurement noise: rms {total:.2f} µm vs {noise:.2f} µm "
                f"sample-to-sample, lag-1 autocorrelation {lag1:.2f}")
    else:
        note = (f"structure left that no candidate explains: residual rms {total:.2f} µm is "
                f"{ratio:.1f}x the sample-to-sample noise ({noise:.2f} µm), lag-1 autocorrelation {lag1:.2f}")
        if period is not None:
            note += f"; a periodicity of {period / 60:.1f} min carries {100 * share:.0f}% of its variance"
            if sensor is not None:
                note += f", the period at which {sensor} oscillates"
        if steps:
            h = [round((t_s[k] - t_s[0]) / 3600.0, 2) for k, _ in steps]
            size = float(np.median([abs(d) for _, d in steps]))
            note += (f"; {len(steps)} sudden step(s) of ~{size:.1f} µm with no temperature change, at "
                     f"{', '.join(f'{v:g}' for v in h[:6])}{' ...' if len(h) > 6 else ''} h")
            if data is not None and data.rpm is None:
                note += " (speed or program changes? with a spindle_rpm column they are fitted as speed steps)"
    rep = ResidualReport(structured, note, noise, lag1, period, sensor)
    rep.steps_h = [float((t_s[k] - t_s[0]) / 3600.0) for k, _ in steps]
    return rep


def _steps(t_s: np.ndarray, e: np.ndarray, noise: float) -> list[tuple[int, float]]:
    """Sudden steps in a residual: where the mean of the next few rows differs
    from that of the previous few by much more than the noise, and more than
    a smooth curve moves over so few rows."""
    n = len(e)
    w = max(5, n // 200)
    if n < 4 * w or noise <= 0:
        return []
    cs = np.concatenate([[0.0], np.cumsum(e)])
    k = np.arange(w, n - w + 1)
    d = (cs[k + w] - cs[k]) / w - (cs[k] - cs[k - w]) / w
    # a smooth curve moves about as much from one window to the next as over
    # the two windows before: a step stands out from both neighbours
    big = np.abs(d) > max(6.0 * noise * math.sqrt(2.0 / w), 3.0 * noise)
    out: list[tuple[int, float]] = []
    for i in np.flatnonzero(big):
        lo, hi = max(i - w, 0), min(i + w + 1, len(d))
        if abs(d[i]) < np.abs(d[lo:hi]).max():
            continue
        side = np.r_[np.abs(d[max(i - 3 * w, 0):max(i - 2 * w, 0)]), np.abs(d[i + 2 * w:i + 3 * w])]
        if len(side) and abs(d[i]) > 3 * side.max():
            out.append((int(k[i]), float(d[i])))
    return out


# Time constants a lag term may have: the run holds at least this many of them.
_SETTLE_TAUS = 4.0
# Kinds of effect (effect and sensor) whose best proposal is re-tuned jointly with those in.
_JOINT_KINDS = 6


def _duplicate(term: Term, others: Sequence[Term]) -> bool:
    """Would ``term`` repeat one of ``others``? The same effect on the same
    sensor does, unless both are lags a factor 2 or more apart (two time
    constants on one sensor: a housing and the shaft behind it)."""
    for o in others:
        if o.effect != term.effect or o.sensor != term.sensor:
            continue
        a, b = getattr(o, "tau_s", None), getattr(term, "tau_s", None)
        if a and b and max(a, b) / min(a, b) >= 2.0 and o.params.get("form") == term.params.get("form"):
            continue
        return True
    return False


def describe(term: Term) -> str:
    where = f" of {term.sensor}" if term.sensor else ""
    p = ", ".join(f"{k} {v}" for k, v in term.params.items())
    return f"{term.effect}{where}" + (f" ({p})" if p else "")


def _judged(model: ThermalModel, rows: ThermalData) -> float | None:
    try:
        return rmse(rows.displacement_um - model.predict(rows))
    except ValueError:
        return None


def analyze(train: ThermalData, test: ThermalData | None = None, *,
            candidates: Sequence[Candidate] | None = None, extra_candidates: Sequence[Candidate] = (),
            max_effects: int = 4, n_blocks: int = 5, gap_rows: int = 10,
            min_gain: float = 0.05, min_z: float = 2.0, max_sensors: int = 8,
            current: ThermalModel | None = None) -> Analysis:
    """Select the sensors, fit the linear baseline on ``train``, then add
    candidate effects while one lowers the held-out error by at least
    ``min_gain`` (relative) with a Diebold-Mariano z of at least ``min_z``.
    Each time one enters, the parameters of those already in are re-chosen
    with it, and any it made redundant leaves: a lag and a speed effect
    together are found as the pair, not as one term that half-explains both.
    A spectral line left in the residual becomes a periodic term, if it
    passes the same test. Effects are chosen on held-out blocks of ``train``
    only; ``test`` (another run) is only reported on, beside the paper's
    eq. 14, plain least squares on the same sensors, and ``current``."""
    if train.displacement_um is None:
        raise ValueError("training data has no displacement_um to fit")
    if len(train) < 10 * n_blocks:
        raise ValueError(f"{len(train)} rows are too few for {n_blocks} held-out blocks "
                         f"(need at least {10 * n_blocks})")
    cands = list(builtin_candidates() if candidates is None else candidates) + list(extra_candidates)
    makers = {c.name: c for c in cands}
    gap = min(gap_rows, len(train) // (4 * n_blocks))
    sensor_terms, notes, kept = select_sensors(train, n_blocks, gap, max_sensors, prune=False)
    if train.rises_from is not None:
        notes.insert(0, f"rows are over {ROOM_REF_MIN_DT_S:g} s apart: every rise is taken from the room's "
                        f"temperature at the start ({train.rises_from}, a line through its first hour), not "
                        f"from each sensor's first reading (a run that starts at speed has warmed by then)")
    base, e_cur = _stage(train, list(sensor_terms), test, n_blocks, gap, notes)
    # Candidates see every usable sensor, kept or not: a sensor whose linear
    # share adds nothing may still carry an effect (a lag of the front bearing).
    view = train.select(_usable_sensors(train, n_blocks, gap)[0])
    y = train.displacement_um
    effects: list[Term] = []
    dropped: set[tuple[str, Any]] = set()
    gains: dict[str, tuple[float, float]] = {}

    # The longest time constant the run can tell from a trend: a lagged part
    # settles (to 98 %) within four of them, and one that never settles within
    # the run is a smooth ramp there, fitted to whatever drifts slowly in this
    # run (the room's day, the references) and extrapolated to the next run
    # with another schedule: test errors of 7-15 µm from 2-µm baselines.
    max_tau_s = float(np.max(train.time_s - train.t0_s)) / _SETTLE_TAUS

    def usable(term) -> bool:
        if getattr(term, "tau_s", 0.0) > max_tau_s:
            return False
        try:
            F = _design(train, [term])
            if test is not None:
                _cols(test, term)
        except (ValueError, KeyError):
            return False       # could not be evaluated (on the test run: a sensor or the speed missing)
        return bool(np.all(np.isfinite(F)) and np.any(np.ptp(F, axis=0) > 0))

    def score(terms: Sequence[Term]) -> tuple[float, np.ndarray]:
        e = _heldout(train, [*sensor_terms, *terms], n_blocks, gap)
        return rmse(e), e

    def alternatives(t: Term) -> list[Term]:
        """The same effect on the same sensor at its other parameters."""
        cand = makers.get(t.effect)
        if cand is None:
            return []
        out = [a for a in cand.propose(view) if a.effect == t.effect and a.sensor == t.sensor]
        refine = getattr(cand, "refine", None)
        return out + (list(refine(t)) if refine is not None else [])

    def tune(terms: list[Term], order: Sequence[int]) -> tuple[float, list[Term], np.ndarray]:
        """Re-choose each listed term's parameter with all the others fitted beside it."""
        r, e = score(terms)
        for i in order:
            for alt in alternatives(terms[i]):
                others = terms[:i] + terms[i + 1:]
                if repr(alt) == repr(terms[i]) or _duplicate(alt, others) or not usable(alt):
                    continue
                trial = [*terms[:i], alt, *terms[i + 1:]]
                r2, e2 = score(trial)
                if r2 < r:
                    r, e, terms = r2, e2, trial
        return r, terms, e

    def step(proposals) -> tuple[float, list[Term], np.ndarray] | None:
        """The best set of effects with one more: each proposal scored beside
        those in; then for the best few kinds, every parameter re-chosen
        jointly (a lag that half-explained a speed effect takes its own time
        constant again once the speed term is beside it)."""
        def ranked(others: list[Term]) -> list[Term]:
            """Each kind's best proposal beside ``others``, best kinds first."""
            per_kind: dict[str, tuple[float, Term]] = {}
            for term in proposals:
                if _duplicate(term, others) or (term.effect, term.sensor) in dropped or not usable(term):
                    continue
                r, _ = score([*others, term])
                kind = f"{term.effect}/{term.sensor}"
                if kind not in per_kind or r < per_kind[kind][0]:
                    per_kind[kind] = (r, term)
            return [t for _, t in sorted(per_kind.values(), key=lambda v: v[0])]

        top = ranked(effects)[:_JOINT_KINDS]
        if not top:
            return None
        best = None
        for term in top:
            n_in = len(effects)
            # the newcomer's parameter refined first, then everyone's with it
            found = tune([*effects, term], [n_in, *range(n_in), n_in] if effects else [n_in])
            if best is None or found[0] < best[0]:
                best = found
        # An effect taken in alone may have stood in for a pair (a short lag of
        # the rear bearing for a speed effect and a lag of the front bearing):
        # each term in turn is swapped for the best kinds ranked beside the
        # others, not beside itself, where its stand-in ranks the true ones low.
        r, terms, e = best
        for _ in range(2 * len(terms)):
            swapped = False
            for i in range(len(terms)):
                others = terms[:i] + terms[i + 1:]
                for term in ranked(others)[:_JOINT_KINDS // 2]:
                    if f"{term.effect}/{term.sensor}" == f"{terms[i].effect}/{terms[i].sensor}":
                        continue
                    found = tune([*terms[:i], term, *terms[i + 1:]], [i, *range(len(terms)), i])
                    if found[0] < r:
                        (r, terms, e), swapped = found, True
            if not swapped:
                break
        # ... or the newcomer does its part alone: it enters as the other leaves.
        for i in range(len(terms) - 2, -1, -1):
            trial = terms[:i] + terms[i + 1:]
            r2, e2 = score(trial)
            if r2 < r:
                r, terms, e = r2, trial, e2
        return r, terms, e

    def admit(found) -> bool:
        nonlocal e_cur
        r, terms, e = found
        gain, z = 1.0 - r / rmse(e_cur), improvement_z(e_cur, e)
        if gain < min_gain or z < min_z:
            return False
        effects[:] = terms
        gains[repr(terms[-1])] = (gain, z)
        e_cur = e
        return True

    def settle() -> None:
        """After an effect entered: sensors whose share the missing effect hid
        come in, and effects the newcomer made redundant go."""
        nonlocal sensor_terms, kept, e_cur
        newcomer = effects[-1]
        sensors2, snotes, kept2 = select_sensors(train, n_blocks, gap, max_sensors, start=sensor_terms,
                                                 fixed=effects, prune=False)
        if [repr(t) for t in sensors2] != [repr(t) for t in sensor_terms]:
            sensor_terms, kept = sensors2, kept2
            e_cur = _heldout(train, [*sensor_terms, *effects], n_blocks, gap)
            notes[:] = [n for n in notes if not n.startswith("sensor selection kept")] + \
                [n for n in snotes if n.startswith("sensor selection kept")]
        for t in list(effects[:-1]):
            rest = [o for o in effects if o is not t]
            e = _heldout(train, [*sensor_terms, *rest], n_blocks, gap)
            if 1.0 - rmse(e_cur) / rmse(e) < min_gain / 2:
                effects[:] = rest
                e_cur = e
                dropped.add((t.effect, t.sensor))
                notes.append(f"{describe(t)} dropped: once {describe(newcomer)} entered it added under "
                             f"{100 * min_gain / 2:g} % on held-out time")

    while len(effects) < max_effects:
        found = step([t for c in cands for t in c.propose(view)])
        if found is None or not admit(found):
            break
        settle()
    # Structure no library term explains, turned into a term where it has a
    # form one can fit: steps at the logged speed changes, a spectral line.
    for _ in range(3):
        if len(effects) >= max_effects + 2:
            break
        res = residual_structure(train.time_s, e_cur, train)
        if not res.structured:
            break
        if not any(t.effect == "speed_step" for t in effects):
            found = step(SpeedStepCandidate().structure(view))
            if found is not None and admit(found):
                settle()
                continue
        if res.period_s is None:
            break
        f0, df = 1.0 / res.period_s, 1.0 / float(np.ptp(train.time_s))
        periods = [PeriodicTerm(1.0 / f) for f in f0 + df * np.linspace(-0.5, 0.5, 11) if f > 0]
        found = step(periods)
        if found is None or not admit(found):
            notes.append(f"a periodicity of {res.period_s / 60:.1f} min is left in the residual, but a "
                         f"periodic term at it does not lower the held-out error enough to keep")
            break
        settle()
    res = residual_structure(train.time_s, e_cur, train)
    if res.structured:
        notes.append("not modelled: " + res.note)
    # Last, let go of sensors that add nothing with the effects in.
    sensor_terms, snotes, kept = select_sensors(train, n_blocks, gap, max_sensors, start=sensor_terms,
                                                fixed=effects, prune=True)
    notes[:] = [n for n in notes if not n.startswith("sensor selection kept")] + \
        [n for n in snotes if n.startswith("sensor selection kept")]
    # The effects in the order of what they carry (held-out error without each):
    # chosen jointly, the order they entered in says little.
    if len(effects) > 1:
        without = {repr(t): rmse(_heldout(train, [*sensor_terms, *(o for o in effects if o is not t)],
                                          n_blocks, gap)) for t in effects}
        effects.sort(key=lambda t: -without[repr(t)])
    found_list: list[EffectFound] = []
    stage = base
    for k, t in enumerate(effects):
        stage, _ = _stage(train, [*sensor_terms, *effects[:k + 1]], test, n_blocks, gap, notes)
        g, z = gains.get(repr(t), (0.0, 0.0))
        found_list.append(EffectFound(t, stage, g, z))
    ls, _ = least_squares_stage(train, test, n_blocks, gap)
    if stage.heldout_rmse_um > ls.heldout_rmse_um:
        notes.append(f"the selected model predicts held-out time worse than plain least squares on every "
                     f"sensor ({stage.heldout_rmse_um:.2f} vs {ls.heldout_rmse_um:.2f} µm): least squares "
                     f"is the model")
        stage, found_list = ls, []
    if test is not None:
        res = residual_structure(test.time_s, test.displacement_um - stage.model.predict(test), test)
        rows, judged_on = test, f"the test run ({len(test)} rows)"
    else:
        res = residual_structure(train.time_s, _heldout(train, stage.model.terms, n_blocks, gap)
                                 if stage is not ls else y - ls.model.predict(train), train)
        rows, judged_on = None, f"held-out time blocks of the training run ({len(train)} rows, {n_blocks} blocks)"
    comparison = _comparison(rows if rows is not None else train, rows is None, base, ls, stage, current)
    return Analysis(base, found_list, stage, res, notes, ls, comparison, kept, judged_on)


def _comparison(rows: ThermalData, cv: bool, base: Stage, ls: Stage, final: Stage,
                current: ThermalModel | None) -> list[Comparison]:
    """Every model on the same rows. Fitted models carry their held-out
    errors (``cv``: blocks of the training run) or their test error; fixed
    models (the paper's, the current one) are predicted on all rows."""
    eq14 = replace(eq14_model(), intercept_um=0.0)
    missing = [s for s in eq14.sensors if s not in rows.temps_c]
    out = [Comparison("paper eq. 14 (intercept dropped: growth from the cold start)",
                      None if missing else _judged(eq14, rows),
                      f"needs {', '.join(missing)}" if missing else "")]
    out.append(Comparison(f"least squares on {len(ls.model.sensors)} sensor(s)", ls.test_rmse_um))
    if current is not None:
        miss = [s for s in current.sensors if s not in rows.temps_c]
        out.append(Comparison("current model", None if miss else _judged(current, rows),
                              f"needs {', '.join(miss)}" if miss else ""))
    else:
        out.append(Comparison(f"current: linear regression on {len(base.model.sensors)} selected sensor(s)",
                              base.test_rmse_um))
    out.append(Comparison(f"new: {len(final.model.names)} term(s)", final.test_rmse_um))
    return out


def split_run(data: ThermalData, fraction: float) -> tuple[ThermalData, ThermalData]:
    """The first ``fraction`` of a run for the fit, the rest held out: split
    by time, as ``refit`` does; the held-out part keeps the run's cold-start
    reference and clock."""
    if not 0 < fraction < 1:
        raise ValueError(f"the split must be in (0, 1), got {fraction}")
    cut = int(round(len(data) * fraction))
    if cut < 1 or cut >= len(data):
        raise ValueError(f"a split at {fraction} of {len(data)} rows leaves one side empty")
    return data.slice(0, cut), data.slice(cut, len(data))


# A heated sensor starting further above the training run's cold start than
# this share of its rise in that run: the test run did not start cold.
WARM_START_SHARE = 0.25
WARM_START_MIN_C = 0.25     # 4 DS18B20 steps: below it a start is cold whatever the run's rise


def reference_test(train: ThermalData, test: ThermalData) -> tuple[ThermalData, str | None]:
    """Make a test run's rises comparable with the fit's. Rises are taken from
    a run's first rows, which is right for a run from a cold start. A test
    run on the training run's clock (its first time after the training's
    last) continues that run: its rises and drift hours are re-referenced to
    the training run's cold start. Any other test run that starts warm is
    refused: from its own first rows every rise would be short by the
    warm-up, an error of the whole growth. Returns the test run and a line
    saying what was done (None when it starts cold)."""
    if test.time_s[0] > train.time_s[-1]:
        t2 = ThermalData(test.time_s, test.temps_c, test.displacement_um, test.rpm,
                         {k: train.reference_c[k] for k in test.temps_c if k in train.reference_c}
                         | {k: v for k, v in test.reference_c.items() if k not in train.reference_c},
                         train.t0_s, train.rises_from)
        return t2, (f"the test run continues the training run's clock (starts at {test.time_s[0]:g} s, "
                    f"the training run ends at {train.time_s[-1]:g} s): its rises are taken from the "
                    f"training run's cold start, not from its own first rows")
    # Against the room when there is a room sensor: another day starts from another room temperature.
    amb = next((s for s in train.sensors if ("room" in s or "ambient" in s) and s in test.temps_c), None)
    warm = []
    for s in test.sensors:
        if s not in train.temps_c or s == amb or "room" in s or "ambient" in s:
            continue
        # each sensor's own start (with rises from the room, the references say nothing of it)
        def start(d, k):
            return _start_temp(d.time_s, d.temps_c[k])
        above = start(test, s) - start(train, s)
        if amb is not None:
            above -= start(test, amb) - start(train, amb)
        span = float(np.ptp(train.rise(s)))
        if above > max(WARM_START_SHARE * span, WARM_START_MIN_C):
            warm.append(f"{s} starts at {start(test, s):.2f} °C, {above:.2f} °C "
                        f"{'further above the room than at' if amb else 'above'} the training run's cold start "
                        f"(it rose {span:.2f} °C in that run)")
    if warm:
        raise ValueError(f"the test run does not start cold: {'; '.join(warm)}; rises from its first rows "
                         f"would miss the warm-up. Give a run from a cold start, one continuing the training "
                         f"run's time_s, or use --split on one run")
    return test, None


# -- refit for the daemon -------------------------------------------------

@dataclass
class RefitResult:
    model: ThermalModel            # the model to use from now on
    candidate: ThermalModel        # what the loop fitted
    before_rmse_um: float          # current model on the held-out tail
    after_rmse_um: float           # new model on the same tail
    better: bool
    analysis: Analysis
    least_squares_rmse_um: float | None = None   # plain least squares, fitted on the same rows, on the tail


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
    cand, ls = a.model, None
    if a.least_squares is not None:
        # never ship worse than plain least squares on the same held-out rows
        ls = rmse(y - a.least_squares.model.predict(data)[tail])
        if ls < after:
            a.notes.append(f"on the held-out tail plain least squares ({ls:.2f} µm) beat the selected model "
                           f"({after:.2f} µm): least squares is the candidate")
            cand, after = a.least_squares.model, ls
    better = after < (1 - min_gain) * before
    return RefitResult(cand if better else current, cand, before, after, better, a, ls)
