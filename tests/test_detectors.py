import numpy as np
import pytest

from lathed.analysis.chatter.detectors import SyncResidualDetector
from lathed.analysis.chatter.registry import DEFAULT_DETECTOR, DETECTORS, describe_params, make_detector
from lathed.analysis.regen import Segment, simulate_cut

RATE = 51200.0


def _run(det, x, rpm, block=4096):
    rpm_arr = np.broadcast_to(np.asarray(rpm, dtype=float), x.shape)
    out = []
    for i in range(0, len(x), block):
        out += det.process(x[i:i + block], float(rpm_arr[i]))
    return out


def test_registry_and_unknown_name():
    assert {"sync_residual", "spectral_ratio", "chaos_sync"} <= set(DETECTORS)
    assert DEFAULT_DETECTOR in DETECTORS
    with pytest.raises(ValueError, match="allowed: chaos_sync, spectral_ratio, sync_cusum, sync_residual"):
        make_detector("nope", RATE)


def test_extra_factories_merge_over_builtins():
    made = []

    def factory(rate_hz, **params):
        made.append((rate_hz, params))
        return "plugin"

    assert make_detector("mine", RATE, extra={"mine": factory}, window_revs=2) == "plugin"
    assert made == [(RATE, {"window_revs": 2})]
    assert make_detector("sync_residual", RATE, extra={"sync_residual": factory}) == "plugin"


def test_params_validated_with_range():
    with pytest.raises(ValueError, match=r"threshold = 0.5 is outside \[1.05, 1000\]"):
        make_detector("sync_residual", RATE, threshold=0.5)
    with pytest.raises(ValueError, match="unknown parameter.*bogus"):
        make_detector("chaos_sync", RATE, bogus=1)
    with pytest.raises(ValueError, match=r"jump_ratio = 1.2 is outside \[1.5, 1000\]"):
        make_detector("sync_cusum", RATE, jump_ratio=1.2)
    assert all(describe_params(n)["jump_ratio"][0] == 3.0 for n in DETECTORS)


@pytest.mark.parametrize("params, msg", [
    # float() took a string, took true as 1 ("1 is outside"), and a count of 4.7 windows (used as 4 or 5)
    ({"threshold": "2"}, "threshold: expected a number, got '2'"),
    ({"learn_windows": True}, "learn_windows: expected a number, got True"),
    ({"learn_windows": 4.7}, r"learn_windows: expected a whole number \(a count\), got 4.7"),
    ({"off_windows": 2.5}, r"off_windows: expected a whole number \(a count\), got 2.5"),
])
def test_params_must_be_numbers_and_counts_whole(params, msg):
    with pytest.raises(ValueError, match=msg):
        make_detector("sync_cusum", RATE, **params)
    with pytest.raises(ValueError, match=r"memory: expected a whole number \(a count\), got 6.5"):
        make_detector("chaos_sync", RATE, memory=6.5)
    assert make_detector("sync_cusum", RATE, learn_windows=5.0, on_windows=3).params["learn_windows"] == 5
    assert "p" in describe_params("chaos_sync")
    assert all(len(v) == 4 for v in describe_params("spectral_ratio").values())


def test_block_size_does_not_change_windows():
    rec = simulate_cut([Segment(0.5, 2500, 1.0)], seed=5)
    a = _run(SyncResidualDetector(RATE), rec.signal, 2500, block=4096)
    b = _run(SyncResidualDetector(RATE), rec.signal, 2500, block=777)
    assert [w.t_s for w in a] == [w.t_s for w in b]
    np.testing.assert_allclose([w.index for w in a], [w.index for w in b], rtol=1e-9)


def test_revolution_difference_cancels_periodic_signal():
    # anything repeating every revolution (runout harmonics, a flat's ringing) cancels
    rpm = 1500.0
    t = np.arange(int(RATE)) / RATE
    f1 = rpm / 60
    x = np.sin(2 * np.pi * f1 * t) + 0.5 * np.sin(2 * np.pi * 23 * f1 * t + 1)
    det = SyncResidualDetector(RATE)
    det.process(x, rpm)
    spr = int(RATE * 60 / rpm)
    d = det._d[spr + 2:det._n]
    assert np.max(np.abs(d)) < 0.02


def test_hysteresis_on_and_off():
    rng = np.random.default_rng(1)
    rpm, n = 3000.0, int(RATE)
    t = np.arange(n) / RATE
    noise = rng.normal(0, 1, 3 * n)
    burst = np.r_[np.zeros(n), 20 * np.sin(2 * np.pi * 655 * t), np.zeros(n)]
    # the burst is switched on at once, a level step jump_ratio would not count: off here
    det = SyncResidualDetector(RATE, jump_ratio=1000)
    wins = _run(det, noise + burst, rpm)
    alarm = np.array([w.alarm for w in wins])
    ts = np.array([w.t_s for w in wins])
    assert not alarm[ts < 1.0].any()
    assert alarm[(ts > 1.1) & (ts < 1.9)].all()
    assert not alarm[ts > 2.2].any()
    # one noisy window over threshold does not raise it
    det2 = SyncResidualDetector(RATE, on_windows=2)
    spike = noise.copy()
    spike[n:n + 200] += 50
    assert not any(w.alarm for w in _run(det2, spike, rpm))


