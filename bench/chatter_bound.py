"""How early a level detector could alarm on the simulated corpus, given each cut's own
steady level in advance: a yardstick for bench_chatter.py's median-delay target.

    .venv/bin/python bench/chatter_bound.py [--seed-bases 100,1000,2000] [--detector sync_cusum]

The corpus is bench_chatter.py's (same seeds).  For every cut the *oracle baseline* is the
median raw measure of its own steady stable cutting: the windows after its first 3
revolutions (and 3 after a speed change or a re-entry) and, for a chatter cut, before it
becomes unstable.  No detector has it: it is the cut's future.  The detector then runs with
that baseline fixed (``set_baseline``) times a margin m, which scales its threshold and CUSUM
allowance alike; each row gives false alarms, misses and the median delay for one m.  The
smallest m with no false alarm is the best that detector's rule can do at zero false alarms
with a perfect baseline.  Cuts unstable from their entry have no stable part and are left
out (they favour no margin: bench_loop.py covers them).  Prints a Markdown table.
"""
from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench_chatter import corpus, run_detector  # noqa: E402

from lathed.analysis.chatter.registry import DEFAULT_DETECTOR, make_detector  # noqa: E402
from lathed.analysis.regen import simulate_cut  # noqa: E402

MARGINS = (1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0)


def steady_level(name: str, rec, kind: str, skip_revs: float) -> tuple[float | None, list[tuple[float, float]]]:
    """Median raw measure of the cut's steady stable windows (None: it has none), and the
    spans (s) left out as not steady: the entry, a speed change, a re-entry."""
    det = make_detector(name, rec.rate_hz, learn_windows=1000)   # all windows learning: raws only
    raws: list[float] = []
    det._collect = raws
    ts = [w.t_s for w in run_detector(det, rec)]
    t = np.array(ts)
    raw = np.array(raws)
    rps = np.array([rec.rpm[min(int(x * rec.rate_hz), len(rec.rpm) - 1)] for x in t]) / 60.0
    ok = np.ones(len(t), bool)
    # a speed change, and a re-entry after more than a revolution out of the cut (not a flat's)
    edges = [0.0] + [i / rec.rate_hz for i in np.flatnonzero(np.abs(np.diff(rec.rpm)) > 0)]
    out = np.flatnonzero(~rec.in_cut)
    spr = rec.rate_hz * 60.0 / float(rec.rpm[0])
    if out.size:
        gaps = np.flatnonzero(np.diff(out) > 1)
        starts, ends = out[np.r_[0, gaps + 1]], out[np.r_[gaps, out.size - 1]]
        edges += [(e + 1) / rec.rate_hz for a, e in zip(starts, ends) if e - a > spr]
    spans = []
    for te in edges:
        i = min(int(te * rec.rate_hz), len(rec.rpm) - 1)
        spans.append((te, te + skip_revs * 60.0 / float(rec.rpm[i])))
        ok &= ~((t > spans[-1][0]) & (t < spans[-1][1]))
    if kind == "chatter" and rec.label == "chatter":
        ok &= t < rec.unstable_at_s
    return (float(np.median(raw[ok])) if ok.sum() >= 4 else None), spans


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed-bases", default="100,1000,2000")
    ap.add_argument("--detector", default=DEFAULT_DETECTOR)
    ap.add_argument("--skip-revs", type=float, default=10.0,
                    help="revolutions after entry, a speed change or a re-entry that are not steady "
                         "cutting: left out of the level, and an alarm raised there is not counted")
    args = ap.parse_args(argv)
    bases = [int(b) for b in args.seed_bases.split(",")]
    rows = {m: [0, 0, []] for m in MARGINS}
    left_out: list[str] = []
    for base in bases:
        for i, (nm, kind, segs, kw) in enumerate(corpus(3.0)):
            rec = simulate_cut(segs, nm, **{"seed": base + i, **kw})
            level, spans = steady_level(args.detector, rec, kind, args.skip_revs)
            if level is None:
                left_out.append(nm)
                continue
            for m in MARGINS:
                det = make_detector(args.detector, rec.rate_hz)
                det.set_baseline(level * m)
                # alarms raised where the cut is not steady (its entry's ring, a speed change) are
                # the settling rules' business, not the margin's
                onsets = [w.t_s for w in run_detector(det, rec) if w.raised_by
                          and not any(a < w.t_s < b for a, b in spans)]
                chatter = kind == "chatter" and rec.label == "chatter"
                if onsets and (not chatter or onsets[0] < rec.unstable_at_s):
                    rows[m][0] += 1
                if chatter:
                    first = next((t for t in onsets if t >= rec.unstable_at_s), None)
                    if first is None:
                        rows[m][1] += 1
                    else:
                        rps = float(rec.rpm[min(int(rec.visible_at_s * rec.rate_hz), len(rec.rpm) - 1)]) / 60.0
                        rows[m][2].append((first - rec.visible_at_s) * rps)
    print(f"{args.detector} with each cut's own steady level as a fixed baseline x margin, alarms raised "
          f"in the {args.skip_revs:g} revolutions after entry, a speed change or a re-entry not counted; corpus of "
          f"bench_chatter.py at seed bases {', '.join(map(str, bases))} ({len(left_out)} cuts with no stable "
          f"part left out: {'; '.join(sorted(set(left_out)))})\n")
    print("| margin | false alarms | missed | median delay (rev) |")
    print("|---|---|---|---|")
    for m, (fa, miss, d) in rows.items():
        print(f"| {m:g} | {fa} | {miss} | {statistics.median(d) if d else float('nan'):.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
