"""Stability refit: effect recovery per undeclared effect, and refit time.

    .venv/bin/python bench/bench_stability.py [--seeds N] [--cuts C] [--repeats R]

The given model is the simulator's lathe (regen.DEFAULT_MODES, DEFAULT_KF);
the cuts come from true dynamics that differ from it by one undeclared effect
(lathed.analysis.stability_cases: the dominant mode 12 % higher, a missing
mode at 950 Hz, process damping 20/n, Kf 45 % higher) or by none.  Labels are
the true lobes with the documented noise model (the limit a cut meets scatters
5 % log-normal, chatter frequencies 0.5 %), C cuts per data set in random
order over 300-6000 r/min and 0.5-2.5x the given critical depth; the refit
fits on the first 70 % and is judged on the last 30 %.

Prints Markdown: per effect over N seeds, how often the right effect is named
first (for none: nothing added) and how often nothing else is, the median held-out accuracy and false-stable
rate (share of held-out cuts called stable that chattered) before/after, and
how many data sets meet the issue's bar (named, accuracy >= 90 %, false stable
<= 5 % after; for none: nothing added); then the median time of one refit on
1,000 cuts.  Then the same refit on cuts labelled by running each through the
regenerative simulator (for the effects it can represent), with the share of
its labels that agree with the true lobes.
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from lathed.analysis.stability_cases import GIVEN, UNDECLARED, generate_cuts, simulate_labels, true_dynamics
from lathed.analysis.stability_refit import refit


def bench_recovery(seeds: int, n_cuts: int) -> int:
    print(f"## Effect recovery, {seeds} data sets of {n_cuts} cuts per effect "
          f"(fit on the first 70 %, judged on the last 30 %)\n")
    print("| undeclared effect | named first | nothing else added | held-out accuracy before | after | "
          "false stable before | after | chatter-frequency error before Hz | after Hz | meets bar |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    misses = []
    for eff in ("none", *UNDECLARED):
        named = only = ok = 0
        acc_b, acc_a, fs_b, fs_a, fe_b, fe_a = [], [], [], [], [], []
        for s in range(seeds):
            r = refit(GIVEN, generate_cuts(true_dynamics(eff), n_cuts, seed=1000 + s))
            names = [e.effect.name for e in r.effects]
            right = names == [] if eff == "none" else names[:1] == [eff]
            named += right
            only += names == ([] if eff == "none" else [eff])
            good = right and (eff == "none" or (r.after.accuracy >= 0.9 and r.after.false_stable_rate <= 0.05))
            ok += good
            if not good:
                misses.append(f"{eff} seed {1000 + s}: added {names or 'nothing'}, accuracy "
                              f"{100 * r.before.accuracy:.1f} -> {100 * r.after.accuracy:.1f} %, false stable "
                              f"{100 * r.after.false_stable_rate:.1f} %")
            acc_b.append(r.before.accuracy)
            acc_a.append(r.after.accuracy)
            fs_b.append(r.before.false_stable_rate)
            fs_a.append(r.after.false_stable_rate)
            fe_b.append(r.before.freq_mae_hz or 0.0)
            fe_a.append(r.after.freq_mae_hz or 0.0)
        med = statistics.median
        print(f"| {eff} | {named}/{seeds} | {only}/{seeds} | {100 * med(acc_b):.1f} % | {100 * med(acc_a):.1f} % | "
              f"{100 * med(fs_b):.1f} % | {100 * med(fs_a):.1f} % | {med(fe_b):.1f} | {med(fe_a):.1f} | "
              f"{ok}/{seeds} |")
    print()
    for m in misses:
        print(f"- miss: {m}")
    total = seeds * (1 + len(UNDECLARED))
    print(f"\ndata sets meeting the bar: {total - len(misses)}/{total}\n")
    return len(misses)


def bench_simulated(n_cuts: int) -> None:
    print(f"## Labels from the regenerative simulator, {n_cuts} cuts per effect\n")
    print("Each cut run through regen.simulate_cut with the true dynamics (15 revolutions, at least 0.3 s, "
          "20 kHz): chatter when its waviness grows visible, the frequency the spectral peak of the tool "
          "vibration. The simulator has no process damping, so that effect is left out.\n")
    print("| undeclared effect | labels as the true lobes | effects added | held-out accuracy before | after | "
          "false stable before | after | chatter-frequency error before Hz | after Hz | simulating s |")
    print("|---|---:|---|---:|---:|---:|---:|---:|---:|---:|")
    for eff in ("none", "natural_frequency", "second_mode", "cutting_coefficient"):
        true = true_dynamics(eff)
        lobe = generate_cuts(true, n_cuts, seed=2000, boundary_sigma=0.0)
        t0 = time.perf_counter()
        cuts = simulate_labels(true, lobe, seed=2000)
        ts = time.perf_counter() - t0
        r = refit(GIVEN, cuts)
        fb, fa = r.before.freq_mae_hz or 0.0, r.after.freq_mae_hz or 0.0
        print(f"| {eff} | {100 * np.mean(cuts.chatter == lobe.chatter):.1f} % | "
              f"{', '.join(e.effect.name for e in r.effects) or '-'} | {100 * r.before.accuracy:.1f} % | "
              f"{100 * r.after.accuracy:.1f} % | {100 * r.before.false_stable_rate:.1f} % | "
              f"{100 * r.after.false_stable_rate:.1f} % | {fb:.1f} | {fa:.1f} | {ts:.0f} |")
    print()


def bench_time(repeats: int) -> None:
    print(f"## Time of one refit on 1,000 cuts (median of {repeats})\n")
    print("| undeclared effect | refit s | effects added |")
    print("|---|---:|---|")
    for eff in ("none", "second_mode", "process_damping"):
        cuts = generate_cuts(true_dynamics(eff), 1000, seed=7)
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            r = refit(GIVEN, cuts)
            ts.append(time.perf_counter() - t0)
        print(f"| {eff} | {np.median(ts):.2f} | {', '.join(e.effect.name for e in r.effects) or '-'} |")
    print()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--cuts", type=int, default=1000, help="cuts per data set")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--sim-cuts", type=int, default=500, help="cuts per effect labelled by the simulator (0: skip)")
    ap.add_argument("--skip-time", action="store_true")
    a = ap.parse_args()
    bench_recovery(a.seeds, a.cuts)
    if a.sim_cuts:
        bench_simulated(a.sim_cuts)
    if not a.skip_time:
        bench_time(a.repeats)


if __name__ == "__main__":
    main()
