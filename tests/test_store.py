"""The embedded store: migrations, record identity, outbox, views."""
from __future__ import annotations

import asyncio
import sqlite3

import pytest

from lathed import store as storemod
from lathed.store import FORWARDED, MIGRATIONS, Store


def test_migrations_are_appended_in_order_and_rerun_is_a_no_op(tmp_path):
    versions = [v for v, _ in MIGRATIONS]
    assert versions == list(range(1, len(versions) + 1))
    s = Store(tmp_path / "a.db")
    s.close()
    again = Store(tmp_path / "a.db")
    assert again.schema_version == versions[-1]
    again.close()


def test_version_1_database_is_upgraded_and_its_events_will_be_forwarded(tmp_path):
    con = sqlite3.connect(tmp_path / "old.db", isolation_level=None)
    con.executescript(MIGRATIONS[0][1] + "PRAGMA user_version=1;")
    con.execute("INSERT INTO events(uuid, t, source, kind, payload) VALUES ('u-old', 1.0, 'x', 'k', '{}')")
    con.close()
    s = Store(tmp_path / "old.db", machine_id="cell-9")
    assert s.schema_version == MIGRATIONS[-1][0]
    ((_, tbl, row),) = s.pending("central", 10)
    assert (tbl, row["uuid"], row["machine_id"]) == ("events", "u-old", "cell-9")
    s.close()


def test_version_4_database_gains_the_turret_tool_in_its_parts_and_views(tmp_path):
    con = sqlite3.connect(tmp_path / "v4.db", isolation_level=None)
    con.executescript("".join(sql for v, sql in MIGRATIONS if v <= 4) + "PRAGMA user_version=4;")
    con.execute("INSERT INTO events(uuid, t, source, kind, payload) VALUES ('c1', 1.0, 'suppress', 'cut', "
                "'{\"machine\": \"lathe\", \"tool_number\": 2, \"outcome\": \"chatter\"}')")
    con.execute("INSERT INTO events(uuid, t, source, kind, payload) VALUES ('a1', 1.0, 'chatter', "
                "'chatter_alarm', '{\"machine\": \"lathe\", \"tool_number\": 2}')")
    con.close()
    s = Store(tmp_path / "v4.db")
    assert s.schema_version == MIGRATIONS[-1][0]
    assert s.query("SELECT outcome, tool_number FROM cuts") == [{"outcome": "chatter", "tool_number": 2}]
    assert s.query("SELECT kind, tool_number FROM chatter_events") == [{"kind": "chatter_alarm", "tool_number": 2}]
    assert {"tools", "unwatched"} <= {n for n, _ in s.columns("workpieces")}
    s.close()


def test_statement_splitter_keeps_trigger_bodies_whole():
    stmts = storemod.statements("CREATE TABLE a(x);\nCREATE TRIGGER t AFTER INSERT ON a\n"
                                "BEGIN INSERT INTO a VALUES (1); INSERT INTO a VALUES (2); END;\n")
    assert len(stmts) == 2 and stmts[1].endswith("END;")
    with pytest.raises(ValueError, match="incomplete"):
        storemod.statements("CREATE TABLE a(x)")


