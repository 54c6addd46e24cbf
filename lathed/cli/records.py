"""``lathectl parts|inspect|experiment|recommend|export``: production records.

Asks the daemon's records analyzer (``[analyzer.records]``) over the control
socket; ``parts``, ``experiment list``, ``recommend`` and ``export`` read its
database, read-only, when the daemon is down.
"""
from __future__ import annotations

import argparse
import csv
import datetime as dt
import json
import math
import sys

from lathed.cli import EX_CANTCREAT, count, once
from lathed.client import DaemonUnavailable
from lathed.cli import add_db_argument, print_json, read_db, remote, remote_or_db


def _num(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return v


def _pair(text: str) -> tuple[str, float]:
    name, sep, value = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"{text!r}: expected NAME=NUMBER")
    return name, _num(value)


def _setting(text: str) -> tuple[str, float | str]:
    name, sep, value = text.partition("=")
    if not sep or not name or not value:
        raise argparse.ArgumentTypeError(f"{text!r}: expected FACTOR=VALUE")
    try:
        return name, _num(value)
    except argparse.ArgumentTypeError:
        return name, value          # a named level, e.g. a cleaning method or an insert grade


def _levels(text: str) -> dict[str, int]:
    out = {}
    for item in text.split(","):
        name, sep, value = item.partition("=")
        if not sep or not name or not value.isdigit() or int(value) < 1:
            raise argparse.ArgumentTypeError(f"{item!r}: expected FACTOR=LEVEL with LEVEL 1, 2, 3...")
        if name.strip() in out:
            raise argparse.ArgumentTypeError(f"{name.strip()!r} given twice")
        out[name.strip()] = int(value)
    return out


def _t(t: float | None) -> str:
    return "-" if t is None else dt.datetime.fromtimestamp(t).strftime("%m-%d %H:%M:%S")


def _f(v, fmt: str = ".3g") -> str:
    return "-" if v is None else format(v, fmt)


