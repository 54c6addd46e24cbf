"""Chatter or stable, from one steady stretch of vibration, without a reference (docs/chatter.md).

Regenerative chatter is a self-excited vibration near a structural mode, not synchronous with the
spindle, that dominates the broadband floor.  A stable cut is the structure's answer to the
cutting force's random part: Gaussian, broad, its level stationary; plus lines that are not
chatter (the spindle's harmonics: runout, imbalance, a flat's or a keyway's impulses; the mains'
multiples, 50 or 60 Hz and 100 or 120 Hz hum).  So, with the mains multiples and the spindle's
low harmonics notched out of the chatter band:

  share  the power within +-BAND_REL of the frequency where it concentrates most, over the
         band's: chatter dominates the floor (0.9-1.0 on the simulated cuts), a stable cut's
         strongest mode holds 0.2-0.7 of it
  cv     that band's envelope's coefficient of variation (its slow trend divided out): a
         Gaussian (stable) vibration's envelope is Rayleigh, cv 0.52; a self-excited
         oscillation's is steady, cv near 0 (0.05-0.2 on the simulated chatter above 1000 r/min)

"chatter": share >= CHATTER_SHARE, or a steady envelope (cv <= STEADY_CV) over a band holding at
least half the power, or a band that is a comb of narrow lines off the spindle's harmonics (comb.py)
whose lines rise and fall together (comb.lock, over at least MIN_CYCLES independent samples): one
oscillation modulated once a revolution, where a stable cut near its limit makes a comb too, but of
independent random lines (docs/chatter.md).  "stable": share <= STABLE_SHARE and a Gaussian
envelope (cv >= GAUSSIAN_CV).
Else "unknown", with the reason.  Both are ratios: the sensor's gain cancels.  The constants are
from the physics above and the simulated cuts (tests/test_verdict.py), none from a recording.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import uniform_filter1d

from lathed.analysis.chatter.comb import MIN_COMB_SHARE, find_comb, lock
from lathed.analysis.chatter.spectrum import fast_len

BAND_REL = 0.05        # the band judged: +-5 % of its frequency (a mode's peak, chatter's wander)
CHATTER_SHARE = 0.85   # chatter: the band holds this share of the power
STEADY_CV = 0.3        # ... or its envelope is this steady over a band holding half of it
STABLE_SHARE = 0.75    # stable: no band holds more than this (a stable cut's strongest mode: <= 0.72)
GAUSSIAN_CV = 0.35     # ... and its envelope varies as a Gaussian vibration's (0.42-0.69 simulated)
TREND_S = 0.5          # the envelope's slow trend (the cut's level changing) is divided out over this
SYNC_HARMONICS = 40    # spindle harmonics notched (beyond, a nominal speed is too coarse to place them)
SPEED_TOL = 0.005      # the spindle's speed known to +-0.5 % (a drive's regulation, a nominal value)
NOTCH_HZ = 0.3         # each notch +-(2.5 bins + this)
MIN_REVS = 4           # a verdict needs at least this many revolutions
MIN_CYCLES = 30        # ... and the band at least this many independent envelope values


@dataclass
class Verdict:
    verdict: str                    # "chatter" | "stable" | "unknown"
    reason: str
    frequency_hz: float | None      # where the power concentrates most
    share: float                    # the power within +-BAND_REL of it, over the band's
    cv: float                       # that band's envelope's coefficient of variation
    comb: str | None = None         # the band as a comb of narrow lines off the harmonics (comb.py), if it is

    def as_dict(self) -> dict:
        r = lambda v, n: None if v is None or not math.isfinite(v) else round(v, n)    # noqa: E731
        return {"verdict": self.verdict, "reason": self.reason, "frequency_hz": r(self.frequency_hz, 1),
                "share": r(self.share, 3), "cv": r(self.cv, 3), "comb": self.comb}


def judge(x: np.ndarray, rate_hz: float, rpm: float, mains_hz: tuple[float, ...] = (50.0, 60.0),
          fmin_hz: float = 50.0, fmax_hz: float = 5000.0) -> Verdict:
    """The verdict on a steady stretch ``x`` at ``rpm`` (see the module's docstring)."""
    x = np.asarray(x, dtype=float)
    n = len(x)
    revs = n / rate_hz * rpm / 60.0
    if revs < MIN_REVS:
        return Verdict("unknown", f"{revs:.1f} revolutions: too short to tell (at least {MIN_REVS})",
                       None, math.nan, math.nan)
    nf = fast_len(n)
    spec = np.fft.rfft(x - x.mean(), nf)
    f = np.arange(len(spec)) * rate_hz / nf
    use = (f >= fmin_hz) & (f <= min(fmax_hz, 0.45 * rate_hz))
    notch = 2.5 * f[1] + NOTCH_HZ
    for m in mains_hz:          # the mains' multiples are not chatter
        if m > 0:
            use &= np.abs(f - m * np.round(f / m)) > notch
    fs = rpm / 60.0             # nor are the spindle's harmonics
    k = np.round(f / fs)
    use &= ~((k >= 1) & (k <= SYNC_HARMONICS) & (np.abs(f - k * fs) <= notch + SPEED_TOL * k * fs))
    p = np.where(use, np.abs(spec) ** 2, 0.0)
    total = float(p.sum())
    if not total > 0:
        return Verdict("unknown", "no vibration in the chatter band", None, math.nan, math.nan)
    c = np.concatenate(([0.0], np.cumsum(p)))
    lo = np.searchsorted(f, f * (1 - BAND_REL))
    hi = np.searchsorted(f, f * (1 + BAND_REL), side="right")
    around = np.where(use, c[hi] - c[lo], 0.0)
    i = int(np.argmax(around))
    fc, share = float(f[i]), float(around[i]) / total
    band = use & (f >= fc * (1 - BAND_REL)) & (f <= fc * (1 + BAND_REL))
    cycles = 2 * BAND_REL * fc * n / rate_hz
    cv = _envelope_cv(spec, band, n, int(TREND_S * rate_hz))
    what = (f"{share:.0%} of the vibration's power lies within {BAND_REL:.0%} of {fc:.0f} Hz, "
            f"its envelope varying by {cv:.2f} of its mean")
    found = find_comb(x, rate_hz, rpm, fc * (1 - BAND_REL), fc * (1 + BAND_REL), mains_hz)
    comb = None
    if found and found.off_harmonic and found.share >= MIN_COMB_SHARE:
        comb = (f"{found.describe()}: regeneration's comb (chatter modulated once a revolution, or a stable "
                "cut near its limit)")
        lk = lock(x, rate_hz, found)
        if lk is not None and lk.samples >= MIN_CYCLES:
            comb = f"{comb}; {lk.describe() if lk.locked else 'its lines vary independently, as random ones do'}"
            if lk.locked and share < CHATTER_SHARE:
                return Verdict("chatter", f"{what}; the band is {found.describe()}, and {lk.describe()}: one "
                               "oscillation modulated once a revolution, self-excited", fc, share, cv, comb)
    if share >= CHATTER_SHARE or (share >= 0.5 and cv <= STEADY_CV and cycles >= MIN_CYCLES):
        return Verdict("chatter", f"{what}: a self-excited vibration that dominates the floor", fc, share, cv, comb)
    if cycles < MIN_CYCLES:
        return Verdict("unknown", f"{what}: too few cycles of that band to tell ({cycles:.0f})", fc, share, cv, comb)
    if share <= STABLE_SHARE and cv >= GAUSSIAN_CV:
        return Verdict("stable", f"{what}: broadband and Gaussian, as a stable cut's", fc, share, cv, comb)
    why = ("it dominates but its envelope varies as a random vibration's" if share > STABLE_SHARE
           else "its envelope is steadier than a random vibration's, yet it does not dominate")
    return Verdict("unknown", f"{what}: {why}", fc, share, cv, comb)


def _envelope_cv(spec: np.ndarray, band: np.ndarray, n: int, trend: int) -> float:
    """The band's analytic envelope's coefficient of variation, its slow trend divided out."""
    nf = 2 * (len(spec) - 1) if len(spec) > 1 else n
    a = np.zeros(nf, dtype=complex)
    a[:len(spec)][band] = 2.0 * spec[band]
    env = np.abs(np.fft.ifft(a)[:n])
    if n > 3 * trend > 0:
        # the moving mean as a running sum: np.convolve's direct sum took 11 s on a 20 s recording
        tr = uniform_filter1d(env, trend)
        e = env[trend:-trend] / np.maximum(tr[trend:-trend], 1e-300)
    else:
        e = env / max(float(env.mean()), 1e-300)
    m = float(e.mean())
    return float(e.std() / m) if m > 0 else math.nan
