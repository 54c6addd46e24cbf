"""lathed-opcua's address space: the daemon's line as OPC 40501 (Machine Tools) lays a machine out.

Objects/Machines/<machine> for every machine of the daemon's status, each with the
40501 components where lathed knows something to put in them:

  Identification   Manufacturer, Model, SerialNumber, YearOfConstruction ([machine.NAME.identification])
  Monitoring       MachineTool/MachineState; Channel1/ChannelState, Feed; Spindle/IsRotating, Override,
                   RotationalSpeed, CommandedSpeed, Load; Axes/<X, Y, Z, B, J1..>; for the analyzers
                   working on the machine Chatter/..., Thermal/..., Suppression/Mode, Strategy, Actions;
                   Values/<quantity> for anything else the machine reports
  Production       ActiveProgram/Name, ActiveProgram/State/CurrentState; PartCount; CycleTime
  Notification     Messages: the event notifier of the machine's records (NotificationEventType)

Browse names are 40501's where it has one (Identification, Monitoring, Spindle, Override,
IsRotating, ChannelState, Production, ActiveProgram, Notification, Messages...), in lathed's
namespace NAMESPACE; the types are the base OPC UA types (FolderType, BaseObjectType,
BaseDataVariableType, AnalogUnitType with EngineeringUnits), not the companion
specification's nodeset, which is not imported. Names 40501 lacks (RotationalSpeed, Axes,
Chatter, Thermal, PartCount...) are lathed's own.

Values carry the sample's own time as SourceTimestamp. While the daemon is unreachable every
live value is BadNoCommunication; while a machine's driver is not connected its values are
UncertainNoCommunicationLastUsableValue; a value the daemon has none of now (the chatter
frequency while there is no chatter) is BadNoDataAvailable.
"""
from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Any

import structlog
from asyncua import Node, Server, ua

log = structlog.get_logger("lathed.opcua")

NAMESPACE = "urn:lathed:opcua"

# lathed's unit text -> UNECE Recommendation 20 code (what OPC UA's EUInformation carries)
UNECE = {"mm": ("MMT", "millimetre"), "µm": ("4H", "micrometre"), "um": ("4H", "micrometre"),
         "r/min": ("RPM", "revolutions per minute"), "%": ("P1", "percent"), "Hz": ("HTZ", "hertz"),
         "s": ("SEC", "second"), "deg": ("DD", "degree"), "°C": ("CEL", "degree Celsius"),
         "m/s²": ("MSK", "metre per second squared"), "m/s^2": ("MSK", "metre per second squared"),
         "mm/rev": (None, "millimetre per revolution")}
CEFACT = "http://www.opcfoundation.org/UA/units/un/cefact"

# a machine's quantity -> (folder, browse name, variant type) in 40501's layout
MACHINE = {
    "spindle_rpm": ("Monitoring/Spindle", "RotationalSpeed", ua.VariantType.Double),
    "spindle_rpm_cmd": ("Monitoring/Spindle", "CommandedSpeed", ua.VariantType.Double),
    "spindle_override_pct": ("Monitoring/Spindle", "Override", ua.VariantType.Double),
    "spindle_load_pct": ("Monitoring/Spindle", "Load", ua.VariantType.Double),
    "feed_mm_rev": ("Monitoring/Channel1", "Feed", ua.VariantType.Double),
    "program_number": ("Production/ActiveProgram", "Name", ua.VariantType.String),
    "program": ("Production/ActiveProgram", "Name", ua.VariantType.String),
    "part_count": ("Production", "PartCount", ua.VariantType.UInt32),
    "cycle_time_s": ("Production", "CycleTime", ua.VariantType.Double),
}
AXIS = re.compile(r"^([a-z]|j\d)_(mm|deg)$")
# program_state (0 idle, 1 running, 2 alarm) -> 40501 ChannelState (Active 0, Interrupted 1, Reset 2)
# and ProductionStateMachine's current state
CHANNEL_STATE = {0: 2, 1: 0, 2: 1}
PRODUCTION_STATE = {0: "Ended", 1: "Running", 2: "Interrupted"}
# an analyzer's quantities, by its plugin: (folder, {quantity: browse name})
D, B = ua.VariantType.Double, ua.VariantType.Boolean
ANALYZER = {
    "chatter": ("Chatter", {"chatter_index": ("ChatterIndex", D), "chatter_threshold": ("ChatterThreshold", D),
                            "chatter_frequency_hz": ("ChatterFrequency", D), "chatter_alarm": ("ChatterAlarm", B),
                            "cutting": ("Cutting", B)}),
    "thermal": ("Thermal", {"predicted_growth_um": ("ThermalGrowth", D), "compensation_um": ("Compensation", D)}),
}
SUPPRESSION_MODES = ("auto", "manual", "off")

