"""The simulated lathe's own record of each part: the truth the closed loop is timed against."""
from __future__ import annotations

from lathed.sim.lathe import Cut, SimLathe


def test_a_stable_part_after_a_chattering_one_keeps_no_marks_of_it():
    """The simulated lathe's watch kept tracking the last part above the limit, so the next
    (stable) part's record copied its surface waviness."""
    lathe = SimLathe(program=(Cut(2500, 3.0, length_mm=10.0), Cut(2500, 1.0, length_mm=10.0)),
                     load_s=0.2, retract_s=0.2)
    while len(lathe.parts) < 3:                  # both parts cut (the third has begun loading)
        lathe.step(4096)
    chattered, stable = lathe.parts[0], lathe.parts[1]
    assert chattered.visible_at_s is not None and chattered.waviness_um
    assert stable.cut_end_s is not None
    assert (stable.visible_at_s, stable.waviness_um) == (None, [])
