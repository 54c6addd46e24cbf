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
