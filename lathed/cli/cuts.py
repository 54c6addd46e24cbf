"""``lathectl cuts``: the daemon's cut records; ``--csv`` exports them for
``lathectl analyze stability``; ``lathectl stability status|refit``: the
stability model refitted on them and adopted by the daemon.

    lathectl cuts [--machine M] [--since 2h|2026-11-23T08:00] [--limit N] [--json | --csv [FILE]]
    lathectl stability refit [--machine M] [--dry-run] [--holdout 0.3] [--json]
    lathectl stability learn [--machine M] [--json]    (no modal model configured: learned from the cuts)
"""
from __future__ import annotations

import argparse
import datetime as dt
import sys
import time

from lathed.cli import EX_CANTCREAT, EX_DATAERR, fail
from lathed.cli import count
from lathed.cli.eventtext import cut_text
from lathed.client import call
from lathed.cli import REFIT_TIMEOUT_S, print_json, remote

MAX_CUTS = 100_000     # the events command's limit


def _since(text: str) -> float:
    """argparse type: a duration back from now ("2h", "30min") or a local date/time; as a Unix time."""
    from lathed.config import parse_duration
    try:
        return time.time() - parse_duration(text)
    except ValueError:
        pass
    try:
        return dt.datetime.fromisoformat(text).timestamp()
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is neither a duration (2h, 30min) nor a date/time "
                                         f"(2026-11-23 or 2026-11-23T08:00)") from None


def _records(args) -> list[dict]:
    limit = MAX_CUTS if args.csv is not None else args.limit
    rows = remote(args, "events", {"kind": "cut", "limit": limit if args.machine is None and args.since is None
                                   else MAX_CUTS})
    out = [r for r in rows if (args.machine is None or r["payload"].get("machine") == args.machine)
           and (args.since is None or r["t"] >= args.since)]
    return out if args.csv is not None else out[-args.limit:]


def run_cuts(args) -> int:
    rows = _records(args)
    if args.csv is not None:
        from lathed.analysis.cut_log import cut_rows
        from lathed.analysis.cuts import write_cuts_csv
        cuts, skipped = cut_rows([r["payload"] for r in rows])
        for why, n in skipped.items():
            print(f"lathectl: {n} cut speed(s) not exported: {why}", file=sys.stderr)
        if cuts is None:
            return fail(f"no exportable cut among {len(rows)} recorded", EX_DATAERR)
        try:
            write_cuts_csv(cuts, sys.stdout if args.csv == "-" else args.csv)
        except OSError as e:
            return fail(f"cannot write {args.csv}: {e.strerror or e}", EX_CANTCREAT)
        if args.csv != "-":
            print(f"{len(cuts)} cut speed(s) of {len(rows)} cut(s) written to {args.csv}")
        return 0
    if args.json:
        print_json([{"id": r["id"], "t": r["t"], "source": r["source"], **r["payload"]} for r in rows])
        return 0
    for r in rows:
        p = r["payload"]
        t = time.strftime("%m-%d %H:%M:%S", time.localtime(p.get("start_t") or r["t"]))
        print(f"{r['id']:>7} {t} {cut_text(p)}")
    if not rows:
        print("(no cuts)")
    return 0


def _analyzer(args) -> str | None:
    """The suppression analyzer of --machine (the one that records its cuts and holds its lobes)."""
    if args.analyzer or not args.machine:
        return args.analyzer
    names = [a["name"] for a in remote(args, "status")["analyzers"] if a.get("machine") == args.machine
             and "cuts_recorded" in a]
    if not names:
        raise SystemExit(fail(f"no suppression analyzer controls machine {args.machine!r}", 1))
    return names[0]


