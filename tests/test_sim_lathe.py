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


def test_a_block_carries_the_speed_it_was_cut_at():
    """The vibration frame's rpm was read before the step, so across a ramp it was the speed
    one step (60 r/min at 3000 r/min/s, 20 ms) before the one the samples were cut at."""
    lathe = SimLathe(program=(Cut(2000, 1.0),), load_s=0.2)
    cut_at = []
    run = lathe.cutter.run
    lathe.cutter.run = lambda n, rpm, *a: cut_at.append(rpm) or run(n, rpm, *a)
    while lathe.phase != "cut":
        lathe.step(1024)
    lathe.write("spindle_rpm_cmd", 2400.0)
    speeds = []
    for _ in range(10):                           # the ramp: 400 r/min at 3000 r/min/s, 7 blocks
        lathe.step(1024)
        speeds.append(lathe.block_rpm)
    assert speeds == cut_at[-10:]
    assert len(set(speeds)) > 5 and speeds[-1] == 2400.0
