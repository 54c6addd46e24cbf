"""The embedded record store: SQLite in WAL mode, written off the event loop.

One writer thread owns the write connection and commits in groups: whatever
queued while the last commit ran goes in the next transaction. A record is
acknowledged (its future resolves) only after its transaction has committed
with synchronous=FULL, so an acknowledged record survives the daemon being
killed.

Every record row carries a stable uuid and the daemon's identity
(``machine_id``), so a central copy can tell records of many daemons apart
and a resend is recognised. Inserting into a forwarded table also appends
to ``outbox`` (by trigger, in the same transaction): the one global order in
which sinks forward, each keeping its progress in ``forward_progress``.
"""
from __future__ import annotations

import asyncio
import json
import math
import os
import queue
import sqlite3
import stat
import threading
import time
import uuid as uuidlib
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import structlog

# the schema's names, where the store's users have always found them
from lathed.schema import EVENT_SQL, KINDS, MIGRATIONS, migrate, statements, unknown_kind  # noqa: F401

log = structlog.get_logger("lathed.store")

# The wall time a stopped daemon's downtime counts for on the store clock at most: a longer
# gap may be a clock set ahead while it was down, and must not age every record at once.
MAX_STOPPED_S = 7 * 86400.0
PRUNE_CHUNK = 2000

# SQLite primary result codes that say the storage failed, not the record:
# IOERR, CORRUPT, FULL, CANTOPEN, READONLY, NOTADB.
STORAGE_ERRORS = frozenset({10, 11, 13, 14, 8, 26})
BARRIER = "-- settled: every record before this one committed"    # queued by Store.settled(), never run

# Tables whose rows are forwarded to sinks, and their JSON-valued columns.
FORWARDED = ("events", "workpieces", "inspections", "sampling_queue", "experiments")
JSON_COLUMNS = frozenset({"payload", "measured", "levels", "settings"})


def connect(path: str | Path, readonly: bool = False) -> sqlite3.Connection:
    if readonly:
        # A stopped daemon's store (lathectl). A clean stop leaves no -wal: opened immutable, reading
        # creates no -shm/-wal beside it, so a member of the lathed group, who may read the store but
        # not write its directory, can read it (mode=ro alone: "attempt to write a readonly database").
        # After a crash the -wal holds records: read it too.
        immutable = "" if Path(f"{path}-wal").exists() else "&immutable=1"
        con = sqlite3.connect(f"{Path(path).absolute().as_uri()}?mode=ro{immutable}", uri=True, timeout=10,
                              check_same_thread=False)
    else:
        con = sqlite3.connect(str(path), timeout=10, isolation_level=None, check_same_thread=False)
        con.execute("PRAGMA journal_mode=WAL")
        con.execute("PRAGMA synchronous=FULL")
    con.row_factory = sqlite3.Row
    return con


def read_rows(con: sqlite3.Connection, sql: str, params: tuple = ()) -> list[dict[str, Any]]:
    """Store.query on any connection (lathectl reads a stopped daemon's database read-only)."""
    return [dict(r) for r in con.execute(sql, params).fetchall()]


def read_events(con: sqlite3.Connection, limit: int | None = 50, kind: str | list[str] | None = None,
                source: str | list[str] | None = None, since_id: int = 0,
                oldest: bool = False) -> list[dict[str, Any]]:
    """Store.events on any connection (lathectl reads a stopped daemon's database read-only).
    ``oldest``: the first ``limit`` after ``since_id`` (to page through), not the newest;
    ``limit`` None: all of them."""
    where, params = ["id > ?"], [since_id]
    for col, want in (("kind", kind), ("source", source)):
        names = [want] if isinstance(want, str) else list(want or [])
        if names:
            where.append(f"{col} IN ({','.join('?' * len(names))})")
            params.extend(names)
    rows = [dict(r) for r in con.execute(f"SELECT id, t, source, kind, payload FROM events "
                                         f"WHERE {' AND '.join(where)} ORDER BY id {'ASC' if oldest else 'DESC'} "
                                         "LIMIT ?", (*params, -1 if limit is None else limit)).fetchall()]
    for r in rows:
        r["payload"] = json.loads(r["payload"])
    return rows if oldest else rows[::-1]


class StoreError(Exception):
    """The store could not take a record; the message says why."""


