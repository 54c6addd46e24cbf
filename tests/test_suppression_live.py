"""Chatter suppression inside the running daemon, on the simulated lathe: the
modes driven with ``lathectl suppress``, the actions in ``lathectl events``,
the spindle following, the safety guard refusing (issue 4, last Done-when item)."""
from __future__ import annotations

import json
import os
import re
import signal

import pytest

from tests.conftest import DEPTH_REGISTER, Daemon, default_table, events, running_daemon, sim_call, sim_config, wait_until


ANALYZERS = default_table("chatter") + "\n" + default_table("suppress")


def sim_set(d, depth) -> dict:
    """The simulator's control socket comes up after the daemon is ready."""
    return wait_until(lambda: sim_call(d.paths["sim"], "set", {"depth_mm": depth}), what="simulator control")


def sim_registers(d) -> dict:
    return sim_call(d.paths["sim"], "status")["registers"]


def suppress(d, *args: str, check: bool = True):
    r = d.ctl("suppress", *args, "--json", check=check)
    return json.loads(r.stdout) if r.returncode == 0 else r


def spindle_commands(d) -> list[dict]:
    return [e for e in events(d, "command_sent") if e["payload"]["action"] == "spindle_rpm"]


def ids(evs: list[dict]) -> set[int]:
    return {e["id"] for e in evs}


