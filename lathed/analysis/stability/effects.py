"""The effects a stability model may lack, each fitted on cuts: a natural
frequency or damping off, the cutting coefficient off, a second mode,
process damping (the table in docs/stability.md), and the training cost they
are fitted by."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Callable, Sequence

import numpy as np

from lathed.analysis.cuts import Cuts
from lathed.analysis.modal import Mode
from lathed.analysis.stability.model import StabilityModel
from lathed.analysis.stability.residual import unexplained
from lathed.analysis.stability.start import frequency_groups, mode_below

# Cost of a cut the model calls stable that chatters, relative to the other
# error: it sends the spindle into chatter, the other only forgoes a speed.
FALSE_STABLE_WEIGHT = 2.0

@dataclass(frozen=True)
class Effect:
    """One effect with its fitted values, applied on top of a model."""
    name: str
    values: tuple[float, ...]
    mode: int | None = None          # which configured mode it changes

    def apply(self, m: StabilityModel) -> StabilityModel:
        modes = list(m.modes)
        if self.name == "natural_frequency":
            modes[self.mode] = replace(modes[self.mode], fn_hz=modes[self.mode].fn_hz * self.values[0])
        elif self.name == "damping":
            modes[self.mode] = replace(modes[self.mode], zeta=min(0.95, modes[self.mode].zeta * self.values[0]))
        elif self.name == "cutting_coefficient":
            return replace(m, kf=m.kf * self.values[0])
        elif self.name == "second_mode":
            modes.append(Mode(*self.values))
        elif self.name == "process_damping":
            return replace(m, process_damping=m.process_damping + self.values[0])
        else:
            raise ValueError(f"unknown effect {self.name}")
        return replace(m, modes=tuple(modes))

    def describe(self, base: StabilityModel, material: str | None = None) -> str:
        v = self.values
        if self.name == "natural_frequency":
            fn = base.modes[self.mode].fn_hz
            return f"natural frequency of mode {self.mode + 1} off: {fn:.1f} -> {fn * v[0]:.1f} Hz ({100 * (v[0] - 1):+.1f} %)"
        if self.name == "damping":
            z = base.modes[self.mode].zeta
            return f"damping of mode {self.mode + 1} off: zeta {z:.4f} -> {min(0.95, z * v[0]):.4f} (x{v[0]:.2f})"
        if self.name == "cutting_coefficient":
            on = f" for {material}" if material else ""
            return (f"cutting coefficient off{on}: Kf {base.kf:.3g} -> {base.kf * v[0]:.3g} N/m^2 (x{v[0]:.2f}; "
                    f"the same cuts fit every mode's stiffness x{1 / v[0]:.2f})")
        if self.name == "second_mode":
            return (f"a second mode the model lacks: {v[0]:.1f} Hz, zeta {v[1]:.4f}, "
                    f"k {v[2]:.3g} N/m along the chip direction")
        return (f"process damping: added damping ratio {v[0]:.3g}/n on every mode "
                f"({v[0] / 500:.4f} at 500 r/min)")

    def to_json(self) -> dict:
        keys = {"natural_frequency": ("fn_factor",), "damping": ("zeta_factor",),
                "cutting_coefficient": ("kf_factor",), "second_mode": ("fn_hz", "zeta", "k_n_per_m", "theta_deg"),
                "process_damping": ("c_rpm",)}[self.name]
        d = {"effect": self.name, **{k: float(f"{x:.6g}") for k, x in zip(keys, self.values)}}
        if self.mode is not None:
            d["mode"] = self.mode + 1
        return d


class Fit:
    """Training cost of a model on cuts: misclassified cuts weighted by how
    costly and how far from the limit they are, plus the chatter-frequency
    misfit where frequencies were measured (the evidence a shifted or a
    missing mode leaves)."""

    def __init__(self, cuts: Cuts):
        self.cuts = cuts
        self.d = cuts.depth_mm * 1e-3
        # deeper limits change no verdict, and a chatter cut called right has its limit below it
        self.cap = 1.05 * float(self.d.max())
        self.fm = cuts.chatter_frequency_hz
        self.has_f = cuts.chatter & np.isfinite(self.fm)

    def __call__(self, model: StabilityModel) -> float:
        try:
            b, fp = model.limit(self.cuts.rpm, self.cap)
        except ValueError:
            return math.inf
        pred = self.d >= b
        obs = self.cuts.chatter
        dist = np.abs(np.log(self.d / np.where(np.isfinite(b), b, self.cap)))
        w = np.where(obs, FALSE_STABLE_WEIGHT, 1.0) * (1.0 + np.minimum(dist, 2.0) / 0.1)
        cost = float(np.sum(w[pred != obs]))
        if self.has_f.any():
            fm = self.fm[self.has_f]
            fpp = fp[self.has_f]
            rel = np.where(np.isfinite(fpp), np.abs(fm - fpp) / fm, 1.0)
            cost += 0.2 * float(np.sum(np.minimum(rel / 0.02, 5.0)))
        return cost


def search(cost: Callable[[StabilityModel], float], make: Callable[[float], Effect | None],
            base: StabilityModel, grid: np.ndarray, refine: int = 6) -> tuple[float, Effect | None]:
    """1-D grid search of one parameter, then a finer grid between the
    neighbours of the best point (the cost is piecewise constant in places,
    so no derivative is used)."""
    def val(x):
        e = make(x)
        return (math.inf, None) if e is None else (cost(e.apply(base)), e)
    scores = [val(x) for x in grid]
    i = int(np.argmin([s[0] for s in scores]))
    best = scores[i]
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    if refine and hi > lo:
        for x in np.geomspace(lo, hi, refine + 2)[1:-1]:
            s = val(x)
            if s[0] < best[0]:
                best = s
    return best


def relocations(base: StabilityModel, cuts: Cuts) -> list[float]:
    """Natural frequencies the chatter says a mode has where no mode of ``base`` is: one
    for each group of measured chatter frequencies that the model's modes and predicted
    chatter frequencies leave mostly unexplained."""
    out = []
    for g in frequency_groups(cuts):
        _, fp = base.limit(cuts.rpm[g])
        if np.mean(unexplained(base, cuts.chatter_frequency_hz[g], np.nan_to_num(fp))) > 0.5:
            out.append(mode_below(cuts.chatter_frequency_hz[g]))
    return out


def fit_candidates(base: StabilityModel, fit: Fit, have: set[str]) -> list[tuple[float, Effect]]:
    """Each candidate effect fitted on the training cuts: (cost, effect)."""
    out: list[tuple[float, Effect]] = []
    moves = relocations(base, fit.cuts)
    for i, mode in enumerate(base.modes):
        if f"natural_frequency{i}" not in have:
            grid = np.geomspace(0.8, 1.25, 23)
            # chatter where no mode is: the grid also reaches each such place within a factor 2
            # (a mode moved there is the simpler answer than a second mode beside it)
            far = [fn / mode.fn_hz for fn in moves if 0.5 <= fn / mode.fn_hz <= 2.0]
            grid = np.unique(np.r_[grid, *[x * np.geomspace(0.95, 1.05, 11) for x in far]])
            c, e = search(fit, lambda s, i=i: Effect("natural_frequency", (s,), i), base, grid)
            if e:
                out.append((c, e))
        if f"damping{i}" not in have:
            c, e = search(fit, lambda s, i=i: Effect("damping", (s,), i), base, np.geomspace(0.33, 3.0, 17))
            if e:
                out.append((c, e))
    if "cutting_coefficient" not in have:
        c, e = search(fit, lambda s: Effect("cutting_coefficient", (s,)), base, np.geomspace(0.33, 3.0, 23))
        if e:
            out.append((c, e))
    if "process_damping" not in have:
        # added damping ratio at the slowest cut from 1 % to 5x the lightest mode's own
        zmin = min(m.zeta for m in base.modes)
        n0 = float(np.percentile(fit.cuts.rpm, 10))
        c, e = search(fit, lambda a: Effect("process_damping", (a,)), base,
                       zmin * n0 * np.geomspace(0.01, 5.0, 15))
        if e:
            out.append((c, e))
    if "second_mode" not in have:
        e = _fit_second_mode(base, fit)
        if e is not None:
            out.append(e)
    return out


def _fit_second_mode(base: StabilityModel, fit: Fit) -> tuple[float, Effect] | None:
    """A mode placed from chatter frequencies no configured mode explains;
    without those there is no evidence for one and it is not proposed."""
    cuts = fit.cuts
    has = fit.has_f
    if has.sum() < 3:
        return None
    _, fp = base.limit(cuts.rpm[has])
    fm = cuts.chatter_frequency_hz[has]
    un = unexplained(base, fm, np.nan_to_num(fp))
    if un.sum() < 3:
        return None
    f0 = float(np.median(fm[un]))
    zeta, theta = 0.035, 0.0
    kf = base.kf
    b_ref = float(np.median(fit.d[cuts.chatter])) if cuts.chatter.any() else float(np.median(fit.d))
    # stiffness whose own b_lim,min = 2 k zeta (1 + zeta) / Kf spans the cut depths
    k_of = lambda b, z: b * kf / (2 * z * (1 + z))  # noqa: E731

    def mk(fn, z, k):
        return Effect("second_mode", (fn, z, k, theta)) if 0 < z < 1 and k > 0 and fn > 0 else None
    fn = f0 / 1.02
    c, e = search(fit, lambda k: mk(fn, zeta, k), base, k_of(b_ref, zeta) * np.geomspace(0.1, 3.0, 11))
    if e is None:
        return None
    k = e.values[2]
    # one pass of coordinate descent: frequency, damping (at the same depth), stiffness
    c, e1 = search(fit, lambda s: mk(fn * s, zeta, k), base, np.geomspace(0.9, 1.06, 9))
    fn = e1.values[0] if e1 else fn
    c, e1 = search(fit, lambda z: mk(fn, z, k * z / zeta), base, np.geomspace(0.01, 0.12, 7))
    if e1:
        k, zeta = e1.values[2], e1.values[1]
    c, e1 = search(fit, lambda s: mk(fn, zeta, k * s), base, np.geomspace(0.6, 1.6, 7))
    k = e1.values[2] if e1 else k
    e = mk(fn, zeta, k)
    return fit(e.apply(base)), e


def key(e: Effect) -> str:
    return e.name + ("" if e.mode is None else str(e.mode))


def compose(base: StabilityModel, effects: Sequence[Effect]) -> StabilityModel:
    m = base
    for e in effects:
        m = e.apply(m)
    return m