class StoreClock:
    """The time retention ages records by: the wall clock where it behaves, lathed's own
    running time where it jumps.  While lathed runs it advances with the monotonic clock,
    so a wall clock set ahead (every record would look old at once) or back (an RTC reset
    at boot, records stamped years ago) moves nothing.  Across a stop it resumes where it
    was plus the wall time the stop took, counted from 0 to ``MAX_STOPPED_S``: a clock
    found behind counts none (records kept longer), one found ahead ages them by at most
    a week.  A store upgraded to it resumes from its newest record's time.  Persisted by
    the writer in every transaction."""

    def __init__(self, saved: tuple[float, float] | None, newest: float | None,
                 wall=time.time, monotonic=time.monotonic) -> None:
        self._monotonic = monotonic
        now = wall()
        self.stopped_s: float | None = None      # the wall time the stop took, as found
        if saved is None and newest is not None:
            # upgraded to the clock: the wall clock now may be the jumped one it is for
            saved = (newest, newest)
        if saved is None:
            base = now
        else:
            self.stopped_s = now - saved[1]
            base = saved[0] + min(max(self.stopped_s, 0.0), MAX_STOPPED_S)
            if not 0.0 <= self.stopped_s <= MAX_STOPPED_S:
                log.warning("store_clock_gap", stopped_s=round(self.stopped_s, 1),
                            counted_s=round(base - saved[0], 1),
                            why="the wall clock moved back, or further ahead than a stop of "
                                f"{MAX_STOPPED_S / 86400:g} days, while lathed was stopped: retention "
                                "counts the stop as this much")
            if newest is not None:       # never behind a row it stamped (saved with them, but be sure)
                base = max(base, newest)
        self._base, self._t0 = base, monotonic()

    def now(self) -> float:
        return self._base + (self._monotonic() - self._t0)


