"""The OPC Foundation companion specifications lathed-opcua's machines are built from
(docs/opcua.md): the published NodeSet files in nodesets/, loaded into asyncua at start, and
the type nodes lathed instantiates, named by their ids in those files."""
from __future__ import annotations

import re
from pathlib import Path

from asyncua import Node, Server, ua
from asyncua.common.structures104 import (load_basetype_alias_xml_import, load_custom_struct_xml_import,
                                          load_enum_xml_import)
from asyncua.common.xmlimporter import XmlImporter

NODESETS = Path(__file__).with_name("nodesets")
UA = "http://opcfoundation.org/UA/"
DI = "http://opcfoundation.org/UA/DI/"
IA = "http://opcfoundation.org/UA/IA/"
MACHINERY = "http://opcfoundation.org/UA/Machinery/"
MACHINE_TOOL = "http://opcfoundation.org/UA/MachineTool/"
# in dependency order: each file's models need the ones before it
FILES = ("Opc.Ua.Di.NodeSet2.xml", "Opc.Ua.IA.NodeSet2.xml", "Opc.Ua.Machinery.NodeSet2.xml",
         "opc.ua.isa95-jobcontrol.nodeset2.xml", "Opc.Ua.Machinery.Jobs.Nodeset2.xml",
         "Opc.Ua.MachineTool.NodeSet2.xml")
_INTEGERS = {ua.ObjectIds.SByte, ua.ObjectIds.Byte, ua.ObjectIds.Int16, ua.ObjectIds.UInt16, ua.ObjectIds.Int32,
             ua.ObjectIds.UInt32, ua.ObjectIds.Int64, ua.ObjectIds.UInt64}
_DESIGN_TOOL_ONLY = re.compile(r'<UAObject [^>]*DesignToolOnly="true"[^>]*>.*?</UAObject>', re.S)

# the numeric ids of what lathed uses, in each model's own namespace
MACHINES_FOLDER = (MACHINERY, 1001)
MACHINE_IDENTIFICATION_TYPE = (MACHINERY, 1012)
MACHINERY_ITEM_STATE_TYPE = (MACHINERY, 1002)
MACHINERY_MONITORING_TYPE = (MACHINERY, 1014)
MACHINE_TOOL_TYPE = (MACHINE_TOOL, 13)
SPINDLE_MONITORING_TYPE = (MACHINE_TOOL, 22)
CHANNEL_MONITORING_TYPE = (MACHINE_TOOL, 16)
MESSAGES_TYPE = (MACHINE_TOOL, 38)
PROGNOSIS_LIST_TYPE = (MACHINE_TOOL, 2)
PART_UNLOAD_PROGNOSIS_TYPE = (MACHINE_TOOL, 5)
NOTIFICATION_EVENT_TYPE = (MACHINE_TOOL, 35)
PRODUCTION_PROGRAM_STATE_MACHINE_TYPE = (MACHINE_TOOL, 15)
ANALOG_UNIT_RANGE_TYPE = (UA, ua.ObjectIds.AnalogUnitRangeType)
ANALOG_UNIT_TYPE = (UA, ua.ObjectIds.AnalogUnitType)


# what a data type node adds to asyncua's ua module, in import order: (kind, node, name, option
# set, parent) with kind "struct", "enum" or "alias"; a cached load (spacecache) replays them
TypeRecord = tuple[str, ua.NodeId, str, bool, ua.NodeId]