def test_suppression_modes_on_the_running_lathe(sim_daemon):
    d = sim_daemon(analyzers=ANALYZERS)
    wait_until(lambda: d.item("analyzers", "suppress")["state"] == "running", what="suppression running")
    st = d.item("analyzers", "suppress")
    assert st["mode"] == "auto" and st["strategy"] == "lobes"
    assert sim_set(d, 3.0) == {"depth_mm": 3.0}     # every part chatters now

    # --- auto: the alarm is acted on, with its critical values ---------------------------------
    act = wait_until(lambda: events(d, "suppression_action"), timeout=30, interval=0.1,
                     what="suppression_action")[0]["payload"]
    assert act["sent"] is True and act["refused"] is None and act["mode"] == "auto" and act["by"] == "suppress"
    assert act["strategy"] in ("sss_lobes", "rated_speed")     # rated: the configured fallback
    # over the threshold, or held above the CUSUM's allowance long enough (sync_cusum)
    assert act["threshold"] > 0 and (act["chatter_index"] > act["threshold"] or (
        act["chatter_index"] > 1.0
        and "sustained rise" in {e["payload"]["raised_by"] for e in events(d, "chatter_alarm")}))
    assert act["chatter_frequency_hz"] > 0
    assert round(act["rpm_before"]) in (1500, 2000, 2500)
    assert 300 <= act["rpm_after"] <= 1.3 * act["rpm_before"] + 1 and act["rpm_after"] != act["rpm_before"]
    sent = spindle_commands(d)
    assert sent[0]["payload"]["value"] == act["rpm_after"]
    assert {(e["source"], e["payload"]["machine"]) for e in sent} == {("suppress", "lathe")}
    # the simulated spindle follows the written speed (the override holds for this part;
    # the policy does not act again within a part once the cut is stable)
    target = sent[-1]["payload"]["value"]
    wait_until(lambda: abs(sim_registers(d)["spindle_rpm_cmd"] - target) < 0.5, timeout=5,
               interval=0.02, what="spindle command register at the new speed")
    wait_until(lambda: abs((d.item("machines", "lathe")["spindle_rpm"] or 0) - target) < 1.0,
               timeout=5, interval=0.05, what="lathe spindle_rpm in status at the new speed")

    # --- manual: a proposal only, no speed change until "suppress now" -------------------------
    st = suppress(d, "manual")
    assert st["mode"] == "manual"
    assert d.item("analyzers", "suppress")["mode"] == "manual"
    assert "mode manual" in d.ctl("suppress").stdout
    mode = events(d, "suppression_mode")[-1]["payload"]
    caller = mode.pop("caller")       # who did it, from the kernel: this test's lathectl
    assert mode == {"machine": "lathe", "from": "auto", "to": "manual", "by": "operator"}
    assert caller["uid"] == os.getuid() and caller["pid"] > 0
    n_sent = len(spindle_commands(d))
    n_proposed = len(events(d, "suppression_proposed"))

    def proposal():
        p = d.item("analyzers", "suppress")["pending"]
        return p if p is not None and len(events(d, "suppression_proposed")) > n_proposed else None
    # ... on the next chattering part; act on it while it is pending (a new part drops it)
    for _ in range(3):
        prop = wait_until(proposal, timeout=30, interval=0.05, what="a pending proposal")
        assert len(spindle_commands(d)) == n_sent          # proposed, not sent
        assert abs(sim_registers(d)["spindle_rpm_cmd"] - prop["rpm_after"]) > 1.0   # not in effect
        r = suppress(d, "now", check=False)
        if isinstance(r, dict):
            break
        assert "no chatter alarm" in r.stderr or "not cutting" in r.stderr, r.stderr
        n_proposed = len(events(d, "suppression_proposed"))
    else:
        pytest.fail("never caught a pending proposal before its part ended")
    assert r["sent"] is True and r["by"] == "operator" and r["mode"] == "manual"
    # the proposal acted on is the one pending at "now": the one read above, or one that
    # replaced it meanwhile (a new alarm in the same cut)
    assert r["rpm_after"] in [e["payload"]["rpm_after"] for e in events(d, "suppression_proposed")[n_proposed:]]
    assert spindle_commands(d)[-1]["payload"]["value"] == r["rpm_after"]
    assert len(spindle_commands(d)) == n_sent + 1
    assert events(d, "suppression_proposed")[-1]["payload"]["mode"] == "manual"

    # --- off: alarms, but no action -------------------------------------------------------------
    assert suppress(d, "off")["mode"] == "off"
    # the mode's event is recorded after the reply, by the store's writer: waited for, not raced
    wait_until(lambda: [e["payload"]["to"] for e in events(d, "suppression_mode")] == ["manual", "off"],
               timeout=10, what="the mode change to off recorded")
    before = {k: ids(events(d, k)) for k in ("suppression_action", "suppression_proposed", "command_sent")}
    n_alarms = len(events(d, "chatter_alarm"))
    # the present alarm ends with its cut; the next part's alarm is seen by the suppression
    # analyzer, and once it has seen it its decision (none) is made
    wait_until(lambda: not d.item("analyzers", "suppress")["chatter_alarm"], timeout=20,
               what="the cut's alarm cleared")
    wait_until(lambda: d.item("analyzers", "suppress")["chatter_alarm"], timeout=30,
               what="a new alarm seen by the suppression analyzer")
    wait_until(lambda: len(events(d, "chatter_alarm")) > n_alarms, timeout=10,
               what="the new alarm recorded (the store writes it after the analyzers see it)")
    for k, seen in before.items():
        assert ids(events(d, k)) == seen, k
    assert d.item("analyzers", "suppress")["pending"] is None
    assert "mode off" in d.ctl("suppress").stdout
    # the modes are in the event log, as lathectl events shows it
    assert "suppression_mode" in d.ctl("events", "--limit", "200").stdout


@pytest.fixture
def tight_guard(tmp_path):
    """The daemon on the simulator with a safety guard that allows 1 r/min per step."""
    cfg, paths = sim_config(tmp_path, analyzers=ANALYZERS)
    text = cfg.read_text()
    assert "offset_rate_max_um_s = 5.0\n" in text
    cfg.write_text(text.replace("offset_rate_max_um_s = 5.0\n",
                                "offset_rate_max_um_s = 5.0\nspindle_rpm_step_max = 1.0\n", 1))
    with running_daemon(cfg, paths) as d:
        yield d


