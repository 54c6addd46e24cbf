"""lathed-web: the operator view in a browser (docs/web.md).

One subscription to the daemon (lathed.push) feeds every page through
server-sent events (lathed.web.live); pages never reach the daemon themselves.
Actions (the suppression switch, suppress now, the thermal touch-off and refit,
an inspection) are the daemon's own control commands, sent with the user's
name, so the event log says who.

Access (lathed.web.access): 127.0.0.1 by default, open to whoever is on this
PC (as user "local", operator). With [users.NAME] accounts every request needs
one (HTTP basic auth; roles viewer and operator), and listening on any other
address requires accounts. Every request must name this view in its Host; an
action needs the operator role, its session's CSRF token and, if the browser
says where it comes from, this view as its Origin. Connections are capped and
slow ones cut (lathed.gate).
"""
from __future__ import annotations

import asyncio
import base64
import hashlib
import json
import math
import secrets
import signal
import sys
import time
import tomllib
from pathlib import Path
from typing import Any

import structlog
from aiohttp import web

from lathed import __version__
from lathed import log as logmod
from lathed.client import default_socket
from lathed.config import EX_CONFIG, ConfigError, Section
from lathed.gate import Gate, fit_to_fd_limit
from lathed.link import ask, loopback
from lathed.lograte import Limited, limit_library_logs
from lathed.web import accounts
from lathed.web.access import COOKIE, Hosts, Logins, Sessions, same_origin
from lathed.web.live import BrowserLink

log = structlog.get_logger("lathed.web")
STATIC = Path(__file__).parent / "static"
# How long one daemon answer serves every page asking the same (each page asks
# parts every 10 s and recommendations every minute): a crowd of pages costs the
# daemon one query, not one each. An action clears them.
SHARED_ANSWER_S = {"parts": 5.0, "recommend": 30.0}
BODY_TIMEOUT_S = 10.0     # an action's body must arrive within this (a trickled body is cut)


class Settings:
    def __init__(self, path: str | None, listen: str | None, port: int | None, sock: str | None):
        data: dict = {}
        if path:
            try:
                data = tomllib.loads(Path(path).read_text())
            except (OSError, tomllib.TOMLDecodeError) as e:
                raise ConfigError(f"{path}: {e}") from None
        file = path or "(defaults)"
        unknown = sorted(set(data) - {"web", "users"})
        if unknown:
            raise ConfigError(f"{file}: unknown table(s) {', '.join(unknown)}; allowed: web, users")
        sec = Section(file, "web", data.get("web", {}))
        self.listen = listen or sec.getstr("listen", "127.0.0.1")
        self.port = port if port is not None else sec.getint("port", 8780, minval=1, maxval=65535)
        self.socket = Path(sock or sec.getstr("socket", "") or default_socket())
        self.rate_hz = sec.getfloat("rate_hz", 4.0, minval=0.5, maxval=20.0)   # the page draws 4 times a second
        self.allowed_hosts = sec.getlist("allowed_hosts", [])
        # default: as many as the open-files limit allows (the unit's LimitNOFILE): a crowd
        # that fits is held, not churned, and churn is what locks a fresh client out
        self.max_connections: int | None = sec.getint("max_connections", None, minval=16, maxval=1 << 20)
        self.max_per_client = sec.getint("max_connections_per_client", 64, minval=4, maxval=65536)
        self.idle_timeout = sec.getduration("idle_timeout", 10.0, minval=1.0, maxval=3600.0)
        self.max_live_pages = sec.getint("max_live_pages", 50, minval=1, maxval=10000)
        if self.max_connections is not None and self.max_live_pages >= self.max_connections:
            raise sec.error("max_live_pages", f"{self.max_live_pages} leaves no connection for anything else: "
                                              f"it must be below max_connections ({self.max_connections})")
        sec.check_unused()
        self.users = accounts.users_from(file, data.get("users"))
        if not self.users and not loopback(self.listen):
            raise ConfigError(f"{file}: [web] listen = {self.listen!r} opens the view to the network: that needs "
                              "accounts ([users.NAME] with role and a password hash from `lathed-web "
                              "hash-password`)")
        self.hosts = Hosts(self.listen, self.allowed_hosts, loopback(self.listen))


