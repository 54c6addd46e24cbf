import numpy as np
import pytest

from lathed.analysis.surface import ideal_ra_m, turned_surface

F = 0.3e-3
RE = 0.8e-3


def _path(revs=120, spr=1000):
    return np.linspace(0, 2 * np.pi * revs, revs * spr)


def test_stable_cut_gives_nose_radius_roughness():
    th = _path()
    s = turned_surface(np.full_like(th, 4e-6), th, F, RE)
    assert s.ra_m() == pytest.approx(ideal_ra_m(F, RE), rel=0.02)
    # Ra scales with feed squared
    s2 = turned_surface(np.full_like(th, 4e-6), th, F / 2, RE)
    assert s2.ra_m() == pytest.approx(s.ra_m() / 4, rel=0.05)
    # crest diameter: twice (tip offset + feed-mark height f^2/8r)
    assert s.diameter_deviation_m(0.015) == pytest.approx(2 * (4e-6 + F ** 2 / (8 * RE)), rel=0.02)


def test_taper_moves_diameter_not_roughness():
    th = _path()
    z_tool = F * th / (2 * np.pi)
    y = 1e-3 * z_tool                       # 1 um of radius per mm of travel
    s = turned_surface(y, th, F, RE)
    assert s.ra_m() == pytest.approx(ideal_ra_m(F, RE), rel=0.03)
    d = s.diameter_deviation_m(0.030) - s.diameter_deviation_m(0.005)
    assert d == pytest.approx(2 * 1e-3 * 0.025, rel=0.03)


def test_chatter_marks_raise_roughness():
    th = _path()
    rng = np.random.default_rng(1)
    # a vibration that is not locked to the revolution: marks differ pass to pass
    y = 10e-6 * np.sin(th * 9.37 + rng.uniform(0, 6.28))
    s = turned_surface(y, th, F, RE)
    assert s.ra_m() > 1.2 * ideal_ra_m(F, RE)


def test_window_selection_and_errors():
    th = _path()
    y = np.where(th < 2 * np.pi * 60, 0.0, 10e-6 * np.sin(th * 9.37))
    s = turned_surface(y, th, F, RE)
    calm = s.ra_m(0.0, 0.015)
    rough = s.ra_m(0.021, 0.034)
    assert calm == pytest.approx(ideal_ra_m(F, RE), rel=0.03) and rough > 1.2 * calm
    with pytest.raises(ValueError, match="no surface at z"):
        s.diameter_deviation_m(1.0)
    with pytest.raises(ValueError, match="monotonically"):
        turned_surface(y, th[::-1], F, RE)
    with pytest.raises(ValueError, match="nose"):
        turned_surface(y, th, 2e-3, RE)
    with pytest.raises(ValueError, match="two spindle revolutions"):
        turned_surface(y[:500], th[:500], F, RE)
