"""A stability model from cut records alone, no tap test (docs/stability.md).

The evidence: a chatter cut's measured frequency lies just above the mode
that chattered, and where in its lobe the speed put it moves it up or down;
the depths that chattered and did not bound the limit from above and below.

* Modes: the measured chatter frequencies fall into groups (one per mode
  that chattered: a gap of more than GROUP_GAP between neighbours starts a
  new one); each group starts a mode just below its lowest frequencies.
* Each mode is written (fn, zeta, b0) with b0 = 2 k zeta (1 + zeta) / Kf its
  own minimum limit, so the limit's scale is one number, nearly independent
  of where the lobes lie.  Kf is a given (only k / Kf is seen for one
  material); theta is 0 (the stiffness found is the one along the chip).
* The cuts' likelihood (``Likelihood``): a cut chatters when its depth is
  above the limit at its speed times a scatter exp(N(0, sigma)) (tool wear,
  hardness, runout), so P(chatter) = Phi(log(depth / b_lim) / sigma), sigma
  fitted with the rest; plus the measured chatter frequencies against the
  predicted ones.  Maximised by Nelder-Mead in log parameters (the limit is a
  minimum over lobes: continuous, not smooth).

``propose`` fits the modes without and with process damping; which one is
used is decided on later cuts (lathed.analysis.stability.learn).  Numeric
only, no asyncio.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from lathed.analysis.cuts import Cuts
from lathed.analysis.modal import Mode
from lathed.analysis.stability.model import StabilityModel

DEFAULT_KF = 2.0e9        # N/m^2, regen.DEFAULT_KF: a scale only (k / Kf is what cuts show)
# Chatter frequencies further apart than this (ratio of neighbours) belong to different modes.
GROUP_GAP = 1.08
# A group needs this many frequencies (and this share of them) to start a mode; fewer are
# left to the residual loop's second mode.
GROUP_MIN = 3
GROUP_SHARE = 0.05
MAX_MODES = 3
# A measured chatter frequency is judged against the predicted one with this relative
# scale: the detector's spectral resolution and the drift of a chatter frequency above the limit.
FREQ_SCALE = 0.02
FREQ_WEIGHT = 0.5         # ... each cut's misfit (rel / FREQ_SCALE)^2, at most FREQ_CAP, times this
FREQ_CAP = 9.0
SIGMA_START = 0.1         # the limit's scatter before it is fitted (log)
SIGMA_RANGE = (0.005, 1.0)
# What is known of the scatter before the cuts: about 10 %, give or take a factor of two
# (log-normal).  Without it a few cuts that a sharp limit separates fit a scatter of nothing,
# and every interval taken from the fit is too narrow.
SIGMA_PRIOR = (0.1, 0.7)
ZETA_START = 0.03
# Nelder-Mead's first steps, in log units: fn, zeta, b0 of a mode, sigma, process damping
STEPS = (0.02, 0.3, 0.15, 0.3, 1.0)


@dataclass(frozen=True)
class Fitted:
    """A model with the scatter of its limit and the cuts' negative log-likelihood."""
    model: StabilityModel
    sigma: float
    nll: float
    evaluations: int


def frequency_groups(cuts: Cuts) -> list[np.ndarray]:
    """Indices of the chatter cuts with a measured frequency, one array per mode that
    chattered, lowest frequency first (at most MAX_MODES: the largest groups)."""
    idx = np.flatnonzero(cuts.chatter & np.isfinite(cuts.chatter_frequency_hz))
    if len(idx) < GROUP_MIN:
        return []
    f = cuts.chatter_frequency_hz[idx]
    o = np.argsort(f, kind="stable")
    cut = np.flatnonzero(f[o][1:] / f[o][:-1] > GROUP_GAP) + 1
    groups = [idx[o[a:b]] for a, b in zip(np.r_[0, cut], np.r_[cut, len(o)])]
    groups = [g for g in groups if len(g) >= max(GROUP_MIN, GROUP_SHARE * len(idx))]
    groups = sorted(groups, key=len, reverse=True)[:MAX_MODES]
    return sorted(groups, key=lambda g: float(np.median(cuts.chatter_frequency_hz[g])))


