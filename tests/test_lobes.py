import math

import numpy as np
import pytest

from lathed.analysis.lobes import StabilityLobes
from lathed.analysis.modal import Mode, oriented_frf


@pytest.mark.parametrize("fn,zeta,k,kf", [
    (250.0, 0.03, 2e7, 1e9),
    (800.0, 0.01, 5e7, 2e9),
    (120.0, 0.08, 8e6, 6e8),
])
def test_single_mode_matches_closed_form(fn, zeta, k, kf):
    lobes = StabilityLobes([Mode(fn, zeta, k)], kf)
    closed = 2 * k * zeta * (1 + zeta) / kf
    assert lobes.b_lim_min_m == pytest.approx(closed, rel=0.005)
    # Re G is most negative at r = sqrt(1 + 2 zeta)
    assert lobes.chatter_frequency_hz == pytest.approx(fn * math.sqrt(1 + 2 * zeta), rel=0.005)


def test_orientation_scales_limit_by_directional_factor():
    base = StabilityLobes([Mode(300, 0.04, 3e7, 0.0)], 1e9).b_lim_min_m
    tilted = StabilityLobes([Mode(300, 0.04, 3e7, 60.0)], 1e9).b_lim_min_m
    assert tilted == pytest.approx(base / math.cos(math.radians(60)) ** 2, rel=0.005)


def test_two_modes_minimum_matches_brute_force():
    modes = [Mode(220, 0.03, 2e7, 30), Mode(610, 0.02, 3.5e7, 70)]
    kf = 1.5e9
    lobes = StabilityLobes(modes, kf)
    f = np.linspace(100, 2000, 2_000_001)
    re = oriented_frf(modes, f).real
    assert lobes.b_lim_min_m == pytest.approx(-1 / (2 * kf * re.min()), rel=1e-4)


def test_boundary_points_satisfy_characteristic_equation():
    modes = [Mode(220, 0.03, 2e7, 30), Mode(610, 0.02, 3.5e7, 70)]
    kf = 1.5e9
    lobes = StabilityLobes(modes, kf)
    rpm = np.array([900.0, 1500.0, 2333.0, 4100.0, 5800.0])
    b, fc = lobes.b_lim_at(rpm)
    w = 2 * np.pi * fc
    T = 60 / rpm
    residual = 1 + kf * b * (1 - np.exp(-1j * w * T)) * oriented_frf(modes, fc)
    assert np.all(np.abs(residual) < 2e-3)
    assert np.all(b >= lobes.b_lim_min_m * (1 - 1e-9))


def test_limit_is_lowest_branch_and_touches_minimum():
    lobes = StabilityLobes([Mode(250, 0.03, 2e7)], 1e9)
    n = np.linspace(300, 6000, 4000)
    b, _ = lobes.b_lim_at(n)
    assert np.all(np.isfinite(b))
    assert b.min() == pytest.approx(lobes.b_lim_min_m, rel=1e-3)
    # at every speed, no lobe piece lies below the reported limit
    for piece in lobes.lobes(300, 6000):
        interp = np.interp(piece.rpm, n, b)
        assert np.all(piece.b_lim_m >= interp * (1 - 5e-3))
    # pockets exist: the limit at a pocket exceeds the minimum several times
    assert b.max() > 3 * lobes.b_lim_min_m


def test_is_stable_and_errors():
    lobes = StabilityLobes([Mode(250, 0.03, 2e7)], 1e9)
    assert not lobes.is_stable(2000, 10 * lobes.b_lim_min_m)[0]
    assert lobes.is_stable(2000, 0.9 * lobes.b_lim_min_m)[0]
    with pytest.raises(ValueError, match="at least one"):
        StabilityLobes([], 1e9)
    with pytest.raises(ValueError, match="Kf"):
        StabilityLobes([Mode(250, 0.03, 2e7)], 0)
    with pytest.raises(ValueError, match="90 deg"):
        StabilityLobes([Mode(250, 0.03, 2e7, 90)], 1e9)
    with pytest.raises(ValueError, match="speed range"):
        lobes.lobes(3000, 1000)


