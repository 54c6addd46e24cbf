"""The daemon on the simulator, driven with lathectl, as an operator would."""
from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess

import pytest

from tests.conftest import BIN, running_daemon, sim_call, sim_config, wait_until


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
    # recovered once it has run a while again (the runner's settled time: retry_max here)
    kinds = wait_until(lambda: (k := [e["kind"] for e in json.loads(d.ctl("events", "--json", "--limit", "200").stdout)])
                       and "machine_recovered" in k and k, what="machine_recovered recorded")
    assert "machine_fault" in kinds and "machine_recovered" in kinds


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


def test_ctrl_c_on_the_terminal_stops_drivers_before_the_simulator_without_a_traceback(sim_daemon):
    # issue 17 item 1: a terminal's Ctrl-C is SIGINT to the whole foreground group. The simulator
    # used to get it too, stop first, and leave the drivers faulting and a traceback behind.
    d = sim_daemon(new_session=True)
    sim = wait_until(lambda: d.item("machines", "lathe")["state"] == "connected" and
                     next(json.loads(ln)["pid"] for ln in d.output().splitlines() if '"simulator_ready"' in ln),
                     what="the lathe connected to the simulator")
    os.killpg(d.proc.pid, signal.SIGINT)
    assert d.proc.wait(30) == 0
    out = d.output()
    tail = out[out.index('"stopping"'):]
    assert "Traceback" not in out and "_fault" not in tail, tail
    with pytest.raises(ProcessLookupError):      # stopped and reaped by lathed, not orphaned
        os.kill(sim, 0)


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


def _fault_daemon(sim_daemon, tmp_path):
    import shutil
    from pathlib import Path
    plugins = tmp_path / "faultplugins"
    plugins.mkdir()
    shutil.copy(Path(__file__).parent / "store_fault_plugin.py", plugins / "test_store_fault.py")
    return sim_daemon(analyzers='[analyzer.faults]\nplugin = "test_store_fault"\n',
                      daemon=f'plugin_dirs = ["{plugins}"]')


def _call(d, cmd, args=None):
    from lathed.client import call
    return call(cmd, args or {}, sock_path=d.socket, timeout=20)


def _count(db, kind):
    import sqlite3
    con = sqlite3.connect(db)
    try:
        return con.execute("SELECT count(*) FROM events WHERE kind = ?", (kind,)).fetchone()[0]
    finally:
        con.close()


def test_store_failures_show_in_status_and_recording_goes_on(sim_daemon, tmp_path):
    # issue 18 D1 + D11: a record the store cannot take, then a full disk, then recovery
    d = _fault_daemon(sim_daemon, tmp_path)
    wait_until(lambda: _call(d, "write") == [], what="fault commands")
    assert "record not stored: OverflowError" in _call(d, "poison")
    assert _call(d, "write", {"n": 3}) == []                      # the writer still writes
    st = d.status()
    store = st["daemon"]["store"]
    assert st["daemon"]["state"] == "running" and store["failed"] == 1 and store["failing"] is False
    text = d.ctl("status").stdout
    assert "store:" in text and "1 failed" in text and "OverflowError" in text and "recovered" not in text

    _call(d, "disk_full")
    errors = _call(d, "write", {"n": 20, "pad": 4000})
    assert errors and all("database or disk is full" in e for e in errors)
    st = d.status()
    assert st["daemon"]["state"] == "degraded: store failing" and st["daemon"]["store"]["failing"] is True
    text = d.ctl("status").stdout
    assert "degraded: store failing" in text.splitlines()[0]
    assert "FAILING" in text and "database or disk is full" in text

    _call(d, "disk_free")
    assert _call(d, "write", {"n": 2, "pad": 4000}) == []
    st = d.status()
    assert st["daemon"]["state"] == "running" and st["daemon"]["store"]["failing"] is False
    line = next(ln for ln in d.ctl("status").stdout.splitlines() if ln.startswith("store:"))
    assert "recovered" in line and "ago" in line and "database or disk is full" in line


def test_sigterm_commits_records_queued_behind_a_poison_record(sim_daemon, tmp_path):
    # issue 18 D1: the poison record killed the writer; SIGTERM then lost every queued record
    d = _fault_daemon(sim_daemon, tmp_path)
    wait_until(lambda: _call(d, "poison"), what="fault commands")
    _call(d, "queue", {"n": 500})
    assert d.stop() == 0
    assert _count(d.paths["state"] / "lathed.db", "command_sent") == 500


def test_a_dead_store_writer_fails_the_daemon_loudly_and_loses_nothing(sim_daemon, tmp_path):
    d = _fault_daemon(sim_daemon, tmp_path)
    wait_until(lambda: _call(d, "write") == [], what="fault commands")
    _call(d, "kill_writer")
    _call(d, "queue", {"n": 200})
    wait_until(lambda: d.proc.poll() is not None, 30, what="the daemon to exit")
    assert d.proc.returncode == 70
    # the whole log: a simulator's pymodbus error at the stop dumps its last frames after it
    assert "store_writer_dead" in d.output(None) and "injected writer death" in d.output(None)
    assert _count(d.paths["state"] / "lathed.db", "command_sent") == 200


