"""Issue 36 experiment: would handing on a forecast combination beat picking one model?

    .venv/bin/python bench/thermal_combination.py collect real|second|recovery [--cache DIR]
    .venv/bin/python bench/thermal_combination.py rules real second recovery [--cache DIR]

``collect`` runs ``analyze`` once per case (the shared real spindle's two channels split by time at
0.5..0.9 step 0.05; bench_thermal's second-pass cases, 10 pairs each; its effect-recovery cases, 20
pairs each) and keeps every candidate's errors: on the newest training rows (``forward_errors``),
over the later half of the training rows for the baselines (the expanding-window errors behind
``rolling_rmse_um``) and on the held-out rows. ``rules`` then judges each hand-on rule, weights
from the training rows only, against the best baseline on the held-out rows. Rules:

- today: what ``analyze`` hands on (the loop if it beats the best baseline on the newest rows by
  5 % consistently, else the baseline with the least rolling error); best_roll_B: that baseline
- eq_B / eq_BL: equal weights over the baselines / and the loop's model
- trim_*: equal weights over those the best does not beat (``beats``, the loop's 5 %, consistently)
  on the rolling errors (B) or on the newest rows (BL)
- stack_*: weights >= 0 summing to 1 with the least squared error of the combination, on the
  rolling errors (B) or the newest rows (B, BL); invmse_BL_fw: weights 1/MSE on the newest rows
- gate+X: the loop if today's test hands it on, else X; +L: the loop in the average unless the
  best baseline beats it on the newest rows; pick_or_stack: the stack only where it beats the best
  single baseline on the rolling errors as the loop must; eq_top2_B_roll: the two best rolling.
"""

from __future__ import annotations

import itertools
import pickle
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_thermal as bt  # noqa: E402
from lathed.analysis.thermal import analyze, baselines as bl, split_run  # noqa: E402
from lathed.analysis.thermal.csvfile import load_thermal_csv  # noqa: E402
from lathed.analysis.forward import N_FOLDS, beats, forward_folds, rmse  # noqa: E402
from lathed.analysis.thermal.fit import fit_coefficients  # noqa: E402
from lathed.sim.thermal import EFFECTS, generate_run, random_schedule  # noqa: E402

# analyze keeps only each baseline's rolling rms; stacking needs the errors themselves, so the
# function that makes them is replaced by one that also records them (in the order fitted).
_ROLL: list[np.ndarray] = []


def _rolling(X, Xf, y, ridge):
    e = []
    for f in forward_folds(len(y), N_FOLDS):
        c, i = fit_coefficients(Xf[:f.lo], y[:f.lo], ridge)
        e.append(y[f.lo:f.hi] - (X[f.lo:f.hi] @ c + i))
    e = np.concatenate(e)
    _ROLL.append(e)
    return float(np.sqrt(np.mean(e ** 2)))


bl._rolling_rmse = _rolling


def record(tr, te):
    _ROLL.clear()
    t0 = time.perf_counter()
    a = analyze(tr, te)
    secs = time.perf_counter() - t0
    assert len(_ROLL) == len(a.baselines)
    cands = {}
    for s, roll in zip(a.baselines, _ROLL):
        cands[s.model.source] = dict(fw=s.forward_errors, roll=roll,
                                     test=te.displacement_um - s.model.predict(te))
    cands["loop"] = dict(fw=a.loop.forward_errors, roll=None, test=te.displacement_um - a.loop.model.predict(te))
    final = "loop" if not a.final.baseline else a.final.model.source
    return dict(cands=cands, final=final, secs=secs, effects=[e.term.effect for e in a.effects])


def collect(what: str, cache: Path):
    out = {}
    if what == "real":
        splits = [round(0.5 + 0.05 * k, 2) for k in range(9)]
        for split in splits:
            for f in sorted(bt.REAL.glob("spindle_ch*.csv")):
                d, _ = load_thermal_csv(f)
                tr, te = split_run(d, split)
                out[(f.stem.split("_")[-1], split)] = r = record(tr, te)
                print(f.stem, split, r["final"], f"{r['secs']:.0f} s", flush=True)
    elif what == "second":
        seeds = 10
        for case in ("lag+speed", "periodic 20 min", "speed steps", "none", "16 sensors, 4 true"):
            for s in range(1, seeds + 1):
                tr, te = bt._pair(case, s, 8.0)
                out[(case, s)] = r = record(tr, te)
                print(case, s, r["final"], f"{r['secs']:.1f} s", flush=True)
    elif what == "recovery":
        seeds = 20
        for eff in ("none", *EFFECTS):
            effects = () if eff == "none" else (eff,)
            for s in range(1, seeds + 1):
                tr = bt.data(generate_run(random_schedule(s, total_s=8 * 3600), effects, seed=s, noise_um=bt.NOISE_UM))
                te = bt.data(generate_run(random_schedule(s + 100, total_s=8 * 3600), effects, seed=s + 100,
                                          noise_um=bt.NOISE_UM))
                out[(eff, s)] = r = record(tr, te)
                print(eff, s, r["final"], f"{r['secs']:.1f} s", flush=True)
    cache.mkdir(parents=True, exist_ok=True)
    with open(cache / f"{what}.pkl", "wb") as fh:
        pickle.dump(out, fh)


