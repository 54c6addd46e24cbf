"""Bad lathectl arguments: one line naming the command and what is wrong, exit 2 (issue 17 item 1)."""
from __future__ import annotations

import pytest

from lathed.cli.main import main


@pytest.mark.parametrize("argv,needle", [
    (["sim", "depth", "abc"], "lathectl sim depth: argument value: 'abc' is neither a depth in mm nor 'program'"),
    (["sim", "depth", "nan"], "outside the depths the simulated lathe cuts"),
    (["sim", "depth", "-1"], "outside the depths the simulated lathe cuts"),
    (["sim", "depth", "20"], "outside the depths the simulated lathe cuts (0..10 mm)"),
    (["nope"], "lathectl: argument COMMAND: invalid choice: 'nope'"),
    # --rpm is optional since a recording's sidecar (lathectl record) carries the speed
    (["analyze", "chatter", "x.wav", "--rpm", "abc"], "lathectl analyze chatter: argument --rpm: 'abc' is not a number"),
    # type=int and type=float took these: a limit of 0 or -1 listed every cut (out[-0:]) or all but
    # one, SQL's LIMIT -3 every event; an outage of -5 s, nan or 1e12 s was sent to the simulator
    (["cuts", "--limit", "0"], "lathectl cuts: argument --limit: 0 must be at least 1"),
    (["cuts", "--limit", "-1"], "lathectl cuts: argument --limit: -1 must be at least 1"),
    (["events", "--db", "x.db", "--limit", "0"], "lathectl events: argument --limit: 0 must be at least 1"),
    (["events", "--db", "x.db", "--limit", "-3"], "lathectl events: argument --limit: -3 must be at least 1"),
    (["sim", "outage", "modbus", "--", "-5"], "lathectl sim outage: argument seconds: '-5' must be a positive number"),
    (["sim", "outage", "modbus", "nan"], "lathectl sim outage: argument seconds: 'nan' must be a positive number"),
    (["sim", "outage", "modbus", "1e12"], "lathectl sim outage: argument seconds: 1e12 s is longer than an outage "
                                          "the simulator takes (at most 3600 s)"),
])
def test_bad_arguments_are_one_line_and_exit_2(argv, needle, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.count("\n") == 1 and needle in err, err


@pytest.mark.parametrize("argv", [["--socket", "{s}", "status"], ["status", "--socket", "{s}"],
                                  ["suppress", "status", "--socket", "{s}"]])
def test_socket_before_or_after_the_command(argv, tmp_path, capsys):
    # issue 17 item 8: `--socket` wherever the user types it
    sock = str(tmp_path / "other.sock")
    assert main([a.format(s=sock) for a in argv]) == 69
    assert f"no daemon listening on {sock}" in capsys.readouterr().err


def test_lathectl_starts_without_numpy_or_scipy():
    # issue 17 item 8: every command imported scipy (0.4 s for --version); the numeric cores
    # are imported when an analysis runs
    import subprocess
    import sys
    code = ("import sys; from lathed.cli.main import build_parser; build_parser().parse_args(['status']); "
            "print(sorted(m for m in ('numpy', 'scipy', 'matplotlib') if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert r.stdout.strip() == "[]", r.stdout + r.stderr


def test_names_kept_beside_the_parser_match_the_registries():
    from lathed.analysis.chatter.registry import DEFAULT_DETECTOR, DETECTORS
    from lathed.cli import analyze_chatter, sim
    from lathed.sim.thermal import EFFECTS
    assert analyze_chatter.BUILTIN_DETECTORS == tuple(sorted(DETECTORS))
    assert analyze_chatter.DEFAULT_DETECTOR == DEFAULT_DETECTOR
    assert sim.THERMAL_EFFECTS == EFFECTS


def test_events_are_read_from_the_database_while_the_daemon_is_down(tmp_path, capsys):
    # issue 17 item 8: records readable with the daemon stopped (read-only: nothing is written)
    import asyncio
    import json

    from lathed.store import Store
    db = tmp_path / "lathed.db"
    store = Store(db)

    async def record():
        await store.record("chatter_alarm", "chatter", {"index": 3.2})
        await store.record("compensation", "thermal", {"offset_um": 1.5})
    asyncio.run(record())
    store.close()
    before = db.read_bytes()
    sock = str(tmp_path / "none.sock")
    assert main(["--socket", sock, "events", "--db", str(db), "--kind", "chatter_alarm", "--json"]) == 0
    out, err = capsys.readouterr()
    assert [(r["kind"], r["payload"]) for r in json.loads(out)] == [("chatter_alarm", {"index": 3.2})]
    assert err == f"lathectl: lathed is not running; events read from {db}\n"
    assert db.read_bytes() == before
    # no database there: the daemon's absence is the one line, as before
    assert main(["--socket", sock, "events", "--db", str(tmp_path / "no.db")]) == 69
    assert "lathed is not running" in capsys.readouterr().err


def test_export_pages_through_every_row_oldest_first(tmp_path, monkeypatch, capsys):
    # issue 17 item 8: export stopped silently at 100,000 rows (and kept the newest)
    import csv
    import json

    from lathed.cli import records as records_cli
    from tests.inproc_daemon import InProcessDaemon
    d = InProcessDaemon(tmp_path)
    try:
        for i in range(23):
            d.run(d.daemon.store.record("test_marker", "test", {"i": i}))
        monkeypatch.setattr(records_cli, "EXPORT_PAGE", 7)
        calls = []

        def remote(args, cmd, a):
            calls.append(a)
            return d.handle(json.dumps({"cmd": cmd, "args": a}).encode() + b"\n")["result"]
        monkeypatch.setattr(records_cli, "remote", remote)
        out = tmp_path / "events.csv"
        assert main(["export", "events", "--out", str(out)]) == 0
        rows = list(csv.DictReader(out.open()))
        ids = [int(r["id"]) for r in rows]
        assert ids == sorted(set(ids)) and len(ids) == ids[-1]          # every event, once, in order
        assert [json.loads(r["payload"])["i"] for r in rows if r["kind"] == "test_marker"] == list(range(23))
        assert len(calls) == len(ids) // 7 + 1 and all(c["limit"] == 7 for c in calls)
        assert f"{len(ids)} events written to {out}" in capsys.readouterr().err
        # --limit: the newest N, oldest first; --json: one object per line
        assert main(["export", "events", "--limit", "5", "--json"]) == 0
        lines = [json.loads(ln) for ln in capsys.readouterr().out.splitlines()]
        assert [r["id"] for r in lines] == ids[-5:]
    finally:
        d.close()


def test_the_simulator_refuses_an_outage_it_cannot_take(tmp_path):
    # its control socket took float(seconds): "-5", nan and 1e12 (a peer down for 30000 years)
    import asyncio

    from lathed.sim.__main__ import Simulator, parse_args
    from tests.conftest import free_port
    sim = Simulator(parse_args(["--modbus-port", str(free_port()), "--vibration-port", str(free_port()),
                                "--serial-link", str(tmp_path / "tty")]))
    for seconds in ("-5", -5, float("nan"), 1e12, 0, True):
        with pytest.raises(ValueError, match=r"^seconds must be a number in \(0, 3600\], got "):
            asyncio.run(sim._command("outage", {"peer": "modbus", "seconds": seconds}))
    assert not sim._outages


@pytest.mark.parametrize("argv,wait", [(["thermal", "refit"], 180.0), (["thermal", "status"], 10.0),
                                       (["thermal", "touchoff"], 10.0)])
def test_a_thermal_refit_is_waited_for_as_long_as_a_stability_refit(argv, wait, monkeypatch, capsys):
    # a refit runs in a process of its own and takes tens of seconds on a busy PC: lathectl
    # waited its usual 10 s and said "lathed did not answer" while the refit went on (seen on a
    # loaded fresh clone in test_thermal_live)
    import lathed.cli.thermal as thermal_cli
    asked = []

    def answer(cmd, args=None, sock_path=None, timeout=10.0):
        asked.append((cmd, args["action"], timeout))
        return {"summary": "ok", "effects": [], "model_before": "eq14", "before_rmse_um": 1.0, "model_after": "x",
                "after_rmse_um": 0.5, "better": True, "rows": 30}
    monkeypatch.setattr(thermal_cli, "call", answer)
    assert main(["--socket", "/nonexistent.sock", *argv]) == 0
    assert asked == [("thermal", argv[1], wait)]
