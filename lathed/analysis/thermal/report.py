"""What ``analyze`` found: the stages of the model, the baselines beside them, the model handed on."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from lathed.analysis.forward import Scored

if TYPE_CHECKING:
    from lathed.analysis.thermal.model import ThermalModel
    from lathed.analysis.thermal.residual import ResidualReport
    from lathed.analysis.thermal.terms import Term


@dataclass(eq=False)        # one fit's result: the same stage is the same object (its errors are arrays)
class Stage:
    """A model fitted on the training rows and its errors: in-sample, forward in time on the
    training rows (what every choice is made on), and on the later rows the report judges on
    (the test rows; without them, the forward errors again)."""
    model: ThermalModel
    rmse_um: float
    forward_rmse_um: float
    test_rmse_um: float
    label: str = ""
    baseline: bool = False
    forward_errors: np.ndarray | None = field(default=None, repr=False)
    # baselines only: expanding-window error over the later half of every training row
    rolling_rmse_um: float | None = None

    def scored(self) -> Scored:
        return Scored(self.label, self.forward_rmse_um, self.test_rmse_um, self.baseline, rolling=self.rolling_rmse_um)

    def to_json(self) -> dict[str, Any]:
        return {"model": self.label, "terms": self.model.names, "rmse_um": round(self.rmse_um, 4),
                "forward_rmse_um": round(self.forward_rmse_um, 4), "test_rmse_um": round(self.test_rmse_um, 4),
                **({"rolling_rmse_um": round(self.rolling_rmse_um, 4)} if self.rolling_rmse_um is not None else {})}


@dataclass
class EffectFound:
    term: Term
    stage: Stage
    gain: float     # relative fall of the forward error when added
    z: float        # its significance

    def to_json(self) -> dict[str, Any]:
        i = self.stage.model.names.index(self.term.names[0])
        coef = self.stage.model.coef[i:i + len(self.term.names)]
        params = dict(self.term.params)
        params["coef"] = [round(float(c), 6) for c in coef] if len(coef) > 1 else round(float(coef[0]), 6)
        return {"effect": self.term.effect, "sensor": self.term.sensor, "params": params,
                "test_rmse_um": round(self.stage.test_rmse_um, 4)}


@dataclass
class SensorKept:
    """A sensor the selection kept, and what it carries."""
    sensor: str
    smooth_s: float
    forward_gain_um: float   # forward error without it less with it
    span_um: float           # its weight times the span of its rise: growth it accounts for
    notch_s: float = 0.0

    def to_json(self) -> dict[str, Any]:
        return {"sensor": self.sensor, "smooth_s": self.smooth_s, "notch_s": self.notch_s,
                "forward_gain_um": round(self.forward_gain_um, 4), "span_um": round(self.span_um, 3)}


@dataclass
class Analysis:
    """``start``: linear on the selected sensors, where the residual loop starts; ``loop``: with
    the effects it found; ``baselines``: the plain models fitted on the same rows; ``final``: the
    model handed on: ``loop`` when it beats every baseline on the newest training rows, else the
    baseline with the least rolling error."""
    start: Stage
    effects: list[EffectFound]
    loop: Stage
    final: Stage
    baselines: list[Stage]
    residual: ResidualReport
    notes: list[str]
    comparison: list[Scored] = field(default_factory=list)
    sensors: list[SensorKept] = field(default_factory=list)
    judged_on: str = ""
    forward_on: str = ""

    @property
    def model(self) -> ThermalModel:
        return self.final.model

    @property
    def least_squares(self) -> Stage:
        """Plain least squares on every sensor (the first baseline)."""
        return self.baselines[0]

    def best_baseline(self, on: str = "test") -> Stage:
        """The baseline with the least error ``on``: "test", "forward" (the newest training rows)
        or "rolling" (the later half of the training rows, the one handed on when the loop loses)."""
        key = {"test": "test_rmse_um", "forward": "forward_rmse_um", "rolling": "rolling_rmse_um"}[on]
        return min(self.baselines, key=lambda s: getattr(s, key))

    def to_json(self) -> dict[str, Any]:
        return {"start": self.start.to_json(), "effects": [e.to_json() for e in self.effects],
                "loop": self.loop.to_json(), "final": self.final.to_json(),
                "handed_on": self.final.label, "baselines": [b.to_json() for b in self.baselines],
                "comparison": {"rows": self.judged_on, "forward": self.forward_on,
                               "models": [c.to_json() for c in self.comparison]},
                "sensors": [k.to_json() for k in self.sensors],
                "residual": {"structured": self.residual.structured, "note": self.residual.note,
                             **({"period_s": round(self.residual.period_s, 1)} if self.residual.period_s else {}),
                             **({"matches_sensor": self.residual.sensor} if self.residual.sensor else {})},
                "notes": self.notes}
