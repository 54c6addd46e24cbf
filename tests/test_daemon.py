"""The daemon on the simulator, driven with lathectl, as an operator would."""
from __future__ import annotations

import json
import os
import socket
import subprocess

from tests.conftest import BIN, sim_call, wait_until


def test_status_json_has_live_values(sim_daemon):
    d = sim_daemon()
    st = wait_until(lambda: (s := d.status()) and all(
        x["state"] == "connected" for x in s["machines"] + s["sensors"]) and s, what="all drivers connected")
    assert st["daemon"]["state"] == "running" and st["daemon"]["version"]
    assert st["daemon"]["uptime_s"] > 0
    lathe = next(m for m in st["machines"] if m["name"] == "lathe")
    assert set(lathe) >= {"name", "kind", "state", "spindle_rpm"} and lathe["kind"] == "lathe"
    for s in st["sensors"]:
        assert set(s) >= {"name", "state", "last_value", "age_s"}
    assert {a["name"] for a in st["analyzers"]} == set()
    temps = wait_until(lambda: d.item("sensors", "temps")["last_value"], what="temperatures")
    assert set(temps) == {"t_front_bearing", "t_rear_bearing", "t_motor", "t_room"}
    assert all(10 < v < 60 for v in temps.values())
    assert d.item("sensors", "accel")["last_value"]["rms"] > 0
    # the program turns parts at 1500, 2000, 2500 r/min: the speed in status follows
    seen = set()
    wait_until(lambda: seen.add(round(d.item("machines", "lathe")["spindle_rpm"] or 0)) or
               len(seen & {1500, 2000}) == 2, timeout=40, interval=0.2, what="spindle speed change")
    # human output names every instance
    text = d.ctl("status").stdout
    for name in ("lathe", "temps", "accel"):
        assert name in text
    events = json.loads(d.ctl("events", "--json").stdout)
    assert events[0]["kind"] == "daemon_started"


def test_modbus_outage_retrying_then_connected(sim_daemon):
    d = sim_daemon()
    wait_until(lambda: d.item("machines", "lathe")["state"] == "connected", what="lathe connected")
    sim_call(d.paths["sim"], "outage", {"peer": "modbus", "seconds": 10})
    down = wait_until(lambda: (m := d.item("machines", "lathe"))["state"] == "retrying" and m,
                      what="lathe retrying")
    assert down["detail"].startswith("retrying in ")
    # meanwhile the other drivers keep delivering
    age = wait_until(lambda: d.item("sensors", "accel")["age_s"] is not None, what="accel")
    assert age is not None and d.item("sensors", "accel")["age_s"] < 1.0
    wait_until(lambda: d.item("machines", "lathe")["state"] == "connected", timeout=25, what="reconnect")
    assert d.proc.poll() is None
    kinds = [e["kind"] for e in json.loads(d.ctl("events", "--json", "--limit", "200").stdout)]
    assert "machine_fault" in kinds and "machine_recovered" in kinds


def test_malformed_requests_get_error_replies(sim_daemon):
    d = sim_daemon()
    with socket.socket(socket.AF_UNIX) as s:
        s.settimeout(10)
        s.connect(str(d.socket))
        f = s.makefile("rwb")
        for bad, want in [(b"not json\n", "malformed request: not JSON"),
                          (b'["cmd"]\n', "malformed request: expected"),
                          (b'{"cmd": "status", "args": 3}\n', "args must be an object"),
                          (b'{"cmd": "explode"}\n', "unknown command 'explode'"),
                          (b'{"cmd": "events", "args": {"limit": -1}}\n', "events: limit: -1 is out of range")]:
            f.write(bad)
            f.flush()
            reply = json.loads(f.readline())
            assert reply["ok"] is False and want in reply["error"], reply
        f.write(b'{"cmd": "ping"}\n')
        f.flush()
        assert json.loads(f.readline()) == {"ok": True, "result": "pong"}
    assert oct(os.stat(d.socket).st_mode & 0o777) == "0o660"


def test_no_daemon_is_one_line(tmp_path):
    r = subprocess.run([str(BIN / "lathectl"), "--socket", str(tmp_path / "none.sock"), "status"],
                       capture_output=True, text=True)
    assert r.returncode == 69
    assert r.stderr == f"lathectl: lathed is not running (no daemon listening on {tmp_path / 'none.sock'})\n"


def test_sigterm_stops_cleanly_and_notifies(sim_daemon, tmp_path):
    notify = tmp_path / "notify.sock"
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    srv.bind(str(notify))
    srv.settimeout(30)
    d = sim_daemon(env={"NOTIFY_SOCKET": str(notify), "WATCHDOG_USEC": "200000"})
    msgs = []
    wait_until(lambda: msgs.append(srv.recv(4096).decode()) or any("WATCHDOG=1" in m for m in msgs),
               what="watchdog ping")
    assert any(m.startswith("READY=1") for m in msgs)
    assert d.stop() == 0
    srv.close()


def test_retention_prunes_old_records_while_running(sim_daemon):
    # keep_days 0.0001 = 8.6 s: the start-up events age out within the test
    d = sim_daemon(extra='[store]\nkeep_days = 0.0001\nprune_every = "1s"\n')

    def events(kind):
        return json.loads(d.ctl("events", "--kind", kind, "--limit", "100", "--json").stdout)
    started = events("daemon_started")
    assert len(started) == 1
    pruned = wait_until(lambda: events("store_pruned"), timeout=30, interval=0.5, what="a store_pruned event")
    p = pruned[0]["payload"]
    assert p["removed"]["events"] >= 1 and p["sinks"] == []
    assert events("daemon_started") == []            # older than 8.6 s: gone
    assert events("store_pruned")[-1]["t"] > started[0]["t"]
    st = d.status()
    assert st["daemon"]["state"] == "running" and st["daemon"]["store"]["keep_days"] == 0.0001
    assert st["daemon"]["store"]["last_prune"]["removed"]["events"] >= 0
