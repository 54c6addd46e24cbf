"""Per-channel cost of audio accelerometers: 1, 2, 4, 8 channels at 51.2 kS/s, each with its
own chatter analyzer, on the default config (the simulated lathe and its line).

A JACK server (dummy backend, 8 capture ports at 51.2 kS/s; tests/ensure_jack.sh installs
it) stands in for an 8-input IEPE interface; a JACK client in this process plays the
simulator's own accelerometer stream (the cut it simulates, lathed.wire over TCP) into
every port. The daemon's sensors accel1..N read channels 1..N of the device through one
capture helper (lathed.audio_capture); chatter1..N analyse them. CPU is user+system time
of the daemon and of its capture helper over the window, as a share of one core; memory
is their resident set at the window's end (every detector's history full by then), less
the JACK server's shared memory the helper maps (an audio server's, not lathed's).

    .venv/bin/python bench/bench_channels.py [--channels 1,2,4,8] [--warmup 20] [--seconds 30]
                                             [--rounds R] [--against REV] [--py-spy]

``--against REV`` runs REV's lathed and plugins (taken out of git) round by round alternately
with this checkout's, on the same machine under the same load: each one's medians over the
rounds, each round's per-channel slope, and the ratio of the medians.

``--py-spy`` samples the daemon with py-spy (``pip install py-spy``; not a dependency)
through each window instead of only timing it, and prints where its CPU went, stage by
stage, and each stage's slope over the channels: the live daemon's own breakdown (the
sampling costs the daemon a little; read the CPU table of a run without it).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
from bench.bench_daemon import config as default_config, cpu_s  # noqa: E402
from lathed.wire import VIB_HEADER, unpack_vibration_header  # noqa: E402
from tests.jack_fixtures import JackServer, jack  # noqa: E402

BIN = Path(sys.executable).parent
RATE = 51200
FULL_SCALE = 5.0 * 1000 / 100.0 * 9.80665      # m/s² at full scale: 100 mV/g into a 5 V interface


def rss_mb(pid: int) -> float:
    """Resident memory less shared memory (RssShmem): a JACK client maps the server's 100 MB
    /dev/shm segment, the audio server's memory (an ALSA device has none)."""
    f = {k: int(v.split()[0]) for k, v in (ln.split(":", 1) for ln in
                                           Path(f"/proc/{pid}/status").read_text().splitlines() if ":" in ln)
         if k in ("VmRSS", "RssShmem")}
    return (f["VmRSS"] - f.get("RssShmem", 0)) / 1024


def sensors(n: int) -> str:
    return "".join(f"""
[sensor.accel{k}]
plugin = "audio_input"
device = "system"
rate = {RATE}
block = 1024
channel = {k}
sensitivity_mv_g = 100.0
full_scale_v = 5.0
""" for k in range(1, n + 1))


def config(tmp: Path, n: int) -> Path:
    cfg = default_config(tmp)
    text = cfg.read_text()
    m = re.search(r"^\[sensor\.accel\]\n.*?(?=^\s*$)", text, re.S | re.M)
    text = text[:m.start()] + sensors(n) + text[m.end():]
    chatter = re.search(r"^\[analyzer\.chatter\]\n.*?(?=^\s*$)", text, re.S | re.M).group(0)
    text = text.replace(chatter, chatter.replace('input = "accel"', 'input = "accel1"'))
    extra = "".join("\n" + chatter.replace("[analyzer.chatter]", f"[analyzer.chatter{k}]")
                    .replace('input = "accel"', f'input = "accel{k}"') + "\n" for k in range(2, n + 1))
    cfg.write_text(text + extra)
    return cfg


