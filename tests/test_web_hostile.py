"""lathed-web against hostile clients (issue 35 cases 4, 5, 7, 8): a real lathed-web
process on loopback, with no daemon behind it unless a case needs one (test_web.py
has those). Different client addresses are different loopback addresses (127.0.0.x)."""
from __future__ import annotations

import base64
import http.client
import json
import re
import resource
import socket
import struct
import subprocess
import time
from pathlib import Path

import pytest

from lathed.web import accounts
from lathed.web.access import Hosts, Logins, Sessions, same_origin, split_host
from tests.conftest import BIN, free_port, wait_until


class Web:
    """A lathed-web process; its log in ``log``."""

    def __init__(self, tmp: Path, config: str = "", nofile: int | None = None, sock: Path | None = None):
        self.port = free_port()
        self.cfg = tmp / "web.toml"
        self.cfg.write_text(f"[web]\nport = {self.port}\nsocket = \"{sock or tmp / 'no-daemon.sock'}\"\n{config}")
        self.log = tmp / "web.log"

        def limit():
            if nofile:
                resource.setrlimit(resource.RLIMIT_NOFILE, (nofile, nofile))
        self.proc = subprocess.Popen([str(BIN / "lathed-web"), "--config", str(self.cfg)], stdout=open(self.log, "wb"),
                                     stderr=subprocess.STDOUT, preexec_fn=limit)
        wait_until(lambda: self.get("/api/health")[0] in (200, 401), timeout=20, what="lathed-web serving")

    def request(self, method: str, path: str, headers: dict | None = None, body: bytes | None = None,
                source: str = "127.0.0.1", timeout: float = 5.0) -> tuple[int, dict, str]:
        c = http.client.HTTPConnection("127.0.0.1", self.port, timeout=timeout, source_address=(source, 0))
        try:
            headers = {"Host": f"127.0.0.1:{self.port}", **(headers or {}),
                       **({"Content-Length": str(len(body))} if body is not None else {})}
            c.putrequest(method, path, skip_host=True, skip_accept_encoding=True)
            for k, v in headers.items():
                c.putheader(k, v)
            c.endheaders(body)
            r = c.getresponse()
            return r.status, dict(r.getheaders()), r.read(100_000).decode(errors="replace")
        finally:
            c.close()

    def get(self, path: str, **kw) -> tuple[int, dict, str]:
        try:
            return self.request("GET", path, **kw)
        except OSError:
            return 0, {}, ""

    def health(self, **kw) -> dict:
        return json.loads(self.get("/api/health", **kw)[2])

    def log_lines(self) -> list[str]:
        return self.log.read_text(errors="replace").splitlines()

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


@pytest.fixture
def web_factory(tmp_path):
    made: list[Web] = []

    def make(**kw) -> Web:
        w = Web(tmp_path, **kw)
        made.append(w)
        return w
    yield make
    for w in made:
        w.stop()


def _basic(user: str, pw: str) -> dict:
    return {"Authorization": "Basic " + base64.b64encode(f"{user}:{pw}".encode()).decode()}


# -- case 4: DNS rebinding, origins, tokens -------------------------------------------------

def test_hosts_are_this_views_names_only():
    h = Hosts("127.0.0.1", None, loopback_only=True)
    for ok in ("127.0.0.1:8780", "localhost:8780", "LOCALHOST", "[::1]:8780", "127.0.0.1"):
        assert h.allowed(ok), ok
    for bad in ("rebind.attacker.example:8780", "127.0.0.1.attacker.example", "", None, "localhost.evil:8780"):
        assert not h.allowed(bad), bad
    named = Hosts("0.0.0.0", ["cell7.plant.example", "10.1.2.3"], loopback_only=False)
    assert named.allowed("cell7.plant.example:8780") and named.allowed("10.1.2.3") and named.allowed("localhost")
    assert not named.allowed("cell8.plant.example")
    assert split_host("[::1]:8780") == ("::1", 8780) and split_host("Cell7.:80") == ("cell7", 80)


