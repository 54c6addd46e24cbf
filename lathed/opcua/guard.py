"""lathed-opcua's limits, so that one client cannot take the server from the others (issue 35;
the values and their config keys: docs/opcua.md).

Connections: at most ``max_connections``; a new one past the cap closes the oldest that has no
session yet, a silent one first (a client that holds sockets open without talking cannot lock
the next one out);
a connection that sends no Hello within ``hello_timeout`` is closed, one without an activated
session within ``activation_timeout`` too. Sessions: at most ``max_subscriptions_per_session``
subscriptions and ``max_monitored_items_per_session`` monitored items (and the server at most
``max_monitored_items``), no publishing or sampling interval below ``min_publishing_interval``,
queues of at most MAX_QUEUE values, a session kept at most SESSION_TIMEOUT_MS after its client
went. The log: each kind of line at most LOG_BURST times a LOG_WINDOW_S, then counted.
"""
from __future__ import annotations

import asyncio
import logging
import socket
import time
from dataclasses import dataclass

import structlog
from asyncua import Server, ua
from asyncua.common import utils
from asyncua.server.binary_server_asyncio import BinaryServer, OPCUAProtocol
from asyncua.server.internal_session import InternalSession

log = structlog.get_logger("lathed.opcua")
MAX_QUEUE = 100                # values a monitored item holds between publishes
SESSION_TIMEOUT_MS = 60_000    # a session outlives its connection at most this long
MAX_LIFETIME_COUNT = 600       # publishing intervals a subscription lives without a publish request
LOG_BURST, LOG_WINDOW_S = 5, 10.0


@dataclass
class Limits:
    max_connections: int = 64
    hello_timeout_s: float = 5.0
    activation_timeout_s: float = 10.0
    max_subscriptions_per_session: int = 10
    max_monitored_items_per_session: int = 500
    max_monitored_items: int = 5000
    min_publishing_interval_ms: float = 50.0


class GuardedServer(Server):
    """asyncua's server with the connection limits (its TCP protocol replaced) and the session
    limits (its subscription service wrapped)."""

    def __init__(self, limits: Limits, **kw):
        super().__init__(**kw)
        self.guard_limits = limits
        self.connections: list[GuardedProtocol] = []
        self.counts: dict[str, int] = {}

    async def init(self, shelf_file=None) -> None:
        await super().init(shelf_file)
        lim, isrv = self.guard_limits, self.iserver
        isrv.max_connections = 10 * lim.max_connections      # ours decides: an evicted one counts until it is gone
        isrv.max_pending_activation_seconds = lim.activation_timeout_s
        isrv.max_session_timeout_ms = SESSION_TIMEOUT_MS
        isrv.max_lifetime_count = MAX_LIFETIME_COUNT
        isrv.max_monitored_item_queue_size = MAX_QUEUE
        isrv.max_subscriptions = lim.max_subscriptions_per_session * lim.max_connections
        InternalSession.max_connections = lim.max_connections   # activated sessions at once
        SessionLimits(self, lim)

    async def start(self) -> None:
        # asyncua's Server.start, with our connections (asyncua names its BinaryServer class here)
        if self.iserver.certificate is not None:
            from asyncua.crypto import uacrypto
            import socket as _socket
            uacrypto.check_certificate(self.iserver.certificate, self._application_uri, _socket.gethostname())
        await self._setup_server_nodes()
        await self.iserver.start()
        try:
            host, port = self._get_bind_socket_info()
            self.bserver = GuardedBinaryServer(self, self.iserver, host, port, self.limits)
            self.bserver.set_policies(self._policies)
            await self.bserver.start()
        except Exception:
            await self.iserver.stop()
            raise

    def count(self, what: str) -> None:
        self.counts[what] = self.counts.get(what, 0) + 1

    def admit(self, proto: GuardedProtocol) -> bool:
        """Room for a new connection: at the cap the oldest one without a session (a silent one
        before one that said Hello) gives way."""
        if len(self.connections) >= self.guard_limits.max_connections:
            idle = [p for p in self.connections if not p.in_session()]
            if not idle:
                self.count("refused")
                log.warning("connection_refused", peer=str(proto.peer_name), open=len(self.connections),
                            why="every connection has a session")
                return False
            # a silent one first: a client that said Hello is mid-handshake (four round trips)
            oldest = min(idle, key=lambda p: (p.talking, p.opened))
            self.connections.remove(oldest)
            self.count("evicted")
            log.warning("connection_closed", peer=str(oldest.peer_name), why="the connection cap: the oldest "
                        "without a session gives way", max_connections=self.guard_limits.max_connections)
            oldest.close()
        self.connections.append(proto)
        return True

    def forget(self, proto: GuardedProtocol) -> None:
        if proto in self.connections:
            self.connections.remove(proto)


