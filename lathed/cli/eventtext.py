"""How a recorded event reads on a terminal (``lathectl events``, ``lathectl cuts``).

A payload is ``key=value`` pairs; nested tables as ``key.sub=value``, lists as
``a, b``, never Python syntax. A ``cut`` record (lathed.analysis.cut_log) is
told as a sentence: machine, tool, depth, outcome, and each speed with its verdict.
"""
from __future__ import annotations

import json
from typing import Any

LIST_ITEMS = 6      # a long list shows its first items and how many more


def value_text(v: Any) -> str:
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:.4g}"
    if v is None:
        return "-"
    if isinstance(v, dict):
        return "{" + " ".join(f"{k}={value_text(x)}" for k, x in v.items()) + "}"
    if isinstance(v, list):
        more = f", ... ({len(v) - LIST_ITEMS} more)" if len(v) > LIST_ITEMS else ""
        return ", ".join(value_text(x) for x in v[:LIST_ITEMS]) + more
    return str(v)


def payload_text(p: Any, prefix: str = "") -> str:
    """``key=value`` pairs; a nested table's keys as ``key.sub``."""
    if not isinstance(p, dict):
        return value_text(p)
    parts = []
    for k, v in p.items():
        if isinstance(v, dict) and v:
            parts.append(payload_text(v, f"{prefix}{k}."))
        else:
            parts.append(f"{prefix}{k}={value_text(v)}")
    return " ".join(parts)


def event_text(kind: str, payload: Any) -> str:
    if kind == "cut" and isinstance(payload, dict) and "speeds" in payload:
        try:
            return cut_text(payload)
        except (KeyError, TypeError, ValueError):   # a record of another shape: as it is
            return json.dumps(payload, default=str)
    return payload_text(payload)


def _f(v, fmt: str) -> str:
    return "-" if v is None else format(v, fmt)


def speed_text(s: dict) -> str:
    """A stretch's speed; one that drifted (constant surface speed) as its range."""
    if s.get("steady") is False and s.get("rpm_min") is not None and s.get("rpm_max") is not None:
        return f"{s['rpm_min']:.0f}..{s['rpm_max']:.0f} (drifting)"
    return _f(s.get("rpm"), ".0f")


def cut_text(p: dict) -> str:
    """One cut record in a line: tool, depth, feed, outcome, each speed's verdict, the first alarm."""
    speeds = " -> ".join(f"{speed_text(s)}{'' if s.get('outcome') is None else ' ' + s['outcome']}"
                         for s in p.get("speeds") or [])
    alarm = "" if p.get("first_alarm_s") is None else \
        (f", first alarm at {p['first_alarm_s']:.2f} s (rev {_f(p.get('first_alarm_rev'), '.0f')}) "
         f"{_f(p.get('chatter_frequency_hz'), '.1f')} Hz")
    cured = {True: ", cured", False: ", not cured", None: ""}[p.get("cured")]
    if p.get("advice"):
        cured += " (speed held: no stable speed within reach)"
    tn = "" if p.get("tool_number") is None else f" tool {p['tool_number']}"
    return (f"{p['machine']:<10} {p.get('tool') or '-'}/{p.get('material') or '-'}{tn} "
            f"depth {_f(p.get('depth_mm'), '.3g')} mm ({p.get('depth_from') or 'unknown'}), "
            f"feed {_f(p.get('feed_mm_rev'), '.3g')}: {p.get('outcome') or 'too short to judge'}; "
            f"r/min {speeds}{alarm}{cured}")
