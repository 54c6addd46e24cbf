"""The OPC UA part of bench/bench_hostile.py (issue 35, defect 6): lathed-opcua beside the daemon,
flooded during the load, and a fresh client timed all along.

  idle TCP       IDLE_SOCKETS connections that never send a Hello, each re-opened (at most
                 IDLE_RATE a second) when the server closes it, as the probe's 4,187 did
  subscriptions  STORM_CLIENTS anonymous clients, each asking for STORM_SUBS subscriptions x
                 STORM_ITEMS monitored items at 10 ms (the probe's one client), keeping what they get
  fresh client   every PROBE_EVERY_S a new client connects, reads the lathe's spindle speed by its
                 40501 path, and leaves: the time from connect to value (bar: FRESH_BAR_S)

Runs in threads of the bench's process, each loop its own; lathed-opcua at its unit's Nice.
"""
from __future__ import annotations

import asyncio
import contextlib
import resource
import socket
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from bench_daemon import BIN, as_unit, cpu_s, free_port, rss_mb  # noqa: E402

IDLE_SOCKETS = 1000
IDLE_RATE = 200.0
STORM_CLIENTS = 4
STORM_SUBS, STORM_ITEMS, STORM_MS = 50, 200, 10
PROBE_EVERY_S = 2.0
FRESH_BAR_S = 2.0
WATCHED = ("RotationalSpeed", "Load", "Override")     # the lathe's spindle: values that change every poll


class Threaded:
    def __init__(self):
        self.stop = threading.Event()
        self.errors: list[str] = []
        self.thread = threading.Thread(target=self._guarded, daemon=True, name=type(self).__name__)

    def start(self):
        self.thread.start()
        return self

    def _guarded(self) -> None:
        try:
            self.run()
        except Exception as e:     # the bench reports its failures, it does not crash on them
            self.errors.append(f"{type(e).__name__}: {e}")

    def join(self) -> None:
        self.stop.set()
        if self.thread.ident is not None:     # started
            self.thread.join(60)


class OpcUa:
    """lathed-opcua on a free port, a client of the daemon's socket, with its default limits."""

    def __init__(self, tmp: Path, sock: Path):
        self.port = free_port()
        self.url = f"opc.tcp://127.0.0.1:{self.port}"
        self.cfg = tmp / "lathed-opcua.toml"
        self.cfg.write_text(f'[opcua]\nport = {self.port}\nsocket = "{sock}"\nstate_dir = "{tmp / "opcua"}"\n')
        self.logfile = tmp / "lathed-opcua.log"
        self.log = open(self.logfile, "wb")
        self.proc = subprocess.Popen([str(BIN / "lathed-opcua"), "--config", str(self.cfg)], stdout=self.log,
                                     stderr=subprocess.STDOUT, **as_unit("lathed-opcua"))

    def wait_serving(self, timeout: float = 240.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise SystemExit(f"lathed-opcua exited {self.proc.returncode}: "
                                 f"{self.logfile.read_text(errors='replace')[-2000:]}")
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=1):
                    return
            except OSError:
                time.sleep(0.5)
        raise SystemExit("lathed-opcua did not listen")

    def stop(self) -> str:
        self.proc.terminate()
        try:
            self.proc.wait(60)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
            return "killed"
        finally:
            self.log.close()
        return f"code {self.proc.returncode}"

    def log_lines(self) -> int:
        return sum(1 for _ in self.logfile.open(errors="replace"))


