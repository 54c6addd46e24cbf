"""The PostgreSQL sink: store-and-forward with no loss and no duplicate,
against a real PostgreSQL server (tests/pg_fixtures.py)."""
from __future__ import annotations

import asyncio
import shutil
import sqlite3
from pathlib import Path

import psycopg
import pytest
import structlog

from lathed.config import Section
from lathed.store import FORWARDED, Store
from lathed_plugins.postgres_sink import PostgresSink
from tests.conftest import Daemon, disk_free, disk_full, wait_until
from tests.pg_fixtures import pg_count, pg_dsn, postgres  # noqa: F401

HERE = Path(__file__).resolve().parent


class Ctx:
    def __init__(self, store):
        self.store = store
        self.log = structlog.get_logger("test")
        self.recorded = []

    def record(self, kind, payload):
        self.recorded.append((kind, payload))
        return self.store.record_future(kind, "central", payload)


def _sink(dsn: str, store: Store, name: str = "central", **keys) -> PostgresSink:
    sec = Section("test.toml", f"analyzer.{name}", {"dsn": dsn, "interval": "20ms", **keys})
    sink = PostgresSink(name, sec)
    sec.check_unused()
    sink.ctx = Ctx(store)
    return sink


async def _drain(sink: PostgresSink, store: Store, timeout: float = 20) -> None:
    task = asyncio.create_task(sink.run())
    try:
        deadline = asyncio.get_running_loop().time() + timeout
        while store.backlog(sink.name) > 0:
            if task.done():
                task.result()
            assert asyncio.get_running_loop().time() < deadline, f"backlog stuck at {store.backlog(sink.name)}"
            await asyncio.sleep(0.02)
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)


def test_forwards_every_table_once_and_resend_is_idempotent(tmp_path, pg_dsn):  # noqa: F811
    store = Store(tmp_path / "a.db", machine_id="cell-a")

    async def s_chatter():
        await store.record("chatter_alarm", "chatter", {"machine": "lathe", "index": 2.5, "threshold": 1.8,
                                                        "chatter_frequency_hz": 197.0, "rpm": 2500.0,
                                                        "depth_mm": 3.0, "tool": "T0101", "material": "C45"})
        await store.record("suppression_action", "suppress", {"strategy": "lobes", "rpm_before": 2500.0,
                                                              "rpm_after": 3250.0, "sent": True})
        await store.record("cut", "suppress", {"machine": "lathe", "tool": "T0101", "material": "C45",
                                               "rpm_start": 2500.0, "rpm_end": 3250.0, "depth_mm": 3.0,
                                               "feed_mm_rev": 0.3, "outcome": "chatter", "first_alarm_s": 0.8,
                                               "chatter_frequency_hz": 197.0, "cured": True,
                                               "speeds": [{"rpm": 2500.0, "outcome": "chatter"},
                                                          {"rpm": 3250.0, "outcome": "stable"}]})

    async def main():
        await s_chatter()
        for i in range(248):
            await asyncio.wrap_future(store.record_future("tick", "w", {"seq": i, "arr": [1, 2]}))
        part = "00000000-0000-0000-0000-000000000001"
        await store.add("workpieces", {"uuid": part, "machine": "lathe", "start_t": 1.0, "end_t": 2.0,
                                       "outcome": "partial", "chatter_alarms": 1, "abnormal": 1,
                                       "reason": "chatter", "unwatched": "records analyzer restarting"})
        await store.add("sampling_queue", {"t": 2.0, "part_uuid": part, "reason": "chatter"})
        await store.add("inspections", {"t": 3.0, "part_uuid": part, "ra_um": 4.2, "diameter_error_um": -30.0,
                                        "measured": {"roundness_um": 3.0}, "inspector": "anna"})
        await store.add("experiments", {"t": 4.0, "tool": "T1", "material": "C45", "levels": {"speed": 1},
                                        "settings": {"speed": 1500}, "ra_um": 2.0})
        sink = _sink(pg_dsn, store, batch=64)
        await _drain(sink, store)
        assert sink.forwarded == store.query("SELECT count(*) AS n FROM outbox")[0]["n"] == 255
        # a crash between the central commit and the local progress update: everything is sent again
        await asyncio.wrap_future(store.set_progress("central", 0))
        again = _sink(pg_dsn, store, batch=100)
        await _drain(again, store)
        assert again.forwarded == 255

    asyncio.run(main())
    with psycopg.connect(pg_dsn) as con:
        counts = {t: con.execute(f"SELECT count(*) FROM {t}").fetchone()[0] for t in FORWARDED}
        assert counts == {"events": 251, "workpieces": 1, "inspections": 1, "sampling_queue": 1,
                          "experiments": 1}
        assert con.execute("SELECT count(DISTINCT payload->>'seq') FROM events WHERE machine_id = 'cell-a'"
                           ).fetchone()[0] == 248
        assert con.execute("SELECT chatter_index, chatter_frequency_hz, tool FROM chatter_events").fetchall() == \
            [(2.5, 197.0, "T0101")]
        assert con.execute("SELECT rpm_after, sent FROM suppression_actions").fetchall() == [(3250.0, True)]
        assert con.execute("SELECT rpm_start, rpm_end, depth_mm, outcome, cured FROM cuts").fetchall() == \
            [(2500.0, 3250.0, 3.0, "chatter", True)]
        assert con.execute("SELECT outcome, unwatched FROM workpieces").fetchall() == \
            [("partial", "records analyzer restarting")]    # a column a later migration added
        ra, measured = con.execute("SELECT ra_um, measured FROM inspections").fetchone()
        assert ra == 4.2 and measured == {"roundness_um": 3.0}   # jsonb, not text
    store.close()


