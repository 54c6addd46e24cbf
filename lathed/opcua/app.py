"""lathed-opcua: the line as an OPC UA server (OPC 40501 Machine Tools layout, lathed.opcua.space).

A process of its own beside the daemon, which keeps no network listener: one subscription
to the daemon's control socket (lathed.push, as lathed-web) feeds every OPC UA client, and
the one write it offers (a machine's suppression mode, only with ``[opcua] writable = true``)
is the daemon's own ``suppress`` command, sent with the OPC UA user's name, so it passes the
daemon's checks and the event log says who.

Access: on a loopback address anonymous clients may read, without security (and users may log
in, their passwords encrypted with the server's certificate). On any other address only
Basic256Sha256 SignAndEncrypt and user accounts ([users.NAME], lathed-web's format and roles):
no anonymous access, nothing in clear. The certificate is self-signed, made on first start
in the state directory (key 0600). Any client application certificate opens a secure channel
unless ``trusted_clients`` names a directory of the ones to accept; the user's account is
checked either way. A write needs the operator role.
"""
from __future__ import annotations

import asyncio
import hashlib
import logging
import os
import signal
import socket
import stat
import sys
import time
import tomllib
from collections import deque
from pathlib import Path

import structlog
from asyncua import Server, ua
from asyncua.crypto.cert_gen import dump_private_key_as_pem, generate_private_key, setup_self_signed_certificate
from asyncua.crypto.permission_rules import User, UserRole
from asyncua.crypto.truststore import TrustStore
from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions
from cryptography.x509.oid import ExtendedKeyUsageOID

from lathed import __version__
from lathed import log as logmod
from lathed.client import default_socket
from lathed.config import EX_CONFIG, ConfigError, Section
from lathed.opcua import nodesets, spacecache
from lathed.opcua.guard import GuardedServer, Limits, LogLimit, flush_logs
from lathed.opcua.space import NAMESPACE, SUPPRESSION_MODES, Space
from lathed.web import accounts
from lathed.link import DaemonLink, ask, loopback

log = structlog.get_logger("lathed.opcua")
EVENTS_REPLAYED = 200    # events a reconnection looks back for, so a short daemon restart loses none
FIRST_STATUS_WAIT_S = 15.0   # for the daemon's first status before listening (its machines built)
BUILD_WAIT_S = 120.0         # ... when the daemon answers and its machines are being built


def default_state_dir() -> Path:
    """systemd's StateDirectory, else a directory inside this environment (as the daemon's)."""
    if os.environ.get("STATE_DIRECTORY"):
        return Path(os.environ["STATE_DIRECTORY"].split(":")[0])
    return Path(sys.prefix) / "var" / "lib" / "lathed-opcua"