def test_every_record_has_uuid_identity_and_an_outbox_entry_in_commit_order(tmp_path):
    s = Store(tmp_path / "a.db", machine_id="cell-1")

    async def main():
        await s.record("chatter_alarm", "chatter", {"machine": "lathe", "index": 2.5, "threshold": 1.0,
                                                    "chatter_frequency_hz": 312.0, "rpm": 2500.0,
                                                    "depth_mm": 3.0, "tool": "T0101", "material": "C45"})
        await s.record("suppression_action", "sss", {"strategy": "sss", "rpm_before": 2500.0,
                                                     "rpm_after": 750.0, "sent": True})
        await s.record("compensation", "thermal", {"predicted_um": 12.0, "offset_um": -12.0, "model": "mlr"})
        await s.add("workpieces", {"machine": "lathe", "start_t": 1.0, "end_t": 2.0, "outcome": "finished",
                                   "chatter_alarms": 0, "abnormal": 0})
        await s.add("inspections", {"t": 1.0, "part_uuid": "p", "measured": {"ovality_um": 2.0}})
    asyncio.run(main())

    pending = s.pending("x", 100)
    assert [tbl for _, tbl, _ in pending] == ["events"] * 3 + ["workpieces", "inspections"]
    assert [oid for oid, _, _ in pending] == sorted(oid for oid, _, _ in pending)
    assert all(r["machine_id"] == "cell-1" and len(r["uuid"]) == 36 for _, _, r in pending)
    assert len({r["uuid"] for _, _, r in pending}) == 5

    (c,) = s.query("SELECT * FROM chatter_events")
    assert (c["chatter_index"], c["threshold"], c["chatter_frequency_hz"], c["rpm"], c["depth_mm"],
            c["tool"], c["material"], c["machine"]) == (2.5, 1.0, 312.0, 2500.0, 3.0, "T0101", "C45", "lathe")
    (a,) = s.query("SELECT * FROM suppression_actions")
    assert (a["rpm_before"], a["rpm_after"], a["sent"]) == (2500.0, 750.0, 1)
    (k,) = s.query("SELECT * FROM compensations")
    assert (k["predicted_um"], k["offset_um"], k["model"]) == (12.0, -12.0, "mlr")

    assert s.backlog("x") == 5
    s.set_progress("x", pending[2][0]).result(5)
    assert s.backlog("x") == 2 and [t for _, t, _ in s.pending("x", 100)] == ["workpieces", "inspections"]
    assert s.backlog("other") == 5     # each sink keeps its own progress
    s.close()


def test_insert_refuses_non_record_tables_and_bad_rows_do_not_sink_the_batch(tmp_path):
    s = Store(tmp_path / "a.db")
    with pytest.raises(ValueError, match="not a record table"):
        s.insert("outbox", {"tbl": "x"})
    bad = s.insert("sampling_queue", {"t": 1.0, "part_uuid": "p"})          # reason is NOT NULL
    good = s.insert("sampling_queue", {"t": 1.0, "part_uuid": "q", "reason": "chatter"})
    with pytest.raises(sqlite3.IntegrityError):
        bad.result(5)
    assert good.result(5) >= 1
    dup = s.insert("sampling_queue", {"t": 2.0, "part_uuid": "q", "reason": "again"})  # queued once only
    with pytest.raises(sqlite3.IntegrityError):
        dup.result(5)
    assert set(FORWARDED) == {r["row_tbl"] for r in s.query(
        "SELECT DISTINCT substr(name, 1, length(name) - 7) AS row_tbl FROM sqlite_master "
        "WHERE type = 'trigger' AND name LIKE '%_outbox'")}
    s.close()


def test_non_finite_numbers_are_recorded_as_null_so_the_views_still_read(tmp_path):
    s = Store(tmp_path / "a.db")
    asyncio.run(s.record("chatter_alarm", "chatter", {"index": float("nan"), "threshold": 1.8,
                                                      "spectrum": [1.0, float("inf")], "nested": {"x": float("-inf")}}))
    (row,) = s.query("SELECT chatter_index, threshold FROM chatter_events")
    assert row == {"chatter_index": None, "threshold": 1.8}
    assert s.events(kind="chatter_alarm")[0]["payload"] == {"index": None, "threshold": 1.8,
                                                           "spectrum": [1.0, None], "nested": {"x": None}}
    s.close()


class Clocks:
    """A wall clock and a monotonic clock the test moves; the store clock runs with the second."""

    def __init__(self, wall: float = 1_790_000_000.0) -> None:
        self.wall_t, self.mono_t = wall, 1000.0

    def wall(self) -> float:
        return self.wall_t

    def mono(self) -> float:
        return self.mono_t

    def run(self, s: float) -> None:
        self.wall_t += s
        self.mono_t += s

    def store(self, path, **kw) -> Store:
        return Store(path, wall=self.wall, monotonic=self.mono, **kw)


