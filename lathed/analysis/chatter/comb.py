"""Is the dominant band a comb of narrow lines off the spindle's harmonics, and are its lines one
oscillation? (docs/chatter.md)

Below about 1000 r/min regenerative chatter leaves the cut for part of every revolution, so its
vibration is modulated once a revolution: the chatter frequency fc = (k + eps) f_rev shows as a
comb of narrow lines fc + m f_rev, all at the same non-zero offset eps from the spindle's
harmonics.  A stable cut's forced lines (runout, a flat's or a keyway's impulses) sit on
k f_rev (eps = 0).  But regeneration also makes a stable cut near its limit a comb between the
harmonics (the delay term vanishes on them), so a comb alone does not decide.  What does: in a
stable cut each line is a regenerative resonance driven by the cutting force's random part, its own
narrow-band Gaussian vibration, independent of the others (they are driven by disjoint parts of the
force's spectrum); chatter's lines are one self-excited oscillation modulated once a revolution, so
they rise and fall together (``lock``).  The spacing is fitted, within SLIP of the nominal rate
(simulated combs, at exact speed, are spaced 0.95-0.97 x it).

The constants are statistics or physics; NARROW was widened after seeing c_770_005 (its lines
wander +-1.3 Hz over 22 s; docs/chatter.md says so):
  LINE_FALSE     a line must stand over the band's median power, and over the median of its own
                 neighbourhood (+-0.4 of a spacing: a smooth random peak is its own floor), by as
                 much as a Gaussian vibration's periodogram bin (chi-square, 2 degrees of freedom:
                 P(x > a median) = 2**-a) reaches with this probability over the whole band
  NARROW         a line holds most of the power within +-0.4 of a spacing around it within +-0.1
                 of a spacing (a flat floor holds a quarter there, a broad mode's peak little more;
                 a line's width is its frequency's wander with the spindle's speed, not a bin)
  SLIP           the spindle's true speed within this fraction of its nominal one
  SIGMAS         the offset must stand this many standard errors from a harmonic, the error
                 propagated from the frequency resolution (a bin's width / sqrt(12) per line)
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import ndtri     # scipy.stats (norm.isf is -ndtri) costs a second to import

from lathed.analysis.chatter.spectrum import fast_len

LINE_FALSE = 0.01     # chance of one false line in the band from a Gaussian floor
NARROW = 0.1          # a line: at least half its neighbourhood's power within +-0.1 spacing of its peak
MIN_LINES = 3         # a comb: the carrier and two sidebands
MIN_COMB_SHARE = 0.5  # ... whose lines hold most of the band's power (the band *is* the comb)
SLIP = 0.05           # a loaded spindle's speed within 5 % of its nominal
SIGMAS = 3.0
MIN_SPACING_BINS = 8  # the spacing must span this many bins to tell lines from the floor between
LOCK_FALSE = 0.001    # chance that two independent random lines read as one oscillation's (lock)
# two independent Gaussian lines: log|a| of each has variance pi^2 / 24 (log of a Rayleigh), so the
# log of their amplitudes' ratio has standard deviation pi / sqrt(12); its sample value over n
# independent samples spreads by LOG_SD_SPREAD / sqrt(n) of it (the difference's excess kurtosis 1.2:
# sqrt(2 + 1.2) / 2); a Monte Carlo of white noise spreads less (conservative)
INDEPENDENT_SD = math.pi / math.sqrt(12.0)
LOG_SD_SPREAD = math.sqrt(3.2) / 2.0


@dataclass
class Comb:
    lines_hz: list[float]       # the comb's lines, strongest first
    spacing_hz: float           # their spacing: the true revolution rate
    offset: float               # the carrier's offset from the spindle's harmonics, in spacings (0..1)
    margin: float               # how far from 0 and 1 the offset must be (SIGMAS standard errors)
    share: float                # the lines' power over the band's

    @property
    def off_harmonic(self) -> bool:
        return self.margin < 0.5 and self.margin < self.offset < 1.0 - self.margin

    def describe(self) -> str:
        return (f"{len(self.lines_hz)} narrow lines ({self.share:.0%} of the band's power) spaced "
                f"{self.spacing_hz:.3f} Hz ({60 * self.spacing_hz:.0f} r/min), at {self.offset:.2f} of a "
                f"spacing off the spindle's harmonics (+-{self.margin:.2f} resolvable)")


def find_comb(x: np.ndarray, rate_hz: float, rpm: float, f_lo: float, f_hi: float,
              exclude_hz: tuple[float, ...] = ()) -> Comb | None:
    """The comb of narrow lines spaced near ``rpm``/60 in f_lo..f_hi, or None (no comb there).
    ``exclude_hz``: line frequencies that are not the process's (the mains' multiples' base)."""
    x = np.asarray(x, dtype=float)
    n = len(x)
    nf = fast_len(n)
    p = np.abs(np.fft.rfft((x - x.mean()) * np.hanning(n), nf)) ** 2
    df = rate_hz / nf
    fr = rpm / 60.0
    if fr * (1 - SLIP) < MIN_SPACING_BINS * df:
        return None
    i0, i1 = int(math.ceil(f_lo / df)), min(int(f_hi / df), len(p) - 2)
    if i1 - i0 < 3 * fr / df:
        return None
    band = p[i0:i1 + 1]
    floor = float(np.median(band))
    total = float(band.sum())
    if not floor > 0:
        return None
    snr = math.log2(len(band) / LINE_FALSE)
    h = int(0.4 * fr * (1 - SLIP) / df)
    nb = max(int(NARROW * fr * (1 - SLIP) / df), 2)
    lines: list[tuple[float, float, float]] = []    # (power near the line, frequency, neighbourhood power)
    for j in np.flatnonzero(band > snr * floor):
        i = i0 + int(j)
        a, b = max(i - h, 0), min(i + h + 1, len(p))
        if p[i] < p[a:b].max():
            continue                                 # not the highest within its neighbourhood
        if p[i] <= snr * float(np.median(p[a:b])):
            continue                                 # a random peak's top: no line over its own floor
        if any(m > 0 and abs(i * df - m * round(i * df / m)) <= nb * df for m in exclude_hz):
            continue
        near = float(p[i - nb:i + nb + 1].sum())
        if near < 0.5 * float(p[a:b].sum()):
            continue                                 # a broad peak, not a line
        # the peak refined by a parabola through the log power (a Hann window's lobe)
        y0, y1, y2 = np.log(p[i - 1:i + 2])
        den = y0 - 2 * y1 + y2
        d = 0.5 * (y0 - y2) / den if den < 0 else 0.0
        lines.append((near, (i + d) * df, float(p[a:b].sum())))
    if len(lines) < MIN_LINES:
        return None
    lines.sort(reverse=True)
    f0 = lines[0][1]
    # spacing: least squares through the strongest line, each line a whole number of spacings off
    m = np.array([round((f - f0) / fr) for _, f, _ in lines])
    f = np.array([f for _, f, _ in lines])
    keep = np.ones(len(m), bool)
    seen: set[int] = set()
    for i, mi in enumerate(m):                      # one line per comb position (the strongest)
        keep[i] = mi not in seen
        seen.add(int(mi))
    m, f = m[keep], f[keep]
    w = [ln for ln, k in zip(lines, keep) if k]
    if len(m) < MIN_LINES or not (m != 0).any():
        return None
    s = float(np.sum(m * (f - f0)) / np.sum(m * m))
    if abs(s / fr - 1.0) > SLIP:
        return None
    on = np.abs(f - f0 - m * s) <= 2 * df           # lines on the comb, to within the resolution
    if on.sum() < MIN_LINES:
        return None
    m, f = m[on], f[on]
    s = float(np.sum(m * (f - f0)) / np.sum(m * m))
    share = sum(ln[0] for ln, o in zip(w, on) if o) / total
    carrier = float(np.mean(f - m * s))             # the carrier's frequency from all the lines
    q = carrier / s
    offset = q - math.floor(q)
    # standard errors from the resolution: a line's frequency to df / sqrt(12)
    sf = df / math.sqrt(12.0)
    s_err = sf / math.sqrt(float(np.sum(m * m)))
    q_err = math.hypot(sf / math.sqrt(len(m)) / s, q * s_err / s)
    return Comb([float(v) for v in f], s, offset, SIGMAS * q_err, share)


