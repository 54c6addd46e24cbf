"""The stability model learned from cut records, how sure it is, and whether
to trust it (docs/stability.md).

``learn`` fits the model from the cuts alone (lathed.analysis.stability.start)
on the earlier cuts, decides between the fits without and with process
damping (on the later cuts of two rolling origins) and lets the residual
loop (lathed.analysis.stability.refit) add what they lack, all judged on the
later cuts; then fits the chosen model on every
cut and resamples the cuts (bootstrap) for intervals on the minimum stable
depth and on the best speeds.  It is trusted only when it classifies the
later cuts well, no worse than a depth threshold fitted on the same cuts
(the plain baseline), and its intervals are narrow; otherwise it says why
and about how many cuts more it needs.  Numeric only, no asyncio.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from lathed.analysis.cuts import Cuts
from lathed.analysis.stability.model import StabilityModel
from lathed.analysis.stability.refit import EffectAdded, refit
from lathed.analysis.stability.residual import Residual, residual
from lathed.analysis.stability.start import DEFAULT_KF, Fitted, Likelihood, maximise, propose

MIN_CUTS = 40             # cut speeds before a model is tried at all
MIN_CHATTER = 10          # ... of them chattering at a measured frequency, in the earlier share
HOLDOUT = 0.3             # the later share the choices are judged on
# Trusted when, on the later cuts: accuracy and false "stable" at least this good (the
# residual loop's "the model explains the cuts"), and no worse than the depth threshold ...
TRUST_ACCURACY = 0.90
TRUST_FALSE_STABLE = 0.05
Z95 = 1.6449
# ... and, over resamples of the cuts, the minimum stable depth known within this share
# (90 % interval: high / low - 1) and each best speed within this either side (the band
# speed selection judges a speed over, LobeSelection.band)
TRUST_DEPTH_SPREAD = 0.30
TRUST_SPEED_SPREAD = 0.03
BOOTSTRAP = 10
# each resample's fit starts at the model fitted on every cut, with smaller steps and fewer evaluations
BOOTSTRAP_EVALUATIONS = 80
BOOTSTRAP_STEP = 0.5
# A fit with process damping is chosen when the later cuts' likelihood favours it this much
# (paired z over the cuts) ...
CHOICE_Z = 2.0
# ... the later cuts of two origins: fitted on the earlier 70 %, judged on the last 30 %; and
# fitted on the earlier 40 %, judged on the 30 % after them.  One origin alone judges on too few
# cuts: the few slow cuts that show process damping decide, and a test on them flips from one
# learn to the next (a model without it, its scatter widened to cover them, was chosen at 300
# cuts after one with it at 200).
EARLIER_ORIGIN = 1 - 2 * HOLDOUT
POCKETS = 3               # best speeds reported: the highest local maxima of the limit
POCKET_MIN = 1.2          # ... at least this many times the minimum stable depth
POCKET_BAND = 0.03        # ... judged, as speed selection judges a speed, by the worst limit within this
SPEED_POINTS = 2000
Z90 = 1.6449


@dataclass(frozen=True)
class Interval:
    """A fitted value and its 90 % interval over resamples of the cuts."""
    value: float
    lo: float
    hi: float

    @property
    def spread(self) -> float:
        """Relative width: hi / lo - 1."""
        return self.hi / self.lo - 1 if self.lo > 0 else math.inf

    def to_json(self, digits: int = 4) -> list[float]:
        return [round(self.value, digits), round(self.lo, digits), round(self.hi, digits)]


@dataclass(frozen=True)
class Pocket:
    """A best speed: a local maximum of the limiting depth over the speed range."""
    rpm: Interval
    limit_mm: float
    found: float              # share of resamples that have it (within 10 % of its speed)


@dataclass
class Baseline:
    """The plain rule beside the model: chatter at and above one depth, at any speed."""
    depth_mm: float
    accuracy: float
    false_stable_rate: float
    predicted: np.ndarray = field(repr=False, default=None)     # chatter, on the later cuts


@dataclass
class Learned:
    model: StabilityModel | None        # None: too few cuts to fit any
    trusted: bool
    why_not: list[str]                  # empty when trusted
    cuts: int
    train: int = 0
    heldout: int = 0
    chose: str = ""                     # "modes" or "modes + process damping"
    sigma: float | None = None          # the scatter of the limit (log), fitted
    effects: list[EffectAdded] = field(default_factory=list)
    start: Residual | None = None       # the fit from the earlier cuts, on the later ones
    after: Residual | None = None       # ... with the residual loop's effects
    baseline: Baseline | None = None
    b_min_mm: Interval | None = None
    pockets: list[Pocket] = field(default_factory=list)
    rpm_range: tuple[float, float] | None = None
    cuts_needed: int | None = None      # about how many cut speeds in all it would need

    def summary(self) -> str:
        if self.model is None:
            return f"no model from {self.cuts} cut speeds: {'; '.join(self.why_not)}"
        a = self.after
        head = (f"{'trusted' if self.trusted else 'not trusted'}: {self.cuts} cut speeds, later "
                f"{self.heldout}: accuracy {100 * a.accuracy:.1f} %, false stable {100 * a.false_stable_rate:.1f} % "
                f"(depth threshold {100 * self.baseline.accuracy:.1f} %)")
        if self.b_min_mm is not None:
            b = self.b_min_mm
            head += f"; minimum stable depth {b.value:.3f} mm ({b.lo:.3f}-{b.hi:.3f})"
        if not self.trusted:
            head += "; " + "; ".join(self.why_not)
        return head

    def to_json(self) -> dict:
        def res(r):
            return None if r is None else r.to_json(misses=False)
        return {"trusted": self.trusted, "why_not": self.why_not, "cuts": self.cuts, "train": self.train,
                "heldout": self.heldout, "cuts_needed": self.cuts_needed, "chose": self.chose,
                "sigma": None if self.sigma is None else round(self.sigma, 4),
                "model": None if self.model is None else self.model.to_json(),
                "effects": [e.to_json() for e in self.effects], "start": res(self.start), "after": res(self.after),
                "baseline": None if self.baseline is None else {
                    "depth_mm": round(self.baseline.depth_mm, 4), "accuracy": round(self.baseline.accuracy, 4),
                    "false_stable_rate": round(self.baseline.false_stable_rate, 4)},
                "b_min_mm": None if self.b_min_mm is None else self.b_min_mm.to_json(),
                "best_rpm": [{"rpm": p.rpm.to_json(1), "limit_mm": round(p.limit_mm, 4), "found": round(p.found, 3)}
                             for p in self.pockets] if self.trusted else [],
                "rpm_range": None if self.rpm_range is None else [round(x, 1) for x in self.rpm_range]}


def baseline(train: Cuts, later: Cuts) -> Baseline:
    """The depth threshold with the fewest errors on ``train``, judged on ``later``."""
    d = np.sort(np.unique(train.depth_mm))
    cand = np.r_[d, d[-1] * 1.01]
    err = [np.sum((train.depth_mm >= t) != train.chatter) for t in cand]
    t = float(cand[int(np.argmin(err))])
    pred = later.depth_mm >= t
    n = max(len(later), 1)
    return Baseline(t, float(np.mean(pred == later.chatter)), float(np.sum(~pred & later.chatter)) / n, pred)


def wilson(k: int, n: int, z: float = Z95) -> tuple[float, float]:
    """The 90 % (two-sided; 95 % one-sided) bounds of a share ``k`` / ``n`` (Wilson's score interval)."""
    if n == 0:
        return 0.0, 1.0
    p, z2 = k / n, z * z
    mid, half = p + z2 / (2 * n), z * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n))
    return (mid - half) / (1 + z2 / n), (mid + half) / (1 + z2 / n)