# records that become OPC UA events (Notification/Messages of their machine, and the Server object),
# with their severity (1..1000); the others stay in the daemon's event log
SEVERITY = {"chatter_alarm": 800, "chatter_cleared": 300, "suppression_action": 500,
            "suppression_advice": 700,   # the speed is held and the chatter goes on: the operator must act
            "suppression_proposed": 500, "suppression_mode": 300, "compensation": 200, "thermal_touchoff": 300,
            "thermal_refit": 200, "part_abnormal": 700, "part_unobserved": 700, "part_inspected": 200, "alarm_raised": 800,
            "alarm_cleared": 300, "command_refused": 700, "command_failed": 800, "implausible_value": 600}

GOOD = ua.StatusCode(ua.StatusCodes.Good)
NO_DAEMON = ua.StatusCode(ua.StatusCodes.BadNoCommunication)
NO_MACHINE = ua.StatusCode(ua.StatusCodes.UncertainNoCommunicationLastUsableValue)
NO_DATA = ua.StatusCode(ua.StatusCodes.BadNoDataAvailable)


def eu_information(unit: str) -> ua.EUInformation:
    code, text = UNECE.get(unit, (None, unit))
    unit_id = -1
    if code is not None:
        unit_id = 0
        for c in code:
            unit_id = unit_id << 8 | ord(c)
    return ua.EUInformation(NamespaceUri=CEFACT, UnitId=unit_id, DisplayName=ua.LocalizedText(unit),
                            Description=ua.LocalizedText(text))


def _time(t: float | None) -> datetime:
    return datetime.fromtimestamp(t, timezone.utc) if t is not None else datetime.now(timezone.utc)


@dataclass
class Var:
    node: Node
    vtype: ua.VariantType
    machine: str | None          # whose driver state decides its quality (None: the daemon's link only)
    live: bool = True            # False: from the config (Identification), good while the server runs
    value: Any = None
    t: float | None = None
    status: ua.StatusCode = field(default_factory=lambda: NO_DAEMON)


