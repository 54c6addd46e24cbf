import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lathed.analysis.lobes import StabilityLobes
from lathed.analysis.modal import Mode
from lathed.analysis.speed_selection import (Cut, Decision, FrequencySelection, LobeSelection, RatedSpeed, reach,
                                             SpindleLimits, SuppressionPolicy, VariationSelection)
from lathed.analysis.speed_variation import SpeedVariation

LIMITS = SpindleLimits()
MODE = Mode(250, 0.03, 2e7)
LOBES = StabilityLobes([MODE], 1e9)


def _cut(depth_m, kt=1.4e9):
    return Cut(depth_m=depth_m, feed_m_per_rev=0.3e-3, diameter_m=0.030, kt_n_per_m2=kt)


def test_torque_curve_peaks_at_base_speed_then_constant_power():
    t = LIMITS.torque_available(np.array([500, 1500, 3000, 6000]))
    assert np.allclose(t, [35.8, 35.8, 17.9, 8.95])
    assert LIMITS.power_w == pytest.approx(35.8 * 1500 * 2 * math.pi / 60)


def test_cut_torque_and_removal_rate():
    c = _cut(3e-3)
    assert c.torque_nm == pytest.approx(1.4e9 * 3e-3 * 0.3e-3 * 0.015)
    assert c.removal_rate_mm3_s(2000) == pytest.approx(3 * 0.3 * math.pi * 30 * 2000 / 60)
    # 18.9 N*m needed: constant power runs out at 35.8*1500/18.9 = 2841 r/min
    assert c.drivable(2800, LIMITS) and not c.drivable(2900, LIMITS)


def test_frequency_selection_puts_revolution_at_chatter_over_integer():
    sel = FrequencySelection(LIMITS)
    d = sel.select(2000, 250.0)
    assert d.rpm_after == pytest.approx(60 * 250 / 3)        # 5000: highest below 6000
    # torque caps it: 3 mm needs 18.9 N*m, good to 2841 r/min -> 60*250/6 = 2500
    d = FrequencySelection(LIMITS, _cut(3e-3)).select(2000, 250.0)
    assert d.rpm_after == pytest.approx(2500)
    assert d.removal_rate_ratio == pytest.approx(1.25)
    d = FrequencySelection(LIMITS, _cut(3e-3)).select(2000, 250.0, avoid=[(2400, 2600)])
    assert d.rpm_after == pytest.approx(60 * 250 / 7)
    assert sel.select(2000, None) is None


def test_lobe_selection_is_stable_and_highest():
    depth = 1.5 * LOBES.b_lim_min_m
    cut = _cut(depth)
    sel = LobeSelection(LOBES, cut, LIMITS)
    d = sel.select(2000, 260.0)
    assert d.expected_stable
    band = np.linspace(d.rpm_after * 0.97, d.rpm_after * 1.03, 301)
    assert LOBES.b_lim_at(band)[0].min() >= 1.15 * depth * (1 - 2e-3)
    # no drivable speed above it has a robustly stable band
    for n in np.linspace(d.rpm_after * 1.01, LIMITS.max_rpm, 60):
        if not cut.drivable(n, LIMITS):
            continue
        b = LOBES.b_lim_at(np.linspace(n * 0.97, min(n * 1.03, 6000), 301))[0]
        assert b.min() < 1.15 * depth * (1 + 2e-3)


def test_lobe_selection_without_a_stable_speed_says_so():
    d = LobeSelection(LOBES, _cut(20 * LOBES.b_lim_min_m, kt=1e7), LIMITS).select(2000, 260.0)
    assert d.expected_stable is False
    assert "no stable speed" in d.reason


def test_rated_speed_and_variation_strategies():
    d = RatedSpeed(750, LOBES, _cut(3e-3)).select(2500, 260.0)
    assert d.rpm_after == 750 and d.removal_rate_ratio == pytest.approx(0.3)
    assert d.expected_stable is False          # 3 mm is far above this model's limit
    sv = SpeedVariation("sine", 0.1, 1.0, 2000)
    d = VariationSelection(sv).select(2500, 260.0)
    assert d.variation is sv and d.rpm_after == 2500
    assert d.record()["variation"]["kind"] == "sine"


def _policy(**kw):
    return SuppressionPolicy(FrequencySelection(LIMITS), LIMITS, fallback=RatedSpeed(750), **kw)