class GuardedBinaryServer(BinaryServer):
    def __init__(self, owner: GuardedServer, *args):
        super().__init__(*args)
        self.owner = owner

    def _make_protocol(self) -> OPCUAProtocol:
        return GuardedProtocol(self.owner, iserver=self.iserver, policies=self._policies, clients=self.clients,
                               closing_tasks=self.closing_tasks, limits=self.limits)


class GuardedProtocol(OPCUAProtocol):
    def __init__(self, owner: GuardedServer, **kw):
        super().__init__(**kw)
        self.owner = owner
        self.opened = time.monotonic()
        self.greeted = False        # a whole Hello processed
        self.talking = False        # bytes came: a client mid-handshake, not a silent socket
        self._hello_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport) -> None:
        self.peer_name = transport.get_extra_info("peername")
        # a loaded loop accepts connections in batches, before reading any: a client whose Hello
        # already waits in the socket is talking, not one of a flood's silent sockets
        self.talking = _waiting(transport.get_extra_info("socket"))
        if not self.owner.admit(self):
            transport.close()
            return
        super().connection_made(transport)
        self._hello_timer = asyncio.get_running_loop().call_later(self.owner.guard_limits.hello_timeout_s,
                                                                   self._no_hello)

    def _no_hello(self) -> None:
        if not self.greeted and self.transport is not None:
            self.owner.count("no_hello")
            log.warning("connection_closed", peer=str(self.peer_name),
                        why=f"no Hello within {self.owner.guard_limits.hello_timeout_s:g} s")
            self.close()

    def in_session(self) -> bool:
        session = self.processor.session if self.processor is not None else None
        return session is not None and session.is_activated()

    def close(self) -> None:
        self.owner.forget(self)
        if self.transport is not None:
            self.transport.close()

    def data_received(self, data: bytes) -> None:
        self.talking = True          # at once, before the message is queued and processed
        super().data_received(data)

    async def _process_one_msg(self, header, buf) -> bool:
        if header.MessageType == ua.MessageType.Hello and not self.greeted:
            self.greeted = True
            if self._hello_timer is not None:
                self._hello_timer.cancel()
        return await super()._process_one_msg(header, buf)

    def connection_lost(self, ex) -> None:
        self.owner.forget(self)
        if self._hello_timer is not None:
            self._hello_timer.cancel()
        super().connection_lost(ex)


def _waiting(tsock) -> bool:
    """Bytes wait unread on the connection (peeked through a duplicate: asyncio's socket lends no recv)."""
    if tsock is None:
        return False
    try:
        with socket.fromfd(tsock.fileno(), tsock.family, tsock.type) as dup:
            return bool(dup.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT))
    except OSError:               # nothing there yet, or gone
        return False


