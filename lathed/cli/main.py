"""lathectl: the operator's command line (docs/lathectl.md).

Commands that ask the running daemon go over its control socket; the
``analyze`` commands run offline on files. Subcommands live in
``lathed/cli/``: a module there defines ``register(sub)`` for top-level
commands and/or ``register_analyze(sub)`` for ``lathectl analyze WHAT``.
"""
from __future__ import annotations

import argparse
import importlib
import json
import pkgutil
import sys
import time
from pathlib import Path
from typing import Any, Callable

from lathed import __version__
from lathed import cli as cli_pkg
from lathed.cli import (EX_UNAVAILABLE, UsageError, add_db_argument, age as _age, count, fmt_value as _fmt_value,
                        print_json, remote, remote_or_db)
from lathed.cli.eventtext import event_text
from lathed.client import DaemonUnavailable, RemoteError, subscribe


def _store_line(st: dict) -> str:
    """The record store's health in one line: failing now, or the last error and whether it passed."""
    now = time.time()
    counts = f"{st['written']} written, {st['failed']} failed, {st['queued']} queued"
    if st.get("failing"):
        since = st.get("failing_since")
        return (f"store: FAILING{'' if since is None else f' for {_age(now - since)}'}: {st.get('last_error')}; "
                f"{counts}")
    line = f"store: {counts}"
    if st.get("last_error"):
        line += f"; last error {_age(now - st['last_error_t'])} ago: {st['last_error']}"
        rec = st.get("recovered_t")
        if rec is not None and rec >= st["last_error_t"]:
            line += f" (recovered {_age(now - rec)} ago)"
    return line


def _print_implausible(entry: dict) -> None:
    """Values a peer sent that the plausibility check refused (lathed.plausible), by quantity and reason."""
    bad = entry.get("implausible")
    if bad:
        print("    implausible values refused: " + ", ".join(
            f"{q} {r} {n}" for q, reasons in bad.items() for r, n in reasons.items()))


def cmd_status(args: argparse.Namespace) -> int:
    st = remote(args, "status")
    if args.json:
        print_json(st)
        return 0
    d = st["daemon"]
    up = d["uptime_s"]
    print(f"lathed {d['version']} {d['state']}, up {int(up // 3600)}h{int(up % 3600 // 60):02d}m{int(up % 60):02d}s "
          f"(name {d['name']}, pid {d['pid']})")
    if d.get("store"):
        print(_store_line(d["store"]))
        kept = (d["store"].get("audit_reserve") or {}).get("kept_bytes")
        if kept:        # commands whose records the store refused: kept until it takes them
            print(f"audit reserve: {kept} bytes of command records kept, waiting for the store")
    dropped = (d.get("bus") or {}).get("dropped")
    if dropped:     # an analysis fell behind its samples and missed these
        print("bus: samples missed by a subscriber behind: "
              + ", ".join(f"{n} {c}" for n, c in sorted(dropped.items())))
    for r in d.get("recordings") or []:     # lathectl record streaming to a client now
        print(f"recording {r['source']}: " + (f"{r['samples']} samples" if r["recording"] else "waiting for a cut")
              + (f", cut {r['cuts_ended'] + 1} of {r['cuts']}" if r["cuts"] and r["recording"] else ""))
    print("machines:")
    for m in st["machines"] or [{"name": "(none)"}]:
        if "state" not in m:
            print("  (none)")
            continue
        rpm = "-" if m.get("spindle_rpm") is None else f"{m['spindle_rpm']:.0f} r/min"
        print(f"  {m['name']:<12} {m.get('kind') or '-':<10} {rpm:>12}  {m['detail']}")
        if m.get("state") == "connected" and m.get("takes") and (m.get("identity") or "confirmed") != "confirmed":
            print(f"    identity {m['identity']}: no command is sent to it")
        if m.get("heartbeat"):      # the count the control's PMC watches (a held override's dead-man)
            print(f"    heartbeat: count {m['heartbeat']['count']}, written every {m['heartbeat']['every_s']:g} s")
        _print_implausible(m)
    print("sensors:")
    for s in st["sensors"]:
        print(f"  {s['name']:<12} {s['detail']:<12} age {_age(s.get('age_s')):<8} {_fmt_value(s.get('last_value'))}")
        _print_implausible(s)
    if not st["sensors"]:
        print("  (none)")
    print("analyzers:")
    for a in st["analyzers"]:
        summary = a.get("summary", "")
        # one that crash-looped and runs again says so, with why (e.g. the store refused its records)
        fault = f"  (restarted after: {a['last_error']})" if a.get("last_error") and a.get("state") == "running" \
            else ""
        print(f"  {a['name']:<12} {a['detail']:<12} {summary}{fault}")
    if not st["analyzers"]:
        print("  (none)")
    return 0


def cmd_plugins(args: argparse.Namespace) -> int:
    plugins = remote(args, "plugins")
    if args.json:
        print_json(plugins)
        return 0
    for p in plugins:
        if p["state"] == "loaded":
            print(f"loaded  {p['name']:<20} {', '.join(p['provides']) or '-'}   ({p['origin']})")
        else:
            print(f"FAILED  {p['name']:<20} {p['error']}   ({p['origin']})")
    return 0


