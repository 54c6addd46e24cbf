"""``lathectl analyze thermal``: fit the thermal growth model to a recorded
run, find the effects the static regression lacks, report before/after."""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

from lathed.cli import EX_CANTCREAT
from lathed.analysis.thermal import Analysis, ThermalData, analyze
from lathed.analysis.thermal_csv import EX_DATAERR, LoadReport, ThermalCsvError, load_thermal_csv


def register_analyze(sub) -> None:
    p = sub.add_parser("thermal", help="thermal growth model: effects the regression lacks, error before/after",
                       description="Fit spindle growth (displacement_um) to temperature rises "
                                   "(t_<place>_c) by least squares, then add the candidate effects "
                                   "(lag, rate, speed, nonlinear, hysteresis, drift) that lower the "
                                   "error on held-out time blocks.")
    p.add_argument("train", metavar="TRAIN.csv", help="run to fit on: time_s, [spindle_rpm], "
                                                      "t_<place>_c..., displacement_um")
    p.add_argument("--test", metavar="TEST.csv", help="another run to report errors on "
                                                     "(default: held-out blocks of TRAIN)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--plot", metavar="OUT.png", help="measured vs predicted before/after, and residuals")
    p.set_defaults(func=run)


def _fail(msg: str, code: int) -> int:
    print(f"lathectl: {msg}", file=sys.stderr)
    return code


def _warn_rejected(path: str, rep: LoadReport) -> None:
    if rep.rejected:
        parts = ", ".join(f"{n} {r} (first at line {rep.first_line[r]})" for r, n in rep.rejected.most_common())
        print(f"lathectl: warning: {sum(rep.rejected.values())} row(s) of {path} rejected: {parts}",
              file=sys.stderr)


def _describe(e) -> str:
    t = e.term
    where = f" of {t.sensor}" if t.sensor else ""
    p = ", ".join(f"{k} {v}" for k, v in t.params.items())
    return f"{t.effect}{where}" + (f" ({p})" if p else "")


def _plot(path: str, a: Analysis, data: ThermalData, label: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    h = (data.time_s - data.time_s[0]) / 3600.0
    y = data.displacement_um
    before = a.baseline.model.predict(data)
    after = a.final.model.predict(data)
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(10, 7), sharex=True)
    ax1.plot(h, y, ".", ms=2, color="0.6", label="measured")
    ax1.plot(h, before, lw=1.2, label=f"before: {len(a.baseline.model.names)} terms")
    ax1.plot(h, after, lw=1.2, label=f"after: {len(a.final.model.names)} terms")
    ax1.set_ylabel("displacement (µm)")
    ax1.set_title(f"thermal growth, {label}")
    ax1.legend(loc="best", fontsize=8)
    ax2.plot(h, y - before, lw=0.8, label=f"before, rmse {a.baseline.test_rmse_um:.2f} µm")
    ax2.plot(h, y - after, lw=0.8, label=f"after, rmse {a.final.test_rmse_um:.2f} µm")
    ax2.axhline(0, color="k", lw=0.5)
    ax2.set_xlabel("time (h)")
    ax2.set_ylabel("residual (µm)")
    ax2.legend(loc="best", fontsize=8)
    fig.tight_layout()
    try:
        fig.savefig(path, dpi=110)
    finally:
        plt.close(fig)


def run(args) -> int:
    try:
        train, rep = load_thermal_csv(args.train)
        test, trep = (load_thermal_csv(args.test) if args.test else (None, None))
    except ThermalCsvError as e:
        return _fail(str(e), e.exit_code)
    if test is not None:
        missing = [c for c in train.sensors if c not in test.temps_c]
        if missing:
            return _fail(f"test file lacks temperature column {missing[0]} that the training file has "
                         f"({args.test}, line 1)", EX_DATAERR)
    try:
        a = analyze(train, test)
    except ValueError as e:
        return _fail(f"{e} ({args.train})", EX_DATAERR)
    if not (math.isfinite(a.baseline.test_rmse_um) and math.isfinite(a.final.test_rmse_um)):
        # never report "error nan µm" and an effect found on numbers that overflowed
        return _fail(f"the fit gave no finite error (values too large to fit together?) ({args.train})",
                     EX_DATAERR)
    _warn_rejected(args.train, rep)
    if trep is not None:
        _warn_rejected(args.test, trep)
    if args.plot:
        try:
            _plot(args.plot, a, test if test is not None else train,
                  f"test {Path(args.test).name}" if test is not None else f"train {Path(args.train).name}")
        except OSError as e:
            return _fail(f"cannot write plot {args.plot}: {e.strerror or e}", EX_CANTCREAT)
    where = "on the test run" if test is not None else "on held-out time blocks"
    if args.json:
        out = a.to_json()
        out["rows"] = rep.to_json()
        if trep is not None:
            out["rows"]["test"] = trep.to_json()
        print(json.dumps(out, indent=1))
        return 0
    b, f = a.baseline, a.final
    print(f"before: linear regression on {len(b.model.names)} temperature rise(s), error {b.test_rmse_um:.2f} µm rms {where}")
    if a.effects:
        fall = 100 * (1 - f.test_rmse_um / b.test_rmse_um) if b.test_rmse_um > 0 else 0.0
        found = "; ".join(_describe(e) for e in a.effects)
        line = f"found: {found}; after: error {f.test_rmse_um:.2f} µm rms ({fall:.0f}% lower)"
    else:
        line = f"found: no effect the regression lacks; after: error {f.test_rmse_um:.2f} µm rms"
    if a.residual.structured:
        line += f" -- {a.residual.note}"
    print(line)
    for n in a.notes:
        print(f"lathectl: note: {n}", file=sys.stderr)
    return 0
