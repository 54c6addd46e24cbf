"""A real Mosquitto broker and a subscriber for the MQTT tests and benchmark.

Each broker is its own process on a free loopback port with a temporary
config (never the package's system service); it can be stopped and started
again on the same port, keeping its persistence file, as a restarted plant
broker does. ``tests/ensure_mosquitto.sh`` installs the binary when missing.
"""
from __future__ import annotations

import json
import os
import pwd
import shutil
import signal
import socket
import subprocess
import threading
import uuid
from pathlib import Path

import paho.mqtt.client as mqtt

from tests.conftest import free_port, wait_until


def mosquitto_binary() -> str:
    for p in ("/usr/sbin/mosquitto", shutil.which("mosquitto")):
        if p and os.access(p, os.X_OK):
            return p
    raise RuntimeError("no mosquitto broker binary; run `bash tests/ensure_mosquitto.sh`")


class Broker:
    def __init__(self, root: Path, listener: str = "", extra: str = ""):
        self.root = root
        root.mkdir(parents=True, exist_ok=True)
        self.port = free_port()
        self.conf = root / "mosquitto.conf"
        # run as whoever runs the tests (as root, mosquitto would otherwise switch to its own user)
        self.conf.write_text(f"listener {self.port} 127.0.0.1\n{listener or 'allow_anonymous true'}\n"
                             f"persistence true\npersistence_location {root}/\nmax_queued_messages 0\n"
                             f"user {pwd.getpwuid(os.getuid()).pw_name}\n{extra}")
        self.proc: subprocess.Popen | None = None

    def start(self) -> None:
        with open(self.root / "mosquitto.log", "ab") as log:
            self.proc = subprocess.Popen([mosquitto_binary(), "-c", str(self.conf)], stdout=log,
                                         stderr=subprocess.STDOUT)

        def listening():
            assert self.proc.poll() is None, f"mosquitto exited {self.proc.returncode}: {self.log()}"
            with socket.create_connection(("127.0.0.1", self.port), timeout=1):
                return True
        wait_until(listening, 15, what=f"mosquitto on port {self.port}")

    def stop(self, sig: int = signal.SIGTERM) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()

    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def log(self) -> str:
        p = self.root / "mosquitto.log"
        return p.read_text(errors="replace")[-2000:] if p.exists() else ""


class Subscriber:
    """Subscribes to ``topic`` at QoS 1 and keeps every message. With a
    ``client_id`` its session is persistent: a broker restart (or a reconnect)
    delivers what was queued for it meanwhile."""

    def __init__(self, port: int, topic: str = "lathed/#", client_id: str | None = None):
        self.messages: list[tuple[str, bytes, bool]] = []
        self._lock = threading.Lock()
        self.connects = 0
        self.c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=client_id or f"test-{uuid.uuid4().hex[:8]}",
                             clean_session=client_id is None)
        self.c.on_connect = self._on_connect
        self.c.on_message = self._on_message
        self.c.reconnect_delay_set(0.1, 0.5)
        self.topic = topic
        self.c.connect("127.0.0.1", port, keepalive=10)
        self.c.loop_start()
        wait_until(lambda: self.connects, 10, what="the test subscriber to connect")

    def _on_connect(self, client, userdata, flags, rc, props=None):
        client.subscribe(self.topic, qos=1)
        self.connects += 1

    def _on_message(self, client, userdata, m):
        with self._lock:
            self.messages.append((m.topic, m.payload, bool(m.retain)))

    def received(self, prefix: str = "") -> list[tuple[str, bytes, bool]]:
        with self._lock:
            return [m for m in self.messages if m[0].startswith(prefix)]

    def json(self, prefix: str = "") -> list[tuple[str, dict]]:
        return [(t, json.loads(p)) for t, p, _ in self.received(prefix)]

    def close(self) -> None:
        self.c.loop_stop()
        self.c.disconnect()


SCHEMAS = Path(__file__).resolve().parent.parent / "lathed" / "schemas" / "mqtt"


def schema_validator(kind: str):
    """The published JSON Schema of a payload kind (event, record, value), checked itself first."""
    from jsonschema import Draft202012Validator
    schema = json.loads((SCHEMAS / f"{kind}.schema.json").read_text())
    Draft202012Validator.check_schema(schema)
    return Draft202012Validator(schema, format_checker=Draft202012Validator.FORMAT_CHECKER)


def check_message(topic: str, payload: bytes, validators: dict | None = None) -> str:
    """A published message against docs/mqtt.md's topic tree and its kind's JSON Schema;
    returns the kind (state, event, record, value). Raises on any mismatch."""
    validators = validators if validators is not None else {k: schema_validator(k) for k in ("event", "record", "value")}
    parts = topic.split("/")
    assert parts[0] == "lathed" and len(parts) in (3, 4, 5), f"{topic}: not in the topic tree"
    if len(parts) == 3:
        assert parts[2] == "state" and payload in (b"online", b"offline"), (topic, payload)
        return "state"
    level = parts[3] if len(parts) == 5 else parts[2]
    kind = {"events": "event", "records": "record", "values": "value"}.get(level)
    assert kind and (kind != "value" or len(parts) == 5), f"{topic}: not in the topic tree"
    msg = json.loads(payload)
    validators[kind].validate(msg)
    assert msg["cell"] == parts[1], (topic, msg["cell"])
    seg = lambda name: "".join("_" if c in "/+#" else c for c in name) if name is not None else None  # noqa: E731
    if kind == "value":
        assert (parts[2], parts[4]) == (seg(msg["source"]), seg(msg["quantity"])), topic
        return kind
    # the machine level is there exactly when the message names a machine
    assert (parts[2] if len(parts) == 5 else None) == seg(msg["machine"]), (topic, msg["machine"])
    assert parts[-1] == seg(msg["kind"] if kind == "event" else msg["table"]), topic
    assert msg["id"] == f"{msg['uuid']}/{msg['seq']}", msg["id"]
    return kind
