"""The OPC Foundation companion specifications lathed-opcua's machines are built from
(docs/opcua.md): the published NodeSet files in nodesets/, loaded into asyncua at start, and
the type nodes lathed instantiates, named by their ids in those files."""
from __future__ import annotations

import re
from pathlib import Path

from asyncua import Node, Server, ua
from asyncua.common.structures104 import load_basetype_alias_xml_import
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


class _Importer(XmlImporter):
    """asyncua's importer, told that an OptionSet over an integer type is that integer.

    asyncua 2.1 knows only OptionSet structures; Machinery Jobs' OutputInfoType (a Byte) is
    then an unknown type, and the structure with a field of it fails to load."""

    async def add_datatype(self, obj, no_namespace_migration=False):
        nodeid = await super().add_datatype(obj, no_namespace_migration)
        if obj.definitions and obj.parent.NamespaceIndex == 0 and obj.parent.Identifier in _INTEGERS:
            await load_basetype_alias_xml_import(self.session, obj.displayname, nodeid, obj.parent)
        return nodeid


async def load(server: Server) -> dict[str, int]:
    """Every file into the server's address space; the namespace index of each model."""
    for name in FILES:
        text = (NODESETS / name).read_text(encoding="utf-8")
        # design-tool-only nodes are not for a server (OPC 10000-6 F.3); DI's have no parent,
        # which asyncua refuses
        await _Importer(server).import_xml(xmlstring=_DESIGN_TOOL_ONLY.sub("", text))
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
