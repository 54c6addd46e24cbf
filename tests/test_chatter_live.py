"""Chatter detection inside the running daemon, on the simulated lathe, seen
through lathectl as an operator sees it (issue 3, last Done-when item)."""
from __future__ import annotations

import json
import re
from contextlib import contextmanager

import pytest

from tests.conftest import DEPTH_REGISTER, Daemon, default_table, events, sim_call, sim_config, wait_until


CHATTER = default_table("chatter")


def sim_set(d, depth) -> dict:
    """Set the simulated depth override once the simulator's control socket is up
    (the daemon is ready before its simulator and drivers are)."""
    return wait_until(lambda: sim_call(d.paths["sim"], "set", {"depth_mm": depth}), what="simulator control")


def chatter(d) -> dict:
    return d.item("analyzers", "chatter")


def part_count(d) -> int:
    return int(sim_call(d.paths["sim"], "status")["registers"]["part_count"])


def test_depth_past_the_limit_raises_a_chatter_event(sim_daemon):
    d = sim_daemon(analyzers=CHATTER)
    wait_until(lambda: chatter(d)["state"] == "running", what="chatter analyzer running")
    assert sim_set(d, 3.0) == {"depth_mm": 3.0}
    # every part now cuts 3 mm deep, above the ~2.4 mm limit: the first cut chatters
    alarms = wait_until(lambda: events(d, "chatter_alarm"), timeout=30, interval=0.2, what="chatter_alarm event")
    a = alarms[0]
    assert a["source"] == "chatter"
    p = a["payload"]
    assert p["machine"] == "lathe" and p["tool"] == "T0101" and p["material"] == "C45"
    # the default config maps no depth register: the cut is seen by the feed, the load or the vibration
    assert p["depth_mm"] is None and p["cut_seen_by"] in ("feed", "load", "vibration")
    assert p["load_pct"] > 20     # a 3 mm chip at 30 mm diameter loads the spindle
    assert p["detector"] == chatter(d)["detector"]
    # over the threshold, or held above the CUSUM's allowance (sync_cusum) long enough
    assert p["raised_by"] in ("threshold", "sustained rise")
    assert p["index"] > (p["threshold"] if p["raised_by"] == "threshold" else 1.0) and p["threshold"] > 0
    assert 50 < p["chatter_frequency_hz"] < 2000      # the structure's modes are at 190 and 620 Hz
    assert round(p["rpm"]) in (1500, 2000, 2500)
    # the analyzer's own status reports it
    st = chatter(d)
    assert st["alarms"] >= 1 and st["windows"] > 0
    assert st["cut_from"] == ["feed", "load", "vibration"]
    assert st["threshold"] is not None
    wait_until(lambda: chatter(d)["cut_state"] == "chatter" or events(d, "chatter_cleared"),
               timeout=15, what="chatter state or a cleared alarm")
    # the human views name it too
    assert "chatter_alarm" in d.ctl("events").stdout
    assert re.search(r"^\s+chatter\s.*\b[1-9]\d* alarm\(s\)", d.ctl("status").stdout, re.M)
    # the depth goes back to the program; the cut ends and the alarm clears with it
    assert sim_set(d, None)["depth_mm"] in (1.0, 3.0)
    cleared = wait_until(lambda: events(d, "chatter_cleared"), timeout=30, interval=0.2,
                         what="chatter_cleared event")
    assert cleared[0]["payload"]["machine"] == "lathe"


def test_cut_state_without_a_depth_register(sim_daemon):
    d = sim_daemon(analyzers=CHATTER)
    assert not re.search(r"^depth_of_cut_mm", d.cfg.read_text(), re.M)     # the default map has none
    assert sim_set(d, 1.0) == {"depth_mm": 1.0}
    # the cut is seen (by the cutting-feed signal, the spindle load or the vibration) and
    # lathectl status says so, and what saw the chip after an approach at feed
    st = wait_until(lambda: (s := chatter(d))["cutting"] and s, timeout=20, interval=0.1, what="a cut seen")
    assert st["cut_seen_by"] in ("feed", "load", "vibration") and st["cut_state"] in ("learning", "watching")
    wait_until(lambda: re.search(r"^\s+chatter\s.*\b(?:learning|watching) \(cut seen by (?:feed|load|vibration)"
                                 r"(?:, chip by (?:load|vibration))?\)",
                                 d.ctl("status").stdout, re.M), timeout=10, interval=0.1,
               what="cut state in lathectl status")
    # and its end, when the tool retracts
    st = wait_until(lambda: not (s := chatter(d))["cutting"] and s, timeout=20, interval=0.1,
                    what="the cut's end")
    assert st["cut_state"] == "idle" and st["cut_seen_by"] is None


