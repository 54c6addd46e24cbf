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


def test_a_face_at_constant_surface_speed_follows_the_diameter():
    """G96: the speed is 1000 V / (pi D) as the tool moves in, up to the clamp; the spindle
    load falls with the radius; a written speed is the pass's speed from then on."""
    import math

    face = Cut(2600, 1.5, 0.1, 4.5, css_m_min=190.0)        # 30 -> 21 mm; 2880 r/min clamped at 2600
    lathe = SimLathe(program=(face,), load_s=0.2, retract_s=0.2)
    seen = []
    while not lathe.parts[0].cut_end_s:
        lathe.step(1024)
        if lathe.phase == "cut":
            d = lathe.diameter_mm
            seen.append((d, lathe.program_rpm, lathe.rpm, lathe.load_pct, lathe.registers()["x_mm"]))
    d, prog, rpm, load, x = map(list, zip(*seen))
    assert d[0] > 29.5 and d[-1] < 21.5 and all(a >= b for a, b in zip(d, d[1:]))
    assert math.isclose(prog[0], 1000 * 190 / (math.pi * d[0]), rel_tol=1e-9)
    assert max(prog) == 2600.0                                # the clamp
    assert all(abs(r - p) < 3000 * 1024 / 51200 + 1e-9 for r, p in zip(rpm, prog))   # followed
    assert load[-1] < 0.8 * load[0] and x[-1] == d[-1] / 2
    assert lathe.parts[0].css_m_min == 190.0 and lathe.parts[0].visible_at_s is None
    # a write: the speed the daemon sent, no longer the diameter's
    lathe = SimLathe(program=(face,), load_s=0.2)
    while lathe.phase != "cut":
        lathe.step(1024)
    lathe.write("spindle_rpm_cmd", 1800.0)
    for _ in range(30):
        lathe.step(1024)
    assert lathe.rpm == 1800.0 and lathe.diameter_mm < 29 and lathe.registers()["spindle_override_pct"] < 100


def test_a_facing_pass_in_a_program_is_checked():
    import pytest

    from lathed.sim.program import parse_cut
    assert parse_cut("3500,1.5,0.1,4.5,css=190") == Cut(3500, 1.5, 0.1, 4.5, css_m_min=190.0)
    assert parse_cut("2000,1").css_m_min == 0.0
    with pytest.raises(ValueError, match=r"css= takes a surface speed in m/min"):
        parse_cut("3500,1.5,0.1,4.5,css=fast")
    with pytest.raises(ValueError, match=r"a facing pass needs css 10..2000 m/min and a radial length under "
                                         r"the bar's radius \(15 mm\)"):
        parse_cut("3500,1.5,0.1,20,css=190")
    with pytest.raises(ValueError, match=r"expected RPM,DEPTH_MM\[,FEED_MM_REV\[,LENGTH_MM\]\]\[,css=M_MIN\]"):
        parse_cut("3500,1.5,0.1,4.5,6,css=190")
    assert parse_cut("2000,0.9,0.3,20,tool=2").tool == 2
    assert parse_cut("3500,1.5,0.1,4.5,tool=2,css=190") == Cut(3500, 1.5, 0.1, 4.5, css_m_min=190.0, tool=2)
    with pytest.raises(ValueError, match=r"tool= is a turret position of the simulated lathe: 1, 2"):
        parse_cut("2000,1,tool=3")
    with pytest.raises(ValueError, match=r"unknown speed=; allowed: css=, tool="):
        parse_cut("2000,1,speed=3")