@dataclass
class Lock:
    sd: float           # the standard deviation of log(|a1| / |a0|), the two strongest lines' amplitudes
    bound: float        # two independent random lines stay above this but with chance LOCK_FALSE
    samples: float      # independent samples of the lines' amplitudes (each band's width x the duration)
    half_hz: float      # each line's band: +- this (half the way to the nearest harmonic or line)

    @property
    def locked(self) -> bool:
        return self.sd < self.bound

    def describe(self) -> str:
        return (f"its two strongest lines rise and fall together (the log of their amplitudes' ratio varies "
                f"by {self.sd:.2f}; independent random lines' by {INDEPENDENT_SD:.2f}, above {self.bound:.2f} "
                f"but with chance {LOCK_FALSE:g} over {self.samples:.0f} independent samples)")


def lock(x: np.ndarray, rate_hz: float, comb: Comb) -> Lock | None:
    """Do the comb's two strongest lines rise and fall together, as one oscillation modulated once a
    revolution does, or independently, as a stable cut's regenerative resonances do?  Each line is
    band-passed over +- half the way to the nearest other line (a spindle harmonic at ``offset``
    spacings, or the comb's next line), and the log of their amplitudes' ratio is compared with
    what two independent Gaussian lines give.  The ratio cancels the sensor's gain and the cut's
    common wander.  None where the comb has fewer than two lines."""
    if len(comb.lines_hz) < 2:
        return None
    x = np.asarray(x, dtype=float)
    n = len(x)
    half = 0.5 * min(comb.offset, 1.0 - comb.offset, 1.0) * comb.spacing_hz
    nf = fast_len(n)
    spec = np.fft.rfft(x - x.mean(), nf)
    f = np.arange(len(spec)) * rate_hz / nf
    edge = int(rate_hz / half) if half > 0 else n      # the band's own ring, two correlation times
    if not half > 0 or n <= 4 * edge:
        return None
    amp = []
    for f0 in comb.lines_hz[:2]:
        a = np.zeros(nf, dtype=complex)
        band = np.abs(f - f0) <= half
        a[:len(spec)][band] = 2.0 * spec[band]
        amp.append(np.abs(np.fft.ifft(a)[edge:n - edge]))
    if not (amp[0] > 0).all() or not (amp[1] > 0).all():
        return None
    sd = float(np.std(np.log(amp[1]) - np.log(amp[0])))
    samples = 2.0 * half * (n - 2 * edge) / rate_hz
    bound = INDEPENDENT_SD * (1.0 - float(-ndtri(LOCK_FALSE)) * LOG_SD_SPREAD / math.sqrt(samples))
    return Lock(sd, bound, samples, half)
