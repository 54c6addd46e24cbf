"""The daemon's refit: analyse all but the newest rows; the model the analysis hands on and every
plain baseline fitted on the same rows then predict the newest rows, and the best of them is
adopted only if it beats the model in use there. See docs/thermal.md."""
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
    candidate: ThermalModel        # the best on the newest rows of the analysis's model and the baselines
    before_rmse_um: float          # the model in use on the newest rows
    after_rmse_um: float           # the candidate on the same rows
    better: bool                   # adopted
    analysis: Analysis
    baselines_rmse_um: dict[str, float] = field(default_factory=dict)   # each baseline on the newest rows
    why: str = ""
    label: str = ""                # what the candidate is

    @property
    def least_squares_rmse_um(self) -> float | None:
        return next(iter(self.baselines_rmse_um.values()), None)

    @property
    def best_baseline(self) -> tuple[str, float] | None:
        return min(self.baselines_rmse_um.items(), key=lambda kv: kv[1], default=None)


def refit(data: ThermalData | ThermalRuns, current: ThermalModel | None = None, *, holdout_fraction: float = 0.2,
          min_gain: float = 0.05, extra_candidates: Sequence[Candidate] = (), **analyze_kw) -> RefitResult:
    """Analyse all but the newest ``holdout_fraction`` of ``data``; of the model it hands on and
    the plain baselines fitted on the same rows, the one that predicts the newest rows best (the
    analysis's on a tie) is the candidate, adopted only if it beats ``current`` (default eq. 14)
    there by ``min_gain`` (relative)."""
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

    before = on_tail(current)
    base = {s.label: on_tail(s.model) for s in a.baselines}
    handed = on_tail(a.model) if not a.final.baseline else base[a.final.label]
    # the analysis's model first: a baseline replaces it only by predicting the newest rows better
    label, after = min([(a.final.label, handed), *base.items()], key=lambda kv: kv[1])
    model = a.model if label == a.final.label else next(s.model for s in a.baselines if s.label == label)
    better, why = adoption(before, after, base, min_gain, n - cut)
    if label != a.final.label:
        why = (f"the analysis handed on {a.final.label} ({handed:.2f} µm on the newest rows); {label} predicts "
               f"them better and is the candidate. {why}")
    return RefitResult(model if better else current, model, before, after, better, a, base, why, label)


def adoption(before: float, after: float, baselines: dict[str, float], min_gain: float, rows: int) -> tuple[bool, str]:
    """Adopt a candidate whose error on the newest rows is ``after``: only if it beats the model
    in use (``before``) by ``min_gain`` (relative) and no baseline fitted on the same rows does
    better there. Returns the verdict and why."""
    name, best = min(baselines.items(), key=lambda kv: kv[1], default=("no baseline", math.inf))
    if best < after:
        return False, f"{name} ({best:.2f} µm) beats the new model ({after:.2f} µm) on the newest {rows} rows"
    if not after < (1 - min_gain) * before:
        return False, (f"the new model ({after:.2f} µm) does not beat the model in use ({before:.2f} µm) "
                       f"by {100 * min_gain:g} % on the newest {rows} rows")
    return True, (f"the new model ({after:.2f} µm) beats the model in use ({before:.2f} µm) and is at or below "
                  f"every baseline (best: {name}, {best:.2f} µm) on the newest {rows} rows")
