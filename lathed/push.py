"""The push side of the control socket: ``subscribe`` streams live values.

A client asks once, on its own connection, for what it wants:

  samples    ["SOURCE/QUANTITY", ...] with shell wildcards ("lathe/*", "*/t_*")
  vibration  [SENSOR, ...]   (wildcards too, "*": every sensor) envelope and spectrum of a waveform (lathed.display),
                             never its raw samples
  views      [ANALYZER, ...] (or "*") an analyzer's plot data (chaos eye, stability lobes)
  states     true            the status of machines, sensors and analyzers
  events     true            new recorded events (kinds / sources narrow them),
                             the last ``events_limit`` of them in the snapshot
  rate_hz                    frames per second (the per-client rate limit)

The reply is the snapshot (everything asked for, as of now); then one line
``{"push": frame}`` per period with what changed (a frame at least every
HEARTBEAT_S, so a client sees a dead daemon). Values are coalesced: a slow
period sends the latest value, not a backlog. Events are never coalesced.
A vibration or analyzer view in a frame carries only its keys that changed
since the last frame (a spectrum's frequencies, an envelope's times, a lobe
chart are sent again only when they move; a key gone from the view comes as
null): merge it into the last one. A view that is null replaces it. A
vibration envelope is new each frame, its spectrum at most every
SPECTRUM_MIN_S (the FFT was most of a view's cost).

A subscriber costs the daemon a bounded amount: one task that makes a frame
each period and writes it; a write the client does not take must drain within
the control request timeout, and no frame is made meanwhile (the next one
carries what changed), so what waits for it is what the socket's buffer holds.
A client that does not drain in time is dropped (counted in status), never
waited for by anything else: the daemon's loop goes on.
"""
from __future__ import annotations

import asyncio
import fnmatch
import json
import time
from typing import Any, Callable

import structlog

from lathed.args import Args
from lathed.bus import Block, Bus
from lathed.control import RequestError, Stream, _default
from lathed.display import Ring
from lathed.viewdelta import changed_keys

log = structlog.get_logger("lathed.push")

HEARTBEAT_S = 1.0        # an empty frame after this long without one
STATES_EVERY_S = 1.0     # machine/analyzer status at most this often
EVENT_POLL_S = 0.2       # new events are read from the store this often (while someone wants them)
EVENT_BATCH = 1000
EVENT_PAGES = 10         # pages read per poll at most (a burst is delivered over several polls)
VIEW_MIN_S = 0.05        # a vibration or analyzer view is computed at most this often, for everyone
SPECTRUM_MIN_S = 0.5     # a vibration spectrum (an FFT, most of a view's cost) at most this often;
                         # the envelope follows every frame
MAX_RATE_HZ = 20.0