def _print_event(r: dict, as_json: bool) -> None:
    if as_json:
        print(json.dumps(r, default=str), flush=True)
        return
    t = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(r["t"]))
    print(f"{r['id']:>7} {t} {r['source']:<12} {r['kind']:<22} {event_text(r['kind'], r['payload'])}", flush=True)


def cmd_events(args: argparse.Namespace) -> int:
    if args.follow:
        # the last --limit events, then each new one as the daemon records it (one JSON line each with --json)
        for frame in (subscribe({"events": True, "events_limit": args.limit,
                                             "kinds": [args.kind] if args.kind else None,
                                             "sources": [args.source] if args.source else None,
                                             "rate_hz": 10.0}, sock_path=args.socket)):
            for r in frame.get("events", []):
                _print_event(r, args.json)
        return 0

    def read(con):
        from lathed.store import read_events, unknown_kind
        if args.kind is not None and (why := unknown_kind(con, [args.kind])):
            raise UsageError(f"--kind: {why}")
        return read_events(con, args.limit, args.kind, args.source)
    rows = remote_or_db(args, "events", "events", {"limit": args.limit, "kind": args.kind, "source": args.source},
                        read)
    if args.json:
        print_json(rows)
        return 0
    for r in rows:
        _print_event(r, False)
    if not rows:
        print("(no events)")
    return 0


def cmd_watch(args: argparse.Namespace) -> int:
    """Live values as they change: one line per value (a JSON line per frame with --json)."""
    patterns = args.pattern or ["*/*"]
    units: dict[str, str] = {}
    for frame in subscribe({"samples": patterns, "rate_hz": args.rate}, sock_path=args.socket):
        if args.json:
            print(json.dumps(frame), flush=True)
            continue
        for key, (t, v, unit) in sorted(frame.get("samples", {}).items()):
            units[key] = unit
            print(f"{time.strftime('%H:%M:%S', time.localtime(t))}.{int(t % 1 * 10)} {key:<32} "
                  f"{_fmt_value(v)} {unit}".rstrip(), flush=True)
    return 0


class Parser(argparse.ArgumentParser):
    """Bad arguments are one line naming the command and what is wrong, exit 2
    (sub-commands' parsers are of this class too: argparse makes them so)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="lathectl", description="Operate and query lathed.")
    p.add_argument("--socket", help="control socket of the daemon (default: $LATHED_SOCKET, "
                                    "/run/lathed/lathed.sock, or the one in this environment)")
    p.add_argument("--version", action="version", version=f"lathectl {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", required=True)

    s = sub.add_parser("status", help="daemon, machines, sensors and analyzers")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_status)
    s = sub.add_parser("plugins", help="loaded and failed plugins")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_plugins)
    s = sub.add_parser("events", help="recent recorded events")
    s.add_argument("--limit", type=count, default=30)   # --db took 0 and -3 (SQL LIMIT -3: all)
    s.add_argument("--kind")
    s.add_argument("--source")
    s.add_argument("--follow", "-f", action="store_true", help="then print each new event as it is recorded")
    add_db_argument(s)
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_events)
    s = sub.add_parser("watch", help="live values as they change (SOURCE/QUANTITY patterns, default all)")
    s.add_argument("pattern", nargs="*", help='e.g. "lathe/spindle_rpm" "temps/*" "chatter/chatter_index"')
    s.add_argument("--rate", type=float, default=2.0, help="updates per second (default 2)")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_watch)

    an = sub.add_parser("analyze", help="offline analyses of recorded files")
    asub = an.add_subparsers(dest="what", metavar="WHAT", required=True)
    for mod in pkgutil.iter_modules(cli_pkg.__path__):
        if mod.name == "main":
            continue
        try:
            m = importlib.import_module(f"lathed.cli.{mod.name}")
        except Exception as e:   # one broken subcommand must not take lathectl down
            print(f"lathectl: warning: subcommand module {mod.name} failed to load: {type(e).__name__}: {e}",
                  file=sys.stderr)
            continue
        if hasattr(m, "register"):
            m.register(sub)
        if hasattr(m, "register_analyze"):
            m.register_analyze(asub)
    _socket_anywhere(p)
    return p


def _socket_anywhere(p: argparse.ArgumentParser) -> None:
    """``--socket`` after the subcommand too (``lathectl status --socket X``), as users type it."""
    for action in p._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in set(action.choices.values()):
                if "--socket" not in child._option_string_actions:
                    child.add_argument("--socket", default=argparse.SUPPRESS, help=argparse.SUPPRESS)
                _socket_anywhere(child)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if not hasattr(args, "socket"):
        args.socket = None
    if getattr(args, "plot", None):
        # before the analysis, not after it: matplotlib is an extra (lathed.extras)
        from lathed.extras import missing
        if why := missing("matplotlib"):
            print(f"lathectl: --plot: {why}", file=sys.stderr)
            return EX_UNAVAILABLE
    try:
        return args.func(args)
    except DaemonUnavailable as e:
        print(f"lathectl: {e}", file=sys.stderr)
        return EX_UNAVAILABLE
    except RemoteError as e:
        print(f"lathectl: lathed refused: {e}", file=sys.stderr)
        return 2 if e.usage else 1      # a wrong argument is a usage error, as argparse's
    except UsageError as e:
        print(f"lathectl: {e}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        return 0
    except KeyboardInterrupt:   # the way out of --follow and watch
        return 130


if __name__ == "__main__":
    sys.exit(main())
