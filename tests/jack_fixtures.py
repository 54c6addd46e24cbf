"""A real JACK audio server for tests, and a player feeding its ports.

jackd (Debian's jackd2, installed by tests/ensure_jack.sh) runs with its dummy backend:
no sound card, the server's own clock paces the periods as a card's would. Each server
has a private name (JACK_DEFAULT_SERVER tells a client, the daemon's capture helper too,
which one). PortAudio opens it as the device "system"; its stream is the JACK client
"PortAudio", whose input ports the player's outputs are connected to.

The player is a JACK client in the test process: its process callback plays queued
segments, and between them its idle signal (the spindle turning in air), on as many
output ports as channels.
"""
from __future__ import annotations

import fcntl
import os
import shutil
import signal
import struct
import subprocess
import threading
import uuid
from collections import deque

import numpy as np
import pytest

from tests.conftest import wait_until

jack = pytest.importorskip("jack", reason="JACK-Client not installed (pip install -e '.[test]')")


def have_jackd() -> bool:
    return shutil.which("jackd") is not None or os.path.exists("/usr/bin/jackd")


def _leftover(name: str) -> list[int]:
    """jackd processes serving ``name`` (a test run killed before it stopped its server)."""
    pids = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                args = open(f"/proc/{d}/cmdline", "rb").read().split(b"\0")
            except OSError:
                continue
            if args and args[0].endswith(b"jackd") and name.encode() in args:
                pids.append(int(d))
    return pids


NAMES = 6          # JACK's table of servers in shared memory has 8 entries
REGISTRY = "/dev/shm/jack-shm-registry"


