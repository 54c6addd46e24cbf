"""``lathectl plant``: every cell's machines and alarms, from the central
PostgreSQL that the cells' postgres_sink instances fill.

A cell is one lathed daemon (its ``[daemon] name``, the records' machine_id).
Its machines are those its last ``daemon_started`` record names, and any
that recorded machine events; an alarm is open when its last record is
``alarm_raised``. Read-only; it needs no daemon, only the database.
"""
from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import time
from typing import Any

from lathed.cli import EX_NOINPUT, EX_UNAVAILABLE, fail, positive

MACHINE_EVENTS = ("alarm_raised", "alarm_cleared", "part_completed", "part_counter_reset")


def register(sub) -> None:
    p = sub.add_parser("plant", help="every cell's machines and alarms, from the central PostgreSQL",
                       description="Lists each cell (lathed daemon) that forwards to the central PostgreSQL "
                                   "(postgres_sink): when it last started and last recorded, its machines "
                                   "with their part counts, open controller alarms, and chatter alarms of "
                                   "the last hours.")
    p.add_argument("--dsn", default=os.environ.get("LATHED_PLANT_DSN"),
                   help="the central database, as postgres_sink's dsn (default: $LATHED_PLANT_DSN)")
    p.add_argument("--hours", type=positive, default=24.0, help="how far back recent alarms go (default 24)")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if not args.dsn:
        return fail("plant: no database: give --dsn or set LATHED_PLANT_DSN (postgres_sink's dsn)", EX_UNAVAILABLE)
    import psycopg   # only this command needs it
    try:
        with psycopg.connect(args.dsn, connect_timeout=10) as con:
            cells = read(con, time.time() - args.hours * 3600)
    except psycopg.errors.UndefinedTable:
        return fail(f"plant: {_where(args.dsn)} holds no lathed records: no postgres_sink has written there yet",
                    EX_NOINPUT)
    except (psycopg.Error, OSError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        return fail(f"plant: PostgreSQL at {_where(args.dsn)} unreachable: {first}", EX_UNAVAILABLE)
    if args.json:
        print(json.dumps(cells, indent=2, default=str))
    else:
        print_cells(cells, args.hours)
    return 0


def read(con, since_t: float) -> list[dict[str, Any]]:
    cells: dict[str, dict[str, Any]] = {}
    for cid, last_t, n in con.execute("SELECT machine_id, max(t), count(*) FROM events GROUP BY machine_id "
                                      "ORDER BY machine_id"):
        cells[cid] = {"cell": cid, "last_record_t": last_t, "events": n, "started_t": None, "version": None,
                      "stopped": False, "machines": {}}

    def machine(cid: str, name: str) -> dict[str, Any]:
        return cells[cid]["machines"].setdefault(name, {"name": name, "kind": None, "parts": None,
                                                        "last_event_t": None, "open_alarms": [],
                                                        "chatter_alarms": 0, "last_chatter": None})

    for cid, kind in con.execute(
            "SELECT DISTINCT ON (machine_id) machine_id, kind FROM events "
            "WHERE kind IN ('daemon_started', 'daemon_stopped') ORDER BY machine_id, t DESC, local_id DESC"):
        cells[cid]["stopped"] = kind == "daemon_stopped"
    for cid, t, payload in con.execute(
            "SELECT DISTINCT ON (machine_id) machine_id, t, payload FROM events "
            "WHERE kind = 'daemon_started' ORDER BY machine_id, t DESC, local_id DESC"):
        cells[cid].update(started_t=t, version=payload.get("version"))
        for name, kind in (payload.get("machines") or {}).items():
            machine(cid, name)["kind"] = kind
    for cid, name, kind, last_t, parts in con.execute(
            "SELECT machine_id, source, max(payload->>'kind'), max(t), "
            "max((payload->>'part_count')::bigint) FILTER (WHERE kind = 'part_completed') "
            "FROM events WHERE kind = ANY(%s) GROUP BY machine_id, source", (list(MACHINE_EVENTS),)):
        m = machine(cid, name)
        m.update(kind=m["kind"] or kind, last_event_t=last_t, parts=parts)
    for cid, name, alarm, kind, t in con.execute(
            "SELECT DISTINCT ON (machine_id, source, payload->>'alarm') machine_id, source, payload->>'alarm', "
            "kind, t FROM events WHERE kind IN ('alarm_raised', 'alarm_cleared') "
            "ORDER BY machine_id, source, payload->>'alarm', t DESC, local_id DESC"):
        if kind == "alarm_raised":
            machine(cid, name)["open_alarms"].append({"alarm": alarm, "since_t": t})
    for cid, name, n, last_t, index in con.execute(
            "SELECT machine_id, machine, count(*), max(t), (array_agg(chatter_index ORDER BY t DESC))[1] "
            "FROM chatter_events WHERE kind = 'chatter_alarm' AND t >= %s GROUP BY machine_id, machine",
            (since_t,)):
        machine(cid, name or "?").update(chatter_alarms=n, last_chatter={"t": last_t, "index": index})
    for c in cells.values():
        c["machines"] = sorted(c["machines"].values(), key=lambda m: m["name"])
    return list(cells.values())


def print_cells(cells: list[dict[str, Any]], hours: float) -> None:
    if not cells:
        print("no cell has forwarded records yet")
        return
    now = time.time()
    for c in cells:
        state = "stopped" if c["stopped"] else "running"
        print(f"cell {c['cell']}: {state}, started {_t(c['started_t'])} (lathed {c['version'] or '?'}), "
              f"last record {_ago(now - c['last_record_t'])} ago, {c['events']} events")
        if not c["machines"]:
            print("  no machines")
            continue
        rows = [["MACHINE", "KIND", "PARTS", "LAST EVENT", "OPEN ALARMS", f"CHATTER ALARMS {hours:g} h"]]
        for m in c["machines"]:
            alarms = ", ".join(f"{a['alarm']} since {_t(a['since_t'])}" for a in m["open_alarms"]) or "-"
            chatter = (f"{m['chatter_alarms']}, last {_t(m['last_chatter']['t'])} index {m['last_chatter']['index']:.3g}"
                       if m["chatter_alarms"] else "-")
            rows.append([m["name"], m["kind"] or "-", "-" if m["parts"] is None else str(m["parts"]),
                         _t(m["last_event_t"]), alarms, chatter])
        widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
        for r in rows:
            print("  " + "  ".join(v.ljust(w) for v, w in zip(r, widths)).rstrip())


def _t(t: float | None) -> str:
    return "-" if t is None else dt.datetime.fromtimestamp(t).strftime("%m-%d %H:%M:%S")


def _ago(s: float) -> str:
    return f"{max(s, 0):.0f} s" if s < 120 else (f"{s / 60:.0f} min" if s < 7200 else f"{s / 3600:.1f} h")


def _where(dsn: str) -> str:
    import psycopg
    from psycopg.conninfo import conninfo_to_dict
    try:
        info = conninfo_to_dict(dsn)
    except psycopg.ProgrammingError:   # a malformed dsn: name it as given
        return repr(dsn)
    return f"{info.get('host', 'localhost')}:{info.get('port', 5432)}/{info.get('dbname', '')}"