class Store:
    def __init__(self, path: str | Path, machine_id: str = "lathed", wall=time.time, monotonic=time.monotonic):
        self.path = Path(path)
        self.machine_id = machine_id
        self.path.parent.mkdir(parents=True, exist_ok=True, mode=0o750)
        self._wcon = connect(self.path)
        _private(self.path)
        self.schema_version = migrate(self._wcon)
        saved = self._wcon.execute("SELECT store_t, wall_t FROM store_clock").fetchone()
        # the clock stamps in id order: its newest row is the last; rows migrated to it, any
        newest = self._wcon.execute("SELECT max(age_t) FROM outbox" if saved is None else
                                    "SELECT age_t FROM outbox ORDER BY id DESC LIMIT 1").fetchone()
        self.clock = StoreClock(None if saved is None else (saved[0], saved[1]),
                                None if newest is None else newest[0], wall, monotonic)
        self._wall = wall
        self._save_clock()
        self.declared_kinds: set[str] = set()    # the loaded plugins' own kinds of event (the daemon sets them)
        self._rcon = connect(self.path)
        self._rlock = threading.Lock()
        self._q: queue.Queue = queue.Queue()
        self._closed = False
        self._orphans: list = []     # the batch in hand when the writer thread died
        self.written = 0
        self.failed = 0
        self.events_stored = 0     # events committed: a reader waiting for new ones looks here before it queries
        self.last_error: str | None = None
        self.last_error_t: float | None = None
        # True while the last transaction failed as a whole (disk full, I/O
        # error) or the writer is gone: the store is not taking records.
        self.failing = False
        self.failing_since: float | None = None
        self.recovered_t: float | None = None    # when the last failing spell ended
        self.writer_error: str | None = None   # why the writer thread stopped, if it did
        self._thread = threading.Thread(target=self._writer, name="lathed-store", daemon=True)
        self._thread.start()

    # -- writing --------------------------------------------------------
    def submit(self, sql: str | list[tuple[str, tuple]], params: tuple) -> Future:
        """Queue one write; the future resolves to lastrowid after commit. A
        list of (sql, params) is executed together, all or none, and resolves
        to the first statement's row id; a params that is callable is called
        with that id (a later row naming the first: a part's id in its event)."""
        fut: Future = Future()
        self._put((sql, params, fut))
        return fut

    def _put(self, item: tuple) -> None:
        if self._closed:
            raise StoreError(f"store {self.path} is closed: record not taken")
        self._q.put(item)

    @property
    def writer_alive(self) -> bool:
        return self._thread.is_alive()

    def _writer(self) -> None:
        batch: list = []
        try:
            while True:
                batch = []
                item = self._q.get()
                if item is None:
                    return
                batch = [item]
                while len(batch) < 5000:
                    try:
                        nxt = self._q.get_nowait()
                    except queue.Empty:
                        break
                    if nxt is None:
                        self._q.put(None)   # finish this batch, then stop
                        break
                    batch.append(nxt)
                try:
                    self._commit(batch)
                except Exception as e:   # a fault of the writer itself: this batch fails, the next is served
                    self._writer_fault(batch, e)
        except BaseException as e:       # the thread ends: say so; close() commits what it held and what is queued
            try:
                if self._wcon.in_transaction:
                    self._wcon.execute("ROLLBACK")
            except BaseException:
                pass
            self._orphans = [item for item in batch if not item[2].done()]
            self.writer_error = _one_line(e)
            self._set_failing(True)
            self._note_error(f"store writer stopped: {self.writer_error}")
            log.critical("store_writer_died", error=self.writer_error, queued=self._q.qsize() + len(self._orphans))

    def _writer_fault(self, batch: list, e: Exception) -> None:
        err = StoreError(f"store writer fault, batch of {len(batch)} not committed: {_one_line(e)}")
        log.error("store_writer_fault", error=str(err))
        try:
            if self._wcon.in_transaction:
                self._wcon.execute("ROLLBACK")
        except Exception as e2:
            log.error("store_rollback_failed", error=_one_line(e2))
        unsettled = [(fut, None, err) for _, _, fut in batch if not fut.done()]
        self.failed += sum(sql is not BARRIER for sql, _, fut in batch if not fut.done())
        self._set_failing(True)
        self._note_error(str(err))
        self._settle_all(unsettled)

    def _set_failing(self, failing: bool) -> None:
        if failing and not self.failing:
            self.failing_since = time.time()
        elif self.failing and not failing:
            self.recovered_t = time.time()
            log.info("store_recovered", failing_s=round(self.recovered_t - (self.failing_since or 0), 3))
        self.failing = failing

    def _note_error(self, text: str) -> None:
        self.last_error, self.last_error_t = text, time.time()

    def _commit(self, batch: list) -> None:
        for _, _, fut in batch:
            # taken: a waiter's late cancel() now fails instead of leaving a committed record
            # with a future nobody may settle; one cancelled before is written all the same
            if isinstance(fut, Future) and not fut.done() and not fut.running():
                fut.set_running_or_notify_cancel()
        results = []
        storage = False    # a record failed for the storage itself (full, I/O), not for its content
        try:
            self._wcon.execute("BEGIN")
            self._save_clock()        # the rows of this transaction are aged from this reading
            for sql, params, fut in batch:
                if sql is BARRIER:
                    results.append((fut, None, None))
                    continue
                try:
                    if isinstance(sql, list):     # statements that stand or fall together
                        self._wcon.execute("SAVEPOINT item")
                        first = None
                        try:
                            for s, p in sql:
                                rowid = self._wcon.execute(s, p(first) if callable(p) else p).lastrowid
                                first = rowid if first is None else first
                        except Exception:
                            self._wcon.execute("ROLLBACK TO item")
                            raise
                        finally:
                            self._wcon.execute("RELEASE item")
                        results.append((fut, first, None))
                    else:
                        results.append((fut, self._wcon.execute(sql, params).lastrowid, None))
                except Exception as e:   # one bad record must not sink the batch...
                    if not self._wcon.in_transaction:
                        raise            # ...unless SQLite rolled the transaction back (disk full)
                    if isinstance(e, sqlite3.Error):
                        storage = storage or getattr(e, "sqlite_errorcode", 0) & 0xFF in STORAGE_ERRORS
                        results.append((fut, None, e))
                    else:                # e.g. OverflowError: an int SQLite cannot bind
                        results.append((fut, None, StoreError(f"record not stored: {_one_line(e)}")))
            self._wcon.execute("COMMIT")
        except sqlite3.Error as e:
            try:
                self._wcon.execute("ROLLBACK")
            except sqlite3.Error:
                pass
            self.failed += sum(sql is not BARRIER for sql, _, _ in batch)
            self._set_failing(True)
            self._note_error(f"commit failed, {len(batch)} records not stored: {_one_line(e)}")
            log.error("store_commit_failed", error=self.last_error)
            results = [(fut, None, e) for _, _, fut in batch]
        else:
            self._set_failing(storage)
            for (sql, _, _), (_, _, err) in zip(batch, results):
                if sql is BARRIER:
                    continue
                if err is None:
                    self.written += 1
                    self.events_stored += sum(s is EVENT_SQL for s, _ in sql) if isinstance(sql, list) \
                        else sql is EVENT_SQL
                else:
                    self.failed += 1
                    self._note_error(_one_line(err))
        self._settle_all(results)

    def _save_clock(self) -> None:
        self._wcon.execute("INSERT INTO store_clock(id, store_t, wall_t) VALUES (1, ?, ?) ON CONFLICT(id) DO "
                           "UPDATE SET store_t = excluded.store_t, wall_t = excluded.wall_t",
                           (self.clock.now(), self._wall()))

    @staticmethod
    def _settle_all(results: list) -> None:
        # Event-loop futures are settled with one wake-up of their loop per
        # batch, not one per record: at thousands of records a second the
        # per-record wake-ups are what would delay the loop.
        by_loop: dict[asyncio.AbstractEventLoop, list] = {}
        for fut, rowid, err in results:
            if isinstance(fut, asyncio.Future):
                by_loop.setdefault(fut.get_loop(), []).append((fut, rowid, err))
            elif fut.done():    # cancelled before the writer took it; the record is committed all the same
                continue
            elif err is None:
                fut.set_result(rowid)
            else:
                fut.set_exception(err)
        for loop, items in by_loop.items():
            try:
                loop.call_soon_threadsafe(_settle, items)
            except RuntimeError:   # that loop has closed: nobody is waiting any more
                pass

    def _submit_async(self, sql: str, params: tuple) -> asyncio.Future:
        fut = asyncio.get_running_loop().create_future()
        self._put((sql, params, fut))
        return fut

    async def record(self, kind: str, source: str, payload: dict[str, Any] | None = None,
                     t: float | None = None) -> int:
        """Record an event; returns its id once durably committed."""
        return await self._submit_async(*self.event_statement(kind, source, payload, t))

    def record_future(self, kind: str, source: str, payload: dict[str, Any] | None = None,
                      t: float | None = None) -> Future:
        return self.submit(*self.event_statement(kind, source, payload, t))

    async def settled(self, timeout: float = 1.0) -> None:
        """Return once every record submitted before the call is committed (or failed), or
        after ``timeout``: a reader after a command sees the events that command recorded
        (the command replies before the writer commits them)."""
        try:
            async with asyncio.timeout(timeout):
                await self._submit_async(BARRIER, ())
        except Exception:       # a failing or closed store: the read goes on with what is there
            pass

    def event_statement(self, kind: str, source: str, payload: dict[str, Any] | None = None,
                        t: float | None = None) -> tuple[str, tuple]:
        """(sql, params) of an event, to submit() in a list with others."""
        body = dumps(payload or {})
        return (EVENT_SQL, (str(uuidlib.uuid4()), self.machine_id, time.time() if t is None else t, source, kind, body))

    def insert(self, table: str, row: dict[str, Any]) -> Future:
        """Insert a record row; uuid and machine_id are filled in unless given,
        JSON columns are serialised. The future resolves to the row id."""
        return self.submit(*self.row_statement(table, row))

    def row_statement(self, table: str, row: dict[str, Any]) -> tuple[str, tuple]:
        """(sql, params) of insert(), to submit() in a list with others."""
        if table not in FORWARDED:
            raise ValueError(f"{table!r} is not a record table; record tables: {', '.join(FORWARDED)}")
        row = {"uuid": str(uuidlib.uuid4()), "machine_id": self.machine_id, **row}
        for k in JSON_COLUMNS & row.keys():
            row[k] = dumps(row[k])
        return f"INSERT INTO {table}({', '.join(row)}) VALUES ({', '.join('?' * len(row))})", tuple(row.values())

    async def add(self, table: str, row: dict[str, Any]) -> int:
        """Insert a record row; returns its id once durably committed."""
        return await self._submit_async(*self.row_statement(table, row))

    # -- forwarding -----------------------------------------------------
    def columns(self, table: str) -> list[tuple[str, str]]:
        """(name, declared type) of a record table, for a sink to mirror it."""
        return [(r["name"], r["type"]) for r in self.query(f"PRAGMA table_info({table})")]

    def progress(self, sink: str) -> int:
        rows = self.query("SELECT outbox_id FROM forward_progress WHERE sink = ?", (sink,))
        return rows[0]["outbox_id"] if rows else 0

    def backlog(self, sink: str) -> int:
        last = self.query("SELECT max(id) AS m FROM outbox")[0]["m"] or 0
        return last - self.progress(sink)

    def pending(self, sink: str, limit: int, after: int | None = None) -> list[tuple[int, str, dict[str, Any]]]:
        """The next records a sink has not forwarded: (outbox id, table, row), in order;
        ``after`` an outbox id instead of the sink's saved progress (a sink reading ahead)."""
        after = self.progress(sink) if after is None else after
        entries = self.query("SELECT id, tbl, row_id FROM outbox WHERE id > ? ORDER BY id LIMIT ?",
                             (after, limit))
        by_table: dict[str, list[int]] = {}
        for e in entries:
            by_table.setdefault(e["tbl"], []).append(e["row_id"])
        rows: dict[tuple[str, int], dict] = {}
        for tbl, ids in by_table.items():
            for r in self.query(f"SELECT * FROM {tbl} WHERE id IN ({','.join('?' * len(ids))})", tuple(ids)):
                rows[(tbl, r["id"])] = r
        out = []
        for e in entries:
            r = rows.get((e["tbl"], e["row_id"]))
            if r is None:   # cannot happen while record rows are never deleted; say so if it does
                raise RuntimeError(f"outbox entry {e['id']} points at missing {e['tbl']} row {e['row_id']}")
            if r.get("machine_id") is None:   # events written before schema 2
                r["machine_id"] = self.machine_id
            out.append((e["id"], e["tbl"], r))
        return out

    def refuse(self, sink: str, outbox_id: int, tbl: str, row_id: int, error: str) -> Future:
        """Set a row aside for ``sink``: its server refused the row itself."""
        return self.submit("INSERT INTO forward_refused(sink, outbox_id, tbl, row_id, error, t) "
                           "VALUES (?,?,?,?,?,?) ON CONFLICT DO NOTHING",
                           (sink, outbox_id, tbl, row_id, error, time.time()))

    def refused(self, sink: str) -> int:
        return self.query("SELECT count(*) AS n FROM forward_refused WHERE sink = ?", (sink,))[0]["n"]

    def prune(self, before_t: float, sinks: list[str]) -> dict[str, int]:
        """Delete record rows aged (``age_t``, the store clock's reading when they were
        written) before ``before_t`` that every sink in ``sinks`` has forwarded (all of
        them when there is no sink), with their outbox entries, in one transaction per
        chunk. Candidates are found on the read connection, walking the outbox in id
        (insertion) order and stopping at the first chunk with nothing old enough, so
        the writer only ever runs deletes by primary key; after each chunk it waits as
        long as the chunk took. Returns rows removed per table."""
        safe = min((self.progress(s) for s in sinks), default=None)
        if safe is None:
            safe = self.query("SELECT max(id) AS m FROM outbox")[0]["m"] or 0
        removed = {t: 0 for t in FORWARDED}
        after = 0
        while True:
            started = time.monotonic()
            entries = self.query("SELECT id, tbl, row_id, age_t FROM outbox WHERE id > ? AND id <= ? "
                                 "ORDER BY id LIMIT ?", (after, safe, PRUNE_CHUNK))
            if not entries:
                break
            after = entries[-1]["id"]
            old: dict[str, list[tuple[int, int]]] = {}
            for e in entries:
                if e["age_t"] is not None and e["age_t"] < before_t:
                    old.setdefault(e["tbl"], []).append((e["id"], e["row_id"]))
            if not old:
                break       # the store clock never runs back: nothing older further on
            stmts = []
            for tbl, pairs in old.items():
                marks = ",".join("?" * len(pairs))
                stmts.append((f"DELETE FROM outbox WHERE id IN ({marks})", tuple(o for o, _ in pairs)))
                stmts.append((f"DELETE FROM {tbl} WHERE id IN ({marks})", tuple(r for _, r in pairs)))
                removed[tbl] += len(pairs)
            self.submit(stmts, ()).result()
            # as long again idle: live records are committed between chunks, not behind them
            time.sleep(min(time.monotonic() - started, 0.25))
        return removed

    def begin_progress(self, sink: str, at_end: bool) -> Future:
        """A sink's first progress, where it has none: after every record stored so far
        (``at_end``, read in the writer, so no record lands between) or before the first.
        A sink with progress keeps it."""
        return self.submit("INSERT OR IGNORE INTO forward_progress(sink, outbox_id, t) "
                           "SELECT ?, CASE WHEN ? THEN coalesce(max(id), 0) ELSE 0 END, ? FROM outbox",
                           (sink, at_end, time.time()))

    def set_progress(self, sink: str, outbox_id: int) -> Future:
        return self.submit("INSERT INTO forward_progress(sink, outbox_id, t) VALUES (?,?,?) "
                           "ON CONFLICT(sink) DO UPDATE SET outbox_id = excluded.outbox_id, t = excluded.t",
                           (sink, outbox_id, time.time()))

    def close(self) -> None:
        """Commit everything queued, then close. Records taken before close are
        committed even when the writer thread is gone (it is done here)."""
        if self._closed:
            return
        self._closed = True
        self._q.put(None)
        self._thread.join()
        rest, self._orphans = self._orphans, []
        while True:
            try:
                item = self._q.get_nowait()
            except queue.Empty:
                break
            if item is not None:
                rest.append(item)
        if rest:
            log.warning("store_draining_without_writer", records=len(rest))
            try:
                self._commit(rest)
            except Exception as e:
                self._writer_fault(rest, e)
        self._wcon.close()
        self._rcon.close()

    # -- reading --------------------------------------------------------
    def query(self, sql: str, params: tuple = ()) -> list[dict[str, Any]]:
        with self._rlock:
            return read_rows(self._rcon, sql, params)

    def events(self, limit: int | None = 50, kind: str | list[str] | None = None,
               source: str | list[str] | None = None, since_id: int = 0,
               oldest: bool = False) -> list[dict[str, Any]]:
        """The newest ``limit`` events after ``since_id`` (``oldest``: the first ``limit``),
        oldest first; kind and source are one name or a list of names (any of them)."""
        with self._rlock:
            return read_events(self._rcon, limit, kind, source, since_id, oldest)

    def unknown_kind(self, kinds: list[str]) -> str | None:
        with self._rlock:
            return unknown_kind(self._rcon, kinds, self.declared_kinds)

    def last_event_id(self) -> int:
        return self.query("SELECT coalesce(max(id), 0) AS id FROM events")[0]["id"]

    def stats(self) -> dict[str, Any]:
        return {"path": str(self.path), "schema_version": self.schema_version, "written": self.written,
                "failed": self.failed, "queued": self._q.qsize(), "last_error": self.last_error,
                "last_error_t": self.last_error_t, "failing": self.failing or not self.writer_alive,
                "failing_since": self.failing_since if self.failing else None, "recovered_t": self.recovered_t,
                "writer_alive": self.writer_alive, "writer_error": self.writer_error,
                # retention's clock against the wall clock: not 0 once the wall clock has jumped
                "clock_minus_wall_s": round(self.clock.now() - self._wall(), 1)}


