"""Store-and-forward of every record to one central PostgreSQL database.

Records are committed locally first and forwarded in outbox order with ON CONFLICT DO
NOTHING on (daemon identity, uuid), so a batch resent after a crash is not duplicated; the
progress lives in SQLite. A batch the server refuses for its content is sent again row by
row, each in a savepoint: refused rows are set aside in ``forward_refused`` and recorded,
the rest goes on. Keys: docs/configuration.md; behaviour: docs/records.md.
"""
from __future__ import annotations

import asyncio
import itertools
import time
from typing import TYPE_CHECKING, Any

from lathed import hookimpl
from lathed.analyzer import Analyzer
from lathed.config import Section
from lathed.extras import MissingExtra, need
from lathed.store import FORWARDED, JSON_COLUMNS

if TYPE_CHECKING:
    import psycopg
    from psycopg import sql

_PG_TYPES = {"INTEGER": "bigint", "REAL": "double precision", "TEXT": "text"}
_DDL_LOCK = 0x6C617468   # advisory lock: daemons starting together create the tables once

# The central counterparts of the local views over the analyzers' events.
_VIEWS = {
    "chatter_events": ("kind IN ('chatter_alarm', 'chatter_cleared')", [
        ("machine", "text"), ("index", "double precision"), ("threshold", "double precision"),
        ("chatter_frequency_hz", "double precision"), ("rpm", "double precision"),
        ("depth_mm", "double precision"), ("tool", "text"), ("material", "text"), ("tool_number", "integer")]),
    "suppression_actions": ("kind = 'suppression_action'", [
        ("strategy", "text"), ("rpm_before", "double precision"), ("rpm_after", "double precision"),
        ("index", "double precision"), ("threshold", "double precision"),
        ("chatter_frequency_hz", "double precision"), ("sent", "boolean"), ("reason", "text")]),
    "cuts": ("kind = 'cut'", [
        ("machine", "text"), ("tool", "text"), ("material", "text"), ("start_t", "double precision"),
        ("end_t", "double precision"), ("rpm_start", "double precision"), ("rpm_end", "double precision"),
        ("depth_mm", "double precision"), ("feed_mm_rev", "double precision"), ("outcome", "text"),
        ("first_alarm_s", "double precision"), ("chatter_frequency_hz", "double precision"),
        ("cured", "boolean"), ("model", "text"), ("tool_number", "integer")]),
    "compensations": ("kind = 'compensation'", [
        ("predicted_um", "double precision"), ("offset_um", "double precision"), ("model", "text")]),
}


