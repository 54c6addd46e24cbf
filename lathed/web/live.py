"""The pages' live updates: one daemon subscription fanned out as server-sent events.

A crowd of pages costs this process a bounded amount (issue 35: 3,500 pages
took 1.9 GB): at most ``max_pages`` streams at once (the next gets "503 too
many live pages", which the page shows); each frame is encoded once for all;
the snapshot a new page starts from is encoded once per frame, not once per
page; a page that reads nothing for WRITE_TIMEOUT_S, or falls BROWSER_QUEUE
frames behind, is cut (it reconnects by itself and redraws). None of this
waits on a page, so the daemon link is read on time and never dropped.
"""
from __future__ import annotations

import asyncio
import json
from pathlib import Path

import structlog
from aiohttp import web

from lathed.link import DaemonLink
from lathed.lograte import Limited

log = structlog.get_logger("lathed.web")
BROWSER_QUEUE = 64        # frames waiting for one page before it is cut (it reconnects by itself)
WRITE_TIMEOUT_S = 10.0    # a page whose socket takes nothing for this long is cut
KEEPALIVE_S = 15.0


class BrowserLink(DaemonLink):
    """The daemon link, fanned out to the pages' event streams."""

    def __init__(self, sock: Path, rate_hz: float, max_pages: int = 200):
        super().__init__(sock, rate_hz)
        self.max_pages = max_pages
        self.browsers: set[asyncio.Queue] = set()
        self.dropped_browsers = 0      # fell behind
        self.cut_browsers = 0          # read nothing for WRITE_TIMEOUT_S
        self.refused_pages = 0
        self._snap: tuple[tuple, bytes] | None = None
        self.lim = Limited(log)

    @staticmethod
    def event(msg: dict) -> bytes:
        return b"data: " + json.dumps(msg, separators=(",", ":")).encode() + b"\n\n"

    def snapshot_event(self) -> bytes:
        """The snapshot as an event, made again only when something came since."""
        key = (self.frames, self.connected, self.error)
        if self._snap is None or self._snap[0] != key:
            self._snap = (key, self.event(self.snapshot()))
        return self._snap[1]

    def broadcast(self, msg: dict) -> None:
        self._snap = None
        data = self.event(msg)
        for q in list(self.browsers):
            try:
                q.put_nowait(data)
            except asyncio.QueueFull:   # a page that does not keep up: cut, it reconnects and redraws
                self.end_stream(q)
                self.dropped_browsers += 1

    def end_stream(self, q: asyncio.Queue) -> None:
        """Its page's event stream ends at once, whatever it had not sent."""
        self.browsers.discard(q)
        while not q.empty():
            q.get_nowait()
        q.put_nowait(None)

    def counts(self) -> dict:
        return {"pages": len(self.browsers), "max_pages": self.max_pages, "refused": self.refused_pages,
                "fell_behind": self.dropped_browsers, "cut_not_reading": self.cut_browsers}

    async def stream(self, request: web.Request) -> web.StreamResponse:
        """GET /events: the snapshot, then each frame, until the page goes."""
        if len(self.browsers) >= self.max_pages:
            self.refused_pages += 1
            self.lim.warning("live_page_refused", pages=len(self.browsers), refused=self.refused_pages,
                             why=f"{self.max_pages} live pages open ([web] max_live_pages)")
            return web.Response(status=503, headers={"Retry-After": "10"},
                                text=f"too many live pages: {self.max_pages} are open (lathed-web's [web] "
                                     "max_live_pages); close one, this page tries again by itself")
        resp = web.StreamResponse(headers={"Content-Type": "text/event-stream", "Cache-Control": "no-cache"})
        q: asyncio.Queue = asyncio.Queue(maxsize=BROWSER_QUEUE)
        q.put_nowait(self.snapshot_event())
        self.browsers.add(q)
        try:
            async with asyncio.timeout(WRITE_TIMEOUT_S):
                await resp.prepare(request)
            while True:
                try:
                    async with asyncio.timeout(KEEPALIVE_S):
                        data = await q.get()
                except TimeoutError:
                    data = b": keep-alive\n\n"
                if data is None:
                    break
                async with asyncio.timeout(WRITE_TIMEOUT_S):
                    await resp.write(data)
        except TimeoutError:          # the page took nothing for WRITE_TIMEOUT_S: its connection goes
            self.cut_browsers += 1
            self.lim.info("live_page_cut", cut=self.cut_browsers,
                          why=f"its socket took nothing for {WRITE_TIMEOUT_S:g} s")
            if request.transport is not None:
                request.transport.abort()
        except (ConnectionError, asyncio.CancelledError):
            pass                      # the page went: nothing to say about it
        finally:
            self.browsers.discard(q)
        return resp
