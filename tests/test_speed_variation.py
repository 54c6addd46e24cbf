import numpy as np
import pytest

from lathed.analysis.speed_variation import SpeedVariation, ramp, ramp_time_s

N0 = 2000.0


def _slope(v, t):
    return np.abs(np.diff(v) / np.diff(t))


@pytest.mark.parametrize("kind", ["sine", "triangle", "square"])
@pytest.mark.parametrize("accel", [200.0, 1000.0, 50_000.0])
def test_profile_respects_acceleration_and_keeps_mean(kind, accel):
    sv = SpeedVariation(kind, amplitude_ratio=0.1, period_s=1.0, accel_rpm_per_s=accel)
    t = np.linspace(0, 3.0, 30_001)
    n = sv.profile(t, N0)
    assert _slope(n, t).max() <= accel * (1 + 1e-6)
    one_period = n[:10_000]
    assert one_period.mean() == pytest.approx(N0, abs=1e-6 * N0)
    amp = (n.max() - n.min()) / 2
    assert amp == pytest.approx(sv.achieved_amplitude_ratio(N0) * N0, rel=1e-3)
    assert amp <= 0.1 * N0 * (1 + 1e-9)


def test_feasible_modulation_is_unchanged():
    # sine needs 2*pi*200/1 = 1257 r/min/s; the spindle gives 5000
    sv = SpeedVariation("sine", 0.1, 1.0, 5000.0)
    t = np.linspace(0, 1, 1001)
    assert np.allclose(sv.profile(t, N0), N0 + 200 * np.sin(2 * np.pi * t))
    assert sv.required_accel(N0) == pytest.approx(2 * np.pi * 200)


def test_slow_spindle_shrinks_amplitude_not_period():
    sv = SpeedVariation("sine", 0.2, 0.5, 300.0)
    assert sv.achieved_amplitude_ratio(N0) == pytest.approx(300 * 0.5 / (2 * np.pi * N0))
    t = np.linspace(0, 1.0, 4001)
    n = sv.profile(t, N0)
    # still periodic with the configured period
    assert np.allclose(n[:2001], n[2000:], atol=1e-9)


def test_square_becomes_trapezoid_with_ramps_at_the_limit():
    sv = SpeedVariation("square", 0.1, 2.0, 2000.0)    # 400 r/min swing in 0.2 s
    t = np.linspace(0, 2.0, 20_001)
    n = sv.profile(t, N0)
    s = _slope(n, t)
    assert s.max() == pytest.approx(2000.0, rel=1e-6)
    at_top = np.isclose(n, N0 + 200)
    assert 0.35 < at_top.mean() < 0.45       # flat tops fill most of the half period


def test_bad_parameters_name_the_problem():
    with pytest.raises(ValueError, match="kind 'saw'"):
        SpeedVariation("saw", 0.1, 1.0, 100.0)
    with pytest.raises(ValueError, match="amplitude ratio"):
        SpeedVariation("sine", 1.5, 1.0, 100.0)
    with pytest.raises(ValueError, match="acceleration"):
        SpeedVariation("sine", 0.1, 1.0, 0.0)


def test_ramp_follows_acceleration_limit():
    t = np.array([-1.0, 0.0, 0.25, 0.5, 1.0, 5.0])
    n = ramp(2500.0, 1500.0, 2000.0, t)
    assert np.allclose(n, [2500, 2500, 2000, 1500, 1500, 1500])
    assert ramp_time_s(2500, 1500, 2000) == pytest.approx(0.5)