def test_a_batch_whose_progress_the_store_refused_is_not_counted(tmp_path, pg_dsn):  # noqa: F811
    """Committed centrally, its progress refused locally (disk full): the sink fails, the batch
    goes again at its restart, and is counted once."""
    store = Store(tmp_path / "a.db", machine_id="cell-a")
    for i in range(3):
        store.record_future("tick", "w", {"seq": i}).result(5)
    disk_full(store, "forward_progress")
    sink = _sink(pg_dsn, store)

    async def main():
        with pytest.raises(sqlite3.DatabaseError, match="disk is full"):
            await asyncio.wait_for(sink.run(), 20)
        assert sink.forwarded == 0 and store.backlog(sink.name) == 3
        await asyncio.wrap_future(disk_free(store))    # space again
        await _drain(sink, store)
        assert sink.forwarded == 3
    asyncio.run(main())
    store.close()


def test_a_row_the_server_refuses_is_set_aside_and_the_rest_goes_on(tmp_path, pg_dsn):  # noqa: F811
    # PostgreSQL's text and jsonb cannot hold NUL; SQLite can: a string read off a
    # machine's registers may carry one.
    store = Store(tmp_path / "a.db", machine_id="cell-nul")

    async def main():
        for i in range(30):
            payload = {"seq": i, "program": "O1000\x00\x00" if i in (7, 21) else "O1000"}
            await asyncio.wrap_future(store.record_future("tick", "w", payload))
        await asyncio.wrap_future(store.record_future("tick", "w\x00", {"seq": 30}))
        sink = _sink(pg_dsn, store, batch=10)
        await _drain(sink, store)
        return sink

    sink = asyncio.run(main())
    with psycopg.connect(pg_dsn) as con:
        seqs = sorted(int(r[0]) for r in con.execute(
            "SELECT payload->>'seq' FROM events WHERE machine_id = 'cell-nul' AND kind = 'tick'"))
    assert seqs == [i for i in range(30) if i not in (7, 21)]
    refused = store.query("SELECT tbl, row_id, error FROM forward_refused WHERE sink = 'central' ORDER BY row_id")
    assert [(r["tbl"], r["row_id"]) for r in refused] == [("events", 8), ("events", 22), ("events", 31)]
    assert all("refused the records" in r["error"] for r in refused), refused
    # each is reported, counted, and still in the local store
    assert [k for k, _ in sink.ctx.recorded] == ["forward_refused"] * 3
    st = sink.status()
    assert st["refused"] == 3 and "3 row(s) refused by the server" in st["summary"]
    assert store.query("SELECT count(*) AS n FROM events WHERE kind = 'tick'")[0]["n"] == 31
    store.close()


