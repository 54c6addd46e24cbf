"""The verdict without a reference (lathed.analysis.chatter.verdict) on simulated steady cuts, and
the spectral shape gate (lathed.analysis.chatter.shape)."""
from __future__ import annotations

import numpy as np
import pytest

from lathed.analysis.chatter.cases import b_lim_mm
from lathed.analysis.chatter.comb import Comb, find_comb, lock
from lathed.analysis.chatter.shape import SpectralShape
from lathed.analysis.chatter.verdict import judge
from lathed.analysis.regen import Segment, simulate_cut


def _steady(rpm: float, share: float, seed: int, skip_s: float = 1.0, **kw) -> tuple[np.ndarray, float]:
    rec = simulate_cut([Segment(skip_s + 1.5, rpm, round(share * b_lim_mm(rpm), 2))], seed=seed, **kw)
    return rec.signal[int(skip_s * rec.rate_hz):], rec.rate_hz


@pytest.mark.parametrize("rpm", [1000.0, 3000.0])
def test_a_steady_stable_cut_is_stable(rpm):
    x, rate = _steady(rpm, 0.6, 41)
    v = judge(x, rate, rpm)
    assert v.verdict == "stable", v.reason


@pytest.mark.parametrize("rpm", [2000.0, 3000.0])
def test_steady_chatter_is_chatter_from_its_first_sample(rpm):
    x, rate = _steady(rpm, 1.6, 42)
    v = judge(x, rate, rpm)
    assert v.verdict == "chatter" and 600 < v.frequency_hz < 700, v.reason


def test_a_mains_line_is_not_chatter():
    # a stable cut with 60 Hz mains hum at 3 x its level, at 120 Hz and its harmonics: the hum
    # would dominate any band were it not the mains'
    x, rate = _steady(1000.0, 0.6, 43)
    t = np.arange(len(x)) / rate
    hum = 3 * np.median(np.abs(x)) / 0.67 * (np.sin(2 * np.pi * 120 * t) + 0.5 * np.sin(2 * np.pi * 240 * t))
    assert judge(x + hum, rate, 1000.0, mains_hz=(60.0,)).verdict == "stable"
    assert judge(x + hum, rate, 1000.0, mains_hz=(50.0,)).verdict != "stable"     # the wrong mains


def test_the_verdict_does_not_depend_on_the_gain():
    x, rate = _steady(2000.0, 1.6, 42)
    a, b = judge(x, rate, 2000.0), judge(1e-3 * x, rate, 2000.0)
    assert (a.verdict, round(a.share, 6), round(a.cv, 6)) == (b.verdict, round(b.share, 6), round(b.cv, 6))


def test_too_short_is_unknown():
    x, rate = _steady(1000.0, 0.6, 41)
    v = judge(x[:int(0.1 * rate)], rate, 1000.0)
    assert v.verdict == "unknown" and "too short" in v.reason


def test_the_shape_index_is_one_for_a_change_of_level_and_grows_for_a_new_line():
    rng = np.random.default_rng(5)
    shape = SpectralShape(51200.0, 50.0, 5000.0)
    n = 8192
    for _ in range(8):
        shape.learn(shape.bands(rng.standard_normal(n)))
    louder = shape.index(shape.bands(3.0 * rng.standard_normal(n)))
    t = np.arange(n) / 51200.0
    line = shape.index(shape.bands(rng.standard_normal(n) + 2.0 * np.sin(2 * np.pi * 650.0 * t)))
    assert 0.7 < louder < 1.4 and line > 3.0, (louder, line)


def _comb(rpm: float, share: float, seed: int, rate: float, **kw):
    # 5 s: lines a revolution apart at these speeds need the resolution of a long stretch
    rec = simulate_cut([Segment(6.0, rpm, round(share * b_lim_mm(rpm), 2))], seed=seed, rate_hz=rate, **kw)
    x = rec.signal[int(rate):]
    v = judge(x, rate, rpm)
    return v, find_comb(x, rate, rpm, 0.95 * v.frequency_hz, 1.05 * v.frequency_hz)


@pytest.mark.parametrize("rpm, rate", [(425.0, 10000.0), (570.0, 10000.0)])   # 10 kHz: the envelope costs less
def test_chatter_below_1000_rpm_is_a_comb_off_the_harmonics(rpm, rate):
    # chatter that leaves the cut every revolution is modulated once a revolution: narrow lines
    # a revolution apart at a non-zero offset from the spindle's harmonics (comb.py)
    v, comb = _comb(rpm, 1.6 if rpm < 500 else 2.5, 1, rate)
    assert v.verdict == "chatter"
    assert comb is not None and comb.off_harmonic, comb and comb.describe()
    assert abs(comb.spacing_hz / (rpm / 60.0) - 1) <= 0.05