class Bridge:
    """The simulator's accelerometer stream played into N JACK ports (the same signal on each)."""

    def __init__(self, server: JackServer, port: int, channels: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        self.buf: deque[np.ndarray] = deque()
        self.have = 0
        self.underruns = 0
        self.started = False
        self.lock = threading.Lock()
        threading.Thread(target=self._read, daemon=True).start()
        self.client = jack.Client("bridge", servername=server.name, no_start_server=True)
        self.ports = [self.client.outports.register(f"out_{i}") for i in range(channels)]
        self.client.set_process_callback(self._process)
        self.client.activate()

    def _exact(self, n: int) -> bytes:
        out = b""
        while len(out) < n:
            chunk = self.sock.recv(n - len(out))
            if not chunk:
                raise ConnectionError("the simulator closed its stream")
            out += chunk
        return out

    def _read(self) -> None:
        try:
            while True:
                channels, n, _, _, _, _ = unpack_vibration_header(self._exact(VIB_HEADER.size))
                x = np.frombuffer(self._exact(4 * n * channels), "<f4").reshape(n, channels)[:, 0] / FULL_SCALE
                with self.lock:
                    self.buf.append(x.astype(np.float32))
                    self.have += n
                    while self.have > 2 * RATE:          # more than 2 s ahead: the oldest go
                        self.have -= len(self.buf.popleft())
        except (ConnectionError, OSError):
            pass

    def _process(self, frames: int) -> None:
        out = np.zeros(frames, np.float32)
        with self.lock:
            if not self.started and self.have >= 0.3 * RATE:
                self.started = True               # a third of a second ahead: the jitter's margin
            if self.started:
                i = 0
                while i < frames and self.buf:
                    b = self.buf[0]
                    k = min(frames - i, len(b))
                    out[i:i + k] = b[:k]
                    i += k
                    self.have -= k
                    if k == len(b):
                        self.buf.popleft()
                    else:
                        self.buf[0] = b[k:]
                if i < frames:
                    self.underruns += 1
        for p in self.ports:
            p.get_array()[:] = out

    def connect(self, n: int) -> None:
        deadline = time.monotonic() + 30
        while True:
            ins = [p.name for p in self.client.get_ports("PortAudio:.*", is_input=True, is_audio=True)]
            if len(ins) >= n:
                break
            if time.monotonic() > deadline:
                raise SystemExit(f"the daemon's capture never opened {n} channels (JACK ports: {ins})")
            time.sleep(0.1)
        for k in range(n):
            self.client.connect(self.ports[k], f"PortAudio:in_{k}")

    def close(self) -> None:
        self.client.deactivate()
        self.client.close()
        self.sock.close()


def status(sock: Path) -> dict:
    r = subprocess.run([str(BIN / "lathectl"), "--socket", str(sock), "status", "--json"], capture_output=True,
                       text=True, timeout=30)
    return json.loads(r.stdout) if r.returncode == 0 else {}


def received(st: dict) -> int:
    """Samples published by the audio sensors (1024 a block)."""
    return 1024 * sum(s.get("blocks") or 0 for s in st.get("sensors", []) if s["name"].startswith("accel"))


SPY_RATE = 250      # py-spy's samples a second
# where the daemon's samples go: a sample counts for the innermost of these functions on its stack
SPY_STAGES = [
    ("hand-over", "the capture helper's frames read and split (audio_device._read)", "AudioDevice._read"),
    ("pipe", "the helper's pipe read into the stream buffer", "_UnixReadPipeTransport._read_ready"),
    ("sensor", "audio_input: a block (conditioning, the gate, the bus)", "AudioInput._on_block"),
    ("machine", "chatter: the machine's samples", "ChatterAnalyzer._on_machine"),
    ("cut", "chatter: the cut state", "CutState.block"),
    ("detector", "chatter: the detector", "RevolutionDetector.process"),
    ("block rest", "chatter: the rest of a block (its samples published)", "ChatterAnalyzer._on_block"),
    ("store", "the store's writer thread (SQLite)", "Store._writer"),
    ("epoll", "the event loop's wait (epoll; idle, mostly)", "EpollSelector.select"),
]


def spy_stages(path: Path) -> dict[str, int]:
    """py-spy's raw (collapsed) stacks -> samples per stage; "all" every sample."""
    out = {k: 0 for k, *_ in SPY_STAGES}
    out["all"] = 0
    fns = {fn: key for key, _, fn in SPY_STAGES}
    others = 0
    for line in path.read_text().splitlines():
        stack, _, count = line.rpartition(" ")
        n = int(count)
        out["all"] += n
        if "BaseEventLoop.run_forever" not in stack and "Store._writer" not in stack:
            # another thread (a serial port's reader, the executor's): py-spy often counts one
            # blocked in a read as active, so these are kept apart
            others += n
            continue
        # the innermost stage the stack is in (a sensor's block is under the hand-over's frames)
        for f in reversed(stack.split(";")):
            key = fns.get(f.partition(" ")[0])
            if key is not None:
                out[key] += n
                break
    out["threads"] = others
    out["rest"] = out["all"] - others - sum(out[k] for k, *_ in SPY_STAGES)
    return out


def tree_of(rev: str | None, tmp: Path) -> Path:
    """A directory whose lathed and lathed_plugins are this checkout's, or REV's."""
    if rev is None:
        return ROOT
    d = tmp / rev.replace("/", "_")
    d.mkdir()
    arch = subprocess.run(["git", "-C", str(ROOT), "archive", rev, "lathed", "plugins"], check=True,
                          capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(d)], input=arch, check=True)
    (d / "lathed_plugins").symlink_to(d / "plugins")
    return d


