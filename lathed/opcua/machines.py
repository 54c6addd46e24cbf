"""One machine's object under the Machinery Machines folder (docs/opcua.md).

A lathe, mill or grinder is a MachineToolType of OPC 40501 (Identification, Monitoring with
the MachineTool, a Spindle and Channel1, Production, Equipment, Notification with Messages and
Prognoses); any other machine (the robot arm) is a Machinery machine: an object with the
Machinery building blocks (Identification, MachineryItemState) and a Machinery Monitoring
folder. Standard children are made from the loaded types; lathed's own values sit beside them
in lathed's namespace. A monitored element (Spindle, Channel1) or one of lathed's objects is
made when its first value comes, so no object stands empty.
"""
from __future__ import annotations

import asyncio

from asyncua import Node, ua
from asyncua.common.instantiate_util import instantiate

from lathed.opcua import nodesets as N

MACHINE_TOOL_KINDS = ("lathe", "mill", "grinder")
MT = N.MACHINE_TOOL

# lathed's unit text -> UNECE Recommendation 20 code (what OPC UA's EUInformation carries)
UNECE = {"mm": ("MMT", "millimetre"), "µm": ("4H", "micrometre"), "um": ("4H", "micrometre"),
         "r/min": ("RPM", "revolutions per minute"), "%": ("P1", "percent"), "Hz": ("HTZ", "hertz"),
         "s": ("SEC", "second"), "deg": ("DD", "degree"), "°C": ("CEL", "degree Celsius"),
         "m/s²": ("MSK", "metre per second squared"), "m/s^2": ("MSK", "metre per second squared"),
         "mm/rev": (None, "millimetre per revolution")}
CEFACT = "http://www.opcfoundation.org/UA/units/un/cefact"
# an override's EURange: the widest a control's 8-bit external override reaches (Fanuc SOV, *FV)
OVERRIDE_RANGE = (0.0, 254.0)


def eu_information(unit: str) -> ua.EUInformation:
    code, text = UNECE.get(unit, (None, unit))
    unit_id = -1
    if code is not None:
        unit_id = 0
        for c in code:
            unit_id = unit_id << 8 | ord(c)
    return ua.EUInformation(NamespaceUri=CEFACT, UnitId=unit_id, DisplayName=ua.LocalizedText(unit),
                            Description=ua.LocalizedText(text))