def run_stability(args) -> int:
    if args.dry_run and args.action != "refit":
        return fail(f"--dry-run is for refit, not {args.action}", 2)
    req = {"action": args.action, "analyzer": _analyzer(args)}
    if args.action == "refit":
        req.update(dry_run=args.dry_run, holdout=args.holdout)
    r = call("stability", req, sock_path=args.socket,
             timeout=REFIT_TIMEOUT_S if args.action in ("refit", "learn") else 10.0)
    if args.json:
        print_json(r)
        return 0
    if args.action == "status":
        print(f"{r['machine']}: model {r['model']} ({r['tool'] or '-'}/{r['material'] or '-'}), "
              f"{r['cuts_recorded']} cut(s) recorded since start")
        le = r.get("learning")
        if le is not None:
            last = le["last"]
            print(f"learning from the cuts: {le['cut_speeds']} usable cut speed(s), next learn at {le['next_learn_at']}"
                  + (" (running)" if le["running"] else "")
                  + ("" if last is None else f"; last: {last['summary']}"))
        return 0
    if args.action == "learn":
        print(f"cuts: {r['cuts']} cut speeds from {r['cut_records']} cut record(s) of {r['machine']}")
        for why, n in r["left_out"].items():
            print(f"left out: {n} {why}")
        print(r["summary"])
        for p in r["best_rpm"]:
            print(f"best speed: {p['rpm'][0]:.0f} r/min (90 % {p['rpm'][1]:.0f}-{p['rpm'][2]:.0f}), "
                  f"limit {p['limit_mm']:.3f} mm")
        print({"adopted": f"learned and in use: {r['model_name']}",
               "withdrawn": "the model in use is withdrawn: suppression is model-free until a learn is trusted",
               "kept": f"not trusted; {r['model_name']} stays in use",
               "not trusted": "not trusted: suppression stays model-free"
                              + (f" (about {r['cuts_needed']} cut speeds needed)" if r["cuts_needed"] else "")}
              [r["verdict"]])
        return 0
    from lathed.cli.analyze_stability import _stage
    print(f"cuts: {r['cuts']} cut speeds from {r['cut_records']} cut record(s) of {r['machine']}: fitted on the "
          f"first {r['train']}, judged on the last {r['heldout']}")
    for why, n in r["left_out"].items():
        print(f"left out: {n} {why}")
    print(_stage("before", _residual(r["before"])))
    for e in r["effects"]:
        print(f"found: {e['description']} (held-out errors {e['heldout_errors'][0]} -> {e['heldout_errors'][1]}, "
              f"kept by {e['kept_by']})")
    print(_stage("after", _residual(r["after"])))
    for s in r["rejected"]:
        print(f"not added: {s}")
    if r["dry_run"]:
        print(f"dry run: {'would adopt' if r['adopt'] else 'would not adopt'}; nothing changed")
    elif r["adopt"]:
        print(f"adopted: {r['model_after_name']} replaces {r['model_before_name']} for speed selection and "
              f"cut-entry avoidance")
    else:
        print(f"not adopted, {r['model_before_name']} kept: {r['reason']}")
    return 0


def _residual(d: dict):
    """The JSON of a Residual back as what _stage prints."""
    from types import SimpleNamespace
    c = d["confusion"]
    return SimpleNamespace(accuracy=d["accuracy"], false_stable_rate=d["false_stable_rate"],
                           false_stable=c["chatter_predicted_stable"], n=d["cuts"],
                           freq_mae_hz=d["chatter_frequency"]["median_abs_error_hz"],
                           freq_n=d["chatter_frequency"]["measured"])


def _share(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not 0.05 <= v <= 0.9:
        raise argparse.ArgumentTypeError(f"{text} must be a share between 0.05 and 0.9")
    return v


def register(sub) -> None:
    p = sub.add_parser("cuts", help="recorded cuts (entry to exit): speeds, depth, chatter, actions; --csv "
                                    "exports them for `lathectl analyze stability`")
    p.add_argument("--machine", help="only this machine's cuts")
    p.add_argument("--since", type=_since, metavar="WHEN", help="only cuts since: a duration back (2h, 30min) "
                                                                 "or a date/time (2026-11-23T08:00)")
    # type=int took 0 and -1: out[-0:] is every cut, out[1:] all but the oldest
    p.add_argument("--limit", type=count, default=100, help="the newest N cuts (default 100; --csv: all)")
    out = p.add_mutually_exclusive_group()
    out.add_argument("--json", action="store_true")
    out.add_argument("--csv", nargs="?", const="-", metavar="FILE",
                     help="cut-record CSV, one row per judged speed of a cut (default: stdout)")
    p.set_defaults(func=run_cuts)

    p = sub.add_parser("stability", help="the stability model: status; refit it on the recorded cuts and adopt "
                                         "it when it classifies held-out cuts better; learn it from the cuts "
                                         "where no modal model is configured")
    p.add_argument("action", choices=("status", "refit", "learn"), nargs="?", default="status")
    p.add_argument("--machine", help="the machine (its suppression analyzer)")
    p.add_argument("--analyzer", help="which suppression analyzer (instead of --machine)")
    p.add_argument("--dry-run", action="store_true", help="report, adopt nothing")
    p.add_argument("--holdout", type=_share, default=0.3, metavar="SHARE",
                   help="share of the latest cut speeds held out to judge the refit (default 0.3)")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=run_stability)
