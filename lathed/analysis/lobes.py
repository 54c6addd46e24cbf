"""Stability lobes for orthogonal turning (Tlusty/Merritt, one chip direction).

The regenerative chip thickness is h(t) = h0 - y(t) + y(t - T); with the
oriented receptance G(w) along the chip direction (lathed.analysis.modal) the
characteristic equation 1 + Kf*b*(1 - exp(-iwT))*G(iw) = 0 gives, for every
chatter frequency w with Re G(w) < 0,

    b_lim(w) = -1 / (2*Kf*Re G(w))
    w*T = eps + 2*pi*k,   eps = 3*pi + 2*atan2(Im G, Re G)   (lobe k = 0, 1, ...)
    n = 60 / T  [r/min]

so each lobe is a curve (n_k(w), b_lim(w)) parameterised by w.  One mode has the
closed form b_lim,min = 2*k*zeta*(1+zeta)/Kf (tests check it).  Pure numpy;
no asyncio, so the daemon, the CLI and the benches share it.
"""
from __future__ import annotations

import cmath
import math
from dataclasses import dataclass

import numpy as np

from lathed.analysis.modal import Mode, oriented_frf

# Lobe branches are cut where b_lim exceeds this multiple of b_lim,min: beyond
# it the depth is far outside anything a lathe takes, and keeping the far
# tails would only multiply the number of lobes to scan at low speed.
B_CAP_FACTOR = 100.0


@dataclass(frozen=True)
class Lobe:
    k: int                  # number of whole waves between passes
    rpm: np.ndarray         # spindle speed along the lobe, ascending chatter frequency
    b_lim_m: np.ndarray     # limiting depth of cut (m)
    chatter_hz: np.ndarray  # chatter frequency at that point