def _claim() -> tuple[str, int]:
    """A server name from a fixed few, held by a lock for this server's life (two suites on one
    machine must not share a name). JACK reclaims a dead server's entry only for its own name,
    so a server killed before it could clean up leaves an entry that only a fixed name frees."""
    for k in range(NAMES):
        fd = os.open(f"/tmp/lathed-jack-{k}.lock", os.O_RDWR | os.O_CREAT, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            continue
        return f"lathed-test-{k}", fd
    raise RuntimeError(f"all {NAMES} JACK test server names are in use (/tmp/lathed-jack-*.lock)")


def _reclaim_dead_entries() -> None:
    """JACK's table of servers (8 entries) frees a dead server's entry only when a server of the
    same name starts; servers killed under other names (older test runs) fill it for good ("Too
    many servers already active"). Free every entry whose process is gone, as JACK does for one
    name, in place (clients keep the table they mapped). The layout is jack2's shm.h; a table of
    another layout is left alone."""
    try:
        f = open(REGISTRY, "r+b")
    except OSError:
        return                      # none yet: the first server makes it
    with f:
        head = f.read(24)
        if len(head) < 24 or head[:4] != b"JACK"[::-1]:
            return
        hdr_len, entry = struct.unpack_from("<ii", head, 16)
        slot = (hdr_len - 24) // 8
        if slot < 8 or hdr_len != 24 + 8 * slot:
            return
        for i in range(8):
            f.seek(24 + i * slot)
            pid = struct.unpack("<i", f.read(4))[0]
            if pid > 0 and not os.path.exists(f"/proc/{pid}"):
                f.seek(24 + i * slot)
                f.write(bytes(slot))


class JackServer:
    """A JACK server under a name of its own (``_claim``), with the dummy backend."""

    def __init__(self, rate: int = 48000, period: int = 1024, capture: int = 2, name: str | None = None) -> None:
        if not have_jackd():
            raise RuntimeError("no jackd; run `bash tests/ensure_jack.sh`")
        self.rate, self.period, self.capture = rate, period, capture
        self._lock: int | None = None
        if name is None:
            name, self._lock = _claim()
        self.name = name
        self.env = {"JACK_DEFAULT_SERVER": self.name, "JACK_NO_START_SERVER": "1",
                    "JACK_NO_AUDIO_RESERVATION": "1"}
        self.proc: subprocess.Popen | None = None
        self.log = b""

    def start(self) -> None:
        for pid in _leftover(self.name):
            os.kill(pid, signal.SIGKILL)
        # one process at a time from freeing dead entries to a server registered in the table
        gate = os.open("/tmp/lathed-jack-start.lock", os.O_RDWR | os.O_CREAT, 0o600)
        fcntl.flock(gate, fcntl.LOCK_EX)
        try:
            _reclaim_dead_entries()
            self._launch()
        finally:
            os.close(gate)

    def _launch(self) -> None:
        # synchronous (-S): each cycle waits for every client (up to -t ms), so a client the busy
        # test machine runs late stalls the dummy device a moment (a step of its clock, which
        # the driver follows) instead of playing zeros for the period it missed
        self.proc = subprocess.Popen(
            ["jackd", "--no-realtime", "-S", "-t", "5000", "-n", self.name, "-d", "dummy", "-r", str(self.rate),
             "-p", str(self.period), "-C", str(self.capture), "-P", "0"],
            env={**os.environ, **self.env}, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            start_new_session=True)
        threading.Thread(target=self._drain, args=(self.proc,), daemon=True).start()

        def up():
            assert self.proc.poll() is None, f"jackd exited {self.proc.returncode}: {self.log[-2000:]!r}"
            c = jack.Client("probe", servername=self.name, no_start_server=True)
            c.close()
            return True
        try:
            wait_until(up, 20, 0.1, what=f"jackd {self.name}")
        except BaseException:
            self.stop()            # not left running under a name another run will claim
            raise

    def _drain(self, proc) -> None:
        for line in proc.stdout:
            self.log = (self.log + line)[-20000:]

    def stop(self) -> None:
        """The server gone, as an audio device unplugged: every client loses it."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                # a server whose capture client was killed can take 10 s or more to act on
                # SIGTERM; killed, it leaves entries the next start frees (_reclaim_dead_entries)
                self.proc.wait(2)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.proc = None

    def release(self) -> None:
        """The server stopped and its name free for another."""
        self.stop()
        if self._lock is not None:
            os.close(self._lock)
            self._lock = None


class Player:
    """Plays queued (frames x channels) float32 segments into JACK; ``idle`` in between."""

    def __init__(self, server: JackServer, channels: int = 1, idle: np.ndarray | None = None) -> None:
        self.server, self.channels = server, channels
        self.client = jack.Client(f"player-{uuid.uuid4().hex[:6]}", servername=server.name, no_start_server=True)
        self.ports = [self.client.outports.register(f"out_{i}") for i in range(channels)]
        self.idle = np.zeros((server.period, channels), np.float32) if idle is None else \
            np.asarray(idle, np.float32).reshape(-1, channels)
        self._idle_pos = 0
        self._queue: deque[tuple[np.ndarray, threading.Event]] = deque()
        self._pos = 0
        self.played = 0          # frames played since activation
        self.client.set_process_callback(self._process)
        self.client.activate()

    def _process(self, frames: int) -> None:
        out = np.empty((frames, self.channels), np.float32)
        i = 0
        while i < frames:
            if self._queue:
                seg, done = self._queue[0]
                n = min(frames - i, len(seg) - self._pos)
                out[i:i + n] = seg[self._pos:self._pos + n]
                self._pos += n
                i += n
                if self._pos >= len(seg):
                    self._queue.popleft()
                    self._pos = 0
                    done.set()
            else:
                n = min(frames - i, len(self.idle) - self._idle_pos)
                out[i:i + n] = self.idle[self._idle_pos:self._idle_pos + n]
                self._idle_pos = (self._idle_pos + n) % len(self.idle)
                i += n
        for k, p in enumerate(self.ports):
            p.get_array()[:] = out[:, k]
        self.played += frames

    def play(self, data: np.ndarray) -> threading.Event:
        """Queue a segment; the event is set once its last frame was played."""
        done = threading.Event()
        self._queue.append((np.ascontiguousarray(np.asarray(data, np.float32).reshape(-1, self.channels)), done))
        return done

    def connect(self, client: str = "PortAudio", first: int = 0, timeout: float = 20.0) -> list[str]:
        """Our outputs to ``client``'s inputs from ``first`` on, once they exist (a capture
        opens its stream after the daemon starts)."""
        def targets():
            names = sorted((p.name for p in self.client.get_ports(f"{client}:.*", is_input=True, is_audio=True)),
                           key=lambda n: int(n.rsplit("_", 1)[1]) if n.rsplit("_", 1)[1].isdigit() else 0)
            return names if len(names) >= first + self.channels else None
        names = wait_until(targets, timeout, 0.05, what=f"JACK input ports of {client}")
        for k, port in enumerate(self.ports):
            dest = names[first + k]
            if port.name not in [p.name for p in self.client.get_all_connections(dest)]:
                self.client.connect(port, dest)
        return names[first:first + self.channels]

    def close(self) -> None:
        try:
            self.client.deactivate()
            self.client.close()
        except jack.JackError:
            pass          # the server is gone already


@pytest.fixture
def jack_server():
    srv = JackServer()
    srv.start()
    yield srv
    srv.release()
