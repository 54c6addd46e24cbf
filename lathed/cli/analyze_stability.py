"""``lathectl analyze stability``: check the stability lobes against cuts,
find the effect the modal model lacks, report before/after; with no modal
model given, learn one from the cuts alone (docs/stability.md).

    lathectl analyze stability CUTS.csv [--mode FN,ZETA,K[,THETA_DEG] ... --kf KF]
        [--machine M] [--tool T] [--material X] [--holdout 0.3] [--plot OUT.png] [--json]

CUTS.csv is the cut-record format of lathed.analysis.cuts.  The earlier cuts
(file order) are fitted on, the last ``--holdout`` share judges.
Exit: 0 ok, 2 usage, 66 file missing/unreadable, 65 data invalid, 73 plot
cannot be written.
"""
from __future__ import annotations

import argparse
import json
import sys

from lathed.cli import EX_CANTCREAT, EX_DATAERR, fail, mode, positive

# misclassified cuts listed in the text report (the JSON has them all)
MAX_LISTED = 10


def _fraction(text: str) -> float:
    v = positive(text)
    if not v < 1:
        raise argparse.ArgumentTypeError(f"{text} must be a share between 0 and 1 (e.g. 0.3)")
    return v


def register_analyze(sub) -> None:
    p = sub.add_parser("stability", help="stability lobes against recorded cuts: the effect the model lacks, "
                                         "accuracy before/after; without --mode, a model learned from the cuts",
                       description="Classify recorded cuts with the stability lobes of a modal model, then add "
                                   "the candidate effects (natural frequency, damping, cutting coefficient, "
                                   "second mode, process damping) that classify held-out cuts better. Without "
                                   "--mode, learn the model from the cuts alone (chatter frequencies and depths) "
                                   "and say how sure it is.")
    p.add_argument("cuts", metavar="CUTS.csv", help="cut records: machine, tool, material, rpm, depth_mm, "
                                                     "feed_mm_rev, outcome, [chatter_frequency_hz]")
    p.add_argument("--mode", dest="modes", action="append", type=mode, metavar="FN,ZETA,K[,THETA_DEG]",
                   help="structural mode: natural frequency Hz, damping ratio, stiffness N/m, "
                        "angle from the surface normal (repeat for several modes); none: learned from the cuts")
    p.add_argument("--kf", type=positive, metavar="N_PER_M2",
                   help="cutting-force coefficient along the chip-thickness direction (needed with --mode; "
                        "learning takes 2e9 unless given: the cuts show only stiffness / Kf)")
    p.add_argument("--machine", help="use only the cuts of this machine")
    p.add_argument("--tool", help="use only the cuts of this tool")
    p.add_argument("--material", help="use only the cuts in this material")
    p.add_argument("--holdout", type=_fraction, default=0.3, metavar="SHARE",
                   help="share of the latest cuts held out to judge the refit (default 0.3)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--plot", metavar="OUT.png", help="old and new lobes with the cuts on them")
    p.set_defaults(func=run)


def _select(cuts, args):
    import numpy as np
    keep = np.ones(len(cuts), bool)
    for col in ("machine", "tool", "material"):
        want = getattr(args, col)
        if want is not None:
            keep &= np.array([v == want for v in getattr(cuts, col)])
    return cuts.take(keep)


def _pct(x: float) -> str:
    return f"{100 * x:.1f} %"


def _stage(label: str, r) -> str:
    f = "no chatter frequency measured" if r.freq_mae_hz is None else \
        f"chatter frequency off by {r.freq_mae_hz:.1f} Hz (median of {r.freq_n})"
    return (f"{label}: held-out accuracy {_pct(r.accuracy)}, false stable {_pct(r.false_stable_rate)} "
            f"({r.false_stable} of {r.n} called stable chattered), {f}")