def test_a_refused_speed_is_recorded_and_never_sent(tight_guard):
    d = tight_guard
    assert sim_set(d, 3.0) == {"depth_mm": 3.0}
    refused = wait_until(lambda: [e for e in events(d, "command_refused")
                                  if e["payload"]["action"] == "spindle_rpm"],
                         timeout=30, interval=0.1, what="command_refused")
    r = refused[0]
    assert r["source"] == "suppress" and r["payload"]["machine"] == "lathe"
    assert "exceeds 1" in r["payload"]["refused"]
    act = wait_until(lambda: events(d, "suppression_action"), timeout=5, what="suppression_action")[0]["payload"]
    assert act["sent"] is False and act["refused"] == r["payload"]["refused"]
    assert act["rpm_after"] == r["payload"]["value"]
    # never sent: no command_sent, and the lathe still runs the program's speed
    assert spindle_commands(d) == []
    assert sim_registers(d)["spindle_override_pct"] == pytest.approx(100.0)
    assert d.item("analyzers", "suppress")["last_action"]["sent"] is False


@pytest.mark.slow
@pytest.mark.parametrize("registers", [DEPTH_REGISTER, ""], ids=["depth register", "depth from spindle load"])
def test_avoid_changes_speed_at_cut_entry_when_the_lobes_predict_chatter(sim_daemon, registers):
    # predicting needs the depth: a machine's depth register, else the spindle load's estimate
    d = sim_daemon(analyzers=default_table("chatter") + "\n" + default_table("suppress") + "\navoid = true\n",
                   registers=registers)
    wait_until(lambda: d.item("analyzers", "suppress")["state"] == "running", what="suppression running")
    assert suppress(d, "status")["avoid"] is True
    assert "avoids predicted chatter at cut entry" in d.ctl("suppress", "status").stdout
    # 1 mm: stable at every programmed speed, nothing predicted
    assert sim_set(d, 1.0) == {"depth_mm": 1.0}
    part0 = sim_call(d.paths["sim"], "status")["part"]
    wait_until(lambda: sim_call(d.paths["sim"], "status")["part"] >= part0 + 3, timeout=60, interval=0.2,
               what="three 1 mm parts")
    assert events(d, "suppression_action") == []
    # 3 mm: above the limit (~2.4 mm) at 1500, 2000 and 2500 r/min
    sim_set(d, 3.0)
    start = sim_call(d.paths["sim"], "status")["part"] + 1       # the first part cut wholly at 3 mm
    acts = wait_until(lambda: len(a := [e for e in events(d, "suppression_action")
                                        if e["payload"]["trigger"] == "predicted"]) >= 4 and a,
                      timeout=60, interval=0.2, what="four predicted actions")
    for e in acts:
        p = e["payload"]
        assert p["sent"] and p["strategy"] == "sss_lobes" and p["expected_stable"] is True, p
        depth = float(re.match(r"predicted at cut entry: ([\d.]+) mm deep, the lobes allow ", p["reason"])[1])
        assert depth == 3.0 if registers else abs(depth - 3.0) < 0.3, p["reason"]
        assert p["chatter_index"] is None and p["rpm_after"] <= 1.3 * p["rpm_before"] + 1
    # each 3 mm part: the speed is written at entry, from the prediction (chatter_index None
    # above), long before detection could act. How soon (the loop's 3 rev + 20 ms target) is a
    # timing figure for `make bench-loop --avoid`, not for a test on a shared, loaded machine.
    # (the G97 parts: the program's seventh part is a G96 face, whose speed the control moves
    # itself; a loaded run that waited long for the four actions reached it, with no entry write)
    parts = [p for p in sim_call(d.paths["sim"], "status", {"parts": 32})["parts"]
             if p["part"] >= start and p["cut_end_s"] is not None and not p["css_m_min"]]
    assert len(parts) >= 2, parts
    for p in parts:
        writes = [w["wall_t"] for w in p["speed_writes"] if "wall_t" in w]
        assert writes and writes[0] - p["cut_start_wall"] < 1.0, p
    # the load that gave the depth was read at the chip's entry (read_on), not only at its poll
    reads_on = d.item("machines", "lathe")["reads_on"]
    assert reads_on.get("chatter.cutting", 0) + reads_on.get("chatter.cut_contact", 0) >= len(parts) + 3, reads_on
    # and no chatter alarm at a speed the lobes call stable for 3 mm (they pick about 1950 r/min
    # for the 1500 r/min part, 2290 for the 2000 and 2500 r/min ones: limits 4.0 and 5.5 mm):
    # the entry's chatter is gone before the detector, which learns its baseline afresh after a
    # speed change at entry, would have seen it grow, and the tool's release at the cut's end is
    # a level step, not chatter (jump_ratio). An alarm where the lobes allow less than 3 mm
    # would be right, so it is not counted against the detector.
    from lathed.analysis.lobes import StabilityLobes
    from lathed.sim.lathe import LATHE_KF, LATHE_MODES
    lobes = StabilityLobes(LATHE_MODES, LATHE_KF)
    for e in events(d, "chatter_alarm"):
        if e["t"] < parts[0]["cut_start_wall"]:
            continue
        rpm = e["payload"]["rpm"]
        assert float(lobes.b_lim_at(rpm)[0][0]) * 1000 < 3.0, (rpm, e["payload"])


