"""issue 17 item 8: --json on every lathectl command, and the records read from
the database, read-only, while the daemon is down (parts, experiment list)."""
from __future__ import annotations

import argparse
import json
import subprocess
import sys

import pytest

from lathed.cli.main import build_parser, main
from lathed.store import Store
from tests.conftest import ROOT, free_port


def _leaves(p: argparse.ArgumentParser, name: str):
    subs = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield name, p
    for a in subs:
        for child_name, child in a.choices.items():
            yield from _leaves(child, f"{name} {child_name}")


def test_every_command_takes_json():
    leaves = dict(_leaves(build_parser(), "lathectl"))
    assert {"lathectl experiment add", "lathectl sim status", "lathectl parts"} <= set(leaves)
    lacking = [name for name, p in leaves.items() if "--json" not in p._option_string_actions]
    assert not lacking, f"without --json: {lacking}"


@pytest.fixture
def sim(tmp_path):
    """The simulator alone (no daemon): its control socket."""
    control = tmp_path / "sim.sock"
    proc = subprocess.Popen([sys.executable, "-m", "lathed.sim", "--modbus-port", str(free_port()),
                             "--vibration-port", str(free_port()), "--serial-link", str(tmp_path / "tty"),
                             "--control", str(control), "--exit-with-parent"],
                            stdout=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        assert proc.stdout.readline().startswith("READY "), "the simulator did not start"
        yield str(control)
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def test_sim_commands_print_text_or_json(sim, capsys):
    def ctl(*args):
        assert main(["sim", "--sim-socket", sim, *args]) == 0
        return capsys.readouterr().out
    status = json.loads(ctl("status", "--json"))
    assert status["peers"]["modbus"] is True and "registers" in status
    text = ctl("status").splitlines()
    assert text[0].startswith(f"simulator: {status['phase']}" if status["phase"] else "simulator: ")
    assert "modbus up" in text[1] and text[2].startswith("registers: ")
    assert json.loads(ctl("depth", "2.5", "--json")) == {"depth_mm": 2.5}
    assert ctl("depth", "1.5") == "simulator: depth of cut 1.5 mm (override; 'program' goes back)\n"
    assert ctl("depth", "program").startswith("simulator: depth of cut ")
    assert json.loads(ctl("outage", "vibration", "0.5", "--json")) == {"peer": "vibration", "seconds": 0.5}
    assert ctl("outage", "serial", "0.5") == "simulator: serial down for 0.5 s\n"


def test_sim_thermal_run_json(tmp_path, capsys):
    out = tmp_path / "run.csv"
    assert main(["sim", "thermal-run", str(out), "--hours", "0.5", "--effect", "lag", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["out"] == str(out) and doc["effects"] == ["lag"] and doc["hours"] == 0.5
    assert doc["rows"] == len(out.read_text().splitlines()) - 1 == 300


# -- records with the daemon down ----------------------------------------------------

@pytest.fixture
def db(tmp_path):
    """A stopped daemon's store: two parts (one abnormal, queued) and trials of two set-ups."""
    path = tmp_path / "lathed.db"
    store = Store(path, machine_id="cell-3")
    for n, (abnormal, depth) in enumerate(((0, 1.0), (1, 3.0)), 1):
        row = {"uuid": f"part-{n}", "machine": "lathe", "part_no": n, "program": 7, "start_t": 1000.0 * n,
               "end_t": 1000.0 * n + 60, "outcome": "finished", "max_chatter_index": 0.4 + abnormal,
               "chatter_alarms": abnormal, "rpm": 2000.0, "depth_mm": depth, "tool": "T0101", "material": "C45",
               "abnormal": abnormal, "reason": "chatter alarm during the cut" if abnormal else None}
        store.insert("workpieces", row).result()
        if abnormal:
            store.insert("sampling_queue", {"t": 1000.0 * n + 61, "part_uuid": row["uuid"],
                                            "reason": row["reason"]}).result()
    for tool, run in (("T0101", 1), ("T0101", 2), ("T0202", 1)):
        store.insert("experiments", {"t": 5000.0 + run, "tool": tool, "material": "C45", "run": run,
                                     "levels": {"speed": run, "feed": 1}, "settings": {"speed": 1500 * run},
                                     "ra_um": 1.1 * run}).result()
    store.close()
    return path


def _offline(tmp_path, capsys, *args):
    before = {p.name: p.read_bytes() for p in tmp_path.glob("lathed.db*")}
    code = main(["--socket", str(tmp_path / "none.sock"), *args])
    out, err = capsys.readouterr()
    assert {p.name: p.read_bytes() for p in tmp_path.glob("lathed.db*")} == before    # nothing written
    return code, out, err


def test_parts_are_read_from_the_database_while_the_daemon_is_down(db, tmp_path, capsys):
    code, out, err = _offline(tmp_path, capsys, "parts", "--db", str(db), "--json")
    assert code == 0
    assert err == f"lathectl: lathed is not running; parts read from {db}\n"
    parts = json.loads(out)
    assert [(p["uuid"], p["machine_id"], p["depth_mm"]) for p in parts] == [("part-1", "cell-3", 1.0),
                                                                            ("part-2", "cell-3", 3.0)]
    code, out, _ = _offline(tmp_path, capsys, "parts", "--db", str(db), "--queue", "--json")
    assert [p["uuid"] for p in json.loads(out)] == ["part-2"]
    code, out, _ = _offline(tmp_path, capsys, "parts", "--db", str(db), "--abnormal")
    assert code == 0 and "ABNORMAL: chatter alarm during the cut; QUEUED for sampling inspection" in out
    assert out.count("\n") == 2                                                   # header and the one part


def test_experiments_are_read_from_the_database_while_the_daemon_is_down(db, tmp_path, capsys, monkeypatch):
    code, out, err = _offline(tmp_path, capsys, "experiment", "list", "--tool", "T0101", "--material", "C45",
                              "--db", str(db), "--json")
    assert code == 0, err
    assert err == f"lathectl: lathed is not running; experiments read from {db}\n"
    trials = json.loads(out)
    assert [(t["run"], t["levels"], t["settings"]) for t in trials] == [
        (1, {"speed": 1, "feed": 1}, {"speed": 1500}), (2, {"speed": 2, "feed": 1}, {"speed": 3000})]
    # the defaults of --tool and --material are the running analyzer's: without it, say so
    monkeypatch.setenv("LATHED_DB", str(db))
    code, out, err = _offline(tmp_path, capsys, "experiment", "list")
    assert (code, out) == (69, "")
    assert err == "lathectl: lathed is not running: give --tool and --material to read the trials from its " \
                  "database\n"


def test_an_unreadable_database_is_one_line(tmp_path, capsys):
    bad = tmp_path / "lathed.db"
    bad.write_bytes(b"not a database, whatever the name says" * 100)
    code, out, err = _offline(tmp_path, capsys, "parts", "--db", str(bad))
    assert (code, out) == (69, "")
    assert err.startswith(f"lathectl: lathed is not running, and {bad} cannot be read: ") and err.count("\n") == 1


def test_records_still_in_the_wal_are_read(tmp_path, capsys):
    # a daemon killed before its checkpoint: the newest records are only in lathed.db-wal
    path = tmp_path / "lathed.db"
    store = Store(path, machine_id="cell-3")
    try:
        store.insert("experiments", {"t": 1.0, "tool": "T1", "material": "C45", "levels": {"speed": 1},
                                     "settings": {}, "ra_um": 0.8}).result()
        assert (tmp_path / "lathed.db-wal").stat().st_size > 0
        code = main(["--socket", str(tmp_path / "none.sock"), "experiment", "list", "--tool", "T1",
                     "--material", "C45", "--db", str(path), "--json"])
        out, err = capsys.readouterr()
        assert code == 0, err
        assert [t["ra_um"] for t in json.loads(out)] == [0.8]
    finally:
        store.close()


def test_recommend_reads_the_trials_from_the_database_while_the_daemon_is_down(tmp_path, capsys):
    from tests.test_taguchi import FACTORS, PHADKE_BEST, phadke_trials
    path = tmp_path / "lathed.db"
    store = Store(path)
    for run, trial in enumerate(phadke_trials("ra_um"), 1):
        store.insert("experiments", {"t": float(run), "tool": "T0101", "material": "C45", "run": run,
                                     "levels": trial["levels"], "settings": {}, "ra_um": trial["ra_um"]}).result()
    store.close()
    code, out, err = _offline(tmp_path, capsys, "recommend", "--tool", "T0101", "--material", "C45",
                              "--db", str(path), "--json")
    assert code == 0, err
    assert err == f"lathectl: lathed is not running; experiments read from {path}\n"
    surface = json.loads(out)["objectives"]["surface"]
    assert {f: surface["best"][f] for f in FACTORS} == PHADKE_BEST
    code, out, err = _offline(tmp_path, capsys, "recommend", "--tool", "T0202", "--material", "C45",
                              "--db", str(path))
    assert (code, out) == (1, "")
    assert err == ("lathectl: no experiment records for tool T0202 and material C45; add them with "
                   "`lathectl experiment add`\n")
    # every pair, and without a tool the defaults of a daemon that is not there cannot be guessed
    code, out, err = _offline(tmp_path, capsys, "recommend", "--all", "--db", str(path), "--json")
    assert code == 0, err
    rec = json.loads(out)
    assert [(p["tool"], p["material"]) for p in rec["pairs"]] == [("T0101", "C45")]
    assert {f: rec["pairs"][0]["objectives"]["surface"]["best"][f] for f in FACTORS} == PHADKE_BEST
    code, out, err = _offline(tmp_path, capsys, "recommend", "--db", str(path))
    assert code != 0 and "give --tool and --material (or --all)" in err


def test_export_reads_every_row_from_the_database_while_the_daemon_is_down(db, tmp_path, capsys, monkeypatch):
    import asyncio

    from lathed.cli import records as records_cli
    store = Store(db, machine_id="cell-3")

    async def record():
        for i in range(23):
            await store.record("test_marker", "test", {"i": i})
    asyncio.run(record())
    store.close()
    monkeypatch.setattr(records_cli, "EXPORT_PAGE", 7)          # pages through, as from the daemon
    code, out, err = _offline(tmp_path, capsys, "export", "events", "--db", str(db), "--json")
    assert code == 0, err
    assert err == f"lathectl: lathed is not running; events read from {db}\n"
    rows = [json.loads(line) for line in out.splitlines()]
    assert [json.loads(r["payload"])["i"] for r in rows] == list(range(23))
    assert [r["id"] for r in rows] == sorted({r["id"] for r in rows})
    code, out, err = _offline(tmp_path, capsys, "export", "events", "--db", str(db), "--limit", "5", "--json")
    assert [json.loads(json.loads(line)["payload"])["i"] for line in out.splitlines()] == list(range(18, 23))
    csv_out = tmp_path / "parts.csv"
    code, out, err = _offline(tmp_path, capsys, "export", "parts", "--db", str(db), "--out", str(csv_out))
    assert code == 0 and err.endswith(f"2 parts written to {csv_out}\n"), err
    lines = csv_out.read_text().splitlines()
    assert lines[0].startswith("id,uuid,machine_id,") and [ln.split(",")[1] for ln in lines[1:]] == ["part-1",
                                                                                                     "part-2"]


def test_sim_started_by_a_daemon_that_stops_at_once_exits_without_a_traceback(tmp_path):
    """A daemon stopped while its simulator starts (systemctl stop right after start) closes
    the pipe the simulator's READY line goes to: the simulator printed a BrokenPipeError
    traceback into the daemon's log."""
    proc = subprocess.Popen([sys.executable, "-m", "lathed.sim", "--modbus-port", str(free_port()),
                             "--vibration-port", str(free_port()), "--serial-link", str(tmp_path / "tty"),
                             "--control", str(tmp_path / "sim.sock")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    proc.stdout.close()             # the reader is gone before READY
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0 and "Traceback" not in err, err
