"""``lathectl analyze thermal``: fit the thermal growth model to recorded runs, find the effects
the static regression lacks, report it beside plain baselines (docs/thermal.md)."""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from typing import TYPE_CHECKING

from lathed.cli import EX_CANTCREAT, EX_DATAERR, count, fail

if TYPE_CHECKING:
    from lathed.analysis.thermal import Analysis
    from lathed.analysis.thermal.csvfile import LoadReport


def register_analyze(sub) -> None:
    p = sub.add_parser("thermal", help="thermal growth model: effects the regression lacks, error before/after",
                       description="Select the temperature sensors (t_<place>_c) and fit spindle growth "
                                   "(displacement_um) to their rises, then add the candidate effects (lag, "
                                   "rate, speed, nonlinear, hysteresis, drift, lag of speed, speed x "
                                   "temperature, lag of T - ambient; speed steps and periodic terms from the "
                                   "residual), every choice judged forward in time. Plain baselines (least "
                                   "squares on all sensors, with the speed, a ridge regression on the "
                                   "temperatures and their lags) are fitted on the same rows; the model "
                                   "handed on is the one of them that predicts the newest training rows "
                                   "best, unless the selected model beats it there by 5 % consistently. "
                                   "The report compares them side by side. See docs/thermal.md.")
    p.add_argument("train", metavar="TRAIN.csv", nargs="+",
                   help="run(s) to fit on, in time order, each from a cold start or continuing the one "
                        "before it: time_s, [spindle_rpm], t_<place>_c..., displacement_um")
    held = p.add_mutually_exclusive_group()
    held.add_argument("--test", metavar="TEST.csv", help="another run to report errors on, from a cold start "
                                                         "or continuing the last TRAIN's time_s "
                                                         "(default: the newest training rows)")
    held.add_argument("--split", metavar="F", type=_fraction,
                      help="fit on the first F of the rows by time (0 < F < 1), report on the rest")
    p.add_argument("--model", metavar="CURRENT.toml", help="the model in use, compared on the same rows")
    p.add_argument("--max-sensors", type=count, default=8, metavar="N",
                   help="at most N temperature sensors in the selected model (default 8)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--plot", metavar="OUT.png", help="growth with each model's prediction, and residuals")
    p.set_defaults(func=run)