def test_retention_deletes_only_old_records_every_sink_has_forwarded(tmp_path, monkeypatch):
    monkeypatch.setattr(storemod, "PRUNE_CHUNK", 7)      # several chunks
    clocks = Clocks()
    s = clocks.store(tmp_path / "a.db", machine_id="cell-r")
    day = 86400.0
    for k in range(40):                                  # 40 old events, then 10 recent ones
        s.record_future("tick", "w", {"k": k}, t=1000.0 + k).result(10)
    part = "00000000-0000-0000-0000-00000000000a"
    s.insert("workpieces", {"uuid": part, "machine": "lathe", "start_t": 1050.0, "end_t": 1060.0,
                            "outcome": "finished", "chatter_alarms": 0, "abnormal": 0}).result(10)
    clocks.run(10 * day)
    for k in range(10):
        s.record_future("tick", "w", {"k": 100 + k}, t=10 * day + k).result(10)
    # sink "central" forwarded the first 30 outbox entries; "backup" only 20
    s.set_progress("central", 30).result(10)
    s.set_progress("backup", 20).result(10)
    removed = s.prune(s.clock.now() - 5 * day, ["central", "backup"])
    assert removed["events"] == 20 and removed["workpieces"] == 0
    ks = [r["payload"]["k"] for r in s.events(100, "tick", None, 0)]
    assert sorted(ks) == list(range(20, 40)) + list(range(100, 110))
    # limit None: every one, oldest first (a refit reads all its measurements)
    assert [r["payload"]["k"] for r in s.events(None, "tick")] == ks
    assert [r["payload"]["k"] for r in s.events(2, "tick")] == ks[-2:]
    # what is left still forwards in order, with no hole in the outbox
    assert [t for _, t, _ in s.pending("backup", 100)][:1] == ["events"] and s.backlog("backup") == 31
    # once both have forwarded everything, the old rest goes, the recent stays
    last = s.query("SELECT max(id) AS m FROM outbox")[0]["m"]
    s.set_progress("central", last).result(10)
    s.set_progress("backup", last).result(10)
    removed = s.prune(s.clock.now() - 5 * day, ["central", "backup"])
    assert removed == {"events": 20, "workpieces": 1, "inspections": 0, "sampling_queue": 0, "experiments": 0}
    assert sorted(r["payload"]["k"] for r in s.events(100, "tick", None, 0)) == list(range(100, 110))
    assert s.pending("backup", 100) == [] and s.prune(s.clock.now() - 5 * day, ["central", "backup"])["events"] == 0
    s.close()


def test_retention_without_sinks_and_with_a_sink_that_never_forwarded(tmp_path):
    s = Store(tmp_path / "a.db")
    for k in range(5):
        s.record_future("tick", "w", {"k": k}, t=1.0).result(10)
    later = s.clock.now() + 1.0
    assert s.prune(later, ["central"])["events"] == 0     # not yet forwarded: kept
    assert s.prune(later, [])["events"] == 5               # no sink: the age alone decides
    s.close()


def _count(path, kind: str) -> int:
    con = sqlite3.connect(path)
    try:
        return con.execute("SELECT count(*) FROM events WHERE kind = ?", (kind,)).fetchone()[0]
    finally:
        con.close()