def _paired_z(a: np.ndarray, b: np.ndarray) -> float:
    """How much lower b's per-cut losses are than a's, in standard errors."""
    d = a - b
    s = float(np.std(d, ddof=1)) if len(d) > 1 else 0.0
    return float(np.mean(d)) / (s / math.sqrt(len(d))) if s > 0 else 0.0


def _gain(fits: dict[str, Fitted], later: Cuts) -> np.ndarray:
    """Per later cut, how much likelier it is under the fit with process damping (log)."""
    plain, damped = fits["modes"], fits["process_damping"]
    lik = Likelihood(later)
    try:
        return lik.per_cut(plain.model, plain.sigma) - lik.per_cut(damped.model, damped.sigma)
    except ValueError:
        return np.zeros(len(later))


def _choose(fits: dict[str, Fitted], later: Cuts,
            earlier: tuple[dict[str, Fitted], Cuts] | None = None) -> tuple[str, Fitted]:
    """Process damping only when the later cuts are significantly likelier with it; ``earlier``:
    another origin's fits and the cuts after it, pooled with ``later`` (each judged on cuts
    later than its own fit)."""
    g = _gain(fits, later)
    if earlier is not None and earlier[0]:
        g = np.r_[_gain(*earlier), g]
    z = _paired_z(g, np.zeros_like(g))
    return ("modes + process damping", fits["process_damping"]) if z >= CHOICE_Z else ("modes", fits["modes"])


def speed_grid(rpm_range: tuple[float, float]) -> np.ndarray:
    return np.geomspace(rpm_range[0], rpm_range[1], SPEED_POINTS)