class Space:
    def __init__(self, server: Server, idx: int):
        self.server, self.idx = server, idx
        self.vars: dict[str, Var] = {}            # path ("lathe/Monitoring/Spindle/Override") -> variable
        self.objects: dict[str, Node] = {}        # path -> object or folder
        self.machines: dict[str, dict] = {}       # name -> its last status
        self.analyzers: dict[str, dict] = {}
        self.sensors: set[str] = set()
        self.writable: dict[ua.NodeId, str] = {}  # suppression Mode node -> its analyzer
        self.can_write = False
        self.connected = False
        self.quality: dict[str, ua.StatusCode] = {}   # machine -> GOOD or NO_MACHINE
        self.last_event_id: int | None = None
        self.events_sent = 0
        self.failing: dict[str, str] = {}         # what -> the error last logged for it

    # -- building ---------------------------------------------------------------------
    async def build(self, writable: bool) -> None:
        self.can_write = writable
        objects = self.server.nodes.objects
        self.objects["Machines"] = await objects.add_folder(self._id("Machines"), self._q("Machines"))
        self.objects["Sensors"] = await objects.add_folder(self._id("Sensors"), self._q("Sensors"))
        self.etype = await self.server.create_custom_event_type(
            self.idx, "NotificationEventType", ua.ObjectIds.BaseEventType,
            [("Identifier", ua.VariantType.String), ("RecordId", ua.VariantType.Int64),
             ("Payload", ua.VariantType.String)])
        self.server_events = await self.server.get_event_generator(self.etype, ua.ObjectIds.Server)
        self.machine_events: dict[str, Any] = {}

    def _id(self, path: str) -> ua.NodeId:
        return ua.NodeId(path, self.idx)

    def _q(self, name: str) -> ua.QualifiedName:
        return ua.QualifiedName(name, self.idx)

    async def _object(self, path: str) -> Node:
        """The object at ``path``, made (with its parents) if new."""
        node = self.objects.get(path)
        if node is None:
            parent_path, _, name = path.rpartition("/")
            parent = await self._object(parent_path) if parent_path else self.server.nodes.objects
            node = await parent.add_object(self._id(path), self._q(name))
            self.objects[path] = node
        return node

    async def _var(self, path: str, vtype: ua.VariantType, unit: str | None, machine: str | None,
                   writable: bool = False, live: bool = True) -> Var:
        v = self.vars.get(path)
        if v is not None:
            return v
        parent_path, _, name = path.rpartition("/")
        parent = await self._object(parent_path)
        if unit and vtype in (ua.VariantType.Double, ua.VariantType.Float):
            node = await self._analog(parent, path, name, unit)
        else:
            node = await parent.add_variable(self._id(path), self._q(name),
                                             ua.Variant(ua.get_default_value(vtype), vtype),
                                             varianttype=vtype, datatype=_datatype(vtype))
        if writable:
            await node.set_writable(True)
        v = self.vars[path] = Var(node, vtype, machine, live)
        return v

    async def _analog(self, parent: Node, path: str, name: str, unit: str) -> Node:
        """An AnalogUnitType variable (Double) with its EngineeringUnits."""
        item = ua.AddNodesItem(RequestedNewNodeId=self._id(path), BrowseName=self._q(name),
                               NodeClass=ua.NodeClass.Variable, ParentNodeId=parent.nodeid,
                               ReferenceTypeId=ua.NodeId(ua.ObjectIds.HasComponent),
                               TypeDefinition=ua.NodeId(ua.ObjectIds.AnalogUnitType))
        attrs = ua.VariableAttributes(DisplayName=ua.LocalizedText(name), Description=ua.LocalizedText(name),
                                      DataType=ua.NodeId(ua.ObjectIds.Double), ValueRank=ua.ValueRank.Scalar,
                                      Value=ua.Variant(0.0, ua.VariantType.Double),
                                      AccessLevel=ua.AccessLevel.CurrentRead.mask,
                                      UserAccessLevel=ua.AccessLevel.CurrentRead.mask)
        item.NodeAttributes = attrs
        res = await self.server.iserver.isession.add_nodes([item])
        res[0].StatusCode.check()
        node = self.server.get_node(res[0].AddedNodeId)
        await node.add_property(self._id(path + "/EngineeringUnits"), ua.QualifiedName("EngineeringUnits", 0),
                                ua.Variant(eu_information(unit), ua.VariantType.ExtensionObject))
        return node

    async def _machine(self, m: dict) -> None:
        name = m["name"]
        base = f"Machines/{name}"
        if name not in self.machines:
            await self._object(base)
            for part in ("Identification", "Monitoring", "Production", "Notification"):
                await self._object(f"{base}/{part}")
            messages = await self._object(f"{base}/Notification/Messages")
            gen = await self.server.get_event_generator(self.etype, messages)
            gen.event.SourceNode = self.objects[base].nodeid
            gen.event.SourceName = name
            self.machine_events[name] = gen
            kind = await self._var(f"{base}/Identification/ComponentName", ua.VariantType.LocalizedText, None,
                                   None, live=False)
            await self._set(kind, ua.LocalizedText(f"{name} ({m.get('kind') or 'machine'})"), None, GOOD)
        ident = m.get("identification") or {}
        if ident != (self.machines.get(name) or {}).get("identification"):   # new, or the config was reloaded
            for key, bname, vtype in (("manufacturer", "Manufacturer", ua.VariantType.LocalizedText),
                                      ("model", "Model", ua.VariantType.LocalizedText),
                                      ("serial_number", "SerialNumber", ua.VariantType.String),
                                      ("year_of_construction", "YearOfConstruction", ua.VariantType.UInt16)):
                if key in ident:
                    v = await self._var(f"{base}/Identification/{bname}", vtype, None, None, live=False)
                    value = ua.LocalizedText(ident[key]) if vtype == ua.VariantType.LocalizedText else ident[key]
                    await self._set(v, value, None, GOOD)
        self.machines[name] = m

    # -- applying what the daemon pushes ------------------------------------------------
    async def apply(self, frame: dict) -> None:
        """One pushed frame; a value that cannot be shown is said once (log) and the rest goes on."""
        if frame.get("status"):
            await self._guarded("status", self.apply_status(frame["status"]))
        for key, (t, value, unit) in (frame.get("samples") or {}).items():
            await self._guarded(key, self.apply_sample(key, t, value, unit))
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
            await self._machine(m)
            base = f"Machines/{m['name']}"
            quality = GOOD if m.get("state") == "connected" else NO_MACHINE
            if self.quality.get(m["name"]) != quality:
                self.quality[m["name"]] = quality
                for v in self.vars.values():
                    if v.machine == m["name"] and v.value is not None:
                        await self._set(v, v.value, v.t, quality)
            state = m.get("machine_state") or m.get("state")
            if state is not None:
                v = await self._var(f"{base}/Monitoring/MachineTool/MachineState", ua.VariantType.String, None, None)
                await self._set(v, str(state), None, GOOD)
        if "sensors" in status:
            self.sensors = {s["name"] for s in status["sensors"]}
        for a in status.get("analyzers", []):
            self.analyzers[a["name"]] = a
            if a.get("plugin") == "suppression" and a.get("machine") in self.machines:
                await self._suppression(a)

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

    def _route(self, src: str, q: str, value: Any) -> tuple[str, ua.VariantType, str | None] | None:
        """Where a sample goes: (path, variant type, machine whose state qualifies it)."""
        if src in self.machines:
            base = f"Machines/{src}"
            if q in MACHINE:
                folder, name, vtype = MACHINE[q]
                return f"{base}/{folder}/{name}", vtype, src
            if (m := AXIS.match(q)) is not None:
                return f"{base}/Monitoring/Axes/{m.group(1).upper()}", ua.VariantType.Double, src
            return f"{base}/Monitoring/Values/{q}", _vtype(value), src
        a = self.analyzers.get(src)
        if a is not None and a.get("machine") in self.machines:
            folder, names = ANALYZER.get(a.get("plugin"), (src, {}))
            name, vtype = names.get(q, (q, _vtype(value)))
            return f"Machines/{a['machine']}/Monitoring/{folder}/{name}", vtype, None
        if src in self.sensors:
            return f"Sensors/{src}/{q}", _vtype(value), src
        return None

    async def apply_sample(self, key: str, t: float, value: Any, unit: str) -> None:
        src, _, q = key.partition("/")
        if src in self.machines and q == "program_state":   # shown as the channel's and the program's state
            return await self._program_state(src, t, value)
        where = self._route(src, q, value)
        if where is None:   # a source not in the status yet (or an analyzer of no machine): its next value will do
            return
        path, vtype, machine = where
        v = await self._var(path, vtype, unit, machine if machine in self.machines else None)
        await self._set(v, _convert(value, v.vtype), t, self.quality.get(machine, GOOD))
        if src in self.machines and q == "spindle_rpm" and isinstance(value, (int, float)):
            rot = await self._var(f"Machines/{src}/Monitoring/Spindle/IsRotating", ua.VariantType.Boolean, None, src)
            await self._set(rot, abs(value) > 0.5, t, self.quality.get(src, GOOD))

    async def _program_state(self, src: str, t: float, value: Any) -> None:
        cs = await self._var(f"Machines/{src}/Monitoring/Channel1/ChannelState", ua.VariantType.Int32, None, src)
        ps = await self._var(f"Machines/{src}/Production/ActiveProgram/State/CurrentState",
                             ua.VariantType.LocalizedText, None, src)
        state = int(value) if isinstance(value, (int, float)) else -1
        await self._set(cs, CHANNEL_STATE.get(state, 1), t, self.quality.get(src, GOOD))
        await self._set(ps, ua.LocalizedText(PRODUCTION_STATE.get(state, "Interrupted")), t,
                        self.quality.get(src, GOOD))

    async def _set(self, v: Var, value: Any, t: float | None, status: ua.StatusCode) -> None:
        v.value, v.t, v.status = value, t, status
        if value is None:    # the source has none now (no chatter: no chatter frequency)
            status = NO_DATA
        dv = ua.DataValue(Value=ua.Variant(ua.get_default_value(v.vtype) if value is None else value, v.vtype),
                          StatusCode=status, SourceTimestamp=_time(t), ServerTimestamp=datetime.now(timezone.utc))
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
            if machine in self.machines:
                ev.SourceNode, ev.SourceName = self.objects[f"Machines/{machine}"].nodeid, machine
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


def _datatype(vtype: ua.VariantType) -> ua.NodeId:
    return ua.NodeId(getattr(ua.ObjectIds, vtype.name))