def test_a_value_sqlite_cannot_bind_fails_only_its_record_and_the_writer_goes_on(tmp_path):
    # issue 18 D1: an int beyond 64 bits raised OverflowError in the writer thread and killed it
    s = Store(tmp_path / "a.db")
    bad = s.insert("experiments", {"t": 1.0, "tool": "T", "material": "M", "levels": {"A": 1},
                                   "settings": {}, "run": 10 ** 30})
    good = s.record_future("tick", "w", {"k": 1})
    with pytest.raises(storemod.StoreError, match="record not stored: OverflowError"):
        bad.result(10)
    assert good.result(10) >= 1
    assert s.record_future("tick", "w", {"k": 2}).result(10) >= 1    # and later records too
    st = s.stats()
    assert (st["failed"], st["written"], st["queued"], st["failing"], st["writer_alive"]) == (1, 2, 0, False, True)
    assert "OverflowError" in st["last_error"] and st["last_error_t"] > 0
    s.close()


def test_close_commits_every_queued_record_even_behind_a_poison_record(tmp_path):
    s = Store(tmp_path / "a.db")
    s.insert("experiments", {"t": 1.0, "tool": "T", "material": "M", "levels": {"A": 1},
                             "settings": {}, "run": 10 ** 30})
    futs = [s.record_future("command_sent", "suppress", {"k": k}) for k in range(300)]
    s.close()                                   # without waiting for any of them
    assert all(f.done() and f.exception() is None for f in futs)
    assert _count(tmp_path / "a.db", "command_sent") == 300
    with pytest.raises(storemod.StoreError, match="closed"):
        s.record_future("late", "w", {})       # refused in one line, not queued forever


def test_a_writer_fault_fails_its_batch_only_and_is_recorded(tmp_path):
    s = Store(tmp_path / "a.db")
    real = s._commit
    calls = []

    def faulty(batch):
        calls.append(len(batch))
        if len(calls) == 1:
            raise RuntimeError("bug in the writer")
        real(batch)
    s._commit = faulty
    with pytest.raises(storemod.StoreError, match="store writer fault.*RuntimeError: bug in the writer"):
        s.record_future("tick", "w", {}).result(10)
    assert s.stats()["failing"] is True
    assert s.record_future("tick", "w", {}).result(10) >= 1          # served again, and recovered
    st = s.stats()
    assert (st["failed"], st["written"], st["failing"]) == (1, 1, False)
    assert "bug in the writer" in st["last_error"]
    s.close()


def test_a_dead_writer_is_reported_and_close_still_commits_the_queue(tmp_path):
    s = Store(tmp_path / "a.db")
    real = s._commit

    def dying(batch):
        s._commit = real                        # for the drain in close()
        raise SystemExit("writer thread killed")
    s._commit = dying
    first = s.record_future("tick", "w", {"k": 0})
    from tests.conftest import wait_until
    wait_until(lambda: not s.writer_alive, 10, what="the writer thread to end")
    st = s.stats()
    assert st["failing"] is True and st["writer_alive"] is False
    assert "SystemExit: writer thread killed" in st["writer_error"]
    later = [s.record_future("command_sent", "suppress", {"k": k}) for k in range(50)]
    s.close()
    assert all(f.result(0) >= 1 for f in later)                    # acknowledged at close
    assert first.result(0) >= 1                                    # the batch in hand when it died, too
    assert _count(tmp_path / "a.db", "command_sent") == 50


def test_any_exception_binding_a_record_fails_that_record_alone(tmp_path):
    class Unadaptable:
        def __conform__(self, protocol):
            raise RuntimeError("cannot adapt")
    s = Store(tmp_path / "a.db")
    bad = s.set_progress("central", Unadaptable())
    good = s.record_future("tick", "w", {})
    with pytest.raises(storemod.StoreError, match="record not stored: RuntimeError: cannot adapt"):
        bad.result(10)
    assert good.result(10) >= 1 and s.stats()["failing"] is False and s.writer_alive
    s.close()