class Machine:
    """The nodes of one machine, and where its parts go."""

    def __init__(self, types: N.Types, idx: int, name: str, kind: str, node: Node):
        self.types, self.server, self.idx = types, types.server, idx
        self.name, self.kind, self.node = name, kind, node
        self.tool = kind in MACHINE_TOOL_KINDS
        self.events: Node = node          # where the machine's records are notified
        self.item_state: Node | None = None
        self.prognoses: Node | None = None
        self.prognosis: Node | None = None
        self.optional: set[str] = set()   # optional children added, by their path

    def q(self, uri: str | None, name: str) -> ua.QualifiedName:
        return ua.QualifiedName(name, self.idx) if uri is None else self.types.q(uri, name)

    def nid(self, *names: str) -> ua.NodeId:
        # as asyncua names the children it instantiates under a string NodeId: parent.child
        return ua.NodeId(".".join(("Machines", self.name) + names), self.idx)

    async def child(self, *path: tuple[str | None, str]) -> Node:
        return await self.node.get_child([self.q(uri, name) for uri, name in path])

    @property
    def monitoring_uri(self) -> str:
        return MT if self.tool else N.MACHINERY

    # -- the parts made when their first value comes ----------------------------------
    async def element(self, name: str) -> Node:
        """A 40501 monitored element (Spindle, Channel1) of the machine tool, with its Name."""
        kind = {"Spindle": N.SPINDLE_MONITORING_TYPE, "Channel1": N.CHANNEL_MONITORING_TYPE}[name]
        monitoring = await self.child((MT, "Monitoring"))
        node = await instance(monitoring, self.types.node(kind), self.nid("Monitoring", name), self.q(None, name))
        await write(self.server, await node.get_child(self.q(MT, "Name")), name, ua.VariantType.String)
        if name == "Channel1":
            await ranged(self.server, await node.get_child(self.q(MT, "FeedOverride")), "%", OVERRIDE_RANGE)
        return node

    async def folder(self, parent: Node, *names: str) -> Node:
        """lathed's folder or object under ``parent`` (Axes, Values, Chatter...)."""
        name = names[-1]
        nid = self.nid(*names)
        if name in ("Axes", "Values"):
            return await parent.add_folder(nid, self.q(None, name))
        return await parent.add_object(nid, self.q(None, name))

    async def override(self, spindle: Node) -> Node:
        """The spindle's optional Override (AnalogUnitRangeType, %)."""
        node = await variable(self.server, spindle, self.types.node(N.ANALOG_UNIT_RANGE_TYPE),
                              self.nid("Monitoring", "Spindle", "Override"), self.q(MT, "Override"), ua.ObjectIds.Double)
        await ranged(self.server, node, "%", OVERRIDE_RANGE)
        return node

    async def identification(self, ident: dict, uri: str) -> None:
        """The nameplate: the mandatory Manufacturer, SerialNumber and ProductInstanceUri (empty
        where the config has none), Model and YearOfConstruction where it has them."""
        node = await self.child((N.DI, "Identification"))
        lt, s = ua.VariantType.LocalizedText, ua.VariantType.String
        await write(self.server, await node.get_child(self.q(N.DI, "Manufacturer")),
                    ua.LocalizedText(ident.get("manufacturer", "")), lt)
        await write(self.server, await node.get_child(self.q(N.DI, "SerialNumber")), ident.get("serial_number", ""), s)
        await write(self.server, await node.get_child(self.q(N.DI, "ProductInstanceUri")), uri, s)
        for key, uri_, bname, vtype, dtype in (
                ("model", N.DI, "Model", lt, ua.ObjectIds.LocalizedText),
                ("year_of_construction", N.MACHINERY, "YearOfConstruction", ua.VariantType.UInt16,
                 ua.ObjectIds.UInt16)):
            if key not in ident:
                continue
            value = ua.LocalizedText(ident[key]) if vtype == lt else ident[key]
            path = f"Identification/{bname}"
            if path not in self.optional:
                await node.add_property(self.nid("Identification", bname), self.q(uri_, bname),
                                        ua.Variant(value, vtype), datatype=ua.NodeId(dtype))
                self.optional.add(path)
            else:
                await write(self.server, await node.get_child(self.q(uri_, bname)), value, vtype)

    async def set_prognosis(self, when, part: str | None) -> None:
        """The machine tool's next part unload (PartUnloadPrognosisType), or none (``when`` None)."""
        if when is None:
            if self.prognosis is not None:
                await self.server.delete_nodes([self.prognosis], recursive=True)
                self.prognosis = None
            return
        if self.prognosis is None:
            self.prognosis = await instance(self.prognoses, self.types.node(N.PART_UNLOAD_PROGNOSIS_TYPE),
                                            self.nid("Notification", "Prognoses", "PartUnload"),
                                            self.q(None, "PartUnload"))
            await write(self.server, await self.prognosis.get_child(self.q(MT, "Location")),
                        ua.LocalizedText(f"{self.name} work area"), ua.VariantType.LocalizedText)
        await write(self.server, await self.prognosis.get_child(self.q(MT, "PredictedTime")), when,
                    ua.VariantType.DateTime)
        await write(self.server, await self.prognosis.get_child(self.q(MT, "PartName")), part or "",
                    ua.VariantType.String)


async def build(types: N.Types, folder: Node, idx: int, name: str, kind: str) -> Machine:
    """The machine's object and its mandatory parts (values come later)."""
    if kind in MACHINE_TOOL_KINDS:
        node = await instance(folder, types.node(N.MACHINE_TOOL_TYPE), ua.NodeId(f"Machines.{name}", idx),
                              ua.QualifiedName(name, idx))
        m = Machine(types, idx, name, kind, node)
        await _machine_tool(m)
    else:
        node = await folder.add_object(ua.NodeId(f"Machines.{name}", idx), ua.QualifiedName(name, idx))
        m = Machine(types, idx, name, kind, node)
        await _machinery_machine(m)
    return m


async def _machine_tool(m: Machine) -> None:
    t = m.types
    notification = await m.child((MT, "Notification"))
    m.events = await instance(notification, t.node(N.MESSAGES_TYPE), m.nid("Notification", "Messages"),
                              t.q(MT, "Messages"))
    await m.events.set_event_notifier([ua.EventNotifier.SubscribeToEvents])
    m.prognoses = await instance(notification, t.node(N.PROGNOSIS_LIST_TYPE), m.nid("Notification", "Prognoses"),
                                 t.q(MT, "Prognoses"))
    blocks = await _building_blocks(m, await m.child((N.DI, "Identification")))
    # one state machine: where 40501 reads it, and (HasAddIn) where Machinery's clients do
    machine_tool = await m.child((MT, "Monitoring"), (MT, "MachineTool"))
    m.item_state = await instance(machine_tool, t.node(N.MACHINERY_ITEM_STATE_TYPE),
                                  m.nid("Monitoring", "MachineTool", "MachineryItemState"),
                                  t.q(N.MACHINERY, "MachineryItemState"))
    await blocks.add_reference(m.item_state.nodeid, ua.ObjectIds.HasAddIn)
    # lathed reads no part program list: the active program is number 0 of none
    program = await m.child((MT, "Production"), (MT, "ActiveProgram"))
    await write(m.server, await program.get_child(m.q(N.UA, "NumberInList")), 0, ua.VariantType.UInt16)