class PostgresSink(Analyzer):
    forwards_records = True     # retention (keep_days) waits for this sink's progress

    def __init__(self, name: str, section: Section):
        super().__init__(name, section)
        # imported here, by a configured sink only: psycopg takes 0.2 s to import and is an extra
        try:
            self.pg = pg = need("psycopg", "the postgres_sink plugin")
        except MissingExtra as e:
            raise section.error("plugin", str(e)) from None
        # what the server raises for a row's content, as opposed to an outage or a schema fault
        self.row_refused = (pg.DataError, pg.IntegrityError)
        self.dsn = section.getstr("dsn")
        try:
            info = pg.conninfo.conninfo_to_dict(self.dsn)
        except pg.ProgrammingError as e:
            raise section.error("dsn", f"not a PostgreSQL connection string: {e}") from None
        self.where = f"{info.get('host', 'localhost')}:{info.get('port', 5432)}/{info.get('dbname', '')}"
        self.batch = section.getint("batch", 500, minval=1, maxval=10_000)
        self.interval = section.getduration("interval", 1.0, minval=0.01, maxval=3600)
        self.timeout = section.getduration("timeout", 30.0, minval=1, maxval=3600)
        self.forwarded = 0
        self.connected = False
        self.last_error: str | None = None
        self.last_forward_t: float | None = None

    async def run(self) -> None:
        try:
            await self._forward()
        except (self.pg.Error, OSError, asyncio.TimeoutError) as e:
            self.last_error = self._cause(e)
            raise ConnectionError(self.last_error) from None
        finally:
            self.connected = False

    async def _forward(self) -> None:
        store = self.ctx.store
        con = await asyncio.wait_for(self.pg.AsyncConnection.connect(
            self.dsn, connect_timeout=max(1, int(self.timeout))), self.timeout)
        async with con:
            inserts = await asyncio.wait_for(self._schema(con), self.timeout)
            self.connected, self.last_error = True, None
            self.ctx.log.info("postgres_connected", server=self.where, backlog=store.backlog(self.name))
            while True:
                batch = await asyncio.to_thread(store.pending, self.name, self.batch)
                if not batch:
                    await asyncio.sleep(self.interval)
                    continue
                try:
                    await asyncio.wait_for(self._send(con, inserts, batch), self.timeout)
                except self.row_refused:
                    await asyncio.wait_for(self._send_each(con, inserts, batch), self.timeout)
                # Counted at the central commit, so a reader who sees the progress saved sees the
                # count; uncounted if the progress is not saved, as the batch goes again.
                self.forwarded += len(batch)
                self.last_forward_t = time.time()
                try:
                    # After the central commit: a crash here only causes a resend, which the keys absorb.
                    await asyncio.wrap_future(store.set_progress(self.name, batch[-1][0]))
                except BaseException:
                    self.forwarded -= len(batch)
                    raise

    async def _schema(self, con: psycopg.AsyncConnection) -> dict[str, tuple[sql.Composed, list[str]]]:
        """Create or extend the central tables from the local schema; returns the inserts."""
        sql = self.pg.sql
        inserts = {}
        async with con.transaction():
            await con.execute("SELECT pg_advisory_xact_lock(%s)", (_DDL_LOCK,))
            for table in FORWARDED:
                cols = [(n, t) for n, t in await asyncio.to_thread(self.ctx.store.columns, table)
                        if n not in ("id", "uuid", "machine_id")]
                await con.execute(sql.SQL(
                    "CREATE TABLE IF NOT EXISTS {} (machine_id text NOT NULL, uuid text NOT NULL, "
                    "local_id bigint NOT NULL, received_at timestamptz NOT NULL DEFAULT now(), "
                    "PRIMARY KEY (machine_id, uuid))").format(sql.Identifier(table)))
                for n, t in cols:   # columns added by later local migrations appear centrally too
                    pgtype = "jsonb" if n in JSON_COLUMNS else _PG_TYPES.get(t.upper(), "text")
                    await con.execute(sql.SQL("ALTER TABLE {} ADD COLUMN IF NOT EXISTS {} {}").format(
                        sql.Identifier(table), sql.Identifier(n), sql.SQL(pgtype)))
                names = ["machine_id", "uuid", "local_id"] + [n for n, _ in cols]
                values = [sql.SQL("%s::jsonb" if n in JSON_COLUMNS else "%s") for n in names]
                inserts[table] = (sql.SQL("INSERT INTO {} ({}) VALUES ({}) ON CONFLICT (machine_id, uuid) "
                                          "DO NOTHING").format(sql.Identifier(table),
                                                               sql.SQL(", ").join(map(sql.Identifier, names)),
                                                               sql.SQL(", ").join(values)),
                                  [n for n, _ in cols])
            for view, (where, fields) in _VIEWS.items():
                cols_sql = sql.SQL(", ").join(
                    sql.SQL("(payload->>{})::{} AS {}").format(
                        sql.Literal(f), sql.SQL(t), sql.Identifier("chatter_index" if f == "index" else f))
                    for f, t in fields)
                await con.execute(sql.SQL("CREATE OR REPLACE VIEW {} AS SELECT machine_id, uuid, local_id, t, "
                                          "source, kind, {} FROM events WHERE {}").format(
                    sql.Identifier(view), cols_sql, sql.SQL(where)))
        return inserts

    async def _send(self, con, inserts, batch: list[tuple[int, str, dict]]) -> None:
        async with con.transaction():
            async with con.cursor() as cur:
                # consecutive rows of one table go as one pipelined executemany; order is kept
                for table, group in itertools.groupby(batch, key=lambda e: e[1]):
                    stmt, cols = inserts[table]
                    await cur.executemany(stmt, [_params(r, cols) for _, _, r in group])

    async def _send_each(self, con, inserts, batch: list[tuple[int, str, dict]]) -> None:
        """The batch again, one savepoint per row: the rows the server refuses
        are set aside and reported; the others are committed."""
        async with con.transaction():
            async with con.cursor() as cur:
                for oid, table, r in batch:
                    stmt, cols = inserts[table]
                    try:
                        async with con.transaction():
                            await cur.execute(stmt, _params(r, cols))
                    except self.row_refused as e:
                        why = self._cause(e)
                        await asyncio.wrap_future(self.ctx.store.refuse(self.name, oid, table, r["id"], why))
                        self.ctx.log.error("forward_refused", table=table, row_id=r["id"], error=why)
                        self.ctx.record("forward_refused", {"sink": self.name, "table": table, "row_id": r["id"],
                                                            "uuid": r["uuid"], "error": why})

    def status(self) -> dict[str, Any]:
        backlog = self.ctx.store.backlog(self.name) if self.ctx else None
        refused = self.ctx.store.refused(self.name) if self.ctx else None
        state = "forwarding" if self.connected else "waiting for PostgreSQL"
        return {"server": self.where, "connected": self.connected, "backlog": backlog,
                "forwarded": self.forwarded, "refused": refused, "last_error": self.last_error,
                "last_forward_t": self.last_forward_t,
                "summary": f"{state} ({self.where}), backlog {backlog}"
                           + (f", {refused} row(s) refused by the server (lathectl events --kind forward_refused)"
                              if refused else "")
                           + (f", last error: {self.last_error}" if self.last_error else "")}

    def _cause(self, e: BaseException) -> str:
        where = self.where
        if isinstance(e, asyncio.TimeoutError):
            return f"PostgreSQL at {where} did not answer in time (server overloaded or network down)"
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        if isinstance(e, (self.pg.OperationalError, OSError)):
            return f"PostgreSQL at {where} unreachable (server down, network, or credentials): {msg}"
        return f"PostgreSQL at {where} refused the records: {type(e).__name__}: {msg}"


def _params(r: dict, cols: list[str]) -> tuple:
    return (r["machine_id"], r["uuid"], r["id"], *(r[c] for c in cols))


@hookimpl
def lathed_analyzer_types():
    return {"postgres_sink": PostgresSink}
