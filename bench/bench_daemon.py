"""Daemon footprint on the default config: time to READY, RSS after 60 s, CPU.

Runs etc/lathed.toml (with the simulator) on free ports in a temporary
directory, as systemd would: READY is the sd_notify datagram. CPU is the
daemon's own (not the simulator's) user+system time over the measuring
window, as a percentage of one core.

    .venv/bin/python bench/bench_daemon.py [--seconds 60] [--starts 5]
"""
from __future__ import annotations

import argparse
import os
import re
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
CLK = os.sysconf("SC_CLK_TCK")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def config(tmp: Path, name: str = "lathed.toml", root: Path = ROOT) -> Path:
    """A copy of etc/ (relative paths keep working) on free ports and private paths; ``name``:
    which shipped config (etc/lathed-cell-opcua.toml: the lathe over OPC UA); ``root``: whose
    etc/ (another revision's tree)."""
    shutil.copytree(root / "etc", tmp / "etc")
    text = (tmp / "etc" / name).read_text()
    ports = {}
    for m in sorted(set(re.findall(r"\b(1502\d)\b", text))):
        ports[m] = str(free_port())
    for old, new in ports.items():
        text = re.sub(rf"\b{old}\b", new, text)
    text = text.replace("{runtime_dir}/sim/", f"{tmp}/")
    text = text.replace("[daemon]", f'[daemon]\nstate_dir = "{tmp}/state"\nruntime_dir = "{tmp}/run"', 1)
    cfg = tmp / "etc" / name
    cfg.write_text(text)
    return cfg


def as_unit(unit: str) -> dict:
    """Popen arguments that start a process at its systemd unit's Nice= (systemd/UNIT.service),
    as the service runs; a priority above the default needs root, else it is said and left."""
    m = re.search(r"^Nice=(-?\d+)", (ROOT / "systemd" / f"{unit}.service").read_text(), re.M)
    nice = int(m.group(1)) if m else 0
    if nice < 0 and os.geteuid() != 0:
        print(f"note: {unit} runs at nice 0, not its unit's {nice} (that needs root)", file=sys.stderr)
        return {}
    return {"preexec_fn": (lambda: os.nice(nice))} if nice else {}


def cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def start(cfg: Path, tmp: Path) -> tuple[subprocess.Popen, float]:
    sock_path = tmp / f"notify-{time.monotonic_ns()}.sock"
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    srv.bind(str(sock_path))
    srv.settimeout(60)
    t0 = time.monotonic()
    proc = subprocess.Popen([str(BIN / "lathed"), "--config", str(cfg)], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, env={**os.environ, "NOTIFY_SOCKET": str(sock_path)},
                            **as_unit("lathed"))
    while True:
        try:
            msg = srv.recv(4096).decode()
        except TimeoutError:
            proc.kill()
            raise SystemExit(f"lathed did not become ready (exit code {proc.poll()}); "
                             f"try: lathed --check-config {cfg}") from None
        if "READY=1" in msg:
            ready = time.monotonic() - t0
            break
    srv.close()
    return proc, ready


def stop(proc: subprocess.Popen) -> None:
    proc.send_signal(signal.SIGTERM)
    proc.wait(30)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--starts", type=int, default=5)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        cfg = config(tmp)
        readies = []
        for _ in range(a.starts):
            proc, ready = start(cfg, tmp)
            readies.append(ready)
            stop(proc)
        proc, _ = start(cfg, tmp)
        time.sleep(5)    # settle: connections made, first blocks analysed
        c0, w0 = cpu_s(proc.pid), time.monotonic()
        time.sleep(a.seconds - 5)
        cpu = 100 * (cpu_s(proc.pid) - c0) / (time.monotonic() - w0)
        rss = rss_mb(proc.pid)
        stop(proc)
    print("| measure (default config, simulator running) | value | target |")
    print("|---|---|---|")
    print(f"| start to READY=1, median of {a.starts} | {statistics.median(readies):.2f} s "
          f"(min {min(readies):.2f}, max {max(readies):.2f}) | < 2 s |")
    print(f"| resident memory after {a.seconds:.0f} s | {rss:.0f} MB | < 150 MB |")
    print(f"| daemon CPU over the last {a.seconds - 5:.0f} s | {cpu:.1f} % of one core | < 10 % |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