def test_server_down_is_a_fault_with_the_cause(tmp_path, postgres):  # noqa: F811
    store = Store(tmp_path / "a.db", machine_id="cell-a")
    sink = _sink(f"host=127.0.0.1 port={postgres.port + 0} user=nobody_here dbname=none", store, timeout="2s")

    async def main():
        with pytest.raises(ConnectionError, match="PostgreSQL at 127.0.0.1"):
            await sink.run()

    asyncio.run(main())
    assert "unreachable" in sink.last_error and sink.status()["backlog"] == 0
    store.close()


def _config(tmp: Path, dsn: str, total: int) -> tuple[Path, Path]:
    plugins = tmp / "plugins"
    plugins.mkdir(exist_ok=True)
    shutil.copy(HERE / "writer_plugin.py", plugins / "test_writer.py")
    cfg = tmp / "lathed.toml"
    cfg.write_text(f"""
[daemon]
name = "cell-pg"
state_dir = "{tmp / 'state'}"
runtime_dir = "{tmp / 'run'}"
plugin_dirs = ["{plugins}"]

[analyzer.writer]
plugin = "test_writer"
total = {total}
every = "4ms"

[analyzer.central]
plugin = "postgres_sink"
dsn = "{dsn}"
batch = 50
interval = "30ms"
timeout = "5s"
retry_initial = "100ms"
retry_max = "400ms"
""")
    return cfg, tmp / "run" / "lathed.sock"


def _local(db: Path, sql: str):
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=10)
    try:
        return con.execute(sql).fetchall()
    finally:
        con.close()


def test_outage_and_restart_lose_nothing_and_duplicate_nothing(tmp_path, postgres, pg_dsn):  # noqa: F811
    total = 900
    cfg, sock = _config(tmp_path, pg_dsn, total)
    db = tmp_path / "state" / "lathed.db"
    d = Daemon(cfg, sock)
    try:
        d.wait_ready()
        wait_until(lambda: pg_count(pg_dsn, "events") >= 100, 30, what="first records in PostgreSQL")
        postgres.stop()                                    # the central side goes away mid-stream
        at_stop = _local(db, "SELECT count(*) FROM events WHERE kind = 'tick'")[0][0]
        wait_until(lambda: "unreachable" in (d.item("analyzers", "central").get("last_error") or ""),
                   20, what="the sink to report the outage")
        wait_until(lambda: _local(db, "SELECT count(*) FROM events WHERE kind = 'tick'")[0][0] >= at_stop + 100,
                   20, what="records written locally during the outage")
        d.proc.kill()                                      # the daemon crashes during the outage
        d.proc.wait(10)
        d.log.close()

        d = Daemon(cfg, sock)
        d.wait_ready()
        wait_until(lambda: d.item("analyzers", "writer").get("done"), 60, what="the writer to finish")
        backlog = d.item("analyzers", "central")["backlog"]
        assert backlog > 100, "records should be waiting while PostgreSQL is down"

        postgres.start()                                   # the central side comes back
        wait_until(lambda: d.item("analyzers", "central")["backlog"] == 0, 60, what="the backlog to drain")
        d.stop()
        local = {u for (u,) in _local(db, "SELECT uuid FROM events")}
        with psycopg.connect(pg_dsn) as con:
            ticks = con.execute("SELECT count(*), count(DISTINCT uuid), count(DISTINCT (payload->>'seq')::int), "
                                "min((payload->>'seq')::int), max((payload->>'seq')::int) "
                                "FROM events WHERE kind = 'tick'").fetchone()
            central = [u for (u,) in con.execute("SELECT uuid FROM events WHERE machine_id = 'cell-pg'")]
        assert ticks == (total, total, total, 0, total - 1)
        assert len(central) == len(set(central))
        # everything recorded before the final stop is central; the stop event itself may trail
        assert set(central) <= local and len(local - set(central)) <= 2
        assert _local(db, "SELECT outbox_id FROM forward_progress WHERE sink = 'central'")[0][0] > total
    finally:
        d.stop()
        if not postgres.running():
            postgres.start()
