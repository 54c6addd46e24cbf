"""Shared test helpers: free ports, condition polling, a daemon on the simulator."""
from __future__ import annotations

import gc
import json
import os
import random
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def pytest_sessionstart(session):
    # CPython 3.11 < 3.11.8 can raise a spurious "AST constructor recursion
    # depth mismatch" (cpython#106905) when a garbage collection runs inside
    # ast construction, which pytest's assertion rewriting does at collection.
    gc.disable()


def pytest_collection_finish(session):
    gc.enable()


_OWN_CACHE: list[str] = []


def pytest_configure(config):
    # lathed-opcua's address space cache (docs/opcua.md), one directory for the whole run: the
    # workers inherit it, so the suite builds the space once. A cached space is the built one
    # (tests/test_opcua_cache.py), so which test builds it first does not matter.
    if "LATHED_TEST_CACHE_DIRECTORY" not in os.environ:
        _OWN_CACHE.append(tempfile.mkdtemp(prefix="lathed-test-cache-"))
        os.environ["LATHED_TEST_CACHE_DIRECTORY"] = os.environ["CACHE_DIRECTORY"] = _OWN_CACHE[0]


def pytest_unconfigure(config):
    for d in _OWN_CACHE:
        shutil.rmtree(d, ignore_errors=True)


BIN = Path(sys.executable).parent


# Seconds each test file took in a full run (tests/durations.py writes it from a --durations=0 log)
DURATIONS = ROOT / "tests" / "durations.json"


# Files that keep a core busy the whole time they run (CPU seconds ~ wall seconds, measured with
# tests/cpu_profile.py). `make test`'s workers take them as one unit, one after another on one
# worker, so that the other workers' files, which mostly wait on a simulator's real time, never
# share two cores with two of these at once.
CPU_BOUND = ("tests/test_bench_hostile.py", "tests/test_install.py", "tests/test_thermal_loop.py",
             "tests/test_thermal_real.py", "tests/test_analyze_thermal_cli.py")


def _unit(path: str) -> str:
    return "cpu-bound" if path in CPU_BOUND else path


def pytest_xdist_make_scheduler(config, log):
    """--dist loadfile with the CPU-bound files one unit (xdist's loadgroup would do it with
    marks, but it renames the tests through an attribute pytest 9 no longer reads)."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class FileUnits(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return _unit(nodeid.split("::", 1)[0])
    return FileUnits(config, log)


def pytest_collection_modifyitems(session, config, items):
    """`make test` runs a file's tests together on one worker (--dist loadfile; the CPU-bound
    files are one unit), units in the order of collection (--no-loadscope-reorder): the longest
    first, so that what is left at the end is short and no worker idles long while another
    finishes a long unit. Only the order depends on the figures; a file not in them counts as
    the median one."""
    try:
        seconds = json.loads(DURATIONS.read_text())
    except (OSError, ValueError):
        return
    median = sorted(seconds.values())[len(seconds) // 2] if seconds else 0.0
    files: dict[str, list] = {}
    for item in items:
        files.setdefault(item.nodeid.split("::", 1)[0], []).append(item)
    units: dict[str, float] = {}
    for f in files:
        units[_unit(f)] = units.get(_unit(f), 0.0) + seconds.get(f, median)
    order = sorted(files, key=lambda f: (-units[_unit(f)], _unit(f)))
    items[:] = [item for f in order for item in files[f]]


def disk_full(store, table: str) -> None:
    """``store`` refuses every row of ``table`` as a full disk does, until ``disk_free``."""
    store.submit(f"CREATE TEMP TRIGGER disk_full BEFORE INSERT ON {table} "
                 "BEGIN SELECT RAISE(ABORT, 'database or disk is full'); END", ()).result(5)


def disk_free(store):
    """Space again (a future: await it with asyncio.wrap_future, or .result())."""
    return store.submit("DROP TRIGGER temp.disk_full", ())


_HANDED_OUT: set[int] = set()


def free_port() -> int:
    """A port free now, below the kernel's ephemeral range (32768-60999 here): the peer binds it
    later, and in between a port from that range can be taken as the source of any connection
    or by a server binding port 0 (a CI run's cell simulator then never served its mill).
    Each xdist worker draws from its own slice of the range and never hands a port out twice:
    between the draw and the peer's bind nothing holds it, and a stack's web server was once
    given its own simulator's Modbus port (six workers draw about a thousand ports a run)."""
    with open("/proc/sys/net/ipv4/ip_local_port_range") as f:
        low = int(f.read().split()[0])
    top = max(low, 10200)
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")[2:]
    count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    span = (top - 10000) // max(count, 1)
    first = 10000 + (int(worker) % count if worker.isdigit() else 0) * span
    ports = [p for p in range(first, first + span) if p not in _HANDED_OUT]
    for port in random.Random().sample(ports, min(200, len(ports))):
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            _HANDED_OUT.add(port)
            return port
    raise RuntimeError(f"no free port in {first}-{first + span - 1} on 127.0.0.1")


def wait_until(pred, timeout: float = 20.0, interval: float = 0.05, what: str = "condition"):
    """Poll ``pred`` until it returns something truthy; fail at the deadline."""
    deadline = time.monotonic() + timeout
    last_exc = None
    while time.monotonic() < deadline:
        try:
            v = pred()
            if v:
                return v
        except AssertionError:
            raise
        except Exception as e:   # the condition may not be observable yet
            last_exc = e
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}"
                         + (f" (last error: {last_exc})" if last_exc else ""))