class PushHub:
    """Every subscriber of one daemon, and what they share: one ring per
    vibration sensor watched, one events poller, cached status and views."""

    def __init__(self, bus: Bus, store, names: dict[str, str], status: Callable[[], dict],
                 views: dict[str, Callable[[], dict | None]], max_subscribers: int,
                 quantities: Callable[[str], frozenset[str] | None] = lambda name: None):
        self.bus, self.store = bus, store
        self.names = names                  # instance name -> "machine" | "sensor" | "analyzer"
        self.quantities = quantities        # name -> every quantity it can publish (None: not fixed)
        self.status = status
        self.view_fns = views               # analyzers that draw something of their own
        self.max_subscribers = max_subscribers
        self.subscribers: set[Subscription] = set()
        self.dropped = 0
        self.last_drop: str | None = None
        self._rings: dict[str, tuple[Ring, Callable, set]] = {}   # sensor -> (ring, its bus tap, watchers)
        self._cache: dict[str, tuple[float, Any]] = {}
        self._vib: dict[str, tuple[float, int, dict | None]] = {}   # sensor -> (when, blocks, view)
        self._spec: dict[str, tuple[float, float, dict]] = {}       # sensor -> (when, rate, spectrum)
        self._json: dict[tuple[str, str], tuple[Any, str]] = {}      # (section, name) -> (view, its JSON)
        self._parts: dict[tuple[str, str, str], tuple[Any, str]] = {}  # ... and each of its values
        self._poller: asyncio.Task | None = None
        self._cursor = 0

    def stats(self) -> dict:
        return {"subscribers": len(self.subscribers), "max_subscribers": self.max_subscribers,
                "dropped": self.dropped, "last_drop": self.last_drop}

    # -- the request -----------------------------------------------------------------
    async def subscribe(self, args: dict) -> Stream:
        a = Args("subscribe", args)
        samples = a.getlist("samples", [])
        vibration = a.getlist("vibration", [])
        views = a.getlist("views", [])
        states = a.getbool("states", False)
        events = a.getbool("events", False)
        kinds = a.getlist("kinds", [])
        sources = a.getlist("sources", [])
        limit = a.getint("events_limit", 50, minval=0, maxval=10_000)
        rate = a.getfloat("rate_hz", 5.0, minval=0.1, maxval=MAX_RATE_HZ)
        a.check_unused()
        for i, pat in enumerate(samples):
            src, sep, q = pat.partition("/")
            if not sep or not src or not q:
                raise a.error(f"samples[{i}]", f"{pat!r} is not SOURCE/QUANTITY (wildcards allowed: lathe/*)")
            if not _wild(src) and src not in self.names:
                raise a.error(f"samples[{i}]", f"no machine, sensor or analyzer named {src!r}; "
                                               f"known: {', '.join(sorted(self.names))}")
            # a quantity its config does not give would never come: the watch waited forever
            have = None if _wild(src) else self.quantities(src)
            if have is not None and not any(fnmatch.fnmatchcase(x, q) for x in have):
                raise a.error(f"samples[{i}]", f"{src!r} publishes no quantity {q!r}; it publishes: "
                                               f"{', '.join(sorted(have))}")
        sensors = sorted(n for n, c in self.names.items() if c == "sensor")
        vibration = _expand(a, "vibration", vibration, sensors, "no sensor named {!r}; sensors: ")
        views = _expand(a, "views", views, sorted(self.view_fns), "{!r} has no view; analyzers with one: ")
        if (kinds or sources) and not events:
            raise a.error("kinds" if kinds else "sources", "narrows events: give events = true too")
        if kinds and (why := await asyncio.to_thread(self.store.unknown_kind, kinds)):
            raise a.error("kinds", why)      # a misspelt kind would follow nothing, forever
        if not (samples or vibration or views or states or events):
            raise a.error(None, "nothing asked for: give samples, vibration, views, states or events")
        if len(self.subscribers) >= self.max_subscribers:
            raise RequestError(f"subscribe: {self.max_subscribers} subscribers already (the daemon's "
                               "[daemon] control_max_subscribers); try again later")
        sub = Subscription(self, samples, vibration, views, states, events, set(kinds), set(sources), rate)
        self.subscribers.add(sub)
        try:
            for name in vibration:
                self._watch(name, sub)
            first: dict[str, Any] = {"t": time.time(), "samples": sub.changed_samples()}
            if states:
                first["status"] = self.status()
            if vibration:
                first["vibration"] = {n: self.vibration_view(n) for n in vibration}
            if views:
                first["views"] = {n: self.view(n) for n in views}
            if events:
                # registered before this query: whatever is committed after it reaches the subscriber
                rows, last = await asyncio.to_thread(self._recent, limit, sub)
                # a poll while it ran handed over events up to ``last`` too: the snapshot has them
                sub._events = [r for r in sub._events if r["id"] > last]
                sub.last_event_id = max(sub.last_event_id, last)
                first["events"] = rows
                self._start_poller(last)
        except BaseException:
            self.remove(sub)
            raise
        sub.first = first
        return sub

    def _recent(self, limit: int, sub: "Subscription") -> tuple[list[dict], int]:
        last = self.store.last_event_id()
        rows = self.store.events(limit, list(sub.kinds), list(sub.sources), 0) if limit else []
        return [r for r in rows if r["id"] <= last], last

    def remove(self, sub: "Subscription") -> None:
        if sub not in self.subscribers:
            return
        self.subscribers.discard(sub)
        for name in sub.vibration:
            entry = self._rings.get(name)
            if entry:
                entry[2].discard(sub)
                if not entry[2]:
                    self.bus.untap(name, entry[1])
                    del self._rings[name]
                    self._vib.pop(name, None)
                    self._spec.pop(name, None)
                    self._json.pop(("vibration", name), None)
        if self._poller and not any(s.events for s in self.subscribers):
            self._poller.cancel()
            self._poller = None

    def drop(self, sub: "Subscription", reason: str) -> None:
        self.dropped += 1
        self.last_drop = f"{time.strftime('%H:%M:%S')}: {reason}"
        log.warning("subscriber_dropped", reason=reason, dropped=self.dropped)

    # -- shared sources --------------------------------------------------------------
    def _watch(self, name: str, sub: "Subscription") -> None:
        if name not in self._rings:
            ring = Ring()

            def tap(msg, add=ring.add) -> None:   # in the bus's publish: a reference kept, no copy
                if type(msg) is Block:
                    add(msg.data, msg.rate_hz, msg.t0)
            self.bus.tap(name, tap)
            self._rings[name] = (ring, tap, set())
        self._rings[name][2].add(sub)

    def _cached(self, key: str, every: float, fn: Callable[[], Any]) -> Any:
        now = time.monotonic()
        hit = self._cache.get(key)
        if hit is None or now - hit[0] >= every:
            hit = (now, fn())
            self._cache[key] = hit
        return hit[1]

    def vibration_view(self, name: str) -> dict | None:
        entry = self._rings.get(name)
        if entry is None:
            return None
        ring = entry[0]
        now = time.monotonic()
        hit = self._vib.get(name)
        if hit is None or hit[1] != ring.blocks and now - hit[0] >= VIEW_MIN_S:
            spec = self._spec.get(name)
            if spec is not None and (now - spec[0] >= SPECTRUM_MIN_S or spec[1] != ring.rate_hz):
                spec = None
            view = ring.view(None if spec is None else spec[2])
            if view is not None and spec is None:
                # the same objects until the next one: a frame carries only keys that changed
                self._spec[name] = (now, ring.rate_hz, {k: view[k] for k in ("spec_f", "spec_a")})
            hit = self._vib[name] = (now, ring.blocks, view)
        return hit[2]

    def view(self, name: str) -> dict | None:
        """The analyzer's view, shared by subscribers within VIEW_MIN_S."""
        return self._cached(f"view:{name}", VIEW_MIN_S, lambda: _safe_view(self.view_fns[name]))

    def states(self) -> dict:
        return self._cached("status", STATES_EVERY_S / 2, self.status)

    def encode_frame(self, f: dict) -> bytes:
        """``{"push": f}`` as one line. The views in it (thousands of numbers, the most of a
        frame) are encoded once for all subscribers, and a value of a view equal to the one
        encoded last time (a spectrum's frequencies, an envelope's times, a chaos eye's
        baseline) is not encoded again."""
        parts = []
        for k, v in f.items():
            if k in ("vibration", "views"):
                v = "{" + ", ".join(f"{json.dumps(n)}: {self._view_json(k, n, x)}" for n, x in v.items()) + "}"
            else:
                v = json.dumps(v, default=_default)
            parts.append(f"{json.dumps(k)}: {v}")
        return ('{"push": {' + ", ".join(parts) + "}}\n").encode()

    def _view_json(self, section: str, name: str, view: dict | None) -> str:
        hit = self._json.get((section, name))
        if hit is not None and hit[0] is view:
            return hit[1]
        if not isinstance(view, dict):
            text = json.dumps(view, default=_default)
        else:
            items = []
            for k, x in view.items():
                key = (section, name, k)
                part = self._parts.get(key)
                if part is None or not isinstance(x, list) or (part[0] is not x and part[0] != x):
                    part = self._parts[key] = (x, json.dumps(x, default=_default))
                items.append(f"{json.dumps(k)}: {part[1]}")
            text = "{" + ", ".join(items) + "}"
        self._json[(section, name)] = (view, text)
        return text

    def _start_poller(self, last: int) -> None:
        if self._poller is None:
            self._cursor = last
            self._poller = asyncio.create_task(self._poll_events())

    async def _poll_events(self) -> None:
        failing_since: float | None = None     # a failing store is said once, and when it recovers
        failures = 0
        seen = None        # the store's count of committed events as of the last query
        while True:
            await asyncio.sleep(EVENT_POLL_S)
            stored = self.store.events_stored
            if stored == seen:   # nothing committed since: no query, no hop to a thread
                continue
            try:
                # the first EVENT_BATCH after the cursor, page after page: a burst of more
                # than a batch between two polls reaches subscribers whole, in order
                rows, more = [], True
                for _ in range(EVENT_PAGES):     # the rest at the next poll, from the new cursor
                    page = await asyncio.to_thread(self.store.events, EVENT_BATCH, None, None,
                                                   rows[-1]["id"] if rows else self._cursor, True)
                    rows += page
                    if len(page) < EVENT_BATCH:
                        more = False
                        break
            except Exception as e:   # the store says why; subscribers get the events on the next poll
                failures += 1
                if failing_since is None:
                    failing_since = time.monotonic()
                    log.error("push_events_failed", error=str(e))
                continue
            if failing_since is not None:
                log.info("push_events_recovered", failed_polls=failures,
                         after_s=round(time.monotonic() - failing_since, 1))
                failing_since, failures = None, 0
            seen = None if more else stored      # more waiting: look again at the next poll
            if rows:
                self._cursor = rows[-1]["id"]
                for sub in list(self.subscribers):
                    if sub.events:
                        sub.add_events(rows)