@pytest.mark.parametrize("name", sorted(DETECTORS))
def test_chatter_detected_after_onset(name):
    rec = simulate_cut([Segment(0.6, 1500, 1.0), Segment(0.8, 1500, 3.0)], seed=21)
    wins = _run(make_detector(name, RATE), rec.signal, 1500)
    first = next((w.t_s for w in wins if w.alarm), None)
    assert first is not None and first >= rec.unstable_at_s


TRAPS = {
    "flat": ([Segment(1.2, 1000, 1.2)], {"flat_fraction": 0.15}),
    "speed change": ([Segment(0.6, 2000, 1.2), Segment(0.6, 2600, 1.2, 0.3)], {}),
    "runout": ([Segment(1.2, 2500, 1.2)], {"runout_um": 40.0}),
    "cut entry": ([Segment(1.2, 1500, 1.4)], {"seed": 7}),
}


@pytest.mark.parametrize("trap", sorted(TRAPS))
@pytest.mark.parametrize("name", ["sync_residual", "chaos_sync", "sync_cusum"])
def test_no_alarm_on_traps(trap, name):
    segs, kw = TRAPS[trap]
    rec = simulate_cut(segs, trap, **{"seed": 3, **kw})
    assert rec.label == "stable"
    wins = _run(make_detector(name, RATE), rec.signal, rec.rpm)
    assert wins and not any(w.alarm for w in wins)


def test_bad_rpm():
    with pytest.raises(ValueError, match="spindle speed"):
        SyncResidualDetector(RATE).process(np.zeros(10), 0.0)


def test_too_slow_blocks_dropped_then_followed():
    det = SyncResidualDetector(RATE)
    assert 10 < det.min_rpm < 60
    assert det.process(np.ones(4096), det.min_rpm / 2) == [] and det.too_slow
    rng = np.random.default_rng(3)
    wins = _run(det, rng.normal(0, 1, int(RATE)), 1800.0)
    assert wins and not det.too_slow


@pytest.mark.parametrize("name", sorted(DETECTORS))
def test_a_rate_too_low_for_a_window_is_refused_at_configuration(name):
    """issue 18 D5: at 1 Hz a window held zero samples (ZeroDivisionError) or a hop of 0 never advanced."""
    with pytest.raises(ValueError, match=rf"sample rate 1 Hz is too low for the {name} detector"):
        make_detector(name, 1.0)


def _mild_worn_flank(rpm: float, seed: int):
    """bench_chatter's slow-growing mild chatter: a worn flank on a taper to 1.05 x the limit."""
    from lathed.analysis.lobes import StabilityLobes
    from lathed.analysis.process_damping import FlankWear
    from lathed.analysis.regen import DEFAULT_KF, DEFAULT_MODES
    b = float(StabilityLobes(DEFAULT_MODES, DEFAULT_KF).b_lim_at(rpm)[0][0]) * 1e3
    return simulate_cut([Segment(1.0, rpm, round(0.9 * b, 2)), Segment(4.0, rpm, round(1.05 * b, 2), 0.5)],
                        seed=seed, flank=FlankWear(), feed_mm_rev=0.3)


@pytest.mark.parametrize("rpm,seed", [(2000.0, 1), (2500.0, 1), (4000.0, 2)])
def test_sync_cusum_catches_mild_chatter_that_stays_below_the_threshold(rpm, seed):
    # held mild by the flank's ploughing, the index stays below the threshold (chaos_sync
    # misses the first two, and is 70 revolutions late on the third); the sum of its
    # sustained rise does not
    rec = _mild_worn_flank(rpm, seed)
    assert rec.label == "chatter"
    first = next((w.t_s for w in _run(make_detector("sync_cusum", RATE), rec.signal, rpm) if w.alarm), None)
    assert first is not None and first >= rec.unstable_at_s
    assert (first - rec.visible_at_s) * rpm / 60.0 < 25.0     # revolutions after visible


@pytest.mark.parametrize("rpm,depth,seed", [(1000, 1.2, 1001), (2000, 1.4, 1006), (500, 1.0, 1000)])
def test_sync_cusum_quiet_on_a_wandering_stable_cut(rpm, depth, seed):
    # regen.Wander: the level of a real stable cut drifts +-20 % over tens of revolutions
    rec = simulate_cut([Segment(6.0, rpm, depth)], seed=seed)
    assert rec.label == "stable"
    wins = _run(make_detector("sync_cusum", RATE), rec.signal, rpm)
    assert wins and not any(w.alarm for w in wins)


