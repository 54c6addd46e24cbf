"""The daemon under a mixed hostile load (issue 18): records kept, loop lag, memory, loops acting.

Runs the default config (etc/lathed.toml, simulator spawned, every part cut
3 mm deep so that chatter happens and suppression acts) on free ports in a
temporary directory, plus two hostile peers the benchmark owns:

  [sensor.hostile_vib]    vibration_tcp on a TCP server here sending bad frames
                          (rpm NaN, rate 1 Hz, bad magic, truncated, huge n)
                          among valid ones; read by [analyzer.hostile_chatter]
  [sensor.hostile_temps]  ds18b20_serial on a pseudo-terminal here sending bad
                          lines (bad checksum, huge seq with uptime 0, junk
                          names, 124.99 °C spikes, garbage) among valid ones;
                          read by [analyzer.hostile_thermal], which computes
                          on the mill (no offset register: it can never write)

Phases: warm-up (``--warmup``, from the daemon's readiness; lathed-web and lathed-opcua
start within it, and the load waits for lathed-opcua to serve), load (``--duration``, 600 s = the issue's 10
minutes), after (``--after``). During the load, all on loopback and local
sockets, bounded and stopping by itself:

  fuzz      a few requests a second on the control socket from a seeded RNG:
            malformed JSON, deep nesting, huge numbers, wrong argument types
            for every command, random bytes; every so often the two heavy
            ones of the issue (a factor level of 300000000 then ``recommend``;
            an experiment run of 10**30)
  slow      200 clients holding an unfinished line (half 1 MB unterminated,
            half one byte a second); a slot the daemon closes is re-opened
            (at most every 5 s)
  records   valid ``experiment_add`` and ``inspect`` requests; each record the
            daemon acknowledged is looked up in lathed.db after SIGTERM, as is
            every event ``events`` reported, and the spindle writes the
            simulated lathe received are matched by ``command_sent`` records

  web       lathed-web beside the daemon, as its unit runs it, under slow-header
            clients, idle TCP connections and a crowd of live pages (bench/hostile_web.py);
            a fresh client asks for its page and its live stream every second

Event-loop lag is the daemon's own (``status`` -> daemon.loop_lag_ms,
lathed/looplag.py), sampled through ordinary connections with a timeout; a
status call that fails is counted. RSS from /proc/PID/status.

    .venv/bin/python bench/bench_hostile.py [--duration 600] [--warmup 60] [--after 60] [--json FILE]
"""
from __future__ import annotations

import argparse
import json
import math
import os
import random
import signal
import socket
import sqlite3
import statistics
import sys
import tempfile
import threading
import time
import tty
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_daemon import config, free_port, rss_mb  # noqa: E402
from bench_loop import DEPTH_MM, start  # noqa: E402
from hostile_web import WebWatch, start_web, web_report  # noqa: E402
import hostile_opcua  # noqa: E402

from lathed.client import call  # noqa: E402
from lathed.wire import VIB_HEADER, VIB_MAGIC, VIB_VERSION, format_temperature_line, pack_vibration  # noqa: E402

SLOW_CLIENTS = 200
SLOW_BIG = (1 << 20) - 64         # just under the daemon's line limit, never terminated
RSS_SETTLE_S = 10.0
STATUS_EVERY_S = 2.0
LAG_BAR_MS = 50.0
RSS_BAR = 0.10
VIB_RATE, VIB_N = 51200, 2048     # 40 ms frames


def _rss(pid: int) -> float | None:
    try:
        return rss_mb(pid)
    except OSError:
        return None


class Stopper:
    """A thread's loop with a stop flag; errors are kept, not raised."""

    def __init__(self):
        self.stop = threading.Event()
        self.errors: list[str] = []
        self.thread: threading.Thread | None = None

    def start(self) -> "Stopper":
        self.thread = threading.Thread(target=self._guarded, daemon=True, name=type(self).__name__)
        self.thread.start()
        return self

    def _guarded(self) -> None:
        try:
            self.run()
        except Exception as e:   # the bench reports its own failures, it does not crash on them
            self.errors.append(f"{type(e).__name__}: {e}")

    def join(self) -> None:
        self.stop.set()
        if self.thread is not None:
            self.thread.join(15)


# -- hostile peers ---------------------------------------------------------------
class VibrationPeer(Stopper):
    """A DAQ on TCP: valid frames, one bad frame in ten while ``hostile`` is set."""
    BAD = ("rpm_nan", "rate_1hz", "bad_magic", "truncated", "huge_n")

    def __init__(self, rng: random.Random):
        super().__init__()
        self.rng = rng
        self.srv = socket.create_server(("127.0.0.1", 0))
        self.srv.settimeout(0.5)
        self.port = self.srv.getsockname()[1]
        self.hostile = threading.Event()
        self.sent = {"valid": 0, **{k: 0 for k in self.BAD}}
        self.connections = 0
        self._bad = 0                     # cycles through BAD across reconnections

    def run(self) -> None:
        noise = np.random.default_rng(self.rng.randrange(1 << 30))
        while not self.stop.is_set():
            try:
                conn, _ = self.srv.accept()
            except TimeoutError:
                continue
            self.connections += 1
            seq, i = 0, 0
            with conn:
                conn.settimeout(2.0)
                try:
                    while not self.stop.is_set():
                        i += 1
                        data = noise.normal(0, 0.5, VIB_N)
                        kind = "valid"
                        if self.hostile.is_set() and i % 10 == 0:
                            kind = self.BAD[self._bad % len(self.BAD)]
                            self._bad += 1
                        t0 = time.time()
                        if kind == "valid":
                            conn.sendall(pack_vibration(seq, t0, 1500.0, VIB_RATE, data))
                        elif kind == "rpm_nan":
                            conn.sendall(pack_vibration(seq, t0, float("nan"), VIB_RATE, data))
                        elif kind == "rate_1hz":
                            conn.sendall(pack_vibration(seq, t0, 1500.0, 1, data[:64]))
                        elif kind == "bad_magic":
                            conn.sendall(b"XVIB" + pack_vibration(seq, t0, 1500.0, VIB_RATE, data)[4:])
                        elif kind == "truncated":
                            frame = pack_vibration(seq, t0, 1500.0, VIB_RATE, data)
                            conn.sendall(frame[:VIB_HEADER.size + 100])
                        else:   # huge_n: 65535 samples x 255 channels announced
                            conn.sendall(VIB_HEADER.pack(VIB_MAGIC, VIB_VERSION, 255, 65535, VIB_RATE, seq, t0,
                                                         1500.0))
                        self.sent[kind] += 1
                        seq += VIB_N
                        if kind == "truncated":
                            break        # the rest of the frame never comes: the link drops
                        self.stop.wait(VIB_N / VIB_RATE)
                except OSError:
                    pass                 # the driver closed the link after a bad frame: it reconnects
        self.srv.close()


