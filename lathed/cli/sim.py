"""lathectl sim: drive the built-in simulator (raise the depth of cut, take a peer down)."""
from __future__ import annotations

import argparse
import json
import socket
from pathlib import Path

from lathed.client import DaemonUnavailable, RemoteError, default_socket
from lathed.lathectl import print_json


def call(path: Path, cmd: str, args: dict) -> object:
    with socket.socket(socket.AF_UNIX) as s:
        s.settimeout(10)
        try:
            s.connect(str(path))
        except (FileNotFoundError, ConnectionRefusedError):
            raise DaemonUnavailable(f"no simulator listening on {path} (is the daemon running on "
                                    "the simulator?)") from None
        s.sendall(json.dumps({"cmd": cmd, "args": args}).encode() + b"\n")
        reply = json.loads(s.makefile("rb").readline())
    if not reply["ok"]:
        raise RemoteError(reply["error"])
    return reply["result"]


def run(args: argparse.Namespace) -> int:
    path = Path(args.sim_socket) if args.sim_socket else \
        (Path(args.socket) if args.socket else default_socket()).with_name("sim.sock")
    if args.what == "depth":
        r = call(path, "set", {"depth_mm": None if args.value == "program" else float(args.value)})
    elif args.what == "outage":
        r = call(path, "outage", {"peer": args.peer, "seconds": args.seconds})
    else:
        r = call(path, "status", {})
    print_json(r)
    return 0


def register(sub) -> None:
    p = sub.add_parser("sim", help="drive the built-in simulator")
    p.add_argument("--sim-socket", help="the simulator's control socket (default: sim.sock beside lathed's)")
    s = p.add_subparsers(dest="what", required=True)
    d = s.add_parser("depth", help="override the depth of cut (mm), or 'program' to go back")
    d.add_argument("value")
    o = s.add_parser("outage", help="take a peer down and bring it back")
    o.add_argument("peer", choices=("modbus", "vibration", "serial", "mill", "grinder", "robot"))
    o.add_argument("seconds", type=float)
    s.add_parser("status", help="the simulator's state")
    p.set_defaults(func=run)
