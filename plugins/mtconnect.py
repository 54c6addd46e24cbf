"""CNC machines that report over MTConnect (read-only): an agent's HTTP interface.

``[machine.X.items]`` maps lathed's names to the agent's dataItemIds, checked against
``/probe`` at connect; then every observation from ``/sample`` in the agent's order, an
agent restart or buffer overrun recorded as ``mtconnect_gap``. It takes no commands.
Keys: docs/configuration.md; behaviour: docs/machines.md.
"""
from __future__ import annotations

import asyncio
import re
import time
from collections import Counter
from datetime import datetime
from xml.etree import ElementTree as ET

from lathed import hookimpl
from lathed.bus import Sample
from lathed.config import Section
from lathed.driver import Driver
from lathed.machine import AXIS, MachineModel

UNITS = {"spindle_rpm": "REVOLUTION/MINUTE", "spindle_load_pct": "PERCENT", "feed_mm_rev": "MILLIMETER/REVOLUTION",
         "spindle_override_pct": "PERCENT"}
AXIS_UNITS = {"mm": "MILLIMETER", "deg": "DEGREE"}
UNIT_TEXT = {"spindle_rpm": "r/min", "spindle_load_pct": "%", "feed_mm_rev": "mm/rev", "spindle_override_pct": "%"}
COUNT = 1000    # observations asked for at a time

# aiohttp, imported with the first machine of this type: the daemon loads every plugin at start,
# and aiohttp's import (its TLS contexts read the system's CA file) costs half a CPU-second
aiohttp = None


def _import_aiohttp() -> None:
    global aiohttp
    import aiohttp


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


def _epoch(stamp: str | None) -> float | None:
    """An MTConnect timestamp (ISO 8601, UTC) in seconds since the epoch."""
    if not stamp:
        return None
    try:
        return datetime.fromisoformat(stamp.replace("Z", "+00:00")).timestamp()
    except ValueError:
        return None


class AgentError(Exception):
    def __init__(self, code: str, text: str):
        super().__init__(f"{code}: {text}")
        self.code = code


