"""Records per second the store sustains without delaying the event loop.

For each offered rate, records are submitted at that rate from the event
loop (as analyzers do: ``await store.record(...)``, acknowledged after a
durable commit) for a few seconds, while a ticker task measures how late the
loop wakes it (loop lag). Prints a Markdown table of medians and p99s; a
rate is sustained when nearly all records are acknowledged in time and the
p99 loop lag stays <= 10 ms (target 5,000/s).

Then retention: a store holding ``--prune-rows`` old events is pruned
while a writer thread records one event every 5 ms; prints the prune rate
and that writer's commit latency, against the same writer with no prune.

    .venv/bin/python bench/bench_store.py [--seconds 3] [--rates 1000,2000,...] [--prune-rows 200000]
"""
from __future__ import annotations

import argparse
import asyncio
import statistics
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from lathed.store import Store

TICK_S = 0.001
LAG_LIMIT_MS = 10.0


async def ticker(lags: list[float], stop: asyncio.Event) -> None:
    while not stop.is_set():
        t0 = time.perf_counter()
        await asyncio.sleep(TICK_S)
        lags.append((time.perf_counter() - t0 - TICK_S) * 1e3)


async def offer(store: Store, rate: float, seconds: float) -> dict:
    lags: list[float] = []
    latencies: list[float] = []
    stop = asyncio.Event()
    tick = asyncio.create_task(ticker(lags, stop))
    pending: set[asyncio.Future] = set()

    def done(t_sub: float):
        return lambda _f: latencies.append((time.perf_counter() - t_sub) * 1e3)

    start = time.perf_counter()
    issued = 0
    while (now := time.perf_counter()) - start < seconds:
        due = int(rate * (now - start)) - issued
        for _ in range(due):
            # a task per record, as an analyzer awaiting store.record() would be: conservative
            fut = asyncio.ensure_future(store.record("bench", "bench", {"seq": issued, "value": 1.5}))
            fut.add_done_callback(done(time.perf_counter()))
            pending.add(fut)
            fut.add_done_callback(pending.discard)
            issued += 1
        await asyncio.sleep(TICK_S)
    in_time = len(latencies)
    await asyncio.gather(*pending)
    elapsed = time.perf_counter() - start
    stop.set()
    await tick
    lag = np.array(lags)
    lat = np.array(latencies)
    return {"offered": rate, "issued": issued, "acked_in_time_per_s": in_time / seconds,
            "drain_s": elapsed - seconds,
            "lag_p50": float(np.median(lag)), "lag_p99": float(np.percentile(lag, 99)),
            "lat_p50": float(np.median(lat)), "lat_p99": float(np.percentile(lat, 99))}


async def run_rate(rate: float, seconds: float, repeats: int) -> dict:
    results = []
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as d:
            store = Store(Path(d) / "bench.db", machine_id="bench")
            try:
                results.append(await offer(store, rate, seconds))
            finally:
                await asyncio.to_thread(store.close)
    # medians over the repeats
    return {k: statistics.median(r[k] for r in results) for k in results[0]}


def commit_latencies(store: Store, seconds: float | None = None, until=None) -> list[float]:
    """One event every 5 ms from a thread, each waited for: its commit latencies (ms)."""
    out: list[float] = []
    t_end = None if seconds is None else time.monotonic() + seconds
    while (until is None or not until.is_set()) and (t_end is None or time.monotonic() < t_end):
        t0 = time.perf_counter()
        store.record_future("live", "bench", {}).result(30)
        out.append((time.perf_counter() - t0) * 1e3)
        time.sleep(0.005)
    return out


def bench_prune(rows: int) -> None:
    with tempfile.TemporaryDirectory() as d:
        store = Store(Path(d) / "bench.db")
        try:
            last = None
            for k in range(rows):
                last = store.record_future("tick", "bench", {"k": k, "rpm": 2000.0, "index": 0.9}, t=1000.0 + k)
            last.result(600)
            old = store.clock.now()    # retention's clock: the live events below are newer
            idle = commit_latencies(store, seconds=2.0)
            done = threading.Event()
            lat: list[float] = []
            th = threading.Thread(target=lambda: lat.extend(commit_latencies(store, until=done)))
            th.start()
            t0 = time.perf_counter()
            removed = store.prune(old, [])["events"]
            dt = time.perf_counter() - t0
            done.set()
            th.join()
        finally:
            store.close()
    q = lambda xs, f: float(np.quantile(xs, f))     # noqa: E731
    print(f"\nretention: {removed:,} old events pruned in {dt:.1f} s ({removed / dt:,.0f} rows/s)\n")
    print("| live writer, one event per 5 ms | commit latency p50 ms | p99 ms | max ms |")
    print("|---|---:|---:|---:|")
    for name, xs in (("store idle", idle), ("while pruning", lat)):
        print(f"| {name} | {q(xs, 0.5):.1f} | {q(xs, 0.99):.1f} | {max(xs):.1f} |")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=3.0)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--rates", default="1000,2000,5000,10000,15000,20000,40000")
    p.add_argument("--prune-rows", type=int, default=200_000, help="old events to prune (0: skip)")
    args = p.parse_args()
    rows = [asyncio.run(run_rate(float(r), args.seconds, args.repeats)) for r in args.rates.split(",")]
    print(f"store: SQLite WAL, synchronous=FULL, group commit; {args.seconds:g} s per rate, "
          f"median of {args.repeats} runs\n")
    print("| offered rec/s | acked in time rec/s | commit latency p50 / p99 ms | loop lag p50 / p99 ms | "
          "drain after s | sustained |")
    print("|---:|---:|---:|---:|---:|:---:|")
    best = 0.0
    for r in rows:
        ok = r["acked_in_time_per_s"] >= 0.95 * r["offered"] and r["lag_p99"] <= LAG_LIMIT_MS and r["drain_s"] < 0.5
        if ok:
            best = max(best, r["offered"])
        print(f"| {r['offered']:,.0f} | {r['acked_in_time_per_s']:,.0f} | {r['lat_p50']:.1f} / {r['lat_p99']:.1f} | "
              f"{r['lag_p50']:.2f} / {r['lag_p99']:.2f} | {r['drain_s']:.2f} | {'yes' if ok else 'no'} |")
    print(f"\nhighest sustained offered rate with p99 loop lag <= {LAG_LIMIT_MS:g} ms: {best:,.0f} records/s")
    if args.prune_rows:
        bench_prune(args.prune_rows)


if __name__ == "__main__":
    main()
