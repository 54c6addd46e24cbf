"""lathed-opcua's address space: the daemon's line as OPC 40501 and the Machinery model lay it
out (the browse paths, types and meanings: docs/opcua.md).

Objects/Machines (Machinery's folder) holds every machine of the daemon's status
(lathed.opcua.machines); Objects/Sensors lathed's own sensors. The daemon's frames are routed
here: a sample to its variable, the status to the machine states and the suppression mode, a
record to an event on the machine's Messages and on the Server object.

Values carry the sample's own time as SourceTimestamp. While the daemon is unreachable every
live value is BadNoCommunication; while a machine's driver is not connected its values are
UncertainNoCommunicationLastUsableValue; a value the daemon has none of now (the chatter
frequency while there is no chatter) is BadNoDataAvailable, as is a mandatory 40501 variable
the machine does not report (FeedOverride without a feed_override_pct register).
"""
from __future__ import annotations

import asyncio
import json
import re
import socket
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Any
from urllib.parse import quote

import structlog
from asyncua import Node, Server, ua

from lathed.opcua import nodesets as N
from lathed.opcua.machines import MT, Machine, build, eu_information, variable, write

log = structlog.get_logger("lathed.opcua")

NAMESPACE = "urn:lathed:opcua"

# a machine tool's quantity -> (path under the machine, browse-name model (None: lathed's), variant type)
TOOL = {
    "spindle_rpm": ("Monitoring/Spindle/RotationalSpeed", None, ua.VariantType.Double),
    "spindle_rpm_cmd": ("Monitoring/Spindle/CommandedSpeed", None, ua.VariantType.Double),
    "spindle_load_pct": ("Monitoring/Spindle/Load", None, ua.VariantType.Double),
    "spindle_override_pct": ("Monitoring/Spindle/Override", MT, ua.VariantType.Double),
    "feed_mm_rev": ("Monitoring/Channel1/Feed", None, ua.VariantType.Double),
    "feed_override_pct": ("Monitoring/Channel1/FeedOverride", MT, ua.VariantType.Double),
    "program_number": ("Production/ActiveProgram/Name", MT, ua.VariantType.String),
    "program": ("Production/ActiveProgram/Name", MT, ua.VariantType.String),
    "part_count": ("Production/PartCount", None, ua.VariantType.UInt32),
    "cycle_time_s": ("Production/CycleTime", None, ua.VariantType.Double),
}
AXIS = re.compile(r"^([a-z]|j\d)_(mm|deg)$")
# program_state (0 idle, 1 running, 2 alarm) -> 40501 ChannelState (Active 0, Interrupted 1, Reset 2),
# the active program's state (ProductionProgramStateMachineType)
CHANNEL_STATE = {0: 2, 1: 0, 2: 1}
PROGRAM_STATE = {0: "Ended", 1: "Running", 2: "Interrupted"}
# ChannelMode and MachineOperationMode: Automatic while a program runs, else Other (lathed reads
# no mode switch): (while running, otherwise)
CHANNEL_MODE = (0, 7)
OPERATION_MODE = (1, 5)
# the machine model's state -> Machinery's MachineryItemState
ITEM_STATE = {"running": "Executing", "idle": "NotExecuting", "alarm": "OutOfService", "disconnected": "NotAvailable"}
# an analyzer's quantities, by its plugin: (object, {quantity: browse name})
D, B = ua.VariantType.Double, ua.VariantType.Boolean
ANALYZER = {
    "chatter": ("Chatter", {"chatter_index": ("ChatterIndex", D), "chatter_threshold": ("ChatterThreshold", D),
                            "chatter_frequency_hz": ("ChatterFrequency", D), "chatter_alarm": ("ChatterAlarm", B),
                            "cutting": ("Cutting", B)}),
    "thermal": ("Thermal", {"predicted_growth_um": ("ThermalGrowth", D), "compensation_um": ("Compensation", D)}),
}
SUPPRESSION_MODES = ("auto", "manual", "off")