def test_origin_is_compared_with_an_allowed_host_and_its_port():
    assert same_origin("http://127.0.0.1:8780", "127.0.0.1:8780", False)
    assert same_origin("https://cell7.plant.example", "cell7.plant.example", True)      # a TLS proxy in front
    assert not same_origin("http://127.0.0.1:3000", "127.0.0.1:8780", False)          # another local site
    assert not same_origin("http://rebind.attacker.example:8780", "127.0.0.1:8780", False)
    assert not same_origin("null", "127.0.0.1:8780", False)
    assert not same_origin("http://127.0.0.1:notaport", "127.0.0.1:8780", False)


def test_each_login_has_its_own_token():
    s = Sessions()
    a, b = s.new("local"), s.new("local")
    assert s.token(a) != s.token(b)
    assert s.check(a, "local", s.token(a)) and not s.check(b, "local", s.token(a))
    assert not s.check(a, "olga", s.token(a))          # another user's session
    assert not s.check(None, "local", s.token(a)) and not s.check("forged", "local", s.token(a))
    t = [1e9]
    s = Sessions(clock=lambda: t[0])
    a = s.new("olga")
    forged = a.rsplit(".", 1)[0] + "." + "0" * 32
    assert s.get(a, "olga") == a and s.get(forged, "olga") is None and s.get(a, "ivan") is None
    t[0] += 24 * 3600 + 1                                  # a day on: a new login is needed
    assert s.get(a, "olga") is None and not s.check(a, "olga", s.token(a))


def test_a_page_of_another_name_gets_no_token_and_no_action(web_factory):
    """The DNS-rebinding case: a page at rebind.attacker.example, its name rebound to
    127.0.0.1, reads the view's page and posts an action with its own Host and Origin."""
    w = web_factory()
    evil = f"rebind.attacker.example:{w.port}"
    status, headers, body = w.get("/", headers={"Host": evil})
    assert status == 421 and "lathed_session" not in headers.get("Set-Cookie", "") and '"csrf"' not in body
    status, _, body = w.request("POST", "/api/suppress", headers={
        "Host": evil, "Origin": f"http://{evil}", "Content-Type": "application/json", "X-CSRF-Token": "0" * 64},
        body=b'{"action": "off"}')
    assert status == 421 and "does not answer to the name" in body
    # the view's own page: a session cookie and a token of its own on each login
    tokens = set()
    for _ in range(2):
        status, headers, body = w.get("/")
        assert status == 200 and "HttpOnly" in headers["Set-Cookie"] and "SameSite=Strict" in headers["Set-Cookie"]
        tokens.add(json.loads(re.search(r'<script id="meta" type="application/json">(.*?)</script>', body)[1])["csrf"])
    assert len(tokens) == 2


# -- case 5: slow headers, idle connections, the log ---------------------------------------

def _connections(port: int, n: int, first_bytes: bytes) -> list[socket.socket]:
    out = []
    for _ in range(n):
        s = socket.socket()
        s.setblocking(False)
        try:
            s.connect(("127.0.0.1", port))
        except BlockingIOError:
            pass
        out.append(s)
    if first_bytes:
        for s in out:
            try:
                s.send(first_bytes)
            except OSError:
                pass
    return out


