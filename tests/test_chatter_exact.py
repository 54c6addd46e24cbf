"""The chatter path's shortcuts against the plain numpy they replace (issue 37: a channel's cost,
bench/bench_channel_path.py): the same numbers, bit for bit, and the same windows."""
from __future__ import annotations

import math

import numpy as np

from lathed.analysis.chatter.detectors import SyncCusumDetector
from lathed.analysis.chatter.registry import make_detector
from lathed.analysis.chatter.shape import SpectralShape
from lathed.analysis.chatter.spectrum import fast_len, median, median_abs, spectral_peak_hz
from lathed.analysis.regen import Segment, simulate_cut

RATE = 51200.0


def test_the_medians_are_np_median_bit_for_bit():
    rng = np.random.default_rng(1)
    for n in list(range(1, 90)) * 10:
        a = rng.normal(size=n) * rng.choice([1e-6, 1.0, 1e6])
        if rng.random() < 0.3:
            a = np.round(a, 1)                      # ties
        if rng.random() < 0.1:
            a[rng.integers(n)] = np.nan
        want, got = np.median(a), median(a.copy())
        assert want == got or (math.isnan(want) and math.isnan(got)), (n, want, got)
        if not np.isnan(a).any():
            assert median_abs(a) == np.median(np.abs(a)), n
    assert math.isnan(median(np.empty(0)))
    for n in (1024, 1229, 2048):                   # a window's raw measure
        d = rng.normal(size=n)
        assert median_abs(d) == np.median(np.abs(d))


def _peak(x, rate, fmin, fmax):
    """spectral_peak_hz as it was: the whole spectrum, np.hanning at each call."""
    n = len(x)
    if n < 8:
        return None
    nf = fast_len(n)
    spec = np.abs(np.fft.rfft(x * np.hanning(n), nf))
    f = np.arange(len(spec)) * rate / nf
    band = np.flatnonzero((f >= fmin) & (f <= min(fmax, rate / 2)))
    if band.size < 3:
        return None
    i = int(band[np.argmax(spec[band])])
    if 0 < i < len(spec) - 1:
        a, b, c = np.log(spec[i - 1:i + 2] + 1e-300)
        den = a - 2 * b + c
        off = 0.5 * (a - c) / den if den < 0 else 0.0
        return float((i + off) * rate / nf)
    return float(f[i])


def test_the_chatter_frequency_is_the_plain_formulas():
    rng = np.random.default_rng(3)
    for _ in range(400):
        n = int(rng.integers(4, 3000))
        x = rng.normal(size=n) + 5 * np.sin(2 * np.pi * rng.uniform(0, 26000) * np.arange(n) / 51200)
        rate = float(rng.choice([51200.0, 48000.0, 1000.0]))
        fmin, fmax = float(rng.choice([0.0, 50.0, 24000.0])), float(rng.choice([100.0, 5000.0, 25600.0]))
        assert spectral_peak_hz(x, rate, fmin, fmax) == _peak(x, rate, fmin, fmax), (n, rate, fmin, fmax)


def test_band_powers_are_the_plain_formulas():
    rng = np.random.default_rng(4)
    shape = SpectralShape(RATE, 50.0, 5000.0)
    for n in (512, 1024, 1229, 2048, 3001):
        d = rng.normal(size=n)
        got = shape.bands(d)
        nf, edges = shape._edges[n]
        ps = np.abs(np.fft.rfft((d - d.mean()) * np.hanning(n), nf)) ** 2
        assert np.array_equal(got, np.add.reduceat(ps, edges[:-1])[:len(edges) - 1])


class _Eager(SyncCusumDetector):
    """The shape index made afresh at the start of every window the rules judge, from the plain
    band powers, as it always was: the gate then reads it."""

    def _level_step(self, start, end, rpm):
        self.shape, self._made = self._shape.index(self._shape.bands(self._d[start:end])), True
        return super()._level_step(start, end, rpm)


def _windows(det, x, rpm, block=1024):
    return [w for i in range(0, len(x), block) for w in det.process(x[i:i + block], rpm)]


def _judged(wins):
    return [(w.t_s, w.index, w.alarm, w.chatter_frequency_hz, w.raised_by, w.judged) for w in wins]


def test_the_shape_made_when_the_gate_needs_it_judges_as_the_one_made_at_once():
    cuts = [([Segment(0.6, 1500, 1.0), Segment(0.8, 1500, 3.0)], 21),          # chatter from mid-cut
            ([Segment(1.0, 2000, 1.0), Segment(1.5, 2000, 1.8)], 5),           # a deeper pass
            ([Segment(2.0, 1000, 1.2)], 1001)]                                  # a stable cut
    made = 0
    for segs, seed in cuts:
        rec = simulate_cut(segs, seed=seed)
        rpm = float(segs[0].rpm)
        lazy = _windows(make_detector("sync_cusum", RATE), rec.signal, rpm)
        eager = _windows(_Eager(RATE), rec.signal, rpm)
        assert _judged(lazy) == _judged(eager), seed
        for a, b in zip(lazy, eager):
            assert math.isnan(a.shape) or a.shape == b.shape
        made += sum(not math.isnan(w.shape) for w in lazy)
    assert made > 0       # the gate looked, somewhere


def test_a_reset_detector_judges_as_a_fresh_one():
    """What a window keeps for the next (levels, the pair of them) goes with the cut: sample
    counts restart at a reset, so a short cut's last window stands where the next cut's first
    judged one does (at 3000 r/min: windows of 1024 samples every 512, the fifth, the first past
    the learning, ends at sample 4098), and there the next cut's level steps 5 x."""
    rng = np.random.default_rng(8)
    rpm = 3000.0
    short = rng.normal(size=4100)                             # five windows, the last judged
    cut = rng.normal(size=int(RATE * 0.3))
    cut[3074:] *= 5.0
    used = make_detector("sync_cusum", RATE)
    assert len(used.process(short, rpm)) == 5
    used.reset()
    fresh = _windows(make_detector("sync_cusum", RATE), cut, rpm)
    assert _judged(_windows(used, cut, rpm)) == _judged(fresh)
    assert fresh[4].t_s * RATE == 4098 and not fresh[4].judged     # the step, not judged
