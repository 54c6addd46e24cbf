"""Thermal residual loop: time to analyse 3000 rows, and effect recovery.

    .venv/bin/python bench/bench_thermal.py [--seeds N] [--repeats R]

Prints Markdown: (1) the median time of ``analyze`` on a 3000-row run
(5 h at one row per 6 s, as in the paper), against the plain baseline fit in
the same process; (2) for each simulated effect (and none) over N train/test
pairs with different speed schedules: how often the right effect is named
first, the median test error before/after and its fall, and how many pairs
meet the issue's bar (named and >= 60 % fall; for none: nothing added and the
test error within 10 % of the probe noise).
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from lathed.analysis.thermal import ThermalData, analyze, baseline_terms, fit_coefficients, _design
from lathed.sim.thermal import EFFECTS, generate_run, random_schedule

NOISE_UM = 0.5


def data(run) -> ThermalData:
    c = run.columns
    return ThermalData(c["time_s"], {k: v for k, v in c.items() if k.startswith("t_")},
                       c["displacement_um"], c["spindle_rpm"])


def bench_time(repeats: int) -> None:
    tr = data(generate_run(random_schedule(11, total_s=18300), ("lag",), seed=11)).slice(0, 3000)
    n = len(tr)

    def base():
        terms, _ = baseline_terms(tr)
        fit_coefficients(_design(tr, terms), tr.displacement_um)

    rows = []
    for name, f in (("baseline least squares only", base), ("full residual loop (analyze)", lambda: analyze(tr))):
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            f()
            ts.append(time.perf_counter() - t0)
        rows.append((name, statistics.median(ts)))
    print(f"## Time to analyse {n} rows (median of {repeats})\n")
    print("| step | median s | x baseline |")
    print("|---|---:|---:|")
    for name, t in rows:
        print(f"| {name} | {t:.3f} | {t / rows[0][1]:.0f} |")
    print(f"\ntarget < 2 s: {'met' if rows[1][1] < 2.0 else 'NOT met'}\n")


def bench_recovery(seeds: int) -> None:
    print(f"## Effect recovery, {seeds} train/test pairs (train seed s, test seed s+100, 5 h each, "
          f"probe noise {NOISE_UM} µm)\n")
    print("| effect in data | named first | median test rmse before µm | after µm | median fall | "
          "meets bar | effects added (per pair) |")
    print("|---|---:|---:|---:|---:|---:|---|")
    for eff in ("none", *EFFECTS):
        effects = () if eff == "none" else (eff,)
        named = ok = 0
        before, after, falls, added = [], [], [], []
        for s in range(1, seeds + 1):
            tr = data(generate_run(random_schedule(s), effects, seed=s, noise_um=NOISE_UM))
            te = data(generate_run(random_schedule(s + 100), effects, seed=s + 100, noise_um=NOISE_UM))
            a = analyze(tr, te)
            names = [e.term.effect for e in a.effects]
            b, f = a.baseline.test_rmse_um, a.final.test_rmse_um
            before.append(b)
            after.append(f)
            falls.append(1 - f / b)
            added.append("+".join(names) or "-")
            if eff == "none":
                named += not names
                ok += (not names) and f <= 1.1 * NOISE_UM
            else:
                named += names[:1] == [eff]
                ok += names[:1] == [eff] and 1 - f / b >= 0.6
        label = "nothing added" if eff == "none" else "named first"
        print(f"| {eff} | {named}/{seeds} ({label}) | {np.median(before):.2f} | {np.median(after):.2f} | "
              f"{100 * np.median(falls):.0f} % | {ok}/{seeds} | {' '.join(added)} |")
    print()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--repeats", type=int, default=7)
    a = ap.parse_args()
    bench_time(a.repeats)
    bench_recovery(a.seeds)


if __name__ == "__main__":
    main()
