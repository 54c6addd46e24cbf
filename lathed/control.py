"""The control socket: JSON lines over a Unix socket, mode 0660.

Request ``{"cmd": NAME, "args": {...}}``; reply ``{"ok": true, "result": ...}``
or ``{"ok": false, "error": "..."}``. A malformed request gets an error reply
and the connection stays usable; nothing a client sends stops the daemon.
Handlers read their arguments through :class:`lathed.args.Args`.

Connections are bounded: at most ``max_clients`` at once (more get a one-line
refusal), a line of at most MAX_LINE bytes, closed after ``idle_timeout``
without a request, and a request line (or the reading of its reply) must
complete within ``request_timeout`` ([daemon] control_* keys).
"""
from __future__ import annotations

import asyncio
import json
import math
import os
import socket
import time
import weakref
from pathlib import Path
from typing import Any, Awaitable, Callable

import structlog

from lathed import caller
from lathed.request_error import ArgumentError, RequestError   # noqa: F401 (imported from here too)

log = structlog.get_logger("lathed.control")

Handler = Callable[[dict[str, Any]], Awaitable[Any]]
# One request line. Every command's arguments fit in a few hundred bytes; the
# StreamReader buffers up to this much per connection (x max_clients is the
# memory a crowd of slow clients can pin).
MAX_LINE = 64 << 10
# Arrays and objects in one request (counted as brackets, also inside strings):
# real requests have under ten; this bounds the JSON nesting depth before
# json.loads (which would recurse 32k deep on a line of '[').
MAX_CONTAINERS = 64
ACCEPT_LOG_EVERY_S = 10.0
HEAVY_AT_ONCE = 2     # O(records) requests run at once; the rest wait their turn
ENCODE_CHUNK = 500    # rows of a reply encoded per call: a few ms of the GIL each


class Stream:
    """A handler's result that keeps the connection (``subscribe``): ``first`` is
    sent as the reply, then :meth:`run` writes lines until it returns. It returns
    a reason when it gives the client up (a slow reader); the connection is then
    aborted, so nothing it did not read stays buffered in the daemon."""

    first: Any = None

    async def run(self, writer: asyncio.StreamWriter, write_timeout: float) -> str | None:
        raise NotImplementedError

    def close(self) -> None:
        """Called once the connection ends, however it ends."""


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


_heavy: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


async def offload(fn: Callable[..., Any], *args: Any) -> Any:
    """Run a request's O(records) work (queries, exports, analyses) in a worker thread, at most
    HEAVY_AT_ONCE at a time: off the event loop, and a crowd of exports cannot take every
    worker thread (the store and drivers use them too) nor hold a result's memory each."""
    loop = asyncio.get_running_loop()
    sem = _heavy.setdefault(loop, asyncio.Semaphore(HEAVY_AT_ONCE))
    async with sem:
        return await asyncio.to_thread(fn, *args)


