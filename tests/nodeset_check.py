"""A type check of a live server's instances against published NodeSet files.

The types are read from the NodeSet XML (the OPC Foundation's base NodeSet as node-opcua-nodesets
ships it, and the companion specifications lathed-opcua ships), not from the server: an
instance conforms when every mandatory child its type (and the instance declaration it came
from) asks for is there with the same browse name and node class, its type definition is the
declared one or a subtype, a variable's DataType is the declared one or a subtype with a
value of that type, and every child with a type of these models conforms in turn.
"""
from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

from asyncua import Client, ua

UA = "http://opcfoundation.org/UA/"
X = "{http://opcfoundation.org/UA/2011/03/UANodeSet.xsd}"
HAS_SUBTYPE, HAS_MODELLING_RULE, HAS_TYPE_DEFINITION = "i=45", "i=37", "i=40"
HIERARCHICAL = {"i=47", "i=46", "i=17604", "i=35", "i=49", "i=33", "i=44", "i=14476"}   # components, properties...
RULES = {"i=78": "Mandatory", "i=80": "Optional", "i=11510": "MandatoryPlaceholder", "i=11508": "OptionalPlaceholder"}
# built-in DataType id -> the variant type a value of it has (an enumeration: Int32)
BUILTIN = {1: "Boolean", 2: "SByte", 3: "Byte", 4: "Int16", 5: "UInt16", 6: "Int32", 7: "UInt32", 8: "Int64",
           9: "UInt64", 10: "Float", 11: "Double", 12: "String", 13: "DateTime", 14: "Guid", 15: "ByteString",
           16: "XmlElement", 17: "NodeId", 18: "ExpandedNodeId", 19: "StatusCode", 20: "QualifiedName",
           21: "LocalizedText", 22: "ExtensionObject", 23: "DataValue", 24: "Variant", 25: "DiagnosticInfo",
           29: "Int32"}


@dataclass
class UaNode:
    key: str                          # "uri|i=13"
    nodeclass: str
    bname: tuple[str, str]            # (uri, name)
    refs: list[tuple[str, str, bool]] = field(default_factory=list)   # (reference type key, target key, forward)
    datatype: str | None = None


class Model:
    """Every node of the NodeSet files, by "namespace URI|identifier"."""

    def __init__(self, files: list[Path]):
        self.nodes: dict[str, UaNode] = {}
        for f in files:
            self._load(f)
        self._inverse()
        self.supertype: dict[str, str] = {}
        for n in self.nodes.values():
            for rt, target, fwd in n.refs:
                if rt == f"{UA}|{HAS_SUBTYPE}" and not fwd:
                    self.supertype[n.key] = target
                elif rt == f"{UA}|{HAS_SUBTYPE}" and fwd:
                    self.supertype.setdefault(target, n.key)

    def _load(self, path: Path) -> None:
        root = ET.parse(path).getroot()
        uris = [UA] + [u.text for u in root.iter(f"{X}Uri")]
        aliases = {a.get("Alias"): a.text for a in root.iter(f"{X}Alias")}

        def key(text: str) -> str:
            text = aliases.get(text, text).strip()
            m = re.match(r"ns=(\d+);(.*)", text)
            return f"{uris[int(m.group(1))]}|{m.group(2)}" if m else f"{UA}|{text}"

        for el in root:
            tag = el.tag.removeprefix(X)
            if not tag.startswith("UA") or tag == "UANodeSet":
                continue
            qn = el.get("BrowseName")
            m = re.match(r"(\d+):(.*)", qn)
            bname = (uris[int(m.group(1))], m.group(2)) if m else (UA, qn)
            node = UaNode(key(el.get("NodeId")), tag[2:], bname,
                          datatype=key(el.get("DataType", "i=24")) if tag in ("UAVariable", "UAVariableType") else None)
            refs = el.find(f"{X}References")
            for r in (refs if refs is not None else []):
                node.refs.append((key(r.get("ReferenceType")), key(r.text), r.get("IsForward", "true") != "false"))
            self.nodes.setdefault(node.key, node)

    def _inverse(self) -> None:
        """The other side of every reference: a file may state either."""
        have = {n.key: set(n.refs) for n in self.nodes.values()}
        for n in list(self.nodes.values()):
            for rt, target, fwd in list(n.refs):
                if target in have and (rt, n.key, not fwd) not in have[target]:
                    have[target].add((rt, n.key, not fwd))
                    self.nodes[target].refs.append((rt, n.key, not fwd))

    def is_subtype(self, sub: str, sup: str) -> bool:
        while sub is not None:
            if sub == sup:
                return True
            sub = self.supertype.get(sub)
        return False

    def rule(self, decl: UaNode) -> str | None:
        return next((RULES.get(t.split("|")[1]) for rt, t, fwd in decl.refs
                     if fwd and rt == f"{UA}|{HAS_MODELLING_RULE}"), None)

    def typedef(self, n: UaNode) -> str | None:
        return next((t for rt, t, fwd in n.refs if fwd and rt == f"{UA}|{HAS_TYPE_DEFINITION}"), None)

    def declared(self, owner: str) -> dict[tuple[str, str], UaNode]:
        """The instance declarations below a type (its supertypes' too) or below a declaration."""
        out: dict[tuple[str, str], UaNode] = {}
        chain, k = [], owner
        node = self.nodes[owner]
        if node.nodeclass in ("ObjectType", "VariableType"):
            while k is not None:
                chain.append(k)
                k = self.supertype.get(k)
        else:                # a declaration: its own children, then its type's
            chain = [owner] + self._type_chain(self.typedef(node))
        for k in chain:
            for rt, target, fwd in self.nodes[k].refs:
                t = self.nodes.get(target)
                if fwd and t is not None and rt.split("|")[1] in HIERARCHICAL and self.rule(t) is not None:
                    out.setdefault(t.bname, t)
        return out

    def _type_chain(self, k: str | None) -> list[str]:
        out = []
        while k is not None and k in self.nodes:
            out.append(k)
            k = self.supertype.get(k)
        return out

    def builtin(self, datatype: str) -> str | None:
        k = datatype
        while k is not None:
            uri, ident = k.split("|")
            if uri == UA and ident.startswith("i=") and int(ident[2:]) in BUILTIN:
                return BUILTIN[int(ident[2:])]
            k = self.supertype.get(k)
        return None