def run(n: int, server: JackServer, warmup: float, seconds: float, spy: bool = False,
        keep: str | None = None, tree: Path = ROOT) -> dict:
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        cfg = config(tmp, n)
        text = cfg.read_text()
        vport = int(re.search(r"^vibration_port = (\d+)", text, re.M).group(1))
        sock = tmp / "run" / "lathed.sock"
        load = [os.getloadavg()[0]]
        # the tree's code first on the path of the daemon, its helper and its simulator (run
        # from the temporary directory: a checkout as the working directory would come first)
        proc = subprocess.Popen([str(BIN / "lathed"), "--config", str(cfg)], stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL, cwd=tmp,
                                env={**os.environ, **server.env, "PYTHONPATH": str(tree)})
        try:
            deadline = time.monotonic() + 60
            while not (st := status(sock)) or any(s["state"] != "connected" for s in st["sensors"]
                                                  if s["name"].startswith("accel")):
                if time.monotonic() > deadline or proc.poll() is not None:
                    raise SystemExit(f"{n} channels: the daemon's sensors did not connect ({st.get('sensors')})")
                time.sleep(0.5)
            bridge = Bridge(server, vport, n)
            bridge.connect(n)
            helper = next(s["helper_pid"] for s in st["sensors"] if s["name"] == "accel1")
            time.sleep(warmup)
            pids = (proc.pid, helper)
            got0 = received(status(sock))
            c0, w0 = [cpu_s(p) for p in pids], time.monotonic()
            spied = None
            if spy:
                spied = Path(keep) / f"daemon-{n}.txt" if keep else tmp / "spy.txt"
                spied.parent.mkdir(parents=True, exist_ok=True)
                subprocess.run([str(BIN / "py-spy"), "record", "-p", str(proc.pid), "-d", f"{seconds:g}",
                                "-r", str(SPY_RATE), "-f", "raw", "-o", str(spied), "--nonblocking"],
                               check=True, capture_output=True)
                time.sleep(max(0.0, seconds - (time.monotonic() - w0)))
            else:
                time.sleep(seconds)
            used = [cpu_s(p) - c for p, c in zip(pids, c0)]
            wall = time.monotonic() - w0
            cpu = [100 * u / wall for u in used]
            rss = [rss_mb(p) for p in pids]
            st = status(sock)
            # seconds of each channel's signal the daemon took in the window: below the wall
            # time when it fell behind (a busy machine), and the CPU it would take at real time
            took = (received(st) - got0) / RATE / n
            windows = sum(a.get("windows", 0) for a in st["analyzers"] if a["name"].startswith("chatter"))
            lost = sum(s.get("lost_samples", 0) or 0 for s in st["sensors"] if s["name"].startswith("accel"))
            bridge.close()
            load.append(os.getloadavg()[0])
            return {"n": n, "cpu": cpu, "rss": rss, "windows": windows, "lost": lost, "load": load,
                    "spy": spy_stages(spied) if spied is not None else None,
                    "underruns": bridge.underruns, "rt": [100 * u / took for u in used] if took > 0 else cpu,
                    "took": took, "wall": wall}
        finally:
            proc.send_signal(signal.SIGTERM)
            proc.wait(60)


def slopes(rows: list[dict]) -> tuple[float, float, float]:
    """Each added channel: the least-squares slopes of CPU, CPU per second of signal, RSS."""
    x = np.array([r["n"] for r in rows], float)
    return tuple(float(np.polyfit(x, [sum(r[k]) for r in rows], 1)[0]) for k in ("cpu", "rt", "rss"))