class ControlServer:
    def __init__(self, path: Path, max_clients: int = 64, idle_timeout: float = 60.0,
                 request_timeout: float = 5.0, operator_groups: list[str] | None = None):
        self.path = path
        self.operator_groups = list(operator_groups or [])   # empty: whoever may connect may act
        self.handlers: dict[str, Handler] = {}
        self._server: asyncio.AbstractServer | None = None
        # (device, inode, ctime) of the socket we bound: a socket bound since may reuse the inode
        self._ident: tuple[int, int, int] | None = None
        self.max_clients = max_clients          # connections served at once; more are refused at once
        self.idle_timeout = idle_timeout        # a connection with no request for this long is closed
        self.request_timeout = request_timeout  # a request line must arrive, and its reply be read, within this
        self.clients = 0
        self.refused = 0
        self.evicted = 0
        # connections waiting for (the rest of) a request line -> since when (loop time)
        self._waiting: dict[asyncio.StreamWriter, float] = {}

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
        if self.clients >= self.max_clients:
            # a full house: the connection that has waited longest for a request line makes room
            # (a crowd of slow or idle clients must not lock out one that has a request), else
            # the newcomer is refused at once with a reason
            victim = min(self._waiting, key=self._waiting.__getitem__, default=None)
            if victim is None:
                self.refused += 1
                writer.write(_encode({"ok": False, "error": f"too many control connections (the daemon serves "
                                                            f"{self.max_clients} at once); try again"}))
                writer.close()
                return
            del self._waiting[victim]
            self.evicted += 1
            victim.transport.abort()
        self.clients += 1
        try:
            # who is on the other end, once per connection, from the kernel; this task's
            # context carries it into every handler and record of this connection
            caller.CALLER.set(caller.peer(writer.get_extra_info("socket"), self.operator_groups))
            while True:
                try:
                    # idle until a request starts; then the whole line within request_timeout
                    # (a client trickling a byte a second is cut, not served forever)
                    self._waiting[writer] = time.monotonic()
                    async with asyncio.timeout(self.idle_timeout):
                        first = await reader.read(1)
                    if not first:
                        break
                    async with asyncio.timeout(self.request_timeout):
                        line = first if first == b"\n" else first + await reader.readline()
                    self._waiting.pop(writer, None)
                except (asyncio.LimitOverrunError, ValueError):
                    await self._reply(writer, {"ok": False, "error": f"request line longer than {MAX_LINE} bytes; "
                                                                     "closing the connection"})
                    break
                except TimeoutError:
                    break
                reply = await self._handle(line)
                if isinstance(reply.get("result"), Stream):
                    await self._stream(reply["result"], reader, writer)
                    break
                await self._reply(writer, reply)
        except (ConnectionError, asyncio.IncompleteReadError, TimeoutError):
            pass
        except asyncio.CancelledError:
            # the daemon stops with this client connected (a subscriber: lathed-web, lathed-opcua).
            # The connection ends here; let through, Python 3.11's stream callback would log the
            # cancellation as an "Exception in callback" traceback (fixed in 3.12).
            pass
        finally:
            self._waiting.pop(writer, None)
            self.clients -= 1
            writer.close()

    async def _stream(self, stream: Stream, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """A subscribed connection: the first reply, then pushed lines until the client
        closes, sends anything (a subscribed connection takes no more requests), or is dropped."""
        try:
            await self._reply(writer, {"ok": True, "result": stream.first})
            pushing = asyncio.create_task(stream.run(writer, self.request_timeout))
            hangup = asyncio.create_task(reader.read(1))
            try:
                await asyncio.wait({pushing, hangup}, return_when=asyncio.FIRST_COMPLETED)
            finally:
                for t in (pushing, hangup):
                    t.cancel()
                await asyncio.gather(pushing, hangup, return_exceptions=True)
        finally:
            stream.close()
        reason = None if pushing.cancelled() or pushing.exception() else pushing.result()
        if hangup.done() and not hangup.cancelled() and not hangup.exception() and hangup.result():
            reason = "a subscribed connection takes no more requests; open another connection"
        if reason is not None:
            # one line saying why, if the client still reads; then abort: a client that does
            # not read must not keep its unread frames in our buffers
            writer.write(_encode({"ok": False, "error": f"subscription ended: {reason}"}))
            writer.transport.abort()

    async def _reply(self, writer: asyncio.StreamWriter, obj: dict) -> None:
        rows = obj.get("result")
        if isinstance(rows, list) and len(rows) > ENCODE_CHUNK:
            # an export of 100k rows is ~0.5 s of encoding: done in a worker, in chunks, so the
            # GIL passes back to the loop between them (one json.dumps call never yields it)
            data = await asyncio.to_thread(_encode_rows, rows)
        else:
            data = _encode(obj)
        writer.write(data)
        async with asyncio.timeout(self.request_timeout):   # a client that never reads its reply is cut
            await writer.drain()

    async def _handle(self, line: bytes) -> dict:
        """One request line to one reply; never raises."""
        if line.count(b"[") + line.count(b"{") > MAX_CONTAINERS:
            return {"ok": False, "error": f"malformed request: more than {MAX_CONTAINERS} JSON arrays/objects"}
        try:
            req = json.loads(line)
        except (ValueError, RecursionError) as e:   # JSONDecodeError, bad UTF-8, a >4300-digit integer
            return {"ok": False, "error": f"malformed request: not JSON ({getattr(e, 'msg', e)})"}
        if not isinstance(req, dict) or not isinstance(req.get("cmd"), str):
            return {"ok": False, "error": 'malformed request: expected {"cmd": NAME, "args": {...}}'}
        args = req.get("args", {})
        if not isinstance(args, dict):
            return {"ok": False, "error": "malformed request: args must be an object"}
        extra = sorted(set(req) - {"cmd", "args"})
        if extra:
            return {"ok": False, "error": f"malformed request: unknown key(s) {', '.join(map(repr, extra))[:200]}; "
                                          "a request has only cmd and args"}
        handler = self.handlers.get(req["cmd"])
        if handler is None:
            return {"ok": False, "error": f"unknown command {req['cmd'][:64]!r}; known: {', '.join(sorted(self.handlers))}"}
        try:
            return {"ok": True, "result": await handler(args)}
        except RequestError as e:
            return {"ok": False, "error": str(e), **({"usage": True} if isinstance(e, ArgumentError) else {})}
        except Exception as e:   # a handler bug is reported to the client and logged; the daemon goes on
            log.exception("control_handler_failed", cmd=req["cmd"])
            return {"ok": False, "error": f"internal error in {req['cmd']}: {type(e).__name__}: {e}"}


class AcceptErrorLog:
    """The loop's exception handler, quieter about one thing: out of file
    descriptors, asyncio reports every retry to accept (with a traceback);
    this logs one line per ``every_s`` with the count, and passes anything
    else to the default handler."""

    def __init__(self, every_s: float = ACCEPT_LOG_EVERY_S):
        self.every_s = every_s
        self.count = 0
        self._last = -math.inf

    def __call__(self, loop: asyncio.AbstractEventLoop, context: dict) -> None:
        if context.get("message") != "socket.accept() out of system resource":
            loop.default_exception_handler(context)
            return
        self.count += 1
        now = time.monotonic()
        if now - self._last >= self.every_s:
            self._last = now
            log.error("control_accept_failed", error=str(context.get("exception")), times=self.count,
                      why="out of file descriptors (raise LimitNOFILE, or find what holds them); "
                          "new clients wait in the backlog")
            self.count = 0


def _encode(obj: dict) -> bytes:
    return json.dumps(obj, default=_default).encode() + b"\n"


def _encode_rows(rows: list) -> bytes:
    """``{"ok": true, "result": rows}`` as _encode makes it, a chunk of rows per json.dumps call."""
    chunks = [json.dumps(rows[i:i + ENCODE_CHUNK], default=_default)[1:-1].encode()
              for i in range(0, len(rows), ENCODE_CHUNK)]
    return b'{"ok": true, "result": [' + b", ".join(chunks) + b"]}\n"


def _default(o: Any) -> Any:
    if hasattr(o, "tolist"):
        return o.tolist()
    return str(o)