def test_slow_and_idle_clients_beyond_the_file_limit_lock_no_one_out(web_factory):
    """Case 5: more slow-header and idle clients than the process has file descriptors.
    A fresh client is still served; the crowd is cut, counted, and logged a few times, not
    once per connection."""
    w = web_factory(config='idle_timeout = "2s"\n', nofile=256)
    idle = _connections(w.port, 300, b"")
    slow = _connections(w.port, 300, b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
    try:
        h = w.health()["connections"]
        assert h["max_connections"] <= 256 - 64          # fitted under the file limit it was given
        # the crowd's connections come in as the kernel lets them (their SYNs are retried)
        wait_until(lambda: w.health()["connections"]["evicted"] > 0, timeout=20, what="the cap reached")
        for _ in range(3):          # fresh clients, one after another, each answered
            status, _, body = w.get("/", timeout=5.0)
            assert status == 200 and "operator view" in body
        assert w.health()["connections"]["open"] <= h["max_connections"]
        # the ones left are closed once idle_timeout passes with no request in hand
        wait_until(lambda: w.health()["connections"]["idle_closed"] > 0, timeout=15, what="idle ones closed")
    finally:
        for s in idle + slow:
            s.close()
    lines = w.log_lines()
    assert not [ln for ln in lines if "Traceback" in ln or "out of system resource" in ln]
    assert len(lines) < 30, lines[:40]          # 600 connections: a few lines, with counts


# -- case 7: a crowd of live pages -----------------------------------------------------------

def _stream(port: int) -> tuple[socket.socket, bytes]:
    s = socket.create_connection(("127.0.0.1", port), timeout=5)
    s.sendall(f"GET /events HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode())
    buf = b""
    while b"\r\n\r\n" not in buf or (buf.startswith(b"HTTP/1.1 200") and b"data: " not in buf):
        chunk = s.recv(65536)
        if not chunk:
            break
        buf += chunk
    return s, buf


def test_live_pages_beyond_the_cap_are_refused_with_a_reason(web_factory):
    w = web_factory(config="max_live_pages = 3\n")
    pages = [_stream(w.port) for _ in range(3)]
    try:
        assert all(b.startswith(b"HTTP/1.1 200") and b"data: {" in b for _, b in pages)
        s, b = _stream(w.port)
        s.close()
        assert b.startswith(b"HTTP/1.1 503") and b"Retry-After: 10" in b
        assert b"too many live pages: 3 are open" in b
        assert w.health()["live"] == {"pages": 3, "max_pages": 3, "refused": 1, "fell_behind": 0,
                                      "cut_not_reading": 0}
        # a page that goes leaves its place, and no traceback
        for s, _ in pages[:2]:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))   # reset, as a killed tab
            s.close()
        wait_until(lambda: _stream(w.port)[1].startswith(b"HTTP/1.1 200"), timeout=20, what="a place again")
    finally:
        for s, _ in pages:
            s.close()
    assert not [ln for ln in w.log_lines() if "Traceback" in ln or "Error handling request" in ln]


def test_new_pages_between_two_frames_share_one_snapshot(tmp_path):
    """3,500 pages each got their own encoding of the snapshot (history of every value): the
    snapshot is encoded once per frame for all the pages that come meanwhile."""
    from lathed.web.live import BrowserLink
    link = BrowserLink(tmp_path / "none.sock", 4.0)
    made = []
    snap = link.snapshot
    link.snapshot = lambda: made.append(1) or snap()
    events = {link.snapshot_event() for _ in range(50)}
    assert len(made) == 1 and len(events) == 1
    link._merge({"samples": {"lathe/spindle_rpm": [1.0, 1500.0, "r/min"]}})
    link.frames += 1
    link.broadcast({"type": "frame"})
    assert b"1500" in link.snapshot_event() and len(made) == 2


# -- case 8: password guessing ---------------------------------------------------------------

def test_logins_back_off_per_client_and_per_account():
    t = [1000.0]
    lg = Logins(free=5, client_max_s=300, account_free=20, account_max_s=60, clock=lambda: t[0])
    for _ in range(5):
        assert lg.wait("10.0.0.9", "olga") == 0
        lg.failed("10.0.0.9", "olga")
    assert lg.wait("10.0.0.9", "olga") == 0          # five free tries
    lg.failed("10.0.0.9", "olga")
    assert lg.wait("10.0.0.9", "olga") == 5.0
    lg.failed("10.0.0.9", "olga")
    assert lg.wait("10.0.0.9", "olga") == 10.0       # doubling
    assert lg.wait("10.0.0.8", "olga") == 0          # another client is not this one
    # many addresses at one account: the account backs off, except where it logged in lately
    lg.succeeded("10.0.0.1", "olga")
    for i in range(20):
        lg.failed(f"10.0.1.{i}", "olga")
    assert lg.wait("10.0.2.1", "olga") > 0 and lg.wait("10.0.0.1", "olga") == 0
    t[0] += 901                                       # a quiet quarter of an hour forgets
    assert lg.wait("10.0.0.9", "olga") == 0 and lg.wait("10.0.2.1", "olga") == 0


