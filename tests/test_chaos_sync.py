import numpy as np
import pytest

from lathed.analysis.chatter.chaos_sync import ChaosSyncDetector
from lathed.analysis.chatter.eye import eye_radius, lorenz_features
from lathed.analysis.regen import Segment, simulate_cut


def test_features_hand_computed():
    e = np.array([1.0, 2.0, 3.0, 4.0])
    phi = lorenz_features(e, a=10, b=28, c=8 / 3)
    # n=0: e=(1,2,3): phi1 = -10+20, phi2 = 28-2-1*3, phi3 = -8+1*2
    # n=1: e=(2,3,4): phi1 = -20+30, phi2 = 56-3-2*4, phi3 = -32/3+2*3
    np.testing.assert_allclose(phi, [[10, 23, -6], [10, 45, -32 / 3 + 6]])
    assert eye_radius(phi[:, 0], phi[:, 1]) == pytest.approx(np.sqrt((100 + 529 + 100 + 2025) / 2))


def test_paper_printed_constants_are_configurable():
    phi = lorenz_features(np.array([1.0, 2.0, 3.0]), a=28, b=10, c=2.66)
    np.testing.assert_allclose(phi[0], [28, 10 - 2 - 3, -2.66 * 3 + 2])


def _run(det, x, rpm, block=4096):
    out = []
    for i in range(0, len(x), block):
        out += det.process(x[i:i + block], rpm)
    return out


@pytest.fixture(scope="module")
def chatter_rec():
    return simulate_cut([Segment(0.6, 2000, 1.0), Segment(0.6, 2000, 3.0)], seed=11)


def test_scale_invariance(chatter_rec):
    a = _run(ChaosSyncDetector(51200.0), chatter_rec.signal, 2000)
    b = _run(ChaosSyncDetector(51200.0), 10 * chatter_rec.signal, 2000)
    ia = np.array([w.index for w in a])
    ib = np.array([w.index for w in b])
    np.testing.assert_allclose(ia, ib, rtol=1e-6)
    assert [w.alarm for w in a] == [w.alarm for w in b]


def test_alarm_on_chatter_with_frequency(chatter_rec):
    wins = _run(ChaosSyncDetector(51200.0), chatter_rec.signal, 2000)
    first = next(w for w in wins if w.alarm)
    assert chatter_rec.unstable_at_s <= first.t_s <= chatter_rec.visible_at_s + 3 * 60 / 2000
    # the default structure chatters near its 620 Hz mode
    assert 550 < first.chatter_frequency_hz < 750
    assert not any(w.alarm for w in wins if w.t_s < chatter_rec.unstable_at_s)


def test_no_alarm_on_flat_and_eye_points():
    rec = simulate_cut([Segment(1.0, 1000, 1.2)], flat_fraction=0.2, seed=4)
    det = ChaosSyncDetector(51200.0)
    wins = _run(det, rec.signal, 1000)
    assert wins and not any(w.alarm for w in wins)
    p1, p2 = det.eye_points()
    assert p1.size == p2.size > 100
    assert det.eye_baseline is not None


def test_reference_baseline_kept_across_reset(chatter_rec):
    stable = simulate_cut([Segment(0.6, 2000, 1.0)], seed=12)
    det = ChaosSyncDetector(51200.0, learn_windows=2)
    det.learn_reference(stable.signal, 2000)
    det.reset()
    assert det.learned
    wins = _run(det, chatter_rec.signal, 2000)
    assert not wins[0].learning          # no learning phase with a reference
    assert any(w.alarm for w in wins)
