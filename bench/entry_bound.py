"""How early any detector could tell a cut unstable from its entry from a stable one, on the
simulated lathe: a yardstick for bench_loop.py's "within 3 revolutions + 20 ms of entry".

    .venv/bin/python bench/entry_bound.py [--seeds 8] [--pipeline-ms 5]

Cuts are regen.simulate_cut's with the live simulator's lathe (its modes and Kf), the tool
entering at t = 0, at bench_loop.py's speeds.  Stable cuts: 0.6, 0.8 and 0.9 x the limit
(b_lim at the speed); unstable: bench_loop.py's 3 mm and 1.1 x the limit; ``--seeds`` draws
of each.  Every window of the detectors' grid (one revolution long, half a revolution apart,
the first one revolution after entry since the revolution difference needs one) gives the
gain-invariant measures a detector without a stable reference has:

  residual growth  sync_residual's raw measure over its lowest since entry
  level growth     the window's median |x| over the first window's

The *oracle* knows every stable cut in advance: its threshold at each window is the highest
value any stable cut of the speed reached there (zero margin).  A cut is caught by the
deadline when it is above that envelope at a window ending before 3 revolutions + 20 ms of
entry less the pipeline (alarm -> Modbus write, bench_loop.py's 4-5 ms).  The columns at
the deadline give the margin a real detector would have to live in: the unstable cuts'
values against the envelope at the last window before it.  No detector has the envelope:
it needs the stable cuts' future.  Prints a Markdown table.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from lathed.analysis.chatter.registry import make_detector  # noqa: E402
from lathed.analysis.lobes import StabilityLobes  # noqa: E402
from lathed.analysis.regen import Segment, simulate_cut  # noqa: E402
from lathed.sim.lathe import LATHE_KF, LATHE_MODES  # noqa: E402

SPEEDS = (1500.0, 2000.0, 2500.0)     # bench_loop.py's program
LOOP_DEPTH_MM = 3.0                   # bench_loop.py's cuts
STABLE = (0.6, 0.8, 0.9)              # x the limit
CUT_S = 0.4


def measures(rec, rpm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Window end times (s from entry), residual growth and level growth."""
    det = make_detector("sync_residual", rec.rate_hz, learn_windows=1000)   # all windows: raws only
    raws: list[float] = []
    det._collect = raws
    levels: list[float] = []
    measure = det._measure

    def with_level(start: int, end: int, r: float) -> float:
        levels.append(float(np.median(np.abs(det._x[start:end]))))
        return measure(start, end, r)
    det._measure = with_level
    ts = []
    for i in range(0, len(rec.signal), 512):
        ts += [w.t_s for w in det.process(rec.signal[i:i + 512], rpm)]
    raw = np.array(raws)
    return np.array(ts), raw / np.minimum.accumulate(raw), np.array(levels) / levels[0]


def run(seeds: int, pipeline_s: float) -> list[str]:
    lobes = StabilityLobes(LATHE_MODES, LATHE_KF)
    rows = []
    for rpm in SPEEDS:
        lim_mm = float(lobes.b_lim_at(rpm)[0][0]) * 1e3
        rev = 60.0 / rpm
        deadline = 3 * rev + 0.020 - pipeline_s

        def cuts(depth: float, seed0: int):
            out = []
            for s in range(seeds):
                rec = simulate_cut([Segment(CUT_S, rpm, round(depth, 3))], seed=seed0 + s,
                                   modes=LATHE_MODES, kf_n_per_m2=LATHE_KF)
                out.append((measures(rec, rpm), rec.label))
            return out
        stable = [m for f in STABLE for m, label in cuts(f * lim_mm, 100) if label == "stable"]
        unstable = {f"{LOOP_DEPTH_MM:g} mm": cuts(LOOP_DEPTH_MM, 200),
                    f"{1.1 * lim_mm:.2f} mm (1.1 x)": cuts(1.1 * lim_mm, 300)}
        t = stable[0][0]
        n = min(len(m[0]) for m in stable + [m for v in unstable.values() for m, _ in v])
        last = int(np.searchsorted(t[:n], deadline, side="right")) - 1
        for k, feature in ((1, "residual growth"), (2, "level growth")):
            env = np.max([m[k][:n] for m in stable], axis=0)
            for label, ms in unstable.items():
                vals = np.array([m[k][:n] for m, _ in ms])
                caught = sum(bool(np.any(v[:last + 1] > env[:last + 1])) for v in vals)
                caught10 = sum(bool(np.any(v[:last + 1] > 1.1 * env[:last + 1])) for v in vals)
                at = vals[:, last]
                rows.append(f"| {rpm:g} | {lim_mm:.2f} | {deadline * 1e3:.0f} ({last + 1}) | {feature} | {label} | "
                            f"{env[last]:.2f} | {at.min():.2f}-{at.max():.2f} | {caught}/{len(vals)} | "
                            f"{caught10}/{len(vals)} |")
    return rows


def theory(pipeline_s: float) -> list[str]:
    """The rightmost characteristic root at each depth (StabilityLobes.growth): how fast the
    chatter mode grows or decays, per revolution and from the first regenerating revolution
    (the first revolution cuts a fresh surface) to the deadline."""
    lobes = StabilityLobes(LATHE_MODES, LATHE_KF)
    rows = []
    for rpm in SPEEDS:
        lim = float(lobes.b_lim_at(rpm)[0][0])
        rev = 60.0 / rpm
        span = 3 * rev + 0.020 - pipeline_s - rev
        cells = []
        for depth in (0.9 * lim, 1.1 * lim, LOOP_DEPTH_MM * 1e-3):
            sigma, _ = lobes.growth(rpm, depth)
            cells.append(f"{sigma:+.1f} | {np.exp(sigma * rev):.3f} | {np.exp(sigma * span):.2f}")
        rows.append(f"| {rpm:g} | {lim * 1e3:.2f} | " + " | ".join(cells) + " |")
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=8, help="draws of each depth (default 8)")
    ap.add_argument("--pipeline-ms", type=float, default=5.0,
                    help="alarm -> speed write, taken off the deadline (bench_loop.py: 4-5 ms)")
    args = ap.parse_args(argv)
    if args.seeds < 1:
        print("entry_bound.py: --seeds must be at least 1", file=sys.stderr)
        return 2
    rows = run(args.seeds, args.pipeline_ms / 1e3)
    print(f"Cuts unstable from entry against stable ones ({', '.join(f'{f:g}' for f in STABLE)} x the limit), "
          f"{args.seeds} seeds each; envelope: the highest any stable cut reached at that window\n")
    print("| speed r/min | limit mm | deadline ms (windows by then) | measure | unstable cut | stable envelope "
          "at the deadline | unstable cuts there | above the envelope by the deadline | ... by 10 % |")
    print("|---|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))
    print("\nLinear theory (the rightmost root of the characteristic equation, StabilityLobes.growth): "
          "sigma 1/s, the chatter mode's amplitude ratio per revolution, and from the first "
          "regenerating revolution to the deadline\n")
    print("| speed r/min | limit mm | 0.9 x limit: sigma | per rev | by the deadline | 1.1 x limit: sigma "
          f"| per rev | by the deadline | {LOOP_DEPTH_MM:g} mm: sigma | per rev | by the deadline |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    print("\n".join(theory(args.pipeline_ms / 1e3)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