@pytest.mark.parametrize("rpm", [320.0, 425.0, 570.0, 770.0])
@pytest.mark.parametrize("kw", [{"flat_fraction": 0.2}, {"flat_fraction": 0.2, "runout_um": 30.0}],
                         ids=["flat", "flat+runout"])
def test_a_stable_cuts_forced_lines_sit_on_the_harmonics(rpm, kw):
    # a flat's impulses make a comb too, but on k x the revolution rate: not chatter
    v, comb = _comb(rpm, 0.6, 1, 10000.0, **kw)
    assert comb is not None and not comb.off_harmonic and v.verdict == "stable", comb and comb.describe()


def test_a_stable_cut_near_its_limit_can_show_regenerations_comb_and_stays_stable():
    # regeneration makes a comb between the harmonics in a stable cut near its limit too (10 s at
    # 320 r/min, 0.85 x: lines 17-94 x their floor, at 0.46 of a spacing off the harmonics): the
    # comb is reported, not taken as chatter
    rec = simulate_cut([Segment(11.0, 320.0, round(0.85 * b_lim_mm(320.0), 2))], seed=11, rate_hz=10000.0)
    v = judge(rec.signal[10000:], 10000.0, 320.0)
    assert rec.label == "stable" and v.verdict == "stable" and v.comb, (v.verdict, v.comb)


def test_a_combs_lines_are_one_oscillation_or_independent():
    # comb.lock: one oscillation modulated once a revolution (chatter leaving the cut for part of
    # every revolution) makes lines that rise and fall together, whatever its slow wander; two
    # independent random lines (a stable cut's regenerative resonances) do not, at any gain
    rate, spacing, f0 = 10000.0, 12.5, 900.0 + 0.7 * 12.5
    t = np.arange(int(20 * rate)) / rate
    rng = np.random.default_rng(5)
    wander = 1 + 0.3 * np.sin(2 * np.pi * 0.07 * t) + 0.2 * np.sin(2 * np.pi * 0.31 * t + 1)
    chatter = wander * np.sin(2 * np.pi * f0 * t) * (1 + 0.8 * np.cos(2 * np.pi * spacing * t))
    comb = Comb([f0, f0 + spacing], spacing, 0.7, 0.05, 0.8)
    assert lock(chatter + 0.05 * rng.standard_normal(len(t)), rate, comb).locked
    from scipy.signal import butter, sosfiltfilt
    lines = sum(sosfiltfilt(butter(2, [f - 0.3, f + 0.3], "bandpass", fs=rate, output="sos"),
                            rng.standard_normal(len(t))) for f in (f0, f0 + spacing))
    for gain in (1.0, 1e-3):
        lk = lock(gain * lines, rate, comb)
        assert lk.samples >= 30 and not lk.locked, lk


@pytest.mark.parametrize("seed", [34, 36])
def test_a_stable_cuts_comb_near_its_limit_is_of_independent_lines(seed):
    # 20 s at 320-500 r/min, 0.85 x the limit: regeneration's comb off the harmonics, long enough to
    # judge its lines (each band's width x the duration over 30), which vary independently: stable
    rpm = {34: 320.0, 36: 500.0}[seed]
    rec = simulate_cut([Segment(21.0, rpm, round(0.85 * b_lim_mm(rpm), 2))], seed=seed, rate_hz=10000.0)
    v = judge(rec.signal[10000:], 10000.0, rpm)
    assert rec.label == "stable" and v.verdict == "stable" and "vary independently" in (v.comb or ""), v


@pytest.mark.parametrize("trend", [400, 401])
def test_the_envelope_trend_is_the_moving_mean_np_convolve_gives(trend):
    # the trend is a running sum (np.convolve's direct sum took 11 s on a 20 s recording): the
    # same mean, window and alignment, even or odd, as the convolution it replaced
    from lathed.analysis.chatter.verdict import _envelope_cv
    rng = np.random.default_rng(3)
    n = 6000
    spec = np.fft.rfft(rng.normal(size=n) * (1 + 0.5 * np.sin(np.arange(n) / 300)))
    band = np.zeros(len(spec), bool)
    band[200:900] = True
    a = np.zeros(n, complex)
    a[:len(spec)][band] = 2.0 * spec[band]
    env = np.abs(np.fft.ifft(a))
    tr = np.convolve(env, np.ones(trend) / trend, mode="same")
    e = env[trend:-trend] / tr[trend:-trend]
    assert _envelope_cv(spec, band, n, trend) == pytest.approx(e.std() / e.mean(), rel=1e-12)