def test_policy_acts_on_alarm_then_holds_for_ramp_and_settling():
    p = _policy(settle_revs=20)
    assert p.observe(0.0, 2000, alarm=False, chatter_frequency_hz=250) is None
    d = p.observe(0.1, 2000, alarm=True, chatter_frequency_hz=250, chatter_index=3.2, threshold=1.0)
    assert d is not None and d.rpm_after == pytest.approx(5000)
    assert d.chatter_index == 3.2 and d.threshold == 1.0
    hold = 0.1 + (5000 - 2000) / LIMITS.accel_rpm_per_s + 20 * 60 / 5000
    assert p.hold_until() == pytest.approx(hold)
    assert p.observe(hold - 1e-3, 5000, alarm=True, chatter_frequency_hz=250) is None
    d2 = p.observe(hold + 1e-3, 5000, alarm=True, chatter_frequency_hz=250)
    assert d2 is not None and d2.rpm_after < 5000


def test_a_rated_speed_beyond_the_speed_cap_or_the_spindle_s_torque_is_not_commanded():
    """The fallback's speed is the operator's number (rated_rpm): the policy holds it to the
    envelope as it does every strategy's, and the spindle must have the torque there."""
    capped = reach(LIMITS, 1500.0, 1.3)                       # at most 1950 r/min
    p = SuppressionPolicy(FrequencySelection(capped), capped, fallback=RatedSpeed(3000))
    assert p.observe(0.0, 1500, alarm=True, chatter_frequency_hz=None) is None and p.exhausted
    heavy = _cut(3e-3, kt=2.2e9)                # 30 N m: 36 available at 750 r/min, 18 at 3000
    assert RatedSpeed(3000, LOBES, heavy, limits=LIMITS).select(2500, 260.0) is None
    assert RatedSpeed(750, LOBES, heavy, limits=LIMITS).select(2500, 260.0) is not None


def test_a_speed_variation_swinging_outside_the_envelope_is_not_started():
    sv = SpeedVariation("sine", 0.2, 1.0, 1e6)
    capped = reach(LIMITS, 1500.0, 1.1)                       # at most 1650 r/min: 1800 would pass it
    p = SuppressionPolicy(VariationSelection(sv), capped)
    assert p.observe(0.0, 1500, alarm=True) is None and p.exhausted
    d = SuppressionPolicy(VariationSelection(sv), reach(LIMITS, 1500.0, 1.3)).observe(0.0, 1500, alarm=True)
    assert d is not None and d.variation is sv


def test_policy_needs_consecutive_alarms_when_confirm_is_set():
    p = _policy(confirm=3)
    for t, alarm in enumerate([True, True, False, True, True]):
        assert p.observe(float(t), 2000, alarm, 250) is None
    assert p.observe(5.0, 2000, True, 250) is not None


def test_policy_never_oscillates_between_two_speeds():
    # a strategy that would bounce between two speeds if it were allowed to
    class Bounce:
        name = "bounce"

        def select(self, rpm_now, fc, avoid=()):
            target = 3000.0 if rpm_now < 2500 else 2000.0      # ignores the bans
            return Decision(self.name, rpm_now, target, fc, None, None, target / rpm_now, "")

    p = SuppressionPolicy(Bounce(), LIMITS, fallback=RatedSpeed(750), settle_revs=5)
    rpm, speeds, t = 2000.0, [2000.0], 0.0
    for _ in range(50):                      # chatter never stops
        d = p.observe(t, rpm, alarm=True, chatter_frequency_hz=250)
        if d is not None:
            rpm = d.rpm_after
            speeds.append(rpm)
        t += 1.0
    assert speeds == [2000.0, 3000.0, 750.0]   # 2000 is banned: no return; then the rule
    assert p.exhausted


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.booleans(), st.floats(120, 900)), min_size=1, max_size=80))
def test_policy_never_revisits_a_speed_it_left(events):
    p = _policy(settle_revs=3, max_changes=4)
    rpm, left, t, n_changes = 2500.0, [], 0.0, 0
    for alarm, fc in events:
        d = p.observe(t, rpm, alarm, fc)
        if d is not None:
            left.append(rpm)
            assert all(abs(d.rpm_after - s) > 0.04 * s * 0.99 for s in left)
            rpm = d.rpm_after
            n_changes += 1
        t += 0.5
    assert n_changes <= 5