class Settings:
    def __init__(self, path: str | None, listen: str | None = None, port: int | None = None,
                 sock: str | None = None):
        data: dict = {}
        if path:
            try:
                data = tomllib.loads(Path(path).read_text())
            except (OSError, tomllib.TOMLDecodeError) as e:
                raise ConfigError(f"{path}: {e}") from None
        file = path or "(defaults)"
        unknown = sorted(set(data) - {"opcua", "users"})
        if unknown:
            raise ConfigError(f"{file}: unknown table(s) {', '.join(unknown)}; allowed: opcua, users")
        sec = Section(file, "opcua", data.get("opcua", {}))
        self.listen = listen or sec.getstr("listen", "127.0.0.1")
        self.port = port if port is not None else sec.getint("port", 4840, minval=1, maxval=65535)
        self.socket = Path(sock or sec.getstr("socket", "") or default_socket())
        self.state_dir = Path(sec.getstr("state_dir", "") or default_state_dir())
        self.rate_hz = sec.getfloat("rate_hz", 10.0, minval=0.5, maxval=20.0)
        self.writable = sec.getbool("writable", False)
        self.name = sec.getstr("name", "lathed")
        d = Limits()
        self.limits = Limits(
            max_connections=sec.getint("max_connections", d.max_connections, minval=2, maxval=10000),
            hello_timeout_s=sec.getduration("hello_timeout", d.hello_timeout_s, minval=0.1, maxval=600.0),
            activation_timeout_s=sec.getduration("activation_timeout", d.activation_timeout_s, minval=0.5,
                                                 maxval=600.0),
            max_subscriptions_per_session=sec.getint("max_subscriptions_per_session", d.max_subscriptions_per_session,
                                                     minval=1, maxval=1000),
            max_monitored_items_per_session=sec.getint("max_monitored_items_per_session",
                                                       d.max_monitored_items_per_session, minval=1, maxval=100000),
            max_monitored_items=sec.getint("max_monitored_items", d.max_monitored_items, minval=1, maxval=1000000),
            min_publishing_interval_ms=1000.0 * sec.getduration("min_publishing_interval",
                                                                d.min_publishing_interval_ms / 1000.0,
                                                                minval=0.01, maxval=60.0))
        trusted = sec.getstr("trusted_clients", "")
        self.trusted_clients = Path(trusted) if trusted else None
        sec.check_unused()
        if self.trusted_clients is not None and not self.trusted_clients.is_dir():
            raise ConfigError(f"{file}: [opcua] trusted_clients: {trusted!r} is not a directory (of the client "
                              "application certificates to accept, DER or PEM)")
        self.users = accounts.users_from(file, data.get("users"), "lathed-opcua")
        self.loopback = loopback(self.listen)
        if not self.loopback and not self.users:
            raise ConfigError(f"{file}: [opcua] listen = {self.listen!r} opens the server to the network: that "
                              "needs accounts ([users.NAME] with role and a password hash from `lathed-opcua "
                              "hash-password`); anonymous access is for loopback only")
        if self.writable and not any(role == "operator" for role, _ in self.users.values()):
            raise ConfigError(f"{file}: [opcua] writable = true but no [users.NAME] has role = \"operator\": "
                              "nobody could write")

    @property
    def url(self) -> str:
        host = f"[{self.listen}]" if ":" in self.listen else self.listen
        return f"opc.tcp://{host}:{self.port}"


class Accounts:
    """asyncua's user manager: anonymous (where allowed) or an account of the config.

    asyncua asks synchronously, in the server's one event loop, so a password check (scrypt,
    ~50 ms on purpose) holds every value update meanwhile: after FAILS_MAX wrong passwords for
    an account within FAILS_WINDOW_S the next are refused unchecked, and a guesser cannot
    stall the server."""

    FAILS_MAX = 5
    FAILS_WINDOW_S = 10.0

    def __init__(self, users: dict[str, tuple[str, str]], anonymous: bool, clock=time.monotonic):
        self.users, self.anonymous, self.clock = users, anonymous, clock
        self._salt = os.urandom(16)
        self._verified: set[tuple[str, bytes]] = set()
        self._fails: dict[str, deque] = {}

    def get_user(self, iserver, username=None, password=None, certificate=None):
        if username is None:
            return User(role=UserRole.User, name=None) if self.anonymous else None
        acct = self.users.get(username)
        if acct is None or not isinstance(password, (str, bytes)):
            log.warning("login_refused", user=username, why="no such account" if acct is None else "no password")
            return None
        pw = password.decode(errors="replace") if isinstance(password, bytes) else password
        key = (username, hashlib.sha256(pw.encode() + self._salt).digest())
        if key in self._verified:     # a session re-activated with a password checked before
            return User(role=UserRole.User, name=username)
        now = self.clock()
        fails = self._fails.setdefault(username, deque(maxlen=self.FAILS_MAX))
        if len(fails) == self.FAILS_MAX and now - fails[0] < self.FAILS_WINDOW_S:
            log.warning("login_refused", user=username,
                        why=f"{self.FAILS_MAX} wrong passwords within {self.FAILS_WINDOW_S:g} s: not checked")
            return None
        if accounts.verify(pw, acct[1]):
            self._verified.add(key)
            return User(role=UserRole.User, name=username)
        fails.append(now)
        log.warning("login_refused", user=username, why="wrong password")
        return None

    def role(self, user: User) -> str | None:
        return self.users[user.name][0] if user.name in self.users else None