async def _machinery_machine(m: Machine) -> None:
    t = m.types
    await m.node.set_event_notifier([ua.EventNotifier.SubscribeToEvents])
    ident = await instance(m.node, t.node(N.MACHINE_IDENTIFICATION_TYPE), m.nid("Identification"),
                           t.q(N.DI, "Identification"), ua.ObjectIds.HasAddIn)
    blocks = await _building_blocks(m, ident)
    m.item_state = await instance(blocks, t.node(N.MACHINERY_ITEM_STATE_TYPE),
                                  m.nid("MachineryBuildingBlocks", "MachineryItemState"),
                                  t.q(N.MACHINERY, "MachineryItemState"), ua.ObjectIds.HasAddIn)
    await instance(m.node, t.node(N.MACHINERY_MONITORING_TYPE), m.nid("Monitoring"), t.q(N.MACHINERY, "Monitoring"))


async def _building_blocks(m: Machine, ident: Node) -> Node:
    """Machinery's MachineryBuildingBlocks folder, holding (by HasAddIn) the Identification."""
    blocks = await m.node.add_folder(m.nid("MachineryBuildingBlocks"), m.q(N.MACHINERY, "MachineryBuildingBlocks"))
    await blocks.add_reference(ident.nodeid, ua.ObjectIds.HasAddIn)
    return blocks


async def instance(parent: Node, type_node: Node, nodeid: ua.NodeId, bname: ua.QualifiedName,
                   reference: int | None = None) -> Node:
    """An instance of the object type with its mandatory children, under ``parent`` by
    ``reference`` (else asyncua's: HasComponent, Organizes under a folder)."""
    node = await parent.add_object(nodeid, bname, objecttype=type_node.nodeid, instantiate_optional=False)
    await asyncio.sleep(0)     # the address space's calls do not yield: let clients in between
    if reference is not None:
        for r in await parent.get_references(direction=ua.BrowseDirection.Forward):
            if r.NodeId == node.nodeid:
                await parent.delete_reference(node, r.ReferenceTypeId, forward=True, bidirectional=True)
        await parent.add_reference(node, reference)
    return node


async def variable(server, parent: Node, type_node: Node, nodeid: ua.NodeId, bname: ua.QualifiedName,
                   datatype: int) -> Node:
    """An instance of the variable type (e.g. AnalogUnitType) holding ``datatype``, read-only."""
    (node, *_) = await instantiate(parent, type_node, nodeid, bname=bname, dname=ua.LocalizedText(bname.Name),
                                   instantiate_optional=False)
    aspace = server.iserver.aspace
    for attr, value in ((ua.AttributeIds.DataType, ua.Variant(ua.NodeId(datatype))),
                        (ua.AttributeIds.ValueRank, ua.Variant(ua.ValueRank.Scalar, ua.VariantType.Int32)),
                        (ua.AttributeIds.AccessLevel, ua.Variant(ua.AccessLevel.CurrentRead.mask, ua.VariantType.Byte)),
                        (ua.AttributeIds.UserAccessLevel,
                         ua.Variant(ua.AccessLevel.CurrentRead.mask, ua.VariantType.Byte))):
        (await aspace.write_attribute_value(node.nodeid, attr, ua.DataValue(value))).check()
    return node


async def ranged(server, node: Node, unit: str, low_high: tuple[float, float]) -> None:
    """An analog item's EngineeringUnits and EURange."""
    await write(server, await node.get_child(ua.QualifiedName("EngineeringUnits", 0)), eu_information(unit),
                ua.VariantType.ExtensionObject)
    range_ = await node.get_child(ua.QualifiedName("EURange", 0))
    await write(server, range_, ua.Range(Low=low_high[0], High=low_high[1]), ua.VariantType.ExtensionObject)


async def write(server, node: Node, value, vtype: ua.VariantType, status: int = ua.StatusCodes.Good) -> None:
    """A value into the address space itself (clients may not write these nodes)."""
    dv = ua.DataValue(Value=ua.Variant(value, vtype), StatusCode=ua.StatusCode(status))
    (await server.iserver.aspace.write_attribute_value(node.nodeid, ua.AttributeIds.Value, dv)).check()
