"""The stability model's residual loop: cuts -> what the model got wrong ->
the effect it lacks -> added -> classification before/after (docs/stability.md).

Each candidate effect is fitted on the earlier cuts (the training share) and
kept only if it classifies the later, held-out cuts better by a margin (a
sign test on the cuts it fixes and breaks), or classifies them no worse
beyond noise and predicts their chatter frequencies markedly better.
Numeric only, no asyncio.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lathed.analysis.cuts import Cuts
from lathed.analysis.stability.effects import Effect, Fit, compose, fit_candidates, key, search
from lathed.analysis.stability.model import StabilityModel
from lathed.analysis.stability.residual import Residual, residual

# An effect that classifies no worse is also kept when it lowers the median
# held-out chatter-frequency error by this much (and significantly).
FREQ_GAIN = 0.3

@dataclass
class EffectAdded:
    effect: Effect
    description: str
    heldout_errors_before: int
    heldout_errors_after: int
    fixed: int            # held-out cuts it turned right
    broken: int           # held-out cuts it turned wrong
    z: float
    kept_by: str          # "classification" or "chatter frequency"

    def to_json(self) -> dict:
        return {**self.effect.to_json(), "description": self.description,
                "heldout_errors": [self.heldout_errors_before, self.heldout_errors_after],
                "fixed": self.fixed, "broken": self.broken, "z": round(self.z, 2), "kept_by": self.kept_by}


@dataclass
class Refit:
    base: StabilityModel
    model: StabilityModel
    effects: list[EffectAdded]
    train: Cuts
    heldout: Cuts
    before: Residual          # the given model on the held-out cuts
    after: Residual           # the refit model on the held-out cuts
    before_all: Residual      # the given model on every cut (with margins)
    rejected: list[str]       # best candidates not kept, and why
    conclusion: str

    def to_json(self) -> dict:
        return {"cuts": len(self.train) + len(self.heldout), "train": len(self.train), "heldout": len(self.heldout),
                "model_before": self.base.to_json(), "model_after": self.model.to_json(),
                "effects": [e.to_json() for e in self.effects],
                "before": self.before.to_json(misses=False), "after": self.after.to_json(misses=False),
                "residual_all_cuts": self.before_all.to_json(), "rejected": self.rejected,
                "conclusion": self.conclusion}


def _med(rel: np.ndarray) -> str:
    return f"{100 * float(np.median(rel)):.1f}" if len(rel) else "-"


def _sign_z(fixed: int, broken: int) -> float:
    return (fixed - broken) / math.sqrt(fixed + broken) if fixed + broken else 0.0


def refit(base: StabilityModel, cuts: Cuts, *, holdout_fraction: float = 0.3, max_effects: int = 3,
          min_gain: float = 0.01, min_z: float = 2.5, min_z_freq: float = 4.0) -> Refit:
    """Fit candidate effects on the earlier cuts and keep those that classify
    the later (held-out) cuts better: at least ``min_gain`` more accuracy and
    a sign-test z of at least ``min_z`` on the cuts an effect fixes and breaks
    (2.5, not 2: the best of some ten candidates is picked on the same cuts),
    or verdicts no worse beyond noise (z > -1) and a chatter-frequency error
    lower on held-out cuts with a sign-test z of ``min_z_freq``."""
    if not 0 < holdout_fraction < 1:
        raise ValueError(f"holdout_fraction must be in (0, 1), got {holdout_fraction}")
    n = len(cuts)
    cut = int(round(n * (1 - holdout_fraction)))
    if cut < 10 or n - cut < 10:
        raise ValueError(f"{n} cuts are too few: the refit needs at least 10 to fit on and 10 held out")
    train, held = cuts.take(np.arange(cut)), cuts.take(np.arange(cut, n))
    fit = Fit(train)
    obs_h = held.chatter

    def heldout_pred(m: StabilityModel) -> np.ndarray:
        return m.predict_chatter(held)[0]

    def n_err(pred):
        return int(np.sum(pred != obs_h))

    has_f = held.chatter & np.isfinite(held.chatter_frequency_hz)

    def freq_err(m: StabilityModel) -> np.ndarray:
        """Relative chatter-frequency error on the held-out chatter cuts (1 where none predicted)."""
        if not has_f.any():
            return np.zeros(0)
        _, fp = m.limit(held.rpm[has_f])
        fm = held.chatter_frequency_hz[has_f]
        return np.where(np.isfinite(fp), np.abs(fm - fp) / fm, 1.0)

    effects: list[EffectAdded] = []
    chosen: list[Effect] = []
    rejected: list[str] = []
    model = base
    pred_cur = heldout_pred(model)
    materials = list(dict.fromkeys(cuts.material))
    material = materials[0] if len(materials) == 1 else None
    while len(chosen) < max_effects:
        cands = fit_candidates(model, fit, {key(e) for e in chosen})
        if not cands:
            break
        scored = []
        for c, e in cands:
            m = e.apply(model)
            p = heldout_pred(m)
            scored.append((n_err(p), c, e, p, freq_err(m)))
        # Occam: the simplest candidate that no other one beats significantly on
        # the held-out cuts, in verdicts or in chatter frequencies, without
        # doing significantly worse in the other (a second mode next to a
        # configured one mimics a shifted mode with three values, not one; a Kf
        # change mimics a second mode in verdicts, not in the frequency it chatters at)
        def z_over(t, u):
            zc = _sign_z(int(np.sum((t[3] == obs_h) & (u[3] != obs_h))), int(np.sum((t[3] != obs_h) & (u[3] == obs_h))))
            zf = _sign_z(int(np.sum(t[4] < u[4])), int(np.sum(t[4] > u[4])))
            return zc, zf

        def beaten(u):
            for t in scored:
                if t is not u:
                    zc, zf = z_over(t, u)
                    if (zc >= min_z and zf > -min_z_freq) or (zf >= min_z_freq and zc > -min_z):
                        return True
            return False
        pool = [u for u in scored if not beaten(u)] or scored
        err, _, e, p, _ = min(pool, key=lambda u: (len(u[2].values), u[0], u[1]))
        fixed = int(np.sum((pred_cur != obs_h) & (p == obs_h)))
        broken = int(np.sum((pred_cur == obs_h) & (p != obs_h)))
        z = _sign_z(fixed, broken)
        gain = (fixed - broken) / len(held)
        f_old, f_new = freq_err(model), freq_err(e.apply(model))
        zf = _sign_z(int(np.sum(f_new < f_old)), int(np.sum(f_new > f_old)))
        desc = e.describe(model, material)
        by_class = gain >= min_gain and z >= min_z
        # a shifted mode moves the lobes at high speed only, where few cuts may
        # lie near the limit; its other evidence is the chatter frequency
        # (verdicts then only need to be no worse beyond noise: z > -1)
        by_freq = (z > -1.0 and zf >= min_z_freq and len(f_old) >= 10
                   and np.median(f_new) <= (1 - FREQ_GAIN) * np.median(f_old))
        if not (by_class or by_freq):
            rejected.append(f"{desc}: held-out errors {n_err(pred_cur)} -> {err} "
                            f"(fixes {fixed}, breaks {broken}; z {z:.1f}), chatter-frequency error "
                            f"{_med(f_old)} -> {_med(f_new)} %: not better by the margin")
            break
        chosen.append(e)
        effects.append(EffectAdded(e, desc, n_err(pred_cur), err, fixed, broken, z,
                                   "classification" if by_class else "chatter frequency"))
        # joint: refit the earlier effects with the new one in place, keep what fits the training cuts better
        if len(chosen) > 1:
            chosen = _joint(base, chosen, fit)
        model = compose(base, chosen)
        pred_cur = heldout_pred(model)
        effects[-1].heldout_errors_after = n_err(pred_cur)
    before, after = residual(base, held, margins=False), residual(model, held, margins=False)
    before_all = residual(base, cuts)
    if effects:
        conclusion = (f"added {', '.join(e.effect.name for e in effects)}: held-out accuracy "
                      f"{100 * before.accuracy:.1f} % -> {100 * after.accuracy:.1f} %")
    elif before.accuracy >= 0.9 and before.false_stable_rate <= 0.05:
        conclusion = (f"the model explains the cuts (held-out accuracy {100 * before.accuracy:.1f} %): "
                      f"no effect added")
    else:
        conclusion = (f"no effect in the library explains the residual: held-out accuracy stays "
                      f"{100 * before.accuracy:.1f} %, {before.false_stable} cut(s) called stable chattered; "
                      f"the misclassified cuts are listed with their margins")
    return Refit(base, model, effects, train, held, before, after, before_all, rejected, conclusion)


def _joint(base: StabilityModel, chosen: list[Effect], fit: Fit) -> list[Effect]:
    """One coordinate pass: each earlier effect's first value refitted with the
    others in place (the effects are not independent: a process damping
    found first absorbs part of a Kf change)."""
    out = list(chosen)
    for i, e in enumerate(out[:-1]):
        # in its place: an effect may change a mode that an earlier second_mode added
        before, after = compose(base, out[:i]), out[i + 1:]

        def cost(m, after=after):
            return fit(compose(m, after))
        x = e.values[0]
        grid = x * np.geomspace(0.8, 1.25, 11) if e.name != "process_damping" else x * np.geomspace(0.5, 2.0, 11)
        if e.name == "second_mode":
            mk = lambda v, e=e: Effect(e.name, (v,) + e.values[1:], e.mode)  # noqa: E731
        else:
            mk = lambda v, e=e: Effect(e.name, (v,), e.mode)  # noqa: E731
        c_new, e_new = search(cost, mk, before, grid)
        if e_new is not None and c_new < cost(e.apply(before)):
            out[i] = e_new
    return out
