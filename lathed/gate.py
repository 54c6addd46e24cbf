"""Connection limits for the TCP servers of the side processes (lathed-web).

The daemon's control socket caps its clients and cuts one that trickles a
request (lathed.control); a side process on TCP needs the same, or 4,000
clients that never finish a request hold every file descriptor (issue 35).
``Gate`` wraps the server's protocol factory:

* at most ``max_connections`` at once: a newcomer over the cap makes room by
  closing the connection that has waited longest without a request in hand
  (a crowd of slow or idle clients never locks out one that has a request);
  when every connection is busy, the newcomer gets "503 too many connections";
* at most ``per_client`` from one remote address (loopback is this PC, and a
  TLS proxy in front: only the total applies), the same way within it;
* a connection with no request in hand for ``idle_timeout`` seconds (the first
  request's headers trickled a byte a second, or an idle keep-alive) is closed.

A request is "in hand" from when the application starts it (``busy``) to its
end (``done``): the owner's middleware says so. Refusals and closes are counted
(``counts()``), and logged at most once per period per kind (lathed.lograte).
"""
from __future__ import annotations

import asyncio
import ipaddress
import resource
import time
from typing import Any, Callable

import structlog

from lathed.lograte import Limited

log = structlog.get_logger("lathed.gate")
FD_RESERVE = 64        # descriptors kept for the rest of the process (the daemon link, files, logs)
BACKLOG = 128          # the listen backlog, at most
# asyncio accepts up to the backlog at each turn of its loop, and a descriptor an eviction
# frees is closed a few turns later: this many backlogs of descriptors are kept free
IN_FLIGHT = 4


def _loopback(host: str | None) -> bool:
    try:
        return host is not None and ipaddress.ip_address(host.split("%")[0]).is_loopback
    except ValueError:
        return False


