"""An OPC UA control's node map: which node holds which lathed value, and how it is written.

Read from a machine's ``[machine.NAME.nodes]`` table (docs/machines.md: OPC UA). A node is
named by its node id or by a browse path from the machine's ``root``; namespaces by URI (an
alias of ``[machine.NAME.namespaces]`` or a built-in one), never by index alone, for a server
numbers its namespaces as it likes and may renumber them at a restart. The map is resolved on
the server at every connect (``resolve``); values are turned into numbers (``number``) and
written back in the node's own type (``variant``). No I/O but ``resolve``.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any

from asyncua import ua

from lathed.config import Section
from lathed.plausible import Plausibility

# the companion specifications a machine tool's server speaks, by the alias a map uses
BUILTIN_NAMESPACES = {
    "ua": "http://opcfoundation.org/UA/",
    "di": "http://opcfoundation.org/UA/DI/",
    "machinery": "http://opcfoundation.org/UA/Machinery/",
    "ia": "http://opcfoundation.org/UA/IA/",
    "mt": "http://opcfoundation.org/UA/MachineTool/",
}
# what lathed writes: an action's value, the override a speed is commanded by, the heartbeat
WRITABLE = ("spindle_rpm_cmd", "offset_x_um", "spindle_override_pct", "heartbeat")
# the nameplate as the server reports it: read once at connect, checked against [identification]
IDENTITY = ("manufacturer", "model", "serial_number")
NODE_ID = re.compile(r"^(?:(ns|nsu)=([^;]+);)?([isgb])=(.+)$", re.S)
INTEGER = {ua.VariantType.SByte: (-2**7, 2**7 - 1), ua.VariantType.Byte: (0, 2**8 - 1),
           ua.VariantType.Int16: (-2**15, 2**15 - 1), ua.VariantType.UInt16: (0, 2**16 - 1),
           ua.VariantType.Int32: (-2**31, 2**31 - 1), ua.VariantType.UInt32: (0, 2**32 - 1),
           ua.VariantType.Int64: (-2**63, 2**63 - 1), ua.VariantType.UInt64: (0, 2**64 - 1)}
WRITABLE_TYPES = (ua.VariantType.Double, ua.VariantType.Float, ua.VariantType.Boolean, *INTEGER)


class MapError(Exception):
    """The map does not fit the server (a node missing, a namespace unknown, a type unwritable)."""


@dataclass(frozen=True)
class Ref:
    """A node by id (``ns``: an alias, a URI or an index; ``kind``: i s g b) or by browse path."""
    text: str                                   # as written in the config, for messages
    ns: str | int = 0
    kind: str = ""
    ident: str = ""
    path: tuple[tuple[str | int, str], ...] = ()    # ((namespace, name), ...) from the root

    def namespaces(self) -> set[str | int]:
        return {self.ns, *(ns for ns, _ in self.path)}

    @classmethod
    def parse(cls, text: str, is_path: bool) -> Ref:
        if is_path:
            parts = []
            for el in text.strip("/").split("/"):
                ns, sep, name = el.rpartition(":")
                if not name:
                    raise ValueError(f"{text!r}: an empty element in the browse path")
                parts.append((_ns(ns) if sep else 0, name))
            return cls(text, path=tuple(parts))
        m = NODE_ID.match(text.strip())
        if m is None:
            raise ValueError(f"{text!r} is not a node id (ns=ALIAS;s=NAME, nsu=URI;i=NUMBER, i=NUMBER, ...)")
        which, ns, kind, ident = m.groups()
        if kind == "i" and not ident.isdigit():
            raise ValueError(f"{text!r}: a numeric node id (i=) must be a number")
        return cls(text, (ns if which == "nsu" else _ns(ns)) if which else 0, kind, ident)


def _ns(text: str) -> str | int:
    return int(text) if text.isdigit() else text


@dataclass
class Entry:
    """One lathed value on the server: where it is read, and how it is written if lathed writes it."""
    name: str
    ref: Ref
    unit: str = ""
    scale: float = 1.0
    # a text's (LocalizedText, String) number, or an enumeration's ("0" = 1): the value lathed knows
    states: dict[str, float] = field(default_factory=dict)
    writable: bool = False
    method: Ref | None = None          # written by calling this method on ``obj``, not by a write
    obj: Ref | None = None
    args: tuple = ()                   # the method's leading arguments (a tool number), then the value
    # filled by resolve():
    node: ua.NodeId | None = None
    vtype: ua.VariantType | None = None        # the type a write or a method's value goes in
    method_node: ua.NodeId | None = None
    obj_node: ua.NodeId | None = None
    arg_types: tuple = ()                      # the method's leading arguments' types, from the server

    def arguments(self, value: float) -> list[ua.Variant]:
        """A method's input: its leading arguments in the types the server declares, then the value."""
        return [ua.Variant(a, t) for a, t in zip(self.args, self.arg_types)] + [self.variant(value)]

    def number(self, value: Any) -> float | None:
        """The value as a number in lathed's unit, or None (a text not in ``states``, null)."""
        if isinstance(value, ua.LocalizedText):
            value = value.Text
        if isinstance(value, str):
            v = self.states.get(value)
            return None if v is None else float(v)
        if isinstance(value, bool):
            return 1.0 if value else 0.0
        if self.states and isinstance(value, int):    # an enumeration's value (40501's ChannelState)
            v = self.states.get(str(value))
            return None if v is None else float(v)
        if isinstance(value, (int, float)) and math.isfinite(float(value)):
            return float(value) * self.scale
        return None

    def variant(self, value: float) -> ua.Variant:
        """``value`` (lathed's unit) in the node's type; an integer never further from zero than
        the value the guard checked (7.5 um to a 1 um node is 7, not 8)."""
        raw = value / self.scale
        if self.vtype == ua.VariantType.Boolean:
            return ua.Variant(raw != 0, self.vtype)
        if self.vtype in INTEGER:
            raw = int(math.trunc(raw + math.copysign(1e-6, raw)))
            lo, hi = INTEGER[self.vtype]
            if not lo <= raw <= hi:
                raise ValueError(f"{value:g} does not fit {self.name}'s {self.vtype.name} node")
            return ua.Variant(raw, self.vtype)
        return ua.Variant(float(raw), self.vtype)