MIN_GAIN = 0.05      # the loop's own min_gain (an effect must lower the error this much)
BASE = ("least_squares", "least_squares_speed", "ridge_lags")


def simplex_ls(E: np.ndarray) -> np.ndarray:
    """w >= 0, sum 1, minimising |E w|: every subset's equality-constrained solution, best feasible."""
    k = E.shape[1]
    G = E.T @ E / len(E)
    best, bw = np.inf, None
    for r in range(1, k + 1):
        for sub in itertools.combinations(range(k), r):
            g = G[np.ix_(sub, sub)] + 1e-12 * np.eye(r)
            w = np.linalg.solve(g, np.ones(r))
            w /= w.sum()
            if np.any(w < -1e-12):
                continue
            v = w @ g @ w
            if v < best:
                best, bw = v, np.zeros(k)
                bw[list(sub)] = w
    return bw


def trimmed(errs: dict[str, np.ndarray]) -> list[str]:
    """Those the best (least rms) does not beat by MIN_GAIN consistently across blocks."""
    b = min(errs, key=lambda k: rmse(errs[k]))
    return [k for k in errs if k == b or not beats(errs[k], errs[b], MIN_GAIN, N_FOLDS).better]


def rules(r) -> dict[str, dict[str, float]]:
    c = r["cands"]
    B = [k for k in BASE if k in c]
    fw = {k: c[k]["fw"] for k in [*B, "loop"]}
    roll = {k: c[k]["roll"] for k in B}
    best_roll = min(B, key=lambda k: rmse(roll[k]))
    best_fw_b = min(B, key=lambda k: rmse(fw[k]))
    loop_wins = beats(fw[best_fw_b], fw["loop"], MIN_GAIN, N_FOLDS).better
    eq = lambda ks: {k: 1 / len(ks) for k in ks}
    out = {"today": {r["final"]: 1.0},
           "best_roll_B": {best_roll: 1.0},
           "eq_B": eq(B),
           "eq_BL": eq([*B, "loop"]),
           "trim_B_roll": eq(trimmed(roll)),
           "trim_BL_fw": eq(trimmed(fw)),
           "gate+eq_B": {"loop": 1.0} if loop_wins else eq(B),
           "gate+trim_B_roll": {"loop": 1.0} if loop_wins else eq(trimmed(roll)),
           }
    # the loop in the average too unless the best baseline beats it on the newest rows
    keepL = not beats(fw["loop"], fw[best_fw_b], MIN_GAIN, N_FOLDS).better
    out["gate+trim_B_roll+L"] = {"loop": 1.0} if loop_wins else eq(trimmed(roll) + (["loop"] if keepL else []))
    out["gate+eq_B+L"] = {"loop": 1.0} if loop_wins else eq(B + (["loop"] if keepL else []))
    w = simplex_ls(np.column_stack([fw[k] for k in [*B, "loop"]]))
    out["stack_BL_fw"] = dict(zip([*B, "loop"], w))
    wb = simplex_ls(np.column_stack([roll[k] for k in B]))
    out["stack_B_roll"] = dict(zip(B, wb))
    out["stack_B_fw"] = dict(zip(B, simplex_ls(np.column_stack([fw[k] for k in B]))))
    top2 = sorted(B, key=lambda k: rmse(roll[k]))[:2]
    out["eq_top2_B_roll"] = eq(top2)
    e_stack = np.column_stack([roll[k] for k in B]) @ wb
    stack_wins = beats(roll[best_roll], e_stack, MIN_GAIN, N_FOLDS).better
    out["pick_or_stack_B_roll"] = dict(zip(B, wb)) if stack_wins else {best_roll: 1.0}
    out["gate+pick_or_stack"] = {"loop": 1.0} if loop_wins else out["pick_or_stack_B_roll"]
    out["gate+stack_B_roll"] = {"loop": 1.0} if loop_wins else dict(zip(B, wb))
    inv = {k: 1 / np.mean(fw[k] ** 2) for k in fw}
    out["invmse_BL_fw"] = {k: v / sum(inv.values()) for k, v in inv.items()}
    return out


