"""``lathectl analyze lobes``: stability lobe diagram of a turning set-up."""
from __future__ import annotations

import argparse
import json
import math
import sys

from lathed.cli import EX_CANTCREAT, mode, positive, spindle_rpm

# JSON stays readable: each lobe is thinned to at most this many points.
MAX_POINTS_PER_LOBE = 400
MAX_DEPTH_MM = 100.0   # --depth: beyond it the number is a typo, not a cut


def _range(text: str) -> tuple[float, float]:
    parts = text.split(":")
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"range {text!r}: expected MIN:MAX in r/min")
    lo, hi = (spindle_rpm(p) for p in parts)
    if not lo < hi:
        raise argparse.ArgumentTypeError(f"range {text!r}: MIN must be below MAX")
    return lo, hi


def _depth(text: str) -> float:
    d = positive(text)
    if d > MAX_DEPTH_MM:
        raise argparse.ArgumentTypeError(f"depth {text} mm: a turning cut is at most {MAX_DEPTH_MM:g} mm deep")
    return d


def register_analyze(sub) -> None:
    p = sub.add_parser("lobes", help="stability lobes (limiting depth of cut vs spindle speed)",
                       description="Stability lobes for turning from a modal model and the "
                                   "cutting coefficient Kf.")
    p.add_argument("--mode", dest="modes", action="append", type=mode, required=True,
                   metavar="FN,ZETA,K[,THETA_DEG]",
                   help="structural mode: natural frequency Hz, damping ratio, stiffness N/m, "
                        "angle from the surface normal (repeat for several modes)")
    p.add_argument("--kf", type=positive, required=True, metavar="N_PER_M2",
                   help="cutting-force coefficient along the chip-thickness direction")
    p.add_argument("--rpm", type=spindle_rpm, help="also report the limiting depth at this speed")
    p.add_argument("--depth", type=_depth, metavar="MM",
                   help="with --rpm: how fast chatter grows (or a disturbance dies out) at this depth of cut")
    p.add_argument("--range", dest="rpm_range", type=_range, default=(500.0, 6000.0),
                   metavar="MIN:MAX", help="spindle speed range in r/min (default 500:6000)")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.add_argument("--plot", metavar="OUT.png", help="write the lobe diagram as a PNG")
    p.set_defaults(func=run)


def _mm(x: float) -> float | None:
    return round(float(x) * 1e3, 6) if math.isfinite(x) else None


def _thin(a):
    import numpy as np
    if len(a) <= MAX_POINTS_PER_LOBE:
        return a
    return a[np.linspace(0, len(a) - 1, MAX_POINTS_PER_LOBE).round().astype(int)]


def run(args) -> int:
    import numpy as np

    from lathed.analysis.lobes import StabilityLobes

    if args.depth is not None and args.rpm is None:
        print("lathectl: --depth needs --rpm (the growth is at one speed)", file=sys.stderr)
        return 64
    try:
        lobes = StabilityLobes(args.modes, args.kf)
    except ValueError as e:
        print(f"lathectl: {e} (--mode/--kf)", file=sys.stderr)
        return 65
    lo, hi = args.rpm_range
    pieces = lobes.lobes(lo, hi)
    out: dict = {
        "b_lim_min_mm": _mm(lobes.b_lim_min_m),
        "chatter_frequency_hz": round(lobes.chatter_frequency_hz, 3),
        "rpm_range": [lo, hi],
    }
    if args.rpm is not None:
        b, fc = lobes.b_lim_at(args.rpm)
        out["b_lim_mm_at_rpm"] = _mm(b[0])
        out["chatter_frequency_hz_at_rpm"] = None if np.isnan(fc[0]) else round(float(fc[0]), 3)
    if args.depth is not None:
        try:
            sigma, f_root = lobes.growth(args.rpm, args.depth * 1e-3)
        except ArithmeticError as e:
            print(f"lathectl: {e}: the spindle is too slow for the model to say how fast chatter grows "
                  f"(--rpm/--depth)", file=sys.stderr)
            return 65
        out["growth_at_depth"] = {"depth_mm": args.depth, "sigma_per_s": round(sigma, 4),
                                  "per_rev": round(math.exp(sigma * 60.0 / args.rpm), 5),
                                  "frequency_hz": round(f_root, 3)}
    out["lobes"] = [{"k": p.k,
                     "rpm": [round(float(x), 3) for x in _thin(p.rpm)],
                     "b_lim_mm": [round(float(x) * 1e3, 6) for x in _thin(p.b_lim_m)]}
                    for p in pieces]

    if args.plot:
        try:
            _plot(pieces, lobes, args, args.plot)
        except OSError as e:
            print(f"lathectl: cannot write plot: {e.strerror} ({args.plot})", file=sys.stderr)
            return EX_CANTCREAT

    if args.json:
        print(json.dumps(out))
    else:
        print(f"critical depth b_lim,min  {out['b_lim_min_mm']:.4f} mm")
        print(f"chatter frequency         {out['chatter_frequency_hz']:.1f} Hz")
        if args.rpm is not None:
            b = out["b_lim_mm_at_rpm"]
            print(f"b_lim at {args.rpm:g} r/min      "
                  + ("above the plotted range" if b is None else f"{b:.4f} mm"))
        if args.depth is not None:
            print(_growth_line(out["growth_at_depth"], args.rpm))
        print(f"lobes in {lo:g}:{hi:g} r/min   {len(pieces)}")
    return 0


def _growth_line(g: dict, rpm: float) -> str:
    """Chatter's amplitude a revolution later, and how many revolutions to double or halve."""
    per_rev, head = g["per_rev"], f"at {g['depth_mm']:g} mm, {rpm:g} r/min"
    revs = math.log(2) / abs(math.log(per_rev)) if per_rev != 1 else math.inf
    if per_rev > 1:
        return (f"{head}: unstable, chatter at {g['frequency_hz']:.1f} Hz grows x{per_rev:.3f} "
                f"a revolution (doubles in {revs:.1f} revolutions)")
    return (f"{head}: stable, a disturbance at {g['frequency_hz']:.1f} Hz dies out x{per_rev:.3f} "
            f"a revolution (halves in {revs:.1f} revolutions)")


def _plot(pieces, lobes, args, path: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    lo, hi = args.rpm_range
    fig, ax = plt.subplots(figsize=(8, 4.5))
    n = np.linspace(lo, hi, 3000)
    b, _ = lobes.b_lim_at(n)
    for p in pieces:
        ax.plot(p.rpm, p.b_lim_m * 1e3, color="0.75", lw=0.7)
    ax.plot(n, b * 1e3, color="C0", lw=1.5, label="stability limit")
    ax.axhline(lobes.b_lim_min_m * 1e3, color="C3", ls="--", lw=0.8,
               label=f"b_lim,min = {lobes.b_lim_min_m * 1e3:.3f} mm")
    if args.rpm is not None:
        ax.axvline(args.rpm, color="C2", ls=":", lw=1)
    finite = b[np.isfinite(b)]
    top = 4 * lobes.b_lim_min_m * 1e3 if finite.size == 0 else min(finite.max(), 6 * finite.min()) * 1e3
    ax.set_ylim(0, top)
    ax.set_xlim(lo, hi)
    ax.set_xlabel("spindle speed (r/min)")
    ax.set_ylabel("limiting depth of cut (mm)")
    ax.legend(loc="upper left")
    fig.tight_layout()
    try:
        fig.savefig(path, dpi=110)
    finally:
        plt.close(fig)
