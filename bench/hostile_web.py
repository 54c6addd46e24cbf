"""The web floods of bench_hostile.py (issue 35 cases 5 and 7): lathed-web as its unit runs it
(Nice=10, LimitNOFILE=4096, the default set-up on loopback) under slow-header clients, idle
TCP connections and a crowd of live pages (half of them never reading), while a fresh client
asks for the page every second.

The flood is its own process (``python bench/hostile_web.py flood ...``): thousands of sockets
in one asyncio loop, each slot re-opened a second after the view closes it, so the pressure
never lets up; it writes its counts as JSON when told to stop (SIGTERM). The fresh client, the
view's /api/health, its RSS and its log are watched from the bench (``WebWatch``).
"""
from __future__ import annotations

import argparse
import asyncio
import http.client
import json
import os
import re
import resource
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

BIN = Path(sys.executable).parent
ROOT = Path(__file__).resolve().parent.parent
FRESH_BAR_S = 2.0
RSS_BAR_MB = 512.0               # the unit's MemoryMax
SLOW, IDLE, LIVE_READ, LIVE_STALL = 2000, 2000, 150, 250     # 4,400: beyond the unit's file limit


def unit_limits(unit: str = "lathed-web") -> tuple[int, int]:
    """(Nice=, LimitNOFILE=) of systemd/UNIT.service."""
    text = (ROOT / "systemd" / f"{unit}.service").read_text()
    nice = re.search(r"^Nice=(-?\d+)", text, re.M)
    nofile = re.search(r"^LimitNOFILE=(\d+)", text, re.M)
    return int(nice.group(1)) if nice else 0, int(nofile.group(1)) if nofile else 1024


def start_web(tmp: Path, sock: Path, port: int) -> subprocess.Popen:
    """lathed-web in the default set-up (no accounts, loopback), as its unit starts it."""
    nice, nofile = unit_limits()
    cfg = tmp / "lathed-web.toml"
    cfg.write_text(f'[web]\nport = {port}\nsocket = "{sock}"\n')

    def as_unit():
        os.nice(nice)
        resource.setrlimit(resource.RLIMIT_NOFILE, (nofile, nofile))
    log = open(tmp / "lathed-web.log", "wb")
    return subprocess.Popen([str(BIN / "lathed-web"), "--config", str(cfg)], stdout=log, stderr=log,
                            preexec_fn=as_unit)


# -- the flood (its own process) ------------------------------------------------------------------
class Flood:
    def __init__(self, port: int):
        self.port = port
        self.counts = {k: {"opened": 0, "closed_by_view": 0, "connect_failed": 0} for k in
                       ("slow_headers", "idle_tcp", "live_reading", "live_stalled")}
        self.counts["live_reading"]["refused_503"] = self.counts["live_stalled"]["refused_503"] = 0
        self.counts["live_reading"]["bytes_read"] = 0
        self.stop = asyncio.Event()

    async def slot(self, kind: str, i: int) -> None:
        c = self.counts[kind]
        await asyncio.sleep(i / 500)                  # 500 new connections a second at first
        while not self.stop.is_set():
            try:
                if kind == "live_stalled":
                    s = socket.socket()
                    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 2048)
                    s.setblocking(False)
                    await asyncio.get_running_loop().sock_connect(s, ("127.0.0.1", self.port))
                    r, w = await asyncio.open_connection(sock=s)
                else:
                    r, w = await asyncio.open_connection("127.0.0.1", self.port)
            except OSError:
                c["connect_failed"] += 1
                await asyncio.sleep(1.0)
                continue
            c["opened"] += 1
            try:
                await self._hold(kind, r, w, c)
            except (OSError, asyncio.IncompleteReadError):
                pass
            finally:
                w.close()
            await asyncio.sleep(1.0)                  # re-opened a second after the view closed it

    async def _hold(self, kind: str, r, w, c) -> None:
        host = f"Host: 127.0.0.1:{self.port}\r\n".encode()
        if kind == "slow_headers":
            w.write(b"GET / HTTP/1.1\r\n" + host)
            while not self.stop.is_set():
                await w.drain()
                try:
                    async with asyncio.timeout(5.0):
                        if not await r.read(1):
                            c["closed_by_view"] += 1
                            return
                except TimeoutError:
                    w.write(b"X-Slow: 1\r\n")         # a header line every 5 s, never the end
        elif kind == "idle_tcp":
            if not await r.read(1) and not self.stop.is_set():
                c["closed_by_view"] += 1
        else:
            w.write(b"GET /events HTTP/1.1\r\n" + host + b"\r\n")
            await w.drain()
            head = await r.readuntil(b"\r\n\r\n")
            if not head.startswith(b"HTTP/1.1 200"):
                c["refused_503" if head.startswith(b"HTTP/1.1 503") else "closed_by_view"] += 1
                await asyncio.sleep(4.0)             # as the page does: again after a while
                return
            if kind == "live_stalled":
                await self.stop.wait()
                return
            while not self.stop.is_set():
                data = await r.read(65536)
                if not data:
                    c["closed_by_view"] += 1
                    return
                c["bytes_read"] += len(data)

    async def run(self, slow: int, idle: int, live_read: int, live_stall: int) -> None:
        loop = asyncio.get_running_loop()
        loop.add_signal_handler(signal.SIGTERM, self.stop.set)
        tasks = [asyncio.create_task(self.slot(kind, i))
                 for kind, n in (("live_reading", live_read), ("live_stalled", live_stall),
                                 ("slow_headers", slow), ("idle_tcp", idle)) for i in range(n)]
        await self.stop.wait()
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)