def test_cusum_ratio_between_one_and_the_threshold():
    for bad in (0.5, 1.0, 2.0, 3.0):
        with pytest.raises(ValueError, match="cusum_ratio"):
            make_detector("sync_residual", RATE, cusum_ratio=bad, threshold=2.0)
    assert make_detector("sync_residual", RATE, cusum_ratio=1.2).params["cusum_ratio"] == 1.2



@pytest.mark.parametrize("rpm,seed", [(2500.0, 1), (4000.0, 2)])
def test_mild_chatter_alarm_holds_while_the_chatter_does(rpm, seed):
    # raised by the sum at an index of 1.2-1.6, the alarm clears below the CUSUM's
    # allowance, not below the threshold's clear level (1.4): no on/off flapping
    rec = _mild_worn_flank(rpm, seed)
    wins = _run(make_detector("sync_cusum", RATE), rec.signal, rpm)
    raised = [w for w in wins if w.raised_by]
    assert raised and raised[0].raised_by in ("sustained rise", "growth")
    assert sum(a.alarm and not b.alarm for a, b in zip(wins, wins[1:])) == 0


class _Scripted(SyncResidualDetector):
    """Windows whose raw measure is given: the alarm logic alone."""
    name = "scripted"

    def __init__(self, raws, **params):
        self._raws = iter(raws)
        super().__init__(RATE, **params)

    def _measure(self, start, end, rpm):
        return next(self._raws, 1.0)


def _scripted_alarms(raws, **params):
    det = _Scripted(raws, cusum_ratio=1.2, threshold=1.6, **params)
    return [w for w in _run(det, np.random.default_rng(0).normal(size=60000), 6000) if w.raised_by]


def test_cusum_sums_a_sustained_rise_but_not_one_spike():
    learn = [1.0] * 4
    # 1.3 x the baseline, below the threshold, held: each window adds log(1.3/1.2)
    raised = _scripted_alarms(learn + [1.0] * 5 + [1.3] * 30)
    assert [w.raised_by for w in raised] == ["sustained rise"]
    # one window at 2.5 x: a chip striking, not chatter (counted as one threshold window)
    assert _scripted_alarms(learn + [1.0] * 5 + [2.5] + [1.0] * 30) == []
    # two at the threshold: the threshold rule raises it, as without a sum
    assert [w.raised_by for w in _scripted_alarms(learn + [1.0] * 5 + [1.7, 1.7] + [1.0] * 30)] == ["threshold"]


def test_growth_raises_the_alarm_the_entry_lifted_baseline_hides():
    # the baseline learned over the entry's ring sits 3 x above the steady level: chatter
    # growing to 3 x that level stays at an index of 1, under the CUSUM's allowance
    entry, steady = [3.0] * 4, [1.0] * 20
    grown = steady + [1.5, 2.2, 3.0, 3.0, 3.0] + [3.0] * 30
    assert _scripted_alarms(entry + grown, growth_ratio=0) == []
    raised = _scripted_alarms(entry + grown, growth_ratio=2.5)
    assert [w.raised_by for w in raised] == ["growth"] and raised[0].index == pytest.approx(1.0)


def test_growth_needs_two_windows_and_the_look_back():
    entry, steady = [3.0] * 4, [1.0] * 20
    # one window at 3 x: a chip striking
    assert _scripted_alarms(entry + steady + [3.0] + [1.0] * 20, growth_ratio=2.5) == []
    # a rise right after the learning windows: no 4 revolutions of steady cutting behind it yet
    assert _scripted_alarms(entry + [1.0, 3.0, 3.0] + [1.0] * 20, growth_ratio=2.5) == []


def test_an_alarm_raised_by_growth_holds_while_the_level_does():
    entry, steady = [3.0] * 4, [1.0] * 20
    det = _Scripted(entry + steady + [3.0] * 40 + [1.0] * 20, cusum_ratio=1.2, threshold=1.6, growth_ratio=2.5)
    wins = _run(det, np.random.default_rng(0).normal(size=60000), 6000)
    assert [w.raised_by for w in wins if w.raised_by] == ["growth"]
    on = [w.alarm for w in wins]
    first, last = on.index(True), len(on) - 1 - on[::-1].index(True)
    # held over the 40 windows at 3 x (index 1.0, under the clear level), cleared once back at 1 x
    assert all(on[first:last + 1]) and last - first >= 38 and not on[-1]


@pytest.mark.parametrize("tail, rise, alarms", [(None, 0.0, []), (None, 1.5, []), (0.0, 1.5, []),
                                               (0.0, 0.0, ["growth"])])
def test_the_tool_leaving_is_not_growth_for_the_ring_decays_within_the_window(monkeypatch, tail, rise, alarms):
    # bench_chatter's re-entry trap (seed base 2000): the release's ring lifts the revolution
    # difference 2-3 x within half a revolution; the ring's decay within the window (the tail
    # test, off with 0) tells it from chatter growing, and so does the shoulder rule (rise_ratio,
    # off with 0: the ring's rise is a step from a steady level, and it does not grow on)
    from lathed.analysis.chatter import rules
    if tail is not None:
        monkeypatch.setattr(rules, "GROWTH_TAIL", tail)
    rec = simulate_cut([Segment(1.5, 2500, 1.2), Segment(0.3, 2500, 0.0), Segment(1.5, 2500, 1.2)], seed=2010)
    assert rec.label == "stable"
    wins = _run(make_detector("sync_cusum", RATE, rise_ratio=rise), rec.signal, 2500.0)
    assert [w.raised_by for w in wins if w.raised_by] == alarms