def test_the_control_socket_of_a_live_daemon_is_never_unlinked(tmp_path):
    import asyncio
    from lathed.control import ControlServer, SocketInUse
    path = tmp_path / "c.sock"

    async def main():
        first = ControlServer(path)
        await first.start()
        with __import__("pytest").raises(SocketInUse, match="another daemon answers on"):
            await ControlServer(path).start()
        assert path.exists()
        # a stale socket (nobody listening) is replaced; closing the old server then leaves the new one
        stale = ControlServer(path)
        first._server.close()
        await first._server.wait_closed()
        await stale.start()
        await first.close()
        assert path.exists() and _pings(path)
        await stale.close()
        assert not path.exists()
    asyncio.run(main())


def _pings(path) -> bool:
    with socket.socket(socket.AF_UNIX) as s:
        s.settimeout(5)
        s.connect(str(path))
        return True


def test_status_text_names_a_failing_store_and_an_analyzer_that_crash_looped(monkeypatch, capsys):
    import time as _time
    import lathed.cli.main as lathectl
    now = _time.time()
    st = {"daemon": {"version": "x", "state": "degraded: store failing", "uptime_s": 75.0, "name": "c", "pid": 1,
                     "store": {"written": 10, "failed": 65, "queued": 3, "failing": True, "failing_since": now - 30,
                               "last_error": "OperationalError: database or disk is full",
                               "last_error_t": now - 1, "recovered_t": None}},
          "machines": [], "sensors": [],
          "analyzers": [{"name": "records", "state": "running", "detail": "running", "summary": "4 parts",
                         "last_error": "OperationalError: database or disk is full"}]}
    lathectl.build_parser()   # the subcommand modules import remote: let them take the real one first
    monkeypatch.setattr(lathectl, "remote", lambda args, cmd, a=None: st)
    assert lathectl.main(["status"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("lathed x degraded: store failing, up 0h01m15s")
    assert out[1].startswith("store: FAILING for 30") and "database or disk is full; 10 written, 65 failed, 3 queued" \
        in out[1]
    assert any(ln.strip().startswith("records") and "restarted after: OperationalError" in ln for ln in out)


# -- one daemon for the tests that only ask it; last in the file, so that it stops as soon as
# they are done (a module's fixture lives to the module's end; idle, it and its simulator
# still cost ~0.15 CPU-s a second) ----------------------------------------------------

@pytest.fixture(scope="module")
def plain_daemon(tmp_path_factory):
    """One daemon on the plain simulator config for the tests that only ask it (status, bad
    requests, a second daemon refused): a start with its simulator costs ~3 CPU-s."""
    cfg, paths = sim_config(tmp_path_factory.mktemp("plain"))
    with running_daemon(cfg, paths) as d:
        yield d


def test_status_json_has_live_values(plain_daemon):
    d = plain_daemon
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
    # connected before its first block: the accel's value comes with the block, not the connect
    accel = wait_until(lambda: d.item("sensors", "accel")["last_value"], what="first accel block")
    assert accel["rms"] > 0
    # the program turns parts at 1500, 2000, 2500 r/min: the speed in status follows
    seen = set()
    wait_until(lambda: seen.add(round(d.item("machines", "lathe")["spindle_rpm"] or 0)) or
               len(seen & {1500, 2000}) == 2, timeout=40, interval=0.2, what="spindle speed change")
    # human output names every instance
    text = d.ctl("status").stdout
    for name in ("lathe", "temps", "accel"):
        assert name in text
    # the shipped map's heartbeat, counted at connect and every 500 ms since
    assert re.search(r"^    heartbeat: count [1-9]\d*, written every 0.5 s$", text, re.M), text
    events = json.loads(d.ctl("events", "--json").stdout)
    assert events[0]["kind"] == "daemon_started"


def test_malformed_requests_get_error_replies(plain_daemon):
    d = plain_daemon
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


def test_a_second_daemon_on_the_same_config_refuses_and_leaves_the_first_alone(plain_daemon):
    # issue 18 D2: the second unlinked the live socket, ran on and deleted the socket at exit
    d = plain_daemon
    ino = os.stat(d.socket).st_ino
    r = subprocess.run([str(BIN / "lathed"), "--config", str(d.cfg)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 75, r.stderr
    (line,) = r.stderr.strip().splitlines()
    assert line == f"lathed: another lathed (pid {d.proc.pid}) holds {d.paths['state'] / 'lathed.lock'}: " \
                   "not starting a second daemon on the same directories"
    assert os.stat(d.socket).st_ino == ino and d.status()["daemon"]["pid"] == d.proc.pid
    # D13: records readable by the group only, also outside systemd
    state = d.paths["state"]
    assert oct(os.stat(state).st_mode & 0o777) == "0o750"
    for f in ("lathed.db", "lathed.db-wal"):
        assert oct(os.stat(state / f).st_mode & 0o777) == "0o640", f