# records that become OPC UA events (the machine's Messages, and the Server object), with their
# severity (1..1000); the others stay in the daemon's event log
SEVERITY = {"chatter_alarm": 800, "chatter_cleared": 300, "suppression_action": 500,
            "suppression_advice": 700,   # the speed is held and the chatter goes on: the operator must act
            "suppression_proposed": 500, "suppression_mode": 300, "compensation": 200, "thermal_touchoff": 300,
            "thermal_refit": 200, "part_abnormal": 700, "part_unobserved": 700, "part_inspected": 200, "alarm_raised": 800,
            "alarm_cleared": 300, "command_refused": 700, "command_failed": 800, "implausible_value": 600}

GOOD = ua.StatusCodes.Good
NO_DAEMON = ua.StatusCodes.BadNoCommunication
NO_MACHINE = ua.StatusCodes.UncertainNoCommunicationLastUsableValue
NO_DATA = ua.StatusCodes.BadNoDataAvailable
WAITING = ua.StatusCodes.BadWaitingForInitialData


def _time(t: float | None) -> datetime:
    return datetime.fromtimestamp(t, timezone.utc) if t is not None else datetime.now(timezone.utc)


@dataclass
class Var:
    node: Node
    vtype: ua.VariantType
    machine: str | None          # whose driver state decides its quality (None: the daemon's link only)
    live: bool = True            # False: from the config (the nameplate), good while the server runs
    value: Any = None
    t: float | None = None
    status: int = field(default=NO_DAEMON)


