"""Who may use the operator view, and from which page: the checks before any handler.

* ``Hosts``: the Host header must name this view (loopback names, the listen
  address, ``[web] allowed_hosts``). A page whose DNS name was rebound to
  127.0.0.1 sends its own name and is refused, so it never reads a token.
* ``same_origin``: an action's Origin must be this view as the (allow-listed)
  Host names it: never compared with a Host an attacker chose.
* ``Sessions``: each login (a page load without a live session cookie) gets a
  session and a CSRF token of its own; an action needs both, for the same user.
  Sessions are signed cookies, not a table a flood could fill.
* ``Logins``: failed passwords back off per client address and per account,
  and are logged (rate-limited, with counts).

docs/web.md has the settings.
"""
from __future__ import annotations

import asyncio
import hashlib
import hmac
import secrets
import socket
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Callable
from urllib.parse import urlsplit

LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")
SESSION_S = 24 * 3600         # a session's life; the next page load after it makes another
COOKIE = "lathed_session"
BACKOFF_FIRST_S = 5.0         # the wait after the free tries; each further failure doubles it
TRUSTED_S = 24 * 3600.0       # an address that logged in to an account within this is spared its back-off


def split_host(value: str) -> tuple[str, int | None]:
    """("name", port) of a Host header or an origin's netloc; the name lower-case, IPv6 without brackets."""
    value = value.strip().lower()
    if value.startswith("["):
        name, _, rest = value[1:].partition("]")
        port = rest[1:] if rest.startswith(":") else ""
    elif value.count(":") == 1:
        name, _, port = value.partition(":")
    else:                       # a bare IPv6 address, or no port
        name, port = value, ""
    try:
        return name.rstrip("."), (int(port) if port else None)
    except ValueError:
        return name.rstrip("."), -1


class Hosts:
    """The names this view answers to."""

    def __init__(self, listen: str, configured: list[str] | None, loopback_only: bool):
        names = set(LOOPBACK_NAMES)
        if listen not in ("0.0.0.0", "::", ""):
            names.add(listen.lower())
        if configured:
            names |= {split_host(h)[0] for h in configured}
        elif not loopback_only:   # reached from the network: this PC's own names by default
            names |= {socket.gethostname().lower(), socket.getfqdn().lower()}
        self.names = frozenset(n for n in names if n)

    def allowed(self, host: str | None) -> bool:
        return host is not None and split_host(host)[0] in self.names


def same_origin(origin: str, host: str, secure: bool) -> bool:
    """Whether ``origin`` (the Origin header) is this view as the Host header names it.
    The Host has passed ``Hosts.allowed`` first: it is a name of ours, not the attacker's."""
    try:
        o = urlsplit(origin)
        o_port = o.port
    except ValueError:
        return False
    if o.scheme not in ("http", "https") or not o.hostname:
        return False
    default = 443 if o.scheme == "https" else 80
    h_name, h_port = split_host(host)
    return (split_host(o.netloc)[0] == h_name
            and (o_port or default) == (h_port or (443 if secure else 80)))


class Sessions:
    """A session is a signed cookie value, ``issued.random.signature`` (the signature over the
    user, the time and the random part), so no table is kept that a flood of page loads could
    fill or evict; the CSRF token is an HMAC of the whole value. A session lasts SESSION_S."""

    def __init__(self, clock: Callable[[], float] = time.time):
        self.secret = secrets.token_bytes(32)
        self.clock = clock
        self.issued = 0

    def _sign(self, user: str, body: str) -> str:
        return hmac.new(self.secret, f"{user}\0{body}".encode(), hashlib.sha256).hexdigest()[:32]

    def token(self, sid: str) -> str:
        return hmac.new(self.secret, b"csrf\0" + sid.encode(), hashlib.sha256).hexdigest()

    def get(self, sid: str | None, user: str) -> str | None:
        """``sid`` if it is a live session of ``user`` made here, else None."""
        if not sid or sid.count(".") != 2:
            return None
        issued, rand, sig = sid.split(".")
        if not hmac.compare_digest(sig, self._sign(user, f"{issued}.{rand}")):
            return None
        try:
            age = self.clock() - int(issued)
        except ValueError:
            return None
        return sid if 0 <= age <= SESSION_S else None

    def new(self, user: str) -> str:
        self.issued += 1
        body = f"{int(self.clock())}.{secrets.token_urlsafe(16)}"
        return f"{body}.{self._sign(user, body)}"

    def check(self, sid: str | None, user: str, token: str) -> bool:
        """An action's cookie and X-CSRF-Token: the same user's live session and its token."""
        live = self.get(sid, user)
        return live is not None and hmac.compare_digest(token, self.token(live))


