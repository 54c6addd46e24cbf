"""bench/bench_hostile.py (issue 18's hostile load) runs and reports every figure.

The bars themselves are the benchmark's verdict (`make bench-hostile`), not asserted here.
"""
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.slow
@pytest.mark.timeout(420)
def test_short_hostile_run_reports_every_field(tmp_path):
    out = tmp_path / "figures.json"
    p = subprocess.run([sys.executable, str(ROOT / "bench" / "bench_hostile.py"), "--duration", "10",
                        "--warmup", "5", "--after", "10", "--json", str(out)],
                       capture_output=True, text=True, timeout=400)
    assert p.returncode == 0, p.stderr[-2000:]
    r = json.loads(out.read_text())
    print(p.stdout)
    assert r["bench_errors"] == []
    rec = r["records"]
    assert rec["error"] is None
    for key in ("experiments", "inspections", "events", "speed_writes"):
        acked, found = rec[key]
        assert isinstance(acked, int) and isinstance(found, int)
    assert rec["experiments"][0] > 0 and rec["events"][0] > 0     # the load did acknowledge records
    assert set(r["store"]) == {"written", "failed", "queued", "last_error"}
    lag = r["loop_lag_ms"]
    assert lag["windows"] > 0 and lag["max"] is not None and lag["histogram"]["n"] > 0
    assert lag["histogram"]["p99_le"] is not None and lag["p50_median_of_windows"] is not None
    assert r["status_calls"]["during_ok"] + r["status_calls"]["during_failed"] > 0
    for k in ("rss_start_mb", "rss_peak_mb", "rss_after_mb", "rss_end_mb", "rss_ratio"):
        assert r[k] > 0, k
    for ph in ("before", "during", "after"):
        assert set(r["loops"][ph]) == {"minutes", "chatter_alarms", "chatter_windows", "suppression_actions",
                                       "thermal_writes", "speed_writes_received", "offset_changes_received",
                                       "chatter_alarm_events", "suppression_action_events", "compensation_events",
                                       "cuts", "cuts_stable", "cuts_chattered", "cuts_cured", "cuts_alarm_unanswered"}
        assert r["loops"][ph]["chatter_alarms"] is not None and r["loops"][ph]["thermal_writes"] is not None
    # the hostile peers were connected, sent bad input, and the daemon's status shows them
    assert r["peer_sent"]["hostile_vib"]["valid"] > 0 and r["peer_sent"]["hostile_temps"]["valid"] > 0
    assert sum(v for k, v in r["peer_sent"]["hostile_temps"].items() if k != "valid") > 0
    assert {"hostile_vib", "hostile_temps", "hostile_chatter", "hostile_thermal"} <= set(r["peers"])
    assert "rejected" in r["peers"]["hostile_temps"] and "failures" in r["peers"]["hostile_vib"]
    assert sum(sum(o.values()) for o in r["fuzz"].values()) > 10
    assert r["slow_clients"]["opened"] >= 200
    # the web floods ran against lathed-web, and a fresh client was asked for every second
    w = r["web"]
    assert w["flood"]["slow_headers"]["opened"] > 0 and w["flood"]["idle_tcp"]["opened"] > 0
    assert w["flood"]["live_reading"]["opened"] > 0 and w["page"]["n"] > 0 and w["live"]["n"] > 0
    assert w["rss_peak_mb"] > 0 and w["health_last"]["connections"]["accepted"] > 0
    # the OPC UA floods ran and lathed-opcua was timed through them
    ua = r["opcua"]
    assert ua["errors"] == [] and ua["fresh_client"]["n"] > 0 and ua["fresh_client"]["median_s"] is not None
    assert ua["idle_tcp"]["opened"] > ua["idle_tcp"]["max_open"] > 0 and ua["idle_tcp"]["closed_by_server"] > 0
    # the storm ran; how far it got in 10 s depends on the machine's load: on a loaded host its
    # clients were still connecting to the flooded server when the load ended (seen with four test
    # workers on two cores). The per-session caps and the notifications themselves are tested in
    # tests/test_opcua.py; `make bench-hostile` runs the storm for minutes.
    st = ua["storm"]
    assert st["connects_tried"] > 0, st
    assert isinstance(st["notifications"], int) and st["notifications"] >= 0
    assert isinstance(ua["storm"]["subscriptions_refused"], int) and isinstance(ua["storm"]["monitored_items_refused"], int)
    for line in ("no record acknowledged and lost", "event-loop lag p99", "RSS back within",
                 "chatter and thermal loops still acting", "the daemon answers a fresh control client",
                 "lathed-web answers a fresh client within 2 s", "the daemon dropped no subscriber",
                 "lathed-web within its MemoryMax", "lathed-opcua answers a fresh client"):
        assert line in p.stdout


def _phase(**kw):
    v = {"chatter_alarms": 0, "chatter_windows": 3000, "suppression_actions": 10, "thermal_writes": 14,
         "speed_writes_received": 10, "offset_changes_received": 7, "cuts": 10, "cuts_stable": 10,
         "cuts_chattered": 0, "cuts_cured": 0, "cuts_alarm_unanswered": 0}
    return {**v, **kw}


def test_loops_acting_holds_for_a_healthy_run_without_alarms():
    """Issue 35 case 12: remembered cures prevent chatter, so a healthy run has no alarms to
    count; the verdict failed it. The figures are a healthy run's (0 alarms, every cut stable)."""
    sys.path.insert(0, str(ROOT / "bench"))
    from bench_hostile import loops_acting
    ok, detail = loops_acting({"during": _phase(), "after": _phase(thermal_writes=5, offset_changes_received=3)})
    assert ok, detail
    assert "0 alarms" in detail and "3000 windows judged" in detail
    # what it is for: a loop that stopped acting fails it
    for dead in ({"chatter_windows": 0}, {"suppression_actions": 0, "speed_writes_received": 0},
                 {"cuts_chattered": 1, "cuts_alarm_unanswered": 1}, {"cuts": 0}):
        assert not loops_acting({"during": _phase(), "after": _phase(**dead)})[0], dead
    assert not loops_acting({"during": _phase(thermal_writes=0, offset_changes_received=0),
                             "after": _phase(thermal_writes=0, offset_changes_received=0)})[0]