def _wild(pattern: str) -> bool:
    return any(c in pattern for c in "*?[")


def _expand(a: Args, key: str, patterns: list[str], names: list[str], missing: str) -> list[str]:
    """Names matching each pattern (shell wildcards: "*" is every one, and may be none: a line
    without a vibration sensor still gets its view); a name that is not there is an error."""
    out: list[str] = []
    for i, pat in enumerate(patterns):
        hit = [n for n in names if fnmatch.fnmatchcase(n, pat)]
        if not hit and not _wild(pat):
            raise a.error(f"{key}[{i}]", missing.format(pat) + (", ".join(names) or "none"))
        out += [n for n in hit if n not in out]
    return out


def _safe_view(fn: Callable[[], dict | None]) -> dict | None:
    try:
        return fn()
    except Exception as e:   # a view bug must not end the subscription
        log.exception("view_failed")
        return {"error": f"{type(e).__name__}: {e}"}


class Subscription(Stream):
    def __init__(self, hub: PushHub, samples: list[str], vibration: list[str], views: list[str], states: bool,
                 events: bool, kinds: set[str], sources: set[str], rate_hz: float):
        self.hub = hub
        self.patterns = [tuple(p.split("/", 1)) for p in samples]
        self.vibration, self.views, self.states, self.events = vibration, views, states, events
        self.kinds, self.sources = kinds, sources
        self.period = 1.0 / rate_hz
        self.last_event_id = 0
        self._events: list[dict] = []
        self._sent: dict[tuple[str, str], float] = {}     # bus key -> t of the sample sent last
        self._match: dict[tuple[str, str], str | None] = {}   # bus key -> its name if asked for (patterns do not change)
        self._sent_vib: dict[str, dict | None] = {}
        self._sent_view: dict[str, dict | None] = {}
        self._states_at = time.monotonic()
        self._frame_at = time.monotonic()

    def add_events(self, rows: list[dict]) -> None:
        for r in rows:
            if r["id"] > self.last_event_id and (not self.kinds or r["kind"] in self.kinds) \
                    and (not self.sources or r["source"] in self.sources):
                self._events.append(r)
                self.last_event_id = r["id"]

    def changed_samples(self) -> dict[str, list]:
        out = {}
        sent, match = self._sent, self._match
        for key, s in self.hub.bus.latest.items():   # (no await in this loop: the dict stays as it is)
            if sent.get(key) == s.t:
                continue
            name = match.get(key, False)
            if name is False:
                wanted = any(fnmatch.fnmatchcase(key[0], ps) and fnmatch.fnmatchcase(key[1], pq)
                             for ps, pq in self.patterns)
                name = match[key] = f"{key[0]}/{key[1]}" if wanted else None
            if name is not None:
                out[name] = [s.t, s.value, s.unit]
                sent[key] = s.t
        return out

    def frame(self) -> dict | None:
        """What changed since the last frame; None if nothing did and no heartbeat is due."""
        now = time.monotonic()
        f: dict[str, Any] = {}
        if self.patterns and (samples := self.changed_samples()):
            f["samples"] = samples
        for name in self.vibration:
            v = self.hub.vibration_view(name)
            last = self._sent_vib.get(name)
            if v is not None and (last is None or v["t_end"] != last["t_end"]):
                f.setdefault("vibration", {})[name] = changed_keys(last, v)[1]
                self._sent_vib[name] = v
        for name in self.views:
            v = self.hub.view(name)
            changed, d = changed_keys(self._sent_view.get(name), v)
            if changed or name not in self._sent_view:   # a lobe chart that did not move is not sent again
                f.setdefault("views", {})[name] = d
                self._sent_view[name] = v
        if self.states and now - self._states_at >= STATES_EVERY_S:
            f["status"] = self.hub.states()
            self._states_at = now
        if self._events:
            f["events"], self._events = self._events, []
        if not f and now - self._frame_at < HEARTBEAT_S:
            return None
        self._frame_at = now
        f["t"] = time.time()
        return f

    async def run(self, writer: asyncio.StreamWriter, write_timeout: float) -> str | None:
        """One task: a frame each period, written at once. While the client does not take
        it the task waits for the write to drain (at most ``write_timeout``) and makes no
        frame: what changed meanwhile comes in the next one, coalesced, so nothing piles up
        but what the transport holds (its high-water mark, and the frame that crossed it)."""
        transport = writer.transport
        try:
            while True:
                await asyncio.sleep(self.period)
                f = self.frame()
                if f is None:
                    continue
                writer.write(self.hub.encode_frame(f))
                if transport.get_write_buffer_size() > transport.get_write_buffer_limits()[1]:
                    try:
                        async with asyncio.timeout(write_timeout):
                            await writer.drain()
                    except TimeoutError:
                        reason = f"the client read nothing for {write_timeout:g} s"
                        self.hub.drop(self, reason)
                        return reason
        except ConnectionError:
            return None
        except Exception as e:   # a bug ends this subscription, said; not the daemon
            log.error("subscription_failed", error=repr(e))
            return f"internal error: {e!r}"
        finally:
            self.close()

    def close(self) -> None:
        self.hub.remove(self)