def read_node_map(sec: Section, plausible: Plausibility | None = None) -> dict[str, Entry]:
    entries: dict[str, Entry] = {}
    for key in sec.keys():
        if not sec.has_section(key):
            raise sec.error(key, f"expected a table {{ node = ... }} or {{ path = ... }}, got {sec.get(key)!r}")
    for sub in sec.subsections():
        node, path = sub.getstr("node", ""), sub.getstr("path", "")
        if bool(node) == bool(path):
            raise sub.error(None, "give node (a node id) or path (a browse path from root), one of them")
        try:
            ref = Ref.parse(node or path, is_path=bool(path))
        except ValueError as e:
            raise sub.error("node" if node else "path", str(e)) from None
        e = Entry(sub.name, ref, unit=sub.getstr("unit", ""), scale=sub.getfloat("scale", 1.0),
                  writable=sub.getbool("writable", False))
        if e.scale == 0 or not math.isfinite(e.scale):
            raise sub.error("scale", "must be a finite number other than 0")
        states = sub.getsection("states", required=False)
        for text in states.keys():
            e.states[text] = states.getfloat(text)
        if "method" in sub:
            try:
                e.method = Ref.parse(sub.getstr("method"), is_path=False)
                e.obj = Ref.parse(sub.getstr("object"), is_path=False)
            except ValueError as err:
                raise sub.error("method", str(err)) from None
            args = sub.getlist("args", [], item=object)
            if any(isinstance(a, bool) or not isinstance(a, (int, float, str)) for a in args):
                raise sub.error("args", "the method's leading arguments are numbers or strings")
            e.args = tuple(args)
            if not e.writable:
                raise sub.error("method", "a method writes the value: give writable = true too")
        if e.writable and e.name not in WRITABLE:   # a typo would leave the action without its node
            raise sub.error("writable", f"no action writes {e.name!r}; writable values: {', '.join(WRITABLE)}")
        if e.name in IDENTITY and (e.writable or e.unit or e.states):
            raise sub.error(None, f"{e.name} is the nameplate's text: read once at connect, as it is")
        if plausible is not None and e.name not in IDENTITY and \
                (why := plausible.unit_problem(e.name, e.unit, sec.table.rsplit(".", 1)[0] + ".plausible")):
            raise sub.error("unit", why)
        sub.check_unused()
        entries[e.name] = e
    if not any(n not in IDENTITY for n in entries):
        raise sec.error(None, "no value mapped; add [<table>.NAME] tables with node or path")
    return entries


