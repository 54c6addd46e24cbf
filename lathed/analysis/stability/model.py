"""The stability model: the modal model of the lobes (lathed.analysis.lobes)
plus process damping, an added damping ratio ``process_damping / n`` on every
mode at spindle speed n (r/min; its force goes as 1/V, and a cut record has no
diameter).  The limit is found per speed, not per lobe, so that damping may
depend on speed: on a frequency grid, lobe k passes speed n where
f*60/n - eps(f)/(2 pi) = k; the limit is the lowest b(f) over those crossings
and the chatter frequency is its f.  See docs/stability.md.  Numeric only.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from lathed.analysis.cuts import Cuts
from lathed.analysis.lobes import B_CAP_FACTOR
from lathed.analysis.modal import Mode

@dataclass(frozen=True)
class StabilityModel:
    modes: tuple[Mode, ...]
    kf: float                           # N/m^2
    process_damping: float = 0.0        # r/min: added damping ratio = this / rpm

    def __post_init__(self) -> None:
        if not self.modes:
            raise ValueError("the stability model needs at least one structural mode")
        if not self.kf > 0:
            raise ValueError(f"cutting coefficient Kf must be > 0 N/m^2, got {self.kf}")
        if self.process_damping < 0:
            raise ValueError(f"process damping must be >= 0, got {self.process_damping}")
        if max(m.u for m in self.modes) < 1e-12:     # as StabilityLobes: cos(90 deg)**2 is not exactly 0
            raise ValueError("every mode is at 90 deg to the chip direction, so no regenerative chatter")

    def limit(self, rpm, b_cap_m: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Limiting depth (m) and chatter frequency (Hz) at each speed; inf/nan
        where no lobe lies below min(B_CAP_FACTOR * b_lim,min, b_cap_m)."""
        return limit_depth(self, np.atleast_1d(np.asarray(rpm, float)), b_cap_m)

    def b_lim_at(self, rpm) -> tuple[np.ndarray, np.ndarray]:
        """As StabilityLobes.b_lim_at, so speed selection (lathed.analysis.speed_selection)
        takes a refitted model, process damping and all, where it takes lobes."""
        return self.limit(rpm)

    def predict_chatter(self, cuts: Cuts, b_cap_m: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(chatter predicted, limit m, chatter frequency Hz) for each cut."""
        b, f = self.limit(cuts.rpm, b_cap_m)
        return cuts.depth_mm * 1e-3 >= b, b, f

    def to_json(self) -> dict:
        return {"modes": [{"fn_hz": round(m.fn_hz, 3), "zeta": round(m.zeta, 5), "k_n_per_m": float(f"{m.k_n_per_m:.5g}"),
                           "theta_deg": round(m.theta_deg, 3)} for m in self.modes],
                "kf_n_per_m2": float(f"{self.kf:.5g}"), "process_damping_rpm": round(self.process_damping, 4)}

    @classmethod
    def from_json(cls, d: dict) -> StabilityModel:
        """The inverse of to_json; ValueError/KeyError/TypeError on a malformed one."""
        modes = tuple(Mode(float(m["fn_hz"]), float(m["zeta"]), float(m["k_n_per_m"]), float(m.get("theta_deg", 0.0)))
                      for m in d["modes"])
        return cls(modes, float(d["kf_n_per_m2"]), float(d.get("process_damping_rpm", 0.0)))


def _grid(modes: Sequence[Mode]) -> np.ndarray:
    fns = [m.fn_hz for m in modes]
    zmin = min(m.zeta for m in modes)
    f_lo, f_hi = 0.3 * min(fns), 6.0 * max(fns)
    # as StabilityLobes: about 20 points per half-power band of the sharpest mode
    n = int(min(40_000, max(4000, math.log(f_hi / f_lo) / (zmin / 20))))
    return np.geomspace(f_lo, f_hi, n)


def _frf(modes: Sequence[Mode], f: np.ndarray, dzeta: np.ndarray | None) -> np.ndarray:
    """Oriented receptance; with ``dzeta`` (one per row) each row has that much
    more damping on every mode."""
    g = None
    for m in modes:
        if dzeta is None:
            h = m.u * m.frf(f)
        else:
            r = f[None, :] / m.fn_hz
            h = m.u / (m.k_n_per_m * (1 - r**2 + 2j * (m.zeta + dzeta[:, None]) * r))
        g = h if g is None else g + h         # not 0 + h: a pass over every speed and frequency
    return g


def limit_depth(model: StabilityModel, rpm: np.ndarray, b_cap_m: float | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    if not np.all(rpm > 0):
        raise ValueError("spindle speeds must be > 0 r/min")
    f_all = _grid(model.modes)
    g0 = _frf(model.modes, f_all, None)
    neg = g0.real < 0
    if not neg.any():
        raise ValueError("the oriented FRF has no negative real part: no regenerative chatter")
    b0 = np.full(len(f_all), np.inf)
    b0[neg] = -1.0 / (2 * model.kf * g0.real[neg])
    cap = B_CAP_FACTOR * float(b0.min())
    if b_cap_m is not None:
        cap = min(cap, b_cap_m)
    # added damping only lowers |Re G|, so the frequencies kept without it hold all with it
    keep = np.flatnonzero(b0 <= cap)
    out_b = np.full(len(rpm), np.inf)
    out_f = np.full(len(rpm), np.nan)
    if len(keep) < 2:
        return out_b, out_f
    f = f_all[keep]
    pair = np.diff(keep) == 1          # neighbours on the grid: a lobe runs between them
    chunk = max(1, 2_000_000 // len(f))   # speeds x frequencies per pass: a few MB
    for s in range(0, len(rpm), chunk):
        n = rpm[s:s + chunk]
        if model.process_damping > 0:
            g = _frf(model.modes, f, model.process_damping / n)
            re = g.real
            b = -1.0 / (2 * model.kf * np.minimum(re, -1e-300))
            b[~(re < 0) | (b > cap)] = np.inf
        else:
            g = g0[keep][None, :]
            b = np.broadcast_to(b0[keep][None, :], (len(n), len(f)))
        eps = 3 * np.pi + 2 * np.arctan2(g.imag, g.real)
        e = eps / (2 * np.pi)
        # the whole number of waves between passes, f*T - eps/(2 pi); in float32 for the
        # scan over all frequencies (it is at most a few thousand, its step between grid
        # neighbours about 0.1), recomputed in float64 where a lobe is found
        kk = np.multiply.outer((60.0 / n).astype(np.float32), f.astype(np.float32))
        kk -= e.astype(np.float32)
        fl = np.floor(kk)
        # a lobe passes between grid neighbours j, j+1 where that number changes
        # (kk > -1 since eps <= 2 pi, so the larger floor is a lobe number >= 0);
        # only those few entries per speed are interpolated
        r, j = np.divmod(np.flatnonzero(fl[:, :-1] != fl[:, 1:]), len(f) - 1)   # np.nonzero's, faster
        on = pair[j]
        r, j = r[on], j[on]
        er = r if e.shape[0] > 1 else np.zeros_like(r)
        k0 = f[j] * 60.0 / n[r] - e[er, j]
        k1 = f[j + 1] * 60.0 / n[r] - e[er, j + 1]
        m = np.maximum(np.floor(k0), np.floor(k1))
        on = np.floor(k0) != np.floor(k1)
        r, j, k0, k1, m = r[on], j[on], k0[on], k1[on], m[on]
        if not len(r):
            continue
        br = r if b.shape[0] > 1 else np.zeros_like(r)
        ba, bz = b[br, j], b[br, j + 1]
        with np.errstate(invalid="ignore"):
            t = np.clip((m - k0) / (k1 - k0), 0.0, 1.0)
            bc = ba + t * (bz - ba)
        bc[~np.isfinite(bc)] = np.inf
        fc = f[j] + t * (f[j + 1] - f[j])
        # lowest crossing per speed, the first of equals: r is in order (np.nonzero's), so each
        # speed's crossings are a run; its minimum, then the first entry equal to it (no sort)
        starts = np.flatnonzero(np.r_[True, r[1:] != r[:-1]])
        group = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(r)]))
        at_min = np.flatnonzero(bc == np.minimum.reduceat(bc, starts)[group])
        first = at_min[np.r_[True, group[at_min][1:] != group[at_min][:-1]]]
        rows = s + r[first]
        ok = np.isfinite(bc[first])
        out_b[rows[ok]] = bc[first][ok]
        out_f[rows[ok]] = fc[first][ok]
    return out_b, out_f
