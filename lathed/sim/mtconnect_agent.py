"""The simulated lathe as an MTConnect agent: a real HTTP server (aiohttp) on loopback
answering ``/probe``, ``/current`` and ``/sample?from=N&count=M`` as the standard's agents
do (MTConnect 1.3 documents; a fixed ring buffer of observations with sequence numbers,
``OUT_OF_RANGE`` for a ``from`` that has left it).

Haas, Okuma, Mazak and DMG Mori controls ship such an agent, read-only: the daemon's
``mtconnect`` driver talks to this one as to theirs.  Only values that change are
observed, as an adapter sends them.
"""
from __future__ import annotations

import itertools
import time
from collections import deque
from datetime import datetime, timezone
from xml.sax.saxutils import quoteattr

from aiohttp import web

STREAMS_NS = "urn:mtconnect.org:MTConnectStreams:1.3"
DEVICES_NS = "urn:mtconnect.org:MTConnectDevices:1.3"
ERROR_NS = "urn:mtconnect.org:MTConnectError:1.3"
BUFFER = 4096       # observations kept: a client further behind gets OUT_OF_RANGE

# id: (the simulator's register, category, type, subType, units, component)
LATHE_ITEMS: dict[str, tuple[str | None, str, str, str | None, str | None, str]] = {
    "avail":      (None, "EVENT", "AVAILABILITY", None, None, "Device"),
    "execution":  ("program_state", "EVENT", "EXECUTION", None, None, "Path"),
    "program":    ("program_number", "EVENT", "PROGRAM", None, None, "Path"),
    "part_count": ("part_count", "EVENT", "PART_COUNT", "ALL", None, "Path"),
    "tool":       ("tool_number", "EVENT", "TOOL_NUMBER", None, None, "Path"),
    "feed":       ("feed_mm_rev", "SAMPLE", "PATH_FEEDRATE_PER_REVOLUTION", "PROGRAMMED",
                   "MILLIMETER/REVOLUTION", "Path"),
    "Sspeed":     ("spindle_rpm", "SAMPLE", "ROTARY_VELOCITY", "ACTUAL", "REVOLUTION/MINUTE", "Rotary"),
    "Sload":      ("spindle_load_pct", "SAMPLE", "LOAD", None, "PERCENT", "Rotary"),
    "Sovr":       ("spindle_override_pct", "EVENT", "ROTARY_VELOCITY_OVERRIDE", None, None, "Rotary"),
    "Xpos":       ("x_mm", "SAMPLE", "POSITION", "ACTUAL", "MILLIMETER", "Linear"),
    "system":     ("alarm_code", "CONDITION", "SYSTEM", None, None, "Controller"),
}
EXECUTION = {0: "READY", 1: "ACTIVE", 2: "STOPPED"}


def _camel(t: str) -> str:
    return "".join(w.capitalize() for w in t.split("_"))


