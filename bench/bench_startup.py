"""CPU seconds each program spends from exec to ready: the suite starts the simulator, the daemon
and lathectl hundreds of times, so their start-up (mostly imports) is a large share of its CPU.

    python bench/bench_startup.py [-n 5] [--against REV] [--only PROGRAM]

Ready: lathed-sim prints READY; the daemon answers `status` on its control socket (its simulator
not spawned: the daemon's own CPU); lathed-web and lathed-opcua accept on their port; lathectl
exits (`status` with no daemon, `--help`); lathed-opcua with its address space cached by an
earlier start (warm) and without (cold, its cache directory empty). The CPU is the process's own (/proc/PID/stat at
ready, or its rusage at exit), children not counted. ``--against REV`` runs a git revision's
lathed/ and plugins/ (or a checkout's, given its directory) with this venv, alternated with
this one start by start, and prints both medians: the machine's load hits both alike.
"""
from __future__ import annotations

import argparse
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
from bench.bench_daemon import cpu_s as cpu_of, free_port  # noqa: E402  (utime + stime, children not counted)

BIN = Path(sys.executable).parent


def until(pred, proc: subprocess.Popen, what: str, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        if proc.poll() is not None:
            raise RuntimeError(f"{what} exited {proc.returncode} before it was ready")
        if time.monotonic() > deadline:
            raise RuntimeError(f"{what} not ready within {timeout:g} s")
        time.sleep(0.01)


def accepts(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=0.5):
            return True
    except OSError:
        return False


def answers(sock: Path) -> bool:
    from lathed.client import call
    try:
        return call("status", {}, sock_path=sock, timeout=5) is not None
    except Exception:      # noqa: BLE001 - not up yet
        return False


def stop(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(20)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def run_served(argv: list[str], env: dict, ready, what: str) -> float:
    # cwd: `python -m` puts it first on sys.path, ahead of --against's tree
    p = subprocess.Popen(argv, env=env, cwd=tempfile.gettempdir(), stdout=subprocess.PIPE,
                         stderr=subprocess.DEVNULL, text=True)
    try:
        ready(p)
        return cpu_of(p.pid)
    finally:
        stop(p)


def sim(tmp: Path, env: dict) -> float:
    argv = [sys.executable, "-m", "lathed.sim", "--host", "127.0.0.1", "--modbus-port", str(free_port()),
            "--vibration-port", str(free_port()), "--serial-link", str(tmp / "sim" / "tty"),
            "--control", str(tmp / "sim.sock")]
    (tmp / "sim").mkdir(mode=0o700, exist_ok=True)

    def ready(p):
        line = p.stdout.readline()
        if not line.startswith("READY"):
            raise RuntimeError(f"lathed-sim: {line.strip() or 'no READY line'}")
    return run_served(argv, env, ready, "lathed-sim")


def daemon(tmp: Path, env: dict) -> float:
    sys.path.insert(0, str(ROOT))
    from tests.conftest import sim_config
    cfg, paths = sim_config(tmp, simulator="spawn = false")
    return run_served([str(BIN / "lathed"), "--config", str(cfg)], env,
                      lambda p: until(lambda: answers(paths["socket"]), p, "lathed"), "lathed")


def web(tmp: Path, env: dict) -> float:
    port = free_port()
    cfg = tmp / "web.toml"
    cfg.write_text(f'[web]\nport = {port}\nsocket = "{tmp / "none.sock"}"\n')
    return run_served([str(BIN / "lathed-web"), "--config", str(cfg)], env,
                      lambda p: until(lambda: accepts(port), p, "lathed-web"), "lathed-web")


def opcua(warm: bool):
    """Its address space cached by an earlier start (the tree's cache directory, filled by the
    unmeasured start), or built (an empty one); a tree without the cache builds it both times."""
    def measure(tmp: Path, env: dict) -> float:
        port = free_port()
        cfg = tmp / "opcua.toml"
        cfg.write_text(f'[opcua]\nport = {port}\nsocket = "{tmp / "none.sock"}"\nstate_dir = "{tmp / "ua"}"\n')
        env = env if warm else {**env, "CACHE_DIRECTORY": str(tmp / "cache")}
        return run_served([str(BIN / "lathed-opcua"), "--config", str(cfg)], env,
                          lambda p: until(lambda: accepts(port), p, "lathed-opcua", 180), "lathed-opcua")
    return measure


def ctl(*args: str):
    def measure(tmp: Path, env: dict) -> float:
        p = subprocess.Popen([str(BIN / "lathectl"), "--socket", str(tmp / "none.sock"), *args], env=env,
                             cwd=tmp, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        _, _, ru = os.wait4(p.pid, 0)
        p.returncode = 0
        return ru.ru_utime + ru.ru_stime
    return measure


PROGRAMS = {"lathed-sim": sim, "lathed": daemon, "lathectl status (no daemon)": ctl("status"),
            "lathectl --help": ctl("--help"), "lathed-web": web,
            "lathed-opcua (cold cache)": opcua(warm=False), "lathed-opcua (warm cache)": opcua(warm=True)}


def tree_env(against: str | None, scratch: Path) -> dict:
    # as `make test`: bytecode cached; lathed-opcua's address space cached per tree
    env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "", "CACHE_DIRECTORY": str(scratch / "cache")}
    if against is not None:
        tree = Path(against)
        if not tree.is_dir():
            tree = scratch / "tree"
            tree.mkdir()
            arch = subprocess.run(["git", "-C", str(ROOT), "archive", against, "lathed", "plugins"], check=True,
                                  capture_output=True).stdout
            subprocess.run(["tar", "-x", "-C", str(tree)], input=arch, check=True)
        tree = tree.resolve()
        # the other checkout's packages ahead of this venv's editable install (which sys.path precedes)
        (scratch / "lathed").symlink_to(tree / "lathed")
        (scratch / "lathed_plugins").symlink_to(tree / "plugins")
        env["PYTHONPATH"] = str(scratch)
    return env


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-n", type=int, default=5, help="starts of each program (and of each tree)")
    ap.add_argument("--against", help="a git revision (e.g. main) or a checkout's directory, alternated with this one")
    ap.add_argument("--only", action="append", choices=sorted(PROGRAMS), help="these programs only")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-startup-") as d:
        d = Path(d)
        (d / "b").mkdir()
        trees = {"this": tree_env(None, d)}
        if a.against:
            trees["against"] = tree_env(a.against, d / "b")
        names = a.only or list(PROGRAMS)
        got = {(n, t): [] for n in names for t in trees}
        for n in names:
            for t, env in trees.items():       # one unmeasured start each: bytecode written
                PROGRAMS[n](Path(tempfile.mkdtemp(dir=d)), env)
            for _ in range(a.n):
                for t, env in trees.items():
                    got[n, t].append(PROGRAMS[n](Path(tempfile.mkdtemp(dir=d)), env))
        cols = list(trees)
        head = " | ".join(f"CPU-s ({t})" for t in cols)
        print(f"| program | {head} |" + (" ratio |" if a.against else ""))
        print("|---|" + "---:|" * (len(cols) + bool(a.against)))
        for n in names:
            med = [statistics.median(got[n, t]) for t in cols]
            ratio = f" {med[0] / med[1]:.2f} |" if a.against else ""
            print(f"| {n} | " + " | ".join(f"{m:.2f}" for m in med) + f" |{ratio}")
        print(f"\nmedian of {a.n} starts each" + (", alternated with " + a.against if a.against else ""))


if __name__ == "__main__":
    main()
