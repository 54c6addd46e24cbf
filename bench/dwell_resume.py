"""Chatter as the feed resumes after a dwell against a depth step mid-pass: visible and alarmed when.

The chatter analyzer alarms later after a dwell's resume than after a depth step mid-pass:
is the delay the detector's or the cut's?

    .venv/bin/python bench/dwell_resume.py [--seeds 5] [--speeds 1500 2000 2500]

One pass on the simulated lathe (lathed.sim.lathe.SimLathe, 0.3 mm/rev), 1 mm deep (stable)
for its first half (1.6 s of cutting), then 3 mm (above the limit, ~2.4 mm at the default speeds)
for 1.6 s more, in three ways:

  dwell 1 s, step at resume   the program's G04 at the pass's middle (``Cut(dwell_s=1)``): the
                              feed stands 1 s with the tool in the work, and the depth is 3 mm
                              from the instant the feed resumes
  no dwell, abrupt step       the depth steps to 3 mm at the pass's middle, the feed going on
  no dwell, ramp 8 rev        the depth rises 1 -> 3 mm over 8 revolutions from the middle
                              (in 64-sample steps: no force step)

The real ChatterAnalyzer (plugins/chatter.py, the shipped config's detector and keys:
sync_cusum, cut_from feed/load/vibration, dwell_axes, dwell_max 2 s) is fed the lathe's 20 ms
frames and its registers every 100 ms, as tests/test_cut_state.py's dwell tests feed it.  Its
alarm is the published ``chatter_alarm`` sample (tapped off the bus).  Chatter is *visible*
by regen's rule (lathed.analysis.regen.wav_rev, VISIBLE_WAVINESS_M): the surface's waviness
over a revolution >= 2 um rms and not shrinking over the next two, revolutions counted from
the step.  All times are from the step (the resume; the ramp's start), in s and in spindle
revolutions.  False alarms: the analyzer's alarms before the step (the pass's entry, its
first half, the dwell), counted over all the seeds.

Why: after a dwell the chip regrows over a revolution as the feed resumes, so no force step
seeds the chatter; it builds from the cut's own noise and shows late (8-30 rev after the
resume against 0-2 rev after an abrupt step), and the alarm follows the visible chatter by
as much as after a step ramped over 8 revolutions, a growth as gradual: the cut's physics,
not a detector defect.  A pass ends 1.6 s after the step: chatter visible late in it may
not be alarmed by then (the cell says how many of the passes had a value).  Prints a
Markdown table; the defaults (45 passes) take about 7 s on 2 shared cores, --seeds 20 30 s.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import structlog

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from lathed.analysis.regen import VISIBLE_WAVINESS_M, wav_rev  # noqa: E402
from lathed.analyzer import AnalyzerContext  # noqa: E402
from lathed.bus import Block, Bus, Sample  # noqa: E402
from lathed.config import Section  # noqa: E402
from lathed.sim.lathe import SimLathe  # noqa: E402
from lathed.sim.program import Cut  # noqa: E402
from lathed_plugins.chatter import ChatterAnalyzer  # noqa: E402

RATE = 51200          # the simulated accelerometer, S/s
FRAME = 1024          # its frames (20 ms)
POLL_S = 0.1          # the registers' poll (the Modbus driver's)
FEED = 0.3            # mm/rev
DEPTH1, DEPTH2 = 1.0, 3.0       # mm: stable, then above the limit
HALF_S = 1.6          # cutting time of the pass's first half; the run ends this long after the step
DWELL_S = 1.0
RAMP_REVS = 8.0
RAMP_STEP = 64        # samples per depth step of the ramp
CASES = ("dwell 1 s, step at resume", "no dwell, abrupt step", f"no dwell, ramp {RAMP_REVS:g} rev")
CONF = {"input": "accel", "machine": "lathe", "cut_from": ["feed", "load", "vibration"],
        "dwell_axes": ["x_mm", "y_mm"], "dwell_max": "2s"}


def visible_after(blocks, i0: int, rpm: float) -> float | None:
    """Seconds from sample ``i0`` to the revolution chatter is visible from (regen's rule,
    revolutions counted from ``i0``), or None."""
    y = np.concatenate([b.y_m for b in blocks])
    wav = wav_rev(y, np.concatenate([b.theta_rad for b in blocks]),
                  np.concatenate([b.in_cut for b in blocks]), RATE)
    rev = int(RATE * 60.0 / rpm)
    nrev = (len(y) - i0) // rev
    r = np.sqrt(np.mean(wav[i0:i0 + nrev * rev].reshape(nrev, rev) ** 2, axis=1))
    for j in range(nrev - 2):
        if r[j] >= VISIBLE_WAVINESS_M and r[j + 1] >= 0.9 * r[j] and r[j + 2] >= 0.9 * r[j + 1]:
            return j * rev / RATE
    return None


def run_pass(rpm: float, seed: int, case: str) -> dict:
    """One pass: the step's time, chatter visible and the first alarm after it (s from the step,
    None if never), and the alarms raised before it."""
    dwell = case == CASES[0]
    ramp_s = RAMP_REVS * 60.0 / rpm if case == CASES[2] else 0.0
    length = 2 * FEED * rpm / 60.0 * HALF_S
    cut = Cut(rpm, DEPTH1, FEED, length, dwell_s=DWELL_S if dwell else 0.0)
    lathe = SimLathe(program=(cut,), load_s=0.5, retract_s=0.2, seed=seed)
    an = ChatterAnalyzer("chatter", Section("bench.toml", "analyzer.chatter", CONF))
    bus = Bus()
    an.ctx = AnalyzerContext(bus, structlog.get_logger("bench"), lambda kind, payload=None: None,
                             None, None, None, lambda name: None, ".")
    alarm = []                   # chatter_alarm as published: (value, sample time)
    bus.tap("chatter", lambda m: alarm.append((m.value, m.t))
            if isinstance(m, Sample) and m.quantity == "chatter_alarm" else None)
    # the surface the tool leaves, for the visible rule (SimLathe.step returns the accelerometer only)
    blocks = []
    cutter = lathe.cutter
    cut_run = cutter.run

    def keep(*a, **kw):
        blocks.append(cut_run(*a, **kw))
        return blocks[-1]
    cutter.run = keep

    poll, k, t_step = 0.037, 0, None
    while lathe.part_count < 1:
        if t_step is None and lathe.phase == "cut" and (
                lathe.record.dwell_end_s is not None if dwell else lathe.y_mm >= length / 2):
            t_step = lathe.n_samples / RATE
            lathe.depth_override_mm = DEPTH1 if ramp_s else DEPTH2
        if ramp_s and t_step is not None and lathe.n_samples / RATE < t_step + ramp_s + FRAME / RATE:
            parts = []
            for _ in range(FRAME // RAMP_STEP):
                tm = (lathe.n_samples + RAMP_STEP / 2) / RATE
                lathe.depth_override_mm = DEPTH1 + (DEPTH2 - DEPTH1) * min(1.0, max(0.0, (tm - t_step) / ramp_s))
                parts.append(lathe.step(RAMP_STEP))
            x = np.concatenate(parts)
        else:
            x = lathe.step(FRAME)
        while lathe.t >= poll:
            for q, v in lathe.registers().items():
                an._on_machine(Sample("lathe", q, float(v), "", poll))
            poll += POLL_S
        an._on_block(Block("accel", "acceleration", RATE, lathe.t - FRAME / RATE, k * FRAME,
                           x.astype(float), lathe.block_rpm))
        k += 1
        if t_step is not None and lathe.t > t_step + HALF_S:
            break
    # rises in publishing order (a clearing at the cut's end is stamped on the host's clock)
    rises = [t for i, (v, t) in enumerate(alarm) if v == 1.0 and (i == 0 or alarm[i - 1][0] != 1.0)]
    first = next((t for t in rises if t >= t_step), None)
    return {"visible": visible_after(blocks, int(round(t_step * RATE)), rpm),
            "alarm": None if first is None else first - t_step,
            "false_alarms": sum(t < t_step for t in rises)}


def cell(xs: list, n: int, p: int) -> str:
    """Median [lowest..highest] of the values present; how many when not all ``n``."""
    v = [x for x in xs if x is not None]
    if not v:
        return f"- (0 of {n})"
    s = f"{statistics.median(v):.{p}f} [{min(v):.{p}f}..{max(v):.{p}f}]" if len(v) > 1 else f"{v[0]:.{p}f}"
    return s if len(v) == n else f"{s} ({len(v)} of {n})"


def revs(xs: list, rps: float) -> list:
    return [None if x is None else x * rps for x in xs]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5,
                    help="passes of each case at each speed, seeds 0..N-1 (default 5)")
    ap.add_argument("--speeds", type=float, nargs="+", default=[1500.0, 2000.0, 2500.0], metavar="RPM",
                    help="spindle speeds, r/min (default 1500 2000 2500)")
    args = ap.parse_args(argv)
    if args.seeds < 1:
        print("dwell_resume.py: --seeds must be at least 1", file=sys.stderr)
        return 2
    if any(not 500 <= s <= 6000 for s in args.speeds):
        print("dwell_resume.py: --speeds take 500..6000 r/min", file=sys.stderr)
        return 2
    structlog.configure(logger_factory=structlog.ReturnLoggerFactory())    # the analyzer's log: not printed
    t0 = time.monotonic()
    print(f"Chatter after a dwell's resume against a depth step mid-pass: {DEPTH1:g} -> {DEPTH2:g} mm, "
          f"{FEED:g} mm/rev, seeds 0-{args.seeds - 1}; median [range] from the step (the resume, the "
          "ramp's start)\n")
    print("| speed r/min | case | visible after the step, s | rev | alarm after the step, s | rev "
          "| delay visible -> alarm, rev | false alarms before the step |")
    print("|---|---|---|---|---|---|---|---|")
    for rpm in args.speeds:
        rps = rpm / 60.0
        for case in CASES:
            rs = [run_pass(rpm, seed, case) for seed in range(args.seeds)]
            vis = [r["visible"] for r in rs]
            al = [r["alarm"] for r in rs]
            delay = [None if v is None or a is None else (a - v) * rps for v, a in zip(vis, al)]
            n = len(rs)
            print(f"| {rpm:g} | {case} | {cell(vis, n, 2)} | {cell(revs(vis, rps), n, 1)} "
                  f"| {cell(al, n, 2)} | {cell(revs(al, rps), n, 1)} | {cell(delay, n, 1)} "
                  f"| {sum(r['false_alarms'] for r in rs)} in {n} pass{'es' if n > 1 else ''} |")
    print(f"\n{len(args.speeds) * len(CASES) * args.seeds} passes in {time.monotonic() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