@pytest.mark.parametrize("rule, rise, revs", [(True, 0.0, 1.67), (False, 0.0, 2.17), (True, 1.5, 3.17),
                                              (False, 1.5, 3.17)])
def test_chatter_rising_through_a_deeper_pass_counts_once_clear_of_the_step(monkeypatch, rule, rise, revs):
    # an abrupt onset (1 -> 3 mm at 2000 r/min, seed 14) whose level jumps 3.5 x within a
    # revolution: the windows whose revolution difference spans the step do not count, but the
    # index and the level keep rising through them; counting that alarms half a revolution
    # sooner (the tool's release rings down instead: test_no_alarm_when_the_tool_leaves_the_work).
    # With the shoulder rule (rise_ratio) the jump opens a deeper pass's span, where a stable
    # shoulder's echo near the limit rises as long (test_no_alarm_on_a_stable_shoulders_echo):
    # nothing there counts before rules.ECHO_REVS (1.67 before it, 2.67 without the rule)
    from lathed.analysis.chatter.base import RevolutionDetector
    if not rule:
        monkeypatch.setattr(RevolutionDetector, "_rising_from_step", lambda self, *a: False)
    rec = simulate_cut([Segment(1.0, 2000, 1.0), Segment(1.0, 2000, 3.0)], seed=14)
    assert rec.label == "chatter"
    first = next(w.t_s for w in _run(make_detector("sync_cusum", RATE, rise_ratio=rise), rec.signal, 2000.0)
                 if w.alarm)
    assert (first - rec.visible_at_s) * 2000 / 60.0 == pytest.approx(revs, abs=0.01)


def _stable_cut_to_its_end(name: str, rpm: float, **params) -> list:
    """A stable 1 mm pass on the simulated lathe whose speed is raised 20 % early in the cut,
    as suppression's avoid does: the detector is reset then (the daemon's rule at entry),
    so it learns the steady cut, not the entry's ring; it watches until 0.15 s after the
    tool left the work (the spindle load, polled, ends the cut that late)."""
    from lathed.sim.lathe import SimLathe
    from lathed.sim.program import Cut
    lathe = SimLathe(program=(Cut(rpm, 1.0, length_mm=20.0),), load_s=0.3, retract_s=0.3)
    det = make_detector(name, lathe.rate_hz, **params)
    wins, blocks, left = [], None, None
    while left is None or lathe.n_samples - left < 0.15 * lathe.rate_hz:
        was = lathe.phase
        data = lathe.step(1024)
        if lathe.phase == "cut" and was != "cut":
            blocks = 0
        elif was == "cut" and lathe.phase != "cut":
            left = lathe.n_samples
        if blocks is None:
            continue
        blocks += 1
        if blocks == 5:
            lathe.write("spindle_rpm_cmd", 1.2 * rpm)
        if blocks in (5, 9):              # the ramp's first and last frames
            det.reset()
        wins += det.process(data, lathe.rpm)
    return wins


@pytest.mark.parametrize("rpm", [1500.0, 2000.0, 2500.0, 4000.0])
@pytest.mark.parametrize("name", ["sync_residual", "sync_cusum", "chaos_sync"])
def test_no_alarm_when_the_tool_leaves_the_work(name, rpm):
    # the tool's release rings the structure at 5-8 x the cut's level, and the revolution
    # difference of a decaying ring looks like lost synchronisation for several revolutions
    # (more of them at 4800 r/min: the ring lasts the same time)
    assert not any(w.alarm for w in _stable_cut_to_its_end(name, rpm))


@pytest.mark.parametrize("rpm", [1500.0, 2000.0, 2500.0, 4000.0])
def test_the_release_ring_is_not_a_judged_index(rpm):
    # the index of the release's windows rises 3-5 x over the threshold; the detector does not
    # judge them (a level step) but for the first, which JudgedIndex drops when the next one
    # shows the step: a part's record keeps the highest of what stands
    from lathed.analysis.chatter.windows import JudgedIndex
    wins = [w for w in _stable_cut_to_its_end("sync_cusum", rpm) if not w.learning]
    assert max(w.index for w in wins) > 2 * wins[0].threshold and not any(w.alarm for w in wins)
    j = JudgedIndex()
    kept = [x for x in (j.push(w, w.t_s) for w in wins) if x is not None]
    assert len(kept) > len(wins) / 2 and max(i for i, _ in kept) < wins[0].threshold


