"""The terms of the thermal model: groups of regression columns computed from a run (batch, for
fitting) or sample by sample (stream, for live prediction), with the same recursions both ways.

Lag vs rate: a sensor that lags its body by a first-order lag τ reads s = body − τ·ds/dt, so with
the sensor's own column in the model a lag of τ spans the same columns as a rate smoothed over τ;
below 5 min it is reported as ``rate``, above as ``lag``. See docs/thermal.md.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:
    from lathed.analysis.thermal.data import ThermalData


# -- filters shared by batch features and streaming prediction -------------

def lag_filter(t_s: np.ndarray, x: np.ndarray, tau_s: float) -> np.ndarray:
    """First-order lag of ``x`` with time constant ``tau_s``, exact for a
    piecewise-constant input, starting settled at ``x[0]``."""
    dt = np.diff(t_s)
    if len(x) < 2:
        return x.astype(float).copy()
    if np.ptp(dt) <= 1e-9 * max(dt[0], 1.0):
        from scipy.signal import lfilter   # here: heavy to import, and only fits need it
        a = 1.0 - math.exp(-dt[0] / tau_s)
        y, _ = lfilter([a], [1.0, a - 1.0], x, zi=[(1.0 - a) * x[0]])
        return y
    # Uneven steps (rows rejected on load): the recursion itself.
    alpha = 1.0 - np.exp(-dt / tau_s)
    y = np.empty(len(x))
    acc = float(x[0])
    y[0] = acc
    xs = x.tolist()
    for k, a in enumerate(alpha.tolist(), start=1):
        acc += a * (xs[k] - acc)
        y[k] = acc
    return y


def play_operator(x: np.ndarray, width: float, start: float | None = None) -> np.ndarray:
    """Backlash (play) operator: follows ``x`` only once it moves more than
    ``width`` away; the simplest model of heating/cooling hysteresis."""
    p = float(x[0]) if start is None else start
    out = []                    # a list, not numpy item by item: this loop runs on every candidate width
    for v in x.tolist():
        if v - p > width:
            p = v - width
        elif p - v > width:
            p = v + width
        out.append(p)
    return np.array(out, dtype=float)


def period_mean(t_s: np.ndarray, x: np.ndarray, period_s: float) -> np.ndarray:
    """Mean of ``x`` over the last ``period_s`` (the rows joined by straight
    lines; before the first row, settled at it): a notch at that period and
    its harmonics. It takes a sensor's own oscillation (coolant past it)
    out and delays the slow heat by only half a period, where a lag long
    enough to damp the oscillation delays it by a whole one and leaves a
    sixth of it. Exact for any spacing of rows, so the live prediction at
    one reading a second computes it the same way."""
    x = np.asarray(x, float)
    t = np.asarray(t_s, float)
    if len(x) < 2:
        return x.copy()
    dt = np.diff(t)
    c = np.concatenate([[0.0], np.cumsum(0.5 * (x[1:] + x[:-1]) * dt)])     # integral from t[0]
    q = t - period_s
    k = np.clip(np.searchsorted(t, q, side="right") - 1, 0, len(t) - 2)
    u = q - t[k]
    slope = np.divide(x[k + 1] - x[k], dt[k], out=np.zeros(len(k)), where=dt[k] > 0)
    cq = np.where(q < t[0], (q - t[0]) * x[0], c[k] + x[k] * u + 0.5 * slope * u * u)
    return (c - cq) / period_s


class _NotchState:
    """``period_mean`` one reading at a time."""
    def __init__(self, period_s: float):
        self.p = period_s
        self.t: list[float] = []
        self.x: list[float] = []
        self.c: list[float] = []        # integral from the first reading to each kept one
        self.t0 = self.x0 = 0.0

    def update(self, t_s: float, x: float) -> float:
        if not self.t:
            self.t0, self.x0 = t_s, x
            self.t, self.x, self.c = [t_s], [x], [0.0]
            return x
        if t_s > self.t[-1]:
            self.c.append(self.c[-1] + 0.5 * (x + self.x[-1]) * (t_s - self.t[-1]))
            self.t.append(t_s)
            self.x.append(x)
        # keep the last reading at or before the window's start, and what follows it
        q = self.t[-1] - self.p
        while len(self.t) > 2 and self.t[1] <= q:
            del self.t[0], self.x[0], self.c[0]
        if q < self.t0:
            cq = (q - self.t0) * self.x0
        else:
            u, d = q - self.t[0], self.t[1] - self.t[0]
            slope = (self.x[1] - self.x[0]) / d if d > 0 else 0.0
            cq = self.c[0] + self.x[0] * u + 0.5 * slope * u * u
        return (self.c[-1] - cq) / self.p


class _LagState:
    def __init__(self, tau_s: float):
        self.tau_s, self.y, self.t = tau_s, None, None

    def update(self, t_s: float, x: float) -> float:
        if self.y is None:
            self.y = x
        elif t_s > self.t:
            self.y += (1.0 - math.exp(-(t_s - self.t) / self.tau_s)) * (x - self.y)
        self.t = t_s
        return self.y


# -- terms ----------------------------------------------------------------

@runtime_checkable
class Term(Protocol):
    """A group of regression columns computed from the data.

    ``features`` is the batch form (rows x len(names)); ``stream`` returns a
    callable ``f(t_s, rises, rpm) -> sequence of len(names)`` giving the same
    values one sample at a time, for live prediction."""
    effect: str
    sensor: str | None
    params: dict[str, float]

    @property
    def names(self) -> tuple[str, ...]: ...
    def features(self, data: ThermalData) -> np.ndarray: ...
    def stream(self): ...


@dataclass(frozen=True)
class LinearTerm:
    """A sensor's rise; with ``smooth_s`` > 0 seen through a first-order lag of
    that time constant, the same at fit and at prediction: a sensor that
    oscillates on its own (coolant past it, a fan cycling) would otherwise
    carry its oscillation straight into the predicted growth."""
    sensor: str
    smooth_s: float = 0.0
    effect: str = "linear"
    notch_s: float = 0.0      # the sensor's own oscillation period, taken out by ``period_mean``

    @property
    def filtered(self) -> bool:
        return bool(self.smooth_s or self.notch_s)

    @property
    def params(self) -> dict[str, float]:
        return ({"smooth_s": round(self.smooth_s, 1)} if self.smooth_s else {}) | \
            ({"notch_s": round(self.notch_s, 1)} if self.notch_s else {})

    @property
    def names(self) -> tuple[str, ...]:
        how = [f"smooth {self.smooth_s:.0f} s"] * bool(self.smooth_s) + [f"notch {self.notch_s:.0f} s"] * bool(
            self.notch_s)
        return (self.sensor + (f" ({', '.join(how)})" if how else ""),)

    def features(self, data: ThermalData) -> np.ndarray:
        x = data.rise(self.sensor)
        if self.notch_s:
            x = period_mean(data.time_s, x, self.notch_s)
        return (lag_filter(data.time_s, x, self.smooth_s) if self.smooth_s else x)[:, None]

    def stream(self):
        if not self.filtered:
            return lambda t, rises, rpm: (rises[self.sensor],)
        nt = _NotchState(self.notch_s) if self.notch_s else None
        st = _LagState(self.smooth_s) if self.smooth_s else None

        def f(t, rises, rpm):
            x = rises[self.sensor]
            x = nt.update(t, x) if nt is not None else x
            return (st.update(t, x) if st is not None else x,)
        return f


@dataclass(frozen=True)
class LagTerm:
    """A body that follows the sensor's rise through a first-order lag."""
    sensor: str
    tau_s: float
    effect: str = "lag"

    @property
    def params(self) -> dict[str, float]:
        return {"tau_s": round(self.tau_s, 1)}

    @property
    def names(self) -> tuple[str, ...]:
        return (f"lag({self.sensor}, tau={self.tau_s:.0f} s)",)

    def features(self, data: ThermalData) -> np.ndarray:
        return lag_filter(data.time_s, data.rise(self.sensor), self.tau_s)[:, None]

    def stream(self):
        st = _LagState(self.tau_s)
        return lambda t, rises, rpm: (st.update(t, rises[self.sensor]),)


