"""How early any detector could tell a step into chatter from a stable shoulder, on the
simulated lathe: a yardstick for issue 38's "median delay no worse than today's" (2.0 rev).

    .venv/bin/python bench/step_bound.py [--draws 48] [--revs 24] [--seed 30000] [--cases]

Stable steps (the envelope; seeds bench_chatter.py's defaults do not use): the shoulders of
bench_chatter.py's shoulder table (5 seeds each), the part-program features' "shoulder up"
(lathed.analysis.chatter.cases; 1000/2000/3000 r/min, 3 seeds each), and ``--draws`` shoulders
at each speed the corpus's steps into chatter use, from 0.3-0.65 to 0.8-0.9 x the limit; a draw
that chatters is left out.  Steps into chatter: bench_chatter.corpus()'s chatter cases whose depth
steps up at one speed (seeds 1000+i as the bench), with the simulator's "visible" instant.

Every case is measured on one grid aligned to its step: windows as sync_cusum's (one revolution
long, 0.02 s at least; half a revolution apart), the k-th ending k hops after the step, against
the pre-step level (the median of the windows over the 4 revolutions before the step).  The
gain-invariant measures a detector without a reference has:

  level growth     the window's median |x| over the pre-step one
  residual growth  the robust rms of the revolution difference (sync_residual's) over pre-step
  residual rise    ... over its lowest since the step (the shoulder rule's growth out of a step)
  shape            the shape gate's index of the revolution difference's spectrum against the
                   pre-step windows' (chatter.shape: 1 for a change of level alone)
  band share       the strongest 6 % band's share of that spectrum's power (50-5000 Hz): plain

The *oracle* alarms on a step into chatter at the first window whose measure is above the
highest any stable step reached at the same window after its step (zero margin, zero false
alarms on the stable steps by construction); "best" takes the first of the five; "per speed"
takes the envelope of the stable steps at the case's speed only (a detector knows the speed).
Its delay is in revolutions after "visible", as bench_chatter.py's; the corpus's other chatter
cases keep sync_cusum's delay on them (bench_chatter.score), the oracle being about steps only.
No detector has the envelope: it needs the stable steps' future, and a grid that knows where the
step was.  A finite draw's envelope is below the population's, so a zero margin flatters the
oracle: the honesty table holds each stable step against the envelope of the others (leave one
out: the false alarms a new stable step would raise) and gives the oracle's medians with the
envelope times a margin.  Then the physics: growth and decay per revolution of a 1.08 x step
and a 0.87 x shoulder's echo, and how many revolutions tell them apart at the seed-to-seed spread.
"""
from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench_chatter import BLOCK, _cut_spans, corpus, score, shoulder_cases  # noqa: E402

from lathed.analysis.chatter.cases import b_lim_mm, segments as feature_segments  # noqa: E402
from lathed.analysis.chatter.registry import DEFAULT_DETECTOR, make_detector  # noqa: E402
from lathed.analysis.chatter.shape import SpectralShape  # noqa: E402
from lathed.analysis.lobes import StabilityLobes  # noqa: E402
from lathed.analysis.regen import DEFAULT_KF, DEFAULT_MODES, Segment as S, simulate_cut  # noqa: E402

MEASURES = ("level growth", "residual growth", "residual rise", "shape", "band share")
PRE_REVS = 4            # revolutions before the step its level is taken over
MARGINS = (1.0, 1.1, 1.25, 1.5, 2.0)
CORPUS_SEED = 1000      # bench_chatter.py's default seed base


def alarms_in_cuts(det, rec) -> bool:
    """Whether the detector alarms on the recording fed as the daemon and bench_chatter.py's
    part-program table feed it: reset at each cut's entry (the depth register's), fed no air
    (a part-program shoulder starts in air: fed whole, its entry read as a step mid-cut)."""
    for a, b in _cut_spans(rec):
        det.reset()
        for i in range(a, b, BLOCK):
            if any(w.alarm for w in det.process(rec.signal[i:min(i + BLOCK, b)], float(rec.rpm[i]))):
                return True
    return False


def step_of(segs) -> tuple[float, float] | None:
    """(step instant s, speed) of a cut whose depth steps up at one speed, else None."""
    t = 0.0
    for a, b in zip(segs, segs[1:]):
        t += a.duration_s
        if (a.depth_mm > 0 and b.depth_mm > a.depth_mm and a.rpm == b.rpm and not b.ramp_s
                and not b.flat_deg):
            return t, float(a.rpm)
    return None


