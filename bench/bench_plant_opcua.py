"""lathed-opcua's cost and latency (issue 15): the daemon alone, then with lathed-opcua and 10 OPC UA clients.

Runs the default config (etc/lathed.toml, simulator spawned, every part cut 3 mm deep so that
chatter happens and suppression acts) on free ports. One daemon, two phases of ``--duration``
seconds each after ``--warmup``:

  none     no subscriber
  opcua    lathed-opcua (one subscription to the daemon, rate_hz 20) serving CLIENTS asyncua
           clients, each with one subscription (publishing interval PUBLISH_MS) monitoring the
           lathe's and the mill's live Doubles (spindle, axes, chatter index...) with the
           StatusValueTimestamp trigger, so every new sample is a notification

Latency: from a sample's measurement (its ``t``, stamped by the driver as it publishes on the
daemon's bus, carried to the client as the value's SourceTimestamp) to the client's handler
receiving it (time.time() there; same clock). Per phase the daemon's CPU (its process only,
from /proc), its event-loop lag; in the second the CPU and RSS of lathed-opcua. The clients run
in this process, on the same two cores.

    .venv/bin/python bench/bench_plant_opcua.py [--duration 60] [--warmup 20] [--json FILE]
"""
from __future__ import annotations

import argparse
import asyncio
import json
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from bench_daemon import BIN, as_unit, config, cpu_s, free_port, rss_mb  # noqa: E402
from bench_loop import DEPTH_MM, start, stop  # noqa: E402
from bench_web import pct  # noqa: E402

from lathed.client import call  # noqa: E402
from tests.test_opcua import WATCHDOG_S, Collect, every_sample, machine_node  # noqa: E402

CLIENTS = 10
PUBLISH_MS = 20
RATE_HZ = 20.0
STATUS_EVERY_S = 2.0
WATCHED = {"lathe": ["Spindle/RotationalSpeed", "Spindle/Load", "Spindle/mt:Override", "Axes/X", "Axes/Y",
                     "Chatter/ChatterIndex"],
           "mill": ["Spindle/RotationalSpeed", "Axes/X", "Axes/Z"]}


async def clients(url: str, seconds: float, ready: asyncio.Event) -> list[float]:
    from asyncua import Client
    lat: list[float] = []
    conns = []
    try:
        for _ in range(CLIENTS):
            c = Client(url, watchdog_intervall=WATCHDOG_S)
            await c.connect()
            conns.append(c)
            got = Collect()
            sub = await c.create_subscription(PUBLISH_MS, got)
            handle = 1
            for machine, paths in WATCHED.items():
                for p in paths:
                    node = await machine_node(c, machine, "mt:Monitoring", *p.split("/"))
                    await every_sample(sub, node, handle)
                    handle += 1
            c.got = got
        ready.set()
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            await asyncio.sleep(0.5)
            for c in conns:
                while not c.got.changes.empty():
                    at, dv = c.got.changes.get_nowait()
                    if dv.StatusCode.is_good() and dv.SourceTimestamp is not None:
                        lat.append(at - dv.SourceTimestamp.timestamp())
    finally:
        for c in conns:
            try:
                await c.disconnect()
            except Exception:      # a loaded server may not answer the close in time: the figures stand
                pass
    return lat


def phase(proc: subprocess.Popen, sock: Path, seconds: float, ua: subprocess.Popen | None) -> dict:
    c0, t0 = cpu_s(proc.pid), time.monotonic()
    u0 = cpu_s(ua.pid) if ua else None
    p50s, p99s, rss = [], [], []
    end = t0 + seconds
    while time.monotonic() < end:
        time.sleep(STATUS_EVERY_S)
        lag = call("status", sock_path=sock)["daemon"]["loop_lag_ms"]
        if lag["p50"] is not None:
            p50s.append(lag["p50"])
            p99s.append(lag["p99"])
        if ua:
            rss.append(rss_mb(ua.pid))
    wall = time.monotonic() - t0
    out = {"seconds": round(wall, 1), "daemon_cpu_pct": 100 * (cpu_s(proc.pid) - c0) / wall,
           "daemon_rss_mb": rss_mb(proc.pid),
           "lag_p50_ms": statistics.median(p50s) if p50s else None, "lag_p99_worst_ms": max(p99s, default=None)}
    if ua:
        out.update(opcua_cpu_pct=100 * (cpu_s(ua.pid) - u0) / wall, opcua_rss_mb_max=max(rss, default=None))
    return out