def mode_below(frequencies_hz: np.ndarray) -> float:
    """Where a mode lies whose chatter was measured at these frequencies: just below the
    lowest (chatter is above its mode, by a few per cent at most of the speeds)."""
    return float(np.percentile(frequencies_hz, 5)) / 1.01


class Likelihood:
    """Negative log-likelihood of cuts under a model (see the module's docstring).
    ``weights``: how often each cut counts (a bootstrap resample); default once."""

    def __init__(self, cuts: Cuts, weights: np.ndarray | None = None):
        self.cuts = cuts
        self.d = cuts.depth_mm * 1e-3
        # limits above this change no cut's likelihood much (3 sigma of a wide scatter)
        self.cap = 1.5 * float(self.d.max())
        self.sign = np.where(cuts.chatter, 1.0, -1.0)
        self.w = np.ones(len(cuts)) if weights is None else np.asarray(weights, float)
        self.fm = cuts.chatter_frequency_hz
        self.has_f = cuts.chatter & np.isfinite(self.fm)
        self.evaluations = 0

    def per_cut(self, model: StabilityModel, sigma: float) -> np.ndarray:
        """Each cut's share of the negative log-likelihood (unweighted)."""
        self.evaluations += 1
        b, fp = model.limit(self.cuts.rpm, self.cap)
        b = np.minimum(b, self.cap)
        from scipy.special import log_ndtr     # scipy on first use: a daemon start need not pay it
        out = -log_ndtr(self.sign * np.log(self.d / b) / sigma)
        if self.has_f.any():
            fpp, fm = fp[self.has_f], self.fm[self.has_f]
            rel = np.where(np.isfinite(fpp), np.abs(fm - fpp) / fm, 1.0)
            out[self.has_f] += FREQ_WEIGHT * np.minimum((rel / FREQ_SCALE) ** 2, FREQ_CAP)
        return out

    def __call__(self, model: StabilityModel, sigma: float) -> float:
        try:
            return float(np.dot(self.w, self.per_cut(model, sigma)))
        except ValueError:          # no regenerative chatter from these values
            return math.inf


def b0_of(mode: Mode, kf: float) -> float:
    """A mode's own minimum limit: 2 k zeta (1 + zeta) / (u Kf)."""
    return 2 * mode.k_n_per_m * mode.zeta * (1 + mode.zeta) / (max(mode.u, 1e-6) * kf)


def _mode(fn: float, zeta: float, b0: float, kf: float, theta: float = 0.0) -> Mode:
    u = max(math.cos(math.radians(theta)) ** 2, 1e-6)
    return Mode(fn, zeta, b0 * u * kf / (2 * zeta * (1 + zeta)), theta)


class _Vector:
    """A model's free values as one vector of logs: (fn, zeta, b0) per mode, sigma, and
    process damping when it is fitted; Kf and each mode's angle stay as they are."""

    def __init__(self, model: StabilityModel, sigma: float, process_damping: bool):
        self.kf, self.thetas = model.kf, [m.theta_deg for m in model.modes]
        self.pd = process_damping
        x = []
        for m in model.modes:
            x += [math.log(m.fn_hz), math.log(m.zeta), math.log(b0_of(m, model.kf))]
        x.append(math.log(sigma))
        if process_damping:
            x.append(math.log(max(model.process_damping, 1e-3)))
        self.x0 = np.array(x)

    def steps(self) -> np.ndarray:
        s = list(STEPS[:3]) * len(self.thetas) + [STEPS[3]] + ([STEPS[4]] if self.pd else [])
        return np.array(s)

    def model(self, x: np.ndarray) -> tuple[StabilityModel, float]:
        modes = []
        for i, th in enumerate(self.thetas):
            fn, z, b0 = np.exp(x[3 * i:3 * i + 3])
            modes.append(_mode(float(fn), float(min(z, 0.9)), float(b0), self.kf, th))
        j = 3 * len(self.thetas)
        sigma = float(np.clip(math.exp(x[j]), *SIGMA_RANGE))
        pd = float(math.exp(x[j + 1])) if self.pd else 0.0
        return StabilityModel(tuple(modes), self.kf, pd), sigma