def run(args) -> int:
    from lathed.analysis.cuts import CutsCsvError, load_cuts_csv
    from lathed.analysis.stability import StabilityModel, refit
    try:
        cuts = load_cuts_csv(args.cuts)
    except CutsCsvError as e:
        for line in e.lines:
            print(f"lathectl: {line}", file=sys.stderr)
        return e.exit_code
    if cuts.ignored_columns:
        # a misspelled optional column (chatter_freq_hz) would silently change the report
        from lathed.analysis.cuts import OPTIONAL, REQUIRED
        print(f"lathectl: warning: {args.cuts}:1: column(s) {', '.join(map(repr, cuts.ignored_columns))} "
              f"ignored (known: {', '.join(REQUIRED + OPTIONAL)})", file=sys.stderr)
    cuts = _select(cuts, args)
    if len(cuts) == 0:
        return fail(f"no cut in {args.cuts} matches --machine/--tool/--material", EX_DATAERR)
    setups = cuts.setups()
    if len(setups) > 1:
        names = ", ".join("/".join(s) for s in setups[:4]) + (", ..." if len(setups) > 4 else "")
        return fail(f"{args.cuts} holds cuts of {len(setups)} set-ups (machine/tool/material: {names}): one "
                     f"modal model fits one set-up; choose with --machine, --tool, --material", EX_DATAERR)
    if not args.modes:
        return _learn(args, cuts, setups[0])
    if args.kf is None:
        return fail("--kf is needed with --mode (the cutting coefficient the modal model is for)", 2)
    try:
        base = StabilityModel(tuple(args.modes), args.kf)
        r = refit(base, cuts, holdout_fraction=args.holdout)
    except ValueError as e:
        return fail(f"{e} ({args.cuts})", EX_DATAERR)
    if args.plot:
        curves = [(r.base, f"given model, held-out accuracy {_pct(r.before.accuracy)}", "given")]
        if r.effects:
            names = ", ".join(e.effect.name.replace("_", " ") for e in r.effects)
            curves.append((r.model, f"refit (+ {names}), held-out accuracy {_pct(r.after.accuracy)}", "fit"))
        try:
            _plot(args.plot, r.train, r.heldout, curves, setups[0])
        except OSError as e:
            return fail(f"cannot write plot {args.plot}: {e.strerror or e}", EX_CANTCREAT)
    if args.json:
        out = {"source": args.cuts, "setup": dict(zip(("machine", "tool", "material"), setups[0])), **r.to_json()}
        print(json.dumps(out, indent=1))
        return 0
    print(f"cuts: {len(cuts)} of {'/'.join(setups[0])} from {args.cuts}: fitted on the first {len(r.train)}, "
          f"judged on the last {len(r.heldout)}")
    print(_stage("before", r.before))
    if r.effects:
        for e in r.effects:
            print(f"found: {e.description} (held-out errors {e.heldout_errors_before} -> "
                  f"{e.heldout_errors_after}, kept by {e.kept_by})")
    else:
        print(f"found: {r.conclusion}")
    print(_stage("after", r.after))
    for s in r.rejected:
        print(f"not added: {s}")
    a = r.before_all
    if a.misses:
        print(f"misclassified by the given model: {len(a.misses)} of {a.n} cuts"
              + (f" (first {MAX_LISTED})" if len(a.misses) > MAX_LISTED else ""))
        for m in a.misses[:MAX_LISTED]:
            lim = "above every lobe" if m.limit_mm is None else f"limit {m.limit_mm:.3f} mm"
            if m.speed_margin_rpm is not None:
                sp = f"the model gets it right {m.speed_margin_rpm:+.0f} r/min away"
            else:
                sp = f"the model calls this depth {'stable' if m.outcome == 'chatter' else 'chatter'} at every speed"
            print(f"  line {m.line}: {m.rpm:.0f} r/min, {m.depth_mm:.3f} mm {m.outcome}; {lim}"
                  + ("" if m.depth_margin_mm is None else f" (depth {m.depth_margin_mm:+.3f} mm from it)")
                  + f"; {sp}")
    if a.freq_unexplained:
        import numpy as np
        print(f"chatter at a frequency no configured mode explains: {len(a.freq_unexplained)} cut(s), "
              f"median {float(np.median(a.freq_unexplained)):.1f} Hz")
    return 0