def override_config(tmp_path, program: str):
    """The lathe's map with the commanded speed read-only and the spindle override writable
    (Fanuc's SOV through the PMC), chatter and suppression as shipped without remember."""
    suppress_table = default_table("suppress").replace("\nremember = true", "\nremember = false")
    cfg, paths = sim_config(tmp_path, analyzers=default_table("chatter") + "\n" + suppress_table + "\n",
                            simulator=f'program = {program}\nload_s = 0.3\nretract_s = 0.2\n')
    text = cfg.read_text()
    for old, new in (('spindle_rpm_cmd = { address = 0, type = "float32", writable = true, unit = "r/min" }',
                      'spindle_rpm_cmd = { address = 0, type = "float32", unit = "r/min" }'),
                     ('spindle_override_pct = { address = 4, type = "float32", unit = "%" }',
                      'spindle_override_pct = { address = 4, type = "float32", unit = "%", writable = true }')):
        assert old in text
        text = text.replace(old, new)
    cfg.write_text(text)
    return cfg, paths


def test_a_control_that_takes_the_speed_as_an_override_is_cured_and_released_live(tmp_path):
    """The lathe's map with the commanded speed read-only and the spindle override writable
    (Fanuc's SOV through the PMC): a 3 mm pass at 2000 r/min chatters, suppression's speed is
    written as a percentage of the programmed speed, and when the cut ends the override goes
    back to 100 % through the guard, so the next pass (1 mm at 1500) runs at its own speed."""
    cfg, paths = override_config(tmp_path, '["2000,3.0,0.3,20", "1500,1.0,0.3,20"]')
    d = Daemon(cfg, paths["socket"])
    d.paths = paths
    try:
        d.wait_ready()
        wait_until(lambda: sim_call(paths["sim"], "status")["part"] >= 5, timeout=90, interval=0.3,
                   what="five parts")
        sent = [e["payload"] for e in spindle_commands(d)]
        cures = [p for p in sent if p["by"] == "suppress" and not p["reason"].startswith("released")]
        released = [p for p in sent if p["reason"].startswith("released")]
        assert cures and released, sent
        assert all(50 <= p["override_pct"] <= 150 and p["override_pct"] != 100 for p in cures), cures
        assert all(p["override_pct"] == 100 for p in released), released
        parts = [p for p in sim_call(paths["sim"], "status", {"parts": 16})["parts"] if p["cut_end_s"] is not None]
        deep = [p for p in parts if p["depth_mm"] == 3.0 and p["speed_writes"]]
        assert deep and all(w.get("override_pct") for p in deep for w in p["speed_writes"]), deep
        # each 1 mm pass cut at its own 1500 r/min: the override was back at 100 % before it
        # (held, it would have run at 1500 x the cure's override)
        light = [e["payload"] for e in events(d, "cut") if (e["payload"]["depth_mm"] or 0) < 2.0]
        assert light and all(abs(c["rpm_start"] - 1500) < 15 for c in light), light
    finally:
        d.stop()


