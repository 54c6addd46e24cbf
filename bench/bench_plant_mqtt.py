"""MQTT end to end: records from the daemon's store through a real Mosquitto
to a subscriber, with a broker restart in the middle.

Each run fills a fresh local store with N chatter-alarm-sized events, starts
the daemon with only the mqtt_sink, and times until a persistent-session
subscriber holds every record; in the restart run the broker is stopped when
half have arrived and started again on the same port after --outage seconds.
Lost (records never received) must be 0; duplicates (the same message id
twice, allowed at QoS 1) are counted. CPU is the daemon's user+system time
over the run as a percentage of one core; RSS is the daemon's at the end.

    .venv/bin/python bench/bench_plant_mqtt.py [--records 20000] [--outage 5]
"""
from __future__ import annotations

import argparse
import asyncio
import json
import os
import sqlite3
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_daemon import BIN, cpu_s, rss_mb  # noqa: E402

from lathed.store import Store  # noqa: E402
from tests.conftest import Daemon, wait_until  # noqa: E402
from tests.mqtt_fixtures import Broker, Subscriber  # noqa: E402

NAME = "bench-cell"


def fill(db: Path, n: int) -> None:
    async def main():
        store = Store(db, machine_id=NAME)
        futs = [store.record_future("chatter_alarm", "chatter", {
            "machine": "lathe", "seq": i, "index": 2.5, "threshold": 1.8, "chatter_frequency_hz": 197.0,
            "rpm": 2500.0, "depth_mm": 3.0, "tool": "T0101", "material": "C45"}) for i in range(n)]
        await asyncio.gather(*map(asyncio.wrap_future, futs))
        await asyncio.to_thread(store.close)
    asyncio.run(main())


def _q(db: Path, sql: str):
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=10)
    try:
        return con.execute(sql).fetchone()[0]
    finally:
        con.close()


def forwarded(db: Path) -> int:
    return _q(db, "SELECT coalesce(max(outbox_id), 0) FROM forward_progress WHERE sink = 'mqtt'")


def run(tmp: Path, n: int, outage: float | None) -> dict:
    tmp.mkdir()
    db = tmp / "state" / "lathed.db"
    fill(db, n)
    last = _q(db, "SELECT max(id) FROM outbox")
    broker = Broker(tmp / "broker")
    broker.start()
    cfg = tmp / "lathed.toml"
    cfg.write_text(f"""
[daemon]
name = "{NAME}"
state_dir = "{tmp / 'state'}"
runtime_dir = "{tmp / 'run'}"
log_level = "warning"

[analyzer.mqtt]
plugin = "mqtt_sink"
host = "127.0.0.1"
port = {broker.port}
start_from = "oldest"      # the records filled in before the first start are the load
batch = 500
interval = "50ms"
timeout = "2s"
retry_initial = "100ms"
retry_max = "500ms"
""")
    sub = d = None
    down_s = 0.0
    try:
        sub = Subscriber(broker.port, f"lathed/{NAME}/lathe/events/#", client_id="bench-historian")
        d = Daemon(cfg, tmp / "run" / "lathed.sock")
        t0, c0 = time.monotonic(), cpu_s(d.proc.pid)
        d.wait_ready(60)
        if outage is not None:
            wait_until(lambda: len(sub.received()) >= n // 2, 300, what="half the records")
            broker.stop()
            down = time.monotonic()
            wait_until(lambda: time.monotonic() - down >= outage, outage + 5, what="the outage's end")
            broker.start()
            down_s = time.monotonic() - down
        # the sink's side: every record acknowledged by the broker (its saved progress)
        wait_until(lambda: forwarded(db) >= last, 300, interval=0.02, what="the sink's progress")
        sunk = time.monotonic() - t0
        # a count first (cheap), then distinct ids (duplicates only add to the count)
        wait_until(lambda: len(sub.messages) >= n, 300, interval=0.02, what="as many messages as records")
        wait_until(lambda: len({json.loads(p)["id"] for _, p, _ in sub.received()}) >= n, 60,
                   interval=0.1, what="every record at the subscriber")
        wall = time.monotonic() - t0
        cpu = 100 * (cpu_s(d.proc.pid) - c0) / wall
        rss = rss_mb(d.proc.pid)
    finally:
        if d is not None:
            d.stop()
        if sub is not None:
            sub.close()
        broker.stop()
    msgs = [json.loads(p) for _, p, _ in sub.received()]
    ids = [m["id"] for m in msgs]
    seqs = {m["payload"]["seq"] for m in msgs}
    return {"n": n, "wall": wall, "down": down_s, "rate": n / wall, "rate_up": n / (wall - down_s),
            "sink_rate": n / (sunk - down_s),
            "lost": n - len(seqs & set(range(n))), "dups": len(ids) - len(set(ids)), "cpu": cpu, "rss": rss}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--records", type=int, default=20_000)
    ap.add_argument("--outage", type=float, default=5.0, help="seconds the broker is down in the restart run")
    a = ap.parse_args()
    if not (BIN / "lathed").exists():
        raise SystemExit("run from the project's venv: .venv/bin/python bench/bench_plant_mqtt.py")
    with tempfile.TemporaryDirectory() as t:
        rows = [("steady", run(Path(t) / "steady", a.records, None)),
                (f"broker restart ({a.outage:g} s down) in the middle", run(Path(t) / "restart", a.records,
                                                                             a.outage))]
    print(f"| MQTT end to end ({a.records} records, QoS 1, Mosquitto on loopback, {os.cpu_count()} cores) "
          "| wall | events/s | events/s while the broker is up | sink events/s (PUBACKed) | lost | duplicates "
          "| daemon CPU | daemon RSS |")
    print("|---|---|---|---|---|---|---|---|---|")
    for label, r in rows:
        print(f"| {label} | {r['wall']:.1f} s | {r['rate']:.0f} | {r['rate_up']:.0f} | {r['sink_rate']:.0f} "
              f"| {r['lost']} | {r['dups']} "
              f"| {r['cpu']:.0f} % of one core | {r['rss']:.0f} MB |")
    print(f"\nCPU is over the whole run (outage included); machine load average at the end "
          f"{os.getloadavg()[0]:.1f} (other processes share the cores).")
    return 1 if any(r["lost"] for _, r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