def medians(runs: list[dict]) -> dict:
    """One channel count's runs -> their median, component by component."""
    return {"n": runs[0]["n"], **{k: [float(np.median([r[k][i] for r in runs])) for i in range(2)]
                                  for k in ("cpu", "rt", "rss")},
            "took": float(np.median([r["took"] for r in runs])), "lost": max(r["lost"] for r in runs),
            "wall": float(np.median([r["wall"] for r in runs]))}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--channels", default="1,2,4,8")
    ap.add_argument("--warmup", type=float, default=20.0)
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--rounds", type=int, default=1)
    ap.add_argument("--against", help="a git revision run alternately with this checkout (e.g. main)")
    ap.add_argument("--py-spy", action="store_true", help="sample the daemon with py-spy: its CPU by stage")
    ap.add_argument("--py-spy-keep", metavar="DIR", help="keep py-spy's raw stacks there (daemon-N.txt)")
    a = ap.parse_args()
    if a.py_spy and not (BIN / "py-spy").exists():
        raise SystemExit(f"--py-spy needs py-spy in {BIN} (pip install py-spy)")
    ns = [int(x) for x in a.channels.split(",")]
    names = ["old", "new"] if a.against else ["new"]
    runs: dict[str, dict[int, list[dict]]] = {name: {n: [] for n in ns} for name in names}
    fits: dict[str, list[tuple[float, float, float]]] = {name: [] for name in names}
    with tempfile.TemporaryDirectory() as d:
        trees = {"new": ROOT} | ({"old": tree_of(a.against, Path(d))} if a.against else {})
        for rnd in range(a.rounds):
            for name in names:
                done = []
                for n in ns:
                    # a server of its own for each run: a client the last daemon's helper left as it
                    # stopped would hold a synchronous server's cycles
                    server = JackServer(rate=RATE, capture=max(ns), name="lathed-bench")
                    server.start()
                    try:
                        done.append(run(n, server, a.warmup, a.seconds, a.py_spy, a.py_spy_keep, trees[name]))
                    finally:
                        server.stop()
                    runs[name][n].append(done[-1])
                if len(done) > 1:
                    fits[name].append(slopes(done))
                    load = [v for r in done for v in r["load"]]
                    print(f"round {rnd + 1}, {a.against if name == 'old' else 'this checkout'}: each added "
                          f"channel {fits[name][-1][0]:+.2f} % of a core, {fits[name][-1][2]:+.1f} MB "
                          f"(load average {min(load):.1f}-{max(load):.1f})", file=sys.stderr, flush=True)
    rows = [medians(runs["new"][n]) for n in ns]
    of = f", median of {a.rounds}" if a.rounds > 1 else ""
    print(f"| channels (51.2 kS/s, a chatter analyzer each{of}) | CPU daemon + helper, % of a core | "
          f"the same per second of signal taken in | RSS daemon + helper, MB | signal taken in over "
          f"{a.seconds:g} s | samples lost |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['n']} | {sum(r['cpu']):.1f} ({r['cpu'][0]:.1f} + {r['cpu'][1]:.1f}) | "
              f"{sum(r['rt']):.1f} | {sum(r['rss']):.0f} ({r['rss'][0]:.0f} + {r['rss'][1]:.0f}) | "
              f"{r['took']:.1f} s a channel | {r['lost']} |")
    if len(rows) > 1:
        cpu, rt, rss = (float(np.median([f[i] for f in fits["new"]])) for i in range(3))
        what = "each added channel (least-squares slope" + (", median of the rounds'" if a.rounds > 1 else "")
        print(f"| {what}) | {cpu:+.2f} % | {rt:+.2f} % | {rss:+.1f} MB | | |")
        if a.against:
            for name in names:
                label = a.against if name == "old" else "this checkout"
                print(f"\n{label}: each added channel " + ", ".join(f"{f[0]:+.2f}" for f in fits[name])
                      + f" % of a core (median {np.median([f[0] for f in fits[name]]):+.2f}), "
                      + ", ".join(f"{f[2]:+.1f}" for f in fits[name])
                      + f" MB (median {np.median([f[2] for f in fits[name]]):+.1f})", end="")
            ratio = np.median([f[0] for f in fits["new"]]) / np.median([f[0] for f in fits["old"]])
            print(f"\nthis checkout / {a.against}, % of a core a channel (medians): {ratio:.2f}")
    load = [v for by in runs.values() for rs in by.values() for r in rs for v in r["load"]]
    print(f"load average over the runs: {min(load):.1f}-{max(load):.1f}")
    if a.py_spy:
        rows = [runs["new"][n][-1] for n in ns]
        pct = 100.0 / (SPY_RATE * a.seconds)          # % of a core a sample is
        print(f"\n| the daemon's CPU by stage (py-spy, % of a core) | "
              + " | ".join(f"{r['n']} ch" for r in rows) + " | each added channel | µs a block and channel |")
        print("|---|" + "---|" * (len(rows) + 2))
        x = np.array([r["n"] for r in rows], float)
        rest = [("rest", "the event loop's rest (asyncio, the subscriptions, the other drivers)", None),
                ("threads", "the other threads (serial readers, the executor: blocked reads counted too)", None),
                ("all", "all the daemon's samples", None)]
        for key, what, _ in [*SPY_STAGES, *rest]:
            v = [r["spy"][key] * pct for r in rows]
            slope = np.polyfit(x, v, 1)[0] if len(rows) > 1 else float("nan")
            print(f"| {key}: {what} | " + " | ".join(f"{u:.2f}" for u in v)
                  + f" | {slope:+.3f} % | {slope * 1e4 * 1024 / RATE:.0f} |")
    behind = [r["n"] for r in rows if r["took"] < 0.95 * r["wall"]]
    if behind:
        print(f"\nnote: with {', '.join(map(str, behind))} channel(s) the daemon took in less signal than the "
              "window's time (the machine was too busy): read the per-second-of-signal column", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
