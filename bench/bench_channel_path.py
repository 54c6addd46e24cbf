"""Where the daemon spends each accelerometer block, per channel: the in-process profile behind
`make bench-channels` (docs/benchmarks.md, "Audio accelerometers, per channel").

The daemon's own code path, without the audio server: N audio_input sensors (the shipped
calibration, 51.2 kS/s, 1024-sample blocks) are handed the capture helper's blocks as
lathed.audio_device hands them, each with its chatter analyzer (the shipped
``[analyzer.chatter]`` table) running as an asyncio task on the real bus, the lathe's
registers published every 100 ms as its driver does. The signal is the simulator's (its
cuts, entries, dwells and chatter), made once and fed to every run. Per block and channel:
the driver (conditioning, the bus), the analyzer's machine samples, its cut state, its
detector (and the detector's parts), its windows' samples, and the rest (asyncio, the
subscriptions): the thread's CPU time in each (a busy machine's preemption not counted; each
timer adds about a microsecond to the stage around it), per block and channel; then the loop's
CPU per block and its slope over the channels (what `make bench-channels` measures as % of a core).

With ``--against REV`` the same runs alternate between this checkout and REV (taken out of
git into a temporary directory), so both are measured under the same load: each stage's
median over the rounds, the ratio new/old, and a check that both published the same chatter
samples (every index, threshold, alarm, frequency, to the bit or within --tol; exit 1 if not).

    .venv/bin/python bench/bench_channel_path.py [--channels 1,4] [--seconds 30] [--rounds 3]
                                                  [--against REV] [--profile]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
RATE = 51200
BLOCK = 1024
POLL_BLOCKS = 5                                  # the lathe's 100 ms poll, in blocks
FULL_SCALE = 5.0 * 1000 / 100.0 * 9.80665        # m/s² at full scale: 100 mV/g into a 5 V interface
T0 = 3.0e9                                       # the stream's first sample, host time (a stamp
                                                 # from the wall clock, a cleared alarm's, is before)

# the stages, in the order printed; "(...)" ones are parts of the stage above them
STAGES = [
    ("driver", "audio_input: a block (calibration, rms, the gate, the bus)"),
    ("  conditioning", "(calibration and DC high-pass; with a ConditionerBank the peak too)"),
    ("  publish", "(the gate's checks and the bus's puts)"),
    ("poll", "the lathe's registers published (per block, shared)"),
    ("machine", "chatter: the machine's samples (the cut's sources)"),
    ("block", "chatter: a block"),
    ("  cut", "(the cut state: vibration source, contact, dwell)"),
    ("  detector", "(the detector's process)"),
    ("    window", "(its windows)"),
    ("      measure", "(the raw measure: robust rms of the revolution difference)"),
    ("      bands", "(the spectral shape's band powers: an FFT)"),
    ("      shape", "(the shape index against the baseline's)"),
    ("      level", "(a window's level and the one a revolution before)"),
    ("      rules", "(shoulder, growth, rising, CUSUM, follow, load)"),
    ("      frequency", "(the chatter frequency while alarmed: an FFT)"),
    ("  samples", "(the windows' samples published)"),
    ("rest", "asyncio and the subscriptions (the loop less the above)"),
    ("total", "the loop's CPU"),
]


# -- the signal ------------------------------------------------------------------------
def make_stream(seconds: float, path: Path, skip: float = 0.0) -> None:
    """The simulator's accelerometer (full scale) and the lathe's registers at each poll,
    from ``skip`` seconds into its program."""
    sys.path.insert(0, str(ROOT))
    from lathed.sim.lathe import SimLathe
    lathe = SimLathe(rate_hz=RATE, seed=0)
    for _ in range(int(skip * RATE / BLOCK)):
        lathe.step(BLOCK)
    n = int(seconds * RATE / BLOCK)
    x = np.empty((n, BLOCK), np.float32)
    regs = []
    for i in range(n):
        if i % POLL_BLOCKS == 0:
            regs.append(lathe.registers())
        x[i] = lathe.step(BLOCK) / FULL_SCALE
    names = sorted(regs[0])
    np.savez(path, x=x, regs=np.array([[r[k] for k in names] for r in regs], float), names=np.array(names))


# -- one run (a subprocess: the tree under test first on its path) -----------------------
def worker(tree: str, stream: str, channels: int, profile: bool) -> dict:
    sys.path.insert(0, tree)
    import asyncio
    import tomllib

    import structlog

    from lathed.analyzer import AnalyzerContext
    from lathed.audio_device import AudioDevice
    from lathed.analysis.chatter.registry import DEFAULT_DETECTOR, DETECTORS
    from lathed.analysis.chatter.shape import SpectralShape
    import lathed.analysis.conditioning as conditioning
    from lathed.analysis.cut.state import CutState
    from lathed.bus import Bus, Sample
    from lathed.config import Section
    from lathed.driver import DriverContext, GatedBus
    from lathed_plugins.audio_input import AudioInput
    from lathed_plugins.chatter import ChatterAnalyzer
    assert Path(sys.modules["lathed"].__file__).resolve().parent == (Path(tree) / "lathed").resolve()

    structlog.configure(logger_factory=structlog.ReturnLoggerFactory())
    log = structlog.get_logger()
    cfg = tomllib.loads((ROOT / "etc" / "lathed.toml").read_text())
    table = cfg["analyzer"]["chatter"]
    spent = {k.strip(): 0.0 for k, _ in STAGES}
    clock = time.thread_time          # CPU time: a busy machine's preemption is not counted

    # an analyzer fed by bus taps runs inside the publish of its sensor's block or the lathe's
    # registers: its time is its own stage's, not the publisher's
    inner = [0.0]

    def timed(cls, name: str, stage: str) -> None:
        f = getattr(cls, name)

        def w(*a, **k):
            t, i0 = clock(), inner[0]
            try:
                return f(*a, **k)
            finally:
                dt = clock() - t
                if stage in ("block", "machine"):
                    inner[0] += dt
                elif stage == "driver":
                    dt -= inner[0] - i0
                spent[stage] += dt
        setattr(cls, name, w)

    timed(AudioInput, "_on_block", "driver")
    if hasattr(conditioning, "ConditionerBank"):     # a device's channels conditioned in one pass
        timed(conditioning.ConditionerBank, "take", "conditioning")
    else:
        timed(conditioning.Conditioner, "process", "conditioning")
    timed(ChatterAnalyzer, "_on_machine", "machine")
    timed(ChatterAnalyzer, "_on_block", "block")
    timed(CutState, "block", "cut")
    det = DETECTORS[table.get("detector", DEFAULT_DETECTOR)]     # its methods timed where it has them
    timed(det, "process", "detector")
    timed(det, "_window", "window")
    timed(SpectralShape, "bands", "bands")
    timed(SpectralShape, "index", "shape")
    timed(det, "_measure", "measure")
    timed(det, "_level", "level")
    for rule in ("_shoulder", "_growth", "_rising_from_step", "_cusum_says", "_follow", "_waiting_for_load"):
        timed(det, rule, "rules")
    timed(det, "_chatter_frequency", "frequency")
    gated = GatedBus.publish

    def publish(self, msg):
        t, i0 = clock(), inner[0]
        try:
            return gated(self, msg)
        finally:
            if msg.source != "lathe":
                spent["publish"] += clock() - t - (inner[0] - i0)
    GatedBus.publish = publish

    units = {k: r.get("unit", "") for k, r in cfg["machine"]["lathe"]["registers"].items()}
    s = np.load(stream)
    x, regs, names = s["x"], s["regs"], [str(k) for k in s["names"]]
    bus = Bus()
    subs = []                                  # every subscription, to wait for each to be drained
    subscribe = bus.subscribe
    bus.subscribe = lambda *a, **k: subs.append(subscribe(*a, **k)) or subs[-1]
    lathe = DriverContext(bus, log, lambda *a: None).bus
    out: list[tuple] = []                      # chatter1's samples: the results compared
    listeners = []
    sensors, analyzers = [], []

    async def attach(sensor, on_block, on_gone, stall_s):
        listeners.append(on_block)
        return {"name": "bench", "hostapi": "none", "latency_s": 0.01, "pid": 0}

    for k in range(1, channels + 1):
        sec = Section("bench.toml", f"sensor.accel{k}", {"device": "bench", "rate": RATE, "block": BLOCK,
                                                          "channel": k, "sensitivity_mv_g": 100.0,
                                                          "full_scale_v": 5.0})
        drv = AudioInput(f"accel{k}", sec)
        drv.dev.attach = attach
        drv.ctx = DriverContext(bus, log, lambda *a: None)
        sensors.append(drv)
        an = ChatterAnalyzer(f"chatter{k}", Section("bench.toml", f"analyzer.chatter{k}",
                                                    {**table, "input": f"accel{k}"}))
        an.ctx = AnalyzerContext(bus, log, lambda *a: None, None, lambda *a: None, None,
                                 lambda name: {"state": "connected"}, str(ROOT / "etc"))
        analyzers.append(an)
    first = bus.publish

    def keep(msg):
        if msg.source == "chatter1" and isinstance(msg, Sample) and msg.quantity != "blind":
            out.append((msg.quantity, msg.value, msg.t if msg.t >= T0 else None))
        first(msg)
    bus.publish = keep

    async def run() -> tuple[float, float]:
        for drv in sensors:
            await drv.connect()
        tasks = [asyncio.create_task(an.run()) for an in analyzers]
        await asyncio.sleep(0)
        wall = cpu = 0.0
        for i in range(len(x)):
            data = np.repeat(x[i][:, None], channels, axis=1)     # the helper's frames x channels
            t = T0 + i * BLOCK / RATE
            c0, w0 = time.process_time(), clock()
            if i % POLL_BLOCKS == 0:
                p0, i0 = clock(), inner[0]
                for name, v in zip(names, regs[i // POLL_BLOCKS]):
                    lathe.publish(Sample("lathe", name, float(v), units.get(name, ""), t))
                spent["poll"] += clock() - p0 - (inner[0] - i0)
            meta = {"adc": t, "host_t": t + 0.002, "overflow": False, "dropped": 0}
            for on_block in listeners:
                on_block(data, meta)
            await asyncio.sleep(0)
            while any(sub._items for sub in subs):
                await asyncio.sleep(0)
            wall += clock() - w0
            cpu += time.process_time() - c0
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        return wall, cpu

    prof = None
    if profile:
        import cProfile
        prof = cProfile.Profile()
        prof.enable()
    wall, cpu = asyncio.run(run())
    if prof is not None:
        prof.disable()
        import pstats
        st = pstats.Stats(prof, stream=sys.stderr)
        st.sort_stats("tottime").print_stats(40)
        st.sort_stats("cumulative").print_stats(60)
    n = len(x) * channels
    us = {k: 1e6 * v / n for k, v in spent.items()}
    us["poll"] = 1e6 * spent["poll"] / len(x)
    us["samples"] = us["block"] - us["cut"] - us["detector"]
    us["rest"] = 1e6 * wall / n - us["driver"] - us["poll"] / channels - us["machine"] - us["block"]
    us["total"] = 1e6 * cpu / n
    return {"us": us, "cpu_per_block": 1e6 * cpu / len(x), "windows": sum(a.windows for a in analyzers),
            "out": out, "blocks": len(x)}


# -- the rounds --------------------------------------------------------------------------
def tree_of(rev: str | None, tmp: Path) -> Path:
    """A directory whose lathed and lathed_plugins are this checkout's, or REV's."""
    d = tmp / (rev or "this").replace("/", "_")
    d.mkdir()
    if rev is None:
        (d / "lathed").symlink_to(ROOT / "lathed")
        (d / "lathed_plugins").symlink_to(ROOT / "plugins")
    else:
        arch = subprocess.run(["git", "-C", str(ROOT), "archive", rev, "lathed", "plugins"], check=True,
                              capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(d)], input=arch, check=True)
        (d / "lathed_plugins").symlink_to(d / "plugins")
    return d


def one(tree: Path, stream: Path, channels: int, profile: bool = False) -> dict:
    with tempfile.NamedTemporaryFile(suffix=".json") as f:
        args = [sys.executable, __file__, "--worker", str(tree), "--stream", str(stream),
                "--channels", str(channels), "--out", f.name] + (["--profile"] if profile else [])
        subprocess.run(args, check=True, env={**os.environ, "PYTHONHASHSEED": "0"})
        return json.loads(Path(f.name).read_text())


def compare(a: list, b: list, tol: float) -> str:
    """How far two runs' chatter samples are apart."""
    if len(a) != len(b):
        return f"DIFFERENT: {len(a)} against {len(b)} samples"
    worst = 0.0
    for (qa, va, ta), (qb, vb, tb) in zip(a, b):
        if qa != qb or ta != tb or (np.isnan(va) != np.isnan(vb)):
            return f"DIFFERENT: {qa} at {ta} against {qb} at {tb}"
        if not np.isnan(va) and va != vb:
            worst = max(worst, abs(va - vb) / max(abs(va), abs(vb)))
    if worst > tol:
        return f"DIFFERENT: values apart by up to {worst:.2e} (relative)"
    return f"the same: {len(a)} samples" + (" bit for bit" if worst == 0 else f", within {worst:.1e}")


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--channels", default="1,4")
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--skip", type=float, default=0.0,
                    help="start this far into the simulator's program (make bench-channels' window "
                         "is about 25-55 s into it)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--against", help="a git revision to compare with (e.g. main)")
    ap.add_argument("--profile", action="store_true", help="cProfile one run of this checkout (stderr)")
    ap.add_argument("--tol", type=float, default=1e-9)
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--stream", help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.worker:
        r = worker(a.worker, a.stream, int(a.channels), a.profile)
        Path(a.out).write_text(json.dumps(r))
        return 0
    ns = [int(c) for c in a.channels.split(",")]
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        stream = tmp / "stream.npz"
        t = time.monotonic()
        make_stream(a.seconds, stream, a.skip)
        print(f"signal: {a.seconds:g} s of the simulator's cuts from {a.skip:g} s in, made in "
              f"{time.monotonic() - t:.0f} s",
              file=sys.stderr)
        trees = {"new": tree_of(None, tmp)}
        if a.against:
            trees["old"] = tree_of(a.against, tmp)
        if a.profile:
            one(trees["new"], stream, max(ns), profile=True)
            return 0
        runs: dict[tuple[str, int], list[dict]] = {}
        for _ in range(a.rounds):
            for n in ns:
                for name in (["old", "new"] if a.against else ["new"]):
                    runs.setdefault((name, n), []).append(one(trees[name], stream, n))
    names = ["old", "new"] if a.against else ["new"]
    med = {k: {s: statistics.median(r["us"][s] for r in v) for s in v[0]["us"]} for k, v in runs.items()}
    n = max(ns)
    head = f"| stage (µs a block and channel, {n} channel(s), median of {a.rounds}) |"
    head += " before | after | after / before |" if a.against else " µs |"
    print(head)
    print("|---|" + ("---|---|---|" if a.against else "---|"))
    for key, what in STAGES:
        s = key.strip()
        label = ("&nbsp;" * (len(key) - len(s))) + f"{s}: {what}"
        if a.against:
            old, new = med[("old", n)][s], med[("new", n)][s]
            print(f"| {label} | {old:.1f} | {new:.1f} | {new / old:.2f} |" if old > 0 else
                  f"| {label} | {old:.1f} | {new:.1f} | |")
        else:
            print(f"| {label} | {med[('new', n)][s]:.1f} |")
    if len(ns) > 1:
        lo, hi = min(ns), max(ns)
        slopes = {}
        for name in names:
            slope = [(b["cpu_per_block"] - c["cpu_per_block"]) / (hi - lo)
                     for b, c in zip(runs[(name, hi)], runs[(name, lo)])]
            us = slopes[name] = statistics.median(slope)
            print(f"\n{name}: each added channel {us:.0f} µs a block (median of {a.rounds}), "
                  f"{us * RATE / BLOCK / 1e4:.2f} % of a core at {RATE / BLOCK:g} blocks a second", end="")
        print(f"\nafter / before: {slopes['new'] / slopes['old']:.2f}" if a.against else "")
    one_run = runs[(names[-1], n)][0]
    print(f"\n{one_run['blocks']} blocks, {one_run['windows']} windows over {n} channel(s)")
    if a.against:
        same = compare(runs[("old", n)][0]["out"], runs[("new", n)][0]["out"], a.tol)
        print(f"chatter1's samples, old against new: {same}")
        return 1 if same.startswith("DIFFERENT") else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
