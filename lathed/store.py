"""The embedded record store: SQLite in WAL mode, written off the event loop.

One writer thread owns the write connection and commits in groups: whatever
queued while the last commit ran goes in the next transaction. A record is
acknowledged (its future resolves) only after its transaction has committed
with synchronous=FULL, so an acknowledged record survives the daemon being
killed.
"""
from __future__ import annotations

import asyncio
import json
import queue
import sqlite3
import threading
import time
import uuid as uuidlib
from concurrent.futures import Future
from pathlib import Path
from typing import Any

# Versioned schema migrations: (version, SQL). Append, never edit.
MIGRATIONS: list[tuple[int, str]] = [
    (1, """
    CREATE TABLE events (
        id      INTEGER PRIMARY KEY AUTOINCREMENT,
        uuid    TEXT NOT NULL UNIQUE,
        t       REAL NOT NULL,
        source  TEXT NOT NULL,
        kind    TEXT NOT NULL,
        payload TEXT NOT NULL
    );
    CREATE INDEX events_kind ON events(kind, id);
    """),
]


def connect(path: str | Path, readonly: bool = False) -> sqlite3.Connection:
    if readonly:
        con = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=10, check_same_thread=False)
    else:
        con = sqlite3.connect(str(path), timeout=10, isolation_level=None, check_same_thread=False)
        con.execute("PRAGMA journal_mode=WAL")
        con.execute("PRAGMA synchronous=FULL")
    con.row_factory = sqlite3.Row
    return con


def migrate(con: sqlite3.Connection) -> int:
    version = con.execute("PRAGMA user_version").fetchone()[0]
    for v, sql in MIGRATIONS:
        if v > version:
            con.execute("BEGIN IMMEDIATE")
            try:
                for stmt in (s.strip() for s in sql.split(";")):
                    if stmt:
                        con.execute(stmt)
                con.execute(f"PRAGMA user_version={v}")
                con.execute("COMMIT")
            except BaseException:
                con.execute("ROLLBACK")
                raise
            version = v
    return version


class Store:
    def __init__(self, path: str | Path, machine_id: str = "lathed"):
        self.path = Path(path)
        self.machine_id = machine_id
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._wcon = connect(self.path)
        self.schema_version = migrate(self._wcon)
        self._rcon = connect(self.path)
        self._rlock = threading.Lock()
        self._q: queue.Queue = queue.Queue()
        self.written = 0
        self.failed = 0
        self.last_error: str | None = None
        self._thread = threading.Thread(target=self._writer, name="lathed-store", daemon=True)
        self._thread.start()

    # -- writing --------------------------------------------------------
    def submit(self, sql: str, params: tuple) -> Future:
        """Queue one write; the future resolves to lastrowid after commit."""
        fut: Future = Future()
        self._q.put((sql, params, fut))
        return fut

    def _writer(self) -> None:
        while True:
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
            self._commit(batch)

    def _commit(self, batch: list) -> None:
        results = []
        try:
            self._wcon.execute("BEGIN")
            for sql, params, fut in batch:
                try:
                    results.append((fut, self._wcon.execute(sql, params).lastrowid, None))
                except sqlite3.Error as e:   # one bad record must not sink the batch
                    results.append((fut, None, e))
            self._wcon.execute("COMMIT")
        except sqlite3.Error as e:
            try:
                self._wcon.execute("ROLLBACK")
            except sqlite3.Error:
                pass
            self.failed += len(batch)
            self.last_error = str(e)
            for _, _, fut in batch:
                fut.set_exception(e)
            return
        for fut, rowid, err in results:
            if err is None:
                self.written += 1
                fut.set_result(rowid)
            else:
                self.failed += 1
                self.last_error = str(err)
                fut.set_exception(err)

    async def record(self, kind: str, source: str, payload: dict[str, Any] | None = None,
                     t: float | None = None) -> int:
        """Record an event; returns its id once durably committed."""
        return await asyncio.wrap_future(self.record_future(kind, source, payload, t))

    def record_future(self, kind: str, source: str, payload: dict[str, Any] | None = None,
                      t: float | None = None) -> Future:
        body = json.dumps(payload or {}, default=_json_default)
        return self.submit(
            "INSERT INTO events(uuid, t, source, kind, payload) VALUES (?,?,?,?,?)",
            (str(uuidlib.uuid4()), time.time() if t is None else t, source, kind, body))

    def close(self) -> None:
        self._q.put(None)
        self._thread.join()
        self._wcon.close()
        self._rcon.close()

    # -- reading --------------------------------------------------------
    def query(self, sql: str, params: tuple = ()) -> list[dict[str, Any]]:
        with self._rlock:
            return [dict(r) for r in self._rcon.execute(sql, params).fetchall()]

    def events(self, limit: int = 50, kind: str | None = None, source: str | None = None,
               since_id: int = 0) -> list[dict[str, Any]]:
        where, params = ["id > ?"], [since_id]
        if kind:
            where.append("kind = ?")
            params.append(kind)
        if source:
            where.append("source = ?")
            params.append(source)
        rows = self.query(f"SELECT id, t, source, kind, payload FROM events WHERE {' AND '.join(where)} "
                          "ORDER BY id DESC LIMIT ?", (*params, limit))
        for r in rows:
            r["payload"] = json.loads(r["payload"])
        return rows[::-1]

    def stats(self) -> dict[str, Any]:
        return {"path": str(self.path), "schema_version": self.schema_version, "written": self.written,
                "failed": self.failed, "queued": self._q.qsize(), "last_error": self.last_error}


def _json_default(o: Any) -> Any:
    # numpy scalars and arrays reach records from the numeric cores.
    if hasattr(o, "tolist"):
        return o.tolist()
    raise TypeError(f"cannot record {type(o).__name__}")
