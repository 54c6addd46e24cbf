"""Suppression's record of one cut (lathed.analysis.cut_log): what it judges a speed by."""
from __future__ import annotations

from lathed.analysis.cut_log import MIN_JUDGE_REVS, CutTracker


def test_a_dwell_judges_no_speed_stable():
    # the feed stopped mid-pass for 1 s at 2000 r/min: 33 revolutions with no chip were counted as
    # judged, so a cure written just before it was called stable (and remembered) on no evidence
    c = CutTracker("lathe", "T0101", "C45")
    c.start(0.0, 2000.0)
    c.chatter(0.1, True, 312.0)
    c.action(0.1, {"trigger": "alarm", "rpm_after": 2300.0}, judge_from_t=0.2)
    c.chatter(0.15, False, None)
    for k in range(3):
        c.speed(0.2 + 0.01 * k, 2300.0)
    c.dwell(0.22, True)
    for k in range(1, 11):
        c.speed(0.22 + 0.1 * k, 2300.0)          # a second standing in the work
    c.dwell(1.22, False)
    rec = c.end(1.24)
    cure = rec["speeds"][-1]
    assert cure["judged_revs"] < MIN_JUDGE_REVS < cure["revs"], cure
    assert rec["cured"] is False and rec["outcome"] == "chatter"
    c.start(2.0, 2300.0)                        # the next cut judges again
    c.speed(3.0, 2300.0)
    assert c.end(3.0)["outcome"] == "stable"


def test_a_speed_whose_index_is_still_rising_is_not_judged_stable():
    # chatter a little above the limit regrows slowly from the quiet a speed change leaves: no
    # alarm within the cure's judged revolutions, but the detector's index rising all through them
    from lathed.analysis.cut_log import RISING_RATIO, cut_rows

    def cure(levels):
        c = CutTracker("lathe", "T0101", "C45")
        c.depth_mm, c.feed_mm_rev = 3.0, 0.3
        c.start(0.0, 3000.0)
        c.chatter(0.1, True, 195.0)
        c.action(0.1, {"trigger": "alarm", "rpm_after": 2000.0, "sent": True}, judge_from_t=1.0)
        c.chatter(0.2, False, None)
        for k, x in enumerate(levels):           # a window every half revolution from 1.0 s
            t = 1.0 + 0.015 * k
            c.speed(t, 2000.0)
            c.index(t, x)
        return c.end(1.0 + 0.015 * len(levels))

    n = 60                                       # 30 judged revolutions
    rec = cure([0.15 * 1.03 ** k for k in range(n)])
    grown = rec["speeds"][-1]
    assert grown["judged_revs"] >= MIN_JUDGE_REVS and grown["first_alarm_s"] is None, grown
    assert grown["outcome"] is None and grown["rising"] >= RISING_RATIO, grown
    assert rec["cured"] is False
    assert cut_rows([rec])[1]["chatter index still rising when the speed ended"] == 1
    # a level that wanders, or falls as the entry's ring dies, is judged stable
    flat = cure([0.15 * (1 + 0.05 * (-1) ** k) for k in range(n)])["speeds"][-1]
    falling = cure([0.3 * 0.98 ** k for k in range(n)])["speeds"][-1]
    assert flat["outcome"] == falling["outcome"] == "stable", (flat, falling)
    # a stable speed held long: only its last revolutions are looked at (a slow wander is no growth)
    long = cure([0.1 * 1.001 ** k for k in range(2000)])["speeds"][-1]     # 7 x over 1000 revolutions
    assert long["outcome"] == "stable" and long["rising"] < RISING_RATIO, long