def test_a_dwell_mid_pass_holds_the_cure_live(tmp_path):
    """A 3 mm pass at 2000 r/min chatters and is cured by an override; halfway along it the feed
    stops for 1 s (G04), the tool in the work: the cutting-feed signal, the spindle load and
    the vibration all say "no chip".  The shipped chatter table (dwell_axes: the control's X
    and Z registers standing) holds the cut over it: the cure is not released before the
    pass's end, the rest of the pass raises no alarm (no re-entry false alarm, no chatter at the
    speed that chattered), one cut record a pass; the retract still releases the override before
    the next pass (1 mm at 1500 r/min) begins.  Before, the dwell ended the cut: the override
    went back to 100 % under the chip and the pass's rest chattered again, two cut records."""
    cfg, paths = override_config(tmp_path, '["2000,3.0,0.3,30,dwell=1", "1500,1.0,0.3,20"]')
    d = Daemon(cfg, paths["socket"])
    d.paths = paths
    try:
        d.wait_ready()
        wait_until(lambda: sim_call(paths["sim"], "status")["part"] >= 5, timeout=90, interval=0.3,
                   what="five parts")
        parts = [p for p in sim_call(paths["sim"], "status", {"parts": 16})["parts"]
                 if p["cut_end_s"] is not None and p["cut_start_wall"] is not None]
        deep = [p for p in parts if p["depth_mm"] == 3.0]
        assert len(deep) >= 2, parts

        def wall(p, sim_t):
            return p["cut_start_wall"] + sim_t - p["cut_start_s"]
        # the daemon ends the last pass's cut when it has seen the chip gone (off_s of quiet in the
        # vibration, the feed's next poll): on a loaded host after the simulator's next part began
        cuts = wait_until(lambda: (c := [e["payload"] for e in events(d, "cut")])
                          and max(x["end_t"] for x in c) > wall(parts[-1], parts[-1]["cut_end_s"]) - 0.5 and c,
                          timeout=10, interval=0.2, what="the last pass's cut record")
        alarms = [e["payload"]["sample_t"] for e in events(d, "chatter_alarm")]
        released = [e["t"] for e in spindle_commands(d) if e["payload"]["reason"].startswith("released")]
        for p in deep:
            start, stop, end = (wall(p, p[k]) for k in ("dwell_start_s", "dwell_end_s", "cut_end_s"))
            # one cut for the pass, over its dwell
            mine = [c for c in cuts if c["start_t"] < end and c["end_t"] > wall(p, p["cut_start_s"])]
            assert len(mine) == 1 and mine[0]["start_t"] < start and mine[0]["end_t"] > stop, mine
            assert mine[0]["outcome"] == "chatter" and mine[0]["rpm_end"] != 2000.0, mine
            # cured once before the dwell, never released under the chip
            assert [w["override_pct"] for w in p["speed_writes"]] and p["speed_writes"][0]["sim_t"] < p["dwell_start_s"]
            assert not [t for t in released if wall(p, p["cut_start_s"]) < t < end], (p, released)
            assert not [t for t in alarms if start < t < end + 0.3], (p, alarms)
        # the retract releases it: each light pass cut at its own speed
        light = [c for c in cuts if (c["depth_mm"] or 0) < 2.0]
        assert light and all(abs(c["rpm_start"] - 1500) < 15 for c in light), light
        assert d.item("analyzers", "chatter")["dwells"] >= 2
    finally:
        d.stop()


def test_no_speed_is_written_while_a_thread_is_cut_live(tmp_path):
    """A threading pass (the control's threading signal on for its cycle) and a turning pass,
    both 3 mm at 2000 r/min, which chatters: the turning pass is cured, the thread is not
    (a speed changed between or within its passes cuts them off one helix). Each speed asked
    in the thread, remembered at its entry or for an alarm, is refused by the guard and
    recorded with the cause; the machine never gets one."""
    cfg, paths = sim_config(tmp_path, analyzers=ANALYZERS,
                            simulator='program = ["2000,3.0,0.3,20,thread=0.3", "2000,3.0,0.3,20"]\n'
                                      'load_s = 0.3\nretract_s = 0.2\n')
    d = Daemon(cfg, paths["socket"])
    d.paths = paths
    try:
        d.wait_ready()
        wait_until(lambda: sim_call(paths["sim"], "status")["part"] >= 5, timeout=90, interval=0.3,
                   what="five parts")
        parts = [p for p in sim_call(paths["sim"], "status", {"parts": 16})["parts"] if p["cut_end_s"] is not None]
        threads, turned = [p for p in parts if p["thread"]], [p for p in parts if not p["thread"]]
        assert len(threads) >= 2 and len(turned) >= 2, parts
        assert all(p["speed_writes"] == [] for p in threads), threads
        assert any(p["speed_writes"] for p in turned), turned
        refused = [e["payload"] for e in events(d, "command_refused")]
        assert refused and all("is cutting a thread (threading = 1)" in r["refused"] for r in refused), refused
        assert {r["by"] for r in refused} == {"suppress"}
        # asked once a thread, then held back for the rest of its cut (no flood of refusals)
        assert len(refused) <= len(threads) + 1, (len(refused), len(threads))
        acts = [e["payload"] for e in events(d, "suppression_action") if not e["payload"]["sent"]]
        assert acts and all("cutting a thread" in a["refused"] for a in acts), acts
    finally:
        d.stop()


