"""Candidate effects for the thermal model and the terms they add.

A *term* is a group of regression columns computed from a run (batch, for
fitting) or sample by sample (stream, for live prediction), with the same
recursions both ways. A *candidate* proposes the terms to try for one effect
the static regression lacks; plugins add candidates through the
``lathed_thermal_candidates`` hook.

Lag vs rate: a sensor that lags its body by a first-order lag τ reads
s = body − τ·ds/dt, so the body is the sensor plus a rate term; with the
sensor's own column in the model, a lag term of time constant τ spans the
same columns as a rate term smoothed over τ. The two are told apart by time
scale: below 5 min it is reported as ``rate``, above as ``lag``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Iterable, Mapping, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:
    from lathed.analysis.thermal import ThermalData


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
    out = np.empty(len(x))
    p = float(x[0]) if start is None else start
    for k, v in enumerate(x.tolist()):
        if v - p > width:
            p = v - width
        elif p - v > width:
            p = v + width
        out[k] = p
    return out


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
    sensor: str
    effect: str = "linear"
    params: dict = field(default_factory=dict)

    @property
    def names(self) -> tuple[str, ...]:
        return (self.sensor,)

    def features(self, data: ThermalData) -> np.ndarray:
        return data.rise(self.sensor)[:, None]

    def stream(self):
        return lambda t, rises, rpm: (rises[self.sensor],)


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

    def stream(self):
        return None   # the predictor feeds its own clock (see ThermalPredictor)


# -- candidates -----------------------------------------------------------

@runtime_checkable
class Candidate(Protocol):
    """An effect the model may lack. ``propose`` yields the terms to try
    (typically one per sensor and parameter value); ``make_term`` rebuilds a
    term from a saved model's ``sensor`` and ``params``. Optionally
    ``refine(term) -> list[Term]`` gives a finer grid around the best one.
    Supplied by plugins through the ``lathed_thermal_candidates`` hook."""
    name: str

    def propose(self, data: ThermalData) -> Iterable[Term]: ...
    def make_term(self, sensor: str | None, params: Mapping[str, Any]) -> Term: ...


def _heated(data: ThermalData) -> list[str]:
    """Sensors on parts the spindle heats (not the room)."""
    return [s for s in data.sensors if "room" not in s]


class LagCandidate:
    name = "lag"
    # Starts above the rate term's smoothing: a short lag is a rate (see RateTerm).
    taus_s = tuple(float(v) for v in np.geomspace(300.0, 4 * 3600.0, 16))

    def propose(self, data):
        return [LagTerm(s, tau) for s in data.sensors for tau in self.taus_s]

    def refine(self, term: LagTerm) -> list[LagTerm]:
        """A finer grid between the coarse neighbours of the best time constant."""
        step = self.taus_s[1] / self.taus_s[0]
        return [LagTerm(term.sensor, float(t)) for t in np.geomspace(term.tau_s / step, term.tau_s * step, 9)]

    def make_term(self, sensor, params):
        return LagTerm(sensor, float(params["tau_s"]))


class RateCandidate:
    name = "rate"
    smooth_s = (60.0, 120.0, 240.0)

    def propose(self, data):
        return [RateTerm(s, w) for s in _heated(data) for w in self.smooth_s]

    def make_term(self, sensor, params):
        return RateTerm(sensor, float(params["smooth_s"]))


class SpeedCandidate:
    name = "speed"

    def propose(self, data):
        if data.rpm is None or np.ptp(data.rpm) == 0:
            return []
        return [SpeedTerm(f) for f in ("n", "n2", "n+n2")]

    def make_term(self, sensor, params):
        return SpeedTerm(str(params.get("form", "n2")))


class NonlinearCandidate:
    name = "nonlinear"

    def propose(self, data):
        return [NonlinearTerm(s) for s in _heated(data)]

    def make_term(self, sensor, params):
        return NonlinearTerm(sensor)


class HysteresisCandidate:
    name = "hysteresis"
    widths_c = tuple(float(v) for v in np.geomspace(0.25, 4.0, 9))

    def propose(self, data):
        out = []
        for s in _heated(data):
            span = np.ptp(data.rise(s))
            out += [HysteresisTerm(s, w) for w in self.widths_c if w < span / 2]
        return out

    def refine(self, term: HysteresisTerm) -> list[HysteresisTerm]:
        step = self.widths_c[1] / self.widths_c[0]
        return [HysteresisTerm(term.sensor, float(w))
                for w in np.geomspace(term.width_c / step, term.width_c * step, 7)]

    def make_term(self, sensor, params):
        return HysteresisTerm(sensor, float(params["width_c"]))


class DriftCandidate:
    name = "drift"

    def propose(self, data):
        return [DriftTerm(round(float(np.max(data.time_s - data.t0_s)) / 3600.0, 2))]

    def make_term(self, sensor, params):
        return DriftTerm(float(params["max_h"]) if "max_h" in params else None)


def builtin_candidates() -> list[Candidate]:
    return [LagCandidate(), RateCandidate(), SpeedCandidate(), NonlinearCandidate(),
            HysteresisCandidate(), DriftCandidate()]