def register(sub) -> None:
    p = sub.add_parser("parts", help="workpieces with their in-process and inspection records",
                       description="Workpieces the daemon tracked, newest last: cutting conditions, the "
                                   "largest chatter index and alarms during the cut, the compensation "
                                   "applied, and the post-process inspection joined to each.")
    p.add_argument("--abnormal", action="store_true", help="only parts cut under abnormal vibration")
    p.add_argument("--queue", action="store_true", help="only parts waiting for sampling inspection")
    p.add_argument("--limit", type=count, default=100)
    add_db_argument(p)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_parts)

    p = sub.add_parser("inspect", help="record a part's post-process inspection",
                       description="Record the post-process measurement of a part (the second of the "
                                   "two-time quality detection). PART is the number shown by "
                                   "`lathectl parts` or a unique prefix of its uuid.")
    p.add_argument("part", metavar="PART")
    p.add_argument("--ra", type=_num, metavar="UM", help="surface roughness Ra, µm")
    p.add_argument("--diameter-error", type=_num, metavar="UM", help="diameter error, µm (signed)")
    p.add_argument("--value", type=_pair, action="append", default=[], metavar="NAME=V",
                   help="another measured value (repeatable)")
    p.add_argument("--by", metavar="WHO", help="inspector")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_inspect)

    p = sub.add_parser("experiment", help="record and list Taguchi experiment trials",
                       description="Trials of a designed experiment (e.g. an L9 orthogonal array over "
                                   "speed, feed and depth of cut) per tool holder and material; "
                                   "`lathectl recommend` analyses them.")
    esub = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    a = esub.add_parser("add", help="record one trial (repeat a run's levels for replicates)",
                        description="Example, run 4 of an L9 over speed, feed, depth: lathectl experiment add "
                                    "--tool T0101 --material C45 --run 4 --levels speed=2,feed=1,depth=2 "
                                    "--setting speed=2000 --setting feed=0.1 --setting depth=1.0 "
                                    "--ra 1.8 --diameter-error -6 --removal-rate 1885")
    a.add_argument("--tool", help="tool holder (default: the records analyzer's tool)")
    a.add_argument("--material", help="work material (default: the records analyzer's material)")
    a.add_argument("--run", type=int, help="run number in the array (for reference)")
    a.add_argument("--levels", type=_levels, required=True, metavar="F=L,...",
                   help="level number of every factor, e.g. speed=1,feed=2,depth=3")
    a.add_argument("--setting", type=_setting, action="append", default=[], metavar="F=VALUE",
                   help="the physical value of a factor's level (repeatable), shown with recommendations")
    a.add_argument("--ra", type=_num, metavar="UM", help="measured Ra, µm (surface)")
    a.add_argument("--diameter-error", type=_num, metavar="UM", help="measured diameter error, µm (precision)")
    a.add_argument("--removal-rate", type=_num, metavar="MM3_MIN", help="material removal rate (efficiency)")
    a.add_argument("--json", action="store_true", help="print the recorded trial's id as JSON")
    a.set_defaults(func=cmd_experiment_add)
    ls = esub.add_parser("list", help="the trials recorded for a tool holder and material")
    ls.add_argument("--tool", help="tool holder (default: the records analyzer's tool; needed with the daemon down)")
    ls.add_argument("--material", help="work material (default: the records analyzer's; needed with the daemon "
                                       "down)")
    add_db_argument(ls)
    ls.add_argument("--json", action="store_true")
    ls.set_defaults(func=cmd_experiment_list)

    p = sub.add_parser("recommend", help="cutting parameters from Taguchi experiments",
                       description="Recommended factor levels for best precision (smaller-the-better "
                                   "|diameter error|), best surface (smaller-the-better Ra) and best "
                                   "efficiency (larger-the-better removal rate), from the main effects "
                                   "of the S/N ratios of the recorded trials.")
    p.add_argument("--tool", help="tool holder (default: the records analyzer's)")
    p.add_argument("--material", help="material (default: the records analyzer's)")
    p.add_argument("--all", action="store_true", help="one recommendation per tool holder and material tried")
    add_db_argument(p)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_recommend)

    p = sub.add_parser("export", help="export records as CSV (all of them, oldest first)")
    p.add_argument("what", choices=("events", "parts", "inspections", "experiments"))
    p.add_argument("--out", metavar="FILE.csv", help="write here instead of standard output")
    p.add_argument("--limit", type=count, help="only the newest N rows (default: every row)")
    add_db_argument(p)
    p.add_argument("--json", action="store_true", help="JSON lines, one object per row, instead of CSV")
    p.set_defaults(func=cmd_export)


def _query(con):
    """lathed.records' query function on a connection lathectl opened."""
    from lathed.store import read_rows
    return lambda sql, params=(): read_rows(con, sql, params)


