"""The control socket: JSON lines over a Unix socket, mode 0660.

Request ``{"cmd": NAME, "args": {...}}``; reply ``{"ok": true, "result": ...}``
or ``{"ok": false, "error": "..."}``. A malformed request gets an error reply
and the connection stays usable; nothing a client sends stops the daemon.
"""
from __future__ import annotations

import asyncio
import json
import os
import socket
from pathlib import Path
from typing import Any, Awaitable, Callable

import structlog

log = structlog.get_logger("lathed.control")

Handler = Callable[[dict[str, Any]], Awaitable[Any]]
MAX_LINE = 1 << 20


class RequestError(Exception):
    """A request the daemon understood but cannot carry out; sent back as the error."""


class SocketInUse(Exception):
    """Another daemon answers on the control socket: it is not ours to replace."""


def _answers(path: Path) -> bool:
    """Whether a daemon accepts connections on ``path`` (else the socket is stale)."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(2.0)
        try:
            s.connect(str(path))
        except (ConnectionRefusedError, FileNotFoundError):
            return False
        except OSError:   # busy or unreadable: someone is there, leave it alone
            return True
        return True


class ControlServer:
    def __init__(self, path: Path):
        self.path = path
        self.handlers: dict[str, Handler] = {}
        self._server: asyncio.AbstractServer | None = None
        # (device, inode, ctime) of the socket we bound: a socket bound since may reuse the inode
        self._ident: tuple[int, int, int] | None = None

    def register(self, name: str, handler: Handler) -> None:
        if name in self.handlers:
            raise ValueError(f"control command {name!r} registered twice")
        self.handlers[name] = handler

    async def start(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.exists() or self.path.is_symlink():
            if _answers(self.path):
                raise SocketInUse(f"another daemon answers on {self.path}: not replacing its socket")
            self.path.unlink()   # a stale socket from a killed daemon
        old = os.umask(0o117)    # created 0660 from the start, no window of wider access
        try:
            self._server = await asyncio.start_unix_server(self._client, path=str(self.path), limit=MAX_LINE)
        finally:
            os.umask(old)
        os.chmod(self.path, 0o660)
        st = os.stat(self.path)
        self._ident = (st.st_dev, st.st_ino, st.st_ctime_ns)

    async def close(self) -> None:
        if self._server:
            self._server.close()
            await self._server.wait_closed()
        try:   # only our own socket: another daemon's, bound since, stays
            st = os.stat(self.path)
            if (st.st_dev, st.st_ino, st.st_ctime_ns) == self._ident:
                self.path.unlink()
        except FileNotFoundError:
            pass

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while True:
                try:
                    line = await reader.readline()
                except (asyncio.LimitOverrunError, ValueError):
                    await self._reply(writer, {"ok": False, "error": f"request longer than {MAX_LINE} bytes"})
                    break
                if not line:
                    break
                await self._reply(writer, await self._handle(line))
        except (ConnectionError, asyncio.IncompleteReadError):
            pass
        finally:
            writer.close()

    async def _reply(self, writer: asyncio.StreamWriter, obj: dict) -> None:
        writer.write(json.dumps(obj, default=_default).encode() + b"\n")
        await writer.drain()

    async def _handle(self, line: bytes) -> dict:
        try:
            req = json.loads(line)
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            return {"ok": False, "error": f"malformed request: not JSON ({e.msg if hasattr(e, 'msg') else e})"}
        if not isinstance(req, dict) or not isinstance(req.get("cmd"), str):
            return {"ok": False, "error": 'malformed request: expected {"cmd": NAME, "args": {...}}'}
        args = req.get("args", {})
        if not isinstance(args, dict):
            return {"ok": False, "error": "malformed request: args must be an object"}
        handler = self.handlers.get(req["cmd"])
        if handler is None:
            return {"ok": False, "error": f"unknown command {req['cmd']!r}; known: {', '.join(sorted(self.handlers))}"}
        try:
            return {"ok": True, "result": await handler(args)}
        except RequestError as e:
            return {"ok": False, "error": str(e)}
        except Exception as e:   # a handler bug is reported to the client and logged; the daemon goes on
            log.exception("control_handler_failed", cmd=req["cmd"])
            return {"ok": False, "error": f"internal error in {req['cmd']}: {type(e).__name__}: {e}"}


def _default(o: Any) -> Any:
    if hasattr(o, "tolist"):
        return o.tolist()
    return str(o)