class SessionLimits:
    """asyncua's subscription service, with each session's subscriptions and monitored items
    counted and capped, and the intervals and queues held within bounds."""

    def __init__(self, server: GuardedServer, limits: Limits):
        self.server, self.limits = server, limits
        self.svc = svc = server.iserver.subscription_service
        self._create_subscription, self._create_items = svc.create_subscription, svc.create_monitored_items
        self._modify_items = svc.modify_monitored_items
        svc.create_subscription = self.create_subscription
        svc.create_monitored_items = self.create_monitored_items
        svc.modify_monitored_items = self.modify_monitored_items

    def _items(self, subs) -> int:
        return sum(len(s.monitored_item_srv._monitored_items) for s in subs)

    async def create_subscription(self, params, callback, session_id, request_callback=None):
        mine = sum(1 for s in self.svc.subscriptions.values() if s.session_id == session_id)
        if mine >= self.limits.max_subscriptions_per_session:
            self.server.count("subscriptions_refused")
            log.warning("subscription_refused", session=str(session_id),
                        why=f"{mine} subscriptions already: max_subscriptions_per_session")
            raise utils.ServiceError(ua.StatusCodes.BadTooManySubscriptions)
        params.RequestedPublishingInterval = max(params.RequestedPublishingInterval or 0.0,
                                                 self.limits.min_publishing_interval_ms)
        return await self._create_subscription(params, callback, session_id, request_callback)

    async def create_monitored_items(self, params: ua.CreateMonitoredItemsParameters):
        sub = self.svc.subscriptions.get(params.SubscriptionId)
        if sub is None:
            return await self._create_items(params)    # asyncua's own refusal
        mine = self._items(s for s in self.svc.subscriptions.values() if s.session_id == sub.session_id)
        room = min(self.limits.max_monitored_items_per_session - mine,
                   self.limits.max_monitored_items - self._items(self.svc.subscriptions.values()))
        room = max(room, 0)
        items = list(params.ItemsToCreate)
        for item in items:
            self._bound(item.RequestedParameters)
        refused = len(items) - room
        if refused > 0:
            self.server.count("monitored_items_refused")
            log.warning("monitored_items_refused", session=str(sub.session_id), refused=refused,
                        why="max_monitored_items_per_session" if mine + room >= self.limits.max_monitored_items_per_session
                        else "max_monitored_items (the server's)")
        params.ItemsToCreate = items[:room]
        results = await self._create_items(params) if room else []
        return results + [ua.MonitoredItemCreateResult(StatusCode=ua.StatusCode(ua.StatusCodes.BadTooManyMonitoredItems))
                          for _ in range(max(refused, 0))]

    def modify_monitored_items(self, params: ua.ModifyMonitoredItemsParameters):
        for item in params.ItemsToModify:
            self._bound(item.RequestedParameters)
        return self._modify_items(params)

    def _bound(self, p: ua.MonitoringParameters) -> None:
        if p.SamplingInterval >= 0:      # -1: the publishing interval's, already bounded
            p.SamplingInterval = max(p.SamplingInterval, self.limits.min_publishing_interval_ms)
        p.QueueSize = min(p.QueueSize, MAX_QUEUE) if p.QueueSize else MAX_QUEUE


class LogLimit(logging.Filter):
    """At most LOG_BURST lines of each kind (logger and message) a LOG_WINDOW_S; the rest counted
    and said in one line when the window closes (``flush``, called every window)."""

    def __init__(self, clock=time.monotonic):
        super().__init__()
        self.clock = clock
        self.windows: dict[tuple[str, str], list] = {}     # kind -> [window start, lines, suppressed]

    @staticmethod
    def kind(record: logging.LogRecord) -> tuple[str, str]:
        msg = record.msg
        if isinstance(msg, dict):          # structlog's event
            return record.name, str(msg.get("event"))
        return record.name, str(msg)[:200]

    def filter(self, record: logging.LogRecord) -> bool:
        if getattr(record, "lathed_summary", False):
            return True
        now = self.clock()
        k = self.kind(record)
        w = self.windows.get(k)
        if w is None or now - w[0] >= LOG_WINDOW_S:
            if w is not None and w[2]:
                self._say(k, w)
            w = self.windows[k] = [now, 0, 0]
        w[1] += 1
        if w[1] <= LOG_BURST:
            return True
        w[2] += 1
        return False

    def flush(self) -> None:
        now = self.clock()
        for k, w in list(self.windows.items()):
            if now - w[0] >= LOG_WINDOW_S:
                if w[2]:
                    self._say(k, w)
                del self.windows[k]

    def _say(self, k: tuple[str, str], w: list) -> None:
        logging.getLogger("lathed.opcua").warning(
            "log_suppressed: %d more lines like %r from %s in %.0f s", w[2], k[1][:120], k[0], LOG_WINDOW_S,
            extra={"lathed_summary": True})
        w[2] = 0


async def flush_logs(limit: LogLimit) -> None:
    while True:
        await asyncio.sleep(LOG_WINDOW_S)
        limit.flush()