def _private(db: Path) -> None:
    """Record files readable by the owner's group only (0640), also when an
    older daemon left them 0644; SQLite gives the -wal/-shm files the mode
    of the database file."""
    for p in (db, db.with_name(db.name + "-wal"), db.with_name(db.name + "-shm")):
        try:
            st = p.stat()
            mode = stat.S_IMODE(st.st_mode)
            if st.st_uid == os.geteuid() and mode & 0o137:
                p.chmod(mode & 0o640)
        except FileNotFoundError:
            pass


def _one_line(exc: BaseException) -> str:
    text = str(exc).splitlines()[0] if str(exc) else ""
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _settle(items: list) -> None:
    for fut, rowid, err in items:
        if fut.done():          # the waiter was cancelled; the record is committed all the same
            continue
        if err is None:
            fut.set_result(rowid)
        else:
            fut.set_exception(err)


def dumps(obj: Any) -> str:
    """JSON for a record. NaN and infinities become null: they are not JSON,
    and SQLite's json_extract and PostgreSQL's jsonb both refuse them."""
    try:
        return json.dumps(obj, default=_json_default, allow_nan=False)
    except ValueError:
        return json.dumps(_finite(json.loads(json.dumps(obj, default=_json_default))), allow_nan=False)


def _finite(o: Any) -> Any:
    if isinstance(o, float):
        return o if math.isfinite(o) else None
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, list):
        return [_finite(v) for v in o]
    return o


def _json_default(o: Any) -> Any:
    # numpy scalars and arrays reach records from the numeric cores.
    if hasattr(o, "tolist"):
        return o.tolist()
    raise TypeError(f"cannot record {type(o).__name__}")