def rev_difference(x: np.ndarray, spr: float) -> np.ndarray:
    """x(theta) - x(theta - 2 pi) at a constant speed, the fractional delay as the detectors
    take it (RevolutionDetector._delayed); the first revolution nan."""
    di, fr = int(spr), spr - int(spr)
    d = np.full(len(x), np.nan)
    d[di + 1:] = x[di + 1:] - ((1.0 - fr) * x[1:len(x) - di] + fr * x[:len(x) - di - 1])
    return d


def measures(rec, t_step: float, rpm: float, revs: float, params: dict) -> tuple[np.ndarray, np.ndarray]:
    """Window ends (revolutions after the step) and the measures (one row each) of the windows
    on the step's grid up to ``revs`` revolutions after it."""
    rate = rec.rate_hz
    spr = rate * 60.0 / rpm
    w_len = int(max(params["window_revs"] * spr, params["min_window_s"] * rate))
    hop = int(max(params["hop_revs"] * spr, params["min_hop_s"] * rate))
    x = rec.signal
    d = rev_difference(x, spr)
    i0 = int(round(t_step * rate))
    shape = SpectralShape(rate, params["fmin_hz"], params["fmax_hz"])

    def window(end: int) -> tuple[float, float, np.ndarray]:
        return (float(np.median(np.abs(x[end - w_len:end]))),
                1.4826 * float(np.median(np.abs(d[end - w_len:end]))),
                shape.bands(d[end - w_len:end]))

    pre = [window(i0 - j * hop) for j in range(int(PRE_REVS * spr / hop) + 1)]
    lvl0 = float(np.median([p[0] for p in pre]))
    res0 = float(np.median([p[1] for p in pre]))
    for p in pre:
        shape.learn(p[2])
    ends, rows = [], []
    k = 1
    while i0 + k * hop <= len(x) and k * hop <= revs * spr:
        lvl, res, bands = window(i0 + k * hop)
        rows.append([lvl / lvl0, res / res0, res, shape.index(bands), float(bands.max() / bands.sum())])
        ends.append(k * hop / spr)
        k += 1
    out = np.array(rows).T
    out[2] = out[2] / np.minimum.accumulate(out[2])      # over its lowest since the step
    return np.array(ends), out


def stable_steps(draws: int, seed: int, revs: float, speeds) -> list[tuple[str, list, int]]:
    """(name, segments, seed) of the stable steps: the shoulder table's, the part-program
    shoulders up, and ``draws`` drawn shoulders at each speed."""
    out = []
    for j, (nm, segs) in enumerate(shoulder_cases(3.0)):
        if nm.startswith("shoulder"):             # a taper and a step down are no step up
            out += [(nm, segs, seed + 10 * j + k) for k in range(5)]
    for j, rpm in enumerate((1000.0, 2000.0, 3000.0)):
        out += [(f"part-program shoulder up {rpm:.0f} r/min", feature_segments("shoulder up", rpm, 0.8),
                 seed + 100 + 10 * j + k) for k in range(3)]
    rng = np.random.default_rng(seed)
    for j, rpm in enumerate(speeds):
        lim = b_lim_mm(rpm)
        after = max(1.5, (revs + 2) * 60.0 / rpm)
        for k in range(draws):
            lo, hi = rng.uniform(0.3, 0.65), rng.uniform(0.8, 0.9)
            out.append((f"drawn {rpm:.0f} r/min {lo:.2f}->{hi:.2f} x", [S(1.5, rpm, round(lo * lim, 2)),
                        S(after, rpm, round(hi * lim, 2))], seed + 1000 * (j + 1) + k))
    return out


