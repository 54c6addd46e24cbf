"""A real JACK audio server for tests, and a player feeding its ports.

jackd (Debian's jackd2, installed by tests/ensure_jack.sh) runs with its dummy backend:
no sound card, the server's own clock paces the periods as a card's would. Each server
has a private name (JACK_DEFAULT_SERVER tells a client, the daemon's capture helper too,
which one). PortAudio opens it as the device "system"; its stream is the JACK client
"PortAudio", whose input ports the player's outputs are connected to.

The player is a JACK client in a process of its own (tests/jack_player.py): it plays
queued segments, and between them its idle signal (the spindle turning in air), on as
many output ports as channels.
"""
from __future__ import annotations

import fcntl
import json
import os
import queue
import shutil
import signal
import struct
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import wait_until
from tests.jack_player import HEAD

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
    """Plays queued (frames x channels) float32 segments into JACK; ``idle`` in between. The
    JACK client is a process of its own (tests/jack_player.py says why)."""

    def __init__(self, server: JackServer, channels: int = 1, idle: np.ndarray | None = None) -> None:
        self.server, self.channels = server, channels
        idle = np.zeros((server.period, channels), np.float32) if idle is None else \
            np.asarray(idle, np.float32).reshape(-1, channels)
        self.proc = subprocess.Popen([sys.executable, str(Path(__file__).with_name("jack_player.py")), server.name,
                                      str(channels)], env={**os.environ, **server.env},
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=False)
        self._seq = 0
        self._done: dict[int, threading.Event] = {}
        self._replies: queue.Queue = queue.Queue()
        self._send(b"IDLE", 0, np.ascontiguousarray(idle).tobytes())
        threading.Thread(target=self._read, daemon=True).start()
        word = self._reply(20)
        assert word == "READY", f"the JACK player did not start: {word}"

    def _send(self, kind: bytes, seq: int, body: bytes) -> None:
        self.proc.stdin.write(HEAD.pack(kind, seq, len(body)) + body)
        self.proc.stdin.flush()

    def _read(self) -> None:
        for raw in self.proc.stdout:
            line = raw.decode().strip()
            if line.startswith("DONE "):
                self._done.pop(int(line[5:])).set()
            else:
                self._replies.put(line)
        self._replies.put(f"the player exited {self.proc.wait()}")

    def _reply(self, timeout: float) -> str:
        try:
            return self._replies.get(timeout=timeout)
        except queue.Empty:
            return f"no answer from the player within {timeout:g} s"

    def play(self, data: np.ndarray) -> threading.Event:
        """Queue a segment; the event is set once its last frame was played."""
        self._seq += 1
        done = self._done[self._seq] = threading.Event()
        seg = np.ascontiguousarray(np.asarray(data, np.float32).reshape(-1, self.channels))
        self._send(b"PLAY", self._seq, seg.tobytes())
        return done

    def connect(self, client: str = "PortAudio", first: int = 0, timeout: float = 20.0) -> list[str]:
        """Our outputs to ``client``'s inputs from ``first`` on, once they exist (a capture
        opens its stream after the daemon starts)."""
        self._send(b"CONN", 0, json.dumps({"client": client, "first": first, "timeout": timeout}).encode())
        word = self._reply(timeout + 10)
        assert word.startswith("CONNECTED "), word
        return json.loads(word[len("CONNECTED "):])

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.stdin.close()
            try:
                self.proc.wait(5)       # a client of a server that is gone may hang in its close
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


@pytest.fixture
def jack_server():
    srv = JackServer()
    srv.start()
    yield srv
    srv.release()