class _Importer(XmlImporter):
    """asyncua's importer, its data types registered by register_types (one path for an XML
    import and a cached load), and told that an OptionSet over an integer type is that integer.

    asyncua 2.1 knows only OptionSet structures; Machinery Jobs' OutputInfoType (a Byte) is
    then an unknown type, and the structure with a field of it fails to load."""

    def __init__(self, server: Server, types: list[TypeRecord]):
        super().__init__(server, auto_load_definitions=False)
        self.types = types

    async def add_datatype(self, obj, no_namespace_migration=False):
        nodeid = await super().add_datatype(obj, no_namespace_migration)
        definition = _attribute(self.session, nodeid, ua.AttributeIds.DataTypeDefinition)
        # the choices asyncua's importer makes when it registers definitions itself
        if isinstance(definition, ua.StructureDefinition):
            record = ("struct", nodeid, obj.displayname, False, obj.parent)
        elif isinstance(definition, ua.EnumDefinition):     # an Enumeration's child, or an OptionSet's
            record = ("enum", nodeid, obj.displayname, obj.parent != ua.NodeId(ua.ObjectIds.Enumeration),
                      obj.parent)
        elif not obj.definitions and obj.parent != ua.NodeId(ua.ObjectIds.Structure):
            name = _attribute(self.session, nodeid, ua.AttributeIds.BrowseName).Name
            record = ("alias", nodeid, name, False, obj.parent)
        elif obj.definitions and obj.parent.NamespaceIndex == 0 and obj.parent.Identifier in _INTEGERS:
            record = ("alias", nodeid, obj.displayname, False, obj.parent)
        else:
            return nodeid
        self.types.append(record)
        await register_types(self.session, [record])
        return nodeid


def _attribute(server: Server, nodeid: ua.NodeId, attr: ua.AttributeIds):
    return server.iserver.aspace.read_attribute_value(nodeid, attr).Value.Value


async def register_types(server: Server, types: list[TypeRecord]) -> None:
    """The classes asyncua encodes and decodes these data types with (its ua module's registry)."""
    for kind, nodeid, name, option_set, parent in types:
        if kind == "alias":
            await load_basetype_alias_xml_import(server, name, nodeid, parent)
            continue
        attrs = ua.DataTypeAttributes(DisplayName=ua.LocalizedText(name))
        attrs.DataTypeDefinition = _attribute(server, nodeid, ua.AttributeIds.DataTypeDefinition)
        if kind == "struct":
            await load_custom_struct_xml_import(nodeid, attrs)
        else:
            await load_enum_xml_import(nodeid, attrs, option_set)


async def load(server: Server, types: list[TypeRecord] | None = None) -> dict[str, int]:
    """Every file into the server's address space; the namespace index of each model. ``types``
    gets the data types registered, in order."""
    types = [] if types is None else types
    for name in FILES:
        text = (NODESETS / name).read_text(encoding="utf-8")
        # design-tool-only nodes are not for a server (OPC 10000-6 F.3); DI's have no parent,
        # which asyncua refuses
        await _Importer(server, types).import_xml(xmlstring=_DESIGN_TOOL_ONLY.sub("", text))
    return await indexes(server)


async def indexes(server: Server) -> dict[str, int]:
    """The namespace index of each model lathed uses."""
    array = await server.get_namespace_array()
    return {uri: array.index(uri) for uri in (UA, DI, IA, MACHINERY, MACHINE_TOOL)}


class Types:
    """The loaded models' nodes by (model, id), and their browse names."""

    def __init__(self, server: Server, ns: dict[str, int]):
        self.server, self.ns = server, ns

    def id(self, ref: tuple[str, int]) -> ua.NodeId:
        uri, i = ref
        return ua.NodeId(i, self.ns[uri])

    def node(self, ref: tuple[str, int]) -> Node:
        return self.server.get_node(self.id(ref))

    def q(self, uri: str, name: str) -> ua.QualifiedName:
        return ua.QualifiedName(name, self.ns[uri])

    async def state(self, machine_type: tuple[str, int], name: str, uri: str) -> tuple[ua.NodeId, int | None]:
        """A state of a state machine type: its node and StateNumber (None where it has none)."""
        node = await self.node(machine_type).get_child(self.q(uri, name))
        try:
            number = await (await node.get_child(ua.QualifiedName("StateNumber", 0))).read_value()
        except ua.UaError:
            number = None
        return node.nodeid, number
