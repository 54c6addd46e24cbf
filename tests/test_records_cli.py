"""lathectl parts / inspect / experiment / recommend / export against the daemon
on the simulated lathe, with a stand-in chatter analyzer on the bus contract."""
from __future__ import annotations

import contextlib
import csv
import io
import json
import shutil
from pathlib import Path

import pytest

import lathed.cli.main as lathectl
from tests.conftest import DEPTH_REGISTER, Daemon, sim_config, wait_until
from tests.test_taguchi import FACTORS, PHADKE_BEST, phadke_trials

HERE = Path(__file__).resolve().parent

ANALYZERS = """
[analyzer.chatter]
plugin = "fake_chatter"
depth_mm = 2.0

[analyzer.records]
plugin = "records"
machine = "lathe"
chatter = "chatter"
tool = "T0101"
material = "C45"
"""


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    # one daemon for the module: the recommendation test runs while the lathe cuts parts
    tmp_path = tmp_path_factory.mktemp("records_cli")
    plugins = tmp_path / "plugins"
    plugins.mkdir()
    shutil.copy(HERE / "fake_chatter_plugin.py", plugins / "fake_chatter.py")
    cfg, paths = sim_config(tmp_path, analyzers=ANALYZERS, registers=DEPTH_REGISTER)
    cfg.write_text(cfg.read_text().replace("[daemon]\n", f'[daemon]\nplugin_dirs = ["{plugins}"]\n', 1))
    d = Daemon(cfg, paths["socket"])
    try:
        d.wait_ready()
        yield d
    finally:
        d.stop()


class Result:
    def __init__(self, returncode: int, stdout: str, stderr: str):
        self.returncode, self.stdout, self.stderr = returncode, stdout, stderr