def test_no_false_alarm_on_stable_cuts(sim_daemon):
    d = sim_daemon(analyzers=CHATTER)
    assert sim_set(d, 1.0) == {"depth_mm": 1.0}
    start = part_count(d)
    # three parts at 1 mm (the program's speeds 1500, 2000, 2500 r/min): the detector
    # learns each cut and watches it, and never cries chatter
    wait_until(lambda: part_count(d) >= start + 3, timeout=45, interval=0.3, what="three stable parts")
    st = chatter(d)
    assert st["windows"] > 20, st        # the detector did analyse the cuts
    assert st["alarms"] == 0, st
    assert events(d, "chatter_alarm") == []
    assert st["cut_state"] != "chatter"


def with_detector(detector: str) -> str:
    """The shipped chatter table with another detector."""
    table, n = re.subn(r'^detector = "\w+"', f'detector = "{detector}"', CHATTER, flags=re.M)
    assert n == 1, CHATTER
    return table


@pytest.mark.parametrize("detector", ["chaos_sync", "sync_cusum"])
def test_no_alarm_when_the_tool_leaves_a_stable_cut(tmp_path, detector):
    # 3 mm parts at 1500 and 2000 r/min, above the limit there; suppression's avoid moves each
    # at entry to a speed the lobes call stable, and the detector learns its baseline afresh
    # after that change: from the steady cut, not from the entry's ring. When the tool leaves
    # the work its release rings the structure at several times the cut's level, and the cut
    # (seen by the polled spindle load too) ends up to a poll later: without jump_ratio the
    # ring's revolution difference read as chatter (index 4-6) at the end of stable cuts.
    from lathed.analysis.lobes import StabilityLobes
    from lathed.sim.lathe import LATHE_KF, LATHE_MODES
    suppress = default_table("suppress")
    cfg, paths = sim_config(tmp_path, analyzers=with_detector(detector) + "\n" + suppress + "\navoid = true\n",
                            registers=DEPTH_REGISTER,
                            # at the shipped rate: at 25.6 kS/s the sync_cusum case alarms 0.12 s into a
                            # cut, on the block where the avoid's speed lands, and this test cannot tell
                            # that alarm's evidence from the programmed speed's (issue 38, open)
                            simulator='program = ["1500,3.0", "2000,3.0"]\nrate_hz = 51200')
    d = Daemon(cfg, paths["socket"])
    d.paths = paths
    try:
        d.wait_ready()
        wait_until(lambda: sim_call(paths["sim"], "status")["part"] >= 5, timeout=90, interval=0.3,
                   what="five parts cut")
        lobes = StabilityLobes(LATHE_MODES, LATHE_KF)
        parts = [p for p in sim_call(paths["sim"], "status", {"parts": 16})["parts"] if p["cut_end_s"] is not None]
        # the cuts the test is about: moved at entry to a speed where 3 mm is stable
        stable = [p for p in parts if p["speed_writes"]
                  and float(lobes.b_lim_at(p["speed_writes"][-1]["rpm"])[0][0]) * 1000 > 3.0]
        assert len(stable) >= 4, parts
        st = chatter(d)
        assert st["detector"] == detector and st["windows"] > 40, st
        alarms = events(d, "chatter_alarm")
        trace = (st, [(a["t"], a["payload"]) for a in alarms],
                 [(p["part"], p["cut_start_wall"], p["cut_start_s"], p["cut_end_s"], p["speed_writes"]) for p in parts])
        # An alarm at a part's programmed speed (1500 or 2000 r/min, above the limit): the tool's
        # contact was seen before the depth register's next poll (100 ms, later on a loaded
        # host), and the chatter from entry was caught before the avoid could act. That is
        # detection doing its job (suppression cures it). An alarm at a speed written to the
        # lathe, one the lobes call stable, or at such a cut's release, is the defect.
        programmed = {1500.0, 2000.0}
        at_speed = [a for a in alarms if round(a["payload"]["rpm"], 1) not in programmed]
        assert at_speed == [], trace
        # ... and the avoid won that race on most parts: at least 3 moved at entry without an alarm
        assert len(stable) - len(alarms) >= 3, trace
    finally:
        d.stop()