def test_err(r, w: dict[str, float]) -> float:
    return rmse(sum(v * r["cands"][k]["test"] for k, v in w.items()))


def evaluate(data):
    rows = {}
    for key, r in data.items():
        bb = min(rmse(r["cands"][k]["test"]) for k in BASE if k in r["cands"])
        loop = rmse(r["cands"]["loop"]["test"])
        rows[key] = {name: test_err(r, w) for name, w in rules(r).items()}
        rows[key]["_best_base"] = bb
        rows[key]["_loop"] = loop
    return rows


def summary(rows, title):
    names = [n for n in next(iter(rows.values())) if not n.startswith("_")]
    print(f"\n### {title}: {len(rows)} cases\n")
    print("| rule | <= best baseline | <= 1.01x | <= 1.05x | worst x best baseline | geo-mean x best baseline | median µm |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for n in names:
        x = np.array([v[n] / v["_best_base"] for v in rows.values()])
        med = np.median([v[n] for v in rows.values()])
        print(f"| {n} | {np.sum(x <= 1.0001)}/{len(x)} | {np.sum(x <= 1.01)}/{len(x)} | {np.sum(x <= 1.05)}/{len(x)} | {x.max():.2f} | {np.exp(np.mean(np.log(x))):.3f} | {med:.2f} |")


def per_case(rows, groups):
    """Per group (e.g. simulated case): count <= best baseline and median µm of each rule."""
    names = [n for n in next(iter(rows.values())) if not n.startswith("_")]
    print("\n| group | best baseline µm | loop µm | " + " | ".join(names) + " |")
    print("|---|---:|---:|" + "---:|" * len(names))
    for g in groups:
        sub = [v for k, v in rows.items() if k[0] == g]
        cells = []
        for n in names:
            ok = sum(v[n] <= v["_best_base"] * 1.0001 for v in sub)
            cells.append(f"{np.median([v[n] for v in sub]):.2f} ({ok}/{len(sub)})")
        print(f"| {g} | {np.median([v['_best_base'] for v in sub]):.2f} | {np.median([v['_loop'] for v in sub]):.2f} | "
              + " | ".join(cells) + " |")


def real_table(rows, rules_shown):
    print("\n| channel | split | best baseline µm | loop µm | " + " | ".join(rules_shown) + " |")
    print("|---|---:|---:|---:|" + "---:|" * len(rules_shown))
    for (ch, split), v in sorted(rows.items(), key=lambda kv: (kv[0][1], kv[0][0])):
        cells = [f"{v[n]:.2f}" + ("" if v[n] <= v["_best_base"] * 1.0001 else f" ({v[n] / v['_best_base']:.2f}x)")
                 for n in rules_shown]
        print(f"| {ch} | {split:.2f} | {v['_best_base']:.2f} | {v['_loop']:.2f} | " + " | ".join(cells) + " |")


def show(what: str, cache: Path):
    if True:
        data = pickle.load(open(cache / f"{what}.pkl", "rb"))
        rows = evaluate(data)
        summary(rows, what)
        if what == "real":
            real_table(rows, ["today", "eq_B", "eq_BL", "trim_B_roll", "stack_B_roll", "stack_BL_fw", "invmse_BL_fw",
                              "gate+eq_B+L"])
            for key in sorted(data, key=lambda k: (k[1], k[0])):
                w = rules(data[key])
                print(key, {n: {k: round(float(x), 2) for k, x in w[n].items() if x > 0} for n in
                            ("stack_B_roll", "stack_BL_fw")})
        else:
            per_case(rows, list(dict.fromkeys(k[0] for k in rows)))


if __name__ == "__main__":
    import argparse
    ap = argparse.ArgumentParser(description="issue 36: forecast combination as the thermal hand-on")
    ap.add_argument("cmd", choices=("collect", "rules"))
    ap.add_argument("what", nargs="+", choices=("real", "second", "recovery"))
    ap.add_argument("--cache", type=Path, default=Path("/tmp/thermal_combination"))
    a = ap.parse_args()
    for w in a.what:
        (collect if a.cmd == "collect" else show)(w, a.cache)
