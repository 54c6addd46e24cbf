"""Candidate effects for the thermal model: each proposes the terms to try for one effect the
static regression lacks. See docs/thermal.md."""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Iterable, Mapping

import numpy as np

from lathed.analysis.thermal.terms import (AmbientLagTerm, DriftTerm, HysteresisTerm, LagTerm, NonlinearTerm,
                                           PeriodicTerm, RateTerm, SpeedLagTerm, SpeedStepTerm, SpeedTempTerm,
                                           SpeedTerm, Term)

if TYPE_CHECKING:
    from lathed.analysis.thermal.data import ThermalData


class Candidate:
    """An effect the model may lack. ``propose`` yields the terms to try (typically one per
    sensor and parameter value); ``make_term`` rebuilds a term from a saved model's ``sensor``
    and ``params``; ``refine`` gives a finer grid around the best one (none by default).
    Plugins supply subclasses through the ``lathed_thermal_candidates`` hook."""
    name: str = ""

    def propose(self, data: ThermalData) -> Iterable[Term]:
        raise NotImplementedError

    def make_term(self, sensor: str | None, params: Mapping[str, Any]) -> Term:
        raise NotImplementedError

    def refine(self, term: Term) -> list[Term]:
        return []

    def for_rows(self, term: Term, data: ThermalData) -> Term:
        """The term as fitted on ``data``, when chosen on fewer rows (a drift held at the span
        it was fitted on takes the longer span)."""
        return term


_TAUS_S = tuple(float(v) for v in np.geomspace(300.0, 4 * 3600.0, 16))


def _heated(data: ThermalData) -> list[str]:
    """Sensors on parts the spindle heats (not the room)."""
    return [s for s in data.sensors if "room" not in s]


class LagCandidate(Candidate):
    name = "lag"
    # Starts above the rate term's smoothing: a short lag is a rate (see RateTerm).
    taus_s = _TAUS_S

    def propose(self, data):
        return [LagTerm(s, tau) for s in data.sensors for tau in self.taus_s]

    def refine(self, term: LagTerm) -> list[LagTerm]:
        """A finer grid between the coarse neighbours of the best time constant."""
        return _refine_tau(term.tau_s, lambda t: LagTerm(term.sensor, t))

    def make_term(self, sensor, params):
        return LagTerm(sensor, float(params["tau_s"]))


class RateCandidate(Candidate):
    name = "rate"
    smooth_s = (60.0, 120.0, 240.0)

    def propose(self, data):
        return [RateTerm(s, w) for s in _heated(data) for w in self.smooth_s]

    def refine(self, term: RateTerm) -> list[RateTerm]:
        """Between the grid's neighbours, up to the shortest lag (above it, a lag)."""
        return [RateTerm(term.sensor, float(w)) for w in np.geomspace(term.smooth_s / 2, term.smooth_s * 2, 9)
                if w < _TAUS_S[0]]

    def make_term(self, sensor, params):
        return RateTerm(sensor, float(params["smooth_s"]))


class SpeedCandidate(Candidate):
    name = "speed"

    def propose(self, data):
        if data.rpm is None or np.ptp(data.rpm) == 0:
            return []
        return [SpeedTerm(f) for f in ("n", "n2", "n+n2")]

    def make_term(self, sensor, params):
        return SpeedTerm(str(params.get("form", "n2")))


class NonlinearCandidate(Candidate):
    name = "nonlinear"

    def propose(self, data):
        return [NonlinearTerm(s) for s in _heated(data)]

    def make_term(self, sensor, params):
        return NonlinearTerm(sensor)


class HysteresisCandidate(Candidate):
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


class DriftCandidate(Candidate):
    name = "drift"

    def propose(self, data):
        return [DriftTerm(round(float(np.max(data.time_s - data.t0_s)) / 3600.0, 2))]

    def for_rows(self, term, data):
        return self.propose(data)[0] if term.max_h is not None else term

    def make_term(self, sensor, params):
        return DriftTerm(float(params["max_h"]) if "max_h" in params else None)