@dataclass(frozen=True)
class RateTerm:
    """dT/dt of a sensor in °C/min, smoothed by a short lag (a 1/16 °C step
    every 6 s would otherwise be all noise). A sensor that lags its body by a
    short first-order lag is exactly this term (body = s + τ·ds/dt)."""
    sensor: str
    smooth_s: float
    effect: str = "rate"

    @property
    def params(self) -> dict[str, float]:
        return {"smooth_s": round(self.smooth_s, 1)}

    @property
    def names(self) -> tuple[str, ...]:
        return (f"rate({self.sensor}, smooth={self.smooth_s:.0f} s)",)

    def features(self, data: ThermalData) -> np.ndarray:
        x = data.rise(self.sensor)
        return ((x - lag_filter(data.time_s, x, self.smooth_s)) * (60.0 / self.smooth_s))[:, None]

    def stream(self):
        st = _LagState(self.smooth_s)

        def f(t, rises, rpm):
            x = rises[self.sensor]
            return ((x - st.update(t, x)) * 60.0 / self.smooth_s,)
        return f


@dataclass(frozen=True)
class SpeedTerm:
    """Spindle speed in krpm and/or its square (centrifugal growth)."""
    form: str = "n2"           # "n", "n2" or "n+n2"
    effect: str = "speed"
    sensor: None = None

    @property
    def params(self) -> dict[str, Any]:
        return {"form": self.form}

    @property
    def names(self) -> tuple[str, ...]:
        return {"n": ("speed_krpm",), "n2": ("speed_krpm^2",),
                "n+n2": ("speed_krpm", "speed_krpm^2")}[self.form]

    def _cols(self, n: np.ndarray) -> list[np.ndarray]:
        return {"n": [n], "n2": [n * n], "n+n2": [n, n * n]}[self.form]

    def features(self, data: ThermalData) -> np.ndarray:
        if data.rpm is None:
            raise ValueError("speed term needs a spindle_rpm column")
        return np.column_stack(self._cols(data.rpm / 1000.0))

    def stream(self):
        def f(t, rises, rpm):
            if rpm is None:
                raise ValueError("the thermal model has a speed term: pass the spindle speed")
            n = np.asarray(rpm / 1000.0)
            return tuple(float(c) for c in self._cols(n))
        return f


