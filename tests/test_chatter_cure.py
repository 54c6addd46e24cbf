"""A cure that does not cure is chatter too: the detector judges the speed suppression moved to.

A speed change makes the detector's windows (a number of revolutions) another length, and so the
spectrum's bands others.  The shape gate compared a window's bands with a baseline of the old
length's: no shape at the new speed, and the threshold and the sum could not alarm there for the
rest of the cut.  On the simulated lathe (its workpiece mode 12 % above the configured one, the
live refit's test) a 3 mm pass at 2750 r/min chatters, the override takes it to 2292 r/min, where
its limit is 2.4 mm: the chatter dies, grows back within a second to 14 x its first alarm's level,
and no alarm was raised; the cut record said "stable" at 2292 r/min.
"""
import numpy as np
import pytest

from lathed.analysis.chatter.registry import make_detector
from lathed.analysis.chatter.windows import JudgedIndex
from lathed.analysis.cut_log import MIN_JUDGE_REVS, RISING_RATIO, CutTracker, cut_rows
from lathed.analysis.lobes import Mode
from lathed.analysis.stability import StabilityModel
from lathed.sim.lathe import LATHE_KF, LATHE_MODES, SimLathe
from lathed.sim.program import parse_cut

SHIFTED = (Mode(round(LATHE_MODES[0].fn_hz * 1.12, 1), 0.03, 7.5e7, 0.0), LATHE_MODES[1])


def cured_pass(detector: str, rpm: float, override_pct: float):
    """(the alarms' (time, rpm, level) in the cut, the level at the cut's end), the override
    written at the first alarm as suppression writes it."""
    sim = SimLathe(program=(parse_cut(f"{rpm:g},3.0,0.3,24"),), modes=SHIFTED, load_s=0.3, retract_s=0.2)
    det = make_detector(detector, 51200.0)
    t0, was, alarms, level = None, False, [], 0.0
    while True:
        a = sim.step(1024)
        if sim.phase != "cut":
            if t0 is not None:
                return alarms, level
            continue
        t0 = sim.t if t0 is None else t0
        level = float(np.std(a))
        for w in det.process(a.astype(float), sim.block_rpm):
            if w.alarm and not was:
                alarms.append((sim.t - t0, sim.block_rpm, level))
                if len(alarms) == 1:
                    sim.write("spindle_override_pct", override_pct)
            was = w.alarm


@pytest.mark.parametrize("detector", ["sync_cusum", "chaos_sync"])
def test_chatter_growing_back_at_the_cure_speed_alarms(detector):
    alarms, end_level = cured_pass(detector, 2750.0, 83.35)
    assert alarms and alarms[0][1] == pytest.approx(2750.0), alarms
    assert end_level > 5 * alarms[0][2], (alarms, end_level)        # it does grow back
    again = [a for a in alarms[1:] if abs(a[1] - 2292.2) < 1.0]
    assert again, f"no alarm at the cure speed: {alarms}, level at the end {end_level:.0f} m/s²"
    assert again[0][2] < 0.2 * end_level, again          # raised while it grew, not at its height


def cure_record(rpm: float, depth_mm: float, cure_rpm: float, length_mm: float = 28.0) -> dict:
    """The cut record suppression keeps (lathed.analysis.cut_log) of a pass on the simulated lathe
    entering at ``rpm``, moved to ``cure_rpm`` at its first alarm: the tracker fed as the daemon
    feeds it (speed, alarms, the judged index), the cure judged once the ramp and 20 revolutions
    of settling are over."""
    sim = SimLathe(program=(parse_cut(f"{rpm:g},{depth_mm:g},0.3,{length_mm:g}"),), load_s=0.3, retract_s=0.2)
    det, judged, cut = make_detector("sync_cusum", 51200.0), JudgedIndex(), CutTracker("lathe", "T0101", "C45")
    cut.depth_mm, cut.feed_mm_rev = depth_mm, 0.3
    was, moved = False, False
    while True:
        a = sim.step(1024)
        if sim.phase != "cut":
            if cut.active:
                return cut.end(sim.t)
            continue
        if not cut.active:
            cut.start(sim.t, sim.block_rpm)
        cut.speed(sim.t, sim.block_rpm)
        for w in det.process(a.astype(float), sim.block_rpm):
            j = judged.push(w, sim.t)
            if j is not None:
                cut.index(j[1], j[0])
            if w.alarm != was:
                cut.chatter(sim.t, w.alarm, w.chatter_frequency_hz)
            if w.alarm and not was and not moved:
                sim.write("spindle_rpm_cmd", cure_rpm)
                hold = abs(cure_rpm - rpm) / 3000.0 + 20 * 60.0 / cure_rpm     # the drive's ramp, settle_revs
                cut.action(sim.t, {"trigger": "alarm", "rpm_after": cure_rpm, "sent": True}, sim.t + hold)
                moved = True
            was = w.alarm


def test_a_cure_above_the_limit_regrowing_too_slowly_to_alarm_is_not_recorded_stable():
    # a 3.68 mm pass entering at 4269 r/min chatters; the frequency rule moves it to 1976 r/min,
    # where the limit is 2.94 mm (1.25 x). The chatter dies in the ramp and grows back from the
    # quiet, but against a baseline learned over the entry's ring (10 x the quiet level) no alarm
    # comes in a 28 mm pass's 28 judged revolutions: the record called the speed stable, evidence
    # the stability learn was fitted on (issue 41's live runs, 24 mm passes: 2 such cures in 200)
    lathe = StabilityModel(LATHE_MODES, LATHE_KF)
    assert 3.677 / (float(lathe.limit(1976.0)[0][0]) * 1e3) == pytest.approx(1.25, abs=0.01)
    rec = cure_record(4269.0, 3.677, 1976.0)
    entry, cure = rec["speeds"]
    assert entry["outcome"] == "chatter" and cure["trigger"] == "alarm" and cure["first_alarm_s"] is None, rec
    assert cure["judged_revs"] >= MIN_JUDGE_REVS, cure
    assert cure["outcome"] is None and cure["rising"] >= RISING_RATIO, cure
    assert rec["cured"] is False
    rows, skipped = cut_rows([rec])
    assert len(rows) == 1 and skipped == {"chatter index still rising when the speed ended": 1}
    # it was chatter: 4 mm more of the pass at that speed and the alarm comes
    assert cure_record(4269.0, 3.677, 1976.0, length_mm=32.0)["speeds"][-1]["outcome"] == "chatter"
    # a cure to a speed well below the limit (0.54 x) is stable, and says so
    ok = cure_record(4178.0, 3.08, 2305.0)["speeds"][-1]
    assert ok["outcome"] == "stable" and ok["rising"] < RISING_RATIO, ok