def test_a_record_whose_waiter_was_cancelled_does_not_fail_its_committed_batch(tmp_path):
    # a sink cancelled while it awaited asyncio.wrap_future(set_progress(...)) cancels the
    # concurrent future: the batch it is in still commits, and is reported committed
    import threading
    s = Store(tmp_path / "a.db")
    real = s._commit
    taken, release = threading.Event(), threading.Event()

    def held(batch):                           # a slow fsync: what comes now queues behind it
        s._commit = real
        taken.set()
        release.wait(10)
        real(batch)
    s._commit = held
    first = s.record_future("tick", "w", {})
    assert taken.wait(10)
    progress = s.set_progress("mqtt", 1)
    event = s.record_future("part_abnormal", "records", {"part": 1})
    assert progress.cancel()
    release.set()
    assert first.result(10) >= 1 and event.result(10) >= 1
    st = s.stats()
    assert (st["failed"], st["failing"], st["last_error"]) == (0, False, None)
    s.close()
    assert _count(tmp_path / "a.db", "part_abnormal") == 1
    con = sqlite3.connect(tmp_path / "a.db")
    assert con.execute("SELECT sink, outbox_id FROM forward_progress").fetchall() == [("mqtt", 1)]
    con.close()


def test_a_sinks_first_progress_is_set_once(tmp_path):
    """begin_progress: after every record so far, or before the first; never over a saved place."""
    s = Store(tmp_path / "a.db")
    try:
        for i in range(3):
            s.record_future("tick", "w", {"i": i})
        s.begin_progress("now", at_end=True).result(10)
        s.begin_progress("oldest", at_end=False).result(10)
        assert (s.progress("now"), s.progress("oldest"), s.backlog("now"), s.backlog("oldest")) == (3, 0, 0, 3)
        s.record_future("tick", "w", {"i": 3}).result(10)
        s.set_progress("oldest", 2).result(10)
        for sink in ("now", "oldest"):               # a restart: the saved place stands
            s.begin_progress(sink, at_end=True).result(10)
        assert (s.progress("now"), s.progress("oldest")) == (3, 2)
    finally:
        s.close()


def test_a_record_taken_by_the_writer_can_no_longer_be_cancelled(tmp_path):
    import threading
    s = Store(tmp_path / "a.db")
    taken, release = threading.Event(), threading.Event()

    def hold():                                # the writer is executing this record
        taken.set()
        release.wait(10)
        return 0
    s._wcon.create_function("hold", 0, hold)
    fut = s.submit("SELECT hold()", ())
    assert taken.wait(10)
    cancelled = fut.cancel()                   # too late: it is being written
    release.set()
    fut.result(10)
    assert not cancelled and s.stats()["failed"] == 0
    s.close()


def test_retention_waits_for_every_configured_sink_also_one_not_running(tmp_path, monkeypatch):
    # a postgres_sink whose constructor failed (psycopg without libpq) and a disabled mqtt_sink
    # are not running; their unforwarded records are kept all the same
    import threading
    import time
    import lathed_plugins.postgres_sink as pg
    from lathed import daemon as daemonmod

    def no_libpq(self, name, section):
        raise ImportError("no pq wrapper available")
    monkeypatch.setattr(pg.PostgresSink, "__init__", no_libpq)
    cfg = tmp_path / "lathed.toml"
    cfg.write_text(f'''
[daemon]
state_dir = "{tmp_path}/state"
runtime_dir = "{tmp_path}/run"
[store]
keep_days = 1
[analyzer.central]
plugin = "postgres_sink"
dsn = "host=db.plant dbname=lathed"
[analyzer.broker]
plugin = "mqtt_sink"
enabled = false
host = "broker.plant"
''')
    cfg, settings, loader, plan, sim = daemonmod.prepare(cfg, strict=False)
    assert "analyzer.central" in plan.skipped and not plan.analyzers
    clocks = Clocks()
    s = clocks.store(tmp_path / "a.db")
    d = daemonmod.Daemon(cfg, settings, loader, plan, sim, s)
    for k in range(5):
        s.record_future("tick", "w", {"k": k}).result(10)
    clocks.run(3 * 86400)
    s.set_progress("broker", 5).result(10)            # forwarded before it was disabled
    real, passes = s.prune, []
    pruned = threading.Event()

    def prune(before_t, sinks):
        passes.append((sorted(sinks), real(before_t, sinks)["events"]))
        pruned.set()
    monkeypatch.setattr(s, "prune", prune)
    d.settings.prune_every = 0.0

    async def one_pass():
        task = asyncio.create_task(d._prune())
        assert await asyncio.to_thread(pruned.wait, 5)
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    asyncio.run(one_pass())
    assert passes[:1] == [(["broker", "central"], 0)]       # central never forwarded: nothing goes
    s.set_progress("central", 2).result(10)
    assert real(s.clock.now() - 86400, ["broker", "central"])["events"] == 2
    s.close()