def _fraction(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not 0.0 < v < 1.0:
        raise argparse.ArgumentTypeError(f"{v:g}: expected a fraction 0 < F < 1")
    return v


def _warn_rejected(path: str, rep: LoadReport) -> None:
    if rep.ignored_columns:
        # a misspelled spindle_rpm would change the fit without a word
        print(f"lathectl: warning: {path}:1: column(s) {', '.join(map(repr, rep.ignored_columns))} ignored "
              "(known: time_s, spindle_rpm, displacement_um, t_<place>_c)", file=sys.stderr)
    if rep.rejected:
        parts = ", ".join(f"{n} {r} (first at line {rep.first_line[r]})" for r, n in rep.rejected.most_common())
        print(f"lathectl: warning: {sum(rep.rejected.values())} row(s) of {path} rejected: {parts}",
              file=sys.stderr)


def _plot(path: str, a: Analysis, data, label: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    h = (data.time_s - data.t0_s) / 3600.0
    y = data.displacement_um
    best = a.best_baseline("rolling")
    lines = [(f"best baseline: {best.label}", best, "tab:gray", "--"),
             ("selected sensors, linear", a.start, "tab:orange", "-"), ("selected model", a.loop, "tab:blue", "-")]
    if a.final is not a.loop and a.final is not best:
        lines.append((f"handed on: {a.final.label}", a.final, "tab:green", "-"))
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(11, 7.5), sharex=True, height_ratios=(3, 2))
    ax1.plot(h, y, ".", ms=1.5, color="k", alpha=0.35, zorder=3, label="measured growth")
    for name, st, color, ls in lines:
        ax1.plot(h, st.model.predict(data), ls, color=color, lw=1.3,
                 label=f"{name}{' (handed on)' if st is a.final else ''}: rmse {st.test_rmse_um:.2f} µm")
    ax1.set_ylabel("growth (µm)")
    ax1.set_title(f"thermal growth, {label}")
    ax1.legend(loc="best", fontsize=8)
    ax1.grid(alpha=0.3)
    for name, st, color, ls in lines:
        ax2.plot(h, y - st.model.predict(data), ls, color=color, lw=0.8, label=name)
    ax2.axhline(0, color="k", lw=0.5)
    ax2.set_xlabel("time since the cold start (h)")
    ax2.set_ylabel("measured - predicted (µm)")
    ax2.legend(loc="best", fontsize=8)
    ax2.grid(alpha=0.3)
    fig.tight_layout()
    try:
        fig.savefig(path, dpi=110)
    finally:
        plt.close(fig)


def _load(args):
    """The training rows (several runs joined), the test rows, the model in use, the load
    reports and a note on the test's reference; ThermalCsvError or ValueError with the line."""
    from lathed.analysis.thermal import join_runs, load_model, reference_test, split_run
    from lathed.analysis.thermal.csvfile import load_thermal_csv

    runs, reps = [], []
    for path in args.train:
        d, rep = load_thermal_csv(path)
        runs.append((path, d))
        reps.append((path, rep))
    train, notes = join_runs(runs)
    test = None
    if args.split is not None:
        try:
            train, test = split_run(train, args.split)
        except ValueError as e:
            raise ValueError(f"--split {args.split}: {e} ({args.train[-1]})") from None
    elif args.test:
        test, rep = load_thermal_csv(args.test)
        reps.append((args.test, rep))
        missing = [c for c in train.sensors if c not in test.temps_c]
        if missing:
            raise ValueError(f"test file lacks temperature column {missing[0]} that the training file has "
                             f"({args.test}, line 1)")
        try:
            test, note = reference_test(train, test)
        except ValueError as e:
            raise ValueError(f"{e} ({args.test})") from None
        notes += [note] if note else []
    current = None
    if args.model:
        try:
            current = load_model(args.model)
        except (OSError, ValueError, KeyError) as e:
            raise ValueError(f"cannot load thermal model {args.model}: {e}") from None
    return train, test, current, reps, notes


def _print_report(a: Analysis, where: str) -> None:
    from lathed.analysis.thermal import describe
    s, lp, f = a.start, a.loop, a.final
    print(f"before: linear regression on {len(s.model.names)} selected temperature rise(s), error "
          f"{s.test_rmse_um:.2f} µm rms {where}")
    if a.effects:
        fall = 100 * (1 - lp.test_rmse_um / s.test_rmse_um) if s.test_rmse_um > 0 else 0.0
        line = (f"found: {'; '.join(describe(e.term) for e in a.effects)}; selected model: error "
                f"{lp.test_rmse_um:.2f} µm rms ({fall:.0f}% lower)")
    else:
        line = f"found: no effect the regression lacks; selected model: error {lp.test_rmse_um:.2f} µm rms"
    if a.residual.structured:
        line += f" -- {a.residual.note}"
    print(line)
    kind = "a plain baseline" if f.baseline else "the selected model"
    print(f"handed on: {f.label} ({kind}), error {f.test_rmse_um:.2f} µm rms {where}")
    print(f"compared side by side (forward: {a.forward_on}; later: {a.judged_on}):")
    for c in a.comparison:
        fw = f"{c.forward:.2f}" if c.forward is not None else "n/a"
        lt = f"{c.later:.2f}" if c.later is not None else "n/a"
        tag = " [baseline]" if c.baseline else ""
        half = f", later half of the training rows {c.rolling:.2f} µm" if c.rolling is not None else ""
        print(f"  {c.label}{tag}: forward {fw} µm{half}, later {lt} µm rms" + (f" ({c.note})" if c.note else ""))
    if a.sensors:
        print("sensors: " + "; ".join(
            f"{k.sensor}{f' (smoothed {k.smooth_s:g} s)' if k.smooth_s else ''}"
            f"{f' (its own {k.notch_s:g}-s oscillation notched out)' if k.notch_s else ''} "
            f"carries {k.span_um:.1f} µm, forward error +{k.forward_gain_um:.2f} µm without it" for k in a.sensors))


def run(args) -> int:
    # numpy and scipy only when the command runs: lathectl's other commands start without them
    from lathed.analysis.thermal import analyze
    from lathed.analysis.thermal.csvfile import ThermalCsvError

    try:
        train, test, current, reps, ref_notes = _load(args)
    except ThermalCsvError as e:
        return fail(str(e), e.exit_code)
    except ValueError as e:
        return fail(str(e), EX_DATAERR)
    try:
        a = analyze(train, test, current=current, max_sensors=args.max_sensors)
    except ValueError as e:
        return fail(f"{e} ({args.train[-1]})", EX_DATAERR)
    if not (math.isfinite(a.start.test_rmse_um) and math.isfinite(a.final.test_rmse_um)):
        # never report "error nan µm" and an effect found on numbers that overflowed
        return fail(f"the fit gave no finite error (values too large to fit together?) ({args.train[-1]})",
                    EX_DATAERR)
    names = ", ".join(Path(p).name for p in args.train)
    if args.split is not None:
        a.judged_on = f"the last {100 * (1 - args.split):.0f} % of {names} ({len(test)} rows)"
    for path, rep in reps:
        _warn_rejected(path, rep)
    for n in ref_notes:
        print(f"lathectl: note: {n}", file=sys.stderr)
    if args.plot:
        label = (f"test {Path(args.test).name}" if args.test else
                 f"last {100 * (1 - args.split):.0f} % of {names}" if args.split is not None
                 else f"train {names}")
        try:
            _plot(args.plot, a, test if test is not None else train, label)
        except OSError as e:
            return fail(f"cannot write plot {args.plot}: {e.strerror or e}", EX_CANTCREAT)
    where = ("on the test run" if args.test else "on the held-out tail" if args.split is not None
             else "on the newest training rows")
    if args.json:
        out = a.to_json()
        out["rows"] = reps[0][1].to_json()
        if len(args.train) > 1:
            out["rows"]["runs"] = {p: r.to_json() for p, r in reps[:len(args.train)]}
        if args.test:
            out["rows"]["test"] = reps[-1][1].to_json()
        if ref_notes:
            out["test_reference"] = "; ".join(ref_notes)
        print(json.dumps(out, indent=1))
        return 0
    _print_report(a, where)
    for n in a.notes:
        print(f"lathectl: note: {n}", file=sys.stderr)
    return 0
