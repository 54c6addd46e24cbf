import math

import numpy as np
import pytest

from lathed.analysis.cuts import Cuts
from lathed.analysis.lobes import StabilityLobes
from lathed.analysis.regen import DEFAULT_KF, DEFAULT_MODES
from lathed.analysis.stability.cases import GIVEN, UNDECLARED, generate_cuts, true_dynamics
from lathed.analysis.stability import StabilityModel, refit, residual
from lathed.analysis.stability.effects import Effect, Fit, compose
from lathed.analysis.stability.refit import _joint


def test_limit_per_speed_matches_the_lobes():
    n = np.geomspace(150, 12000, 3000)     # more speeds than one pass holds
    b, f = GIVEN.limit(n)
    bl, fl = StabilityLobes(DEFAULT_MODES, DEFAULT_KF).b_lim_at(n)
    assert np.allclose(b, bl, rtol=1e-4) and np.allclose(f, fl, rtol=1e-4)


def test_process_damping_raises_the_limit_most_at_low_speed():
    pd = StabilityModel(DEFAULT_MODES, DEFAULT_KF, process_damping=20.0)
    n = np.array([400.0, 4000.0])
    ratio = pd.limit(n)[0] / GIVEN.limit(n)[0]
    assert ratio[0] > 1.8 and 1.0 < ratio[1] < ratio[0]


def test_residual_confusion_margins_and_frequencies():
    rpm = np.array([1000.0, 2000.0, 3000.0, 1500.0])
    b, f = GIVEN.limit(rpm)
    # a stable cut at half the limit, a chatter cut at twice it, then one of each on the wrong side
    depth = np.array([0.5, 2.0, 0.7, 1.3]) * b * 1e3
    chatter = np.array([False, True, True, False])
    freq = np.array([np.nan, f[1] + 7.0, 1.5 * f[2], np.nan])
    r = residual(GIVEN, Cuts.from_arrays(rpm, depth, chatter, freq))
    assert (r.true_stable, r.true_chatter, r.false_stable, r.false_chatter) == (1, 1, 1, 1)
    assert r.accuracy == 0.5 and r.false_stable_rate == 0.25
    assert r.freq_n == 2 and r.freq_unexplained == [pytest.approx(1.5 * f[2])]
    miss = {m.line: m for m in r.misses}
    fs, fc = miss[4], miss[5]     # line = row + 2
    assert fs.outcome == "chatter" and fs.depth_margin_mm == pytest.approx(-0.3 * b[2] * 1e3, rel=1e-6)
    assert fc.outcome == "stable" and fc.depth_margin_mm == pytest.approx(0.3 * b[3] * 1e3, rel=1e-6)
    # below the critical depth: at no speed would the model have called chatter
    assert fs.speed_margin_rpm is None
    # above the limit: the nearest speed where the model calls that depth stable
    d = fc.depth_mm * 1e-3
    to = fc.rpm + fc.speed_margin_rpm
    assert GIVEN.limit(to)[0][0] > d * 0.999
    between = np.linspace(fc.rpm, to, 200)[:-2]
    assert np.all(GIVEN.limit(between)[0] <= d)


@pytest.mark.parametrize("effect", UNDECLARED)
def test_refit_names_the_undeclared_effect_and_accuracy_rises(effect):
    cuts = generate_cuts(true_dynamics(effect), 400, seed=3)
    r = refit(GIVEN, cuts)
    assert [e.effect.name for e in r.effects][:1] == [effect], r.conclusion
    assert r.after.accuracy > r.before.accuracy
    assert r.after.accuracy >= 0.9 and r.after.false_stable_rate <= 0.05


def test_matching_dynamics_add_nothing():
    r = refit(GIVEN, generate_cuts(true_dynamics("none"), 400, seed=4))
    assert r.effects == [] and r.model == GIVEN
    assert "no effect added" in r.conclusion


def test_no_library_effect_is_said_plainly():
    # labels that no lobe diagram can produce: chatter decided by a coin
    cuts = generate_cuts(GIVEN, 300, seed=5)
    cuts.chatter = np.random.default_rng(0).random(len(cuts)) < 0.5
    cuts.chatter_frequency_hz[:] = math.nan
    r = refit(GIVEN, cuts)
    assert r.effects == []
    assert r.conclusion.startswith("no effect in the library explains the residual")


@pytest.mark.parametrize("effect", ["natural_frequency", "second_mode"])
def test_lobe_labels_agree_with_the_regenerative_simulator(effect):
    # the generator labels by the true lobes; the simulator, cutting with the
    # true dynamics, must agree away from the limit and chatter at the frequency given
    from lathed.analysis.stability.cases import simulate_labels
    true = true_dynamics(effect)
    rpm = np.array([900.0, 2600.0, 4500.0])
    b, f = true.limit(rpm)
    cuts = Cuts.from_arrays(np.r_[rpm, rpm], np.r_[0.8 * b, 1.12 * b] * 1e3, [False] * 3 + [True] * 3)
    sim = simulate_labels(true, cuts)
    assert list(sim.chatter) == list(cuts.chatter)
    assert np.allclose(sim.chatter_frequency_hz[3:], f, rtol=0.03)


def test_joint_refit_keeps_an_effect_on_an_added_mode_in_its_place():
    # a second mode found first, then its frequency refined (mode 3 exists only after it),
    # then a third effect: the joint pass refits each effect in its place, not on the bare model
    cuts = generate_cuts(true_dynamics("second_mode"), 200, seed=5)
    added = Effect("second_mode", (950.0, 0.03, 2.0e7, 0.0))
    chosen = [added, Effect("natural_frequency", (1.02,), len(GIVEN.modes)), Effect("cutting_coefficient", (1.1,))]
    out = _joint(GIVEN, chosen, Fit(cuts))
    assert [e.name for e in out] == [e.name for e in chosen] and out[1].mode == len(GIVEN.modes)
    assert len(compose(GIVEN, out).modes) == len(GIVEN.modes) + 1