class Checker:
    """Walks a live server's instances and lists every way they differ from their types."""

    def __init__(self, model: Model, client: Client):
        self.model, self.client = model, client
        self.errors: list[str] = []
        self.checked = 0
        self.seen: set[tuple[str, str | None]] = set()

    async def _key(self, nodeid: ua.NodeId | ua.ExpandedNodeId) -> str:
        uri = self.ns[nodeid.NamespaceIndex]
        ident = {ua.NodeIdType.String: "s=", ua.NodeIdType.Guid: "g=", ua.NodeIdType.ByteString: "b="}.get(
            nodeid.NodeIdType, "i=") + str(nodeid.Identifier)
        return f"{uri}|{ident}"

    async def check_instance(self, node, where: str, owner: str | None = None) -> None:
        """``node`` against ``owner`` (a declaration's key), else against its own type definition."""
        self.ns = await self.client.get_namespace_array()
        if (node.nodeid.to_string(), owner) in self.seen:    # reached again (HasAddIn, HasNotifier)
            return
        self.seen.add((node.nodeid.to_string(), owner))
        tdid = await node.read_type_definition()
        if tdid is None:
            return
        typedef = await self._key(tdid)
        if owner is None:
            if typedef not in self.model.nodes:
                return           # a type of no model loaded here (lathed's own folders are FolderType: known)
            owner = typedef
        self.checked += 1
        refs = await node.get_references(refs=ua.ObjectIds.HierarchicalReferences,
                                         direction=ua.BrowseDirection.Forward, includesubtypes=True)
        children = {}
        for r in refs:
            children[(self.ns[r.BrowseName.NamespaceIndex], r.BrowseName.Name)] = r
        declared = self.model.declared(owner)
        for bname, decl in declared.items():
            if self.model.rule(decl) == "Mandatory" and bname not in children:
                self.errors.append(f"{where}: mandatory {bname[1]} ({bname[0]}) missing")
        for bname, r in children.items():
            child = self.client.get_node(r.NodeId)
            at = f"{where}/{bname[1]}"
            decl = declared.get(bname)
            if decl is not None:
                await self._conforms(child, r, decl, at)
                await self.check_instance(child, at, decl.key)
            elif r.NodeClass in (ua.NodeClass.Object, ua.NodeClass.Variable):
                await self.check_instance(child, at)

    async def _conforms(self, child, r, decl: UaNode, at: str) -> None:
        if r.NodeClass.name != decl.nodeclass:
            self.errors.append(f"{at}: a {r.NodeClass.name}, declared a {decl.nodeclass}")
            return
        want = self.model.typedef(decl)
        got = await self._key(r.TypeDefinition) if r.TypeDefinition else None
        if want and not (got and self.model.is_subtype(got, want)):
            self.errors.append(f"{at}: type {got}, declared {want}")
        if decl.nodeclass != "Variable":
            return
        dt = await self._key(await child.read_data_type())
        if not self.model.is_subtype(dt, decl.datatype):
            self.errors.append(f"{at}: DataType {dt}, declared {decl.datatype}")
        dv = await child.read_data_value(raise_on_bad_status=False)
        if dv.StatusCode.is_good() and dv.Value is not None and dv.Value.Value is not None:
            builtin = self.model.builtin(dt)
            if builtin not in (None, "Variant") and dv.Value.VariantType.name != builtin:
                self.errors.append(f"{at}: a {dv.Value.VariantType.name} value, its DataType is a {builtin}")


def default_files(node_modules: Path, ours: Path) -> list[Path]:
    base = node_modules / "node-opcua-nodesets" / "nodesets" / "Opc.Ua.NodeSet2.xml"
    from lathed.opcua.nodesets import FILES
    return [base] + [ours / f for f in FILES]