@contextmanager
def program_run(tmp_path, program: list[str], parts: int, more: str = ""):
    """The shipped chatter and suppression tables (cures not remembered: every pass is
    detection's), and ``more``, on a simulator running ``program``; yields the daemon once
    ``parts`` are cut."""
    suppress = default_table("suppress").replace("\nremember = true", "\nremember = false")
    cfg, paths = sim_config(tmp_path, analyzers=CHATTER + "\n" + suppress + "\n" + more,
                            simulator=f"program = {json.dumps(program)}\nload_s = 0.3\nretract_s = 0.2\n")
    d = Daemon(cfg, paths["socket"])
    d.paths = paths
    try:
        d.wait_ready()
        wait_until(lambda: sim_call(paths["sim"], "status")["part"] >= parts, timeout=90, interval=0.3,
                   what=f"{parts} parts cut")
        yield d
    finally:
        d.stop()


def test_constant_surface_speed_face_is_judged_live(tmp_path):
    """A face at constant surface speed (G96): the spindle runs up from 2016 to 2880 r/min as
    the tool moves in.  The default config (no depth register): the 1.5 mm faces (the default
    program's) are one cut each, judged stable; the 3 mm ones chatter and are caught while the
    speed drifts, and suppression moves them."""
    with program_run(tmp_path, ["3500,1.5,0.1,4.5,css=190", "3500,3.0,0.1,4.5,css=190"], 5) as d:
        parts = [p for p in sim_call(d.paths["sim"], "status", {"parts": 16})["parts"]
                 if p["cut_end_s"] is not None and p["cut_start_wall"] is not None]
        alarms = [e["payload"]["sample_t"] for e in events(d, "chatter_alarm")]

        def alarmed(p):
            c0 = p["cut_start_wall"]
            return [t for t in alarms if c0 <= t <= c0 + p["cut_end_s"] - p["cut_start_s"] + 0.1]
        shallow = [p for p in parts if p["depth_mm"] == 1.5]
        deep = [p for p in parts if p["depth_mm"] == 3.0]
        assert len(shallow) >= 2 and len(deep) >= 2, parts
        assert all(p["css_m_min"] == 190.0 and p["rpm"] == pytest.approx(2016, abs=1) for p in parts)
        assert [alarmed(p) for p in shallow] == [[]] * len(shallow)
        # one cut record a face, judged over its drifting speed (the cut state held through it)
        cuts = [e["payload"] for e in events(d, "cut") if e["payload"]["feed_mm_rev"] == 0.1]
        stable = [c for c in cuts if c["outcome"] == "stable"]
        assert len(stable) >= len(shallow) - 1 and len(cuts) <= len(shallow) + len(deep) + 1, cuts
        assert all(not c["speeds"][0]["steady"] and c["speeds"][0]["rpm_max"] > 2500 for c in stable), stable
        for p in deep:
            assert alarmed(p), p
            assert p["speed_writes"], p           # suppression moved the face's spindle
        assert chatter(d)["windows"] > 100


def test_a_turret_tool_the_model_is_not_for_is_handled_model_free_live(tmp_path):
    """The simulated turret's tool 2 (a boring bar, a limit of 0.6 mm) chatters at 0.9 mm; the
    shipped config's model is tool 1's (tool_number = 1), read from the tool_number register
    over Modbus: the bar's chatter gets the model-free frequency rule and its cut record says
    so, while tool 1's cuts keep the model."""
    assert "\ntool_number = 1" in default_table("suppress")
    with program_run(tmp_path, ["2000,0.9,0.3,20,tool=2", "2000,1.0,0.3,20"], 4,
                     more=default_table("records").replace('\nthermal = "thermal"', "")) as d:
        # the daemon's records, not the simulator's part count: on a loaded host the first part
        # can be cut before the turret's tool number is first polled, and the records lag the cuts
        def recorded():
            cuts = [e["payload"] for e in events(d, "cut")]
            bar = [c for c in cuts if c["tool_number"] == 2 and c["outcome"] == "chatter"]
            turning = [c for c in cuts if c["tool_number"] == 1]
            return (cuts, bar, turning) if bar and turning else None
        cuts, bar, turning = wait_until(recorded, timeout=60, interval=0.3,
                                        what="a chattered cut of tool 2 and a cut of tool 1 recorded")
        assert all(c["model"] is None for c in bar) and all(c["model"] == "configured" for c in turning), \
            [(c["tool_number"], c["model"], c["outcome"], c.get("start_s"), c.get("duration_s")) for c in cuts]
        acts = [e["payload"] for e in events(d, "suppression_action")]
        assert acts and all(a["strategy"] == "sss_frequency" and a["model"] is None for a in acts), acts
        assert "tool 1" in d.item("analyzers", "suppress")["summary"]
        alarms = [e["payload"] for e in events(d, "chatter_alarm")]      # the bar's: it alone chatters
        assert alarms and {a["tool_number"] for a in alarms} == {2}, alarms
        # each part (one pass here) records the tool that cut it, and the bar's alarm names it
        parts = [p for p in json.loads(d.ctl("parts", "--json").stdout) if p["outcome"] == "finished"]
        assert {p["tools"] for p in parts} == {"1", "2"}, parts
        assert all("with tool 2" in p["reason"] for p in parts if p["tools"] == "2" and p["chatter_alarms"])
        assert any(p["chatter_alarms"] for p in parts if p["tools"] == "2"), parts
        assert not any(p["chatter_alarms"] for p in parts if p["tools"] == "1"), parts