def test_a_threading_pass_sets_the_controls_threading_signal_for_its_cycle():
    import pytest

    from lathed.sim.program import parse_cut
    assert parse_cut("2000,0.3,1.5,40,thread=1.5") == parse_cut("2000,0.3,thread=1.5") == Cut(
        2000, 0.3, 1.5, 40, thread=True)
    for text, why in (("2000,0.3,1.0,thread=1.5", "a thread.s feed is its pitch: 1.0 against thread=1.5"),
                      ("2000,0.3,thread=1,thread=1.5", "thread= given twice"),
                      ("2000,0.3,thread=fine", "thread= takes the pitch in mm"),
                      ("2000,0.3,thread=3", "thread= takes a pitch of 0..2 mm"),
                      ("2000,0.3,dwell=1,thread=1", "a threading pass takes no css= \\(G96\\), dwell=")):
        with pytest.raises(ValueError, match=why):
            parse_cut(text)
    lathe = SimLathe(program=tuple(parse_cut(c) for c in ("2000,1.0,0.3,10", "2000,0.3,1.5,10,thread=1.5")),
                     load_s=0.2, retract_s=0.2)
    seen = set()
    while len(lathe.parts) < 3:
        lathe.step(2048)
        r = lathe.registers()
        seen.add((lathe.part_index, lathe.phase, r["threading"], r["feed_mm_rev"]))
    assert {(i, t, f) for i, _, t, f in seen} == {(0, 0, 0.3), (1, 1, 1.5), (2, 0, 0.3)}
    assert {"load", "cut", "retract"} <= {ph for i, ph, *_ in seen if i == 1}
    assert [p.thread for p in lathe.parts] == [False, True, False]


def test_the_turrets_second_tool_is_a_boring_bar_with_its_own_limit():
    from lathed.sim.program import parse_cut
    lathe = SimLathe(program=tuple(parse_cut(c) for c in ("2000,1.0,0.3,10", "2000,0.9,0.3,10,tool=2")),
                     load_s=0.2, retract_s=0.2)
    tools = set()
    while len(lathe.parts) < 3:
        lathe.step(2048)
        if lathe.phase == "cut":
            tools.add((lathe.part_index, lathe.registers()["tool_number"]))
    turning, bar = lathe.parts[0], lathe.parts[1]
    assert tools == {(0, 1), (1, 2)}
    assert turning.b_lim_mm > 2.3 and 0.5 < bar.b_lim_mm < 0.7
    assert turning.visible_at_s is None and bar.visible_at_s is not None     # 0.9 mm chatters on the bar


def test_a_dwell_stops_the_feed_with_the_tool_in_the_work():
    """dwell=S: halfway along the pass the feed stands S seconds (G04), the spindle turning.
    The chip is what the tool advanced over the last revolution, so it thins to nothing within
    one (sparkout): the load falls to the spindle's own, the vibration to the air's; the
    control's cutting-feed signal is off (Fanuc's CUT), the axes stand, the tool is in the work.
    Then the pass goes on, the chip growing back over a revolution."""
    import numpy as np
    import pytest

    from lathed.sim.lathe import IDLE_LOAD_PCT
    from lathed.sim.program import parse_cut
    cut = parse_cut("2000,1.0,0.3,20,dwell=0.5")
    assert cut == Cut(2000, 1.0, 0.3, 20, dwell_s=0.5) and parse_cut("2000,1").dwell_s == 0.0
    for bad in ("2000,1,dwell=0", "2000,1,dwell=61", "2000,1,dwell=long"):
        with pytest.raises(ValueError, match=r"dwell= takes"):
            parse_cut(bad)
    lathe = SimLathe(program=(cut,), load_s=0.2, retract_s=0.2)
    chips = []
    run = lathe.cutter.run
    lathe.cutter.run = lambda *a: chips.append(run(*a)) or chips[-1]
    steps = []        # (time at the step's end, registers, load, vibration rms, deepest chip)
    while len(lathe.parts) < 2:
        n = len(chips)
        x = lathe.step(1024)
        h = max(float(np.max(b.h_m)) for b in chips[n:])
        steps.append((lathe.t, lathe.registers(), lathe.load_pct, float(np.std(x)), h))
    rec = lathe.parts[0]
    assert rec.dwell_end_s - rec.dwell_start_s == pytest.approx(0.5, abs=0.021)
    # the pass is its length at its feed, plus the dwell
    assert rec.cut_end_s - rec.cut_start_s == pytest.approx(20 / (0.3 * 2000 / 60) + 0.5, abs=0.05)
    rev = 60 / 2000
    air = [s for s in steps if s[1]["depth_of_cut_mm"] == 0 and s[0] < rec.cut_start_s]
    cutting = [s for s in steps if rec.cut_start_s + 0.1 < s[0] < rec.dwell_start_s]
    dwell = [s for s in steps if rec.dwell_start_s + 3 * rev < s[0] <= rec.dwell_end_s]   # sparkout: 3 revs
    after = [s for s in steps if rec.dwell_end_s + 2 * rev < s[0] < rec.cut_end_s]
    assert len(dwell) > 15 and cutting and after and air
    air_rms = float(np.median([s[3] for s in air]))
    for t, regs, load, rms, h in dwell:
        assert regs["cutting_feed"] == 0 and regs["depth_of_cut_mm"] == 1.0       # in the work, not feeding
        assert (regs["x_mm"], regs["y_mm"]) == (14.0, pytest.approx(10.0))        # the axes stand mid-pass
        assert load < IDLE_LOAD_PCT + 0.05 and h < 1e-6 and rms < 1.3 * air_rms   # no chip to speak of
    for t, regs, load, rms, h in cutting + after:
        assert regs["cutting_feed"] == 1 and load > IDLE_LOAD_PCT + 15 and h > 2e-4
    # the chip thins over the revolution after the stop, not at once: a step there rings the structure
    first = [s for s in steps if rec.dwell_start_s + 0.01 < s[0] <= rec.dwell_start_s + rev + 0.01]
    assert first and all(IDLE_LOAD_PCT + 1 < s[2] < cutting[-1][2] - 1 for s in first), first
    assert max(s[3] for s in steps if rec.dwell_start_s < s[0] <= rec.dwell_end_s) < max(s[3] for s in cutting)


