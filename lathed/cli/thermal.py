"""lathectl thermal status|refit|touchoff: the live thermal compensation."""
from __future__ import annotations

import argparse

from lathed.cli import REFIT_TIMEOUT_S, print_json
from lathed.client import call


def run(args: argparse.Namespace) -> int:
    r = call("thermal", {"action": args.action, "analyzer": args.analyzer}, sock_path=args.socket,
             timeout=REFIT_TIMEOUT_S if args.action == "refit" else 10.0)
    if args.json:
        print_json(r)
    elif args.action == "refit":
        effects = ", ".join(f"{e['effect']}({e['sensor']})" if e["sensor"] else e["effect"]
                            for e in r["effects"]) or "none"
        print(f"before: {r['model_before']}, error on the newest probes {r['before_rmse_um']:.2f} µm")
        for label, v in r.get("baselines_rmse_um", {}).items():
            print(f"baseline: {label}, fitted on the same rows: {v:.2f} µm")
        print(f"after:  {r['model_after']} ({r.get('handed_on', 'new model')}), error {r['after_rmse_um']:.2f} µm "
              f"({'adopted' if r['better'] else 'not adopted: old model kept'}); effects found: {effects}; "
              f"{r['rows']} probe measurements")
        if r.get("why"):
            print(f"why: {r['why']}")
    else:
        print(r["summary"] + (f"; last refused: {r['refused']}" if r.get("refused") else ""))
    return 0


def register(sub) -> None:
    p = sub.add_parser("thermal", help="thermal compensation: status; refit the model on stored probe data; "
                                       "touchoff: the tool was just touched off (growth counts from now)")
    p.add_argument("action", choices=("status", "refit", "touchoff"), nargs="?", default="status")
    p.add_argument("--analyzer", help="which thermal analyzer (when there are several)")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=run)