class App:
    def __init__(self, settings: Settings):
        self.s = settings
        self.link = BrowserLink(settings.socket, settings.rate_hz, settings.max_live_pages)
        cap, self.backlog = fit_to_fd_limit(settings.max_connections)
        self.gate = Gate(max_connections=cap, per_client=settings.max_per_client, idle_timeout=settings.idle_timeout)
        self.sessions = Sessions()
        self.logins = Logins()
        self.lim = Limited(log)
        self._key_salt = secrets.token_bytes(16)
        self._verified: dict[tuple[str, bytes], float] = {}
        self._answers: dict[str, tuple[float, asyncio.Future]] = {}
        # an unknown name costs a check too: how long a refusal takes does not tell which names exist
        self._dummy = accounts.hash_password(secrets.token_hex(8)) if settings.users else ""

    # -- before any handler ----------------------------------------------------------------
    @web.middleware
    async def gated(self, request: web.Request, handler):
        """The gate's bookkeeping (a request in hand is never the one evicted) and the Host check."""
        self.gate.busy(request.transport)
        try:
            if not self.s.hosts.allowed(request.host):
                self.lim.warning("host_refused", host=request.host[:200], client=request.remote,
                                 why="not a name of this view ([web] allowed_hosts)")
                return web.Response(status=421, text=f"this view does not answer to the name {request.host[:200]!r}"
                                                     " (lathed-web's [web] allowed_hosts lists the names it does)")
            return await handler(request)
        finally:
            self.gate.done(request.transport)

    async def user(self, request: web.Request) -> tuple[str, str]:
        """(user, role) of a request, or raises 401 (429 while its client or account backs off)."""
        if not self.s.users:
            return "local", "operator"
        auth = request.headers.get("Authorization", "")
        if not auth.startswith("Basic "):
            raise self._unauthorized()
        try:
            name, _, pw = base64.b64decode(auth[6:]).decode().partition(":")
        except ValueError:
            name, pw = "", ""
        acct = self.s.users.get(name)
        key = (name, hashlib.sha256(pw.encode() + self._key_salt).digest())
        if acct is not None and key in self._verified:
            return name, acct[0]
        client = request.remote or "?"
        async with self.logins.lock(client):
            if acct is not None and key in self._verified:   # checked while this one waited its turn
                return name, acct[0]
            wait = self.logins.wait(client, name if acct is not None else None)
            if wait > 0:
                self.lim.warning("login_backoff", key=client, client=client, user=name[:64],
                                 retry_after_s=math.ceil(wait), refused=self.logins.refused_total)
                raise web.HTTPTooManyRequests(headers={"Retry-After": str(math.ceil(wait))},
                                              text=f"too many failed logins: try again in {math.ceil(wait)} s")
            # scrypt takes ~50 ms on purpose: in a thread, so guessing never stalls the pages
            ok = await asyncio.to_thread(accounts.verify, pw, acct[1] if acct is not None else self._dummy)
            if ok and acct is not None:
                self.logins.succeeded(client, name)
                self._verified[key] = time.time()
                return name, acct[0]
            f = self.logins.failed(client, name if acct is not None else None)
            self.lim.warning("login_failed", key=client, client=client, user=name[:64],
                             known_user=acct is not None, failures=f.count,
                             backoff_s=round(max(0.0, f.until - self.logins.clock()), 1))
        raise self._unauthorized()

    @staticmethod
    def _unauthorized() -> web.HTTPUnauthorized:
        return web.HTTPUnauthorized(headers={"WWW-Authenticate": 'Basic realm="lathed", charset="UTF-8"'},
                                    text="an account is needed (ask for one: [users] in lathed-web's config)")

    @web.middleware
    async def access(self, request: web.Request, handler):
        request["user"], request["role"] = await self.user(request)
        resp = await handler(request)
        resp.headers.setdefault("X-Frame-Options", "DENY")
        resp.headers.setdefault("X-Content-Type-Options", "nosniff")
        return resp

    # -- pages -----------------------------------------------------------------------------
    async def index(self, request: web.Request) -> web.Response:
        user = request["user"]
        sid = self.sessions.get(request.cookies.get(COOKIE), user) or self.sessions.new(user)
        html = (STATIC / "index.html").read_text()
        meta = json.dumps({"user": user, "role": request["role"], "csrf": self.sessions.token(sid),
                           "version": __version__})
        resp = web.Response(text=html.replace("{{META}}", meta.replace("<", "\\u003c")), content_type="text/html",
                            headers={"Cache-Control": "no-store"})
        resp.set_cookie(COOKIE, sid, httponly=True, samesite="Strict", path="/", secure=request.secure)
        return resp

    async def events(self, request: web.Request) -> web.StreamResponse:
        return await self.link.stream(request)

    async def health(self, request: web.Request) -> web.Response:
        """What this process holds: the daemon link, live pages, connections (the page shows a refusal with it)."""
        return web.json_response({"daemon": {"connected": self.link.connected, "error": self.link.error,
                                             "frames": self.link.frames},
                                  "live": self.link.counts(), "connections": self.gate.counts(),
                                  "logins": {"failed": self.logins.failed_total,
                                             "refused": self.logins.refused_total},
                                  "sessions_issued": self.sessions.issued})

    async def api_get(self, request: web.Request) -> web.Response:
        what = request.match_info["what"]
        q = request.query
        if what == "parts":
            cmd, args = "parts", {"limit": 200, "abnormal": q.get("abnormal") == "1"}
        elif what == "recommend":
            cmd, args = "recommend", {"all": True}
        elif what == "health":
            return await self.health(request)
        else:
            raise web.HTTPNotFound(text=f"no {what!r} here")
        try:
            res = await self._shared(cmd, args, SHARED_ANSWER_S[what])
        except RuntimeError as e:   # the daemon's answer, e.g. no experiments recorded: shown as such
            return web.json_response({"error": str(e)})
        except (OSError, ValueError, TimeoutError) as e:
            return web.json_response({"error": f"the daemon is not reachable: {e}"}, status=502)
        return web.json_response({"result": res})

    async def _shared(self, cmd: str, args: dict, keep_s: float) -> Any:
        """The daemon's answer to (cmd, args), one request for every page that asks within
        keep_s (those asking while it is on its way wait for the same one); a failure is
        not kept."""
        key = json.dumps([cmd, args], sort_keys=True)
        now = time.monotonic()
        hit = self._answers.get(key)
        if hit is None or (hit[1].done() and (now - hit[0] >= keep_s or hit[1].cancelled()
                                             or hit[1].exception() is not None)):
            hit = (now, asyncio.ensure_future(ask(self.s.socket, cmd, args)))
            self._answers[key] = hit
        return await asyncio.shield(hit[1])

    def _refuse_action(self, request: web.Request) -> web.Response | None:
        """Why an action request is not this view's own page acting for its user, or None."""
        user, role = request["user"], request["role"]
        if not self.sessions.check(request.cookies.get(COOKIE), user, request.headers.get("X-CSRF-Token", "")):
            return web.json_response({"error": "missing or wrong CSRF token: reload the page"}, status=403)
        origin = request.headers.get("Origin")
        site = request.headers.get("Sec-Fetch-Site")
        if (origin is not None and not same_origin(origin, request.host, request.secure)) \
                or site not in (None, "same-origin", "none"):
            self.lim.warning("action_cross_site", origin=(origin or "")[:200], host=request.host[:200], site=site)
            return web.json_response({"error": f"a request from another site ({origin or site}) is refused"},
                                     status=403)
        if role != "operator":
            log.warning("action_refused", user=user, role=role, path=request.path)
            return web.json_response({"error": f"{user} is a {role}: actions need the operator role"}, status=403)
        return None

    async def action(self, request: web.Request) -> web.Response:
        if (refused := self._refuse_action(request)) is not None:
            return refused
        user = request["user"]
        try:
            async with asyncio.timeout(BODY_TIMEOUT_S):
                body = await request.json()
            if not isinstance(body, dict):
                raise ValueError("expected a JSON object")
        except TimeoutError:
            return web.json_response({"error": f"the request body did not arrive within {BODY_TIMEOUT_S:g} s"},
                                     status=408)
        except ValueError as e:
            return web.json_response({"error": f"malformed action: {e}"}, status=400)
        what = request.match_info["what"]
        if what == "suppress":
            cmd, args = "suppress", {"action": body.get("action"), "by": user}
        elif what == "thermal":
            if body.get("action") not in ("touchoff", "refit"):
                return web.json_response({"error": "thermal: the actions here are touchoff and refit"}, status=400)
            cmd, args = "thermal", {"action": body["action"], "by": user}
        elif what == "inspect":
            cmd, args = "inspect", {"part": body.get("part"), "ra_um": body.get("ra_um"),
                                    "diameter_error_um": body.get("diameter_error_um"), "by": user}
        else:
            return web.json_response({"error": f"no action {what!r}"}, status=404)
        try:
            res = await ask(self.s.socket, cmd, args)
        except RuntimeError as e:   # the daemon's own one-line refusal
            return web.json_response({"error": str(e)}, status=400)
        except (OSError, ValueError, TimeoutError) as e:
            return web.json_response({"error": f"the daemon is not reachable: {e}"}, status=502)
        log.info("action", user=user, cmd=cmd, args=args)
        self._answers.clear()     # an inspection or a refit shows at once, not after keep_s
        return web.json_response(res)

    def build(self) -> web.Application:
        app = web.Application(middlewares=[self.gated, self.access], client_max_size=64 << 10)
        app.router.add_get("/", self.index)
        app.router.add_get("/events", self.events)
        app.router.add_get("/api/{what}", self.api_get)
        app.router.add_post("/api/{what}", self.action)
        app.router.add_static("/static/", STATIC)
        app.on_startup.append(self._start)
        app.on_shutdown.append(self._stop)
        return app

    async def _start(self, app: web.Application) -> None:
        self._task = asyncio.create_task(self.link.run())

    async def _stop(self, app: web.Application) -> None:
        # on shutdown, before aiohttp waits for open requests: an open page's event stream
        # would otherwise hold the stop for aiohttp's shutdown timeout
        self._task.cancel()
        for q in list(self.link.browsers):
            self.link.end_stream(q)
        await asyncio.gather(self._task, return_exceptions=True)
        for lim in (self.lim, self.gate.lim, self.link.lim):
            lim.flush()

    async def serve(self) -> None:
        """Until SIGTERM or SIGINT: the app behind the gate on [web] listen:port."""
        # the gate closes idle connections (and counts them); aiohttp's own timer is the backstop
        runner = web.AppRunner(self.build(), access_log=None, shutdown_timeout=5.0,
                               keepalive_timeout=2 * self.s.idle_timeout + 1)
        await runner.setup()
        self.gate.factory = runner.server
        loop = asyncio.get_running_loop()
        stop = asyncio.Event()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, stop.set)
        try:
            server = await loop.create_server(self.gate, self.s.listen, self.s.port, reuse_address=True,
                                              backlog=self.backlog)
        except OSError:
            await runner.cleanup()
            raise
        try:
            await stop.wait()
        finally:
            server.close()
            await runner.cleanup()


def main(argv: list[str] | None = None) -> int:
    args = accounts.side_process_args("lathed-web", "The operator view of lathed, in a browser.",
                                      "LATHED_WEB_CONFIG", "none: local only", 8780, argv, __version__)
    if isinstance(args, int):      # hash-password
        return args
    logmod.setup("info")
    limit_library_logs()
    try:
        settings = Settings(args.config, args.listen, args.port, args.socket)
    except ConfigError as e:
        print(f"lathed-web: {e}", file=sys.stderr)
        return EX_CONFIG
    app = App(settings)
    host = f"[{settings.listen}]" if ":" in settings.listen else settings.listen
    print(f"lathed-web: the operator view is at http://{host}:{settings.port}/ "
          f"(daemon socket {settings.socket})", flush=True)
    try:
        asyncio.run(app.serve())
    except OSError as e:
        print(f"lathed-web: cannot listen on {settings.listen}:{settings.port}: {e.strerror or e}", file=sys.stderr)
        return 71
    return 0


if __name__ == "__main__":
    sys.exit(main())
