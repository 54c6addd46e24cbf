"""The operator view's cost (issue 14): the daemon with and without 5 browsers watching.

Runs the default config (etc/lathed.toml, simulator spawned, every part cut
3 mm deep so that chatter happens and suppression acts; its ``remember = true`` turned
off, as bench_loop.py does, so that every cut's cure is an alarm's) on free ports. One
daemon, 5 headless Chromium pages (Debian's /usr/bin/chromium via Playwright)
open on lathed-web throughout, and ``--cycles`` pairs of phases of
``--seconds`` each, interleaved so that the shared machine's drift falls on
both alike:

  none   lathed-web stopped: no subscriber (the pages wait, disconnected)
  web    lathed-web running, subscribed to the daemon, the 5 pages reloaded and live on it

Per phase: the daemon's CPU (its process only, from /proc), its event-loop lag
(status -> daemon.loop_lag_ms, p50 and p99 of its 10 s windows), the chatter
loop's alarm -> speed write latency (``alarm_to_write_ms`` of the phase's
suppression_action events); in the web phases the CPU and RSS of lathed-web
and the time from a sample's measurement (its ``t``, stamped by the driver as
it publishes on the bus) to the page receiving its frame (Date.now() in the
page as the frame arrives; same clock). The table gives medians over the
cycles, and the median of each cycle's web / none ratio.

    .venv/bin/python bench/bench_web.py [--cycles 6] [--seconds 20] [--warmup 20] [--json FILE]
"""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_daemon import BIN, as_unit, config, cpu_s, free_port, rss_mb  # noqa: E402
from bench_loop import DEPTH_MM, start, stop  # noqa: E402

from lathed.client import call  # noqa: E402

BROWSERS = 5
STATUS_EVERY_S = 2.0
CHROMIUM = "/usr/bin/chromium"
# wraps the page's EventSource: for each frame, now - t of every sample in it
LATENCY_PROBE = """
window.__lat = [];
const ES = window.EventSource;
window.EventSource = function (url) {
  const es = new ES(url);
  es.addEventListener("message", (e) => {
    const now = Date.now() / 1000, m = JSON.parse(e.data);
    if (m.type !== "frame") return;
    for (const [k, s] of Object.entries(m.samples || {})) if (window.__lat.length < 200000) window.__lat.push(now - s[0]);
  });
  return es;
};
"""


def pct(xs: list[float], p: float) -> float | None:
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(p / 100 * len(xs)))] if xs else None


def phase(proc: subprocess.Popen, sock: Path, seconds: float, web: subprocess.Popen | None) -> dict:
    first_id = call("events", {"limit": 1}, sock_path=sock)
    first_id = first_id[-1]["id"] if first_id else 0
    c0, t0 = cpu_s(proc.pid), time.monotonic()
    w0 = cpu_s(web.pid) if web else None
    p50s, p99s, rss = [], [], []
    end = t0 + seconds
    while time.monotonic() < end:
        time.sleep(STATUS_EVERY_S)
        lag = call("status", sock_path=sock)["daemon"]["loop_lag_ms"]
        if lag["p50"] is not None:
            p50s.append(lag["p50"])
            p99s.append(lag["p99"])
        if web:
            rss.append(rss_mb(web.pid))
    wall = time.monotonic() - t0
    out = {"seconds": round(wall, 1), "daemon_cpu_pct": 100 * (cpu_s(proc.pid) - c0) / wall,
           "lag_p50_ms": statistics.median(p50s) if p50s else None, "lag_p99_worst_ms": max(p99s, default=None)}
    acts = [e for e in call("events", {"kind": "suppression_action", "since_id": first_id, "limit": 10_000},
                            sock_path=sock) if e["payload"].get("alarm_to_write_ms") is not None]
    lat = [e["payload"]["alarm_to_write_ms"] for e in acts]
    out.update(actions=len(lat), alarm_to_write_median_ms=pct(lat, 50), alarm_to_write_max_ms=max(lat, default=None))
    if web:
        out.update(web_cpu_pct=100 * (cpu_s(web.pid) - w0) / wall, web_rss_mb_max=max(rss, default=None))
    return out


