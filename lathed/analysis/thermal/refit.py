"""The daemon's refit: fit on all but the newest rows, adopt only a model that predicts the newest
rows better than the model in use and than every plain baseline fitted on the same rows."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

from lathed.analysis.forward import rmse
from lathed.analysis.thermal.candidates import Candidate
from lathed.analysis.thermal.data import ThermalData, ThermalRuns
from lathed.analysis.thermal.loop import analyze
from lathed.analysis.thermal.model import ThermalModel, eq14_model
from lathed.analysis.thermal.report import Analysis


@dataclass
class RefitResult:
    model: ThermalModel            # the model to use from now on
    candidate: ThermalModel        # the model the analysis handed on
    before_rmse_um: float          # the model in use on the newest rows
    after_rmse_um: float           # the candidate on the same rows
    better: bool                   # adopted
    analysis: Analysis
    baselines_rmse_um: dict[str, float] = field(default_factory=dict)   # each baseline on the newest rows
    why: str = ""

    @property
    def least_squares_rmse_um(self) -> float | None:
        return next(iter(self.baselines_rmse_um.values()), None)

    @property
    def best_baseline(self) -> tuple[str, float] | None:
        return min(self.baselines_rmse_um.items(), key=lambda kv: kv[1], default=None)


def refit(data: ThermalData | ThermalRuns, current: ThermalModel | None = None, *, holdout_fraction: float = 0.2,
          min_gain: float = 0.05, extra_candidates: Sequence[Candidate] = (), **analyze_kw) -> RefitResult:
    """Analyse all but the newest ``holdout_fraction`` of ``data``; adopt the model it hands on
    only if, on those newest rows, it beats ``current`` (default eq. 14) by ``min_gain``
    (relative) and no plain baseline fitted on the same rows beats it."""
    if data.displacement_um is None:
        raise ValueError("refit needs measured displacements")
    if not 0 < holdout_fraction < 1:
        raise ValueError(f"holdout_fraction must be in (0, 1), got {holdout_fraction}")
    n = len(data)
    cut = int(round(n * (1 - holdout_fraction)))
    current = current or eq14_model()
    a = analyze(data.slice(0, cut), extra_candidates=extra_candidates, **analyze_kw)
    y = data.displacement_um[cut:]

    def on_tail(model: ThermalModel) -> float:
        # predicted over every row, so terms with memory carry into the newest ones
        return rmse(y - model.predict(data)[cut:])

    before, after = on_tail(current), on_tail(a.model)
    base = {s.label: on_tail(s.model) for s in a.baselines}
    better, why = adoption(before, after, base, min_gain, n - cut)
    return RefitResult(a.model if better else current, a.model, before, after, better, a, base, why)


def adoption(before: float, after: float, baselines: dict[str, float], min_gain: float, rows: int) -> tuple[bool, str]:
    """Adopt a new model whose error on the newest rows is ``after``: only if it beats the model
    in use (``before``) by ``min_gain`` (relative) and no baseline fitted on the same rows beats
    it there. Returns the verdict and why."""
    name, best = min(baselines.items(), key=lambda kv: kv[1], default=("no baseline", math.inf))
    if not after < (1 - min_gain) * before:
        return False, (f"the new model ({after:.2f} µm) does not beat the model in use ({before:.2f} µm) "
                       f"by {100 * min_gain:g} % on the newest {rows} rows")
    if best < after:
        return False, f"{name} ({best:.2f} µm) beats the new model ({after:.2f} µm) on the newest {rows} rows"
    return True, (f"the new model ({after:.2f} µm) beats the model in use ({before:.2f} µm) and every "
                  f"baseline (best: {name}, {best:.2f} µm) on the newest {rows} rows")