def _prune_pass(tmp_path, store: Store, keep_days: float) -> dict:
    """One retention pass of a daemon (no sinks) over ``store``; its last_prune."""
    from lathed import daemon as daemonmod
    cfg = tmp_path / "lathed.toml"
    cfg.write_text(f'[daemon]\nstate_dir = "{tmp_path}/state"\nruntime_dir = "{tmp_path}/run"\n'
                   f'[store]\nkeep_days = {keep_days}\n[sensor.t]\nplugin = "ds18b20_serial"\nport = "/dev/null"\n')
    cfg, settings, loader, plan, sim = daemonmod.prepare(cfg, strict=False)
    d = daemonmod.Daemon(cfg, settings, loader, plan, sim, store)
    d.settings.prune_every = 0.0

    async def one_pass():
        task = asyncio.create_task(d._prune())
        while d.last_prune is None:
            await asyncio.sleep(0)     # the pass runs in a thread: yield until it has reported
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    asyncio.run(asyncio.wait_for(one_pass(), 10))
    return d.last_prune


def test_a_wall_clock_set_ahead_ages_no_record(tmp_path, monkeypatch):
    # the PC's clock jumps 400 days ahead (a dead RTC battery, then a wrong NTP answer, or a
    # typo in `date`): aged by the wall clock, every record was older than keep_days at once
    import time
    clocks = Clocks(wall=time.time())
    s = clocks.store(tmp_path / "a.db")
    for k in range(5):
        s.record_future("tick", "w", {"k": k}).result(10)
    clocks.run(3600.0)
    clocks.wall_t += 400 * 86400.0
    monkeypatch.setattr(time, "time", clocks.wall)
    assert _prune_pass(tmp_path, s, keep_days=30)["removed"]["events"] == 0
    assert _count(tmp_path / "a.db", "tick") == 5
    assert s.stats()["clock_minus_wall_s"] == -400 * 86400.0
    s.close()


def test_records_written_while_the_clock_was_behind_are_not_deleted_when_it_is_set_right(tmp_path, monkeypatch):
    # a reboot with the RTC reset to 2000: records are stamped 2000 until NTP sets the clock
    # right; aged by their stamps they were deleted at the next pass, minutes old
    import time
    right = time.time()
    clocks = Clocks(wall=right)
    s = clocks.store(tmp_path / "a.db")
    s.record_future("tick", "w", {"k": 0}).result(10)
    s.close()
    clocks.wall_t = 946_684_800.0                  # 2000-01-01
    s = clocks.store(tmp_path / "a.db")            # the stop counts nothing: the clock is behind
    monkeypatch.setattr(time, "time", clocks.wall)
    for k in range(1, 6):
        s.record_future("tick", "w", {"k": k}).result(10)
    assert s.events(1, "tick", None, 0)[0]["t"] == 946_684_800.0
    clocks.run(120.0)
    clocks.wall_t = right + 180.0                  # NTP sets it right
    assert _prune_pass(tmp_path, s, keep_days=1)["removed"]["events"] == 0
    assert _count(tmp_path / "a.db", "tick") == 6
    s.close()


