"""lathectl sim: drive the built-in simulator (raise the depth of cut, take a peer down),
or write a simulated thermal run to CSV for ``lathectl analyze thermal``."""
from __future__ import annotations

import argparse
import json
import socket
from pathlib import Path

from lathed.cli import positive
from lathed.client import DaemonUnavailable, RemoteError, default_socket
from lathed.cli import fmt_value as _fmt_value, print_json
from lathed.sim.program import MAX_DEPTH_MM, MAX_OUTAGE_S   # no numpy: lathectl starts without it


# lathed.sim.thermal.EFFECTS, named here so lathectl starts without numpy and scipy (a test keeps them equal)
THERMAL_EFFECTS = ("lag", "rate", "speed", "nonlinear", "hysteresis", "drift")


def depth_value(text: str) -> float | None:
    """argparse type: a depth of cut in mm, or 'program' (None: the program's own)."""
    if text == "program":
        return None
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is neither a depth in mm nor 'program'") from None
    if not 0.0 <= v <= MAX_DEPTH_MM:
        raise argparse.ArgumentTypeError(f"{text} mm is outside the depths the simulated lathe cuts (0..{MAX_DEPTH_MM:g} mm)")
    return v


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


def thermal_run(args: argparse.Namespace) -> int:
    """Offline: the simulated spindle from a cold start, as a CSV ``analyze thermal`` reads."""
    import sys

    from lathed.cli import EX_CANTCREAT
    from lathed.sim.thermal import add_periodic, add_speed_steps, generate_run, many_sensors, random_schedule
    run = generate_run(random_schedule(args.seed, total_s=args.hours * 3600), args.effect or (), seed=args.seed,
                       noise_um=args.noise_um, dt_s=args.row_s)
    extra = []
    if args.sensors > 4:
        run = many_sensors(run, args.seed, n_sensors=args.sensors)
        extra.append(f"{args.sensors} sensors of which 4 carry the growth")
    if args.periodic_min:
        run = add_periodic(run, period_s=args.periodic_min * 60.0)
        extra.append(f"a {args.periodic_min:g}-min cycle no sensor sees")
    if args.speed_step_um:
        run = add_speed_steps(run, step_um=args.speed_step_um)
        extra.append(f"steps of {args.speed_step_um:g} µm at speed changes")
    try:
        run.write_csv(args.out)
    except OSError as e:
        print(f"lathectl: cannot write {args.out}: {e.strerror}", file=sys.stderr)
        return EX_CANTCREAT
    if args.json:
        print_json({"out": str(args.out), "rows": len(run), "hours": args.hours, "seed": args.seed,
                    "effects": sorted(run.effects), "noise_um": args.noise_um, "sensors": args.sensors,
                    "periodic_min": args.periodic_min, "speed_step_um": args.speed_step_um})
        return 0
    print(f"{args.out}: {len(run)} rows, {args.hours:g} h from a cold start, speed schedule and day of seed "
          f"{args.seed}, effects: {', '.join(sorted(run.effects)) or 'none'}, probe noise {args.noise_um:g} µm"
          + "".join(f", {e}" for e in extra))
    return 0


def run(args: argparse.Namespace) -> int:
    if args.what == "thermal-run":
        return thermal_run(args)
    path = Path(args.sim_socket) if args.sim_socket else \
        (Path(args.socket) if args.socket else default_socket()).with_name("sim.sock")
    if args.what == "depth":
        r = call(path, "set", {"depth_mm": args.value})
        text = f"simulator: depth of cut {r['depth_mm']:g} mm" + \
            (" (the program's)" if args.value is None else " (override; 'program' goes back)")
    elif args.what == "outage":
        r = call(path, "outage", {"peer": args.peer, "seconds": args.seconds})
        text = f"simulator: {r['peer']} down for {r['seconds']:g} s"
    else:
        r = call(path, "status", {})
        text = _status_text(r)
    if args.json:
        print_json(r)
    else:
        print(text)
    return 0


def _status_text(r: dict) -> str:
    lines = [f"simulator: {r['phase']}, part {r['part']}, simulated time {r['t']:.0f} s, "
             f"thermal growth {r['displacement_um']:.1f} µm, {r['overruns']} overruns",
             "peers: " + ", ".join(f"{p} {'up' if up else 'DOWN'}" for p, up in r["peers"].items()),
             "registers: " + _fmt_value(r["registers"]),
             "temperatures: " + _fmt_value(r["temperatures"])]
    lines += [f"{name}: {_fmt_value(m)}" for name, m in r["line"].items()]
    for w in r.get("watchdog_resets", []):
        lines.append(f"PMC watchdog: a held override of {w['override_pct']:g} % taken back to 100 % after "
                     f"{w['silent_s']:g} s without a heartbeat")
    return "\n".join(lines)


def outage_seconds(text: str) -> float:
    """argparse type: an outage's length, 0 < s <= MAX_OUTAGE_S (float() took -5, nan and 1e12)."""
    v = positive(text)
    if v > MAX_OUTAGE_S:
        raise argparse.ArgumentTypeError(f"{text} s is longer than an outage the simulator takes "
                                         f"(at most {MAX_OUTAGE_S:g} s)")
    return v


def register(sub) -> None:
    p = sub.add_parser("sim", help="drive the built-in simulator")
    p.add_argument("--sim-socket", help="the simulator's control socket (default: sim.sock beside lathed's)")
    s = p.add_subparsers(dest="what", required=True)
    d = s.add_parser("depth", help="override the depth of cut (mm), or 'program' to go back")
    d.add_argument("value", type=depth_value, help="mm, or 'program'")
    o = s.add_parser("outage", help="take a peer down and bring it back")
    o.add_argument("peer", choices=("modbus", "vibration", "serial", "opcua", "mill", "grinder", "robot"))
    o.add_argument("seconds", type=outage_seconds)
    st = s.add_parser("status", help="the simulator's state")
    for c in (d, o, st):
        c.add_argument("--json", action="store_true", help="print the simulator's reply as JSON")
    t = s.add_parser("thermal-run", help="write a simulated thermal run (CSV) for `lathectl analyze thermal`; "
                                         "no daemon needed")
    t.add_argument("out", metavar="OUT.csv")
    t.add_argument("--effect", action="append", choices=THERMAL_EFFECTS,
                   help="an effect the static regression lacks, put into the data (repeatable; default none)")
    t.add_argument("--hours", type=positive, default=8.0, help="length of the run (default 8: one shift)")
    t.add_argument("--seed", type=int, default=1, help="speed schedule, sensor noise and time of day")
    t.add_argument("--noise-um", type=float, default=0.5, help="probe repeatability, µm (default 0.5)")
    t.add_argument("--row-s", type=positive, default=6.0, help="seconds between rows (default 6)")
    t.add_argument("--sensors", type=int, default=4, choices=range(4, 65), metavar="N",
                   help="temperature sensors, 4..64: beyond the four that carry the growth, sensors that "
                        "do not (some oscillating on their own); the motor's then oscillates too")
    t.add_argument("--periodic-min", type=positive, help="add a cycle of this period (min) to the growth "
                                                         "that no sensor sees")
    t.add_argument("--speed-step-um", type=float, help="add a step of this size to the growth while the "
                                                       "speed is at 2750 r/min or more")
    t.add_argument("--json", action="store_true", help="print what was written as JSON")
    p.set_defaults(func=run)