@pytest.mark.parametrize("rpm", [1903.0, 2280.0, 3000.0, 4500.0, 6000.0])
def test_no_alarm_wherever_a_stable_pass_ends_on_the_window_grid(rpm):
    # issue 38's live false alarms: a pass on the simulated lathe at 0.7 x its limit, ending at 8
    # phases of a revolution (where the release falls on the windows is chance: live, it moved
    # with the instant a cure's speed reached the machine on a loaded host), then 0.15 s in air
    # (the cut state ends the cut that late). A release late in a window lifted its level 1.5-3 x:
    # the shoulder rule took it for a deeper pass, and the ring's next windows (a jump, then
    # falling) for growth out of it: 11 of these 40 ends alarmed
    from lathed.analysis.lobes import StabilityLobes
    from lathed.sim.lathe import LATHE_KF, LATHE_MODES
    depth = round(0.7 * float(StabilityLobes(LATHE_MODES, LATHE_KF).b_lim_at(np.array([rpm]))[0][0]) * 1e3, 2)
    alarmed = []
    for k in range(8):
        rec = simulate_cut([Segment(1.0 + k / 8 * 60.0 / rpm, rpm, depth), Segment(0.15, rpm, 0.0)],
                           modes=LATHE_MODES, kf_n_per_m2=LATHE_KF, feed_mm_rev=0.3, seed=k)
        assert rec.label == "stable"
        wins = _run(make_detector(DEFAULT_DETECTOR, RATE), rec.signal, rpm, block=1024)
        alarmed += [(k, w.raised_by) for w in wins if w.raised_by]
    assert alarmed == []


def test_without_jump_ratio_the_tool_leaving_raises_the_alarm():
    # the test above can fail: with the step not recognised, sync_residual cries chatter
    assert any(w.alarm for w in _stable_cut_to_its_end("sync_residual", 2000.0, jump_ratio=1000))


def _shoulder(name: str, seed: int, **params) -> list:
    """A stable cut that steps from 0.5 to 1.3 mm in the middle (a shoulder in the
    profile; the limit at 1000 r/min is about 1.5 mm): the same cut throughout, as the
    cut state sees it."""
    rec = simulate_cut([Segment(1.2, 1000, 0.5), Segment(1.2, 1000, 1.3)], seed=seed)
    assert rec.label == "stable"
    return _run(make_detector(name, RATE, **params), rec.signal, rec.rpm)


@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_no_alarm_on_a_shoulder(seed):
    # the residual of a stable cut scales with the cutting force, and near the limit the deeper
    # pass's echo lifts it 2-5 x over a few revolutions: the level the step brings is not chatter
    assert not any(w.alarm for w in _shoulder(DEFAULT_DETECTOR, seed))


def test_no_alarm_on_a_shoulder_whose_level_jumps():
    # 0.5 -> 1.3 mm at 1000 r/min (0.85 x the limit) lifts the level 3.6 x within a window (seed
    # 13030, bench_chatter's held-out shoulder table): taken for the tool's entry, not a deeper
    # pass, its level was judged against the shallower pass's baseline once its ring stopped
    # falling, and the sum alarmed (with the level's noise margin, rules.LEVEL_FALL)
    rec = simulate_cut([Segment(1.5, 1000, 0.5), Segment(1.5, 1000, 1.3)], seed=13030)
    assert rec.label == "stable"
    assert not any(w.alarm for w in _run(make_detector(DEFAULT_DETECTOR, RATE), rec.signal, rec.rpm))


def test_a_step_into_chatter_whose_level_plateaus_is_caught_as_it_grows():
    # the mild 4500 r/min step (1 -> 1.74 mm, 1.08 x the limit; bench_chatter's corpus, seed 1031):
    # its level held at 49.5 then 49.4 within the step's span, which the release's test read as
    # a ring falling (a 0.2 % dip, inside the level's own noise): caught 5.4 revolutions after
    # visible; with rules.LEVEL_FALL, as it grows, 2.4; 3.4 since growth out of a step waits for
    # a stable echo's peak (rules.ECHO_REVS: at 2.4 a 0.89 x shoulder's echo looks the same)
    rec = simulate_cut([Segment(1.0, 4500, 1.0), Segment(4.0, 4500, 1.74)], seed=1031)
    assert rec.label == "chatter"
    first = next(w.t_s for w in _run(make_detector(DEFAULT_DETECTOR, RATE), rec.signal, rec.rpm) if w.alarm)
    assert rec.unstable_at_s <= first and (first - rec.visible_at_s) * 4500 / 60.0 <= 4.0


# stable shoulders at 4500 r/min that sync_cusum alarmed on 2-3.5 revolutions after the step
# (bench/step_bound.py's drawn shoulders, seeds from 30000: 11 of its 48 at 4500 r/min): the echo
# of a step to 0.82-0.89 x the limit grows past rise_growth x the span's first window, as chatter
# out of a step does, or rises window after window through a jump (38033), then falls
# (rules.ECHO_REVS)
@pytest.mark.parametrize("lo,hi,seed", [(0.35, 0.89, 38001), (0.39, 0.88, 38014), (0.35, 0.87, 38021),
                                        (0.41, 0.82, 38025), (0.31, 0.84, 38033)])