def test_guessing_passwords_backs_off_and_is_logged(web_factory):
    users = "".join(f'[users.{u}]\nrole = "operator"\npassword = "{accounts.hash_password(u + "-pw")}"\n'
                    for u in ("olga", "ivan"))
    w = web_factory(config=users)
    assert w.get("/", headers=_basic("olga", "olga-pw"))[0] == 200          # olga, before any guessing
    answers = [w.get("/", headers=_basic("ivan", f"guess{i}"), source="127.0.0.2")[0] for i in range(10)]
    assert answers[:6] == [401] * 6 and set(answers[6:]) == {429}, answers
    status, headers, body = w.get("/", headers=_basic("ivan", "ivan-pw"), source="127.0.0.2")
    assert status == 429 and int(headers["Retry-After"]) >= 1 and "too many failed logins" in body
    # the guesser's back-off is its own: ivan from elsewhere, olga from here, are let in
    assert w.get("/", headers=_basic("ivan", "ivan-pw"), source="127.0.0.3")[0] == 200
    assert w.get("/", headers=_basic("olga", "olga-pw"))[0] == 200
    # an unknown name is a failure of its client too, and takes as long to refuse
    assert w.get("/", headers=_basic("nobody", "x"), source="127.0.0.4")[0] == 401
    failed = [json.loads(ln) for ln in w.log_lines() if '"login_failed"' in ln]
    assert failed and failed[0]["client"] == "127.0.0.2" and failed[0]["user"] == "ivan"
    assert len(failed) < 7                                                     # rate-limited, with counts
    assert any(f["client"] == "127.0.0.4" and f["known_user"] is False for f in failed)
    assert w.health(headers=_basic("olga", "olga-pw"))["logins"]["failed"] == 7


class _Transport:
    def __init__(self, peer: str):
        self.peer, self.sent, self.closed = peer, b"", None

    def get_extra_info(self, name):
        return (self.peer, 40000) if name == "peername" else None

    def write(self, data):
        self.sent += data

    def close(self):
        self.closed = "close"

    def abort(self):
        self.closed = "abort"


def test_the_gate_evicts_the_longest_waiting_never_a_request_in_hand():
    from lathed.gate import Gate
    t = [0.0]
    g = Gate(factory=None, max_connections=3, per_client=2, idle_timeout=10.0, clock=lambda: t[0])

    def connect(peer):
        c = g()
        tr = _Transport(peer)
        c.connection_made(tr)
        t[0] += 1
        return c, tr
    (a, ta), (b, tb), (c, tc) = connect("127.0.0.1"), connect("127.0.0.1"), connect("127.0.0.1")
    g.busy(ta)                                   # a has a request in hand (a live page)
    d, td = connect("127.0.0.1")                 # over the cap: b, the longest waiting, makes room
    assert tb.closed == "abort" and ta.closed is None and d.admitted and g.counts()["evicted"] == 1
    g.busy(tc)
    g.busy(td)
    e, te = connect("127.0.0.1")                 # every one busy: the newcomer is refused, saying why
    assert not e.admitted and te.closed == "close" and te.sent.startswith(b"HTTP/1.1 503")
    assert b"too many connections (3 at once, all busy)" in te.sent
    # one remote address: its own oldest waiting connection makes room, then it is refused
    g2 = Gate(factory=None, max_connections=100, per_client=2, idle_timeout=10.0, clock=lambda: t[0])
    g = g2
    (r1, tr1), (r2, tr2) = connect("10.9.9.9"), connect("10.9.9.9")
    r3, tr3 = connect("10.9.9.9")
    assert tr1.closed == "abort" and r3.admitted
    g.busy(tr2)
    g.busy(tr3)
    r4, tr4 = connect("10.9.9.9")
    assert not r4.admitted and b"too many connections from 10.9.9.9 (2 at once)" in tr4.sent
    assert connect("10.9.9.8")[0].admitted      # another address is not held back