def read_namespaces(sec: Section) -> dict[str, str]:
    out = dict(BUILTIN_NAMESPACES)
    for alias in sec.keys():
        if alias.isdigit():
            raise sec.error(alias, "an alias must not be a number (ns=2 is an index)")
        out[alias] = sec.getstr(alias)
    return out


class Resolver:
    """Turns a map's references into the server's node ids, on a connected asyncua client."""

    def __init__(self, client, aliases: dict[str, str], root: Ref | None):
        self.client, self.aliases, self.root = client, aliases, root
        self._index: dict[str, int] = {}

    async def start(self) -> None:
        array = await self.client.get_namespace_array()
        self._index = {uri: i for i, uri in enumerate(array)}

    def ns_index(self, ns: str | int, where: str) -> int:
        if isinstance(ns, int):
            return ns
        uri = self.aliases.get(ns, ns)
        if uri not in self._index:
            what = f"namespace {ns!r} ({uri})" if uri != ns else f"namespace {uri}"
            raise MapError(f"{where}: the server has no {what}: a map for another control?")
        return self._index[uri]

    def node_id(self, ref: Ref, where: str) -> ua.NodeId:
        idx = self.ns_index(ref.ns, where)
        ident: Any = ref.ident
        if ref.kind == "i":
            ident = int(ident)
        elif ref.kind in ("g", "b"):
            return ua.NodeId.from_string(f"ns={idx};{ref.kind}={ref.ident}")
        return ua.NodeId(ident, idx)

    async def root_node(self) -> ua.NodeId:
        """The root of the browse paths: a node id, or a path from the Objects folder."""
        if self.root is None:
            return ua.NodeId(ua.ObjectIds.ObjectsFolder)
        if not self.root.path:
            return self.node_id(self.root, "root")
        return (await self.paths(ua.NodeId(ua.ObjectIds.ObjectsFolder), [(self.root, "root")]))[0]

    async def paths(self, start: ua.NodeId, refs: list[tuple[Ref, str]]) -> list[ua.NodeId]:
        """Browse paths to node ids, in one request."""
        rpaths = []
        for ref, where in refs:
            els = [ua.RelativePathElement(ReferenceTypeId=ua.NodeId(ua.ObjectIds.HierarchicalReferences),
                                          IsInverse=False, IncludeSubtypes=True,
                                          TargetName=ua.QualifiedName(name, self.ns_index(ns, where)))
                   for ns, name in ref.path]
            rpaths.append(ua.RelativePath(Elements=els))
        results = await self.client.translate_browsepaths(start, rpaths) if rpaths else []
        out = []
        for (ref, where), res in zip(refs, results):
            if not res.StatusCode.is_good() or not res.Targets:
                raise MapError(f"{where}: no node at {ref.text!r} ({res.StatusCode.name}): a map for "
                               "another control, or root wrong?")
            tid = res.Targets[0].TargetId      # an ExpandedNodeId: on this server, so a plain one
            out.append(ua.NodeId(tid.Identifier, tid.NamespaceIndex, tid.NodeIdType))
        return out