def test_no_alarm_on_a_stable_shoulders_echo(lo, hi, seed):
    from lathed.analysis.chatter.cases import b_lim_mm
    lim = b_lim_mm(4500.0)
    rec = simulate_cut([Segment(1.5, 4500, round(lo * lim, 2)), Segment(1.5, 4500, round(hi * lim, 2))], seed=seed)
    assert rec.label == "stable"
    assert not any(w.alarm for w in _run(make_detector(DEFAULT_DETECTOR, RATE), rec.signal, rec.rpm))


def test_growth_at_a_deeper_pass_span_end_is_followed_one_window_more():
    # bench_chatter's 6000 r/min step (1.5 -> 2.4 mm, seed 1022): its last window in the step's
    # span grew past the echo's bound (rise_growth x the span's lowest), the next outside it grew
    # on, but the span had ended and its level was taken as the deeper pass's: 5.0 revolutions
    # after visible; followed one window more, as it grows, 3.5
    rec = simulate_cut([Segment(1.5, 6000, 1.5), Segment(1.5, 6000, 2.4)], seed=1022)
    assert rec.label == "chatter"
    first = next(w.t_s for w in _run(make_detector(DEFAULT_DETECTOR, RATE), rec.signal, rec.rpm) if w.alarm)
    assert rec.unstable_at_s <= first and (first - rec.visible_at_s) * 6000 / 60.0 <= 4.0


def test_without_the_shoulder_rule_a_shoulder_alarms():
    # the test above can fail: the threshold read the deeper pass's level as chatter (issue 38)
    assert any(w.alarm for w in _shoulder(DEFAULT_DETECTOR, 2, rise_ratio=0))


@pytest.mark.parametrize("rpm", [1500.0, 2500.0])
def test_a_step_into_chatter_is_caught_as_it_grows_out_of_the_step(rpm):
    # a deeper pass above the limit: the first revolutions look like a stable shoulder's, but
    # chatter grows beyond a stable echo's bound within the step's span
    rec = simulate_cut([Segment(1.0, rpm, 1.0), Segment(1.0, rpm, 3.0)], seed=11)
    assert rec.label == "chatter"
    wins = _run(make_detector(DEFAULT_DETECTOR, RATE), rec.signal, rpm)
    first = next(w for w in wins if w.alarm)
    assert first.t_s >= rec.unstable_at_s
    # 2.0-2.3 with the old threshold; 1.3-3.5 now (median 2.2 over 18 draws at 1500-2500 r/min)
    assert (first.t_s - rec.visible_at_s) * rpm / 60.0 <= 4.0


@pytest.mark.parametrize("seed", [3, 4])
def test_with_a_reference_chatter_is_caught_on_its_level(seed):
    # bench_chatter's reference rows: the shape gate held back a referenced threshold and sum
    # (the corpus's median 0.4 -> 2.0 revolutions); a reference vouches for the level, so a
    # step into chatter at 500 r/min (1 -> 2 mm) is caught within a revolution of being
    # visible, not 1.7-2.2 later when it has grown
    rec = simulate_cut([Segment(2.0, 500, 1.0), Segment(2.0, 500, 2.0)], seed=seed)
    assert rec.label == "chatter"
    det = make_detector(DEFAULT_DETECTOR, RATE)
    det.learn_reference(rec.signal[int(0.5 * RATE):int(1.5 * RATE)], 500.0)
    wins = _run(det, rec.signal[int(1.0 * RATE):], 500.0)
    first = next(w.t_s for w in wins if w.alarm) + 1.0
    assert 0 <= (first - rec.visible_at_s) * 500 / 60.0 <= 1.0


def test_with_a_reference_a_deeper_pass_is_judged_by_its_level():
    # a reference vouches for the level at its depth: the shoulder rule and the shape gate are
    # off, and the deeper pass (1.3 mm against a 0.5 mm reference) reads as the level it is
    rec = simulate_cut([Segment(1.2, 1000, 0.5), Segment(1.2, 1000, 1.3)], seed=2)
    det = make_detector(DEFAULT_DETECTOR, RATE)
    det.learn_reference(rec.signal[int(0.3 * RATE):int(1.1 * RATE)], 1000.0)   # the 0.5 mm pass, steady
    skip = int(0.5 * RATE)             # from steady cutting: a reference does not skip the entry's ring
    wins = _run(det, rec.signal[skip:], 1000.0)
    assert not any(w.alarm for w in wins if w.t_s < 0.7) and any(w.alarm for w in wins)


def _mid_cut(rpm: float, seed: int, **params) -> list:
    """A stable 10 s cut seen from its second second on, as a recording sees a cut (the
    baseline learned from steady cutting, without the entry's ring to lift it)."""
    rec = simulate_cut([Segment(11.0, rpm, 1.0)], seed=seed)
    assert rec.label == "stable"
    skip = int(rec.rate_hz)
    return _run(make_detector(DEFAULT_DETECTOR, RATE, **params), rec.signal[skip:], rpm)