def flood_main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--json", type=Path, required=True)
    for name, n in (("slow", SLOW), ("idle", IDLE), ("live-read", LIVE_READ), ("live-stall", LIVE_STALL)):
        ap.add_argument(f"--{name}", type=int, default=n)
    a = ap.parse_args(argv)
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
    f = Flood(a.port)
    asyncio.run(f.run(a.slow, a.idle, a.live_read, a.live_stall))
    a.json.write_text(json.dumps(f.counts))
    return 0


# -- watched from the bench -------------------------------------------------------------------
def _cpu_s(pid: int) -> float | None:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except OSError:
        return None


def _get(port: int, path: str, timeout: float) -> tuple[str, float]:
    """A fresh client: (outcome, seconds) of one GET on a new connection."""
    t = time.monotonic()
    c = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout)
    try:
        c.request("GET", path)
        r = c.getresponse()
        if path == "/events" and r.status == 200:
            line = r.readline()                      # the snapshot: the live stream began
            outcome = "live" if line.startswith(b"data: ") else "no snapshot"
        else:
            r.read()
            outcome = str(r.status)
    except TimeoutError:
        outcome = "timeout"
    except OSError as e:
        outcome = type(e).__name__
    finally:
        c.close()
    return outcome, time.monotonic() - t


class WebWatch:
    """Each second during the flood: a fresh client's page and live stream, /api/health, RSS."""

    def __init__(self, port: int, pid: int, log: Path):
        self.port, self.pid, self.log = port, pid, log
        self.page: list[tuple[str, float]] = []
        self.live: list[tuple[str, float]] = []
        self.health: list[dict] = []
        self.rss: list[float] = []
        self.stop = threading.Event()
        self.threads = [threading.Thread(target=self._every, args=(f, period), daemon=True, name=f.__name__)
                        for f, period in ((self._page, 1.0), (self._live, 2.0), (self._health, 2.0))]
        self.cpu: list[tuple[float, float]] = []          # (t, CPU seconds of lathed-web)
        self.flood: subprocess.Popen | None = None
        self.flood_json: Path | None = None
        self.log_at = 0

    def start_flood(self, tmp: Path) -> None:
        self.log_at = self.log.stat().st_size if self.log.exists() else 0
        self.flood_json = tmp / "web-flood.json"
        # the flood at the lowest priority: from the network it would cost this PC nothing; here
        # it shares the 2 cores with what it floods, and must not win by taking their CPU
        self.flood = subprocess.Popen([sys.executable, __file__, "flood", "--port", str(self.port),
                                       "--json", str(self.flood_json)], preexec_fn=lambda: os.nice(19))
        self.t0 = time.monotonic()
        self.cpu0 = _cpu_s(self.pid)
        for th in self.threads:
            th.start()

    def _every(self, f, period: float) -> None:
        while not self.stop.wait(period):
            f()

    def _page(self) -> None:
        self.page.append(_get(self.port, "/", 10.0))

    def _live(self) -> None:
        self.live.append(_get(self.port, "/events", 10.0))

    def _health(self) -> None:
        try:
            c = http.client.HTTPConnection("127.0.0.1", self.port, timeout=10)
            c.request("GET", "/api/health")
            self.health.append(json.loads(c.getresponse().read()))
            c.close()
        except (OSError, ValueError):
            pass
        try:
            for line in Path(f"/proc/{self.pid}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    self.rss.append(int(line.split()[1]) / 1024)
        except OSError:
            pass

    def end_flood(self) -> dict:
        if self.flood is None:
            return {}
        self.stop.set()
        for th in self.threads:
            th.join(30)
        cpu = _cpu_s(self.pid)
        cpu_pct = None if cpu is None or self.cpu0 is None else 100 * (cpu - self.cpu0) / (time.monotonic() - self.t0)
        flood = {}
        if self.flood is not None:
            self.flood.send_signal(signal.SIGTERM)
            try:
                self.flood.wait(60)
                flood = json.loads(self.flood_json.read_text())
            except (subprocess.TimeoutExpired, OSError, ValueError) as e:
                self.flood.kill()
                flood = {"error": f"the flood did not report: {e}"}
        log = self.log.read_bytes()[self.log_at:] if self.log.exists() else b""
        return {"flood": flood, "page": self._times(self.page), "live": self._times(self.live),
                "health_last": self.health[-1] if self.health else None,
                "link_down_seen": sum(not h["daemon"]["connected"] for h in self.health),
                "rss_peak_mb": max(self.rss, default=None), "cpu_pct": cpu_pct,
                "log_bytes": len(log), "log_lines": log.count(b"\n"),
                "log_tracebacks": log.count(b"Traceback")}

    @staticmethod
    def _times(xs: list[tuple[str, float]]) -> dict:
        ts = sorted(t for _, t in xs)
        outcomes: dict[str, int] = {}
        for o, _ in xs:
            outcomes[o] = outcomes.get(o, 0) + 1
        return {"n": len(xs), "outcomes": outcomes, "max_s": ts[-1] if ts else None,
                "p50_s": ts[len(ts) // 2] if ts else None,
                "over_bar": sum(t > FRESH_BAR_S for t in ts)}


def web_report(w: dict, daemon_dropped: int | None) -> tuple[list[str], list[tuple[str, bool, str]]]:
    """Table rows and verdicts (text, passed, detail) of the web floods."""
    f = w["flood"]
    rows = [f"| web flood: connections opened / closed by the view, by kind | " + "; ".join(
                f"{k} {v.get('opened')} / {v.get('closed_by_view')}" + (f" (503 {v['refused_503']})" if "refused_503"
                                                                       in v else "")
                for k, v in f.items() if isinstance(v, dict)) + " | |",
            f"| web: fresh client's page, answered / p50 / max | {w['page']['outcomes']} / "
            f"{_s(w['page']['p50_s'])} / {_s(w['page']['max_s'])} | 200 within {FRESH_BAR_S:g} s |",
            f"| web: fresh client's live stream, outcomes / p50 / max | {w['live']['outcomes']} / "
            f"{_s(w['live']['p50_s'])} / {_s(w['live']['max_s'])} | an answer (live, or 503 with a reason) "
            f"within {FRESH_BAR_S:g} s |",
            f"| web: lathed-web RSS peak / CPU during the flood | {_s(w['rss_peak_mb'], ' MB', 0)} / "
            f"{_s(w.get('cpu_pct'), ' %', 0)} | < {RSS_BAR_MB:g} MB (MemoryMax) |",
            f"| web: lathed-web log during the flood | {w['log_lines']} lines, {w['log_bytes']} bytes, "
            f"{w['log_tracebacks']} tracebacks | |",
            f"| web: lathed-web's view of itself at the end (/api/health) | "
            f"{json.dumps({k: (w['health_last'] or {}).get(k) for k in ('live', 'connections')})} | |"]
    page_ok = w["page"]["n"] > 0 and w["page"]["outcomes"].get("200", 0) == w["page"]["n"] \
        and w["page"]["over_bar"] == 0
    live_ok = w["live"]["n"] > 0 and w["live"]["over_bar"] == 0 and \
        sum(n for o, n in w["live"]["outcomes"].items() if o in ("live", "503")) == w["live"]["n"]
    verdicts = [
        ("lathed-web answers a fresh client within 2 s during the flood", page_ok and live_ok,
         f"page {w['page']['outcomes']} max {_s(w['page']['max_s'])}; live stream {w['live']['outcomes']} "
         f"max {_s(w['live']['max_s'])}"),
        # the daemon's count is of every subscriber (lathed-web's and lathed-opcua's links alike)
        ("the daemon dropped no subscriber (lathed-web, lathed-opcua); lathed-web's link never down",
         w["link_down_seen"] == 0 and daemon_dropped == 0,
         f"{daemon_dropped} subscribers dropped by the daemon, lathed-web's link seen down {w['link_down_seen']} times"),
        (f"lathed-web within its MemoryMax ({RSS_BAR_MB:g} MB), no log flood",
         w["rss_peak_mb"] is not None and w["rss_peak_mb"] < RSS_BAR_MB and w["log_tracebacks"] == 0
         and w["log_bytes"] < (1 << 20),
         f"RSS peak {_s(w['rss_peak_mb'], ' MB', 0)}, log {w['log_bytes']} bytes, {w['log_tracebacks']} tracebacks")]
    return rows, verdicts


def _s(x, unit: str = " s", p: int = 2) -> str:
    return "-" if x is None else f"{x:.{p}f}{unit}"


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "flood":
        sys.exit(flood_main(sys.argv[2:]))
    sys.exit("usage: hostile_web.py flood --port N --json FILE  (bench_hostile.py runs it)")