@dataclass(frozen=True)
class NonlinearTerm:
    """Square of a sensor's rise."""
    sensor: str
    effect: str = "nonlinear"
    params: dict = field(default_factory=lambda: {"power": 2})

    @property
    def names(self) -> tuple[str, ...]:
        return (f"{self.sensor}^2",)

    def features(self, data: ThermalData) -> np.ndarray:
        return (data.rise(self.sensor) ** 2)[:, None]

    def stream(self):
        return lambda t, rises, rpm: (rises[self.sensor] ** 2,)


@dataclass(frozen=True)
class HysteresisTerm:
    """Play operator of a sensor's rise minus the rise: ±width, its sign set
    by whether the part last heated or cooled."""
    sensor: str
    width_c: float
    effect: str = "hysteresis"

    @property
    def params(self) -> dict[str, float]:
        return {"width_c": round(self.width_c, 3)}

    @property
    def names(self) -> tuple[str, ...]:
        return (f"hysteresis({self.sensor}, width={self.width_c:.2f} C)",)

    def features(self, data: ThermalData) -> np.ndarray:
        x = data.rise(self.sensor)
        return (play_operator(x, self.width_c) - x)[:, None]

    def stream(self):
        state = {"p": None}

        def f(t, rises, rpm):
            v = rises[self.sensor]
            p = v if state["p"] is None else min(max(state["p"], v - self.width_c), v + self.width_c)
            state["p"] = p
            return (p - v,)
        return f


