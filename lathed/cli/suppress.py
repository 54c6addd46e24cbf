"""lathectl suppress auto|manual|off|now|forget|status: the chatter suppression switch."""
from __future__ import annotations

import argparse

from lathed.cli import print_json, remote


def run(args: argparse.Namespace) -> int:
    r = remote(args, "suppress", {"action": args.action, "analyzer": args.analyzer, "by": args.by})
    if args.json:
        print_json(r)
    elif args.action == "now":
        verb = "sent" if r["sent"] else f"REFUSED ({r['refused']})"
        print(f"{r['strategy']}: {r['rpm_before']:.0f} -> {r['rpm_after']:.0f} r/min {verb}")
    else:
        last = r.get("last_action")
        print(f"mode {r['mode']}, strategy {r['strategy']}"
              + (", avoids predicted chatter at cut entry" if r.get("avoid") else "")
              + f", chatter alarm {'ON' if r['chatter_alarm'] else 'off'}, {r['actions']} action(s)"
              + (f"; last {last['rpm_before']:.0f} -> {last['rpm_after']:.0f} r/min"
                 + (f" ({last['trigger']})" if last.get("trigger") in ("predicted", "remembered") else "")
                 if last else ""))
        if r.get("remember"):
            cures = r.get("cures") or []
            print(f"{len(cures)} remembered cure(s)" + (": " if cures else "")
                  + ", ".join(f"{c['rpm_entry']:.0f} -> {c['rpm']:.0f} r/min"
                              + (f" (chattered {c['depth_mm']:g} mm deep)" if c.get("depth_mm") else "")
                              + (f" with tool {c['tool_number']}" if c.get("tool_number") is not None else "")
                              for c in cures))
        if r.get("advisories"):
            print(f"{r['advisories']} cut(s) held with advice; last: {r['last_advice']['advice']}")
    return 0


def register(sub) -> None:
    p = sub.add_parser("suppress", help="chatter suppression: auto | manual | off, act now, or forget the "
                                        "remembered cures (a new tool or set-up)")
    p.add_argument("action", choices=("auto", "manual", "off", "now", "forget", "status"), nargs="?",
                   default="status")
    p.add_argument("--analyzer", help="which suppression analyzer (when there are several)")
    p.add_argument("--by", default="operator", help="who acts, for the record")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=run)