def _refine_tau(tau_s: float, make) -> list:
    """A finer grid between the coarse neighbours of a time constant, never
    below the shortest lag: a shorter one is a rate (see RateTerm), and
    refined down step by step a lag would take the rate's place."""
    step = _TAUS_S[1] / _TAUS_S[0]
    return [make(float(t)) for t in np.geomspace(tau_s / step, tau_s * step, 9) if t >= _TAUS_S[0]]


def _ambient(data: ThermalData) -> list[str]:
    return [s for s in data.sensors if "room" in s or "ambient" in s]


class SpeedLagCandidate(Candidate):
    name = "speed_lag"
    taus_s = _TAUS_S

    def propose(self, data):
        if data.rpm is None or np.ptp(data.rpm) == 0:
            return []
        return [SpeedLagTerm(tau, f) for f in ("n", "n2") for tau in self.taus_s]

    def refine(self, term: SpeedLagTerm) -> list[SpeedLagTerm]:
        return _refine_tau(term.tau_s, lambda t: SpeedLagTerm(t, term.form))

    def make_term(self, sensor, params):
        return SpeedLagTerm(float(params["tau_s"]), str(params.get("form", "n")))


class SpeedTempCandidate(Candidate):
    name = "speed_x_temp"

    def propose(self, data):
        if data.rpm is None or np.ptp(data.rpm) == 0:
            return []
        return [SpeedTempTerm(s) for s in _heated(data)]

    def make_term(self, sensor, params):
        return SpeedTempTerm(sensor)


class AmbientLagCandidate(Candidate):
    name = "lag_ambient"
    taus_s = _TAUS_S

    def propose(self, data):
        return [AmbientLagTerm(s, a, tau) for a in _ambient(data) for s in _heated(data)
                if s != a for tau in self.taus_s]

    def refine(self, term: AmbientLagTerm) -> list[AmbientLagTerm]:
        return _refine_tau(term.tau_s, lambda t: AmbientLagTerm(term.sensor, term.ambient, t))

    def make_term(self, sensor, params):
        return AmbientLagTerm(sensor, str(params["ambient"]), float(params["tau_s"]))


class SpeedStepCandidate(Candidate):
    """Offsets per speed level, when the speeds run are a few discrete levels
    (a program's speeds). Not proposed beside the smooth effects (with a
    column per level it would fit a speed squared as well, and be chosen for
    the noise): the loop builds it from the speed log once the library is
    exhausted and the residual still has structure (see ``structure``)."""
    name = "speed_step"
    max_levels = 12

    def propose(self, data):
        return []

    def structure(self, data) -> list[SpeedStepTerm]:
        if data.rpm is None or np.ptp(data.rpm) == 0:
            return []
        levels = np.unique(np.round(data.rpm, 0))
        if not 2 <= len(levels) <= self.max_levels:
            return []
        # a column per level, and one switch between each two neighbouring levels
        return [SpeedStepTerm(tuple(float(v) for v in levels)),
                *(SpeedStepTerm(above_rpm=float(v)) for v in (levels[:-1] + levels[1:]) / 2)]

    def make_term(self, sensor, params):
        if "above_rpm" in params:
            return SpeedStepTerm(above_rpm=float(params["above_rpm"]))
        return SpeedStepTerm(tuple(float(v) for v in params["levels_rpm"]))


class PeriodicCandidate(Candidate):
    """Not proposed blindly (any period fits something): the loop builds its
    term from a period found in the residual (see ``residual_structure``)."""
    name = "periodic"

    def propose(self, data):
        return []

    def make_term(self, sensor, params):
        return PeriodicTerm(float(params["period_s"]))


def builtin_candidates() -> list[Candidate]:
    return [LagCandidate(), RateCandidate(), SpeedCandidate(), NonlinearCandidate(),
            HysteresisCandidate(), DriftCandidate(), SpeedLagCandidate(), SpeedTempCandidate(),
            AmbientLagCandidate(), SpeedStepCandidate(), PeriodicCandidate()]