def test_closed_loop_on_the_simulator_restabilises_the_cut():
    """Policy + lobe strategy + a spindle ramping at its limit, on the
    regenerative simulator; the alarm is the surface waviness the simulator
    itself reports, so this checks the loop, not a detector."""
    from lathed.analysis.regen import VISIBLE_WAVINESS_M, RegenerativeTurning, surface_waviness

    modes = (Mode(190.0, 0.03, 7.5e7), Mode(620.0, 0.035, 4.0e8, 30.0))
    kf, rate, depth_mm, block = 2e9, 10_000.0, 3.0, 200
    lobes = StabilityLobes(modes, kf)
    cut = Cut(depth_mm * 1e-3, 0.3e-3, 0.030, 1.5e9)
    assert not lobes.is_stable(2500.0, cut.depth_m)[0]
    policy = SuppressionPolicy(LobeSelection(lobes, cut, LIMITS), LIMITS, fallback=RatedSpeed(750),
                               settle_revs=10)
    sim = RegenerativeTurning(modes, kf, rate_hz=rate, seed=2)
    rpm = cmd = 2500.0
    t, y, th, inc, decisions = 0.0, [], [], [], []
    while t < 2.5:
        out = sim.run(block, rpm, depth_mm, 0.3)
        y.append(out.y_m), th.append(out.theta_rad), inc.append(out.in_cut)
        t += block / rate
        spr = int(rate * 60 / rpm)
        wav = surface_waviness(np.concatenate(y[-8:]), np.concatenate(th[-8:]), np.concatenate(inc[-8:]),
                              rate_hz=rate)
        d = policy.observe(t, rpm, bool(wav[-1] > VISIBLE_WAVINESS_M), 195.0)
        if d is not None:
            decisions.append(d)
            cmd = d.rpm_after
        rpm += float(np.clip(cmd - rpm, -LIMITS.accel_rpm_per_s * block / rate,
                             LIMITS.accel_rpm_per_s * block / rate))
    y, th, inc = np.concatenate(y), np.concatenate(th), np.concatenate(inc)
    assert len(decisions) == 1 and decisions[0].expected_stable
    assert decisions[0].removal_rate_ratio >= 0.6
    wav = surface_waviness(y, th, inc, rate_hz=rate)
    tail = np.median(wav[-spr:])
    assert tail < VISIBLE_WAVINESS_M
    assert tail < 0.2 * wav.max(), (tail, wav.max())     # chatter had been well visible


# -- no stable speed within reach: hold and advise, or move ------------------------------------

def _reach_policy(depth_m, when, rated=750.0, rpm=2000.0):
    from lathed.analysis.speed_selection import lobe_policy
    return lobe_policy(LOBES, _cut(depth_m), LIMITS, rpm, 1.3, rated, when_no_stable_speed=when)


def _grid():
    sel = _reach_policy(1e-3, "hold").strategy
    sel.limit_mm(2000.0)
    n, b, worst = sel.grid
    return n, b, worst, (n >= LIMITS.min_rpm) & (n <= 1.3 * 2000)


def test_policy_holds_and_advises_when_the_model_says_every_speed_within_reach_chatters():
    from lathed.analysis.speed_selection import Advice
    n, b, worst, reach = _grid()
    depth = 1.1 * float(b[reach].max())     # above the limit at every speed within reach, 750 r/min too
    assert _cut(depth).drivable(n[reach], LIMITS).all()
    # "move": the most stable speed, which the lobes themselves say will chatter
    d = _reach_policy(depth, "move").observe(0.0, 2000.0, True, 260.0)
    assert d.rpm_after != 2000.0 and d.expected_stable is False
    # "hold": no move, the advice instead, once
    p = _reach_policy(depth, "hold")
    a = p.observe(0.0, 2000.0, True, 260.0, chatter_index=4.0, threshold=1.0)
    assert isinstance(a, Advice) and p.changes == [] and p.advice is a and p.exhausted
    assert a.rpm == 2000.0 and a.depth_mm == pytest.approx(depth * 1e3)
    assert a.limit_mm == pytest.approx(float(LOBES.b_lim_at(2000.0)[0][0]) * 1e3, rel=1e-3)
    assert a.best_limit_mm == pytest.approx(float(b[reach].max()) * 1e3)
    assert a.best_rpm == pytest.approx(float(n[reach][np.argmax(b[reach])]))
    assert a.safe_depth_mm == pytest.approx(float(np.interp(2000.0, n, worst)) * 1e3 / 1.15)
    assert a.max_rpm <= 2600.0 and a.chatter_index == 4.0 and a.chatter_frequency_hz == 260.0
    text = a.record()["advice"]
    assert text.startswith(f"no stable speed within 100-{a.max_rpm:.0f} r/min at {depth * 1e3:.2f} mm: "
                           f"the model's limit is {a.limit_mm:.2f} mm at 2000 r/min")
    assert text.endswith(f"reduce the depth of cut below {a.safe_depth_mm:.2f} mm (stable here with the lobes' margin) or stiffen the set-up")
    assert p.observe(1e7, 2000.0, True, 260.0) is None       # said once; the speed stays
    p.reset()
    assert p.advice is None and isinstance(p.observe(0.0, 2000.0, True, 260.0), Advice)


