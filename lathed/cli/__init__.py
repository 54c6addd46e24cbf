"""lathectl subcommands: each module defines register(sub) and/or register_analyze(sub)."""
from __future__ import annotations

import argparse
import math
import sys

# sysexits codes the offline commands use
EX_DATAERR, EX_NOINPUT, EX_UNAVAILABLE, EX_CANTCREAT = 65, 66, 69, 73


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
