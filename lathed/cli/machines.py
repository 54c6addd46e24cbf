"""``lathectl machines``: the line's machines in the uniform machine model,
live values as they are, stale ones marked, never passed off as live."""
from __future__ import annotations

from typing import Any

STALE = "?"


def register(sub) -> None:
    p = sub.add_parser("machines", help="machines with their live and stale values",
                       description="State, spindle speed, part count, cycle time, program, alarms and "
                                   f"axis positions of every machine. A value marked {STALE} is stale: "
                                   "the last one known, older than the driver's stale_after or from "
                                   "before the link dropped.")
    p.add_argument("--json", action="store_true", help="print the machines as JSON")
    p.set_defaults(func=run)


def _v(entry: dict | None, fmt: str = "{}") -> str:
    if not entry:
        return "-"
    v = entry["value"]
    if isinstance(v, list):
        text = ",".join(map(str, v)) or "none"
    else:
        text = fmt.format(v)
    return text + (STALE if entry["stale"] else "")


def rows(machines: list[dict[str, Any]]) -> list[list[str]]:
    out = []
    for m in machines:
        mod = m.get("model") or {}
        state = mod.get("state") or ("disconnected" if m.get("state") != "connected" else "-")
        out.append([m["name"], m.get("kind") or "-", state, m.get("state", "-"),
                    _v(mod.get("spindle_rpm"), "{:.0f}"), _v(mod.get("part_count")),
                    _v(mod.get("cycle_time_s"), "{:.1f}"), _v(mod.get("program")), _v(mod.get("alarms")),
                    _v(mod.get("gripper"))])
    return out


HEAD = ["NAME", "KIND", "STATE", "LINK", "RPM", "PARTS", "CYCLE_S", "PROGRAM", "ALARMS", "GRIPPER"]


def run(args) -> int:
    from lathed.cli import print_json, remote
    st = remote(args, "status")
    machines = st["machines"]
    if args.json:
        print_json(machines)
        return 0
    if not machines:
        print("(no machines configured)")
        return 0
    table = [HEAD] + rows(machines)
    widths = [max(len(r[i]) for r in table) for i in range(len(HEAD))]
    any_stale = False
    for r, m in zip(table, [None] + machines):
        print("  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip())
        if m is None:
            continue
        axes = (m.get("model") or {}).get("axes") or {}
        if axes:
            print("    axes: " + "  ".join(f"{a}={_v(e, '{:.3f}')}" for a, e in axes.items()))
        if m.get("state") not in ("connected", None):
            print(f"    link: {m.get('detail')}")
        any_stale |= STALE in "".join(r) or any(e and e["stale"] for e in axes.values())
    if any_stale:
        print(f"({STALE}: stale, the last value known, not live)")
    return 0