def start_web(port: int, sock: Path) -> subprocess.Popen:
    return subprocess.Popen([str(BIN / "lathed-web"), "--port", str(port), "--socket", str(sock)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, **as_unit("lathed-web"))


def subscribers(sock: Path) -> int:
    return call("status", sock_path=sock)["daemon"]["control"]["subscribers"]


def until(cond, timeout: float, what: str) -> None:
    end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > end:
            raise SystemExit(f"bench_web: {what} did not happen within {timeout:g} s")
        time.sleep(0.1)


def chromium_at(nice: int, tmp: Path) -> str:
    """Chromium started at ``nice`` (its renderers inherit it): a kiosk page on the
    machine PC run as the units run lathed-web (Nice=10), not at the daemon's own level."""
    if not nice:
        return CHROMIUM
    wrapper = tmp / "chromium-nice"
    wrapper.write_text(f'#!/bin/sh\nexec nice -n {int(nice)} {CHROMIUM} "$@"\n')
    wrapper.chmod(0o755)
    return str(wrapper)


def run(cycles: int, seconds: float, warmup: float, browsers: int = BROWSERS, browser_nice: int = 0) -> dict:
    from playwright.sync_api import sync_playwright
    with tempfile.TemporaryDirectory(prefix="bench-web-") as d:
        tmp = Path(d)
        cfg = config(tmp)
        text = cfg.read_text().replace("[simulator]", f"[simulator]\ndepth_mm = {DEPTH_MM}", 1)
        # remembered cures would change the speed before chatter: no alarm, no alarm -> write to time
        if "\nremember = true" not in text:
            raise SystemExit("bench_web.py: etc/lathed.toml no longer sets remember = true in [analyzer.suppress]")
        cfg.write_text(text.replace("\nremember = true", "\nremember = false", 1))
        sock = tmp / "run" / "lathed.sock"
        proc = start(cfg, tmp)
        port = free_port()
        web = start_web(port, sock)
        res: dict[str, list] = {"none": [], "web": [], "latency_ms": []}
        try:
            time.sleep(warmup)
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=chromium_at(browser_nice, tmp), args=["--no-sandbox"])
                pages = []
                for _ in range(browsers):
                    page = browser.new_page(viewport={"width": 1600, "height": 1300})
                    page.add_init_script(LATENCY_PROBE)
                    for _ in range(50):
                        try:
                            page.goto(f"http://127.0.0.1:{port}/")
                            break
                        except Exception:   # lathed-web still starting
                            time.sleep(0.2)
                    pages.append(page)
                for c in range(cycles):
                    web.terminate()
                    web.wait(10)
                    until(lambda: subscribers(sock) == 0, 10, "the daemon dropping lathed-web's subscription")
                    res["none"].append(phase(proc, sock, seconds, None))
                    web = start_web(port, sock)
                    until(lambda: subscribers(sock) == 1, 20, "lathed-web subscribing")
                    for page in pages:      # (a page's EventSource comes back by itself, after a backoff)
                        page.reload()
                        page.wait_for_selector("#link.ok", timeout=30_000)
                    res["web"].append(phase(proc, sock, seconds, web))
                    res["latency_ms"] += [x * 1000 for page in pages for x in page.evaluate("window.__lat")]
                    print(f"cycle {c + 1}/{cycles}: daemon CPU {res['none'][-1]['daemon_cpu_pct']:.1f} % "
                          f"without, {res['web'][-1]['daemon_cpu_pct']:.1f} % with", file=sys.stderr)
                browser.close()
        finally:
            web.terminate()
            web.wait(10)
            stop(proc, tmp)
    return res


def _f(v, digits=1, unit=""):
    return "-" if v is None else f"{v:.{digits}f}{unit}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cycles", type=int, default=6, help="pairs of phases (none, web)")
    ap.add_argument("--seconds", type=float, default=20.0, help="seconds per phase")
    ap.add_argument("--warmup", type=float, default=20.0)
    ap.add_argument("--browsers", type=int, default=BROWSERS,
                    help="pages open (0: the daemon's cost of lathed-web's subscription alone)")
    ap.add_argument("--browser-nice", type=int, default=0, choices=range(0, 20), metavar="0..19",
                    help="start Chromium at this nice (default 0: the browsers compete with the daemon "
                         "as any process would; 10: as lathed-web's unit runs)")
    ap.add_argument("--json", help="also write the results here")
    a = ap.parse_args()
    r = run(a.cycles, a.seconds, a.warmup, a.browsers, a.browser_nice)
    if a.json:
        Path(a.json).write_text(json.dumps(r, indent=2))
    n, w = r["none"], r["web"]

    def med(rows, key):
        xs = [x[key] for x in rows if x.get(key) is not None]
        return statistics.median(xs) if xs else None

    def ratio(key):
        rs = [b[key] / a_[key] for a_, b in zip(n, w) if a_.get(key) and b.get(key) is not None]
        return f"{statistics.median(rs):.2f} ({min(rs):.2f}-{max(rs):.2f})" if rs else "-"

    acts = sum(x["actions"] for x in n), sum(x["actions"] for x in w)
    print(f"Operator view cost: default config on the simulator, {DEPTH_MM:g} mm cuts; {a.cycles} interleaved "
          f"cycles of {a.seconds:.0f} s without and {a.seconds:.0f} s with lathed-web and {a.browsers} Chromium "
          f"pages on it{f' (Chromium at nice {a.browser_nice})' if a.browser_nice else ''}; medians over the cycles\n")
    print(f"| measure | no clients | lathed-web + {a.browsers} browsers | ratio with / without, median (range) "
          "(bar: <= 1.10) |")
    print("|---|---|---|---|")

    def row(label, key, digits, unit):
        print(f"| {label} | {_f(med(n, key), digits, unit)} | {_f(med(w, key), digits, unit)} | {ratio(key)} |")
    row("daemon CPU", "daemon_cpu_pct", 1, " %")
    row("daemon loop lag p50", "lag_p50_ms", 2, " ms")
    row("daemon loop lag p99 (worst window of the phase)", "lag_p99_worst_ms", 1, " ms")
    row(f"chatter alarm -> speed write, median ({acts[0]} / {acts[1]} actions)", "alarm_to_write_median_ms", 1, " ms")
    row("chatter alarm -> speed write, max", "alarm_to_write_max_ms", 1, " ms")
    print(f"| lathed-web CPU | | {_f(med(w, 'web_cpu_pct'), 1, ' %')} | |")
    print(f"| lathed-web RSS, max | | {_f(max((x['web_rss_mb_max'] for x in w), default=None), 1, ' MB')} | |")
    lat = r["latency_ms"]
    print(f"| sample on the bus -> frame in the page, median / p99 ({len(lat)} samples) | | "
          f"{_f(pct(lat, 50), 0, ' ms')} / {_f(pct(lat, 99), 0, ' ms')} | |")
    print("\nThe browsers share the machine's 2 cores with the daemon in both phases (idle, waiting to "
          "reconnect, while lathed-web is stopped).")
    return 0


if __name__ == "__main__":
    sys.exit(main())