def _now_iso(t: float) -> str:
    return datetime.fromtimestamp(t, timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


class MTConnectAgent:
    def __init__(self, host: str, port: int, device: str = "SimLathe", items=None,
                 serial_number: str = "SIM-LATHE-0001"):
        self.host, self.port, self.device = host, port, device
        # the device's Description, as a real agent's /probe gives it: what the daemon identifies it by
        self.description = {"manufacturer": "lathed simulator", "model": "MC4200-class lathe (simulated)",
                            "serialNumber": serial_number}
        self.items = items or LATHE_ITEMS
        self.instance_id = int(time.time())
        self._seq = itertools.count(1)
        self.buffer: deque[tuple[int, str, float, str, str | None]] = deque(maxlen=BUFFER)  # seq, id, t, value, code
        self.latest: dict[str, tuple[int, str, float, str, str | None]] = {}
        self.next_seq = 1
        self._runner: web.AppRunner | None = None
        self.up = False
        self._observe("avail", "AVAILABLE")

    # -- values ----------------------------------------------------------------
    def _observe(self, item: str, value: str, code: str | None = None) -> None:
        old = self.latest.get(item)
        if old is not None and (old[3], old[4]) == (value, code):
            return
        obs = (next(self._seq), item, time.time(), value, code)
        self.buffer.append(obs)
        self.latest[item] = obs
        self.next_seq = obs[0] + 1

    def update(self, registers: dict[str, float]) -> None:
        """The simulated controller's values, as its adapter would report them."""
        for item, (reg, category, typ, *_ ) in self.items.items():
            if reg is None or reg not in registers:
                continue
            v = registers[reg]
            if typ == "EXECUTION":
                self._observe(item, EXECUTION.get(int(v), "READY"))
            elif typ == "PROGRAM":
                self._observe(item, f"O{int(v):04d}")
            elif category == "CONDITION":
                self._observe(item, "Fault" if int(v) else "Normal", str(int(v)) if int(v) else None)
            elif typ in ("PART_COUNT", "TOOL_NUMBER"):
                self._observe(item, str(int(v)))
            else:
                self._observe(item, f"{v:.4f}")

    # -- documents -----------------------------------------------------------------
    def _header(self, ns_extra: str = "") -> str:
        first = self.buffer[0][0] if self.buffer else self.next_seq
        return (f'<Header creationTime="{_now_iso(time.time())}" sender="lathed-sim" '
                f'instanceId="{self.instance_id}" version="1.3.0" bufferSize="{BUFFER}" '
                f'nextSequence="{self.next_seq}" firstSequence="{first}" lastSequence="{self.next_seq - 1}"'
                f'{ns_extra}/>')

    def probe(self) -> str:
        comps: dict[str, list[str]] = {}
        for item, (_reg, category, typ, sub, units, comp) in self.items.items():
            attrs = f'id="{item}" category="{category}" type="{typ}"'
            attrs += f' subType="{sub}"' if sub else ""
            attrs += f' units="{units}"' if units else ""
            comps.setdefault(comp, []).append(f"<DataItem {attrs}/>")
        body = "".join(f'<Components><{c} id="{c.lower()}1" name="{c}"><DataItems>{"".join(d)}</DataItems>'
                       f"</{c}></Components>" for c, d in comps.items())
        return (f'<?xml version="1.0" encoding="UTF-8"?><MTConnectDevices xmlns="{DEVICES_NS}">'
                f'{self._header()}<Devices><Device id="d1" name="{self.device}" uuid="sim-lathe-1">'
                f'<Description {" ".join(f"{k}={quoteattr(v)}" for k, v in self.description.items())}/>'
                f"{body}</Device></Devices></MTConnectDevices>")

    def streams(self, observations) -> str:
        by_comp: dict[str, dict[str, list[str]]] = {}
        for seq, item, t, value, code in observations:
            _reg, category, typ, sub, _units, comp = self.items[item]
            attrs = f'dataItemId="{item}" timestamp="{_now_iso(t)}" sequence="{seq}"'
            attrs += f' subType="{sub}"' if sub else ""
            if category == "CONDITION":
                attrs += f' type="{typ}"' + (f" nativeCode={quoteattr(code)}" if code else "")
                el = f"<{value} {attrs}/>"
                group = "Condition"
            else:
                esc = value.replace("&", "&amp;").replace("<", "&lt;")
                el = f"<{_camel(typ)} {attrs}>{esc}</{_camel(typ)}>"
                group = "Samples" if category == "SAMPLE" else "Events"
            by_comp.setdefault(comp, {}).setdefault(group, []).append(el)
        body = "".join(
            f'<ComponentStream component="{c}" name="{c}" componentId="{c.lower()}1">'
            + "".join(f"<{g}>{''.join(els)}</{g}>" for g, els in groups.items()) + "</ComponentStream>"
            for c, groups in by_comp.items())
        return (f'<?xml version="1.0" encoding="UTF-8"?><MTConnectStreams xmlns="{STREAMS_NS}">'
                f'{self._header()}<Streams><DeviceStream name="{self.device}" uuid="sim-lathe-1">'
                f"{body}</DeviceStream></Streams></MTConnectStreams>")

    def error(self, code: str, text: str) -> str:
        return (f'<?xml version="1.0" encoding="UTF-8"?><MTConnectError xmlns="{ERROR_NS}">{self._header()}'
                f'<Errors><Error errorCode="{code}">{text}</Error></Errors></MTConnectError>')

    # -- HTTP --------------------------------------------------------------------------
    def _xml(self, text: str, status: int = 200) -> web.Response:
        return web.Response(text=text, status=status, content_type="text/xml")

    async def _probe(self, request: web.Request) -> web.Response:
        return self._xml(self.probe())

    async def _current(self, request: web.Request) -> web.Response:
        return self._xml(self.streams(sorted(self.latest.values())))

    async def _sample(self, request: web.Request) -> web.Response:
        try:
            first = self.buffer[0][0] if self.buffer else self.next_seq
            start = int(request.query.get("from", first))
            count = int(request.query.get("count", 100))
        except ValueError:
            return self._xml(self.error("INVALID_REQUEST", "'from' and 'count' must be integers"), 400)
        if not first <= start <= self.next_seq:
            return self._xml(self.error("OUT_OF_RANGE", f"'from' must be within {first} and {self.next_seq}"),
                             404)
        obs = [o for o in self.buffer if o[0] >= start][:max(1, count)]
        doc = self.streams(obs)
        if obs:    # the next sequence to ask for: after the last one returned
            doc = doc.replace(f'nextSequence="{self.next_seq}"', f'nextSequence="{obs[-1][0] + 1}"', 1)
        return self._xml(doc)

    async def start(self) -> None:
        app = web.Application()
        for prefix in ("", f"/{self.device}"):
            app.router.add_get(f"{prefix}/probe", self._probe)
            app.router.add_get(f"{prefix}/current", self._current)
            app.router.add_get(f"{prefix}/sample", self._sample)
        self._runner = web.AppRunner(app, access_log=None)
        await self._runner.setup()
        site = web.TCPSite(self._runner, self.host, self.port)
        await site.start()
        if not self.port:
            self.port = self._runner.addresses[0][1]
        self.up = True

    async def stop(self) -> None:
        self.up = False
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
