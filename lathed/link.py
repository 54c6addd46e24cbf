"""The side processes' link to the daemon: one subscription over the control socket.

lathed-web and lathed-opcua are separate processes that speak only the
control socket (as Moonraker beside Klipper): each keeps one ``subscribe``
connection (lathed.push), merges what it pushes, reconnects by itself when
the daemon stops or restarts, and hands each frame on (``broadcast``).
``ask`` sends one control request (an action, with the user's name).
"""
from __future__ import annotations

import asyncio
import ipaddress
import json
from collections import deque
from pathlib import Path
from typing import Any

import structlog

from lathed.viewdelta import merge_view

log = structlog.get_logger("lathed.link")
HISTORY = 300          # points per value kept for a new page's charts
EVENTS_KEPT = 200
RETRY_S = 1.0
LINE_LIMIT = 16 << 20  # one pushed line (a status of a large line of machines, with views)


def loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class DaemonLink:
    """The one subscription; what it has seen, for a client that comes now."""

    def __init__(self, sock: Path, rate_hz: float):
        self.sock, self.rate_hz = sock, rate_hz
        self.connected = False
        self.error: str | None = "not connected yet"
        self.status: dict | None = None
        self.latest: dict[str, list] = {}
        self.history: dict[str, deque] = {}
        self.vibration: dict[str, Any] = {}
        self.views: dict[str, Any] = {}
        self.events: deque = deque(maxlen=EVENTS_KEPT)
        self.frames = 0

    def subscription(self) -> dict:
        """What to ask the daemon for (lathed.push)."""
        return {"samples": ["*/*"], "vibration": ["*"], "views": ["*"], "states": True, "events": True,
                "events_limit": EVENTS_KEPT, "rate_hz": self.rate_hz}

    def snapshot(self) -> dict:
        return {"type": "init", "connected": self.connected, "error": self.error, "status": self.status,
                "units": {k: v[2] for k, v in self.latest.items()},
                "history": {k: [[p[0] for p in h], [p[1] for p in h]] for k, h in self.history.items()},
                "vibration": self.vibration, "views": self.views, "events": list(self.events)}

    def _merge(self, f: dict) -> None:
        for k, (t, v, unit) in f.get("samples", {}).items():
            self.latest[k] = [t, v, unit]
            self.history.setdefault(k, deque(maxlen=HISTORY)).append((t, v))
        for k, v in f.get("vibration", {}).items():
            if v is not None:
                self.vibration[k] = merge_view(self.vibration.get(k), v)
        for k, v in f.get("views", {}).items():
            self.views[k] = merge_view(self.views.get(k), v)
        if f.get("status"):
            self.status = f["status"]
        self.events.extend(f.get("events", []))

    def broadcast(self, msg: dict) -> None:
        """Hand a message on (the snapshot at connect, each frame, link up/down)."""
        raise NotImplementedError

    def _down(self, why: str) -> None:
        if self.connected or self.error != why:
            self.connected, self.error = False, why
            log.warning("daemon_link_down", socket=str(self.sock), error=why)
            self.broadcast({"type": "link", "connected": False, "error": why})

    async def run(self) -> None:
        while True:
            try:
                await self._session()
            except (FileNotFoundError, ConnectionRefusedError) as e:
                self._down(f"no daemon on {self.sock} ({e.strerror or e})")
            except (OSError, asyncio.IncompleteReadError, ValueError) as e:
                self._down(f"lost the daemon on {self.sock}: {getattr(e, 'strerror', None) or e}")
            except Refused as e:
                self._down(str(e))
            await asyncio.sleep(RETRY_S)

    async def _session(self) -> None:
        reader, writer = await asyncio.open_unix_connection(str(self.sock), limit=LINE_LIMIT)
        try:
            writer.write(json.dumps({"cmd": "subscribe", "args": self.subscription()}).encode() + b"\n")
            await writer.drain()
            first = await self._line(reader)
            if not first.get("ok"):
                raise Refused(f"the daemon refused the subscription: {first.get('error')}")
            snap = first["result"]
            self.latest, self.history, self.vibration, self.views = {}, {}, {}, {}
            self.events.clear()
            self._merge(snap)
            self.connected, self.error = True, None
            log.info("daemon_link_up", socket=str(self.sock))
            self.broadcast(self.snapshot())
            while True:
                msg = await self._line(reader)
                if "push" not in msg:
                    raise Refused(msg.get("error", "the daemon ended the subscription"))
                self.frames += 1
                self._merge(msg["push"])
                self.broadcast({"type": "frame", **msg["push"]})
        finally:
            writer.close()

    @staticmethod
    async def _line(reader: asyncio.StreamReader) -> dict:
        async with asyncio.timeout(10.0):   # the daemon sends a frame every second at least
            line = await reader.readline()
        if not line:
            raise ConnectionResetError(0, "it closed the connection (stopped or restarting?)")
        return json.loads(line)


class Refused(Exception):
    pass


async def ask(sock: Path, cmd: str, args: dict) -> Any:
    """One control request; RuntimeError with the daemon's one-line reason if refused."""
    reader, writer = await asyncio.open_unix_connection(str(sock), limit=LINE_LIMIT)
    try:
        writer.write(json.dumps({"cmd": cmd, "args": args}).encode() + b"\n")
        async with asyncio.timeout(15.0):
            reply = json.loads(await reader.readline())
    finally:
        writer.close()
    if not reply.get("ok"):
        raise RuntimeError(reply.get("error", "refused"))
    return reply["result"]
