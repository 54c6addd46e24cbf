"""The stability model learned from cut records alone (issue 41): the modes
from the chatter frequencies, the limit's scale from the depths, how sure it
is, when it is trusted, and a wrong starting model corrected by moving its
mode rather than adding another."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from lathed.analysis.cuts import Cuts
from lathed.analysis.stability import StabilityModel, refit, residual
from lathed.analysis.stability.cases import generate_cuts, random_machine, true_dynamics
from lathed.analysis.stability.learn import (MIN_CHATTER, MIN_CUTS, Learned, Learner, _choose, learn, pockets,
                                             speed_grid, wilson)
from lathed.analysis.stability.start import frequency_groups, propose
from lathed.sim.lathe import LATHE_KF, LATHE_MODES

LATHE = StabilityModel(LATHE_MODES, LATHE_KF)


@pytest.fixture(scope="module")
def lathe_cuts():
    """150 cuts on the simulated lathe, then 600 more to judge on."""
    c = generate_cuts(LATHE, 750, given=LATHE, seed=11)
    return c.take(np.arange(150)), c.take(np.arange(150, 750))


@pytest.fixture(scope="module")
def learned(lathe_cuts):
    return learn(lathe_cuts[0])


def test_chatter_frequencies_group_by_mode_and_a_stray_one_starts_none():
    f = np.r_[np.linspace(192, 205, 12), np.linspace(625, 660, 6), 1500.0]
    n = len(f)
    cuts = Cuts.from_arrays(np.full(n, 2000.0), np.full(n, 3.0), np.ones(n, bool), f)
    groups = frequency_groups(cuts)
    assert [len(g) for g in groups] == [12, 6]
    assert [cuts.chatter_frequency_hz[g].min() for g in groups] == [192, 625]


def test_the_model_from_cuts_alone_finds_the_mode_and_classifies_later_cuts_as_the_truth(learned, lathe_cuts):
    later = lathe_cuts[1]
    assert learned.trusted, learned.why_not
    # only the 190 Hz workpiece mode chatters at these depths: the model has it, just below its chatter
    (mode,) = learned.model.modes
    assert mode.fn_hz == pytest.approx(190.0, rel=0.02)
    mine, truth = residual(learned.model, later, margins=False), residual(LATHE, later, margins=False)
    assert mine.accuracy >= truth.accuracy - 0.02 and mine.false_stable_rate <= 0.03
    # better than the plain rule on the same later cuts
    assert learned.after.accuracy > learned.baseline.accuracy
    # how sure: the interval on the minimum stable depth holds the true one, and the best speeds are the true pockets
    grid = speed_grid(learned.rpm_range)
    b_true, true_pockets = pockets(LATHE, grid)
    assert learned.b_min_mm.lo <= b_true * 1e3 <= learned.b_min_mm.hi
    assert learned.b_min_mm.spread < 0.3
    assert learned.pockets
    for p in learned.pockets:
        assert p.rpm.spread < 0.06
        assert min(abs(np.log(q / p.rpm.value)) for q, _ in true_pockets) < 0.02
    j = learned.to_json()
    assert j["trusted"] and j["best_rpm"] and j["b_min_mm"][1] <= j["b_min_mm"][0] <= j["b_min_mm"][2]


def test_too_few_cuts_or_no_chatter_frequency_is_no_model_and_says_what_it_needs(lathe_cuts):
    few = learn(lathe_cuts[0].take(np.arange(MIN_CUTS - 1)))
    assert few.model is None and not few.trusted and few.cuts_needed == MIN_CUTS
    assert f"at least {MIN_CUTS}" in few.why_not[0]
    c = lathe_cuts[0]
    blind = learn(Cuts.from_arrays(c.rpm, c.depth_mm, c.chatter))       # no frequency measured
    assert blind.model is None and f"at least {MIN_CHATTER}" in blind.why_not[0]


def test_a_model_it_cannot_trust_recommends_no_speed_and_says_how_many_cuts_it_needs():
    # verdicts that no lobes explain: chatter at random, at frequencies around one mode
    rng = np.random.default_rng(5)
    n = 80
    chatter = rng.random(n) < 0.5
    cuts = Cuts.from_arrays(np.exp(rng.uniform(np.log(500), np.log(5000), n)), rng.uniform(1, 4, n), chatter,
                            np.where(chatter, rng.uniform(195, 215, n), np.nan))
    lr = learn(cuts)
    assert lr.model is not None and not lr.trusted
    assert any("accuracy" in w for w in lr.why_not)
    assert lr.to_json()["best_rpm"] == []
    assert lr.cuts_needed > n


def test_process_damping_is_taken_only_when_the_later_cuts_favour_it():
    for effect, want in (("process_damping", "modes + process damping"), ("none", "modes")):
        cuts = generate_cuts(true_dynamics(effect), 200, seed=21)
        train, later = cuts.take(np.arange(140)), cuts.take(np.arange(140, 200))
        chose, fitted = _choose(propose(train), later)
        assert chose == want, effect
    assert fitted.model.process_damping == 0


def test_process_damping_is_judged_on_two_origins_not_flipped_by_the_few_slow_cuts_of_one():
    # a 139 Hz machine with process damping: judged on the last 30 % of 300 cuts alone, the few slow
    # cuts there left the test short of z 2, a model without process damping (its scatter widened to
    # 17 % to cover them) was chosen, trusted, and was wrong on 7 % of the later cuts
    true, kw = random_machine(9004)
    cuts = generate_cuts(true, 1300, seed=9004, **kw)
    lr = learn(cuts.take(np.arange(300)), bootstrap=2)
    assert lr.chose == "modes + process damping" and lr.model.process_damping > 0
    r = residual(lr.model, cuts.take(np.arange(300, 1300)), margins=False)
    assert r.accuracy >= 0.95 and r.false_stable_rate <= 0.03


def _learned(model, trusted, train):
    return Learned(model, trusted, [] if trusted else ["not good"], 0, train=train)


def test_the_learner_learns_as_cuts_grow_uses_a_trusted_model_and_withdraws_one_the_later_cuts_refute():
    l = Learner()
    assert not l.due(MIN_CUTS - 1) and l.due(MIN_CUTS)
    cuts = generate_cuts(LATHE, 100, given=LATHE, seed=2)
    assert l.consider(_learned(None, False, 70), cuts) == "not trusted" and l.model is None
    assert l.next_at == 125 and not l.due(124)
    assert l.consider(_learned(LATHE, True, 70), cuts) == "adopted" and l.model is LATHE
    # an untrusted learn keeps a model the later cuts agree with ...
    assert l.consider(_learned(None, False, 70), cuts) == "kept" and l.model is LATHE
    # ... and drops one they refute (the 190 Hz mode far stiffer than it is: every cut called stable)
    stiff = replace(LATHE, modes=(replace(LATHE_MODES[0], k_n_per_m=1e10), LATHE_MODES[1]))
    l.model = stiff
    assert l.consider(_learned(None, False, 70), cuts) == "withdrawn" and l.model is None
    # learning on the newest cut speeds only: the next learn counts from all that were recorded
    l.consider(_learned(None, False, 70), cuts, seen=2000)
    assert l.next_at == 2500


@pytest.mark.parametrize("factor", [1.35, 0.65])
def test_a_start_35_percent_off_in_frequency_moves_the_mode_and_adds_no_phantom(factor, lathe_cuts):
    train, later = generate_cuts(LATHE, 300, given=LATHE, seed=4), lathe_cuts[1]
    wrong = replace(LATHE, modes=(replace(LATHE_MODES[0], fn_hz=190.0 * factor), LATHE_MODES[1]))
    r = refit(wrong, train)
    assert [(e.effect.name, e.effect.mode) for e in r.effects] == [("natural_frequency", 0)], r.conclusion
    assert len(r.model.modes) == 2 and r.model.modes[0].fn_hz == pytest.approx(190.0, rel=0.02)
    right = refit(LATHE, train)
    a, b = residual(r.model, later, margins=False), residual(right.model, later, margins=False)
    assert a.accuracy >= b.accuracy - 0.01




def test_a_model_in_use_is_withdrawn_only_when_the_later_cuts_are_surely_below_the_bar():
    l = Learner()
    cuts = generate_cuts(LATHE, 60, given=LATHE, seed=2)
    l.consider(_learned(LATHE, True, 45), cuts)
    # one of the 15 later cuts called stable chattered (7 %): noise, not a refutation
    near = cuts.take(np.arange(60))
    b = LATHE.limit(near.rpm)[0][45:] * 1e3
    fs = 45 + int(np.flatnonzero(near.depth_mm[45:] < 0.9 * b)[0])
    flipped = Cuts.from_arrays(near.rpm, near.depth_mm, np.where(np.arange(60) == fs, True, near.chatter),
                               near.chatter_frequency_hz)
    assert residual(LATHE, flipped.take(np.arange(45, 60)), margins=False).false_stable >= 1
    assert l.consider(_learned(None, False, 45), flipped) == "kept" and l.model is LATHE
    assert wilson(12, 12)[0] == pytest.approx(0.816, abs=1e-3) and wilson(0, 0) == (0.0, 1.0)
    assert wilson(1, 15)[0] < 0.05 < wilson(1, 15)[1]