@pytest.mark.parametrize("rpm", [1500.0, 2000.0, 2500.0])
def test_time_domain_agrees_with_lobes(rpm):
    """5 % below the computed limit the cut-entry transient dies out in the
    regenerative simulator; 5 % above it grows."""
    from lathed.analysis.regen import DEFAULT_KF, DEFAULT_MODES, RegenerativeTurning

    lobes = StabilityLobes(DEFAULT_MODES, DEFAULT_KF)
    b_lim = lobes.b_lim_at(rpm)[0][0]
    rate = 20000.0
    growth = {}
    for factor in (0.95, 1.05):
        sim = RegenerativeTurning(DEFAULT_MODES, DEFAULT_KF, rate_hz=rate, noise_rms=0.0,
                                  process_noise=0.0, seed=0)
        y = sim.run(int(rate * 1.0), rpm, factor * b_lim * 1e3, 0.1).y_m
        w = int(0.1 * rate)
        early = np.std(y[int(0.3 * rate):int(0.3 * rate) + w])
        growth[factor] = np.std(y[-w:]) / early
    assert growth[0.95] < 0.6, growth
    assert growth[1.05] > 1.5, growth


@pytest.mark.parametrize("structure", ["default", "live lathe"])
@pytest.mark.parametrize("rpm", [40.0, 700.0, 2000.0, 4500.0])
def test_the_growth_rate_crosses_zero_at_the_limit(structure, rpm):
    """The rightmost characteristic root: decaying below b_lim, growing above, on the
    limit at b_lim, with the chatter frequency the lobes give there."""
    from lathed.analysis.regen import DEFAULT_KF, DEFAULT_MODES
    from lathed.sim.lathe import LATHE_KF, LATHE_MODES
    modes, kf = (DEFAULT_MODES, DEFAULT_KF) if structure == "default" else (LATHE_MODES, LATHE_KF)
    lobes = StabilityLobes(modes, kf)
    b, f = (float(v[0]) for v in lobes.b_lim_at(rpm))
    below, above = lobes.growth(rpm, 0.9 * b)[0], lobes.growth(rpm, 1.1 * b)[0]
    sigma, f_at = lobes.growth(rpm, b)
    assert below < 0 < above
    assert abs(sigma) < 0.05 * min(-below, above)
    assert f_at == pytest.approx(f, rel=0.01)


def test_a_shallow_cut_decays_as_the_structure_does():
    """A cut 1 um deep barely touches the modes: the rightmost root is the weakest-damped
    mode's own pole (found from its first-order shift, outside a grid start's basin)."""
    mode = Mode(300, 0.04, 3e7)
    sigma, f = StabilityLobes([mode], 1e9).growth(2000.0, 1e-9)
    assert sigma == pytest.approx(-mode.zeta * mode.wn, rel=1e-3)
    assert f == pytest.approx(mode.fn_hz * math.sqrt(1 - mode.zeta**2), rel=1e-3)


def test_the_growth_rate_needs_a_speed_and_a_depth():
    lobes = StabilityLobes([Mode(300, 0.04, 3e7)], 1e9)
    with pytest.raises(ValueError, match="speed and a depth"):
        lobes.growth(0.0, 1e-3)


@pytest.mark.parametrize("rpm", [1500.0, 2000.0])
def test_the_simulated_lathe_grows_chatter_as_the_theory_says(rpm):
    """The live lathe's 3 mm cut: the chatter band's envelope (a revolution's mean) grows
    at the rightmost root's rate, to within 15 %, over 0.1-0.5 s (before it saturates)."""
    from scipy.signal import butter, hilbert, sosfiltfilt

    from lathed.analysis.regen import Segment, simulate_cut
    from lathed.sim.lathe import LATHE_KF, LATHE_MODES
    sigma, f = StabilityLobes(LATHE_MODES, LATHE_KF).growth(rpm, 3e-3)
    rec = simulate_cut([Segment(0.6, rpm, 3.0)], seed=1, modes=LATHE_MODES, kf_n_per_m2=LATHE_KF)
    sos = butter(4, [f - 15, f + 15], btype="band", fs=rec.rate_hz, output="sos")
    env = np.abs(hilbert(sosfiltfilt(sos, rec.signal)))
    n = int(rec.rate_hz * 60 / rpm)
    revs = env[:len(env) // n * n].reshape(-1, n).mean(axis=1)
    t = (np.arange(len(revs)) + 0.5) * 60 / rpm
    sel = (t > 0.1) & (t < 0.5)
    fitted = np.polyfit(t[sel], np.log(revs[sel]), 1)[0]
    assert fitted == pytest.approx(sigma, rel=0.15), (fitted, sigma)