def _learn(args, cuts, setup) -> int:
    """No modal model given: the model from the cuts alone, how sure it is, and its speeds
    only when it is trusted."""
    from lathed.analysis.stability.learn import learn
    from lathed.analysis.stability.start import DEFAULT_KF
    kf = args.kf or DEFAULT_KF
    try:
        lr = learn(cuts, kf=kf, holdout_fraction=args.holdout)
    except ValueError as e:
        return fail(f"{e} ({args.cuts})", EX_DATAERR)
    if lr.model is None:
        return fail(f"no model learned from {args.cuts}: {'; '.join(lr.why_not)}"
                    + (f" (about {lr.cuts_needed} cut speeds needed)" if lr.cuts_needed else ""), EX_DATAERR)
    if args.plot:
        later = cuts.take(range(lr.train, len(cuts)))
        try:
            _plot(args.plot, cuts.take(range(lr.train)), later,
                  [(lr.model, f"learned from the cuts ({'trusted' if lr.trusted else 'not trusted'}), "
                              f"accuracy on the later cuts {_pct(lr.after.accuracy)}", "fit")], setup)
        except OSError as e:
            return fail(f"cannot write plot {args.plot}: {e.strerror or e}", EX_CANTCREAT)
    if args.json:
        print(json.dumps({"source": args.cuts, "setup": dict(zip(("machine", "tool", "material"), setup)),
                          "learned": lr.to_json()}, indent=1))
        return 0
    print(f"cuts: {len(cuts)} of {'/'.join(setup)} from {args.cuts}: no modal model given, learned from the "
          f"first {lr.train} cuts alone (Kf {kf:.3g} N/m^2 taken: the cuts show stiffness / Kf), judged on the "
          f"last {lr.heldout}")
    for i, m in enumerate(lr.model.modes):
        print(f"mode {i + 1}: {m.fn_hz:.1f} Hz, zeta {m.zeta:.4f}, k {m.k_n_per_m:.3g} N/m")
    if lr.model.process_damping:
        print(f"process damping: added damping ratio {lr.model.process_damping:.3g}/n")
    print(f"the limit scatters {100 * lr.sigma:.1f} % from cut to cut (fitted)")
    print(_stage("start", lr.start))
    for e in lr.effects:
        print(f"found: {e.description} (held-out errors {e.heldout_errors_before} -> {e.heldout_errors_after}, "
              f"kept by {e.kept_by})")
    print(_stage("learned", lr.after) + f"; a depth threshold ({lr.baseline.depth_mm:.3f} mm): accuracy "
          f"{_pct(lr.baseline.accuracy)}, false stable {_pct(lr.baseline.false_stable_rate)}")
    b = lr.b_min_mm
    print(f"minimum stable depth: {b.value:.3f} mm (90 %: {b.lo:.3f}-{b.hi:.3f}) over "
          f"{lr.rpm_range[0]:.0f}-{lr.rpm_range[1]:.0f} r/min")
    if lr.trusted:
        for p in lr.pockets:
            print(f"best speed: {p.rpm.value:.0f} r/min (90 %: {p.rpm.lo:.0f}-{p.rpm.hi:.0f}), limit "
                  f"{p.limit_mm:.3f} mm")
        if not lr.pockets:
            print("best speed: no pocket in this speed range rises above the lobes' floor")
        print("trusted: classifies the later cuts well, no worse than a depth threshold, and its intervals are narrow")
    else:
        for w in lr.why_not:
            print(f"not trusted: {w}")
        print(f"no speed recommended from a model not trusted; about {lr.cuts_needed} cut speeds in all would "
              f"settle it")
    return 0


def _plot(path: str, train, heldout, curves, setup) -> None:
    """The cuts (fitted on, held out) with each of ``curves``: (model, label, "given" | "fit")."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker
    import numpy as np

    rpm = np.r_[train.rpm, heldout.rpm]
    depth = np.r_[train.depth_mm, heldout.depth_mm]
    chatter = np.r_[train.chatter, heldout.chatter]
    held = np.r_[np.zeros(len(train), bool), np.ones(len(heldout), bool)]
    lo, hi = rpm.min() / 1.05, rpm.max() * 1.05
    n = np.geomspace(lo, hi, 3000)
    fig, ax = plt.subplots(figsize=(10, 6.2))
    for model, label, kind in curves:
        b, _ = model.limit(n)
        if kind == "given":
            ax.plot(n, b * 1e3, color="0.45", lw=1.3, ls="--", label=label)
        else:
            ax.plot(n, b * 1e3, color="C0", lw=1.8, label=label)
    for ch, mk, col, name in ((False, "o", "C2", "stable"), (True, "x", "C3", "chatter")):
        for h, alpha in ((False, 0.35), (True, 0.9)):
            sel = (chatter == ch) & (held == h)
            if sel.any():
                ax.scatter(rpm[sel], depth[sel], marker=mk, s=18, color=col, alpha=alpha, lw=1.2,
                           facecolors="none" if mk == "o" else None,
                           label=f"{name} cut ({'held out' if h else 'fitted on'})")
    ax.set_xscale("log")
    ax.set_xlim(lo, hi)
    # plain r/min numbers, not powers of ten
    ticks = [t for t in (50, 100, 200, 300, 500, 700, 1000, 1500, 2000, 3000, 4000, 5000, 6000, 8000,
                         10000, 15000, 20000, 30000, 50000) if lo <= t <= hi]
    if len(ticks) >= 2:
        ax.set_xticks(ticks, [f"{t:g}" for t in ticks])
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_ylim(0, 1.15 * depth.max())
    ax.set_xlabel("spindle speed (r/min, log scale)")
    ax.set_ylabel("depth of cut (mm)")
    ax.set_title(f"stability lobes and cuts, {'/'.join(setup)}")
    ax.grid(True, which="both", color="0.9", lw=0.5)
    # below the axes: cuts fill the whole diagram
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=3, fontsize=8, frameon=False)
    fig.tight_layout()
    try:
        fig.savefig(path, dpi=110)
    finally:
        plt.close(fig)
