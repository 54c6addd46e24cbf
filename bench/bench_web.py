"""The operator view's cost (issue 14): the daemon with and without 5 browsers watching.

Runs the default config (etc/lathed.toml, simulator spawned, every part cut
3 mm deep so that chatter happens and suppression acts) on free ports. One
daemon, two phases of ``--duration`` seconds each after ``--warmup``:

  none     no subscriber
  web0     lathed-web subscribed, no page open (the daemon's cost of the view alone)
  web      lathed-web (one subscription to the daemon) with 5 headless
           Chromium pages open on it (Debian's /usr/bin/chromium via Playwright)

Per phase: the daemon's CPU (its process only, from /proc), its event-loop lag
(status -> daemon.loop_lag_ms, the median p50 and the worst p99 of the 10 s
windows), the chatter loop's alarm -> speed write latency (the
``alarm_to_write_ms`` of the phase's suppression_action events); in the web
phase the CPU and RSS of lathed-web, and the time from a sample's measurement
(its ``t``, stamped by the driver as it publishes on the bus) to the page
receiving its frame (Date.now() in the page as the frame arrives; same clock).

    .venv/bin/python bench/bench_web.py [--duration 120] [--warmup 30] [--json FILE]
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
from bench_daemon import BIN, config, cpu_s, free_port, rss_mb  # noqa: E402
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


def run(duration: float, warmup: float) -> dict:
    from playwright.sync_api import sync_playwright
    with tempfile.TemporaryDirectory(prefix="bench-web-") as d:
        tmp = Path(d)
        cfg = config(tmp)
        cfg.write_text(cfg.read_text().replace("[simulator]", f"[simulator]\ndepth_mm = {DEPTH_MM}", 1))
        sock = tmp / "run" / "lathed.sock"
        proc = start(cfg, tmp)
        web = None
        try:
            time.sleep(warmup)
            res = {"none": phase(proc, sock, duration, None)}
            port = free_port()
            web = subprocess.Popen([str(BIN / "lathed-web"), "--port", str(port), "--socket", str(sock)],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            # lathed-web subscribed, no page: the daemon's own cost of serving the view, apart from
            # the CPU five Chromiums take from the same cores
            time.sleep(3)
            res["web0"] = phase(proc, sock, duration, web)
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
                pages = []
                for _ in range(BROWSERS):
                    page = browser.new_page(viewport={"width": 1600, "height": 1300})
                    page.add_init_script(LATENCY_PROBE)
                    for _ in range(50):
                        try:
                            page.goto(f"http://127.0.0.1:{port}/")
                            break
                        except Exception:   # lathed-web still starting
                            time.sleep(0.2)
                    page.wait_for_selector("#link.ok", timeout=30_000)
                    pages.append(page)
                time.sleep(5)
                for page in pages:
                    page.evaluate("window.__lat = []")
                res["web"] = phase(proc, sock, duration, web)
                lat = [x * 1000 for page in pages for x in page.evaluate("window.__lat")]
                res["web"].update(frame_latency_median_ms=pct(lat, 50), frame_latency_p99_ms=pct(lat, 99),
                                  frame_latency_n=len(lat))
                browser.close()
        finally:
            if web:
                web.terminate()
                web.wait(10)
            stop(proc, tmp)
    return res


def _f(v, digits=1, unit=""):
    return "-" if v is None else f"{v:.{digits}f}{unit}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=120.0, help="seconds per phase")
    ap.add_argument("--warmup", type=float, default=30.0)
    ap.add_argument("--json", help="also write the results here")
    a = ap.parse_args()
    r = run(a.duration, a.warmup)
    if a.json:
        Path(a.json).write_text(json.dumps(r, indent=2))
    n, w0, w = r["none"], r["web0"], r["web"]

    def ratio(key, w=w):
        return "-" if not n.get(key) or w.get(key) is None else f"{w[key] / n[key]:.2f}"
    print(f"Operator view cost: default config on the simulator, {DEPTH_MM:g} mm cuts, {a.duration:.0f} s per "
          f"phase, {BROWSERS} Chromium pages on lathed-web in the second\n")
    print("| measure | no clients | lathed-web, no page | lathed-web + 5 browsers | ratios to no clients "
          "(bar: <= 1.10) |")
    print("|---|---|---|---|---|")

    def row(label, key, digits, unit):
        print(f"| {label} | {_f(n[key], digits, unit)} | {_f(w0[key], digits, unit)} | {_f(w[key], digits, unit)} | "
              f"{ratio(key, w0)} / {ratio(key)} |")
    row("daemon CPU", "daemon_cpu_pct", 1, " %")
    row("daemon loop lag p50 (median of 10 s windows)", "lag_p50_ms", 2, " ms")
    row("daemon loop lag p99 (worst 10 s window)", "lag_p99_worst_ms", 1, " ms")
    row(f"chatter alarm -> speed write, median ({n['actions']} / {w0['actions']} / {w['actions']} actions)",
        "alarm_to_write_median_ms", 1, " ms")
    row("chatter alarm -> speed write, max", "alarm_to_write_max_ms", 1, " ms")
    print(f"| lathed-web CPU | | {_f(w0['web_cpu_pct'], 1, ' %')} | {_f(w['web_cpu_pct'], 1, ' %')} | |")
    print(f"| lathed-web RSS, max | | {_f(w0['web_rss_mb_max'], 1, ' MB')} | {_f(w['web_rss_mb_max'], 1, ' MB')} | |")
    print(f"| sample on the bus -> frame in the page, median / p99 ({w['frame_latency_n']} samples) | | | "
          f"{_f(w['frame_latency_median_ms'], 0, ' ms')} / {_f(w['frame_latency_p99_ms'], 0, ' ms')} | |")
    print("\nThe machine's cores are shared with the browsers: in the last column the daemon also competes "
          "with five Chromiums for CPU.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
