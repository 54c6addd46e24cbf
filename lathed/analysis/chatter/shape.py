"""Has the spectrum of the revolution difference changed shape, or only its level?

A stable cut's vibration is the structure's answer to the cutting force's random part: a
deeper pass (a shoulder), a harder spot of the bar, the chip's own slow wander or a sensor's
gain all scale that force, and so the whole spectrum, by one factor.  Regenerative chatter adds
power in one narrow band near a structural mode.  So, band by band (bands ``REL_WIDTH`` of
their frequency wide, at least two FFT bins), the window's power over the baseline's: the
median of those ratios is the level change, and

    shape = sum(P) / (median(P / B) * sum(B))

is 1 for any change of level alone and grows with the power that is new in shape (docs/chatter.md).
Gain- and level-invariant; costs one FFT of a window.
"""
from __future__ import annotations

import math

import numpy as np

from lathed.analysis.chatter.spectrum import fast_len, hann, median, rfft

REL_WIDTH = 0.06      # a band's width over its centre frequency (a damped mode's peak spans 1-2)
MIN_BINS = 2          # ... and never under two FFT bins


class SpectralShape:
    """Band powers of windows, a baseline of them, and the shape index of a window against it."""

    def __init__(self, rate_hz: float, fmin_hz: float, fmax_hz: float) -> None:
        self.rate, self.fmin, self.fmax = float(rate_hz), max(float(fmin_hz), 1.0), float(fmax_hz)
        self._edges: dict[int, tuple[int, np.ndarray]] = {}    # window length -> (fft length, bin edges)
        self.reset()

    def reset(self) -> None:
        self._base: np.ndarray | None = None
        self._base_n = 0
        self._base_len: int | None = None     # the window length the baseline's bands are of
        self._now_len: int | None = None      # ... and the last window's (bands())
        self._moved: tuple[int, np.ndarray] | None = None   # the baseline spread onto a length's bands

    def bands(self, d: np.ndarray) -> np.ndarray:
        n = len(d)
        if n not in self._edges:
            nf = fast_len(n)
            df = self.rate / nf
            hi = min(self.fmax, self.rate / 2)
            edges, f = [int(math.ceil(self.fmin / df))], self.fmin
            while f < hi:
                f = max(f * (1 + REL_WIDTH), f + MIN_BINS * df)
                edges.append(min(int(round(f / df)), int(hi / df)))
            self._edges[n] = (nf, np.unique(np.asarray(edges)))
        nf, edges = self._edges[n]
        self._now_len = n
        # np.mean's sum and division without its wrapper, the window applied in place (the same
        # numbers, bit for bit)
        w = d - np.add.reduce(d) / n
        w *= hann(n)
        ps = np.abs(rfft(w, nf))
        ps *= ps                               # ** 2, in place
        return np.add.reduceat(ps, edges[:-1])[:len(edges) - 1]

    def _base_for(self, n: int) -> np.ndarray | None:
        """The baseline as bands of a window ``n`` long.  A new speed makes the windows (a
        number of revolutions) another length and the bands others: the baseline's power is
        spread over its bands' frequencies and summed into the new ones, in the new length's
        scale (a band's power grows with the square of the window's length).  Without this a
        cure's new speed had no shape to judge against, and chatter there raised no alarm."""
        b = self._base
        if b is None or self._base_len is None or n == self._base_len or n not in self._edges:
            return b
        if self._moved is not None and self._moved[0] == n:    # once per length, not per window
            return self._moved[1]
        nf0, e0 = self._edges[self._base_len]
        nf1, e1 = self._edges[n]
        f0 = e0[:len(b) + 1] * (self.rate / nf0)
        cum = np.concatenate(([0.0], np.cumsum(b)))
        f1 = e1 * (self.rate / nf1)
        moved = np.diff(np.interp(f1, f0, cum)) * (nf1 / nf0) ** 2
        self._moved = (n, moved)
        return moved

    def learn(self, bands: np.ndarray) -> None:
        """A stable window's bands: the baseline is their running mean (carried over to the
        bands of a new window length when the speed changes)."""
        n = self._now_len
        if self._base is not None and n != self._base_len:
            self._base = self._base_for(n)
        self._moved = None                     # the baseline changes below
        if self._base is None or len(bands) != len(self._base):
            self._base, self._base_n = np.zeros(len(bands)), 0
        self._base_len = n
        self._base_n += 1
        self._base += (bands - self._base) / self._base_n

    @property
    def learned(self) -> int:
        return self._base_n

    def index(self, bands: np.ndarray) -> float:
        """The shape index of these bands against the baseline (nan: none at this window length)."""
        b = self._base_for(self._now_len) if self._now_len is not None else self._base
        if b is None or len(bands) != len(b) or not self._base_n:
            return math.nan
        ok = b > 0
        if not ok.any():
            return math.nan
        p, q = bands[ok], b[ok]
        level = median(p / q)
        if not level > 0:
            return math.nan
        return float(np.add.reduce(p)) / (level * float(np.add.reduce(q)))