def sim_call(path: str | Path, cmd: str, args: dict | None = None) -> object:
    """A command to the simulator's control socket (as `lathectl sim` sends it)."""
    from lathed.cli.sim import call
    return call(Path(path), cmd, args or {})


REGISTERS = (ROOT / "etc" / "lathed.toml").read_text().split("[machine.lathe.registers]", 1)[1].split("\n[", 1)[0]
# the simulated lathe's serial number and where its control serves it: the daemon commands only a
# peer confirmed to be the configured machine
LATHE_SERIAL = "SIM-LATHE-0001"
IDENTITY_REGISTERS = '\n[machine.lathe.identity]\nserial_number = { address = 36, words = 8 }\n'
IDENTITY = '\n[machine.lathe.identification]\nserial_number = "SIM-LATHE-0001"\n' + IDENTITY_REGISTERS
# the simulated CNC has it; the default config does not map it (real controls rarely report it)
DEPTH_REGISTER = 'depth_of_cut_mm = { address = 20, type = "float32", unit = "mm" }\n'


DEFAULT_CONFIG = (ROOT / "etc" / "lathed.toml").read_text()


def default_table(name: str) -> str:
    """The ``[analyzer.NAME]`` table of the shipped default config, verbatim."""
    m = re.search(rf"^\[analyzer\.{name}\]\n.*?(?=^\s*$|\Z)", DEFAULT_CONFIG, re.S | re.M)
    assert m, f"no [analyzer.{name}] in etc/lathed.toml"
    return m.group(0)


def events(d, kind: str, limit: int = 1000) -> list[dict]:
    """The daemon's newest ``limit`` events of ``kind``, oldest first, as `lathectl events --json`
    lists them: asked in this process while the daemon runs (the tests poll it), through
    lathectl once it has stopped (lathectl then reads them from its database)."""
    from lathed.client import DaemonUnavailable, RemoteError, call
    try:
        return call("events", {"limit": limit, "kind": kind, "source": None}, sock_path=d.socket, timeout=60)
    except RemoteError as e:
        raise AssertionError(f"lathectl events --kind {kind}: lathed refused: {e}") from None
    except DaemonUnavailable:
        return json.loads(d.ctl("events", "--kind", kind, "--limit", str(limit), "--json").stdout)


def without_dangling_read_on(text: str) -> str:
    """The shipped map reads the load at the chatter analyzer's cut entry (read_on): a test
    config without that analyzer takes the map without it (naming it is a config error)."""
    return text if "[analyzer.chatter]" in text else re.sub(r', read_on = \[[^]]*\]', "", text)


# The simulated accelerometer at half the shipped 51.2 kS/s: the suite's live stacks cost half the
# CPU (simulator and chatter analyzer), and the band that matters (modes of 150-600 Hz, their
# chatter below 2 kHz) is far under its Nyquist. The benchmarks run the shipped rate.
SIM_RATE_HZ = 25600
SIM_RATE = f"rate_hz = {SIM_RATE_HZ}"


def sim_config(tmp: Path, extra: str = "", analyzers: str = "", time_scale: float = 30.0,
               daemon: str = "", simulator: str = "", registers: str = "") -> tuple[Path, dict]:
    """A config running the simulator on free ports in a private directory."""
    mport, vport = free_port(), free_port()
    link = tmp / "ttyARDUINO"
    paths = {"modbus_port": mport, "vibration_port": vport, "link": link, "sim": tmp / "run" / "sim.sock",
             "socket": tmp / "run" / "lathed.sock", "state": tmp / "state"}
    text = f"""
[daemon]
name = "test-cell"
state_dir = "{tmp / 'state'}"
runtime_dir = "{tmp / 'run'}"
{daemon}

[simulator]
modbus_port = {mport}
vibration_port = {vport}
serial_link = "{link}"
control = "{paths['sim']}"
time_scale = {time_scale}
{simulator if "rate_hz" in simulator else SIM_RATE + chr(10) + simulator}

[machine.lathe]
plugin = "modbus_cnc"
kind = "lathe"
host = "127.0.0.1"
port = {mport}
poll = "100ms"
retry_initial = "200ms"
retry_max = "1s"

[machine.lathe.limits]
spindle_rpm_min = 300.0
spindle_rpm_max = 6000.0
offset_max_um = 60.0
offset_rate_max_um_s = 5.0

[machine.lathe.registers]
{REGISTERS}
{registers}
{IDENTITY if "[machine.lathe.identification]" not in extra else IDENTITY_REGISTERS}

[sensor.temps]
plugin = "ds18b20_serial"
port = "{link}"
stale_after = "5s"
retry_initial = "200ms"
retry_max = "1s"

[sensor.temps.plausible]
# the simulated spindle warms time_scale times faster than a real one; lines
# read in one burst after a stall share an arrival time
"t_*" = {{ rate = {2.0 * time_scale}, tol = {0.5 + 0.05 * time_scale} }}

[sensor.accel]
plugin = "vibration_tcp"
host = "127.0.0.1"
port = {vport}
retry_initial = "200ms"
retry_max = "1s"
{extra}
{analyzers}
"""
    text = without_dangling_read_on(text)
    cfg = tmp / "lathed.toml"
    cfg.write_text(text)
    return cfg, paths