def _stored(paths, kind: str) -> list[dict]:
    import sqlite3
    con = sqlite3.connect(f"file:{paths['state'] / 'lathed.db'}?mode=ro", uri=True, timeout=10)
    rows = [json.loads(p) for (p,) in con.execute("SELECT payload FROM events WHERE kind = ? ORDER BY id", (kind,))]
    con.close()
    return rows


def _stopped_mid_cure(tmp_path, program: str):
    """A daemon on the override map, sent SIGTERM once a cure holds the override mid-cut."""
    cfg, paths = override_config(tmp_path, program)
    d = Daemon(cfg, paths["socket"])
    d.paths = paths
    d.wait_ready()
    wait_until(lambda: [e for e in spindle_commands(d) if e["payload"]["by"] == "suppress"],
               timeout=60, interval=0.2, what="a cure written as an override")
    assert sim_registers(d)["spindle_override_pct"] != 100.0
    d.proc.send_signal(signal.SIGTERM)
    return d, paths


def test_a_stop_mid_cure_waits_for_the_cut_to_end_live(tmp_path):
    """Stopped (SIGTERM: systemctl stop or restart) while a cure holds the override mid-cut,
    the daemon goes on supervising until the cut ends, so the pass is finished at the cured
    speed, not the one that chattered; the cut's end releases the override as after any cut,
    and then the daemon stops."""
    d, paths = _stopped_mid_cure(tmp_path, '["2000,3.0,0.3,80"]')     # an 8 s pass
    try:
        st = wait_until(lambda: (s := d.status()["daemon"]["state"]).startswith("stopping") and s,
                        what="the stopping daemon's state")
        assert st == "stopping: waiting up to 60 s for the cut to end (lathe spindle_rpm held)", st
        assert d.proc.wait(60) == 0
    finally:
        d.stop()
    waited = _stored(paths, "stop_waited")
    assert len(waited) == 1 and waited[0]["ended"] == "the cut ended" and waited[0]["held"] == ["lathe spindle_rpm"]
    sent = [p for p in _stored(paths, "command_sent") if p["action"] == "spindle_rpm"]
    assert sent[-1]["override_pct"] == 100.0 and sent[-1]["reason"].startswith("released"), sent
    assert sent[-1]["reason"] != "released: the daemon is stopping", sent


def test_a_second_signal_stops_at_once_and_releases_the_override_live(tmp_path):
    """The override holds beyond the daemon: stopped in the middle of a cured cut with a second
    SIGTERM (or Ctrl-C) while it waits for the cut's end, the daemon writes the programmed speed
    back (override 100 %) through the guard before it closes the link, and records it."""
    d, paths = _stopped_mid_cure(tmp_path, '["2000,3.0,0.3,400"]')     # a 40 s pass
    try:
        wait_until(lambda: d.status()["daemon"]["state"].startswith("stopping: waiting"),
                   what="the daemon waiting for the cut's end")
        d.proc.send_signal(signal.SIGTERM)
        assert d.proc.wait(20) == 0
    finally:
        d.stop()
    assert _stored(paths, "stop_waited")[0]["ended"] == "a second stop signal"
    rows = [p for p in _stored(paths, "command_sent") if p["action"] == "spindle_rpm"]
    assert rows[-1]["reason"] == "released: the daemon is stopping" and rows[-1]["override_pct"] == 100.0, rows
