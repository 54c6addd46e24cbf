"""A thermal run's rows: time, temperatures, speed, growth, and the rises the model reads.

Units: temperatures °C, rises °C from the run's cold start, displacement µm, time s, speed r/min.
See docs/thermal.md.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

_REF_ROWS = 10        # rows in the line fitted for the starting temperature when rows are sparse
_REF_WINDOW_S = 300.0  # ... or the span of the quadratic fitted when they are dense (see start_temp)
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

def start_temp(t_s: np.ndarray, x: np.ndarray) -> float:
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


def noise_only(x: np.ndarray) -> bool:
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
                self.reference_c = {k: start_temp(self.time_s, v) for k, v in self.temps_c.items()}
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
            ref = {k: start_temp(self.time_s, v) for k, v in self.temps_c.items()}
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
            cache[("fit", column)] = sm if noise_only(x - sm) else x
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