def _target(n, b, worst, reach, rpm=2000.0):
    """The speed the rule moves to when none is stable with the margin: the most stable over
    the band, the speed just left banned (+-4 %)."""
    left = reach & ~((n >= 0.96 * rpm) & (n <= 1.04 * rpm))
    return int(np.flatnonzero(left)[np.argmax(worst[left])])


def test_policy_moves_as_before_when_the_speed_it_moves_to_is_above_the_depth():
    n, b, worst, reach = _grid()
    j = _target(n, b, worst, reach)
    # stable with the margin near 2500 r/min; and above the limit there but not by the margin
    for depth, stable in ((1.2 * LOBES.b_lim_min_m, True), (0.95 * float(b[j]), False)):
        assert bool(depth * 1.15 <= worst[reach].max()) is stable
        d_hold = _reach_policy(depth, "hold").observe(0.0, 2000.0, True, 260.0)
        d_move = _reach_policy(depth, "move").observe(0.0, 2000.0, True, 260.0)
        assert d_hold == d_move and d_hold.expected_stable is stable and d_hold.rpm_after <= 2600.0


def test_policy_holds_when_the_speed_it_would_move_to_chatters_though_a_narrow_cusp_does_not():
    """A lobe's cusp above the depth, narrower than the band, is not where the rule moves: it
    moves to the most stable speed over the band, whose own limit is below the depth.  That
    move is one the model itself says chatters; it used to be made (the closed loop from zero:
    five in six such moves chattered again)."""
    from lathed.analysis.speed_selection import Advice
    n, b, worst, reach = _grid()
    j = _target(n, b, worst, reach)
    depth = 1.05 * float(b[j])
    assert depth < float(b[reach].max())          # the cusp is above the depth
    d = _reach_policy(depth, "move").observe(0.0, 2000.0, True, 260.0)
    assert d.rpm_after == pytest.approx(n[j]) and d.expected_b_lim_mm < depth * 1e3
    a = _reach_policy(depth, "hold").observe(0.0, 2000.0, True, 260.0)
    assert isinstance(a, Advice) and a.depth_mm == pytest.approx(depth * 1e3)
    assert "on a cusp narrower than the lobes' speed band; speed held" in a.advice


def test_holding_takes_no_fallback_the_lobes_say_chatters_when_the_budget_is_spent():
    from lathed.analysis.speed_selection import Advice
    n, b, worst, reach = _grid()
    j = _target(n, b, worst, reach)
    depth = 0.95 * float(b[j])            # above the limit at the rule's speed, not by the margin
    rated = 750.0
    assert float(LOBES.b_lim_at(rated)[0][0]) < depth     # the rated speed chatters at this depth
    for when in ("hold", "move"):
        p = _reach_policy(depth, when, rated=rated)
        p.max_changes = 1
        d = p.observe(0.0, 2000.0, True, 260.0)
        assert d.strategy == "sss_lobes" and d.rpm_after == pytest.approx(n[j])
        # it chattered there too; the budget is spent: the fallback is all that is left
        d = p.observe(1e6, d.rpm_after, True, 260.0)
        if when == "hold":
            assert d is None and p.exhausted and len(p.changes) == 1
        else:
            assert d.strategy == "rated_speed" and d.expected_stable is False


def test_holding_does_not_take_a_rated_speed_above_the_speed_cap():
    """Every speed within reach chatters; a rated speed above the reach would not, but the
    cap (max_speed_ratio x the programmed speed, for the tool's life) holds for the paper's
    rule too: the speed is held with advice."""
    from lathed.analysis.speed_selection import Advice
    n, b, worst, reach = _grid()
    depth = 1.1 * float(b[reach].max())
    above = np.linspace(2700, 6000, 500)
    b_above = LOBES.b_lim_at(above)[0]
    rated = float(above[np.argmax(b_above)])
    assert float(b_above.max()) > depth
    d = _reach_policy(depth, "hold", rated=rated).observe(0.0, 2000.0, True, 260.0)
    assert isinstance(d, Advice)


def test_when_no_stable_speed_must_be_hold_or_move():
    with pytest.raises(ValueError, match="when_no_stable_speed 'stay' is not one of hold, move"):
        _reach_policy(1e-3, "stay")
