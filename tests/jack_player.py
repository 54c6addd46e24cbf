"""The test player's JACK client, run as a process of its own by tests/jack_fixtures.Player.

    python tests/jack_player.py SERVER CHANNELS

Why a process: the JACK server runs synchronously (-S), so each period waits for the player's
process callback, which needs the GIL. In a pytest worker that has run many tests, a full
garbage collection or a long C call holding the GIL, on a loaded machine, stalled the player and
so the whole server for over half a second: the capture under test then saw no samples and
said, rightly, "device gone". Here nothing but this file's reader thread shares the GIL.

stdin, from the test: messages of HEAD then a payload. IDLE (first, once: frames x channels
float32 played between segments), PLAY (seq, frames: a segment), CONN (a JSON request:
connect our outputs to a client's inputs once they exist). stdout, to the test: lines
``READY``, ``DONE seq`` (a segment's last frame played), ``CONNECTED [ports]`` or ``ERROR why``.
"""
from __future__ import annotations

import json
import struct
import sys
import threading
import time
import uuid
from collections import deque

import numpy as np

HEAD = struct.Struct("<4sII")      # kind, seq, payload bytes


def read_exactly(f, n: int) -> bytes | None:
    buf = b""
    while len(buf) < n:
        chunk = f.read(n - len(buf))
        if not chunk:
            return None
        buf += chunk
    return buf


def main() -> int:
    import jack

    server, channels = sys.argv[1], int(sys.argv[2])
    inp, out = sys.stdin.buffer, sys.stdout
    lock = threading.Lock()

    def say(line: str) -> None:
        with lock:
            out.write(line + "\n")
            out.flush()

    head = read_exactly(inp, HEAD.size)
    if head is None:
        return 0
    kind, _, size = HEAD.unpack(head)
    assert kind == b"IDLE", kind
    idle = np.frombuffer(read_exactly(inp, size), np.float32).reshape(-1, channels)
    client = jack.Client(f"player-{uuid.uuid4().hex[:6]}", servername=server, no_start_server=True)
    ports = [client.outports.register(f"out_{i}") for i in range(channels)]
    queue: deque[tuple[np.ndarray, int]] = deque()
    finished: deque[int] = deque()
    wake = threading.Event()
    state = {"idle_pos": 0, "pos": 0}

    def process(frames: int) -> None:
        buf = np.empty((frames, channels), np.float32)
        i = 0
        while i < frames:
            if queue:
                seg, seq = queue[0]
                n = min(frames - i, len(seg) - state["pos"])
                buf[i:i + n] = seg[state["pos"]:state["pos"] + n]
                state["pos"] += n
                i += n
                if state["pos"] >= len(seg):
                    queue.popleft()
                    state["pos"] = 0
                    finished.append(seq)
                    wake.set()
            else:
                n = min(frames - i, len(idle) - state["idle_pos"])
                buf[i:i + n] = idle[state["idle_pos"]:state["idle_pos"] + n]
                state["idle_pos"] = (state["idle_pos"] + n) % len(idle)
                i += n
        for k, p in enumerate(ports):
            p.get_array()[:] = buf[:, k]

    def tell_done() -> None:        # never write from the process callback
        while True:
            wake.wait()
            wake.clear()
            while finished:
                say(f"DONE {finished.popleft()}")

    def connect(req: dict) -> None:
        want = f"{req['client']}:.*"
        deadline = time.monotonic() + req["timeout"]
        while True:
            names = sorted((p.name for p in client.get_ports(want, is_input=True, is_audio=True)),
                           key=lambda n: int(n.rsplit("_", 1)[1]) if n.rsplit("_", 1)[1].isdigit() else 0)
            if len(names) >= req["first"] + channels:
                break
            if time.monotonic() > deadline:
                say(f"ERROR no JACK input ports of {req['client']} within {req['timeout']:g} s: {names}")
                return
            time.sleep(0.05)
        for k, port in enumerate(ports):
            dest = names[req["first"] + k]
            if port.name not in [p.name for p in client.get_all_connections(dest)]:
                client.connect(port, dest)
        say("CONNECTED " + json.dumps(names[req["first"]:req["first"] + channels]))

    client.set_process_callback(process)
    client.activate()
    threading.Thread(target=tell_done, daemon=True).start()
    say("READY")
    while (head := read_exactly(inp, HEAD.size)) is not None:
        kind, seq, size = HEAD.unpack(head)
        body = read_exactly(inp, size)
        if body is None:
            break
        if kind == b"PLAY":
            queue.append((np.frombuffer(body, np.float32).reshape(-1, channels), seq))
        elif kind == b"CONN":
            try:
                connect(json.loads(body))
            except jack.JackError as e:
                say(f"ERROR {e}")
    # stdin closed: the test is done with us (the server may be gone already)
    try:
        client.deactivate()
        client.close()
    except jack.JackError:
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