def test_light_passes_are_judged_with_the_cutting_feed_signal_live(tmp_path):
    """Finishing passes: a 0.3 mm pass at 0.1 mm/rev (stable) loads the spindle 2 % and
    vibrates 1.1 x the air, so the load and the vibration see only its entry's ring (two cut
    records of 0.17 s, neither judged, without the feed).  With the control's cutting-feed
    signal each is one cut, judged stable over its length, its release not taken for chatter;
    a boring bar's 0.9 mm pass at 0.05 mm/rev (its limit 0.6 mm) is still caught within a
    few revolutions of the chip, the record counting from the chip, not from the approach."""
    assert 'cut_from = ["feed", "load", "vibration"]' in CHATTER
    with program_run(tmp_path, ["2000,0.9,0.05,6,tool=2", "2000,0.3,0.1,6"], 5) as d:
        cuts = [e["payload"] for e in events(d, "cut")]
        light = [c for c in cuts if c["tool_number"] == 1]
        bar = [c for c in cuts if c["tool_number"] == 2]
        assert len(light) == 2 and len(bar) >= 2, cuts
        for c in light:
            assert c["outcome"] == "stable" and c["duration_s"] > 1.5, c
            assert c["speeds"][0]["judged_revs"] > 50, c
        for c in bar:
            assert c["outcome"] == "chatter" and c["first_alarm_rev"] < 8, c
        assert chatter(d)["cut_from"] == ["feed", "load", "vibration"]


@pytest.mark.slow
def test_part_program_features_raise_no_alarm_and_the_deep_passes_are_cured_live(tmp_path):
    """A part program as a shop runs one (issue 38), in the simulator's program syntax: a
    shoulder up (1 -> 2 mm, 0.8 x the limit at 2000 r/min) and one down, a keyway met mid-pass
    (15 deg of every revolution), a flat along the bar from the entry (25 deg), and a 3 mm pass
    above the limit.  The shipped configuration: no alarm on the features; each 3 mm pass is
    caught and suppression moves its speed."""
    program = ["2000,1.0,0.3,24,step=2.0@10", "2000,2.0,0.3,24,step=1.0@10", "2000,1.2,0.3,24,flat=15@10",
               "2500,1.2,0.3,24,flat=25", "2500,3.0,0.3,20"]
    with program_run(tmp_path, program, 10) as d:
        parts = [p for p in sim_call(d.paths["sim"], "status", {"parts": 16})["parts"]
                 if p["cut_end_s"] is not None and p["cut_start_wall"] is not None]
        alarms = [e["payload"]["sample_t"] for e in events(d, "chatter_alarm")]

        def alarmed(p):
            c0 = p["cut_start_wall"]
            return [t for t in alarms if c0 <= t <= c0 + p["cut_end_s"] - p["cut_start_s"] + 0.1]
        deep = [p for p in parts if p["depth_mm"] == 3.0]
        features = [p for p in parts if p["depth_mm"] < 3.0]
        assert len(deep) >= 1 and len(features) >= 6, parts
        assert [alarmed(p) for p in features] == [[]] * len(features), (
            [(p["part"], p["depth_mm"], alarmed(p)) for p in parts],
            [(e["payload"]["raised_by"], e["payload"]["index"], e["payload"]["sample_t"])
             for e in events(d, "chatter_alarm")])
        for p in deep:
            assert alarmed(p) and p["speed_writes"], p
        assert chatter(d)["windows"] > 200
