"""lathed-web: the operator view in a browser.

One subscription to the daemon (lathed.push) feeds every browser through
server-sent events; browsers never reach the daemon themselves, and a crowd
of them costs the daemon nothing more than one subscriber. Actions (the
suppression switch, suppress now, the thermal touch-off, an inspection) are the daemon's own
control commands, sent with the user's name, so the event log says who.

Access: 127.0.0.1 by default, open to whoever is on this PC (as user
"local", operator). With [users.NAME] accounts every request needs one
(HTTP basic auth; roles viewer and operator), and listening on any other
address requires accounts. An action needs the operator role (else 403) and
the page's CSRF token in X-CSRF-Token, which a cross-site page cannot read.
"""
from __future__ import annotations

import asyncio
import base64
import hashlib
import hmac
import json
import secrets
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
from lathed.link import DaemonLink, ask, loopback
from lathed.web import accounts

log = structlog.get_logger("lathed.web")
STATIC = Path(__file__).parent / "static"
BROWSER_QUEUE = 64     # messages waiting for one browser before it is dropped (it reconnects by itself)
# How long one daemon answer serves every page asking the same (each page asks
# parts every 10 s and recommendations every minute): a crowd of pages costs the
# daemon one query, not one each. An action clears them.
SHARED_ANSWER_S = {"parts": 5.0, "recommend": 30.0}


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
        sec.check_unused()
        self.users = accounts.users_from(file, data.get("users"))
        if not self.users and not loopback(self.listen):
            raise ConfigError(f"{file}: [web] listen = {self.listen!r} opens the view to the network: that needs "
                              "accounts ([users.NAME] with role and a password hash from `lathed-web "
                              "hash-password`)")


class BrowserLink(DaemonLink):
    """The daemon link, fanned out to the browsers' event streams."""

    def __init__(self, sock: Path, rate_hz: float):
        super().__init__(sock, rate_hz)
        self.browsers: set[asyncio.Queue] = set()
        self.dropped_browsers = 0

    def broadcast(self, msg: dict) -> None:
        data = json.dumps(msg)
        for q in list(self.browsers):
            try:
                q.put_nowait(data)
            except asyncio.QueueFull:   # a browser that does not keep up: cut, it reconnects and redraws
                self.end_stream(q)
                self.dropped_browsers += 1

    def end_stream(self, q: asyncio.Queue) -> None:
        """Its page's event stream ends at once, whatever it had not sent."""
        self.browsers.discard(q)
        while not q.empty():
            q.get_nowait()
        q.put_nowait(None)


# -- the web side ----------------------------------------------------------------
class App:
    def __init__(self, settings: Settings):
        self.s = settings
        self.link = BrowserLink(settings.socket, settings.rate_hz)
        self.secret = secrets.token_bytes(32)
        self._verified: dict[tuple[str, bytes], float] = {}
        self._answers: dict[str, tuple[float, asyncio.Future]] = {}

    def csrf(self, user: str) -> str:
        return hmac.new(self.secret, user.encode(), hashlib.sha256).hexdigest()

    async def user(self, request: web.Request) -> tuple[str, str]:
        """(user, role) of a request, or raises 401."""
        if not self.s.users:
            return "local", "operator"
        auth = request.headers.get("Authorization", "")
        if auth.startswith("Basic "):
            try:
                name, _, pw = base64.b64decode(auth[6:]).decode().partition(":")
            except ValueError:
                name, pw = "", ""
            acct = self.s.users.get(name)
            if acct is not None:
                key = (name, hashlib.sha256(pw.encode() + self.secret).digest())
                # scrypt takes ~50 ms on purpose: in a thread, so guessing never stalls the pages
                if key in self._verified or await asyncio.to_thread(accounts.verify, pw, acct[1]):
                    self._verified[key] = time.time()
                    return name, acct[0]
        raise web.HTTPUnauthorized(headers={"WWW-Authenticate": 'Basic realm="lathed", charset="UTF-8"'},
                                   text="an account is needed (ask for one: [users] in lathed-web's config)")

    @web.middleware
    async def access(self, request: web.Request, handler):
        request["user"], request["role"] = await self.user(request)
        resp = await handler(request)
        resp.headers.setdefault("X-Frame-Options", "DENY")
        resp.headers.setdefault("X-Content-Type-Options", "nosniff")
        return resp

    async def index(self, request: web.Request) -> web.Response:
        html = (STATIC / "index.html").read_text()
        meta = json.dumps({"user": request["user"], "role": request["role"], "csrf": self.csrf(request["user"]),
                           "version": __version__})
        return web.Response(text=html.replace("{{META}}", meta.replace("<", "\\u003c")), content_type="text/html")

    async def events(self, request: web.Request) -> web.StreamResponse:
        resp = web.StreamResponse(headers={"Content-Type": "text/event-stream", "Cache-Control": "no-cache"})
        await resp.prepare(request)
        q: asyncio.Queue = asyncio.Queue(maxsize=BROWSER_QUEUE)
        q.put_nowait(json.dumps(self.link.snapshot()))
        self.link.browsers.add(q)
        try:
            while True:
                try:
                    async with asyncio.timeout(15.0):
                        data = await q.get()
                except TimeoutError:
                    await resp.write(b": keep-alive\n\n")
                    continue
                if data is None:
                    break
                await resp.write(b"data: " + data.encode() + b"\n\n")
        except (ConnectionError, asyncio.CancelledError):
            pass
        finally:
            self.link.browsers.discard(q)
        return resp

    async def api_get(self, request: web.Request) -> web.Response:
        what = request.match_info["what"]
        q = request.query
        if what == "parts":
            cmd, args = "parts", {"limit": 200, "abnormal": q.get("abnormal") == "1"}
        elif what == "recommend":
            cmd, args = "recommend", {"all": True}
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

    async def action(self, request: web.Request) -> web.Response:
        user, role = request["user"], request["role"]
        if not hmac.compare_digest(request.headers.get("X-CSRF-Token", ""), self.csrf(user)):
            return web.json_response({"error": "missing or wrong CSRF token: reload the page"}, status=403)
        origin = request.headers.get("Origin")
        if origin is not None and origin.split("://", 1)[-1] != request.host:
            return web.json_response({"error": f"a request from another site ({origin}) is refused"}, status=403)
        if role != "operator":
            log.warning("action_refused", user=user, role=role, path=request.path)
            return web.json_response({"error": f"{user} is a {role}: actions need the operator role"}, status=403)
        try:
            body = await request.json()
            if not isinstance(body, dict):
                raise ValueError("expected a JSON object")
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
        app = web.Application(middlewares=[self.access], client_max_size=64 << 10)
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
        # would otherwise hold the stop for aiohttp's shutdown timeout (a minute)
        self._task.cancel()
        for q in list(self.link.browsers):
            self.link.end_stream(q)
        await asyncio.gather(self._task, return_exceptions=True)


def main(argv: list[str] | None = None) -> int:
    args = accounts.side_process_args("lathed-web", "The operator view of lathed, in a browser.",
                                      "LATHED_WEB_CONFIG", "none: local only", 8780, argv, __version__)
    if isinstance(args, int):      # hash-password
        return args
    logmod.setup("info")
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
        web.run_app(app.build(), host=settings.listen, port=settings.port, print=None,
                    access_log=None, handle_signals=True)
    except OSError as e:
        print(f"lathed-web: cannot listen on {settings.listen}:{settings.port}: {e.strerror or e}", file=sys.stderr)
        return 71
    return 0


if __name__ == "__main__":
    sys.exit(main())