def ctl(d: Daemon, *args: str, check: bool = True) -> Result:
    """lathectl in this process (a subprocess per call costs a second of imports)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = lathectl.main(["--socket", str(d.socket), *args])
        except SystemExit as e:   # argparse errors
            code = e.code
    r = Result(code, out.getvalue(), err.getvalue())
    if check and code != 0:
        raise AssertionError(f"lathectl {' '.join(args)} exited {code}: {r.stderr.strip()}")
    return r


def _json(d: Daemon, *args: str):
    return json.loads(ctl(d, *args, "--json").stdout)


def test_recommend_reproduces_the_worked_example(daemon):
    d = daemon
    r = ctl(d, "recommend", "--tool", "T0101", "--material", "C45", check=False)
    assert r.returncode == 1 and "no experiment records" in r.stderr
    for run, trial in enumerate(phadke_trials("ra_um"), 1):
        levels = ",".join(f"{f}={lv}" for f, lv in trial["levels"].items())
        ctl(d, "experiment", "add", "--tool", "T0101", "--material", "C45", "--run", str(run),
              "--levels", levels, "--setting", f"temperature={[0, 'T0-25C', 'T0', 'T0+25C'][trial['levels']['temperature']]}",
              "--ra", repr(trial["ra_um"]))
    assert len(_json(d, "experiment", "list", "--tool", "T0101", "--material", "C45")) == 9
    rec = _json(d, "recommend", "--tool", "T0101", "--material", "C45")
    surface = rec["objectives"]["surface"]
    assert {f: surface["best"][f] for f in FACTORS} == PHADKE_BEST
    assert surface["effects"]["temperature"] == pytest.approx({"1": -20.0, "2": -45.0, "3": -60.0})
    assert surface["best_settings"]["temperature"] == ["T0-25C"]
    text = ctl(d, "recommend", "--tool", "T0101", "--material", "C45").stdout
    assert "best surface" in text and "temperature=1 (T0-25C)" in text and "cleaning=2/3" in text
    bad = ctl(d, "experiment", "add", "--tool", "T0101", "--material", "C45", "--levels", "speed=1",
                "--ra", "1", check=False)
    assert bad.returncode == 1 and "use the factors" in bad.stderr


def test_recommend_all_gives_one_recommendation_per_tool_holder_and_material(daemon):
    d = daemon
    for run, trial in enumerate(phadke_trials("ra_um"), 1):
        levels = ",".join(f"{f}={lv}" for f, lv in trial["levels"].items())
        ctl(d, "experiment", "add", "--tool", "T0202", "--material", "Al6061", "--run", str(run),
            "--levels", levels, "--ra", repr(trial["ra_um"]))
    # a removal rate of 0 has no larger-the-better S/N: that pair says why, the others are still given
    ctl(d, "experiment", "add", "--tool", "T0303", "--material", "C45", "--levels", "speed=1",
        "--removal-rate", "0")
    rec = _json(d, "recommend", "--all")
    pairs = {(r["tool"], r["material"]): r for r in rec["pairs"]}
    assert ("T0202", "Al6061") in pairs and ("T0303", "C45") in pairs
    assert rec["pairs"][0]["tool"] == "T0303"          # most recently tried first
    assert pairs[("T0303", "C45")]["error"].startswith("recommend: T0303/C45:")
    good = pairs[("T0202", "Al6061")]
    assert {f: good["objectives"]["surface"]["best"][f] for f in FACTORS} == PHADKE_BEST
    assert rec["current"] == {"tool": "T0101", "material": "C45"}
    text = ctl(d, "recommend", "--all").stdout
    assert "tool T0202, material Al6061" in text and "tool T0303, material C45: recommend:" in text


def test_chattered_part_is_queued_inspected_and_joined(daemon, tmp_path):
    d = daemon
    # every third simulated part is cut 3 mm deep and chatters
    abnormal = wait_until(lambda: _json(d, "parts", "--abnormal"), 90, interval=0.5,
                          what="a part cut under chatter")
    part = abnormal[0]
    assert part["abnormal"] == 1 and part["depth_mm"] == pytest.approx(3.0)
    assert part["chatter_alarms"] >= 1 and part["max_chatter_index"] > 1.0 and "chatter" in part["reason"]
    assert part["machine_id"] == "test-cell" and part["tool"] == "T0101" and part["material"] == "C45"
    assert part["id"] in [p["id"] for p in _json(d, "parts", "--queue")]
    text = ctl(d, "parts", "--abnormal").stdout
    assert "QUEUED for sampling inspection" in text

    out = ctl(d, "inspect", str(part["id"]), "--ra", "4.49", "--diameter-error", "-32",
                "--value", "roundness_um=3.5", "--by", "qa-anna").stdout
    assert "recorded" in out
    joined = next(p for p in _json(d, "parts") if p["id"] == part["id"])
    assert (joined["ra_um"], joined["diameter_error_um"], joined["measured"], joined["inspector"]) == \
        (4.49, -32.0, {"roundness_um": 3.5}, "qa-anna")
    assert joined["max_chatter_index"] == part["max_chatter_index"]      # both records, one row
    assert part["id"] not in [p["id"] for p in _json(d, "parts", "--queue")]
    assert "inspected" in ctl(d, "parts").stdout

    r = ctl(d, "inspect", "99999", "--ra", "1", check=False)
    assert r.returncode == 1 and r.stderr.count("\n") == 1 and "no part '99999'" in r.stderr

    out_csv = tmp_path / "parts.csv"
    ctl(d, "export", "parts", "--out", str(out_csv))
    rows = list(csv.DictReader(out_csv.open()))
    row = next(r for r in rows if r["id"] == str(part["id"]))
    assert row["ra_um"] == "4.49" and json.loads(row["measured"]) == {"roundness_um": 3.5}
    events = ctl(d, "export", "events").stdout.splitlines()
    assert events[0].startswith("id,uuid,machine_id,t,source,kind,payload")
    assert any(",part_abnormal," in ln for ln in events) and any(",chatter_alarm," in ln for ln in events)


def test_no_daemon_exits_69(tmp_path, monkeypatch):
    from lathed.cli.main import main
    monkeypatch.setenv("LATHED_DB", str(tmp_path / "no.db"))    # nor a database to read instead
    assert main(["--socket", str(tmp_path / "none.sock"), "parts"]) == 69


def test_a_stopped_daemons_store_of_an_older_schema_is_one_line_not_a_missing_column(tmp_path, capsys):
    # after an upgrade, before lathed has started once: "no such column: w.unwatched"
    import sqlite3
    from lathed.cli.main import main
    from lathed.store import MIGRATIONS, statements
    con = sqlite3.connect(tmp_path / "lathed.db", isolation_level=None)
    for _, sql in MIGRATIONS[:5]:
        for stmt in statements(sql):
            con.execute(stmt)
    con.execute("PRAGMA user_version=5")
    con.close()
    assert main(["--socket", str(tmp_path / "none.sock"), "parts", "--db", str(tmp_path / "lathed.db")]) == 69
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.endswith(f"(schema version 5, older than this lathectl's "
                                                   f"{MIGRATIONS[-1][0]}: start lathed once to upgrade it)\n"), err
    # what the old schema has is still read
    assert main(["--socket", str(tmp_path / "none.sock"), "events", "--db", str(tmp_path / "lathed.db")]) == 0


def test_a_misspelt_kind_on_a_stopped_daemons_store_is_one_usage_line(tmp_path, capsys):
    # it listed "(no events)", exit 0, as if none had happened
    from lathed.cli.main import main
    from lathed.store import Store
    s = Store(tmp_path / "lathed.db")
    s.record_future("robot_gripper_slip", "arm", {"n": 1}).result()     # a plugin's own kind
    s.close()
    argv = ["--socket", str(tmp_path / "none.sock"), "events", "--db", str(tmp_path / "lathed.db")]
    assert main([*argv, "--kind", "chatter_alram"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lathectl: --kind: 'chatter_alram' is not a kind of event (did you mean "
                          "'chatter_alarm'?); known: alarm_cleared, ")
    assert err.count("\n") == 1 and "robot_gripper_slip" in err
    assert main([*argv, "--kind", "robot_gripper_slip"]) == 0
    assert "robot_gripper_slip" in capsys.readouterr().out
    assert main([*argv, "--kind", "chatter_alarm"]) == 0          # known, none recorded yet
    assert "(no events)" in capsys.readouterr().out


@pytest.mark.parametrize("argv, msg", [
    (["inspect", "2", "--value", "x=1", "--value", "x=2"], "lathectl: --value x given twice"),
    (["experiment", "add", "--tool", "T1", "--material", "C45", "--run", "1", "--levels", "speed=1",
      "--setting", "speed=1", "--setting", "speed=2"], "lathectl: --setting speed given twice"),
    (["experiment", "add", "--tool", "T1", "--material", "C45", "--run", "1", "--levels", "speed=1,speed=2"],
     "'speed' given twice"),
])
def test_a_name_given_twice_is_refused_not_overwritten(argv, msg, tmp_path, capsys):
    # the last value was kept without a word (x = 2 stored for the inspection)
    from lathed.cli.main import main
    try:
        code = main(["--socket", str(tmp_path / "none.sock"), *argv])
    except SystemExit as e:
        code = e.code
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and msg in err, err


def test_parts_made_while_lathed_was_down_are_listed_not_observed_and_queued(tmp_path, capsys):
    from lathed.cli.records import _t
    from tests.test_records import lathed_down_for_parts_4_to_6
    db = lathed_down_for_parts_4_to_6(tmp_path, t0=1_700_000_000.0)
    code = lathectl.main(["--socket", str(tmp_path / "none.sock"), "parts", "--db", str(db)])
    out = capsys.readouterr().out
    lines = {int(ln.split()[1]): ln for ln in out.splitlines()[1:]}     # by part number
    assert code == 0 and sorted(lines) == [2, 3, 4, 5, 6, 7]
    made = f"made {_t(1_700_000_001.3)} - {_t(1_700_003_601.4)}"    # the last part seen; the first reading after
    for no in (4, 5, 6):      # no chatter figures: nothing was watched, not "0 alarms"
        assert lines[no].split()[5:12] == ["unobserved", "-", "-", "-", "-", "-", "-"], lines[no]
        assert lines[no].endswith(f"NOT OBSERVED (lathed was not running), {made}; "
                                  "QUEUED for sampling inspection"), lines[no]
    assert lines[7].endswith("NOT WATCHED WHOLE (lathed was not running); QUEUED for sampling inspection")
    assert lines[3].split()[5] == "finished" and lines[3].endswith("  -")
    lathectl.main(["--socket", str(tmp_path / "none.sock"), "parts", "--db", str(db), "--queue", "--json"])
    queued = json.loads(capsys.readouterr().out)
    assert [(p["part_no"], p["outcome"], p["queued_reason"]) for p in queued if p["part_no"] >= 4] == [
        (4, "unobserved", "not observed: lathed was not running"),
        (5, "unobserved", "not observed: lathed was not running"),
        (6, "unobserved", "not observed: lathed was not running"),
        (7, "partial", "not watched whole: lathed was not running")]