@dataclass(frozen=True)
class DriftTerm:
    """Hours since the run started: a creep no sensor sees. Held at
    ``max_h``, the span it was fitted on: a creep seen for 8 h says nothing
    of hour 30 (a daemon restarted on a touch-off of the day before would
    otherwise extrapolate a straight line into the offset)."""
    max_h: float | None = None
    effect: str = "drift"
    sensor: None = None

    @property
    def params(self) -> dict[str, float]:
        return {} if self.max_h is None else {"max_h": round(self.max_h, 2)}

    @property
    def names(self) -> tuple[str, ...]:
        return ("hours",)

    def hours(self, h):
        return h if self.max_h is None else np.minimum(h, self.max_h)

    def features(self, data: ThermalData) -> np.ndarray:
        return self.hours((data.time_s - data.t0_s) / 3600.0)[:, None]

    def run_clock(self, t_run_s: float) -> tuple[float]:
        return (float(self.hours(t_run_s / 3600.0)),)

    def stream(self):
        return None   # the predictor feeds its own clock (see ThermalPredictor)


@dataclass(frozen=True)
class SpeedLagTerm:
    """Spindle speed (krpm, or its square) through a first-order lag: heat
    that speed puts into a part no sensor is on (the spindle nose, the
    shaft's inner race) reaches the growth with that part's own delay."""
    tau_s: float
    form: str = "n"            # "n" or "n2"
    effect: str = "speed_lag"
    sensor: None = None

    @property
    def params(self) -> dict[str, Any]:
        return {"tau_s": round(self.tau_s, 1), "form": self.form}

    @property
    def names(self) -> tuple[str, ...]:
        return (f"lag(speed_krpm{'^2' if self.form == 'n2' else ''}, tau={self.tau_s:.0f} s)",)

    def _u(self, rpm):
        n = np.asarray(rpm, dtype=float) / 1000.0
        return n * n if self.form == "n2" else n

    def features(self, data: ThermalData) -> np.ndarray:
        if data.rpm is None:
            raise ValueError("speed lag term needs a spindle_rpm column")
        return lag_filter(data.time_s, self._u(data.rpm), self.tau_s)[:, None]

    def stream(self):
        st = _LagState(self.tau_s)

        def f(t, rises, rpm):
            if rpm is None:
                raise ValueError("the thermal model has a speed lag term: pass the spindle speed")
            return (st.update(t, float(self._u(rpm))),)
        return f


@dataclass(frozen=True)
class SpeedTempTerm:
    """Speed (krpm) times a sensor's rise: a bearing's preload, and so its
    growth per °C, changes with speed."""
    sensor: str
    effect: str = "speed_x_temp"
    params: dict = field(default_factory=dict)

    @property
    def names(self) -> tuple[str, ...]:
        return (f"speed_krpm*{self.sensor}",)

    def features(self, data: ThermalData) -> np.ndarray:
        if data.rpm is None:
            raise ValueError("speed x temperature term needs a spindle_rpm column")
        return (data.rpm / 1000.0 * data.rise(self.sensor))[:, None]

    def stream(self):
        def f(t, rises, rpm):
            if rpm is None:
                raise ValueError("the thermal model has a speed x temperature term: pass the spindle speed")
            return (rpm / 1000.0 * rises[self.sensor],)
        return f


