"""The thermal model: displacement = Σ coef·column + intercept over its terms; saved as TOML,
predicted in batch and live. See docs/thermal.md."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from lathed.analysis.thermal.candidates import Candidate, builtin_candidates
from lathed.analysis.thermal.data import ThermalData, sensor_column
from lathed.analysis.thermal.fit import design
from lathed.analysis.thermal.terms import LinearTerm, Term

# The paper's printed eq. 14 (ΔN in mm per °C rise); we work in µm.
EQ14_COEF_MM_PER_C = {"t_front_bearing_c": -0.00911, "t_rear_bearing_c": 0.00606,
                      "t_motor_c": 0.009833, "t_room_c": 0.000548}
EQ14_INTERCEPT_MM = -0.22194


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
        return design(data.rises_as(self.rises_from), self.terms) @ self.coef + self.intercept_um

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
