"""What each part of lathed-web's subscription costs the daemon, beside the measure's own floor.

One daemon on the default config (simulator, 3 mm cuts, as ab_subscription.py). Each cycle runs
phases in the same order: no subscriber, then one subscriber asking for one part only (samples,
vibration, views, states, events) or for all of it (lathed-web's request), with a second phase
without a subscriber among them: how far two phases without one differ is the floor below which
a part's cost cannot be told. Per phase the daemon's CPU (its process only, /proc), and per
part the median over cycles of (phase - the cycle's first phase without a subscriber).

    .venv/bin/python bench/sub_parts.py [--cycles 4] [--seconds 12]
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ab_subscription import Reader, start  # noqa: E402
from bench_daemon import cpu_s  # noqa: E402

PARTS = ("samples", "vibration", "views", "states", "events")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cycles", type=int, default=4)
    ap.add_argument("--seconds", type=float, default=12.0)
    ap.add_argument("--warmup", type=float, default=15.0)
    ap.add_argument("--settle", type=float, default=1.5)
    a = ap.parse_args()
    phases: dict[str, tuple[str, ...] | None] = {"none": None, "all": PARTS, "none again": None,
                                                  **{p: (p,) for p in PARTS}}
    cpu: dict[str, list[float]] = {p: [] for p in phases}
    rate: dict[str, list[float]] = {p: [] for p in phases}
    with tempfile.TemporaryDirectory(prefix="sub-parts-") as d:
        (Path(d) / "daemon").mkdir()
        proc, sock = start("-", Path(d) / "daemon")
        try:
            time.sleep(a.warmup)
            for c in range(a.cycles):
                for name, parts in phases.items():
                    r = Reader(sock, parts) if parts else None
                    time.sleep(a.settle)
                    c0, b0, t0 = cpu_s(proc.pid), r.bytes if r else 0, time.monotonic()
                    time.sleep(a.seconds)
                    wall = time.monotonic() - t0
                    cpu[name].append(100 * (cpu_s(proc.pid) - c0) / wall)
                    if r:
                        rate[name].append((r.bytes - b0) / wall / 1000)
                        if r.bytes == 0:
                            raise SystemExit(f"sub_parts: the subscriber to {name} received nothing")
                        r.close()
                print(f"cycle {c + 1}/{a.cycles}: " + ", ".join(f"{n} {v[-1]:.2f}" for n, v in cpu.items()),
                      file=sys.stderr)
        finally:
            proc.terminate()
            proc.wait(20)
    print(f"\nDaemon CPU (% of a core), {a.cycles} cycles of {a.seconds:g} s phases; cost: the median over "
          "cycles of the phase less the cycle's first phase without a subscriber\n")
    print("| phase | KB/s to the subscriber | daemon CPU, median | cost, median (range) |")
    print("|---|---|---|---|")
    for name, v in cpu.items():
        diff = [x - z for x, z in zip(v, cpu["none"])]
        kb = f"{statistics.median(rate[name]):.1f}" if rate[name] else ""
        print(f"| {name} | {kb} | {statistics.median(v):.2f} | "
              f"{statistics.median(diff):.2f} ({min(diff):.2f} .. {max(diff):.2f}) |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