class WriteGate:
    """The server's write service, with the suppression modes forwarded to the daemon.

    Every other node is read-only to clients (asyncua's own check refuses them); the server's
    own updates (the Admin role, never given to a client) pass straight through."""

    def __init__(self, server: Server, space: Space, users: Accounts, sock: Path):
        self.space, self.users, self.sock = space, users, sock
        self.service = server.iserver.attribute_service
        self._write = self.service.write
        self.service.write = self.write

    async def write(self, params: ua.WriteParameters, user: User = User(role=UserRole.Admin)) -> list:
        if user.role == UserRole.Admin:
            return await self._write(params, user)
        out = []
        for wv in params.NodesToWrite:
            analyzer = self.space.writable.get(wv.NodeId) if wv.AttributeId == ua.AttributeIds.Value else None
            if analyzer is None or not self.space.can_write:
                out += await self._write(ua.WriteParameters(NodesToWrite=[wv]), user)
            else:
                out.append(await self._suppress(analyzer, wv, user))
        return out

    async def _suppress(self, analyzer: str, wv: ua.WriteValue, user: User) -> ua.StatusCode:
        who = user.name or "anonymous"
        role = self.users.role(user)
        if role != "operator":
            log.warning("write_refused", user=who, role=role, node=wv.NodeId.to_string(),
                        why="the operator role is needed")
            return ua.StatusCode(ua.StatusCodes.BadUserAccessDenied)
        mode = wv.Value.Value.Value if wv.Value is not None and wv.Value.Value is not None else None
        if not isinstance(mode, str):
            return ua.StatusCode(ua.StatusCodes.BadTypeMismatch)
        if mode not in SUPPRESSION_MODES:
            log.warning("write_refused", user=who, value=mode, why=f"not one of {', '.join(SUPPRESSION_MODES)}")
            return ua.StatusCode(ua.StatusCodes.BadOutOfRange)
        try:
            res = await ask(self.sock, "suppress", {"action": mode, "by": who, "analyzer": analyzer})
        except RuntimeError as e:      # the daemon's own refusal, e.g. this process is not an operator there
            log.warning("write_refused", user=who, value=mode, why=str(e))
            return ua.StatusCode(ua.StatusCodes.BadRequestNotAllowed)
        except (OSError, ValueError, TimeoutError) as e:
            log.warning("write_failed", user=who, value=mode, why=f"the daemon is not reachable: {e}")
            return ua.StatusCode(ua.StatusCodes.BadNoCommunication)
        log.info("write", user=who, analyzer=analyzer, mode=res.get("mode"))
        await self.space.apply_status({"analyzers": [{**self.space.analyzers.get(analyzer, {}), **res,
                                                      "name": analyzer}]})
        return ua.StatusCode(ua.StatusCodes.Good)


class UaLink(DaemonLink):
    """The daemon link, asking for what the address space shows, handing it on in order."""

    def __init__(self, sock: Path, rate_hz: float):
        super().__init__(sock, rate_hz)
        self.queue: asyncio.Queue = asyncio.Queue()
        self._first: dict = {}

    def subscription(self) -> dict:
        return {"samples": ["*/*"], "states": True, "events": True, "events_limit": EVENTS_REPLAYED,
                "rate_hz": self.rate_hz}

    def _merge(self, f: dict) -> None:
        self._first = f

    def snapshot(self) -> dict:
        return {"type": "init", **self._first}

    def broadcast(self, msg: dict) -> None:
        self.queue.put_nowait(msg)