class IdleFlood(Threaded):
    """Connections that never send a Hello, re-opened when closed."""

    def __init__(self, port: int, n: int = IDLE_SOCKETS):
        super().__init__()
        self.port, self.n = port, n
        self.opened = self.closed_by_server = self.connect_failed = self.max_open = 0

    def run(self) -> None:
        soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
        resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, min(hard, self.n + 512)), hard))
        socks: list[socket.socket] = []
        budget, last = 0.0, time.monotonic()
        while not self.stop.wait(0.05):
            now = time.monotonic()
            budget = min(budget + (now - last) * IDLE_RATE, IDLE_RATE)
            last = now
            alive = []
            for s in socks:
                try:
                    if s.recv(1) == b"":
                        raise ConnectionResetError
                    alive.append(s)
                except BlockingIOError:
                    alive.append(s)
                except OSError:
                    s.close()
                    self.closed_by_server += 1
            socks = alive
            while len(socks) < self.n and budget >= 1:
                budget -= 1
                s = socket.socket()
                s.setblocking(False)
                try:
                    s.connect(("127.0.0.1", self.port))
                except BlockingIOError:
                    pass
                except OSError:
                    s.close()
                    self.connect_failed += 1
                    continue
                socks.append(s)
                self.opened += 1
            self.max_open = max(self.max_open, len(socks))
        for s in socks:
            s.close()


async def _lathe_node(c, *path: str):
    from asyncua import ua

    from lathed.opcua.nodesets import MACHINE_TOOL, MACHINERY
    from lathed.opcua.space import NAMESPACE
    ns = await c.get_namespace_array()
    folder = c.get_node(ua.NodeId(1001, ns.index(MACHINERY)))
    return await folder.get_child([ua.QualifiedName("lathe", ns.index(NAMESPACE)),
                                   ua.QualifiedName("Monitoring", ns.index(MACHINE_TOOL)),
                                   *(ua.QualifiedName(p, ns.index(NAMESPACE)) for p in path)])


class Storm(Threaded):
    """Anonymous clients asking for far more subscriptions and items than a session gets."""

    def __init__(self, url: str):
        super().__init__()
        self.url = url
        self.subs = self.subs_refused = self.items = self.items_refused = self.notifications = 0
        self.reconnects = self.attempts = 0

    def run(self) -> None:
        asyncio.run(self._main())

    async def _main(self) -> None:
        clients = asyncio.gather(*(self._client(i) for i in range(STORM_CLIENTS)))
        while not (self.stop.is_set() or clients.done()):
            await asyncio.sleep(0.1)
        # the load is over: a client waiting on a request (up to its 30 s timeout) is not waited
        # for; one closing its session is given a few seconds, then left (the server is stopped next)
        clients.cancel()
        await asyncio.wait({clients}, timeout=5.0)
        clients.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await clients

    async def _client(self, i: int) -> None:
        from asyncua import Client, ua
        storm = self

        class Count:
            def datachange_notification(self, node, val, data):
                storm.notifications += 1

            def status_change_notification(self, status):
                pass
        while not self.stop.is_set():
            self.attempts += 1
            try:
                async with Client(self.url, timeout=30, watchdog_intervall=30) as c:
                    nodes = [await _lathe_node(c, "Spindle", n) if n != "Override" else
                             await _override(c) for n in WATCHED]
                    for _ in range(STORM_SUBS):
                        if self.stop.is_set():       # the load is over: asking on would hold up join()
                            break
                        try:
                            sub = await c.create_subscription(STORM_MS, Count())
                            self.subs += 1
                        except ua.uaerrors.BadTooManySubscriptions:
                            self.subs_refused += 1
                            continue
                        res = await sub.subscribe_data_change([nodes[k % len(nodes)] for k in range(STORM_ITEMS)],
                                                              sampling_interval=0)
                        ok = sum(isinstance(h, int) for h in res)
                        self.items += ok
                        self.items_refused += len(res) - ok
                    while not self.stop.is_set():
                        await asyncio.sleep(0.5)
                return
            except Exception:
                self.reconnects += 1
                await asyncio.sleep(1.0)


async def _override(c):
    from asyncua import ua

    from lathed.opcua.nodesets import MACHINE_TOOL
    spindle = await _lathe_node(c, "Spindle")
    ns = await c.get_namespace_array()
    return await spindle.get_child(ua.QualifiedName("Override", ns.index(MACHINE_TOOL)))