class Daemon:
    def __init__(self, cfg: Path, socket_path: Path, env: dict | None = None, new_session: bool = False):
        self.cfg = cfg
        self.socket = socket_path
        self.log = open(cfg.with_suffix(".log"), "wb")
        self.proc = subprocess.Popen([str(BIN / "lathed"), "--config", str(cfg)], stdout=self.log,
                                     stderr=subprocess.STDOUT, env={**os.environ, **(env or {})},
                                     start_new_session=new_session)

    def ctl(self, *args: str, check: bool = True) -> subprocess.CompletedProcess:
        r = subprocess.run([str(BIN / "lathectl"), "--socket", str(self.socket), *args],
                           capture_output=True, text=True, timeout=60)
        if check and r.returncode != 0:
            raise AssertionError(f"lathectl {' '.join(args)} exited {r.returncode}: {r.stderr.strip()}")
        return r

    def status(self) -> dict:
        """What `lathectl status --json` prints, asked in this process: the tests poll it, and a
        lathectl process per poll took a core's worth of imports away from the daemon under test."""
        from lathed.client import DaemonUnavailable, RemoteError, call
        try:
            return call("status", {}, sock_path=self.socket, timeout=60)
        except (DaemonUnavailable, RemoteError) as e:     # as ctl(): lathectl would exit non-zero
            raise AssertionError(f"lathectl status --json: {e}") from None

    def item(self, group: str, name: str) -> dict:
        return next(x for x in self.status()[group] if x["name"] == name)

    def wait_ready(self, timeout: float = 30.0) -> None:
        from lathed.client import call

        def up():     # asked in this process: a lathectl per poll slowed the start it waits for
            assert self.proc.poll() is None, f"daemon exited {self.proc.returncode}: {self.output()}"
            return call("status", {}, sock_path=self.socket, timeout=10) is not None
        wait_until(up, timeout, what="daemon control socket")

    def output(self, tail: int | None = 4000) -> str:
        """The daemon's log, its last ``tail`` characters (None: all of it)."""
        self.log.flush()
        text = self.cfg.with_suffix(".log").read_text(errors="replace")
        return text if tail is None else text[-tail:]

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()
        return self.proc.returncode


@contextmanager
def running_daemon(cfg: Path, paths: dict):
    """The daemon on ``cfg`` (from ``sim_config``), ready; stopped on leaving."""
    d = Daemon(cfg, paths["socket"])
    d.paths = paths
    try:
        d.wait_ready()
        yield d
    finally:
        d.stop()


@pytest.fixture
def sim_daemon(tmp_path):
    """The daemon with its simulator, on free ports; stopped at the end."""
    started = []

    def start(extra: str = "", analyzers: str = "", env: dict | None = None, time_scale: float = 30.0,
              daemon: str = "", registers: str = "", new_session: bool = False):
        cfg, paths = sim_config(tmp_path, extra, analyzers, time_scale, daemon, registers=registers)
        d = Daemon(cfg, paths["socket"], env, new_session)
        d.paths = paths
        started.append(d)
        d.wait_ready()
        return d

    yield start
    for d in started:
        d.stop()


def pytest_sessionfinish(session, exitstatus):
    # Tasks that pymodbus leaves behind when a test cancels a driver mid-read
    # are reported by asyncio when collected: collect now, so the report comes
    # before pytest's summary line, not after it at interpreter exit.
    gc.collect()


def shipped_config(tmp: Path, name: str = "lathed.toml") -> tuple[Path, Path]:
    """etc/lathed.toml (or another shipped config) on free ports, with its state and sockets in ``tmp``."""
    text = (ROOT / "etc" / name).read_text()
    for port in ("15020", "15021", "15022", "15024"):
        text = text.replace(port, str(free_port()))
    text = text.replace('name = "sim-cell-1"', f'name = "web-test"\nstate_dir = "{tmp / "state"}"\n'
                                                f'runtime_dir = "{tmp / "run"}"')
    text = text.replace('dbc = "robot_arm.dbc"', f'dbc = "{ROOT / "etc" / "robot_arm.dbc"}"')
    text = text.replace('plugin_dirs = ["plugins.d"]', f'plugin_dirs = ["{ROOT / "etc" / "plugins.d"}"]')
    text = text.replace("\n[simulator]\n", f"\n[simulator]\n{SIM_RATE}\n", 1)    # as sim_config's
    cfg = tmp / "lathed.toml"
    cfg.write_text(text)
    return cfg, tmp / "run" / "lathed.sock"