def physics(rpm: float, seeds: int, seed: int, revs: int = 30) -> str:
    """A 1.08 x step into chatter against a 0.87 x shoulder at ``rpm``, ``seeds`` draws of each,
    both stepping 1.74 x in depth (from 0.62 and 0.5 x: the level brings no difference): the
    revolution difference's rms per revolution after the step over the pre-step's; the echo's
    decay and the chatter's growth per revolution fitted to the draws' median, against the
    linear theory's; the stable draws' spread once the echo is gone (the cut's own wander); the
    revolutions 1.08 x needs to grow through it; and where the draws part in fact."""
    lim = b_lim_mm(rpm)
    lobes = StabilityLobes(DEFAULT_MODES, DEFAULT_KF)
    spr = 51200.0 * 60.0 / rpm
    out = {}
    for pre, share in ((0.5, 0.87), (0.62, 1.08)):
        curves = []
        for k in range(seeds):
            rec = simulate_cut([S(1.0, rpm, round(pre * lim, 2)), S((revs + 3) / rpm * 60.0, rpm,
                                round(share * lim, 2))], seed=seed + 20000 + 100 * int(share > 1) + k)
            if rec.label != ("chatter" if share > 1 else "stable"):
                continue
            d = rev_difference(rec.signal, spr)
            i0, n = int(round(1.0 * rec.rate_hz)), int(spr)
            base = float(np.sqrt(np.mean(d[i0 - PRE_REVS * n:i0] ** 2)))
            curves.append([float(np.sqrt(np.mean(d[i0 + r * n:i0 + (r + 1) * n] ** 2))) / base
                           for r in range(revs)])
        out[share] = np.array(curves)
    st, ch = out[0.87], out[1.08]
    med, cmed = np.median(st, axis=0), np.median(ch, axis=0)
    floor = float(np.median(med[revs // 3:]))             # the deeper pass's own level
    top = int(np.argmax(med))
    tail = []                                              # the echo above it, from its peak
    for r in range(top, revs):
        if med[r] - floor < 0.1 * floor:
            break
        tail.append(r)
    q = float(np.exp(np.polyfit(tail, np.log(med[tail] - floor), 1)[0])) if len(tail) >= 2 else float("nan")
    g = float(np.exp(np.polyfit(np.arange(3, revs), np.log(cmed[3:]), 1)[0]))
    theory = [float(np.exp(lobes.growth(rpm, x * lim * 1e-3)[0] * 60.0 / rpm)) for x in (0.87, 1.08)]
    gone = tail[-1] + 1 if tail else top + 1
    spread = float(st[:, gone:].max() / floor)
    need = math.log(spread) / math.log(g) if g > 1 else float("inf")
    half = next((r for r in range(revs) if cmed[r] > st[:, r:].max()), None)
    every = next((r for r in range(revs) if ch[:, r].min() > st[:, r:].max()), None)
    return (f"| {rpm:g} | {len(st)} / {len(ch)} | {med[top]:.1f} at rev {top}, {floor:.1f} from rev {gone} | "
            f"{q:.2f} (theory {theory[0]:.3f}) | {g:.3f} (theory {theory[1]:.3f}) | {spread:.2f} | {need:.0f} | "
            f"{'-' if half is None else half} | {'-' if every is None else every} |")


def fmt(v: float | None) -> str:
    return "-" if v is None else f"{v:+.1f}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=48, help="drawn stable shoulders at each speed (default 48)")
    ap.add_argument("--revs", type=float, default=24.0, help="revolutions after the step looked at (default 24)")
    ap.add_argument("--seed", type=int, default=30000, help="first seed of the stable steps (default 30000)")
    ap.add_argument("--physics-seeds", type=int, default=12, help="draws of each in the physics table (default 12)")
    ap.add_argument("--cases", action="store_true", help="per stable step: its highest value of each measure")
    args = ap.parse_args(argv)
    if args.draws < 0 or args.revs < 2 or args.physics_seeds < 2:
        print("step_bound.py: --draws >= 0, --revs >= 2 and --physics-seeds >= 2", file=sys.stderr)
        return 2
    t0 = time.time()
    params = make_detector(DEFAULT_DETECTOR, 51200.0).params
    # the corpus at the bench's seeds: its steps into chatter, and sync_cusum's delays on the rest
    recs, steps = [], []
    for i, (nm, kind, segs, kw) in enumerate(corpus(3.0)):
        rec = simulate_cut(segs, nm, **{"seed": CORPUS_SEED + i, **kw})
        recs.append((rec, kind))
        st = step_of(segs)
        if kind == "chatter" and rec.label == "chatter" and st is not None:
            steps.append((rec, *st))
    per_case: list = []
    score(DEFAULT_DETECTOR, recs, {}, per_case)
    bench = dict(per_case)
    speeds = sorted({rpm for _, _, rpm in steps})

    stable, dropped, cusum_fa = [], 0, {}
    for nm, segs, seed in stable_steps(args.draws, args.seed, args.revs, speeds):
        rec = simulate_cut(segs, nm, seed=seed)
        if rec.label != "stable":
            dropped += 1
            continue
        t, rpm = step_of(segs)
        stable.append((nm, rpm, *measures(rec, t, rpm, args.revs, params)))
        alarmed = alarms_in_cuts(make_detector(DEFAULT_DETECTOR, rec.rate_hz), rec)
        cusum_fa[rpm] = cusum_fa.get(rpm, 0) + alarmed

    # the stable steps' measures as one array (steps x measures x windows), -inf where none
    kmax = max(m.shape[1] for *_, m in stable)
    sm = np.full((len(stable), len(MEASURES), kmax), -np.inf)
    for i, (*_, m) in enumerate(stable):
        sm[i, :, :m.shape[1]] = np.nan_to_num(m, nan=-np.inf)
    srpm = np.array([r for _, r, _, _ in stable])
    cover = min(len(e) for _, _, e, _ in stable)

    def envelope(rpm: float | None, leave: int = -1) -> np.ndarray:
        """The highest any stable step (at this speed; None: at any; but ``leave``) reached at each window."""
        mask = (srpm == rpm) if rpm is not None else np.ones(len(stable), bool)
        if leave >= 0:
            mask[leave] = False
        return sm[mask].max(axis=0)
    pooled = envelope(None)

    def oracle(e: np.ndarray, m: np.ndarray, env: np.ndarray, after: np.ndarray, vis: float,
               margin: float = 1.0) -> list:
        """Per measure, revolutions from "visible" to the first window over margin x the envelope
        (None: none in the horizon)."""
        n = min(len(e), env.shape[1])
        out = []
        for j in range(len(MEASURES)):
            over = np.flatnonzero((m[j, :n] > margin * env[j, :n]) & after[:n])
            out.append(None if not over.size else float(e[over[0]] - vis))
        return out

    def left_out(per_speed: bool, margin: float) -> int:
        """Stable steps over margin x the envelope of the others (at their speed): the false alarms
        the oracle would raise on a new stable step with an envelope drawn as this one."""
        return sum(bool(np.any(sm[i] > margin * envelope(srpm[i] if per_speed else None, i)))
                   for i in range(len(stable)))

    rows, caught = [], {}
    per_measure = {m: [] for m in MEASURES + ("best", "best, per speed")}
    own_measure = {m: [] for m in MEASURES}         # each measure alone, each speed's own envelope
    measured = []
    for rec, t, rpm in steps:
        e, m = measures(rec, t, rpm, args.revs, params)
        vis = (rec.visible_at_s - t) * rpm / 60.0
        after = (t + e * 60.0 / rpm) >= rec.unstable_at_s      # the bench counts an earlier alarm false
        measured.append((rec, t, rpm, e, m, after, vis))
        cells = oracle(e, m, pooled, after, vis)
        best = min((c for c in cells if c is not None), default=None)
        mine = oracle(e, m, envelope(rpm), after, vis)
        own = min((c for c in mine if c is not None), default=None)
        by = "" if own is None else f" ({MEASURES[mine.index(own)]})"
        caught[rec.name] = best
        end = float(min(e[-1], kmax / 2) - vis)       # not caught: at least the horizon's end
        for name, c in zip(per_measure, cells + [best, own]):
            per_measure[name].append(c if c is not None else end)
        for name, c in zip(MEASURES, mine):
            own_measure[name].append(c if c is not None else end)
        rows.append(f"| {rec.name} | {max(rec.depth_mm) / b_lim_mm(rpm):.2f} | {vis:.0f} | "
                    + " | ".join(fmt(c) for c in cells) + f" | **{fmt(best)}** | {fmt(own)}{by} | "
                    + f"{fmt(bench.get(rec.name))} |")
    others = [v for k, v in bench.items() if k not in caught]
    whole = {name: d + others for name, d in per_measure.items()}
    wall = time.time() - t0

    print(f"Steps into chatter (bench_chatter.corpus(), seeds {CORPUS_SEED}+i) against {len(stable)} stable "
          f"steps (the shoulder table's 4 x 5 seeds, part-program shoulders up 3 x 3, {args.draws} drawn at "
          f"each of {len(speeds)} speeds from 0.3-0.65 to 0.8-0.9 x the limit; seeds from {args.seed}; {dropped} "
          f"drawn that chattered left out; {DEFAULT_DETECTOR} alarms on {sum(cusum_fa.values())} of them: "
          + ", ".join(f"{n} at {r:g}" for r, n in sorted(cusum_fa.items()) if n) + f" r/min), {args.revs:g} "
          f"revolutions after each step (every stable step covers {cover / 2:g}).  The envelope at every window "
          "is the highest any stable step reached there; per speed: any at the case's speed.  Delay: "
          "revolutions from \"visible\" to the oracle's first window over the envelope (negative: before); "
          "'-': not over it in the horizon (counted in the medians as the horizon's end).\n")
    print("| step into chatter | deep x limit | visible (rev after the step) | "
          + " | ".join(MEASURES) + f" | best | best, per-speed envelope | {DEFAULT_DETECTOR} (bench) |")
    print("|---|---|---|" + "---|" * (len(MEASURES) + 3))
    print("\n".join(rows))
    print(f"| **median, {len(steps)} steps** | | | " + " | ".join(
        f"**{statistics.median(d):+.2f}**" for d in per_measure.values())
        + f" | {statistics.median(bench[r.name] for r, _, _ in steps):+.2f} |")
    print(f"| **median, corpus ({len(whole['best'])}: the other {len(others)} at {DEFAULT_DETECTOR}'s)** | | | "
          + " | ".join(f"**{statistics.median(d):+.2f}**" for d in whole.values())
          + f" | {statistics.median(bench.values()):+.2f} |")
    print("| ... each measure alone, each speed's own envelope | | | " + " | ".join(
        f"{statistics.median(d + others):+.2f}" for d in own_measure.values()) + " | | | |")
    for name, label, per_speed in (("best", "the pooled envelope", False),
                                   ("best, per speed", "each speed's own envelope", True)):
        med = statistics.median(whole[name])
        print(f"\nThe oracle's corpus median with {label} (best measure per case): {med:.2f} revolutions: "
              + ("**AT OR UNDER 2.0: THE TARGET IS REACHABLE IN PRINCIPLE** at zero margin on these stable steps"
                 if med <= 2.0 else "over 2.0: with these measures no detector without a false alarm on these "
                 "stable steps reaches it, even knowing their envelope and where the step is")
              + f"; a new stable step crosses such an envelope in {left_out(per_speed, 1.0)} of {len(stable)} "
              "(each against the others').")
    # how honest a zero margin is: each stable step against the others' envelope, and the oracle
    # with a margin over it
    print("\nThe envelope's honesty: each stable step against the envelope of the others (leave one out), and "
          "the oracle with the envelope times a margin (best measure per case; medians in revolutions after "
          "\"visible\", the corpus's other cases at " + DEFAULT_DETECTOR + "'s):\n")
    print("| margin | pooled: stable steps over the others' | steps median | corpus median "
          "| per speed: stable steps over the others' | steps median | corpus median |")
    print("|---|---|---|---|---|---|---|")
    for margin in MARGINS:
        cells = []
        for per_speed in (False, True):
            d = []
            for rec, t, rpm, e, m, after, vis in measured:
                c = [x for x in oracle(e, m, envelope(rpm if per_speed else None), after, vis, margin)
                     if x is not None]
                d.append(min(c) if c else float(min(e[-1], kmax / 2) - vis))
            cells.append(f"{left_out(per_speed, margin)}/{len(stable)} | {statistics.median(d):+.2f} | "
                         f"{statistics.median(d + others):+.2f}")
        print(f"| {margin:g} | " + " | ".join(cells) + " |")
    if args.cases:
        print("\n| stable step | " + " | ".join(f"highest {n}" for n in MEASURES) + " |")
        print("|---|" + "---|" * len(MEASURES))
        for nm, _, _, m in stable:
            print(f"| {nm} | " + " | ".join(f"{np.nanmax(r):.2f}" for r in m) + " |")
    print("\nPhysics, the revolution difference alone: a 1.08 x step into chatter against a 0.87 x shoulder, "
          f"{args.physics_seeds} draws each, both stepping 1.74 x in depth (from 0.62 and 0.5 x); per revolution "
          "after the step its rms over the pre-step's.  The echo's decay: of the stable median's excess over the "
          "deeper pass's own level, fitted from its peak; the growth: of the chatter median from the 3rd revolution; "
          "theory: the characteristic equation's rightmost root (StabilityLobes.growth).  Spread: the stable draws' "
          "highest over their median level once the echo is gone (the cut's own wander); revolutions for 1.08 x "
          "to grow through it: log(spread) / log(growth).  Parted: the first revolution from which the chatter "
          "median (every chatter draw) is above every stable draw from then on.\n")
    print("| speed r/min | draws stable / chatter | stable: echo's peak, own level | 0.87 x: echo's decay per rev "
          "| 1.08 x: growth per rev | spread | revs to grow through it | parted: median | parted: every draw |")
    print("|---|---|---|---|---|---|---|---|---|")
    for rpm in (1000.0, 2000.0, 3000.0):
        print(physics(rpm, args.physics_seeds, args.seed))
    print(f"\n({time.time() - t0:.0f} s wall; the tables above {wall:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