def test_the_store_clock_counts_a_stop_up_to_a_week(tmp_path):
    day = 86400.0
    clocks = Clocks()
    s = clocks.store(tmp_path / "a.db")
    t0 = s.clock.now()
    clocks.run(60.0)
    clocks.wall_t += 30 * day                      # a jump while running counts nothing
    assert s.clock.now() == pytest.approx(t0 + 60.0)
    s.close()
    for stopped, counted in ((3 * day, 3 * day), (400 * day, 7 * day), (-2 * day, 0.0)):
        before = Store(tmp_path / "a.db", wall=clocks.wall, monotonic=clocks.mono)
        was = before.clock.now()
        before.close()
        clocks.wall_t += stopped
        after = clocks.store(tmp_path / "a.db")
        assert after.clock.now() == pytest.approx(was + counted, abs=1e-6), stopped
        after.close()


def test_version_5_database_ages_its_rows_by_their_record_time(tmp_path):
    con = sqlite3.connect(tmp_path / "old.db", isolation_level=None)
    for v, sql in MIGRATIONS[:5]:
        for stmt in storemod.statements(sql):
            con.execute(stmt)
    con.execute("PRAGMA user_version=5")
    con.execute("INSERT INTO events(uuid, t, source, kind, payload) VALUES ('u-old', 1000.0, 'x', 'k', '{}')")
    con.execute("INSERT INTO workpieces(uuid, machine_id, machine, start_t, end_t, outcome, chatter_alarms, "
                "abnormal) VALUES ('p-old', 'm', 'lathe', 10.0, 2000.0, 'finished', 0, 0)")
    con.close()
    s = Store(tmp_path / "old.db")
    assert {r["tbl"]: r["age_t"] for r in s.query("SELECT tbl, age_t FROM outbox")} == \
        {"events": 1000.0, "workpieces": 2000.0}
    assert s.prune(1500.0, [])["events"] == 1 and s.prune(1500.0, [])["workpieces"] == 0
    s.close()


def _recorded_kinds() -> tuple[set[str], list[str]]:
    """The kinds the code records: first arguments of record(), record_future(),
    event_statement() and the drivers' _record(); f"{category}_fault" as its tail."""
    import ast
    from pathlib import Path
    root = Path(__file__).resolve().parent.parent
    kinds, other = set(), []
    for p in [*(root / "lathed").rglob("*.py"), *(root / "plugins").glob("*.py")]:
        for n in ast.walk(ast.parse(p.read_text(encoding="utf-8"))):
            if not (isinstance(n, ast.Call) and n.args):
                continue
            name = n.func.attr if isinstance(n.func, ast.Attribute) else getattr(n.func, "id", None)
            if name not in ("record", "record_future", "event_statement", "_record"):
                continue
            a = n.args[0]
            if isinstance(a, ast.Constant) and isinstance(a.value, str):
                kinds.add(a.value)
            elif isinstance(a, ast.JoinedStr) and isinstance(a.values[-1], ast.Constant):
                kinds |= {f"{c}{a.values[-1].value}" for c in ("machine", "sensor", "analyzer")}
            else:
                other.append(f"{p.relative_to(root)}:{n.lineno}")
    return kinds, other


def test_every_kind_the_code_records_is_a_known_kind():
    # lathectl events --kind refuses a kind not known (a misspelt one listed nothing, without a word)
    kinds, _ = _recorded_kinds()
    assert len(kinds) > 40
    assert kinds - storemod.KINDS == set()


def test_a_kind_is_known_from_the_code_or_the_store_and_an_unknown_one_is_named(tmp_path):
    s = Store(tmp_path / "a.db")
    try:
        assert s.unknown_kind(["chatter_alarm"]) is None          # known before any was recorded
        why = s.unknown_kind(["chatter_alarm", "chatter_alram"])
        assert why.startswith("'chatter_alram' is not a kind of event (did you mean 'chatter_alarm'?); known: "
                              "alarm_cleared, ")
        assert "chatter_alarm" in why and "\n" not in why
        s.record_future("robot_gripper_slip", "arm", {}).result()  # a third-party plugin's kind
        assert s.unknown_kind(["robot_gripper_slip"]) is None
        assert "robot_gripper_slip" in s.unknown_kind(["nope"])
    finally:
        s.close()