@dataclass(frozen=True)
class AmbientLagTerm:
    """A body that follows a sensor's rise above the room's through a
    first-order lag: a part cooled by the room lags the difference, not the
    sensor alone."""
    sensor: str
    ambient: str
    tau_s: float
    effect: str = "lag_ambient"

    @property
    def params(self) -> dict[str, Any]:
        return {"tau_s": round(self.tau_s, 1), "ambient": self.ambient}

    @property
    def sensors(self) -> tuple[str, str]:
        return (self.sensor, self.ambient)

    @property
    def names(self) -> tuple[str, ...]:
        return (f"lag({self.sensor} - {self.ambient}, tau={self.tau_s:.0f} s)",)

    def features(self, data: ThermalData) -> np.ndarray:
        return lag_filter(data.time_s, data.rise(self.sensor) - data.rise(self.ambient), self.tau_s)[:, None]

    def stream(self):
        st = _LagState(self.tau_s)
        return lambda t, rises, rpm: (st.update(t, rises[self.sensor] - rises[self.ambient]),)


@dataclass(frozen=True)
class PeriodicTerm:
    """A sine and cosine at ``period_s`` on the run's clock (time since its
    start): a cycle in the growth no sensor explains (a coolant pump, a
    door). Its phase is fitted as the sin/cos pair's weights."""
    period_s: float
    effect: str = "periodic"
    sensor: None = None

    @property
    def params(self) -> dict[str, float]:
        return {"period_s": round(self.period_s, 1)}

    @property
    def names(self) -> tuple[str, ...]:
        return (f"sin({self.period_s:.0f} s)", f"cos({self.period_s:.0f} s)")

    def at(self, t_run_s):
        w = 2 * math.pi * np.asarray(t_run_s, dtype=float) / self.period_s
        return np.column_stack([np.sin(w), np.cos(w)])

    def features(self, data: ThermalData) -> np.ndarray:
        return self.at(data.time_s - data.t0_s)

    def run_clock(self, t_run_s: float) -> tuple[float, float]:
        return tuple(float(v) for v in self.at([t_run_s])[0])

    def stream(self):
        return None   # on the run's clock: the predictor feeds it (see ThermalPredictor)


@dataclass(frozen=True)
class SpeedStepTerm:
    """One offset per speed level seen in the fit (the lowest is the zero):
    growth that steps when the speed changes and holds while it holds, by an
    amount no smooth function of speed gives (a preload switch, a resonance).
    A speed not among ``levels`` takes the nearest level's offset. With
    ``above_rpm``, one offset above that speed instead (one switch): a column
    per level leaves levels run in only one held-out block, which the
    held-out test cannot judge, so it refused the steps a switch makes."""
    levels: tuple[float, ...] = ()
    effect: str = "speed_step"
    sensor: None = None
    above_rpm: float | None = None

    @property
    def params(self) -> dict[str, Any]:
        if self.above_rpm is not None:
            return {"above_rpm": float(self.above_rpm)}
        return {"levels_rpm": [float(v) for v in self.levels]}

    @property
    def names(self) -> tuple[str, ...]:
        if self.above_rpm is not None:
            return (f"step(speed>={self.above_rpm:g} r/min)",)
        return tuple(f"step(speed={v:g} r/min)" for v in self.levels[1:])

    def at(self, rpm) -> np.ndarray:
        rpm = np.asarray(rpm, dtype=float)
        if self.above_rpm is not None:
            return (rpm >= self.above_rpm).astype(float)[:, None]
        lv = np.asarray(self.levels, dtype=float)
        k = np.argmin(np.abs(rpm[:, None] - lv[None, :]), axis=1)
        return (k[:, None] == np.arange(1, len(lv))[None, :]).astype(float)

    def features(self, data: ThermalData) -> np.ndarray:
        if data.rpm is None:
            raise ValueError("speed step term needs a spindle_rpm column")
        return self.at(data.rpm)

    def stream(self):
        def f(t, rises, rpm):
            if rpm is None:
                raise ValueError("the thermal model has a speed step term: pass the spindle speed")
            return tuple(float(v) for v in self.at([rpm])[0])
        return f