def ensure_certificate(state_dir: Path, app_uri: str) -> tuple[Path, Path]:
    """The server's key and self-signed certificate, made on first start (key 0600)."""
    state_dir.mkdir(parents=True, exist_ok=True, mode=0o700)
    key, cert = state_dir / "server-key.pem", state_dir / "server-cert.der"
    if not key.exists():
        fd = os.open(key, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "wb") as f:
            f.write(dump_private_key_as_pem(generate_private_key()))
        cert.unlink(missing_ok=True)
        log.info("certificate_key_made", path=str(key))
    mode = stat.S_IMODE(key.stat().st_mode)
    if mode & 0o077:
        raise ConfigError(f"{key}: the private key is readable by others (mode {mode:04o}): chmod 600 it")
    return key, cert


async def serve(settings: Settings, stop: asyncio.Event, log_limit: LogLimit | None = None) -> int:
    users = Accounts(settings.users, anonymous=settings.loopback)
    server = GuardedServer(settings.limits, user_manager=users)
    ns = await spacecache.open_space(server, spacecache.default_dir())   # init and the NodeSets
    server.set_endpoint(settings.url)
    server.set_server_name(f"lathed-opcua ({settings.name})")
    app_uri = f"urn:lathed:opcua:{socket.gethostname()}"
    await server.set_application_uri(app_uri)
    server.product_uri = "urn:lathed"
    key, cert = ensure_certificate(settings.state_dir, app_uri)
    await setup_self_signed_certificate(key, cert, app_uri, socket.gethostname(),
                                        [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH],
                                        {"organizationName": "lathed", "commonName": f"lathed-opcua {settings.name}"})
    await server.load_certificate(str(cert))
    await server.load_private_key(str(key))
    if settings.loopback:
        server.set_security_policy([ua.SecurityPolicyType.NoSecurity,
                                    ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt])
        server.set_identity_tokens([ua.AnonymousIdentityToken] +
                                   ([ua.UserNameIdentityToken] if settings.users else []))
    else:
        server.set_security_policy([ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt])
        server.set_identity_tokens([ua.UserNameIdentityToken])
    if settings.trusted_clients is not None:
        # only the client applications whose certificates are there, in date, their URI as they say
        store = TrustStore([settings.trusted_clients], [])
        try:
            await store.load()
        except ValueError as e:   # every file there is read as a certificate
            raise ConfigError(f"[opcua] trusted_clients: {settings.trusted_clients} holds a file that is not a "
                              f"certificate: {e}") from None
        server.set_certificate_validator(CertificateValidator(
            CertificateValidatorOptions.TIME_RANGE | CertificateValidatorOptions.URI |
            CertificateValidatorOptions.TRUSTED | CertificateValidatorOptions.PEER_CLIENT, store))
    idx = await server.register_namespace(NAMESPACE)
    space = Space(server, idx, nodesets.Types(server, ns))
    await space.build(settings.writable)
    WriteGate(server, space, users, settings.socket)
    link = UaLink(settings.socket, settings.rate_hz)
    tasks = [asyncio.create_task(link.run()), asyncio.create_task(_feed(link, space))]
    if log_limit is not None:
        tasks.append(asyncio.create_task(flush_logs(log_limit)))
    try:
        # the machines are built from the daemon's first status before the port opens: building
        # one holds the loop for a while, and a client should find them all at once
        await _first_status(space, link, stop)
        if not space.ready.is_set() and not stop.is_set():
            log.warning("daemon_not_reached", socket=str(settings.socket), waited_s=FIRST_STATUS_WAIT_S,
                        why="serving without the machines; they appear when the daemon answers")
        try:
            await server.start()
        except OSError as e:
            print(f"lathed-opcua: cannot listen on {settings.listen}:{settings.port}: {e.strerror or e}",
                  file=sys.stderr)
            return 71
        security = "anonymous read, no security (loopback)" if settings.loopback else \
            "Basic256Sha256 SignAndEncrypt, accounts only"
        print(f"lathed-opcua: serving {settings.url} ({security}; namespace {NAMESPACE}; "
              f"daemon socket {settings.socket})", flush=True)
        await stop.wait()
    finally:
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        await server.stop()
    return 0