@dataclass
class Failures:
    count: int = 0
    last_t: float = 0.0
    until: float = 0.0       # no password of this client/account is checked before this


class Logins:
    """Back-off on failed passwords. Per client address: after ``free`` failures each
    further one doubles its wait (5 s, 10 s, ... up to ``client_max_s``). Per account,
    whichever address guesses: after ``account_free`` failures the same, up to
    ``account_max_s``, except for an address that logged in to it lately (its owner
    is not locked out by someone else's guessing). A quiet ``forget_s`` clears a count."""

    def __init__(self, free: int = 5, client_max_s: float = 300.0, account_free: int = 20,
                 account_max_s: float = 60.0, forget_s: float = 900.0, kept: int = 10_000,
                 clock: Callable[[], float] = time.monotonic):
        self.free, self.client_max_s = free, client_max_s
        self.account_free, self.account_max_s = account_free, account_max_s
        self.forget_s, self.kept, self.clock = forget_s, kept, clock
        self.clients: OrderedDict[str, Failures] = OrderedDict()
        self.accounts: dict[str, Failures] = {}
        self.trusted: OrderedDict[tuple[str, str], float] = OrderedDict()   # (client, account) -> last login
        self.locks: dict[str, asyncio.Lock] = {}
        self.failed_total = self.refused_total = 0

    def lock(self, client: str) -> asyncio.Lock:
        """One password check at a time per client: a burst of parallel guesses waits its turn."""
        lk = self.locks.get(client)
        if lk is None:
            if len(self.locks) > self.kept:
                for k in [k for k, v in self.locks.items() if not v.locked()]:
                    del self.locks[k]
            lk = self.locks[client] = asyncio.Lock()
        return lk

    def _live(self, table: dict, key: str) -> Failures | None:
        f = table.get(key)
        if f is not None and self.clock() - f.last_t > self.forget_s:
            del table[key]
            return None
        return f

    def wait(self, client: str, account: str | None) -> float:
        """Seconds before a password from ``client`` for ``account`` may be checked (0: now)."""
        now = self.clock()
        waits = [0.0]
        if (f := self._live(self.clients, client)) is not None:
            waits.append(f.until - now)
        if account is not None and (a := self._live(self.accounts, account)) is not None \
                and now - self.trusted.get((client, account), -TRUSTED_S) > TRUSTED_S:
            waits.append(a.until - now)
        w = max(waits)
        if w > 0:
            self.refused_total += 1
        return max(0.0, w)

    def failed(self, client: str, account: str | None) -> Failures:
        now = self.clock()
        self.failed_total += 1
        f = self._bump(self.clients, client, now, self.free, self.client_max_s)
        self.clients.move_to_end(client)
        while len(self.clients) > self.kept:
            self.clients.popitem(last=False)
        if account is not None:
            self._bump(self.accounts, account, now, self.account_free, self.account_max_s)
        return f

    def _bump(self, table: dict, key: str, now: float, free: int, most: float) -> Failures:
        f = table.get(key)
        if f is None or now - f.last_t > self.forget_s:
            f = table[key] = Failures()
        f.count += 1
        f.last_t = now
        if f.count > free:
            f.until = now + min(most, BACKOFF_FIRST_S * 2.0 ** (f.count - free - 1))
        return f

    def succeeded(self, client: str, account: str) -> None:
        self.clients.pop(client, None)
        self.trusted[(client, account)] = self.clock()
        self.trusted.move_to_end((client, account))
        while len(self.trusted) > self.kept:
            self.trusted.popitem(last=False)
