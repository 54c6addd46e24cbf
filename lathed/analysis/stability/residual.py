"""What a stability model predicted against what the cuts did: the confusion,
the chatter-frequency error, and each misclassified cut with its margins."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from lathed.analysis.cuts import Cuts
from lathed.analysis.stability.model import StabilityModel

# A cut's speed is scanned this far either side for the nearest speed at
# which the model would have got it right (its margin in speed).
SPEED_SCAN = (0.5, 2.0)
# A measured chatter frequency is "explained" when it lies within this of the
# predicted one or of a configured natural frequency.
FREQ_EXPLAINED = 0.10

@dataclass
class Miss:
    """A cut the model got wrong and how far it was from being right."""
    line: int
    rpm: float
    depth_mm: float
    outcome: str                 # what happened
    limit_mm: float | None       # the model's limit at that speed (None: above every lobe)
    depth_margin_mm: float | None   # depth - limit: > 0 above the limit
    speed_margin_rpm: float | None  # signed distance to the nearest speed the model gets it right

    def to_json(self) -> dict:
        r = lambda x, d=4: None if x is None else round(x, d)  # noqa: E731
        return {"line": self.line, "rpm": r(self.rpm, 1), "depth_mm": r(self.depth_mm), "outcome": self.outcome,
                "limit_mm": r(self.limit_mm), "depth_margin_mm": r(self.depth_margin_mm),
                "speed_margin_rpm": r(self.speed_margin_rpm, 1)}


@dataclass
class Residual:
    """What a model predicted against what happened, on a set of cuts."""
    n: int
    true_stable: int
    true_chatter: int
    false_stable: int            # called stable, chattered: the costly kind
    false_chatter: int           # called chatter, was stable
    freq_n: int                  # chatter cuts with a measured frequency
    freq_mae_hz: float | None    # median |measured - predicted|
    freq_unexplained: list[float]   # measured frequencies no mode explains
    misses: list[Miss] = field(default_factory=list)

    @property
    def accuracy(self) -> float:
        return (self.true_stable + self.true_chatter) / self.n if self.n else float("nan")

    @property
    def false_stable_rate(self) -> float:
        """Share of the cuts that the model called stable and that chattered."""
        return self.false_stable / self.n if self.n else float("nan")

    def to_json(self, misses: bool = True) -> dict:
        d = {"cuts": self.n, "accuracy": round(self.accuracy, 4),
             "false_stable_rate": round(self.false_stable_rate, 4),
             "confusion": {"stable_predicted_stable": self.true_stable, "chatter_predicted_chatter": self.true_chatter,
                           "chatter_predicted_stable": self.false_stable, "stable_predicted_chatter": self.false_chatter},
             "chatter_frequency": {"measured": self.freq_n,
                                   "median_abs_error_hz": None if self.freq_mae_hz is None else round(self.freq_mae_hz, 2),
                                   "unexplained": len(self.freq_unexplained),
                                   "unexplained_median_hz": (round(float(np.median(self.freq_unexplained)), 1)
                                                             if self.freq_unexplained else None)}}
        if misses:
            d["misclassified"] = [m.to_json() for m in self.misses]
        return d


def unexplained(model: StabilityModel, fm: np.ndarray, fp: np.ndarray) -> np.ndarray:
    near_pred = np.abs(fm - fp) <= FREQ_EXPLAINED * fm
    near_mode = np.zeros(len(fm), bool)
    for m in model.modes:
        near_mode |= np.abs(fm - m.fn_hz) <= FREQ_EXPLAINED * m.fn_hz
    return ~(near_pred | near_mode)


def residual(model: StabilityModel, cuts: Cuts, margins: bool = True) -> Residual:
    pred, b, fp = model.predict_chatter(cuts)
    obs = cuts.chatter
    fm = cuts.chatter_frequency_hz
    has = obs & np.isfinite(fm)
    both = has & np.isfinite(fp)
    mae = float(np.median(np.abs(fm[both] - fp[both]))) if both.any() else None
    unexpl = has & unexplained(model, np.nan_to_num(fm), np.nan_to_num(fp))
    res = Residual(len(cuts), int(np.sum(~pred & ~obs)), int(np.sum(pred & obs)), int(np.sum(~pred & obs)),
                   int(np.sum(pred & ~obs)), int(has.sum()), mae, [float(x) for x in fm[unexpl]])
    wrong = np.flatnonzero(pred != obs)
    if margins and len(wrong):
        lo, hi = cuts.rpm.min() * SPEED_SCAN[0], cuts.rpm.max() * SPEED_SCAN[1]
        grid = np.geomspace(lo, hi, 3000)
        bg, _ = model.limit(grid)
        for i in wrong:
            d = cuts.depth_mm[i] * 1e-3
            right = (d >= bg) == obs[i]
            near = None
            if right.any():
                j = np.flatnonzero(right)
                k = j[np.argmin(np.abs(np.log(grid[j] / cuts.rpm[i])))]
                near = float(grid[k] - cuts.rpm[i])
            lim = float(b[i]) * 1e3 if math.isfinite(b[i]) else None
            res.misses.append(Miss(int(cuts.line[i]), float(cuts.rpm[i]), float(cuts.depth_mm[i]),
                                   "chatter" if obs[i] else "stable", lim,
                                   None if lim is None else float(cuts.depth_mm[i]) - lim, near))
    return res