def test_a_schema_upgrade_at_start_tells_systemd_it_may_take_long(tmp_path, monkeypatch):
    # a big store's upgrade outlasting the start timeout would be killed, rolled back and tried
    # again at each restart: the daemon would never start
    import socket
    from lathed.daemon import open_store
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(tmp_path / "notify"))
    sock.setblocking(False)
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "notify"))
    con = sqlite3.connect(tmp_path / "old.db", isolation_level=None)
    for v, sql in MIGRATIONS[:5]:
        for stmt in storemod.statements(sql):
            con.execute(stmt)
    con.execute("PRAGMA user_version=5")
    con.close()
    open_store(tmp_path / "old.db", "cell").close()
    said = sock.recv(4096).decode()
    assert f"from schema 5 to {MIGRATIONS[-1][0]}" in said and "EXTEND_TIMEOUT_USEC=3600000000" in said
    open_store(tmp_path / "old.db", "cell").close()          # upgraded: nothing to say
    with pytest.raises(BlockingIOError):
        sock.recv(4096)
    sock.close()


@pytest.mark.parametrize("wall_at_upgrade, resumes_at", [(400 * 86400.0, 7 * 86400.0), (-20 * 365 * 86400.0, 0.0)])
def test_a_store_upgraded_to_the_clock_resumes_from_its_newest_record(tmp_path, wall_at_upgrade, resumes_at):
    # the first start after the upgrade took the wall clock as it found it: a year ahead, it
    # aged every record at once; behind (an RTC reset), new rows sat years before the old ones
    t_last = 1_790_000_000.0
    con = sqlite3.connect(tmp_path / "old.db", isolation_level=None)
    for v, sql in MIGRATIONS[:5]:
        for stmt in storemod.statements(sql):
            con.execute(stmt)
    con.execute("PRAGMA user_version=5")
    for k in range(10):
        con.execute("INSERT INTO events(uuid, t, source, kind, payload) VALUES (?, ?, 'x', 'tick', '{}')",
                    (f"u{k}", t_last - (9 - k) * 86400.0))
    con.close()
    clocks = Clocks(wall=t_last + wall_at_upgrade)
    s = clocks.store(tmp_path / "old.db")
    assert s.clock.now() == pytest.approx(t_last + resumes_at)
    assert s.prune(s.clock.now() - 30 * 86400.0, [])["events"] == 0
    s.record_future("tick", "w", {}).result(10)
    ages = [r["age_t"] for r in s.query("SELECT age_t FROM outbox ORDER BY id")]
    assert ages == sorted(ages)
    s.close()


def test_settled_returns_once_the_records_before_it_are_committed(tmp_path):
    # `lathectl events` after a command: the command replies before the writer commits the
    # events it recorded; the read waits for them (Store.settled) instead of missing them
    import threading
    s = Store(tmp_path / "a.db")
    real, gate = s._commit, threading.Event()

    def slow(batch):
        gate.wait(10)
        real(batch)
    s._commit = slow
    fut = s.record_future("suppression_mode", "suppression", {"mode": "advise"})

    async def main():
        waiter = asyncio.create_task(s.settled(timeout=10))
        await asyncio.sleep(0)
        seen_before = [e["kind"] for e in s.events(kind="suppression_mode")]
        gate.set()
        await waiter
        return seen_before, [e["kind"] for e in s.events(kind="suppression_mode")]
    before, after = asyncio.run(main())
    assert before == [] and after == ["suppression_mode"] and fut.done()
    assert s.stats()["written"] == 1 and s.stats()["failed"] == 0      # the barrier is no record
    s.close()
    asyncio.run(s.settled(timeout=1))      # a closed store: the read goes on with what is there