async def _first_status(space: Space, link: UaLink, stop: asyncio.Event) -> None:
    """Until the first status is applied, the stop, or FIRST_STATUS_WAIT_S without a daemon (with
    one, building its machines may take longer on a loaded machine: up to BUILD_WAIT_S)."""
    t0 = asyncio.get_running_loop().time()
    while not space.ready.is_set() and not stop.is_set():
        waited = asyncio.get_running_loop().time() - t0
        if waited > BUILD_WAIT_S or (waited > FIRST_STATUS_WAIT_S and not link.connected):
            return
        try:
            await asyncio.wait_for(space.ready.wait(), 0.5)
        except TimeoutError:
            pass


def coalesced(batch: list[dict]) -> list[dict]:
    """Frames queued while the address space was busy, merged into one (the newest value of
    each sample, every event, the last status); a link or init message keeps its place."""
    out: list[dict] = []
    for msg in batch:
        prev = out[-1] if out else None
        if msg["type"] == "frame" and prev is not None and prev["type"] == "frame":
            prev["samples"] = {**(prev.get("samples") or {}), **(msg.get("samples") or {})}
            prev["events"] = [*(prev.get("events") or []), *(msg.get("events") or [])]
            if msg.get("status"):
                prev["status"] = msg["status"]
        else:
            out.append(dict(msg))
    return out


async def _feed(link: UaLink, space: Space) -> None:
    """The link's messages into the address space, in order. Under a subscription storm a frame
    takes long to apply: what queued meanwhile is applied as one frame, so the link keeps
    reading (the daemon drops a subscriber that does not) and nothing piles up."""
    failing: str | None = None
    while True:
        batch = [await link.queue.get()]
        while not link.queue.empty():
            batch.append(link.queue.get_nowait())
        for msg in coalesced(batch):
            try:
                if msg["type"] == "link":
                    await space.daemon_lost()
                else:
                    if msg["type"] == "init":
                        space.connected = True
                        latest = max((e["id"] for e in msg.get("events") or []), default=0)
                        # first start: the snapshot's events are history; after a reconnection those
                        # past the last one shown were missed and go out now (a new store starts over)
                        if space.last_event_id is None or latest < space.last_event_id:
                            space.last_event_id = latest
                    await space.apply(msg)
                    if msg["type"] == "init":
                        space.ready.set()
                failing = None
            except Exception as e:   # a bug here must not stop the values (the next frame goes on); said once
                if repr(e) != failing:
                    failing = repr(e)
                    log.exception("apply_failed", type=msg.get("type"))


def main(argv: list[str] | None = None) -> int:
    args = accounts.side_process_args("lathed-opcua", "lathed's line as an OPC UA server (OPC 40501 Machine "
                                      "Tools layout).", "LATHED_OPCUA_CONFIG", "none: loopback, read-only", 4840,
                                      argv, __version__)
    if isinstance(args, int):      # hash-password
        return args
    logmod.setup("info")
    logging.getLogger("asyncua").setLevel(logging.ERROR)   # its per-request chatter; ours says what matters
    log_limit = LogLimit()     # a flood of bad connections is counted, not logged line by line
    for handler in logging.getLogger().handlers:
        handler.addFilter(log_limit)
    try:
        settings = Settings(args.config, args.listen, args.port, args.socket)
    except ConfigError as e:
        print(f"lathed-opcua: {e}", file=sys.stderr)
        return EX_CONFIG

    async def run() -> int:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, stop.set)
        try:
            return await serve(settings, stop, log_limit)
        except ConfigError as e:
            print(f"lathed-opcua: {e}", file=sys.stderr)
            return EX_CONFIG
        except OSError as e:
            print(f"lathed-opcua: {settings.state_dir}: {e.strerror or e}", file=sys.stderr)
            return 73
    return asyncio.run(run())


if __name__ == "__main__":
    sys.exit(main())