def cmd_parts(args: argparse.Namespace) -> int:
    def read(con):
        from lathed import records
        return records.parts(_query(con), args.abnormal, args.queue, args.limit)
    rows = remote_or_db(args, "parts", "parts", {"abnormal": args.abnormal, "pending": args.queue,
                                                 "limit": args.limit}, read)
    if args.json:
        print_json(rows)
        return 0
    if not rows:
        print("(no parts)")
        return 0
    print(f"{'part':>5} {'no':>5} {'prog':>5} {'ended':<14} {'outcome':<10} {'tools':<5} {'r/min':>6} {'depth':>5} "
          f"{'chatter':>8} {'alarms':>6} {'comp µm':>7}  {'Ra µm':>6} {'dD µm':>6}  state")
    for r in rows:
        if r["inspected_t"] is not None:
            state = f"inspected {_t(r['inspected_t'])}" + (f" by {r['inspector']}" if r["inspector"] else "")
        elif r["queued_t"] is not None:
            state = "QUEUED for sampling inspection"
        else:
            state = "-"
        if r.get("unwatched"):
            # not judged by its vibration: the interval is the one it was made in, not its cut
            state = (f"NOT OBSERVED ({r['unwatched']}), made {_t(r['start_t'])} - {_t(r['end_t'])}"
                     if r["outcome"] == "unobserved" else f"NOT WATCHED WHOLE ({r['unwatched']})") + f"; {state}"
        if r["abnormal"]:
            state = f"ABNORMAL: {r['reason']}; {state}"
        print(f"{r['id']:>5} {_f(r['part_no'], 'd'):>5} {_f(r['program'], 'd'):>5} {_t(r['end_t']):<14} "
              f"{r['outcome']:<10} {r.get('tools') or '-':<5} {_f(r['rpm'], '.0f'):>6} {_f(r['depth_mm'], '.2g'):>5} "
              f"{_f(r['max_chatter_index']):>8} {'-' if r['outcome'] == 'unobserved' else r['chatter_alarms']:>6} {_f(r['compensation_um'], '.1f'):>7}  "
              f"{_f(r['ra_um'], '.2f'):>6} {_f(r['diameter_error_um'], '.1f'):>6}  {state}")
    return 0


def cmd_inspect(args: argparse.Namespace) -> int:
    values = once(args.value, "--value")
    if values is None:
        return 2
    part = remote(args, "inspect", {"part": args.part, "ra_um": args.ra, "diameter_error_um": args.diameter_error,
                                    "values": values, "by": args.by})
    if args.json:
        print_json(part)
    else:
        print(f"part {part['id']} ({part['uuid'][:8]}): Ra {_f(part['ra_um'], '.2f')} µm, "
              f"diameter error {_f(part['diameter_error_um'], '.1f')} µm recorded"
              + (" (was queued for sampling inspection)" if part["queued_t"] else ""))
    return 0


def cmd_experiment_add(args: argparse.Namespace) -> int:
    settings = once(args.setting, "--setting")
    if settings is None:
        return 2
    unknown = set(settings) - set(args.levels)
    if unknown:
        print(f"lathectl: --setting for {', '.join(sorted(unknown))}, which --levels does not name",
              file=sys.stderr)
        return 2
    res = remote(args, "experiment_add", {"tool": args.tool, "material": args.material, "run": args.run,
                                          "levels": args.levels, "settings": settings, "ra_um": args.ra,
                                          "diameter_error_um": args.diameter_error,
                                          "removal_rate": args.removal_rate})
    if args.json:
        print_json(res)
    else:
        print(f"trial {res['id']} recorded")
    return 0


def cmd_experiment_list(args: argparse.Namespace) -> int:
    def read(con):
        from lathed import records
        if args.tool is None or args.material is None:
            # their defaults are the running records analyzer's configuration
            raise DaemonUnavailable("lathed is not running: give --tool and --material to read the trials "
                                    "from its database")
        return records.experiments(_query(con), args.tool, args.material)
    rows = remote_or_db(args, "experiments", "experiments", {"tool": args.tool, "material": args.material}, read)
    if args.json:
        print_json(rows)
        return 0
    for r in rows:
        lv = ",".join(f"{k}={v}" for k, v in sorted(r["levels"].items()))
        print(f"{r['id']:>5} run {_f(r['run'], 'd'):>3} {lv:<30} Ra {_f(r['ra_um'])} dD {_f(r['diameter_error_um'])} "
              f"MRR {_f(r['removal_rate'])}")
    if not rows:
        print("(no trials)")
    return 0


