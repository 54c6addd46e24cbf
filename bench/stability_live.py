"""The closed loop from zero in the live simulator (issue 41; docs/stability.md).

Runs the daemon on the default config (etc/lathed.toml, simulator spawned) with
no modal model (strategy "lobes" without ``modes``), remembered cures off (so
each pass is answered by the policy alone) and the depth register on, the
simulator cutting the refit benchmark's cut program (bench_stability.py's closed
loop: speeds log-uniform 1000-4500 r/min, depths 0.6-1.6x the simulated lathe's
critical depth).  The daemon answers chatter model-free until a model learned
from its own cut records is trusted, then from that model's lobes.  From its cut
records: re-chatters (a stretch at a speed suppression moved to that chattered
again) in each third of the program, when a learn was trusted, the learns.

    .venv/bin/python bench/stability_live.py [--cuts 200] [--seed 0] [--timeout 5400] [--keep DIR]
"""
from __future__ import annotations

import argparse
import json
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_daemon import config  # noqa: E402
from bench_loop import events, start, stop  # noqa: E402

from lathed.analysis.cut_log import RISING_RATIO  # noqa: E402
from lathed.analysis.stability import StabilityModel  # noqa: E402
from lathed.client import call  # noqa: E402
from lathed.sim.lathe import LATHE_KF, LATHE_MODES  # noqa: E402

CUT_LENGTH_MM = 24.0     # 80 revolutions: room for a move, its settle and a verdict
FEED_MM_REV = 0.3


def program(n: int, seed: int) -> list[tuple[float, float]]:
    """bench_stability.py's closed-loop program: (rpm, depth mm)."""
    given = StabilityModel(LATHE_MODES, LATHE_KF)
    b_min = float(given.limit(np.geomspace(300, 6000, 2000))[0].min())
    rng = np.random.default_rng(3000 + seed)
    rpm = np.exp(rng.uniform(np.log(1000), np.log(4500), n))
    return list(zip(rpm.round(0), (b_min * 1e3 * rng.uniform(0.6, 1.6, n)).round(3)))


def edit(cfg: Path, prog: list[tuple[float, float]]) -> None:
    text = cfg.read_text()
    text = re.sub(r'^modes = \[.*\]\n', "", text, count=1, flags=re.M)      # [analyzer.suppress]'s tap test
    text = text.replace("\nremember = true", "\nremember = false", 1)
    text = text.replace("# depth_of_cut_mm = {", "depth_of_cut_mm = {", 1)
    lines = json.dumps([f"{r:g},{d:g},{FEED_MM_REV:g},{CUT_LENGTH_MM:g}" for r, d in prog])
    text = text.replace("[simulator]\n", f"[simulator]\nprogram = {lines}\nload_s = 0.3\nretract_s = 0.2\n", 1)
    assert "remember = false" in text and "\ndepth_of_cut_mm = {" in text
    cfg.write_text(text)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cuts", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--timeout", type=float, default=5400.0, help="seconds for the whole program")
    ap.add_argument("--keep", type=Path, help="copy the daemon's state directory (lathed.db) and log here")
    a = ap.parse_args()
    prog = program(a.cuts, a.seed)
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        cfg = config(tmp)
        edit(cfg, prog)
        proc = start(cfg, tmp)
        sock = tmp / "run" / "lathed.sock"
        t0 = time.monotonic()
        try:
            while True:
                cuts = [c for c in events(sock, "cut") if c["payload"]["machine"] == "lathe"]
                if len(cuts) >= a.cuts or time.monotonic() - t0 > a.timeout:
                    break
                time.sleep(5.0)
            learned = events(sock, "stability_model_learned")
            untrusted = events(sock, "stability_learn_not_trusted")
            status = call("stability", {"action": "status", "analyzer": "suppress"}, sock_path=sock, timeout=10.0)
        finally:
            stop(proc, tmp)
            if a.keep is not None:
                shutil.copytree(tmp / "state", a.keep / "state", dirs_exist_ok=True)
                shutil.copy(tmp / "lathed.log", a.keep / "lathed.log")
    cuts = sorted(cuts, key=lambda c: c["id"])[:a.cuts]
    n = len(cuts)
    # re-chatters, moves, chatter at entry, ended in chatter, moves still rising at their end (not judged)
    thirds = [[0, 0, 0, 0, 0] for _ in range(3)]
    for i, c in enumerate(cuts):
        k = min(2, 3 * i // max(n, 1))
        for s in c["payload"]["speeds"]:
            moved = s["trigger"] != "entry"
            thirds[k][1] += moved and s["trigger"] == "alarm"
            thirds[k][0] += moved and s["outcome"] == "chatter"
            thirds[k][2] += not moved and s["outcome"] == "chatter"
            thirds[k][4] += moved and s["outcome"] is None and (s.get("rising") or 0) >= RISING_RATIO
        speeds = c["payload"]["speeds"]
        thirds[k][3] += bool(speeds) and speeds[-1]["outcome"] == "chatter"
    first_trusted = min((e["t"] for e in learned), default=None)
    at = next((i + 1 for i, c in enumerate(cuts) if first_trusted is not None and c["t"] > first_trusted), None)
    print(f"## The closed loop from zero, live: {n} cuts of the program (seed {a.seed}) on the simulated lathe, "
          f"{time.monotonic() - t0:.0f} s\n")
    print("| | first third | middle | last third |")
    print("|---|---:|---:|---:|")
    print("| re-chatters (a move that chattered again) | " + " | ".join(str(t[0]) for t in thirds) + " |")
    print("| moves on an alarm | " + " | ".join(str(t[1]) for t in thirds) + " |")
    print("| cuts chattering at entry | " + " | ".join(str(t[2]) for t in thirds) + " |")
    print("| cuts ending in chatter (held, or no move left) | " + " | ".join(str(t[3]) for t in thirds) + " |")
    print("| moves whose chatter index was still rising at the pass's end (not judged) | "
          + " | ".join(str(t[4]) for t in thirds) + " |")
    ratio = f"{thirds[2][0] / thirds[0][0]:.2f}" if thirds[0][0] else "-"
    print(f"\nre-chatters last / first third: {ratio}; first trusted learn before cut {at}; learns trusted "
          f"{len(learned)}, not trusted {len(untrusted)}; model in use at the end: {status['model']}")
    for kind, evs in (("learned", learned), ("not trusted", untrusted)):
        for e in evs:
            print(f"- {kind}: {e['payload']['summary']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