def pockets(model: StabilityModel, n: np.ndarray, least: float = POCKET_MIN, most: int | None = POCKETS
            ) -> tuple[float, list[tuple[float, float]]]:
    """(the minimum limit, m; the best speeds as (rpm, m), highest first): the local maxima
    of the worst limit within +-POCKET_BAND of each speed on ``n`` (a geometric grid), so a
    lobe's cusp narrower than the band is no pocket; at least ``least`` x the minimum."""
    b, _ = model.limit(n)
    b_min = float(np.min(b))
    top = float(np.max(b[np.isfinite(b)])) if np.isfinite(b).any() else b_min
    b = np.where(np.isfinite(b), b, 2 * top)      # above every lobe: the best there is
    half = max(1, int(round(math.log1p(POCKET_BAND) / math.log(n[1] / n[0]))))
    from scipy.ndimage import minimum_filter1d     # scipy on first use: a daemon start need not pay it
    w = minimum_filter1d(b, 2 * half + 1, mode="nearest")
    i = np.flatnonzero((w[1:-1] > w[:-2]) & (w[1:-1] >= w[2:])) + 1
    peaks = sorted(((float(n[j]), float(w[j])) for j in i if w[j] >= least * b_min), key=lambda p: -p[1])
    return b_min, peaks[:most]


def _interval(value: float, samples: list[float], step: float = 0.0) -> Interval:
    """``value`` with a 90 % interval from the spread of its resampled logs; at least
    ``step`` (a log) either side, the grid it was found on."""
    if len(samples) < 2:
        return Interval(value, 0.0, math.inf)
    s = max(Z90 * float(np.std(np.log(samples), ddof=1)), step)
    return Interval(value, value * math.exp(-s), value * math.exp(s))


def learn(cuts: Cuts, *, kf: float = DEFAULT_KF, rpm_range: tuple[float, float] | None = None,
          holdout_fraction: float = HOLDOUT, bootstrap: int = BOOTSTRAP, seed: int = 0) -> Learned:
    """The stability model of these cuts (in the order they were made), with no model given."""
    n = len(cuts)
    if n < MIN_CUTS:
        return Learned(None, False, [f"{n} cut speeds; a model needs at least {MIN_CUTS}"], n, cuts_needed=MIN_CUTS)
    cut = int(round(n * (1 - holdout_fraction)))
    train, later = cuts.take(np.arange(cut)), cuts.take(np.arange(cut, n))
    n_f = int(np.sum(train.chatter & np.isfinite(train.chatter_frequency_hz)))
    if n_f < MIN_CHATTER:
        need = int(math.ceil(MIN_CHATTER / max(n_f, 1) * n)) if n_f else None
        return Learned(None, False, [f"{n_f} of the earlier {cut} cut speeds chattered at a measured frequency; "
                                     f"a model needs at least {MIN_CHATTER}"], n, cut, n - cut, cuts_needed=need)
    fits = propose(train, kf)
    if not fits:
        return Learned(None, False, ["no group of chatter frequencies to place a mode at"], n, cut, n - cut)
    mid = int(round(n * EARLIER_ORIGIN))
    first = cuts.take(np.arange(mid))
    earlier = None
    if mid >= MIN_CUTS and int(np.sum(first.chatter & np.isfinite(first.chatter_frequency_hz))) >= MIN_CHATTER:
        earlier = (propose(first, kf), cuts.take(np.arange(mid, cut)))
    chose, fitted = _choose(fits, later, earlier)
    r = refit(fitted.model, cuts, holdout_fraction=holdout_fraction)
    base = baseline(train, later)
    # the structure chosen on the later cuts, its values fitted on every cut
    final = maximise(Likelihood(cuts), r.model, fitted.sigma)
    rpm_range = rpm_range or (float(cuts.rpm.min()), float(cuts.rpm.max()))
    grid = speed_grid(rpm_range)
    b_min, peaks = pockets(final.model, grid)
    rng = np.random.default_rng(seed)
    b_s: list[float] = []
    p_s: list[list[float]] = [[] for _ in peaks]
    for _ in range(bootstrap):
        w = rng.multinomial(n, np.full(n, 1.0 / n))
        fb = maximise(Likelihood(cuts, w), final.model, final.sigma, max_evaluations=BOOTSTRAP_EVALUATIONS,
                      tolerance=3e-3, step=BOOTSTRAP_STEP)
        bb, pb = pockets(fb.model, grid, least=1.0, most=None)   # the pocket moved, lower or not
        b_s.append(bb)
        for k, (rpm, _) in enumerate(peaks):
            near = [q for q, _ in pb if abs(math.log(q / rpm)) <= 0.1]
            if near:
                p_s[k].append(min(near, key=lambda q: abs(math.log(q / rpm))))
    b_int = _interval(b_min * 1e3, [x * 1e3 for x in b_s])
    step = math.log(grid[1] / grid[0])
    pk = [Pocket(_interval(rpm, s, step), lim * 1e3, len(s) / max(bootstrap, 1)) for (rpm, lim), s in zip(peaks, p_s)]
    why = []
    a = r.after
    if a.accuracy < TRUST_ACCURACY or a.false_stable_rate > TRUST_FALSE_STABLE:
        why.append(f"on the later {a.n} cut speeds accuracy {100 * a.accuracy:.1f} % and false stable "
                   f"{100 * a.false_stable_rate:.1f} %, not >= {100 * TRUST_ACCURACY:.0f} % and <= "
                   f"{100 * TRUST_FALSE_STABLE:.0f} %")
    # worse than the depth threshold beyond one standard error of the cuts they disagree on
    pred = r.model.predict_chatter(later)[0]
    worse = int(np.sum((pred != later.chatter) & (base.predicted == later.chatter)))
    better = int(np.sum((pred == later.chatter) & (base.predicted != later.chatter)))
    if worse > better and (worse - better) >= math.sqrt(worse + better):
        why.append(f"on the later cut speeds it classifies worse than a depth threshold "
                   f"({100 * a.accuracy:.1f} % against {100 * base.accuracy:.1f} %)")
    spread_need = []
    if b_int.spread > TRUST_DEPTH_SPREAD:
        why.append(f"minimum stable depth {b_int.value:.3f} mm, 90 % between {b_int.lo:.3f} and {b_int.hi:.3f}: "
                   f"wider than {100 * TRUST_DEPTH_SPREAD:.0f} %")
        spread_need.append(b_int.spread / TRUST_DEPTH_SPREAD)
    for p in pk:
        half = p.rpm.spread / 2
        if p.found < 0.9 or half > TRUST_SPEED_SPREAD:
            why.append(f"best speed {p.rpm.value:.0f} r/min, 90 % between {p.rpm.lo:.0f} and {p.rpm.hi:.0f}"
                       + (f" (in {100 * p.found:.0f} % of resamples)" if p.found < 0.9 else "")
                       + f": not within {100 * TRUST_SPEED_SPREAD:.0f} %")
            spread_need.append(max(half / TRUST_SPEED_SPREAD, 1.0 if p.found >= 0.9 else 1.5))
    # an interval narrows as 1/sqrt(cuts): the cuts that would bring the widest within its bar
    need = int(math.ceil(n * max(spread_need) ** 2)) if spread_need else (None if not why else int(n * 1.5))
    return Learned(final.model, not why, why, n, cut, n - cut, chose, final.sigma, r.effects,
                   residual(fitted.model, later, margins=False), a, base, b_int, pk, rpm_range,
                   None if not why else max(need, n + 1))