def fit_to_fd_limit(wanted: int | None) -> tuple[int, int]:
    """(connection cap, listen backlog) the file-descriptor limit allows; ``wanted`` None:
    as many as it allows. Descriptors accepted but not yet admitted or closed are kept free
    (IN_FLIGHT backlogs), and the backlog is a fifth of the cap at most (a fresh client
    accepted in a burst is read before the burst could evict it).
    For a cap that is asked for, the soft limit is raised toward the hard one if it must;
    what does not fit is said, and the cap lowered."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if wanted is not None:
        need = wanted + FD_RESERVE + IN_FLIGHT * min(BACKLOG, wanted // 5)
        if soft != resource.RLIM_INFINITY and soft < need:
            new = need if hard == resource.RLIM_INFINITY else min(need, hard)
            try:
                resource.setrlimit(resource.RLIMIT_NOFILE, (new, hard))
                soft = new
            except (ValueError, OSError):
                pass
        if soft == resource.RLIM_INFINITY or soft >= need:
            return wanted, min(BACKLOG, wanted // 5)
    room = max(16, (1 << 16 if soft == resource.RLIM_INFINITY else soft) - FD_RESERVE)
    backlog = max(4, min(BACKLOG, room // (5 + IN_FLIGHT)))
    if wanted is not None:
        log.warning("connection_cap_lowered", wanted=wanted, cap=room - IN_FLIGHT * backlog, open_files_limit=soft,
                    why="the open-files limit (LimitNOFILE) leaves no room for more")
    return room - IN_FLIGHT * backlog, backlog


class Gated(asyncio.Protocol):
    """One connection: the inner protocol (aiohttp's) behind the gate's bookkeeping. The inner
    one is made at the first byte: a connection that never sends one costs only this."""

    def __init__(self, gate: "Gate"):
        self.gate = gate
        self.inner: asyncio.Protocol | None = None
        self.transport: asyncio.Transport | None = None
        self.client: str | None = None
        self.busy = 0
        self.admitted = False    # refused ones never reach an inner protocol

    # what asyncio calls, handed on
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport   # type: ignore[assignment]
        peer = transport.get_extra_info("peername")
        self.client = peer[0] if isinstance(peer, tuple) else None
        self.admitted = self.gate.admit(self)

    def connection_lost(self, exc: Exception | None) -> None:
        self.gate.forget(self)
        self.admitted = False
        if self.inner is not None:
            inner, self.inner = self.inner, None
            inner.connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        if not self.admitted:
            return
        if self.inner is None:
            assert self.gate.factory is not None, "Gate.factory is set before serving"
            self.inner = self.gate.factory()
            self.inner.connection_made(self.transport)
        self.inner.data_received(data)   # type: ignore[attr-defined]

    def eof_received(self) -> bool | None:
        return self.inner.eof_received() if self.inner is not None else None   # type: ignore[attr-defined]

    def pause_writing(self) -> None:
        if self.inner is not None:
            self.inner.pause_writing()

    def resume_writing(self) -> None:
        if self.inner is not None:
            self.inner.resume_writing()


class Gate:
    """The protocol factory to give ``loop.create_server``; ``factory`` makes the inner protocol."""

    def __init__(self, factory: Callable[[], asyncio.Protocol] | None = None, max_connections: int = 4000,
                 per_client: int = 64, idle_timeout: float = 10.0, name: str = "web",
                 clock: Callable[[], float] = time.monotonic):
        self.factory = factory
        self.max_connections, self.per_client, self.idle_timeout = max_connections, per_client, idle_timeout
        self.name, self.clock = name, clock
        self.open: set[Gated] = set()
        self.by_transport: dict[Any, Gated] = {}
        self.per: dict[str, int] = {}
        # connections with no request in hand -> since when; insertion order is that order
        self.waiting: dict[Gated, float] = {}
        self.accepted = self.refused = self.evicted = self.timed_out = 0
        self.lim = Limited(log)
        self._sweeper: asyncio.TimerHandle | None = None

    def __call__(self) -> Gated:
        return Gated(self)

    # -- admission --------------------------------------------------------------------
    def admit(self, c: Gated) -> bool:
        limited = not _loopback(c.client) and c.client is not None
        if limited and self.per.get(c.client, 0) >= self.per_client:
            if not self._evict(lambda v: v.client == c.client):
                return self._refuse(c, f"too many connections from {c.client} ({self.per_client} at once)")
        if len(self.open) >= self.max_connections and not self._evict(lambda v: True):
            return self._refuse(c, f"too many connections ({self.max_connections} at once, all busy)")
        self.accepted += 1
        self.open.add(c)
        self.by_transport[c.transport] = c
        if c.client is not None:
            self.per[c.client] = self.per.get(c.client, 0) + 1
        self.waiting[c] = self.clock()
        self._sweep_later()
        return True

    def _evict(self, which: Callable[[Gated], bool]) -> bool:
        victim = next((v for v in self.waiting if which(v)), None)   # the one waiting longest
        if victim is None:
            return False
        self.evicted += 1
        self.lim.warning("connection_evicted", server=self.name, client=victim.client, evicted=self.evicted,
                         why="a newcomer needed its place and it had no request in hand")
        self._close(victim)
        return True

    def _refuse(self, c: Gated, why: str) -> bool:
        self.refused += 1
        self.lim.warning("connection_refused", server=self.name, client=c.client, refused=self.refused, why=why)
        body = f"{why}; try again in a few seconds\n".encode()
        assert c.transport is not None
        c.transport.write(b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: text/plain; charset=utf-8\r\n"
                          b"Retry-After: 5\r\nConnection: close\r\nContent-Length: %d\r\n\r\n" % len(body) + body)
        c.transport.close()
        return False

    def _close(self, c: Gated) -> None:
        self.forget(c)          # its place is free now, not when asyncio reports the close
        if c.transport is not None:
            c.transport.abort()

    def forget(self, c: Gated) -> None:
        if c not in self.open:
            return
        self.open.discard(c)
        self.by_transport.pop(c.transport, None)
        self.waiting.pop(c, None)
        if c.client is not None:
            n = self.per.get(c.client, 1) - 1
            if n:
                self.per[c.client] = n
            else:
                self.per.pop(c.client, None)

    # -- what the application says --------------------------------------------------------
    def busy(self, transport: Any) -> None:
        c = self.by_transport.get(transport)
        if c is not None:
            c.busy += 1
            self.waiting.pop(c, None)

    def done(self, transport: Any) -> None:
        c = self.by_transport.get(transport)
        if c is not None:
            c.busy -= 1
            if c.busy <= 0 and c in self.open:
                c.busy = 0
                self.waiting[c] = self.clock()
                self._sweep_later()

    # -- the idle sweep ---------------------------------------------------------------------
    def _sweep_later(self) -> None:
        if self._sweeper is None:
            try:
                loop = asyncio.get_running_loop()
            except RuntimeError:
                return
            self._sweeper = loop.call_later(min(1.0, self.idle_timeout / 4), self._sweep)

    def _sweep(self) -> None:
        self._sweeper = None
        cutoff = self.clock() - self.idle_timeout
        while self.waiting:
            c, since = next(iter(self.waiting.items()))
            if since > cutoff:
                break
            self.timed_out += 1
            self.lim.info("connection_idle_closed", server=self.name, client=c.client, closed=self.timed_out,
                          why=f"no request in hand for {self.idle_timeout:g} s")
            self._close(c)
        if self.waiting:
            self._sweep_later()

    def counts(self) -> dict:
        return {"open": len(self.open), "waiting": len(self.waiting), "accepted": self.accepted,
                "refused": self.refused, "evicted": self.evicted, "idle_closed": self.timed_out,
                "max_connections": self.max_connections}
