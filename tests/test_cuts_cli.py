"""lathectl cuts: filters, the CSV export and what it leaves out (the daemon's reply stood in for)."""
from __future__ import annotations

import time

import pytest

import lathed.cli.main as lathectl
from lathed.analysis.cuts import load_cuts_csv
from lathed.cli import cuts as cuts_cli


def record(i, machine="lathe", t=None, depth=3.0, speeds=None):
    return {"id": i, "t": t or time.time(), "source": "suppress", "kind": "cut", "payload": {
        "machine": machine, "tool": "T0101", "material": "C45", "start_t": t or time.time(), "depth_mm": depth,
        "depth_from": None if depth is None else "register", "feed_mm_rev": 0.3, "outcome": "chatter",
        "first_alarm_s": 0.5, "first_alarm_rev": 19.0, "chatter_frequency_hz": 218.0, "cured": True,
        "actions": [{"rpm_after": 3029.0}],
        "speeds": speeds or [{"rpm": 2250.0, "outcome": "chatter", "steady": True, "chatter_frequency_hz": 218.0},
                             {"rpm": 3029.0, "outcome": "stable", "steady": True, "chatter_frequency_hz": None},
                             {"rpm": 2620.0, "outcome": None, "steady": False, "chatter_frequency_hz": None}]}}


@pytest.fixture
def daemon_cuts(monkeypatch):
    rows = [record(1, t=time.time() - 7200), record(2, machine="mill"), record(3, depth=None), record(4)]
    asked = []

    def remote(args, cmd, cmd_args=None):
        asked.append((cmd, cmd_args))
        assert cmd == "events" and cmd_args["kind"] == "cut"
        return rows[-cmd_args["limit"]:]
    monkeypatch.setattr(cuts_cli, "remote", remote)
    return asked


def test_machine_and_since_filter_the_cuts(daemon_cuts, capsys):
    assert lathectl.main(["cuts", "--machine", "lathe", "--since", "1h"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in out] == ["3", "4"]
    assert "r/min 2250 chatter -> 3029 stable -> 2620, first alarm at 0.50 s (rev 19) 218.0 Hz, cured" in out[1]
    assert "depth - mm (unknown)" in out[0]
    assert lathectl.main(["cuts", "--since", "2026-01-01T00:00", "--limit", "1"]) == 0
    assert [line.split()[0] for line in capsys.readouterr().out.splitlines()] == ["4"]


def test_a_drifting_speed_is_shown_as_its_range(monkeypatch, capsys):
    # a face at constant surface speed: one stretch, judged stable, its speed not one speed
    rows = [record(1, speeds=[{"rpm": 2432.0, "outcome": "stable", "steady": False, "rpm_min": 2016.2,
                               "rpm_max": 2879.6, "chatter_frequency_hz": None}])]
    monkeypatch.setattr(cuts_cli, "remote", lambda args, cmd, cmd_args=None: rows)
    assert lathectl.main(["cuts"]) == 0
    assert "r/min 2016..2880 (drifting) stable" in capsys.readouterr().out


def test_an_unreadable_since_is_one_line(capsys):
    with pytest.raises(SystemExit) as e:
        lathectl.main(["cuts", "--since", "yesterday"])
    assert e.value.code == 2
    assert "'yesterday' is neither a duration (2h, 30min) nor a date/time" in capsys.readouterr().err


def test_csv_export_reads_back_and_says_what_it_left_out(daemon_cuts, tmp_path, capsys):
    path = tmp_path / "cuts.csv"
    assert lathectl.main(["cuts", "--csv", str(path), "--machine", "lathe"]) == 0
    cuts = load_cuts_csv(path)
    assert list(cuts.rpm) == [2250.0, 3029.0, 2250.0, 3029.0] and list(cuts.chatter) == [True, False, True, False]
    assert list(cuts.chatter_frequency_hz[cuts.chatter]) == [218.0, 218.0]
    err = capsys.readouterr().err
    assert "lathectl: 3 cut speed(s) not exported: too short to judge or speed modulated" in err
    assert "lathectl: 2 cut speed(s) not exported: no depth of cut known" in err


def test_events_print_a_cut_as_a_line_to_read(tmp_path, capsys):
    """Issue 39: `lathectl events` printed a cut record as ~980 characters of Python syntax."""
    import asyncio

    from lathed.analysis.cut_log import CutTracker
    from lathed.store import Store
    tr = CutTracker("lathe", "T0101", "C45")
    tr.start(100.0, 2000.0)
    tr.depth_mm, tr.depth_from, tr.feed_mm_rev = 3.0, "register", 0.3
    for i in range(1, 40):
        tr.speed(100.0 + 0.05 * i, 2000.0)
    tr.chatter(101.2, True, 195.0)
    tr.action(101.3, {"trigger": "alarm", "strategy": "sss_lobes", "rpm_before": 2000.0, "rpm_after": 2298.0,
                      "sent": True, "by": "suppress"}, 101.8)
    tr.chatter(101.9, False, None)
    for i in range(1, 120):
        tr.speed(101.3 + 0.05 * i, 2298.0)
    rec = tr.end(107.3)
    store = Store(tmp_path / "lathed.db")
    asyncio.run(store.record("cut", "suppress", rec))
    store.close()
    assert lathectl.main(["--socket", str(tmp_path / "none.sock"), "events", "--db", str(tmp_path / "lathed.db")]) == 0
    line = capsys.readouterr().out.strip()
    assert "{'" not in line and "[{" not in line and "None" not in line, line
    assert len(line) < 250, (len(line), line)
    assert "T0101/C45 depth 3 mm (register), feed 0.3: chatter; r/min 2000 chatter -> 2298 stable" in line
    assert "first alarm at 1.20 s" in line and "195.0 Hz, cured" in line
