"""lathectl subcommands: each module defines register(sub) and/or register_analyze(sub)."""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any, Callable

from lathed.client import DaemonUnavailable, call, default_db

# sysexits codes the offline commands use
EX_DATAERR, EX_NOINPUT, EX_UNAVAILABLE, EX_CANTCREAT = 65, 66, 69, 73
# a refit (stability or thermal) takes tens of seconds on a big store or a busy PC; other
# commands are answered within lathectl's usual 10 s
REFIT_TIMEOUT_S = 180.0


class UsageError(Exception):
    """A bad argument found past the parser (against a stopped daemon's store): one line, exit 2."""


def positive(text: str) -> float:
    """argparse type: a finite number > 0."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (v > 0 and math.isfinite(v)):
        raise argparse.ArgumentTypeError(f"{text!r} must be a positive number")
    return v


def count(text: str) -> int:
    """argparse type: a whole number >= 1 (a limit, a number of sensors)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"{v} must be at least 1")
    return v


SPINDLE_RPM_MAX = 100_000.0    # beyond any machine-tool spindle (lathed.plausible's r/min bound)


def spindle_rpm(text: str) -> float:
    """argparse type: a spindle speed, > 0 and at most SPINDLE_RPM_MAX r/min."""
    v = positive(text)
    if v > SPINDLE_RPM_MAX:
        raise argparse.ArgumentTypeError(f"{text} r/min is beyond any spindle (at most {SPINDLE_RPM_MAX:g})")
    return v


def mode(text: str):
    """argparse type: a structural mode FN,ZETA,K[,THETA_DEG] (numpy only once a mode is parsed)."""
    from lathed.analysis.modal import parse_mode
    try:
        return parse_mode(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def once(pairs: list, option: str) -> dict | None:
    """NAME=V options as a dict; a name given twice is one line on stderr and None, for
    exit 2 (the last one would be kept without a word)."""
    seen = [n for n, _ in pairs]
    twice = sorted({n for n in seen if seen.count(n) > 1})
    if twice:
        print(f"lathectl: {option} {twice[0]} given twice", file=sys.stderr)
        return None
    return dict(pairs)


def fail(msg: str, code: int) -> int:
    """One line on stderr naming what is wrong; the exit code to return."""
    print(f"lathectl: {msg}", file=sys.stderr)
    return code


# -- asking the daemon, or its store when it is down -----------------------------------
def remote(args: argparse.Namespace, cmd: str, cmd_args: dict | None = None) -> Any:
    """Ask the daemon; errors propagate to main() which prints one line."""
    return call(cmd, cmd_args, sock_path=args.socket)


def remote_or_db(args: argparse.Namespace, what: str, cmd: str, cmd_args: dict, read: Callable[[Any], Any]) -> Any:
    """Ask the daemon; when it is down, ``read(con)`` its records from its database (read_db)."""
    try:
        return remote(args, cmd, cmd_args)
    except DaemonUnavailable as e:
        return read_db(args, what, read, e)


def read_db(args: argparse.Namespace, what: str, read: Callable[[Any], Any], down: DaemonUnavailable) -> Any:
    """``read(con)`` on the daemon's database (--db, else client.default_db()) opened
    read-only, saying so in one line on stderr; with no database there, ``down`` is raised."""
    db = Path(args.db) if args.db else default_db()
    if not db.is_file():
        raise down
    import sqlite3

    from lathed.store import MIGRATIONS, connect
    version = latest = MIGRATIONS[-1][0]
    try:
        con = connect(db, readonly=True)
        try:
            version = con.execute("PRAGMA user_version").fetchone()[0]
            result = read(con)
        finally:
            con.close()
    except sqlite3.Error as e:
        # read-only, an older store cannot be upgraded here: a query may need a column it lacks
        old = (f" (schema version {version}, older than this lathectl's {latest}: start lathed once to "
               "upgrade it)") if version < latest else ""
        raise DaemonUnavailable(f"lathed is not running, and {db} cannot be read: {e}{old}") from None
    print(f"lathectl: lathed is not running; {what} read from {db}", file=sys.stderr)
    return result


def add_db_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--db", help="when the daemon is down, read this lathed.db (default: the service's "
                                "/var/lib/lathed/lathed.db, or the one in this environment)")


def print_json(obj: Any) -> None:
    print(json.dumps(obj, indent=2, default=str))


def age(s: float | None) -> str:
    return "-" if s is None else (f"{s:.1f} s" if s < 120 else f"{s / 60:.0f} min")


def fmt_value(v: Any) -> str:
    if isinstance(v, dict):
        return " ".join(f"{k}={fmt_value(x)}" for k, x in v.items())
    if isinstance(v, float):
        return f"{v:.4g}"
    return "-" if v is None else str(v)