class FreshClient(Threaded):
    """A new client every PROBE_EVERY_S: connect, read the spindle speed, leave."""

    def __init__(self, url: str):
        super().__init__()
        self.url = url
        self.times: list[tuple[float, float | None, str | None]] = []   # (wall t, seconds or None, error)

    def run(self) -> None:
        asyncio.run(self._main())

    async def _main(self) -> None:
        from asyncua import Client
        while not self.stop.is_set():
            t0, wall = time.monotonic(), time.time()
            try:
                async with Client(self.url, timeout=10, watchdog_intervall=30) as c:
                    dv = await (await _lathe_node(c, "Spindle", "RotationalSpeed")).read_data_value()
                    assert dv.Value.Value is not None
                self.times.append((wall, time.monotonic() - t0, None))
            except Exception as e:
                self.times.append((wall, None, f"{type(e).__name__}: {e}"[:200]))
            await asyncio.sleep(max(0.0, PROBE_EVERY_S - (time.monotonic() - t0)))


def figures(ua: OpcUa, idle: IdleFlood, storm: Storm, probe: FreshClient, t_load: float, t_end: float,
            cpu0: float, wall: float) -> dict:
    during = [(t, s, e) for t, s, e in probe.times if t_load <= t <= t_end]
    ok = [s for _, s, e in during if s is not None]
    return {"fresh_client": {"n": len(during), "failed": sum(s is None for _, s, _ in during),
                             "over_bar": sum(s is None or s > FRESH_BAR_S for _, s, _ in during),
                             "median_s": statistics.median(ok) if ok else None, "max_s": max(ok, default=None),
                             "errors": sorted({e for _, _, e in during if e})[:3],
                             "before_load": [round(s, 3) for t, s, _ in probe.times if t < t_load and s is not None][-3:]},
            "idle_tcp": {"opened": idle.opened, "closed_by_server": idle.closed_by_server,
                         "connect_failed": idle.connect_failed, "max_open": idle.max_open},
            "storm": {"clients": STORM_CLIENTS, "subscriptions": storm.subs, "subscriptions_refused": storm.subs_refused,
                      "monitored_items": storm.items, "monitored_items_refused": storm.items_refused,
                      "notifications": storm.notifications, "reconnects": storm.reconnects,
                      "connects_tried": storm.attempts},
            "opcua_cpu_pct": 100 * (cpu_s(ua.proc.pid) - cpu0) / wall if ua.proc.poll() is None else None,
            "opcua_rss_mb": rss_mb(ua.proc.pid) if ua.proc.poll() is None else None,
            "opcua_log_lines": ua.log_lines(),
            "errors": [f"{n}: {e}" for n, o in (("idle", idle), ("storm", storm), ("probe", probe)) for e in o.errors]}


def report(r: dict) -> list[str]:
    """Table rows and the verdict line."""
    f = r["fresh_client"]
    cpu = "-" if r["opcua_cpu_pct"] is None else f"{r['opcua_cpu_pct']:.0f} %"
    rss = "-" if r["opcua_rss_mb"] is None else f"{r['opcua_rss_mb']:.0f} MB"
    rows = [f"| OPC UA fresh client during the floods: connect + read, median / max ({f['n']} tries) | "
            + ("-" if f["median_s"] is None else f"{f['median_s']:.2f} / {f['max_s']:.2f} s")
            + f"; {f['failed']} failed | < {FRESH_BAR_S:g} s each |",
            f"| OPC UA idle TCP flood (never a Hello) | {r['idle_tcp']} | closed by the server |",
            f"| OPC UA subscription storm ({STORM_CLIENTS} clients x {STORM_SUBS} x {STORM_ITEMS} items at "
            f"{STORM_MS} ms asked) | {r['storm']} | capped per session |",
            f"| lathed-opcua CPU during the load / RSS after / log lines | {cpu} / {rss} / {r['opcua_log_lines']} | |"]
    if r["errors"]:
        rows.append(f"| OPC UA bench errors | {'; '.join(r['errors'])} | |")
    ok = f["n"] > 0 and f["over_bar"] == 0
    verdict = (f"- lathed-opcua answers a fresh client within {FRESH_BAR_S:g} s during the floods: "
               f"{'PASS' if ok else 'FAIL'} ({f['n'] - f['over_bar']} of {f['n']} within the bar"
               + (f"; {f['errors'][0]}" if f["errors"] else "") + ")")
    return rows + ["", verdict]
