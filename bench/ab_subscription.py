"""A/B of what one subscriber (lathed-web's subscription, no browser) costs the daemon:
this tree against another revision, in the same run.

Two daemons run side by side on the default config (simulator, 3 mm cuts so that
chatter and suppression act), one from this tree and one from ``--base`` (a git
revision, extracted to a temporary directory and imported in place of this tree).
Each cycle has a phase without and one with a subscriber on each daemon, the same
request lathed-web makes (lathed.link), read and thrown away by this process; the
daemons' CPU (their process only, /proc) per phase, and per cycle each daemon's
with - without (the subscription's cost, % of a core) and with / without.
Medians over the cycles: the two daemons see the same neighbours at the same time.

    .venv/bin/python bench/ab_subscription.py [--base main] [--cycles 8] [--seconds 15] [--own-config]
"""
from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_daemon import ROOT, as_unit, config, cpu_s  # noqa: E402
from bench_loop import DEPTH_MM  # noqa: E402

from lathed.link import DaemonLink  # noqa: E402

# imports the daemon from SRC, not from the editable install of this tree
LAUNCH = """import sys
src = sys.argv.pop(1)
if src != "-":
    sys.meta_path[:] = [f for f in sys.meta_path if "editable" not in repr(f)]
    sys.path.insert(0, src)
from lathed.daemon import main
sys.exit(main())
"""


def start(src: str, tmp: Path, own_config: bool = False) -> tuple[subprocess.Popen, Path]:
    cfg = config(tmp, root=Path(src)) if own_config and src != "-" else config(tmp)
    cfg.write_text(cfg.read_text().replace("[simulator]", f"[simulator]\ndepth_mm = {DEPTH_MM}", 1))
    ns = tmp / "notify.sock"
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    srv.bind(str(ns))
    srv.settimeout(60)
    log = open(tmp / "lathed.log", "wb")
    proc = subprocess.Popen([sys.executable, "-c", LAUNCH, src, "--config", str(cfg)], stdout=log, stderr=log,
                            env={**os.environ, "NOTIFY_SOCKET": str(ns)}, **as_unit("lathed"))
    try:
        while "READY=1" not in srv.recv(4096).decode():
            pass
    finally:
        srv.close()
    return proc, tmp / "run" / "lathed.sock"


class Reader:
    """One subscription (lathed-web's request, or only the keys in ``parts`` of it: samples,
    vibration, views, states, events), read and discarded on a thread (its cost is this process's)."""

    def __init__(self, sock: Path, parts: tuple[str, ...] | None = None):
        self.s = socket.socket(socket.AF_UNIX)
        self.s.connect(str(sock))
        args = DaemonLink(sock, 4.0).subscription()
        if parts is not None:
            args = {k: v for k, v in args.items() if k in parts or k == "rate_hz"
                    or (k == "events_limit" and "events" in parts)}
        self.s.sendall(json.dumps({"cmd": "subscribe", "args": args}).encode() + b"\n")
        self.bytes = 0
        self.t = threading.Thread(target=self._read, daemon=True)
        self.t.start()

    def _read(self) -> None:
        try:
            while chunk := self.s.recv(1 << 16):
                self.bytes += len(chunk)
        except OSError:
            pass

    def close(self) -> None:
        self.s.shutdown(socket.SHUT_RDWR)
        self.s.close()
        self.t.join(5)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--base", default="main", help="git revision to compare with")
    ap.add_argument("--this", default=None, help="git revision for the other side (default: the working tree)")
    ap.add_argument("--cycles", type=int, default=8)
    ap.add_argument("--seconds", type=float, default=15.0)
    ap.add_argument("--warmup", type=float, default=15.0)
    ap.add_argument("--settle", type=float, default=2.0, help="seconds after (un)subscribing before a phase")
    ap.add_argument("--own-config", action="store_true",
                    help="each side runs its own revision's etc/lathed.toml (an older daemon may refuse today's)")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="ab-sub-") as d:
        d = Path(d)
        def extract(rev: str, to: Path) -> str:
            rev = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", rev], capture_output=True,
                                 text=True, check=True).stdout.strip()
            to.mkdir()
            subprocess.run(f"git -C {ROOT} archive {rev} | tar -x -C {to}", shell=True, check=True)
            (to / "lathed_plugins").symlink_to("plugins")    # as the editable install maps it
            return rev
        rev = extract(a.base, d / "src-base")
        this_rev = extract(a.this, d / "src-this") if a.this else "working tree"
        sides = {}
        for name, src in (("base", str(d / "src-base")), ("this", str(d / "src-this") if a.this else "-")):
            (d / name).mkdir()
            sides[name] = start(src, d / name, a.own_config)
        rows: dict[str, list] = {n: [] for n in sides}
        try:
            time.sleep(a.warmup)
            for c in range(a.cycles):
                per = {}
                for phase in ("none", "sub"):
                    readers = [Reader(sock) for _, sock in sides.values()] if phase == "sub" else []
                    time.sleep(a.settle)
                    c0 = {n: cpu_s(p.pid) for n, (p, _) in sides.items()}
                    t0 = time.monotonic()
                    time.sleep(a.seconds)
                    wall = time.monotonic() - t0
                    for n, (p, _) in sides.items():
                        per[(n, phase)] = 100 * (cpu_s(p.pid) - c0[n]) / wall
                    for r in readers:
                        if r.bytes == 0:
                            raise SystemExit("ab_subscription: a subscriber received nothing")
                        r.close()
                for n in sides:
                    rows[n].append((per[(n, "none")], per[(n, "sub")]))
                print(f"cycle {c + 1}/{a.cycles}: " + ", ".join(
                    f"{n} {per[(n, 'none')]:.2f} -> {per[(n, 'sub')]:.2f} %" for n in sides), file=sys.stderr)
        finally:
            for p, _ in sides.values():
                p.terminate()
            for p, _ in sides.values():
                p.wait(20)
    print(f"\nDaemon CPU (% of a core), {a.cycles} interleaved cycles of {a.seconds:g} s without and with one "
          f"subscriber (lathed-web's request, rate 4/s); base = {a.base} ({rev}), this = {a.this or '-'} ({this_rev})\n")
    print("| daemon | no subscriber | subscribed | cost (with - without), median (range) | with / without |")
    print("|---|---|---|---|---|")
    for n, rs in rows.items():
        cost = [s - z for z, s in rs]
        print(f"| {n} | {statistics.median(z for z, _ in rs):.2f} | {statistics.median(s for _, s in rs):.2f} | "
              f"{statistics.median(cost):.2f} ({min(cost):.2f} .. {max(cost):.2f}) | "
              f"{statistics.median(s / z for z, s in rs):.3f} |")
    paired = [(sb - zb) - (st - zt) for (zb, sb), (zt, st) in zip(rows["base"], rows["this"])]
    print(f"\ncost saved per cycle (base - this), median: {statistics.median(paired):.2f} % of a core "
          f"(range {min(paired):.2f} .. {max(paired):.2f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