class SerialPeer(Stopper):
    """An Arduino on a pty: a line every 0.5 s, one bad line in three while ``hostile`` is set."""
    BAD = ("bad_checksum", "huge_seq_uptime_0", "junk_name", "spike_124.99", "garbage")

    def __init__(self, rng: random.Random):
        super().__init__()
        self.rng = rng
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)            # a serial port does no line editing or echo
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self.slave)
        self.hostile = threading.Event()
        self.sent = {"valid": 0, **{k: 0 for k in self.BAD}}
        self.dropped = 0

    def run(self) -> None:
        seq, i, t0 = 1, 0, time.monotonic()
        while not self.stop.wait(0.5):
            i += 1
            uptime = int((time.monotonic() - t0) * 1000) + 1000
            temps = {"front_bearing": 30.0 + 0.001 * i, "rear_bearing": 28.0 + 0.001 * i, "room": 21.0}
            kind = self.BAD[(i // 3) % len(self.BAD)] if self.hostile.is_set() and i % 3 == 0 else "valid"
            if kind == "valid":
                line = format_temperature_line(seq, uptime, temps)
                seq += 1
            elif kind == "bad_checksum":
                good = format_temperature_line(seq, uptime, temps)
                line = good[:-4] + b"%02X\r\n" % ((int(good[-4:-2], 16) + 1) % 256)
            elif kind == "huge_seq_uptime_0":
                line = format_temperature_line(2 ** 62, 0, temps)
            elif kind == "junk_name":
                line = format_temperature_line(seq, uptime, {f"junk{self.rng.randrange(10**9)}": 25.0})
                seq += 1
            elif kind == "spike_124.99":
                line = format_temperature_line(seq, uptime, {**temps, "front_bearing": 124.99})
                seq += 1
            else:
                line = bytes(self.rng.randrange(256) for _ in range(self.rng.randrange(1, 300))) + b"\n"
            try:
                os.write(self.master, line)
                self.sent[kind] += 1
            except OSError:               # nobody reading and the tty buffer full
                self.dropped += 1

    def close(self) -> None:
        for fd in (self.master, self.slave):
            os.close(fd)


# -- control-socket load ----------------------------------------------------------
def raw_request(sock: Path, data: bytes, timeout: float = 5.0) -> tuple[str, dict | None]:
    """One request as bytes on its own connection: (outcome, reply)."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout)
    try:
        s.connect(str(sock))
        s.sendall(data)
        buf = b""
        while not buf.endswith(b"\n"):
            chunk = s.recv(1 << 16)
            if not chunk:
                return "closed without reply", None
            buf += chunk
    except TimeoutError:
        return "timeout", None
    except OSError as e:
        return f"socket error ({type(e).__name__})", None
    finally:
        s.close()
    try:
        reply = json.loads(buf.split(b"\n", 1)[0])
    except ValueError:
        return "reply not JSON", None
    if reply.get("ok"):
        return "ok", reply
    return ("internal error" if "internal error" in str(reply.get("error")) else "refused"), reply


COMMANDS = ("status", "plugins", "events", "ping", "parts", "inspect", "experiment_add", "experiments",
            "export", "suppress", "thermal")
WRONG = (None, [], {}, "abc", 1e308, -1, True, [1], {"x": 1}, "", "x" * 10000, float("nan"), 10 ** 30,
         -1e308, [[[[]]]])
ARG_NAMES = ("limit", "since_id", "kind", "source", "part", "ra_um", "diameter_error_um", "values", "levels",
             "settings", "run", "tool", "material", "what", "analyzer", "action", "abnormal", "pending")


def fuzz_request(rng: random.Random) -> tuple[str, bytes]:
    """(kind, bytes) of one hostile request."""
    k = rng.randrange(10)
    if k == 0:
        good = json.dumps({"cmd": "status", "args": {}})
        return "malformed JSON", rng.choice([good[:rng.randrange(1, len(good))], "{'cmd': 'status'}",
                                              '{"cmd": status}', "[1,2", '{"cmd":"ping"}}']).encode() + b"\n"
    if k == 1:
        d = rng.choice([1000, 10000, 100000])
        body = "[" * d + "]" * d
        if rng.random() < 0.5:
            body = '{"cmd": "status", "args": {"x": ' + body + "}}"
        return "deep nesting", body.encode() + b"\n"
    if k == 2:
        return "huge numbers", rng.choice([
            b'{"cmd": "events", "args": {"limit": 1e999}}\n',
            b'{"cmd": "events", "args": {"since_id": ' + b"9" * 5000 + b"}}\n",
            b'{"cmd": "parts", "args": {"limit": -1e308}}\n'])
    if k == 3:
        return "events bad args", json.dumps({"cmd": "events", "args": rng.choice([
            {"since_id": "abc"}, {"since_id": float("nan")}, {"since_id": 1e30}, {"kind": [1]}])}).encode() + b"\n"
    if k == 4:
        return "suppress bad args", json.dumps({"cmd": "suppress", "args": {"analyzer": ["x"]}}).encode() + b"\n"
    if k == 5:
        return "inspect 400 digits", (b'{"cmd": "inspect", "args": {"part": "1", "ra_um": ' + b"7" * 400
                                      + b"}}\n")
    if k == 6:
        junk = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 2000))).replace(b"\n", b" ")
        return "random bytes", junk + b"\n"
    cmd = rng.choice(COMMANDS)
    args = {rng.choice(ARG_NAMES): rng.choice(WRONG) for _ in range(rng.randrange(1, 4))}
    return "wrong types", json.dumps({"cmd": cmd, "args": args}).encode() + b"\n"


class Fuzzer(Stopper):
    """A few hostile requests a second, valid records among them, the heavy ones every ``heavy_every``."""

    def __init__(self, sock: Path, rng: random.Random, heavy_every: float, per_s: float = 4.0):
        super().__init__()
        self.sock, self.rng, self.heavy_every, self.per_s = sock, rng, heavy_every, per_s
        self.outcomes: dict[str, dict[str, int]] = {}
        self.experiments: list[int] = []            # ids acknowledged
        self.inspections: list[tuple[str, float]] = []
        self.heavy: list[str] = []
        self.valid_failed = 0
        self._heavy_threads: list[threading.Thread] = []

    def join(self) -> None:
        super().join()
        for th in self._heavy_threads:
            th.join(35)

    def _count(self, kind: str, outcome: str) -> None:
        self.outcomes.setdefault(kind, {}).setdefault(outcome, 0)
        self.outcomes[kind][outcome] += 1

    def _call(self, cmd: str, args: dict, timeout: float = 10.0):
        try:
            return call(cmd, args, sock_path=self.sock, timeout=timeout)
        except Exception as e:
            self.valid_failed += 1
            return e

    def run(self) -> None:
        t0 = time.monotonic()
        next_heavy, heavy_i, i = t0 + 5.0, 0, 0
        while not self.stop.wait(1.0 / self.per_s):
            i += 1
            if time.monotonic() >= next_heavy:
                next_heavy += self.heavy_every
                th = threading.Thread(target=self._heavy, args=(heavy_i,), daemon=True)
                th.start()
                self._heavy_threads.append(th)
                heavy_i += 1
                continue
            if i % 8 == 0:
                self._valid_records()
                continue
            kind, data = fuzz_request(self.rng)
            outcome, _ = raw_request(self.sock, data)
            self._count(kind, outcome)

    def _valid_records(self) -> None:
        r = self._call("experiment_add", {"levels": {"A": self.rng.randint(1, 3), "B": self.rng.randint(1, 3)},
                                          "ra_um": round(self.rng.uniform(0.5, 3.0), 6)})
        if isinstance(r, dict) and "id" in r:
            self.experiments.append(r["id"])
        parts = self._call("parts", {"limit": 1})
        if isinstance(parts, list) and parts:
            ra = round(self.rng.uniform(0.2, 2.0), 6)
            r = self._call("inspect", {"part": str(parts[0]["id"]), "ra_um": ra, "by": "bench_hostile"})
            if isinstance(r, dict):
                self.inspections.append((parts[0]["uuid"], ra))

    def _heavy(self, n: int) -> None:
        if n % 2 == 0:   # D3: a factor level of 300000000, then recommend
            t = time.monotonic()
            o1, _ = raw_request(self.sock, json.dumps({"cmd": "experiment_add", "args": {
                "levels": {"A": 300_000_000, "B": 1}, "ra_um": 1.0}}).encode() + b"\n", timeout=30.0)
            o2, _ = raw_request(self.sock, b'{"cmd": "recommend", "args": {}}\n', timeout=30.0)
            self.heavy.append(f"level 3e8 + recommend: {o1} / {o2} in {time.monotonic() - t:.1f} s")
        else:            # D1: a run number sqlite cannot hold
            t = time.monotonic()
            o, _ = raw_request(self.sock, json.dumps({"cmd": "experiment_add", "args": {
                "levels": {"A": 1, "B": 2}, "ra_um": 1.0, "run": 10 ** 30}}).encode() + b"\n", timeout=30.0)
            self.heavy.append(f"run 10**30: {o} in {time.monotonic() - t:.1f} s")


class SlowClients(Stopper):
    """``n`` connections holding an unfinished line: even slots 1 MB, odd slots a byte a second."""

    def __init__(self, sock: Path, n: int = SLOW_CLIENTS):
        super().__init__()
        self.sock, self.n = sock, n
        self.big = memoryview(b'{"cmd": "status", "args": {"pad": "' + b"x" * SLOW_BIG)
        self.slots: list[dict] = [{"s": None, "sent": 0, "next": 0.0, "opened": 0} for _ in range(n)]
        self.opened = self.dropped = self.connect_failed = 0
        self.max_open = 0

    def _open(self, slot: dict, now: float) -> None:
        slot["next"] = now + 5.0          # a dropped slot comes back at most every 5 s
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(1.0)
        try:
            s.connect(str(self.sock))
        except OSError:
            s.close()
            self.connect_failed += 1
            return
        s.setblocking(False)
        slot.update(s=s, sent=0)
        self.opened += 1

    def _drop(self, slot: dict) -> None:
        slot["s"].close()
        slot["s"] = None
        self.dropped += 1

    def run(self) -> None:
        start = time.monotonic()
        while not self.stop.wait(0.1):
            now = time.monotonic()
            ramp = min(self.n, int((now - start) * 50) + 1)      # 50 new connections a second at first
            for i, slot in enumerate(self.slots[:ramp]):
                if slot["s"] is None:
                    if now >= slot["next"]:
                        self._open(slot, now)
                    continue
                s = slot["s"]
                try:
                    if s.recv(4096) == b"":
                        self._drop(slot)
                        continue
                except BlockingIOError:
                    pass
                except OSError:
                    self._drop(slot)
                    continue
                try:
                    if i % 2 == 0:
                        if slot["sent"] < len(self.big):
                            slot["sent"] += s.send(self.big[slot["sent"]:slot["sent"] + (1 << 16)])
                    elif now >= slot.get("byte_at", 0.0):
                        slot["byte_at"] = now + 1.0
                        slot["sent"] += s.send(b"x" if slot["sent"] else b'{"cmd": "status", "args": {"p": "')
                except BlockingIOError:
                    pass
                except OSError:
                    self._drop(slot)
            self.max_open = max(self.max_open, sum(sl["s"] is not None for sl in self.slots))
        for slot in self.slots:
            if slot["s"] is not None:
                slot["s"].close()
                slot["s"] = None


# -- observation -------------------------------------------------------------------
class Sampler(Stopper):
    """Status, events and the simulator's received speed writes, every STATUS_EVERY_S; RSS every second."""

    def __init__(self, sock: Path, sim_sock: Path, pid: int):
        super().__init__()
        self.sock, self.sim_sock, self.pid = sock, sim_sock, pid
        self.status: list[tuple[float, dict | None, str | None]] = []   # (t, reply, error)
        self.events: dict[int, dict] = {}
        self.speed_writes: dict[tuple, float] = {}                       # (part, sim_t) -> wall_t
        self.rss: list[tuple[float, float]] = []
        self.offsets: list[tuple[float, float]] = []                     # (t, offset_x_um the lathe holds)
        self.events_failed = 0
        self.status_s: list[tuple[float, float]] = []                    # (t, seconds a fresh status call took)
        self._since = 0

    def run(self) -> None:
        last = 0.0
        while not self.stop.wait(1.0):
            r = _rss(self.pid)
            if r is not None:
                self.rss.append((time.time(), r))
            if time.monotonic() - last < STATUS_EVERY_S:
                continue
            last = time.monotonic()
            self.poll()

    def poll(self) -> None:
        t = time.time()
        try:
            st = call("status", {}, sock_path=self.sock, timeout=5.0)
            self.status_s.append((t, time.time() - t))
            self.status.append((t, st, None))
        except Exception as e:
            self.status.append((t, None, f"{type(e).__name__}: {e}"))
        try:
            while True:
                evs = call("events", {"limit": 5000, "since_id": self._since}, sock_path=self.sock, timeout=10.0)
                for e in evs:
                    self.events[e["id"]] = e
                if evs:
                    self._since = evs[-1]["id"]
                if len(evs) < 5000:
                    break
        except Exception:
            self.events_failed += 1
        try:
            st = call("status", {"parts": 64}, sock_path=self.sim_sock, timeout=5.0)
            self.offsets.append((t, st["registers"]["offset_x_um"]))
            for p in st["parts"]:
                for w in p["speed_writes"]:
                    self.speed_writes[(p["part"], w["sim_t"])] = w.get("wall_t") or t
        except Exception:
            pass


def lag_from_histograms(first: dict | None, last: dict | None) -> dict | None:
    """p50/p99 (upper bin edge), share above the bar and wakes, between two since_start histograms."""
    if not first or not last:
        return None
    edges = last["edges_ms"]
    counts = [b - a for a, b in zip(first["counts"], last["counts"])]
    n = sum(counts)
    if n == 0:
        return None

    def upper(p: float) -> float:
        acc = 0
        for i, c in enumerate(counts):
            acc += c
            if acc >= p / 100 * n:
                return edges[i] if i < len(edges) else math.inf
        return math.inf
    bar_bin = edges.index(LAG_BAR_MS)     # bin i holds (edges[i-1], edges[i]]
    above = sum(counts[bar_bin + 1:])
    return {"n": n, "p50_le": upper(50), "p99_le": upper(99), "above_bar": above}


COUNTERS = {"chatter_alarms": ("chatter", "alarms"), "chatter_windows": ("chatter", "windows"),
            "suppression_actions": ("suppress", "actions"), "thermal_writes": ("thermal", "writes")}


def counters(sampler: Sampler, t: float) -> dict:
    """The loops' own counters in the newest status the daemon answered by ``t`` (or the first after)."""
    answered = [(ts, s) for ts, s, _ in sampler.status if s is not None]
    upto = [s for ts, s in answered if ts <= t] or [s for _, s in answered[:1]]
    if not upto:
        return {}
    ans = {an["name"]: an for an in upto[-1]["analyzers"]}
    return {k: ans[name][field] for k, (name, field) in COUNTERS.items() if field in ans.get(name, {})}


def cut_counts(cuts: list[dict]) -> dict:
    """The lathe's cut records of a phase: how each ended, and whether an alarm in it was answered."""
    chattered = [c for c in cuts if c.get("alarms")]
    return {"cuts": len(cuts), "cuts_stable": sum(c.get("outcome") == "stable" for c in cuts),
            "cuts_chattered": len(chattered), "cuts_cured": sum(bool(c.get("cured")) for c in chattered),
            "cuts_alarm_unanswered": sum(not any(a.get("sent") for a in c.get("actions") or []) for c in chattered)}


def loops_acting(loops: dict) -> tuple[bool, str]:
    """Whether the chatter and thermal loops still act during and after the load. Remembered
    cures mean a healthy run may see no chatter at all (issue 35 case 12), so alarms are not
    the measure: the detector must still judge windows, suppression must still move the
    lathe's spindle (the lathe received the writes), every cut must end (recorded), an alarm
    in a cut must be answered by a sent action, and the thermal loop must still write offsets
    that the lathe received."""
    dur, aft = loops["during"], loops["after"]
    n = lambda v, k: v.get(k) or 0  # noqa: E731
    chatter = all(n(v, "chatter_windows") > 0 and n(v, "suppression_actions") > 0 and v["speed_writes_received"] > 0
                  and n(v, "cuts") > 0 and n(v, "cuts_alarm_unanswered") == 0 for v in (dur, aft))
    thermal = n(dur, "thermal_writes") + n(aft, "thermal_writes") > 0 \
        and dur["offset_changes_received"] + aft["offset_changes_received"] > 0
    detail = "; ".join(
        f"{ph}: {_f(v.get('chatter_windows'))} windows judged, {_f(v.get('suppression_actions'))} suppressions "
        f"({v['speed_writes_received']} speed writes received), {v.get('cuts', 0)} cuts ({v.get('cuts_stable', 0)} "
        f"stable, {v.get('cuts_chattered', 0)} chattered of which {v.get('cuts_cured', 0)} cured, "
        f"{v.get('cuts_alarm_unanswered', 0)} alarms unanswered), {_f(v.get('chatter_alarms'))} alarms, "
        f"{_f(v.get('thermal_writes'))} thermal writes ({v['offset_changes_received']} offset changes received)"
        for ph, v in (("during", dur), ("after", aft)))
    return chatter and thermal, detail


def in_db(db: Path, fz: Fuzzer, sampler: Sampler) -> dict:
    """Every acknowledged record looked up in lathed.db after the daemon stopped."""
    out = {"experiments": [len(fz.experiments), 0], "inspections": [len(fz.inspections), 0],
           "events": [len(sampler.events), 0], "speed_writes": [len(sampler.speed_writes), 0], "error": None}
    try:
        con = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=30)
        q = lambda sql, p=(): con.execute(sql, p).fetchall()  # noqa: E731
        ids = {r[0] for r in q("SELECT id FROM experiments")}
        out["experiments"][1] = sum(i in ids for i in fz.experiments)
        insp = {(r[0], r[1]) for r in q("SELECT part_uuid, ra_um FROM inspections")}
        out["inspections"][1] = sum((u, ra) in insp for u, ra in fz.inspections)
        evids = {r[0] for r in q("SELECT id FROM events")}
        out["events"][1] = sum(i in evids for i in sampler.events)
        sent = q("SELECT count(*) FROM events WHERE kind = 'command_sent' AND json_extract(payload, '$.machine') = "
                 "'lathe' AND json_extract(payload, '$.action') = 'spindle_rpm'")[0][0]
        out["speed_writes"][1] = sent
        con.close()
    except sqlite3.Error as e:
        out["error"] = f"{type(e).__name__}: {e}"
    return out


def hostile_config(cfg: Path, vib_port: int, tty_path: str) -> None:
    text = cfg.read_text().replace("[simulator]", f"[simulator]\ndepth_mm = {DEPTH_MM}", 1)
    text += f"""
[sensor.hostile_vib]
plugin = "vibration_tcp"
host = "127.0.0.1"
port = {vib_port}
retry_initial = "200ms"
retry_max = "2s"

[sensor.hostile_temps]
plugin = "ds18b20_serial"
port = "{tty_path}"
stale_after = "10s"
retry_initial = "200ms"
retry_max = "2s"

[analyzer.hostile_chatter]
plugin = "chatter"
input = "hostile_vib"
machine = "lathe"

# the mill has no offset register: this one computes on hostile input but cannot write
[analyzer.hostile_thermal]
plugin = "thermal"
input = "hostile_temps"
machine = "mill"
"""
    cfg.write_text(text)


def stop_daemon(proc, tmp: Path) -> str:
    if proc.poll() is not None:
        return f"had exited (code {proc.returncode}) before SIGTERM"
    t = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(30)
    except Exception:
        proc.kill()
        proc.wait()
        return "did not stop within 30 s of SIGTERM: killed"
    return f"stopped in {time.monotonic() - t:.1f} s, code {proc.returncode}"


def run(a) -> dict:
    rng = random.Random(a.seed)
    res: dict = {"duration_s": a.duration, "warmup_s": a.warmup, "after_s": a.after, "seed": a.seed}
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        cfg = config(tmp)
        vib, ser = VibrationPeer(random.Random(rng.random())), SerialPeer(random.Random(rng.random()))
        hostile_config(cfg, vib.port, ser.path)
        vib.start()
        ser.start()
        proc = start(cfg, tmp)
        t_ready = time.time()
        sock, sim_sock = tmp / "run" / "lathed.sock", tmp / "run" / "sim.sock"
        # lathed-opcua's start (its nodeset import, ~10 s) runs inside the warm-up, not before it
        ua = hostile_opcua.OpcUa(tmp, sock) if a.opcua else None
        web_port = free_port()
        web = start_web(tmp, sock, web_port) if a.web else None
        webw = WebWatch(web_port, web.pid if web else 0, tmp / "lathed-web.log")
        sampler = Sampler(sock, sim_sock, proc.pid).start()
        fz = Fuzzer(sock, random.Random(rng.random()), heavy_every=max(30.0, a.duration / 5))
        slow = SlowClients(sock)
        ua_floods = None
        try:
            if ua is not None:
                ua_floods = opcua_start(ua)
            time.sleep(max(0.0, t_ready + a.warmup - time.time()))
            t_load = time.time()
            if ua_floods:
                ua_cpu0, ua_t0 = opcua_load(ua_floods)
            res["rss_start_mb"] = _rss(proc.pid)
            vib.hostile.set()
            ser.hostile.set()
            fz.start()
            slow.start()
            if web is not None:
                webw.start_flood(tmp)
            deadline = time.monotonic() + a.duration
            while time.monotonic() < deadline and proc.poll() is None:
                time.sleep(min(1.0, max(0.0, deadline - time.monotonic())))
            res["web"] = webw.end_flood()
            slow.join()
            fz.join()
            vib.hostile.clear()
            ser.hostile.clear()
            t_end = time.time()
            if ua_floods:
                res["opcua"] = opcua_end(ua_floods, t_load, t_end, ua_cpu0, ua_t0)
            time.sleep(RSS_SETTLE_S)
            res["rss_after_mb"] = _rss(proc.pid)
            time.sleep(max(0.0, a.after - RSS_SETTLE_S))
            res["rss_end_mb"] = _rss(proc.pid)
            sampler.join()
            sampler.poll()                  # the last events before the stop
            t_stop = time.time()
            # the newest status the daemon answered (the last call may have failed: counted above)
            final = next((s for _, s, _ in reversed(sampler.status) if s is not None), None)
            res["last_status_failed"] = bool(sampler.status) and sampler.status[-1][1] is None
        finally:
            slow.join()
            fz.join()
            sampler.join()
            if "web" not in res:
                res["web"] = webw.end_flood()
            if ua_floods:
                for flood in ua_floods[1:]:
                    flood.join()
            # the three are told to stop at once and then waited for (each stop takes a second or two)
            if web is not None:
                web.terminate()
            if ua is not None:
                ua.proc.terminate()
            res["daemon_stop"] = stop_daemon(proc, tmp)
            if web is not None:
                web.wait(15)
            if ua is not None:
                res["opcua_stop"] = ua.stop()
            vib.join()
            ser.join()
            ser.close()
        res["records"] = in_db(tmp / "state" / "lathed.db", fz, sampler)
        res["log_tail"] = [ln[:300] for ln in (tmp / "lathed.log").read_text(errors="replace").splitlines()[-5:]]
        errors = [ln[:300] for ln in (tmp / "lathed.log").read_text(errors="replace").splitlines()
                  if '"level": "error"' in ln or "[error" in ln]
        res["log_errors"], res["log_error_lines"] = len(errors), errors[:5]
    # -- figures ---------------------------------------------------------------------
    ok_during = [(t, s) for t, s, e in sampler.status if s is not None and t_load <= t <= t_end]
    fail_during = [e for t, s, e in sampler.status if s is None and t_load <= t <= t_end]
    took = [d for t, d in sampler.status_s if t_load <= t <= t_end]
    res["status_calls"] = {"during_ok": len(ok_during), "during_failed": len(fail_during),
                           "during_max_s": max(took, default=None), "during_over_2s": sum(d > 2.0 for d in took),
                           "failures": sorted(set(fail_during))[:5],
                           "all_failed": sum(s is None for _, s, _ in sampler.status)}
    lags = [s["daemon"].get("loop_lag_ms") for _, s in ok_during if s["daemon"].get("loop_lag_ms")]
    # a window ends at its status call: those up to one window after the load still saw it
    covering = [s["daemon"]["loop_lag_ms"] for t, s, _ in sampler.status if s is not None
                and s["daemon"].get("loop_lag_ms") and t_load < t <= t_end + s["daemon"]["loop_lag_ms"]["window_s"]]
    before = [s for t, s, _ in sampler.status if s is not None and t < t_load]
    first = (before[-1] if before else (ok_during[0][1] if ok_during else None))
    # the histogram up to a few seconds after the load: a stall at its end is recorded when the loop wakes
    after_ok = [s for t, s, _ in sampler.status if s is not None and t > t_end + 5.0]
    last = after_ok[0] if after_ok else (ok_during[-1][1] if ok_during else None)
    hist = lag_from_histograms(first and first["daemon"].get("loop_lag_ms", {}).get("since_start"),
                               last and last["daemon"].get("loop_lag_ms", {}).get("since_start"))
    res["loop_lag_ms"] = {
        "p50_median_of_windows": statistics.median([x["p50"] for x in lags if x["p50"] is not None]) if lags else None,
        "p99_worst_window": max((x["p99"] for x in lags if x["p99"] is not None), default=None),
        "max": max((x["max"] for x in lags + covering if x["max"] is not None), default=None),
        "windows": len(lags), "histogram": hist}
    rss_load = [r for t, r in sampler.rss if t_load <= t <= t_end]
    res["rss_peak_mb"] = max(rss_load) if rss_load else None
    res["rss_ratio"] = (res["rss_after_mb"] / res["rss_start_mb"]
                        if res.get("rss_after_mb") and res.get("rss_start_mb") else None)
    phases = {"before": (0.0, t_load), "during": (t_load, t_end), "after": (t_end, t_stop)}
    acts = {}
    for ph, (t0, t1) in phases.items():
        ev = [e for e in sampler.events.values() if t0 <= e["t"] < t1]
        span = (t1 - t0) if ph != "before" else t_load - t_ready
        c0, c1 = (counters(sampler, t0) if ph != "before" else {}), counters(sampler, t1)
        offs = [o for t, o in sampler.offsets if t0 <= t < t1]
        acts[ph] = {"minutes": span / 60.0,
                    **{k: (c1[k] - c0.get(k, 0)) if k in c1 else None for k in COUNTERS},
                    "speed_writes_received": sum(t0 <= w < t1 for w in sampler.speed_writes.values()),
                    "offset_changes_received": sum(x != y for x, y in zip(offs, offs[1:])),
                    "chatter_alarm_events": sum(e["kind"] == "chatter_alarm" and e["source"] == "chatter"
                                                for e in ev),
                    "suppression_action_events": sum(e["kind"] == "suppression_action" for e in ev),
                    "compensation_events": sum(e["kind"] == "compensation" and e["source"] == "thermal"
                                               for e in ev),
                    **cut_counts([e["payload"] for e in ev if e["kind"] == "cut"
                                  and e["payload"].get("machine") == "lathe"])}
    res["loops"] = acts
    drops = [s["daemon"]["control"].get("dropped", 0) for t, s, _ in sampler.status
             if s is not None and t_load - STATUS_EVERY_S * 2 <= t <= t_end + STATUS_EVERY_S * 2]
    res["web_daemon_dropped"] = (drops[-1] - drops[0]) if drops else None
    peers = {}
    if final is not None:
        for s in final.get("sensors", []):
            if s["name"].startswith("hostile_"):
                peers[s["name"]] = {k: v for k, v in s.items()
                                    if k not in ("name", "plugin", "detail", "sensors", "last_value", "kind")}
        for an in final.get("analyzers", []):
            if an["name"].startswith("hostile_"):
                peers[an["name"]] = {"state": an["state"], "last_error": an.get("last_error")}
        res["store"] = {k: final["daemon"]["store"].get(k) for k in ("written", "failed", "queued", "last_error")}
        res["daemon_state"] = final["daemon"]["state"]
    else:
        res["store"] = None
        res["daemon_state"] = "no status reply after the load"
    for name in ("hostile_vib", "hostile_temps", "hostile_chatter", "hostile_thermal"):
        faults = sum(e["source"] == name and e["kind"].endswith("_fault") for e in sampler.events.values())
        peers.setdefault(name, {})["fault_events"] = faults
    res["peers"] = peers
    res["peer_sent"] = {"hostile_vib": vib.sent, "hostile_temps": ser.sent}
    res["fuzz"] = fz.outcomes
    res["fuzz_heavy"] = fz.heavy
    res["valid_requests_failed"] = fz.valid_failed
    res["slow_clients"] = {"opened": slow.opened, "dropped_by_daemon": slow.dropped,
                           "connect_failed": slow.connect_failed, "max_open": slow.max_open}
    res["bench_errors"] = [f"{n}: {e}" for n, o in (("vib", vib), ("serial", ser), ("fuzz", fz), ("slow", slow),
                                                     ("sampler", sampler)) for e in o.errors]
    return res


# -- the OPC UA floods (bench/hostile_opcua.py) -----------------------------------------
def opcua_start(ua: hostile_opcua.OpcUa) -> tuple:
    """Once lathed-opcua (started beside the daemon) serves: the fresh-client probe from now on
    (the floods wait)."""
    try:
        ua.wait_serving()
    except BaseException:
        ua.stop()             # not left running (at 80 % of a core) when the bench gives up on it
        raise
    return (ua, hostile_opcua.IdleFlood(ua.port), hostile_opcua.Storm(ua.url),
            hostile_opcua.FreshClient(ua.url).start())


def opcua_load(floods: tuple) -> tuple[float, float]:
    ua, idle, storm, _ = floods
    idle.start()
    storm.start()
    return hostile_opcua.cpu_s(ua.proc.pid), time.monotonic()


def opcua_end(floods: tuple, t_load: float, t_end: float, cpu0: float, t0: float) -> dict:
    ua, idle, storm, probe = floods
    wall = time.monotonic() - t0
    idle.join()
    storm.join()
    probe.join()
    return hostile_opcua.figures(ua, idle, storm, probe, t_load, t_end, cpu0, wall)


def _f(x, p=1, unit="") -> str:
    return "-" if x is None else (f"{x:.{p}f}{unit}" if isinstance(x, float) else f"{x}{unit}")


def report(r: dict) -> None:
    rec = r["records"]
    lost = sum(max(0, ack - found) for key, (ack, found) in ((k, rec[k]) for k in
                                                              ("experiments", "inspections", "events")))
    writes_unrecorded = max(0, rec["speed_writes"][0] - rec["speed_writes"][1])
    lag = r["loop_lag_ms"]
    hist = lag["histogram"]
    sc = r["status_calls"]
    st = r["store"] or {}
    print(f"Hostile load against the daemon on the simulator: {r['duration_s']:.0f} s of load "
          f"(warm-up {r['warmup_s']:.0f} s, after {r['after_s']:.0f} s, seed {r['seed']}); "
          f"daemon {r['daemon_stop']}\n")
    print("| measure | value | bar (issue 18) |")
    print("|---|---|---|")
    print(f"| records acknowledged / found in lathed.db after SIGTERM: experiments | "
          f"{rec['experiments'][0]} / {rec['experiments'][1]} | all found |")
    print(f"| ... inspections | {rec['inspections'][0]} / {rec['inspections'][1]} | all found |")
    print(f"| ... events reported by `events` | {rec['events'][0]} / {rec['events'][1]} | all found |")
    print(f"| spindle writes the lathe received / command_sent records | {rec['speed_writes'][0]} / "
          f"{rec['speed_writes'][1]} | every write recorded |")
    print(f"| valid experiment_add / parts / inspect requests that got no acknowledgement | "
          f"{r['valid_requests_failed']} | 0 |")
    print(f"| store written / failed / queued (last status) | {_f(st.get('written'))} / {_f(st.get('failed'))} / "
          f"{_f(st.get('queued'))} | failed 0, queue drained |")
    print(f"| event-loop lag during load, p50 (median of {lag['windows']} status windows) | "
          f"{_f(lag['p50_median_of_windows'], 2, ' ms')} | |")
    print(f"| event-loop lag p99, worst 10 s window / from the histogram | {_f(lag['p99_worst_window'], 1, ' ms')} / "
          + (f"<= {hist['p99_le']} ms ({hist['above_bar']} of {hist['n']} wakes > {LAG_BAR_MS:g} ms)" if hist
             else "-") + f" | < {LAG_BAR_MS:g} ms |")
    print(f"| event-loop lag max | {_f(lag['max'], 1, ' ms')} | |")
    print(f"| status calls during load ok / failed (5 s timeout) | {sc['during_ok']} / {sc['during_failed']} | "
          "0 failed |")
    print(f"| RSS at start / peak during load / {RSS_SETTLE_S:.0f} s after load / end | "
          f"{_f(r.get('rss_start_mb'), 0)} / {_f(r.get('rss_peak_mb'), 0)} / {_f(r.get('rss_after_mb'), 0)} / "
          f"{_f(r.get('rss_end_mb'), 0)} MB | |")
    print(f"| RSS after / start | {_f(r.get('rss_ratio'), 3)} | <= {1 + RSS_BAR:.2f} |")
    for ph, v in r["loops"].items():
        print(f"| {ph} load ({v['minutes']:.1f} min): chatter alarms / suppression actions / thermal writes "
              f"(daemon's counters); speed writes / offset changes the lathe received; alarm / suppression / "
              f"compensation records | {_f(v['chatter_alarms'])} / {_f(v['suppression_actions'])} / "
              f"{_f(v['thermal_writes'])}; {v['speed_writes_received']} / {v['offset_changes_received']}; "
              f"{v['chatter_alarm_events']} / {v['suppression_action_events']} / {v['compensation_events']} "
              "| still acting |")
    for name, p in r["peers"].items():
        print(f"| peer {name} | {json.dumps(p, default=str)[:500]} | bad input seen and counted |")
    print(f"| hostile frames / lines sent | vib {json.dumps(r['peer_sent']['hostile_vib'])}; "
          f"temps {json.dumps(r['peer_sent']['hostile_temps'])} | |")
    fz = {k: v for k, v in r["fuzz"].items()}
    print(f"| fuzz requests by outcome | {json.dumps(fz)} | no internal error, a reply to each |")
    print(f"| heavy requests | {'; '.join(r['fuzz_heavy']) or '-'} | |")
    print(f"| slow clients | {json.dumps(r['slow_clients'])} | |")
    print(f"| error lines in the daemon's log | {r['log_errors']} | |")
    web_rows, web_verdicts = web_report(r["web"], r.get("web_daemon_dropped")) if r.get("web") else ([], [])
    opcua_lines = hostile_opcua.report(r["opcua"]) if r.get("opcua") else []
    for row in web_rows + opcua_lines[:-2]:
        print(row)
    for ln in r.get("log_error_lines", []):
        print(f"\n    {ln}")
    if r["bench_errors"]:
        print(f"| bench errors | {'; '.join(r['bench_errors'])} | |")
    print()
    verdict = lambda ok: "PASS" if ok else "FAIL"  # noqa: E731
    print(f"- no record acknowledged and lost: {verdict(lost == 0 and writes_unrecorded == 0 and not rec['error'])}"
          f" ({lost} acknowledged records missing, {writes_unrecorded} received writes without command_sent"
          + (f", db: {rec['error']}" if rec["error"] else "") + ")")
    p99 = hist["p99_le"] if hist else None
    lag_ok = p99 is not None and p99 <= LAG_BAR_MS and hist["above_bar"] <= 0.01 * hist["n"] \
        and sc["during_failed"] == 0
    print(f"- event-loop lag p99 < {LAG_BAR_MS:g} ms: {verdict(lag_ok)}"
          f" (p99 <= {p99} ms, {sc['during_failed']} status calls failed)")
    ratio = r.get("rss_ratio")
    print(f"- RSS back within {RSS_BAR:.0%} of its start: {verdict(ratio is not None and ratio <= 1 + RSS_BAR)}"
          f" ({_f(ratio, 3)})")
    acting, detail = loops_acting(r["loops"])
    print(f"- chatter and thermal loops still acting: {verdict(acting)} ({detail})")
    print(f"- the daemon answers a fresh control client within 2 s during the load: "
          f"{verdict(sc['during_failed'] == 0 and sc.get('during_over_2s', 1) == 0 and sc['during_ok'] > 0)} "
          f"({sc['during_ok']} status calls, slowest {_f(sc.get('during_max_s'), 2, ' s')}, {sc['during_failed']} failed)")
    for text, ok, why in web_verdicts:
        print(f"- {text}: {verdict(ok)} ({why})")
    if opcua_lines:
        print(opcua_lines[-1])


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--duration", type=float, default=600.0, help="seconds of hostile load (issue: 10 min)")
    ap.add_argument("--warmup", type=float, default=60.0, help="seconds before the load")
    ap.add_argument("--after", type=float, default=60.0, help=f"seconds after it (>= {RSS_SETTLE_S:g})")
    ap.add_argument("--seed", type=int, default=18)
    ap.add_argument("--json", type=Path, help="also write the figures here")
    ap.add_argument("--no-web", dest="web", action="store_false",
                    help="without lathed-web and its floods (a baseline for the daemon's figures)")
    ap.add_argument("--no-opcua", dest="opcua", action="store_false",
                    help="without lathed-opcua and its floods (bench/hostile_opcua.py)")
    a = ap.parse_args()
    a.after = max(a.after, RSS_SETTLE_S)
    r = run(a)
    report(r)
    if a.json:
        a.json.write_text(json.dumps(r, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