def run(duration: float, warmup: float) -> dict:
    with tempfile.TemporaryDirectory(prefix="bench-opcua-") as d:
        tmp = Path(d)
        cfg = config(tmp)
        cfg.write_text(cfg.read_text().replace("[simulator]", f"[simulator]\ndepth_mm = {DEPTH_MM}", 1))
        sock = tmp / "run" / "lathed.sock"
        proc = start(cfg, tmp)
        ua = None
        try:
            time.sleep(warmup)
            res = {"none": phase(proc, sock, duration, None)}
            port = free_port()
            uacfg = tmp / "lathed-opcua.toml"
            uacfg.write_text(f'[opcua]\nport = {port}\nsocket = "{sock}"\nstate_dir = "{tmp / "opcua"}"\n'
                             f"rate_hz = {RATE_HZ}\n")
            log = open(tmp / "lathed-opcua.log", "wb")
            ua = subprocess.Popen([str(BIN / "lathed-opcua"), "--config", str(uacfg)], stdout=log,
                                  stderr=subprocess.STDOUT, **as_unit("lathed-opcua"))
            url = f"opc.tcp://127.0.0.1:{port}"

            async def measure() -> tuple[dict, list[float]]:
                deadline = time.monotonic() + 240    # a loaded machine: lathed-opcua may take a minute to listen
                while time.monotonic() < deadline and ua.poll() is None:
                    try:
                        socket.create_connection(("127.0.0.1", port), timeout=1).close()
                        break
                    except OSError:
                        await asyncio.sleep(0.5)
                why = "no client got through"
                while time.monotonic() < deadline + 300:   # its nodes appear with the first status and samples
                    ready = asyncio.Event()
                    task = asyncio.create_task(clients(url, duration, ready))
                    waiter = asyncio.create_task(ready.wait())
                    await asyncio.wait({task, waiter}, return_when=asyncio.FIRST_COMPLETED)
                    if ready.is_set():
                        break
                    waiter.cancel()
                    try:
                        task.result()
                    except Exception as e:    # kept: a node the watch list names wrong fails here every try
                        why = f"{type(e).__name__}: {e}"
                        await asyncio.sleep(0.2)
                else:
                    raise SystemExit(f"bench_plant_opcua: the clients could not watch their nodes ({why}); "
                                     f"lathed-opcua's log: {(tmp / 'lathed-opcua.log').read_text()[-2000:]}")
                stats = await asyncio.to_thread(phase, proc, sock, duration, ua)
                return stats, await task
            res["opcua"], lat = asyncio.run(measure())
            lat_ms = [x * 1000 for x in lat]
            res["opcua"].update(latency_median_ms=pct(lat_ms, 50), latency_p99_ms=pct(lat_ms, 99),
                                latency_max_ms=max(lat_ms, default=None), latency_n=len(lat_ms))
        finally:
            if ua:
                ua.terminate()
                try:
                    ua.wait(60)      # a loaded machine: its stop can take a while
                except subprocess.TimeoutExpired:
                    ua.kill()
                    ua.wait()
            stop(proc, tmp)
    return res


def _f(v, digits=1, unit=""):
    return "-" if v is None else f"{v:.{digits}f}{unit}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=60.0, help="seconds per phase")
    ap.add_argument("--warmup", type=float, default=20.0)
    ap.add_argument("--json", help="also write the results here")
    a = ap.parse_args()
    r = run(a.duration, a.warmup)
    if a.json:
        Path(a.json).write_text(json.dumps(r, indent=2))
    n, o = r["none"], r["opcua"]
    items = sum(len(p) for p in WATCHED.values())
    print(f"OPC UA: default config on the simulator, {DEPTH_MM:g} mm cuts, {a.duration:.0f} s per phase; "
          f"{CLIENTS} asyncua clients x {items} monitored values (every sample), publishing interval "
          f"{PUBLISH_MS} ms, lathed-opcua taking {RATE_HZ:g} frames/s from the daemon\n")
    print("| measure | daemon alone | daemon + lathed-opcua + 10 clients |")
    print("|---|---|---|")
    print(f"| daemon CPU | {_f(n['daemon_cpu_pct'], 1, ' %')} | {_f(o['daemon_cpu_pct'], 1, ' %')} |")
    print(f"| daemon RSS | {_f(n['daemon_rss_mb'], 1, ' MB')} | {_f(o['daemon_rss_mb'], 1, ' MB')} |")
    print(f"| daemon loop lag p50 (median of 10 s windows) | {_f(n['lag_p50_ms'], 2, ' ms')} | "
          f"{_f(o['lag_p50_ms'], 2, ' ms')} |")
    print(f"| daemon loop lag p99 (worst 10 s window) | {_f(n['lag_p99_worst_ms'], 1, ' ms')} | "
          f"{_f(o['lag_p99_worst_ms'], 1, ' ms')} |")
    print(f"| lathed-opcua CPU | | {_f(o['opcua_cpu_pct'], 1, ' %')} |")
    print(f"| lathed-opcua RSS, max | | {_f(o['opcua_rss_mb_max'], 1, ' MB')} |")
    print(f"| sample on the bus -> client data change, median / p99 / max ({o['latency_n']} notifications) | | "
          f"{_f(o['latency_median_ms'], 0, ' ms')} / {_f(o['latency_p99_ms'], 0, ' ms')} / "
          f"{_f(o['latency_max_ms'], 0, ' ms')} |")
    print("\nThe 10 clients run in the benchmark's own process on the same two cores.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