def cmd_recommend(args: argparse.Namespace) -> int:
    req = {k: v for k, v in (("tool", args.tool), ("material", args.material)) if v is not None}

    def read(con):
        from lathed import records
        if args.all:
            return records.recommendations(_query(con), args.tool, args.material)
        if args.tool is None or args.material is None:
            # their defaults are the running records analyzer's configuration
            raise DaemonUnavailable("lathed is not running: give --tool and --material (or --all) to read the "
                                    "trials from its database")
        return records.recommendation(_query(con), args.tool, args.material)
    try:
        rec = remote_or_db(args, "experiments", "recommend", {**req, "all": True} if args.all else req, read)
    except ValueError as e:       # read from the database: the daemon's refusal, in the same words
        print(f"lathectl: {e}", file=sys.stderr)
        return 1
    if args.json:
        print_json(rec)
        return 0
    if not args.all:
        _print_recommendation(rec)
        return 0
    for r in rec["pairs"]:
        if "error" in r:
            print(f"tool {r['tool']}, material {r['material']}: {r['error']}")
        else:
            _print_recommendation(r)
    if not rec["pairs"]:
        print("(no experiment records; add them with `lathectl experiment add`)")
    return 0


def _print_recommendation(rec: dict) -> None:
    print(f"tool {rec['tool']}, material {rec['material']}: {rec['trials']} trials, factors "
          f"{', '.join(rec['factors'])}")
    for obj, res in rec["objectives"].items():
        if res is None:
            print(f"best {obj}: no trials measured it")
            continue
        parts = []
        for f in rec["factors"]:
            lv = "/".join(str(x) for x in res["best"][f])
            vals = [v for v in res["best_settings"][f] if v is not None]
            parts.append(f"{f}={lv}" + (f" ({'/'.join(map(str, vals))})" if vals else ""))
        note = "" if res["balanced"] else "  [unbalanced: some runs missing]"
        print(f"best {obj:<10} {'  '.join(parts)}   ({res['sn']} {res['response']}, "
              f"{res['runs']} runs; influence: {' > '.join(res['rank'])}){note}")


EXPORT_PAGE = 10_000   # rows per request: the daemon's reply and ours stay small, however many there are




def _pages(fetch, limit: int | None):
    """Every row, oldest first, a page per ``fetch(limit, after_id)`` (or the newest ``limit`` in one,
    at most 100000)."""
    if limit:
        yield fetch(min(limit, 100_000), None)
        return
    after = 0
    while True:
        rows = fetch(EXPORT_PAGE, after)
        yield rows
        if len(rows) < EXPORT_PAGE:
            return
        after = rows[-1]["id"]


def cmd_export(args: argparse.Namespace) -> int:
    try:
        out = open(args.out, "w", newline="", encoding="utf-8") if args.out else sys.stdout
    except OSError as e:
        print(f"lathectl: cannot write {args.out}: {e.strerror}", file=sys.stderr)
        return EX_CANTCREAT
    n, w = 0, None

    def write(rows: list[dict]) -> None:
        nonlocal n, w
        for r in rows:
            if args.json:
                out.write(json.dumps(r) + "\n")
                continue
            if w is None:
                w = csv.DictWriter(out, fieldnames=list(r))
                w.writeheader()
            w.writerow({k: json.dumps(v) if isinstance(v, (dict, list)) else v for k, v in r.items()})
        n += len(rows)

    def from_db(con) -> None:
        from lathed import records
        q = _query(con)
        for rows in _pages(lambda limit, after: records.export_page(q, args.what, limit, after), args.limit):
            write(rows)

    pages = _pages(lambda limit, after: remote(args, "export", {"what": args.what, "limit": limit}
                                               | ({} if after is None else {"after_id": after})), args.limit)
    try:
        try:
            first = next(pages)
        except DaemonUnavailable as e:   # before any row: the whole table from the database instead
            read_db(args, args.what, from_db, e)
        else:
            write(first)
            for rows in pages:
                write(rows)
    finally:
        if args.out:
            out.close()
    if args.out:
        print(f"{n} {args.what} written to {args.out}", file=sys.stderr)
    if args.limit and args.limit > 100_000:
        print("lathectl: --limit is at most 100000 rows; the newest 100000 were written", file=sys.stderr)
    return 0
