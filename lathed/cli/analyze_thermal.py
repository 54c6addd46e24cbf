"""``lathectl analyze thermal``: fit the thermal growth model to a recorded
run, find the effects the static regression lacks, report before/after."""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from typing import TYPE_CHECKING

from lathed.cli import EX_CANTCREAT, EX_DATAERR, count, fail

if TYPE_CHECKING:
    from lathed.analysis.thermal import Analysis, ThermalData
    from lathed.analysis.thermal_csv import LoadReport


def register_analyze(sub) -> None:
    p = sub.add_parser("thermal", help="thermal growth model: effects the regression lacks, error before/after",
                       description="Select the temperature sensors (t_<place>_c) and fit spindle growth "
                                   "(displacement_um) to their rises by least squares, then add the "
                                   "candidate effects (lag, rate, speed, nonlinear, hysteresis, drift, "
                                   "lag of speed, speed x temperature, lag of T - ambient; speed steps "
                                   "and periodic terms from the residual) that lower the error on "
                                   "held-out time. The report compares, on the same rows, the paper's "
                                   "eq. 14, plain least squares, the current and the new model.")
    p.add_argument("train", metavar="TRAIN.csv", help="run to fit on: time_s, [spindle_rpm], "
                                                      "t_<place>_c..., displacement_um")
    held = p.add_mutually_exclusive_group()
    held.add_argument("--test", metavar="TEST.csv", help="another run to report errors on, from a cold start "
                                                         "or continuing TRAIN's time_s "
                                                         "(default: held-out blocks of TRAIN)")
    held.add_argument("--split", metavar="F", type=_fraction,
                      help="fit on the first F of TRAIN by time (0 < F < 1), report on the rest")
    p.add_argument("--model", metavar="CURRENT.toml", help="the model in use, compared on the same rows "
                                                           "(default: the linear regression the loop starts from)")
    p.add_argument("--max-sensors", type=count, default=8, metavar="N",
                   help="at most N temperature sensors in the model (default 8)")
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


def _plot(path: str, a: Analysis, data: ThermalData, label: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    h = (data.time_s - data.t0_s) / 3600.0
    y = data.displacement_um
    lines = [("least squares", a.least_squares, "tab:gray", "--"),
             ("before", a.baseline, "tab:orange", "-"), ("after", a.final, "tab:blue", "-")]
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(11, 7.5), sharex=True, height_ratios=(3, 2))
    ax1.plot(h, y, ".", ms=1.5, color="k", alpha=0.35, zorder=3, label="measured growth")
    for name, st, color, ls in lines:
        if st is not None:
            ax1.plot(h, st.model.predict(data), ls, color=color, lw=1.3,
                     label=f"{name}: {len(st.model.names)} terms, rmse {st.test_rmse_um:.2f} µm")
    ax1.set_ylabel("growth (µm)")
    ax1.set_title(f"thermal growth, {label}")
    ax1.legend(loc="best", fontsize=8)
    ax1.grid(alpha=0.3)
    for name, st, color, ls in lines:
        if st is not None:
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


def run(args) -> int:
    # numpy and scipy only when the command runs: lathectl's other commands start without them
    from lathed.analysis.thermal import analyze, describe, load_model, reference_test, split_run
    from lathed.analysis.thermal_csv import ThermalCsvError, load_thermal_csv

    try:
        train, rep = load_thermal_csv(args.train)
        test, trep = (load_thermal_csv(args.test) if args.test else (None, None))
    except ThermalCsvError as e:
        return fail(str(e), e.exit_code)
    current = None
    if args.model:
        try:
            current = load_model(args.model)
        except (OSError, ValueError, KeyError) as e:
            return fail(f"cannot load thermal model {args.model}: {e}", EX_DATAERR)
    reference_note = None
    if args.split is not None:
        try:
            train, test = split_run(train, args.split)
        except ValueError as e:
            return fail(f"--split {args.split}: {e} ({args.train})", EX_DATAERR)
    elif test is not None:
        missing = [c for c in train.sensors if c not in test.temps_c]
        if missing:
            return fail(f"test file lacks temperature column {missing[0]} that the training file has "
                         f"({args.test}, line 1)", EX_DATAERR)
        try:
            test, reference_note = reference_test(train, test)
        except ValueError as e:
            return fail(f"{e} ({args.test})", EX_DATAERR)
    try:
        a = analyze(train, test, current=current, max_sensors=args.max_sensors)
    except ValueError as e:
        return fail(f"{e} ({args.train})", EX_DATAERR)
    if not (math.isfinite(a.baseline.test_rmse_um) and math.isfinite(a.final.test_rmse_um)):
        # never report "error nan µm" and an effect found on numbers that overflowed
        return fail(f"the fit gave no finite error (values too large to fit together?) ({args.train})",
                     EX_DATAERR)
    if args.split is not None:
        a.judged_on = f"the last {100 * (1 - args.split):.0f} % of {Path(args.train).name} ({len(test)} rows)"
    _warn_rejected(args.train, rep)
    if trep is not None:
        _warn_rejected(args.test, trep)
    if reference_note:
        print(f"lathectl: note: {reference_note}", file=sys.stderr)
    if args.plot:
        label = (f"test {Path(args.test).name}" if args.test else
                 f"last {100 * (1 - args.split):.0f} % of {Path(args.train).name}" if args.split is not None
                 else f"train {Path(args.train).name} (held-out blocks)")
        try:
            _plot(args.plot, a, test if test is not None else train, label)
        except OSError as e:
            return fail(f"cannot write plot {args.plot}: {e.strerror or e}", EX_CANTCREAT)
    where = ("on the test run" if args.test else "on the held-out tail" if args.split is not None
             else "on held-out time blocks")
    if args.json:
        out = a.to_json()
        out["rows"] = rep.to_json()
        if trep is not None:
            out["rows"]["test"] = trep.to_json()
        if reference_note:
            out["test_reference"] = reference_note
        print(json.dumps(out, indent=1))
        return 0
    b, f = a.baseline, a.final
    print(f"before: linear regression on {len(b.model.names)} temperature rise(s), error {b.test_rmse_um:.2f} µm rms {where}")
    if a.effects:
        fall = 100 * (1 - f.test_rmse_um / b.test_rmse_um) if b.test_rmse_um > 0 else 0.0
        found = "; ".join(describe(e.term) for e in a.effects)
        line = f"found: {found}; after: error {f.test_rmse_um:.2f} µm rms ({fall:.0f}% lower)"
    else:
        line = f"found: no effect the regression lacks; after: error {f.test_rmse_um:.2f} µm rms"
    if a.residual.structured:
        line += f" -- {a.residual.note}"
    print(line)
    print(f"compared on the same rows ({a.judged_on}):")
    for c in a.comparison:
        val = f"{c.rmse_um:.2f} µm rms" if c.rmse_um is not None else "n/a"
        print(f"  {c.label}: {val}" + (f" ({c.note})" if c.note else ""))
    if a.sensors:
        print("sensors: " + "; ".join(
            f"{k.sensor}{f' (smoothed {k.smooth_s:g} s)' if k.smooth_s else ''}"
            f"{f' (its own {k.notch_s:g}-s oscillation notched out)' if k.notch_s else ''} "
            f"carries {k.span_um:.1f} µm, "
            f"held-out error +{k.heldout_gain_um:.2f} µm without it" for k in a.sensors))
    for n in a.notes:
        print(f"lathectl: note: {n}", file=sys.stderr)
    return 0
