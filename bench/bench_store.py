"""Records per second the store sustains without delaying the event loop.

For each offered rate, records are submitted at that rate from the event
loop (as analyzers do: ``await store.record(...)``, acknowledged after a
durable commit) for a few seconds, while a ticker task measures how late the
loop wakes it (loop lag). Prints a Markdown table of medians and p99s; a
rate is sustained when nearly all records are acknowledged in time and the
p99 loop lag stays <= 10 ms (target 5,000/s).

    .venv/bin/python bench/bench_store.py [--seconds 3] [--rates 1000,2000,...]
"""
from __future__ import annotations

import argparse
import asyncio
import statistics
import tempfile
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


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=3.0)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--rates", default="1000,2000,5000,10000,15000,20000,40000")
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


if __name__ == "__main__":
    main()