def maximise(lik: Likelihood, model: StabilityModel, sigma: float = SIGMA_START, *,
             process_damping: bool | None = None, max_evaluations: int | None = None,
             tolerance: float = 2e-3, step: float = 1.0) -> Fitted:
    """The likelihood's maximum near ``model`` (Nelder-Mead from steps of ``step`` x STEPS),
    with SIGMA_PRIOR on the scatter.
    ``process_damping``: fit it too (default: when the model has some)."""
    pd = model.process_damping > 0 if process_damping is None else process_damping
    v = _Vector(model, sigma, pd)
    n0 = lik.evaluations

    def cost(x):
        try:
            m, s = v.model(x)
        except (ValueError, OverflowError):
            return math.inf
        return lik(m, s) + 0.5 * (math.log(s / SIGMA_PRIOR[0]) / SIGMA_PRIOR[1]) ** 2
    x0, st = v.x0, step * v.steps()
    simplex = np.vstack([x0] + [x0 + st[i] * np.eye(len(x0))[i] for i in range(len(x0))])
    from scipy.optimize import minimize
    r = minimize(cost, x0, method="Nelder-Mead",
                 options={"initial_simplex": simplex, "xatol": tolerance, "fatol": 0.02,
                          "maxfev": max_evaluations or 150 * len(x0)})
    m, s = v.model(r.x)
    return Fitted(m, s, float(r.fun), lik.evaluations - n0)


def initial(cuts: Cuts, kf: float = DEFAULT_KF) -> StabilityModel | None:
    """Modes at the chatter-frequency groups, the limit's scale searched on the
    likelihood; None without a group (no chatter at a measured frequency)."""
    groups = frequency_groups(cuts)
    if not groups:
        return None
    d = cuts.depth_mm * 1e-3
    first = [(mode_below(cuts.chatter_frequency_hz[g]), float(np.percentile(d[g], 10))) for g in groups]
    lik = Likelihood(cuts)

    def at(s):
        return StabilityModel(tuple(_mode(fn, ZETA_START, b * s, kf) for fn, b in first), kf)
    scales = np.geomspace(0.3, 3.0, 15)
    return at(scales[int(np.argmin([lik(at(s), SIGMA_START) for s in scales]))])


def with_process_damping(lik: Likelihood, start: StabilityModel, sigma: float = SIGMA_START) -> StabilityModel:
    """``start`` with the process damping that fits best from a scan (added damping ratio at
    the slow cuts from 1 % to 5x the lightest mode's own), to start a fit from."""
    zmin = min(m.zeta for m in start.modes)
    n0 = float(np.percentile(lik.cuts.rpm, 10))
    grid = zmin * n0 * np.geomspace(0.01, 5.0, 12)
    costs = [lik(replace(start, process_damping=float(c)), sigma) for c in grid]
    return replace(start, process_damping=float(grid[int(np.argmin(costs))]))


def propose(cuts: Cuts, kf: float = DEFAULT_KF) -> dict[str, Fitted]:
    """The model from these cuts alone, without and with process damping
    (``{"modes": ..., "process_damping": ...}``); empty without chatter at a measured
    frequency."""
    start = initial(cuts, kf)
    if start is None:
        return {}
    lik = Likelihood(cuts)
    plain = maximise(lik, start, process_damping=False)
    # from the same start, not from the plain fit: without it, damping too high stands in
    # for process damping, and a fit from there stays there
    damped = maximise(lik, with_process_damping(lik, start), process_damping=True)
    return {"modes": plain, "process_damping": damped}