@pytest.mark.parametrize("rpm, seed", [(770.0, 9020), (1000.0, 9031), (1000.0, 9032)])
def test_the_baseline_follows_a_stable_cuts_wander(rpm, seed):
    # learned in a few revolutions, the baseline knows nothing of the cut's wander, and the
    # CUSUM sums it into an alarm; raised to the calm windows' upper range, it does not
    assert any(w.alarm for w in _mid_cut(rpm, seed, follow_quantile=0, shape_min=0))
    assert not any(w.alarm for w in _mid_cut(rpm, seed, shape_min=0))
    assert not any(w.alarm for w in _mid_cut(rpm, seed))


@pytest.mark.parametrize("seed", [9040, 9041])
def test_no_alarm_on_a_long_stable_cut_learned_mid_cut(seed):
    # a wander in the first revolutions, before the baseline has seen 8 calm windows, changes the
    # level, not the spectrum's shape (chatter.shape): the gate holds the sum back
    assert any(w.alarm for w in _mid_cut(2000.0, seed, shape_min=0))
    assert not any(w.alarm for w in _mid_cut(2000.0, seed))


@pytest.mark.parametrize("rpm", [1000.0, 2000.0])
@pytest.mark.parametrize("what", ["mains 120 Hz at 3 x the cut's level", "gain rising 30 %"])
def test_a_mains_line_or_a_slow_gain_change_is_not_chatter(rpm, what):
    # the real data's README: a mains line (120 Hz and harmonics there, 100 Hz elsewhere)
    # or a slow change of gain must not raise an alarm
    rec = simulate_cut([Segment(4.0, rpm, 1.0)], seed=301)
    x, t = rec.signal, np.arange(len(rec.signal)) / RATE
    if what.startswith("mains"):
        a = 3 * np.median(np.abs(x[len(x) // 2:])) / 0.67
        x = x + a * (np.sin(2 * np.pi * 120 * t) + 0.5 * np.sin(2 * np.pi * 240 * t + 1)
                     + 0.3 * np.sin(2 * np.pi * 360 * t + 2))
    else:
        x = x * (1 + 0.3 * t / t[-1])
    assert not any(w.alarm for w in _run(make_detector(DEFAULT_DETECTOR, RATE), x, rpm))


@pytest.mark.parametrize("name", sorted(DETECTORS))
def test_every_detector_draws_the_chaos_eye(name):
    """The operator's chaos eye (the paper's graph) whatever the detector: the
    recent points against the cut's first window stay about its size in a stable
    cut and grow far past it in chatter."""
    from lathed.analysis.chatter.eye import eye_radius
    rec = simulate_cut([Segment(0.6, 1500, 1.0), Segment(0.8, 1500, 3.0)], seed=21)
    det, sizes = make_detector(name, RATE), {}
    assert det.eye_views()[1] is None            # nothing cut yet: no baseline to draw
    for i in range(0, len(rec.signal), 512):
        det.process(rec.signal[i:i + 512], 1500)
        for t in (0.5, 1.35):                    # stable; chattering
            if abs((i + 512) / RATE - t) < 0.005:
                (p1, p2), base = det.eye_views()
                sizes[t] = eye_radius(p1, p2) / eye_radius(*base)
    assert sizes[0.5] < 2.0 and sizes[1.35] > 20.0, sizes


def test_chatter_under_constant_surface_speed_is_caught():
    """G96: the speed follows the diameter, a slow drift (here 0.2-0.3 % a revolution), not
    a drive's ramp: the windows are judged, and chatter growing in them is caught (it was
    waited out as a speed change, and never alarmed)."""
    rec = simulate_cut([Segment(1.0, 1500, 1.0), Segment(2.0, 1800, 2.6, 2.0)], seed=1)
    assert rec.label == "chatter"
    wins = _run(make_detector(DEFAULT_DETECTOR, RATE), rec.signal, rec.rpm)
    first = next(w.t_s for w in wins if w.alarm)
    assert rec.unstable_at_s < first < rec.visible_at_s + 5 * 60 / 1800


@pytest.mark.parametrize("n0, n1", [(1000.0, 2000.0), (2000.0, 1200.0), (3000.0, 4000.0)])   # 0.3-2 % a rev
def test_a_stable_cut_under_constant_surface_speed_does_not_alarm(n0, n1):
    rec = simulate_cut([Segment(1.0, n0, 1.0), Segment(3.0, n1, 1.0, 3.0)], seed=11)
    assert rec.label == "stable"
    wins = _run(make_detector(DEFAULT_DETECTOR, RATE), rec.signal, rec.rpm)
    assert not any(w.alarm for w in wins) and sum(w.judged for w in wins) > 0.6 * len(wins)


@pytest.mark.parametrize("block", [64, 512])
def test_a_drive_ramp_is_waited_out_whatever_the_block_size(block):
    """A speed change at the drive's acceleration (2000 r/min/s: 3-4 % a revolution) is
    waited out over the ramp and settle_revs after it, with blocks of any size (a speed
    compared block to block moved by less than the old 0.2 % gate in small blocks)."""
    rec = simulate_cut([Segment(1.5, 2000, 1.2), Segment(1.5, 2600, 1.2, 0.3)], seed=5)
    wins = _run(make_detector(DEFAULT_DETECTOR, RATE), rec.signal, rec.rpm, block=block)
    during = [w for w in wins if 1.5 + 0.5 * 60 / 2000 <= w.t_s <= 1.8 + 60 / 2600]
    assert during and not any(w.judged for w in during)


def _light_pass(seed: int) -> tuple[np.ndarray, int, int]:
    """The simulated lathe's 0.3 mm finishing pass at 0.1 mm/rev, 2000 r/min: signal, first
    sample of the chip, and the sample the tool leaves at."""
    from lathed.sim.lathe import SimLathe
    from lathed.sim.program import Cut
    lathe = SimLathe(program=(Cut(2000, 0.3, 0.1, 6.0),), load_s=0.4, retract_s=0.3, seed=seed)
    out, start, end = [], None, None
    while lathe.part_count < 1:
        out.append(lathe.step(512))
        n = 512 * len(out)
        if lathe.phase == "cut" and start is None:
            start = n - 512
        if lathe.phase == "retract" and end is None and start is not None:
            end = n - 512
    return np.concatenate(out).astype(float), start, end


@pytest.mark.parametrize("seed", [0, 1])
def test_the_release_from_a_light_cut_is_an_impulse_not_chatter(seed):
    """The tool leaving a light cut rings the structure 5 x over the cut within a frame, but
    lifts a window's median |x| less than jump_ratio: the polled cut state (the feed signal)
    still says cutting, and the revolution difference read it as chatter.  The vibration's
    entry frame jumps 5 x over the frames before (chatter grows a few % a frame): the cut
    state tells the detector, whose windows across it do not count.  (The shoulder rule,
    rise_ratio, also holds the ring's span; off here, so the impulse alone is tested, and on in
    the last case: either suffices.)"""
    from lathed.analysis.cut.sources import VibrationCutDetector
    signal, start, end = _light_pass(seed)
    alarms = {}
    for told, rise in ((False, 0), (True, 0), ("shoulder rule", 1.5)):
        vib, det, alarm = VibrationCutDetector(51200.0), make_detector("sync_cusum", 51200.0, rise_ratio=rise), False
        for i in range(start, end + 10240, 1024):
            blk = signal[i:i + 1024]
            at = vib.process(blk)
            if told is True and at is not None and i > start + 51200 * 0.1 and vib.cutting:
                assert vib.entry_jump >= 2.0, vib.entry_jump
                det.impulse(at, 2000.0)
            alarm |= any(w.alarm for w in det.process(blk, 2000.0))
        alarms[told] = alarm
    assert alarms == {False: True, True: False, "shoulder rule": False}


def test_median_abs_is_numpys_bit_for_bit():
    from lathed.analysis.chatter.spectrum import median_abs
    rng = np.random.default_rng(3)
    for n in (1, 2, 3, 16, 1535, 1536, 4097):
        for _ in range(20):
            x = rng.standard_normal(n) * rng.uniform(0.1, 10.0)
            assert median_abs(x) == float(np.median(np.abs(x))), n


@pytest.mark.parametrize("name", ["sync_cusum", "chaos_sync"])
def test_history_sized_to_the_speed_gives_the_same_windows(name, monkeypatch):
    """A detector keeps the history its speed needs (growing for a slower one), not 10 s of
    every per-sample buffer (12-16 MB a channel): its windows are those of one that keeps all."""
    import lathed.analysis.chatter.base as dets
    rng = np.random.default_rng(3)
    x = rng.normal(size=51200 * 12)
    speeds = [1500.0 if i < 51200 * 6 else 200.0 for i in range(0, len(x), 1024)]

    def windows():
        det = make_detector(name, 51200.0)
        out = {}
        for k, i in enumerate(range(0, len(x), 1024)):
            out.update({w.t_s: (w.index, w.alarm, w.judged) for w in det.process(x[i:i + 1024], speeds[k])})
        return out, len(det._x)
    small, size = windows()
    monkeypatch.setattr(dets, "_HIST_START", dets._HIST)
    full, _ = windows()
    assert len(small) > 100 and all(full[t] == w or np.isnan(w[0]) and np.isnan(full[t][0])
                                    for t, w in small.items())
    # but a window the slower speed's first revolution would reach before the kept history
    # for: across the speed change, never judged
    assert all(not full[t][2] for t in set(full) - set(small)) and len(full) - len(small) <= 2
    assert size < dets._HIST // 4          # 200 r/min at 51.2 kS/s: grown, still a fraction of the most