class Space:
    def __init__(self, server: Server, idx: int, types: N.Types):
        self.server, self.idx, self.types = server, idx, types
        self.vars: dict[str, Var] = {}            # path ("Machines/lathe/Monitoring/Spindle/Override") -> variable
        self.objects: dict[str, Node] = {}        # path -> object or folder
        self.machines: dict[str, dict] = {}       # name -> its last status
        self.built: dict[str, Machine] = {}
        self.analyzers: dict[str, dict] = {}
        self.sensors: set[str] = set()
        self.writable: dict[ua.NodeId, str] = {}  # suppression Mode node -> its analyzer
        self.can_write = False
        self.connected = False
        self.quality: dict[str, int] = {}         # machine -> GOOD or NO_MACHINE
        self.production: dict[str, dict] = {}     # machine -> what its prognosis is made of
        self.last_event_id: int | None = None
        self.events_sent = 0
        self.failing: dict[str, str] = {}         # what -> the error last logged for it
        self.cell = socket.gethostname()
        self.ready = asyncio.Event()              # the daemon's first status is in

    # -- building ---------------------------------------------------------------------
    async def build(self, writable: bool) -> None:
        self.can_write = writable
        self.objects["Machines"] = self.types.node(N.MACHINES_FOLDER)
        self.objects["Sensors"] = await self.server.nodes.objects.add_folder(self._id("Sensors"), self._q("Sensors"))
        self.etype = await self.server.create_custom_event_type(
            self.idx, "RecordEventType", self.types.id(N.NOTIFICATION_EVENT_TYPE),
            [("RecordId", ua.VariantType.Int64), ("Payload", ua.VariantType.String)])
        self.server_events = await self._generator(ua.ObjectIds.Server)
        self.machine_events: dict[str, Any] = {}
        t = self.types
        self.states = {
            ("item", s): await t.state(N.MACHINERY_ITEM_STATE_TYPE, s, N.MACHINERY) for s in ITEM_STATE.values()}
        self.states.update({("program", s): await t.state(N.PRODUCTION_PROGRAM_STATE_MACHINE_TYPE, s, MT)
                            for s in PROGRAM_STATE.values()})

    async def _generator(self, emitting):
        gen = await self.server.get_event_generator(self.etype, emitting)
        # 40501's Identifier has no default value, and asyncua leaves such a property out of the event
        gen.event.add_property("Identifier", "", ua.VariantType.String)
        return gen

    def _id(self, path: str) -> ua.NodeId:
        return ua.NodeId(path.replace("/", "."), self.idx)

    def _q(self, name: str) -> ua.QualifiedName:
        return ua.QualifiedName(name, self.idx)

    async def _machine(self, m: dict) -> Machine:
        name = m["name"]
        mach = self.built.get(name)
        if mach is None:
            mach = self.built[name] = await build(self.types, self.objects["Machines"], self.idx, name,
                                                  m.get("kind") or "machine")
            base = f"Machines/{name}"
            self.objects[base] = mach.node
            mon = await mach.child((mach.monitoring_uri, "Monitoring"))
            self.objects[f"{base}/Monitoring"] = mon
            if mach.tool:
                for path in ("Production", "Production/ActiveProgram"):
                    self.objects[f"{base}/{path}"] = await mach.child(*((MT, p) for p in path.split("/")))
            gen = await self._generator(mach.events)
            gen.event.SourceNode, gen.event.SourceName = mach.node.nodeid, name
            self.machine_events[name] = gen
            await self._state_vars(mach)
        ident = m.get("identification") or {}
        if name not in self.machines or ident != self.machines[name].get("identification"):  # new, or reloaded
            uri = product_instance_uri(self.cell, name, ident)
            await mach.identification(ident, uri)
        self.machines[name] = m
        return mach

    async def _state_vars(self, mach: Machine) -> None:
        """The state machines' current state (and its Id, Number) as variables of the machine."""
        base, name = f"Machines/{mach.name}", mach.name

        def ua0(n: str) -> ua.QualifiedName:
            return ua.QualifiedName(n, 0)
        cur = await mach.item_state.get_child(ua0("CurrentState"))
        self._track(f"{base}/ItemState", cur, ua.VariantType.LocalizedText, None)
        self._track(f"{base}/ItemState/Id", await cur.get_child(ua0("Id")), ua.VariantType.NodeId, None)
        if not mach.tool:
            return
        mon = ((MT, "Monitoring"),)
        self._track(f"{base}/Monitoring/MachineTool/OperationMode",
                    await mach.child(*mon, (MT, "MachineTool"), (MT, "OperationMode")), ua.VariantType.Int32, name)
        cur = await mach.child((MT, "Production"), (MT, "ActiveProgram"), (MT, "State"), (N.UA, "CurrentState"))
        self._track(f"{base}/Production/ActiveProgram/State", cur, ua.VariantType.LocalizedText, name)
        self._track(f"{base}/Production/ActiveProgram/State/Id", await cur.get_child(ua0("Id")),
                    ua.VariantType.NodeId, name)
        self._track(f"{base}/Production/ActiveProgram/State/Number", await cur.get_child(ua0("Number")),
                    ua.VariantType.UInt32, name)
        self._track(f"{base}/Production/ActiveProgram/Name",
                    await mach.child((MT, "Production"), (MT, "ActiveProgram"), (MT, "Name")),
                    ua.VariantType.String, name)

    def _track(self, path: str, node: Node, vtype: ua.VariantType, machine: str | None, live: bool = True) -> Var:
        v = self.vars[path] = Var(node, vtype, machine, live)
        return v

    async def _object(self, path: str) -> Node:
        """The object at ``path``, made (with its parents) if new: a 40501 Spindle or Channel1 of
        a machine tool, else one of lathed's (Axes, Values, Chatter...)."""
        node = self.objects.get(path)
        if node is None:
            parent_path, _, name = path.rpartition("/")
            parent = await self._object(parent_path)
            parts = path.split("/")
            if parts[0] == "Machines":
                mach = self.built[parts[1]]
                if mach.tool and len(parts) == 4 and name in ("Spindle", "Channel1"):
                    node = await mach.element(name)
                    await self._element_vars(mach, path, node)
                else:
                    node = await mach.folder(parent, *parts[2:])
            elif len(parts) == 2:     # a sensor's object
                node = await parent.add_object(self._id(path), self._q(name))
            else:
                raise KeyError(path)
            self.objects[path] = node
        return node

    async def _element_vars(self, mach: Machine, path: str, node: Node) -> None:
        """A new monitored element's mandatory variables, waiting for their first value."""
        names = {"Spindle": (("IsRotating", ua.VariantType.Boolean),),
                 "Channel1": (("ChannelState", ua.VariantType.Int32), ("ChannelMode", ua.VariantType.Int32),
                              ("FeedOverride", ua.VariantType.Double))}[path.rsplit("/", 1)[1]]
        for name, vtype in names:
            v = self._track(f"{path}/{name}", await node.get_child(mach.q(MT, name)), vtype, mach.name)
            # no feed override register: the 40501 variable is there, with no data
            status = NO_DATA if name == "FeedOverride" else WAITING
            await self._set(v, None, None, status)

    async def _var(self, path: str, vtype: ua.VariantType, unit: str | None, machine: str | None,
                   std: str | None = None, writable: bool = False) -> Var:
        """The variable at ``path``: a standard one (``std``: its model's URI) found or added,
        else one of lathed's, made."""
        v = self.vars.get(path)
        if v is not None:
            return v
        parent_path, _, name = path.rpartition("/")
        parent = await self._object(parent_path)
        if std is not None:
            mach = self.built[path.split("/")[1]]
            if name == "Override":
                node = await mach.override(parent)
            else:
                node = await parent.get_child(mach.q(std, name))
        elif unit and vtype == ua.VariantType.Double:
            node = await variable(self.server, parent, self.types.node(N.ANALOG_UNIT_TYPE), self._id(path),
                                  self._q(name), ua.ObjectIds.Double)
            await write(self.server, await node.get_child(ua.QualifiedName("EngineeringUnits", 0)),
                        eu_information(unit), ua.VariantType.ExtensionObject)
        else:
            node = await parent.add_variable(self._id(path), self._q(name),
                                             ua.Variant(ua.get_default_value(vtype), vtype),
                                             varianttype=vtype, datatype=ua.NodeId(getattr(ua.ObjectIds, vtype.name)))
        if writable:
            await node.set_writable(True)
        await asyncio.sleep(0)     # the address space's calls do not yield: let clients in between
        return self._track(path, node, vtype, machine)

    # -- applying what the daemon pushes ------------------------------------------------
    async def apply(self, frame: dict) -> None:
        """One pushed frame; a value that cannot be shown is said once (log) and the rest goes on."""
        if frame.get("status"):
            await self._guarded("status", self.apply_status(frame["status"]))
        for key, (t, value, unit) in (frame.get("samples") or {}).items():
            await self._guarded(key, self.apply_sample(key, t, value, unit))
            await asyncio.sleep(0)   # each value fans out to every monitored item: the link reads between
        for e in sorted(frame.get("events") or [], key=lambda e: e["id"]):
            await self._guarded(f"event {e.get('kind')}", self.apply_event(e))

    async def _guarded(self, what: str, step) -> None:
        try:
            await step
            self.failing.pop(what, None)
        except Exception as e:
            if self.failing.get(what) != repr(e):
                self.failing[what] = repr(e)
                log.exception("value_not_shown", what=what, error=repr(e))

    async def apply_status(self, status: dict) -> None:
        for m in status.get("machines", []):
            mach = await self._machine(m)
            quality = GOOD if m.get("state") == "connected" else NO_MACHINE
            if self.quality.get(m["name"]) != quality:
                self.quality[m["name"]] = quality
                for v in self.vars.values():
                    if v.machine == m["name"] and v.value is not None:
                        await self._set(v, v.value, v.t, quality)
            state = m.get("machine_state") or ("disconnected" if m.get("state") != "connected" else None)
            if state in ITEM_STATE:
                await self._state(f"Machines/{mach.name}/ItemState", ("item", ITEM_STATE[state]), None, GOOD)
        if "sensors" in status:
            self.sensors = {s["name"] for s in status["sensors"]}
        for a in status.get("analyzers", []):
            self.analyzers[a["name"]] = a
            if a.get("plugin") == "suppression" and a.get("machine") in self.machines:
                await self._suppression(a)

    async def _state(self, path: str, state: tuple[str, str], t: float | None, status: int) -> None:
        """A state machine's CurrentState: its name, Id and (where it has one) Number."""
        nodeid, number = self.states[state]
        await self._set(self.vars[path], ua.LocalizedText(state[1]), t, status)
        await self._set(self.vars[f"{path}/Id"], nodeid, t, status)
        if f"{path}/Number" in self.vars and number is not None:
            await self._set(self.vars[f"{path}/Number"], int(number), t, status)

    async def _suppression(self, a: dict) -> None:
        base = f"Machines/{a['machine']}/Monitoring/Suppression"
        if self.vars.get(f"{base}/Mode") is None:
            v = await self._var(f"{base}/Mode", ua.VariantType.String, None, None, writable=self.can_write)
            self.writable[v.node.nodeid] = a["name"]
        for name, key, vtype in (("Mode", "mode", ua.VariantType.String),
                                 ("Strategy", "strategy", ua.VariantType.String),
                                 ("Actions", "actions", ua.VariantType.UInt32)):
            if a.get(key) is not None:
                v = await self._var(f"{base}/{name}", vtype, None, None)
                await self._set(v, a[key], None, GOOD)

    def _route(self, src: str, q: str, value: Any) -> tuple[str, ua.VariantType, str | None, str | None] | None:
        """Where a sample goes: (path, variant type, machine whose state qualifies it, standard model)."""
        if src in self.machines:
            base, mach = f"Machines/{src}", self.built[src]
            if mach.tool and q in TOOL:
                path, std, vtype = TOOL[q]
                return f"{base}/{path}", vtype, src, std
            if (m := AXIS.match(q)) is not None:
                return f"{base}/Monitoring/Axes/{m.group(1).upper()}", ua.VariantType.Double, src, None
            return f"{base}/Monitoring/Values/{q}", _vtype(value), src, None
        a = self.analyzers.get(src)
        if a is not None and a.get("machine") in self.machines:
            folder, names = ANALYZER.get(a.get("plugin"), (src, {}))
            name, vtype = names.get(q, (q, _vtype(value)))
            return f"Machines/{a['machine']}/Monitoring/{folder}/{name}", vtype, None, None
        if src in self.sensors:
            return f"Sensors/{src}/{q}", _vtype(value), src, None
        return None

    async def apply_sample(self, key: str, t: float, value: Any, unit: str) -> None:
        src, _, q = key.partition("/")
        mach = self.built.get(src) if src in self.machines else None
        if mach is not None and mach.tool and q == "program_state":
            return await self._program_state(mach, t, value)
        where = self._route(src, q, value)
        if where is None:   # a source not in the status yet (or an analyzer of no machine): its next value will do
            return
        path, vtype, machine, std = where
        v = await self._var(path, vtype, unit, machine if machine in self.machines else None, std)
        await self._set(v, _convert(value, v.vtype), t, self.quality.get(machine, GOOD))
        if mach is not None and mach.tool:
            if q == "spindle_rpm" and isinstance(value, (int, float)):
                await self._set(self.vars[f"Machines/{src}/Monitoring/Spindle/IsRotating"], abs(value) > 0.5, t,
                                self.quality.get(src, GOOD))
            if q in ("part_count", "cycle_time_s", "program", "program_number"):
                await self._prognosis(mach, q, t, value)

    async def _program_state(self, mach: Machine, t: float, value: Any) -> None:
        base, quality = f"Machines/{mach.name}", self.quality.get(mach.name, GOOD)
        state = int(value) if isinstance(value, (int, float)) else -1
        await self._object(f"{base}/Monitoring/Channel1")
        channel = f"{base}/Monitoring/Channel1"
        await self._set(self.vars[f"{channel}/ChannelState"], CHANNEL_STATE.get(state, 1), t, quality)
        running = state == 1
        await self._set(self.vars[f"{channel}/ChannelMode"], CHANNEL_MODE[0 if running else 1], t, quality)
        await self._set(self.vars[f"{base}/Monitoring/MachineTool/OperationMode"],
                        OPERATION_MODE[0 if running else 1], t, quality)
        await self._state(f"{base}/Production/ActiveProgram/State", ("program", PROGRAM_STATE.get(state, "Interrupted")),
                          t, quality)
        await self._prognosis(mach, "program_state", t, state)

    async def _prognosis(self, mach: Machine, q: str, t: float, value: Any) -> None:
        """The next part's unload: the last part's end plus the last cycle time, while a program runs."""
        p = self.production.setdefault(mach.name, {})
        if q == "part_count":
            if p.get("count") is not None and value != p["count"]:
                p["part_t"] = t
            p["count"] = value
        elif q == "cycle_time_s":
            p["cycle"] = value
        elif q == "program_state":
            p["running"] = value == 1
        else:
            p["program"] = _convert(value, ua.VariantType.String)
        cycle = p.get("cycle")
        ok = p.get("running") and p.get("part_t") is not None and isinstance(cycle, (int, float)) and cycle > 0
        await mach.set_prognosis(_time(p["part_t"] + cycle) if ok else None,
                                 f"program {p['program']}" if p.get("program") else None)

    async def _set(self, v: Var, value: Any, t: float | None, status: int) -> None:
        v.value, v.t, v.status = value, t, status
        if value is None and status == GOOD:    # the source has none now (no chatter: no chatter frequency)
            status = NO_DATA
        dv = ua.DataValue(Value=ua.Variant(ua.get_default_value(v.vtype) if value is None else value, v.vtype),
                          StatusCode=ua.StatusCode(status), SourceTimestamp=_time(t),
                          ServerTimestamp=datetime.now(timezone.utc))
        # to the address space itself: Server.write_attribute_value drops the status it answers
        res = await self.server.iserver.aspace.write_attribute_value(v.node.nodeid, ua.AttributeIds.Value, dv)
        res.check()     # e.g. BadTypeMismatch: a value of another type than the node's first

    async def apply_event(self, e: dict) -> None:
        if self.last_event_id is not None and e["id"] <= self.last_event_id:
            return     # seen before the daemon link dropped
        self.last_event_id = e["id"]
        severity = SEVERITY.get(e["kind"])
        if severity is None:
            return
        payload = e.get("payload") or {}
        if e["kind"] == "suppression_action" and payload.get("sent") is False:
            severity = 700   # the guard refused the new speed: the chatter goes on
        machine = payload.get("machine") if isinstance(payload.get("machine"), str) else None
        if machine is None and e["source"] in self.machines:
            machine = e["source"]
        text = json.dumps(payload, default=str, separators=(", ", ": "))
        message = f"{e['kind']}" + (f" on {machine}" if machine else "") + f" ({e['source']}): {text}"
        gens = [self.server_events] + ([self.machine_events[machine]] if machine in self.machine_events else [])
        for gen in gens:
            ev = gen.event
            if machine in self.built:
                ev.SourceNode, ev.SourceName = self.built[machine].node.nodeid, machine
            else:
                ev.SourceNode, ev.SourceName = ua.NodeId(ua.ObjectIds.Server), e["source"]
            ev.Severity = severity
            ev.Identifier = e["kind"]
            ev.RecordId = int(e["id"])
            ev.Payload = text
            await gen.trigger(time_attr=_time(e["t"]), message=message[:1000])
        self.events_sent += 1

    async def daemon_lost(self) -> None:
        self.connected = False
        for v in self.vars.values():
            if v.live and v.value is not None and v.status != NO_DAEMON:
                await self._set(v, v.value, v.t, NO_DAEMON)


def product_instance_uri(cell: str, name: str, ident: dict) -> str:
    """The machine's globally unique URI (Machinery): its maker and serial number where known."""
    if ident.get("manufacturer") and ident.get("serial_number"):
        return f"urn:{quote(ident['manufacturer'], safe='')}:{quote(ident['serial_number'], safe='')}"
    return f"urn:lathed:{quote(cell, safe='')}:{quote(name, safe='')}"


def _vtype(value: Any) -> ua.VariantType:
    if isinstance(value, bool):
        return ua.VariantType.Boolean
    if isinstance(value, (int, float)):
        return ua.VariantType.Double
    return ua.VariantType.String


def _convert(value: Any, vtype: ua.VariantType) -> Any:
    if value is None:
        return None
    if vtype == ua.VariantType.Double:
        return float(value)
    if vtype == ua.VariantType.Boolean:
        return bool(value)
    if vtype in (ua.VariantType.UInt32, ua.VariantType.Int32, ua.VariantType.UInt16):
        return int(value)
    if vtype == ua.VariantType.String:
        if isinstance(value, float) and value.is_integer():
            return str(int(value))     # a program number read as a float register
        return value if isinstance(value, str) else json.dumps(value)
    return value