def test_part_program_features_along_a_pass():
    """step= (a shoulder), flat= (a flat or a keyway from a place along the pass) and groove= (no
    material over a stretch): the chip's depth and the interrupted share of a revolution follow
    the tool along the pass, the depth register shows the chip's, and a bad one is one line."""
    import pytest

    from lathed.sim.program import parse_cut
    cut = parse_cut("2000,1.0,0.3,30,step=2.0@10,flat=15@20,groove=5+2")
    assert (cut.step_depth_mm, cut.step_at_mm, cut.flat_deg, cut.flat_at_mm) == (2.0, 10.0, 15.0, 20.0)
    assert [cut.depth_at(y) for y in (1, 5.5, 8, 12)] == [1.0, 0.0, 1.0, 2.0]
    assert [cut.flat_at(y) for y in (1, 19, 21)] == [0.0, 0.0, 15.0]
    assert parse_cut("2000,1,flat=25").flat_at(0.0) == 25.0
    for text, why in (("2000,1,step=2", "step= takes DEPTH_MM@MM"),
                      ("2000,1,step=two@3", "step= takes DEPTH_MM@MM as numbers"),
                      ("2000,1,0.3,40,step=2@50", "step= at 50 mm is outside the pass's 0..40 mm"),
                      ("2000,1,step=20@5", "step= takes a depth of 0..10 mm"),
                      ("2000,1,flat=200", "flat= takes 0..180 degrees"),
                      ("2000,1,groove=10", "groove= takes MM\\+WIDTH_MM"),
                      ("3500,1.5,0.1,4.5,css=190,flat=10", "a facing pass \\(css=\\) takes no step=")):
        with pytest.raises(ValueError, match=why):
            parse_cut(text)
    lathe = SimLathe(program=(cut,), load_s=0.2, retract_s=0.2)
    seen = {}
    while lathe.part_index == 0:
        lathe.step(1024)
        if lathe.phase == "cut":
            seen[round(lathe.y_mm)] = (lathe.registers()["depth_of_cut_mm"], lathe.cutter.flat_fraction * 360)
    assert seen[3] == (1.0, 0.0) and seen[6] == (0.0, 0.0) and seen[15] == (2.0, 0.0) and seen[25] == (2.0, 15.0)