class MTConnect(Driver):
    role = "machine"
    actions: tuple[str, ...] = ()      # read-only: MTConnect has no writes

    def __init__(self, name: str, section: Section):
        super().__init__(name, section)
        _import_aiohttp()
        self.kind = section.getstr("kind", "lathe", choices=("lathe", "mill", "grinder"))
        self.url = section.getstr("url").rstrip("/")
        if not re.match(r"^https?://[^/]+", self.url):
            raise section.error("url", f"{self.url!r} is not an http:// or https:// address of an agent")
        self.device = section.getstr("device", "")
        self.poll = section.getduration("poll", 0.1, minval=0.01, maxval=60)
        self.timeout = section.getduration("timeout", 1.0, minval=0.05, maxval=60)
        self.stale_after = section.getduration("stale_after", max(2.0, 3 * self.poll), minval=0.05)
        if self.stale_after <= self.poll:
            raise section.error("stale_after", f"must be longer than the poll ({self.poll:g} s)")
        items = section.getsection("items")
        self.items: dict[str, str] = {}          # dataItemId -> lathed name
        for name_ in items.keys():
            ident = items.getstr(name_)
            if ident in self.items:
                raise items.error(name_, f"item {ident!r} is already mapped to {self.items[ident]!r}")
            self.items[ident] = name_
        if not self.items:
            raise items.error(None, "no items mapped; add lathed_name = \"dataItemId\" lines")
        self.base = f"{self.url}/{self.device}" if self.device else self.url
        self.model = MachineModel(self.kind, self.stale_after, self._record)
        self.session: aiohttp.ClientSession | None = None
        self.kinds: dict[str, tuple[str, str]] = {}   # dataItemId -> (category, type), from /probe
        self.description: dict[str, str] = {}         # the device's Description in /probe
        self.instance: str | None = None
        self.next_seq: int | None = None
        self.values: dict[str, tuple[float, float]] = {}
        self.unavailable: set[str] = set()
        self.polls = 0
        self.observations = 0
        self.gaps = 0
        self.errors: Counter = Counter()

    def _record(self, kind: str, payload: dict) -> None:
        if self.ctx is not None:
            self.ctx.record(kind, payload)

    # -- the agent --------------------------------------------------------------------
    async def _get(self, path: str) -> ET.Element:
        try:
            async with asyncio.timeout(self.timeout + 1):
                async with self.session.get(f"{self.base}/{path}") as r:
                    body = await r.read()
        except asyncio.TimeoutError as e:
            self.errors["timeout"] += 1
            raise TimeoutError(f"no answer from the MTConnect agent at {self.url} within {self.timeout:g} s") from e
        except aiohttp.ClientError as e:
            self.errors["connection"] += 1
            raise ConnectionError(f"MTConnect agent at {self.url}: {e} (agent down or network?)") from e
        try:
            root = ET.fromstring(body)
        except ET.ParseError as e:
            self.errors["malformed"] += 1
            raise ValueError(f"{self.base}/{path} is not an MTConnect document ({e}; HTTP {r.status})") from None
        if _local(root.tag) == "MTConnectError":
            err = next((e for e in root.iter() if _local(e.tag) == "Error"), None)
            code = err.get("errorCode", "?") if err is not None else "?"
            raise AgentError(code, (err.text or "").strip() if err is not None else "")
        return root

    async def connect(self) -> None:
        self.session = aiohttp.ClientSession(timeout=aiohttp.ClientTimeout(total=self.timeout))
        try:
            probe = await self._get("probe")
        except AgentError as e:
            raise ConnectionError(f"the agent at {self.url} refused /probe ({e}): is device "
                                  f"{self.device!r} served there?") from None
        have = {d.get("id"): d for d in probe.iter() if _local(d.tag) == "DataItem"}
        self.description = self._description(probe)
        for ident, name in self.items.items():
            d = have.get(ident)
            if d is None:
                raise ConnectionError(f"{self.name}: items.{name} = {ident!r} is not a data item of "
                                      f"{self.device or 'the agent'} at {self.url}; it has: {', '.join(sorted(have))}")
            ax = AXIS.match(name)
            want = AXIS_UNITS[ax.group(2)] if ax else UNITS.get(name)
            if want and d.get("units") not in (None, want):
                raise ConnectionError(f"{self.name}: items.{name} = {ident!r} is in {d.get('units')}, "
                                      f"not {want}: map an item in {want}")
            self.kinds[ident] = (d.get("category", ""), d.get("type", ""))
        if self.next_seq is None:
            await self._current()
        # else a reconnect: the next sample goes on from the last sequence read, so the outage
        # loses nothing the agent still buffers
        self.model.link_up()

    def _description(self, probe: ET.Element) -> dict[str, str]:
        """The device's Description attributes (manufacturer, model, serialNumber) in
        [identification]'s keys: the device named by ``device``, else the only one."""
        devices = [d for group in probe.iter() if _local(group.tag) == "Devices"
                   for d in group if _local(d.tag) == "Device"]
        if self.device:
            devices = [d for d in devices if self.device in (d.get("name"), d.get("uuid"), d.get("id"))]
        if len(devices) != 1:
            return {}
        desc = next((e for e in devices[0] if _local(e.tag) == "Description"), None)
        if desc is None:
            return {}
        keys = {"manufacturer": "manufacturer", "model": "model", "serialNumber": "serial_number"}
        return {ours: desc.get(theirs).strip() for theirs, ours in keys.items() if desc.get(theirs)}

    async def identify(self) -> dict[str, str] | None:
        """The agent's Description of the device, read at connect (/probe)."""
        return self.description or None

    async def close(self) -> None:
        self.model.link_down()
        if self.session is not None:
            await self.session.close()
            self.session = None

    async def _current(self) -> None:
        doc = await self._get("current")
        h = self._header(doc)
        self.instance, self.next_seq = h.get("instanceId", ""), int(h.get("nextSequence"))
        self._publish(doc, h)

    def _header(self, doc: ET.Element) -> ET.Element:
        h = next((e for e in doc.iter() if _local(e.tag) == "Header"), None)
        if h is None or not (h.get("nextSequence") or "").isdigit():
            raise ValueError(f"{self.url}: an MTConnect document without a Header's nextSequence")
        return h

    async def run(self) -> None:
        while True:
            try:
                doc = await self._get(f"sample?from={self.next_seq}&count={COUNT}")
            except AgentError as e:
                if e.code != "OUT_OF_RANGE":
                    raise
                self._gap(f"observations from sequence {self.next_seq} left the agent's buffer before "
                          "they were read")
                await self._current()
                continue
            h = self._header(doc)
            instance, nxt = h.get("instanceId", ""), int(h.get("nextSequence"))
            if instance != self.instance:
                self._gap(f"the agent restarted (instanceId {self.instance} -> {instance}): what it "
                          "observed after the last read and before its restart is gone")
                await self._current()
                continue
            self._publish(doc, h)
            self.next_seq = nxt
            self.polls += 1
            if (h.get("lastSequence") or "").isdigit() and int(h.get("lastSequence")) >= nxt:
                continue        # more than COUNT new: ask again at once
            await asyncio.sleep(self.poll)

    def _gap(self, why: str) -> None:
        self.gaps += 1
        self.errors["gap"] += 1
        payload = {"machine": self.name, "agent": self.url, "why": why}
        self.ctx.log.warning("mtconnect_gap", **payload)
        self._record("mtconnect_gap", payload)

    # -- observations -------------------------------------------------------------------
    def _publish(self, doc: ET.Element, h: ET.Element) -> None:
        now = time.time()
        created = _epoch(h.get("creationTime"))
        obs = sorted(((int(e.get("sequence", 0)), e) for e in doc.iter() if e.get("dataItemId") in self.items),
                     key=lambda p: p[0])
        seen = set()
        for _, e in obs:
            ident = e.get("dataItemId")
            name = self.items[ident]
            seen.add(name)
            v = self._value(ident, e)
            if v is None:
                self.unavailable.add(name)     # UNAVAILABLE: the last value goes stale
                continue
            self.unavailable.discard(name)
            self.observations += 1
            # the arrival, less how long before the document the agent observed it: the
            # spacing of a batch's observations is the agent's, the clock this PC's
            ts = _epoch(e.get("timestamp"))
            t = now - max(0.0, created - ts) if ts is not None and created is not None else now
            self._publish_one(name, v, t)
        # an agent reports changes only: a value it did not observe again still holds now, as
        # a Modbus register read again does (the analyzers and the model see it every poll)
        for name, (v, _) in list(self.values.items()):
            if name not in seen and name not in self.unavailable:
                self._publish_one(name, v, now)
        self.mark_data()

    def _publish_one(self, name: str, v: float, t: float) -> None:
        if self.ctx.bus.publish(Sample(self.name, name, v, UNIT_TEXT.get(name, ""), t)):
            self.values[name] = (v, t)
            self.model.reading(name, v, t)

    def _value(self, ident: str, e: ET.Element) -> float | None:
        category, typ = self.kinds.get(ident, ("", ""))
        if category == "CONDITION":
            level = _local(e.tag)
            if level == "Unavailable":
                return None
            if level == "Fault":
                code = e.get("nativeCode", "")
                return float(code) if code.isdigit() and int(code) else 1.0
            return 0.0
        text = (e.text or "").strip()
        if text == "UNAVAILABLE" or not text:
            return None
        if typ == "EXECUTION":
            return 1.0 if text == "ACTIVE" else 0.0
        if typ == "PROGRAM":
            digits = re.sub(r"\D", "", text)
            return float(digits) if digits else None
        try:
            return float(text)
        except ValueError:
            self.errors["unreadable"] += 1
            return None

    def quantities(self) -> frozenset[str]:
        return frozenset(self.items.values())

    def current(self, action: str) -> float | None:
        """The spindle's speed as the agent last reported it (shown by status; no action takes it)."""
        v = self.values.get("spindle_rpm") if action == "spindle_rpm" else None
        if v is None or self.session is None or time.time() - v[1] > self.stale_after:
            return None
        return v[0]

    def status(self) -> dict:
        now = time.time()
        values = {n: {"value": v, "age_s": round(now - t, 3), "stale": self.session is None or
                      now - t > self.stale_after} for n, (v, t) in self.values.items()}
        return {"spindle_rpm": self.model.live("spindle_rpm"), "machine_state": self.model.state(),
                "model": self.model.snapshot(), "values": values, "polls": self.polls,
                "observations": self.observations,
                "link": {"transport": "mtconnect", "where": self.url, "instance": self.instance,
                         "next_sequence": self.next_seq, "gaps": self.gaps, "errors": dict(self.errors)}}


@hookimpl
def lathed_driver_types():
    return {"mtconnect": MTConnect}