class StabilityLobes:
    """Stability lobe diagram of one turning set-up (modes + cutting coefficient).

    ``kf_n_per_m2`` is the cutting-force coefficient along the chip-thickness
    direction (force = Kf * depth * chip thickness).
    """

    def __init__(self, modes: list[Mode] | tuple[Mode, ...], kf_n_per_m2: float) -> None:
        if not modes:
            raise ValueError("stability lobes need at least one structural mode")
        if not kf_n_per_m2 > 0:
            raise ValueError(f"cutting coefficient Kf must be > 0 N/m^2, got {kf_n_per_m2}")
        self.modes = tuple(modes)
        self.kf = float(kf_n_per_m2)

        fns = [m.fn_hz for m in self.modes]
        zmin = min(m.zeta for m in self.modes)
        f_lo, f_hi = 0.3 * min(fns), 6.0 * max(fns)
        # Resolve the narrowest resonance: about 20 points per half-power band.
        n = int(min(400_000, max(4000, math.log(f_hi / f_lo) / (zmin / 20))))
        f = np.geomspace(f_lo, f_hi, n)
        g = oriented_frf(self.modes, f)

        # Critical (minimum) depth: refine the grid minimum of Re G.
        i = int(np.argmin(g.real))
        if not g.real[i] < 0 or max(m.u for m in self.modes) < 1e-12:
            raise ValueError("the oriented FRF has no negative real part: every mode is "
                             "at 90 deg to the chip direction, so no regenerative chatter")
        lo, hi = f[max(i - 1, 0)], f[min(i + 1, n - 1)]
        # two zooms of a dense grid: Re G is smooth and flat at its minimum, so
        # this is as exact as a scalar minimiser (and spares importing scipy.optimize)
        for _ in range(2):
            ff = np.linspace(lo, hi, 2001)
            gr = np.real(oriented_frf(self.modes, ff))
            j = int(np.argmin(gr))
            lo, hi = ff[max(j - 1, 0)], ff[min(j + 1, len(ff) - 1)]
        fc = float(ff[j]) if gr[j] < g.real[i] else float(f[i])
        re_min = min(float(gr[j]), float(g.real[i]))
        self.b_lim_min_m = -1.0 / (2 * self.kf * re_min)
        self.chatter_frequency_hz = fc

        keep = g.real < 0
        b = np.full(n, np.inf)
        b[keep] = -1.0 / (2 * self.kf * g.real[keep])
        keep &= b <= B_CAP_FACTOR * self.b_lim_min_m
        self._f = f
        self._b = b
        # eps in (pi, 2*pi] wherever Re G < 0
        self._eps = 3 * np.pi + 2 * np.arctan2(g.imag, g.real)
        self._keep = keep
        # contiguous runs of usable frequencies
        edges = np.flatnonzero(np.diff(np.r_[0, keep.astype(np.int8), 0]))
        self._runs = list(zip(edges[0::2], edges[1::2]))

    # -- lobes ---------------------------------------------------------------
    def _k_range(self, rpm_min: float, rpm_max: float) -> range:
        """Lobe numbers whose curve can reach into [rpm_min, rpm_max]."""
        fk = self._f[self._keep]
        ek = self._eps[self._keep] / (2 * np.pi)
        # n_k = 60 f / (eps/2pi + k): lobe k spans [min, max] of that over f
        k_lo = max(0, int(math.floor(60 * fk.min() / rpm_max - ek.max())))
        k_hi = int(math.ceil(60 * fk.max() / rpm_min - ek.min()))
        return range(k_lo, max(k_lo, k_hi) + 1)

    def lobe(self, k: int) -> list[Lobe]:
        """Lobe k, one piece per frequency band where chatter is possible."""
        out = []
        for a, z in self._runs:
            f = self._f[a:z]
            rpm = 60 * 2 * np.pi * f / (self._eps[a:z] + 2 * np.pi * k)
            out.append(Lobe(k, rpm, self._b[a:z], f))
        return out

    def lobes(self, rpm_min: float, rpm_max: float) -> list[Lobe]:
        """All lobe pieces that enter [rpm_min, rpm_max], clipped to it."""
        if not 0 < rpm_min < rpm_max:
            raise ValueError(f"speed range must satisfy 0 < min < max, got {rpm_min}:{rpm_max}")
        out = []
        for k in self._k_range(rpm_min, rpm_max):
            for piece in self.lobe(k):
                sel = (piece.rpm >= rpm_min) & (piece.rpm <= rpm_max)
                if sel.any():
                    out.append(Lobe(k, piece.rpm[sel], piece.b_lim_m[sel], piece.chatter_hz[sel]))
        return out

    # -- queries ---------------------------------------------------------------
    def b_lim_at(self, rpm: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Limiting depth (m) and the chatter frequency (Hz) it would have, at
        each speed: the lowest of all lobe branches over that speed.  ``inf``
        where no branch lies below B_CAP_FACTOR * b_lim,min."""
        n = np.atleast_1d(np.asarray(rpm, dtype=float))
        if not np.all(n > 0):
            raise ValueError("spindle speeds must be > 0 r/min")
        best_b = np.full(n.shape, np.inf)
        best_f = np.full(n.shape, np.nan)
        for k in self._k_range(float(n.min()), float(n.max())):
            for piece in self.lobe(k):
                # split into monotone stretches of speed so np.interp applies
                d = np.sign(np.diff(piece.rpm))
                cuts = np.flatnonzero(d[1:] != d[:-1]) + 1
                bounds = np.r_[0, cuts, len(piece.rpm) - 1]
                for s, e in zip(bounds[:-1], bounds[1:]):
                    r = piece.rpm[s:e + 1]
                    if r[0] > r[-1]:
                        r = r[::-1]
                        bb, ff = piece.b_lim_m[s:e + 1][::-1], piece.chatter_hz[s:e + 1][::-1]
                    else:
                        bb, ff = piece.b_lim_m[s:e + 1], piece.chatter_hz[s:e + 1]
                    inside = (n >= r[0]) & (n <= r[-1])
                    if not inside.any():
                        continue
                    b_here = np.interp(n[inside], r, bb)
                    f_here = np.interp(n[inside], r, ff)
                    better = b_here < best_b[inside]
                    idx = np.flatnonzero(inside)[better]
                    best_b[idx] = b_here[better]
                    best_f[idx] = f_here[better]
        return best_b, best_f

    def growth(self, rpm: float, depth_m: float) -> tuple[float, float]:
        """The rightmost root s = sigma + i*2*pi*f of the characteristic equation
        1 + Kf*b*(1 - exp(-sT))*G(s) = 0 at this speed and depth: (sigma in 1/s, f in Hz).
        Chatter's amplitude grows as exp(sigma*t), by exp(sigma*60/rpm) a revolution;
        sigma crosses 0 at b_lim.  Newton's method from a grid a third of the spindle
        frequency apart over each mode's band (the roots near a mode are about one
        spindle frequency apart)."""
        if not rpm > 0 or not depth_m > 0:
            raise ValueError(f"growth needs a speed and a depth > 0, got {rpm} r/min, {depth_m} m")
        T = 60.0 / rpm
        m = [(md.u, md.mass_kg, 2 * md.zeta * md.wn * md.mass_kg, md.k_n_per_m) for md in self.modes]
        g = self.kf * depth_m

        def f_df(s: complex) -> tuple[complex, complex, float]:
            """F, F' and the size of F's regenerative term (F's own scale near a pole)."""
            den = [mm * s * s + c * s + k for _, mm, c, k in m]
            phi = sum(u / d for (u, *_), d in zip(m, den))
            dphi = -sum(u * (2 * mm * s + c) / d**2 for (u, mm, c, _), d in zip(m, den))
            e = cmath.exp(-s * T)
            loop = g * (1 - e) * phi
            return 1 + loop, g * (T * e * phi + (1 - e) * dphi), abs(loop)

        best: complex | None = None
        for md in self.modes:
            # a third of the spindle frequency apart, but at most 400 starts a mode (slow spindles)
            step = min(max(rpm / 60.0 / 3.0, 0.002 * md.fn_hz), 0.02 * md.fn_hz)
            # and the mode's pole moved by a shallow cut (first order: Phi ~ R / (s - p)), where
            # a grid start would fall outside Newton's narrow basin
            wd = md.wn * math.sqrt(1 - md.zeta**2)
            p = complex(-md.zeta * md.wn, wd)
            near = ([p - g * (1 - cmath.exp(-p * T)) * md.u / (md.mass_kg * 2j * wd)]
                    if -p.real * T < 600 else [])
            # a slow spindle's roots crowd the axis (within a few 1/T): start there, not at the pole's
            sigma0 = -min(md.zeta * md.wn, 3.0 / T)
            for s in [*near, *(complex(sigma0, 2 * math.pi * f0)
                              for f0 in np.arange(0.7 * md.fn_hz, 1.5 * md.fn_hz, step))]:
                for _ in range(50):
                    # far into the left half-plane exp(-sT) overflows: no root we want there
                    if not (-s.real * T < 600 and abs(s.real) < 10 * md.wn):
                        s = complex(math.nan, 0.0)
                        break
                    f, df, _ = f_df(s)
                    if df == 0:
                        break
                    ds = f / df
                    s -= ds
                    if abs(ds) < 1e-9 * abs(s):
                        break
                if not s.imag > 0 or not -s.real * T < 600:
                    continue
                f, _, scale = f_df(s)
                if abs(f) < 1e-6 * (1 + scale) and (best is None or s.real > best.real):
                    best = s
        if best is None:
            raise ArithmeticError(f"no characteristic root found at {rpm:g} r/min, {depth_m * 1e3:g} mm")
        return float(best.real), float(best.imag / (2 * math.pi))

    def is_stable(self, rpm: np.ndarray | float, depth_m: float, margin: float = 1.0) -> np.ndarray:
        """True where ``depth_m * margin`` is below the limiting depth."""
        b, _ = self.b_lim_at(rpm)
        return depth_m * margin < b