class Learner:
    """When to learn again as cuts accumulate, and which learned model to use: none until a
    learn is trusted; then the newest trusted one; a model in use that the newest later cuts
    judge below the bar is withdrawn (back to the model-free fallback) until a learn is
    trusted again.  The daemon's suppression and the benchmark's closed loop both run it."""

    GROWTH = 1.25      # learn again when the cut speeds have grown by this share ...
    STEP = 10          # ... and by at least this many

    def __init__(self) -> None:
        self.next_at = MIN_CUTS
        self.model: StabilityModel | None = None
        self.last: Learned | None = None

    def due(self, n_cuts: int) -> bool:
        return n_cuts >= self.next_at

    def consider(self, learned: Learned, cuts: Cuts, seen: int | None = None) -> str:
        """Take the result of ``learn(cuts)``: "adopted", "withdrawn", "kept" (the model in
        use stays) or "not trusted" (there is none).  ``seen``: the cut speeds recorded in all,
        when ``cuts`` are only the newest of them.  A model in use is withdrawn only when the
        later cuts are surely (95 %) below the bar: one false "stable" in 15 is not that."""
        n = len(cuts)
        m = max(n, seen or 0)
        self.next_at = max(m + self.STEP, int(math.ceil(m * self.GROWTH)))
        self.last = learned
        if learned.trusted:
            self.model = learned.model
            return "adopted"
        if self.model is None:
            return "not trusted"
        if learned.train and learned.train < n:
            r = residual(self.model, cuts.take(np.arange(learned.train, n)), margins=False)
            if (wilson(r.true_stable + r.true_chatter, r.n)[1] < TRUST_ACCURACY
                    or wilson(r.false_stable, r.n)[0] > TRUST_FALSE_STABLE):
                self.model = None
                return "withdrawn"
        return "kept"
