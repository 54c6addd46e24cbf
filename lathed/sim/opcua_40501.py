"""The simulated control's OPC 40501 (Machine Tools) tree, beside its own namespace, as controls
that offer umati lay it out (SINUMERIK's OPC UA server serves both).

Objects/Machines/lathe, with the companion specification's browse names in their namespaces
(Machinery, DI, MachineTool) and the machine's element names (Spindle, Channel1) in the
control's: Identification (Manufacturer, Model, SerialNumber), Monitoring/Spindle (Override,
IsRotating), Monitoring/Channel1 (ChannelState, FeedOverride), Production/ActiveProgram/State/
CurrentState, Production/Statistics/PartsProducedInLifetime, Notification/Messages (an event
notifier). The browse names and meanings are 40501's; the type definitions are the base
types (the nodesets are not imported), which a client reading by browse path does not see.
"""
from __future__ import annotations

from asyncua import Node, Server, ua

MT, DI, MACHINERY = ("http://opcfoundation.org/UA/MachineTool/", "http://opcfoundation.org/UA/DI/",
                     "http://opcfoundation.org/UA/Machinery/")
# program_state (0 idle, 1 running, 2 alarm) -> ChannelState (Active 0, Interrupted 1, Reset 2) and
# the active program's CurrentState
CHANNEL_STATE = {0: 2, 1: 0, 2: 1}
PROGRAM_STATE = {0: "Ended", 1: "Running", 2: "Interrupted"}


class Tree40501:
    def __init__(self, server: Server, idx: int):
        self.server, self.idx = server, idx
        self.vars: dict[str, tuple[Node, ua.VariantType]] = {}
        self._last: dict[str, object] = {}

    async def build(self, identification: dict[str, str]) -> None:
        s, own = self.server, self.idx
        mt, di, machinery = [await s.register_namespace(u) for u in (MT, DI, MACHINERY)]
        machines = await s.nodes.objects.add_folder(ua.NodeId("Machines", machinery), ua.QualifiedName("Machines",
                                                                                                     machinery))
        lathe = await machines.add_object(ua.NodeId("Machines.lathe", own), ua.QualifiedName("lathe", own))

        async def obj(parent: Node, path: str, ns: int) -> Node:
            return await parent.add_object(ua.NodeId(f"Machines.lathe.{path}", own),
                                           ua.QualifiedName(path.rsplit(".", 1)[-1], ns))

        async def var(parent: Node, path: str, ns: int, value, vtype: ua.VariantType) -> None:
            node = await parent.add_variable(ua.NodeId(f"Machines.lathe.{path}", own),
                                             ua.QualifiedName(path.rsplit(".", 1)[-1], ns), ua.Variant(value, vtype))
            self.vars[path] = node, vtype
        ident = await obj(lathe, "Identification", di)
        for key, name, vtype in (("manufacturer", "Manufacturer", ua.VariantType.LocalizedText),
                                 ("model", "Model", ua.VariantType.LocalizedText),
                                 ("serial_number", "SerialNumber", ua.VariantType.String)):
            v = identification[key]
            await var(ident, f"Identification.{name}", di, ua.LocalizedText(v) if vtype == ua.VariantType.LocalizedText
                      else v, vtype)
        monitoring = await obj(lathe, "Monitoring", mt)
        spindle = await obj(monitoring, "Monitoring.Spindle", own)
        await var(spindle, "Monitoring.Spindle.Override", mt, 100.0, ua.VariantType.Double)
        await var(spindle, "Monitoring.Spindle.IsRotating", mt, False, ua.VariantType.Boolean)
        channel = await obj(monitoring, "Monitoring.Channel1", own)
        await var(channel, "Monitoring.Channel1.ChannelState", mt, 2, ua.VariantType.Int32)
        await var(channel, "Monitoring.Channel1.FeedOverride", mt, 100.0, ua.VariantType.Double)
        production = await obj(lathe, "Production", mt)
        program = await obj(production, "Production.ActiveProgram", mt)
        state = await obj(program, "Production.ActiveProgram.State", mt)
        await state.add_variable(ua.NodeId("Machines.lathe.Production.ActiveProgram.State.CurrentState", own),
                                 ua.QualifiedName("CurrentState", 0), ua.LocalizedText("Ended"))
        self.vars["Production.ActiveProgram.State.CurrentState"] = (
            s.get_node(ua.NodeId("Machines.lathe.Production.ActiveProgram.State.CurrentState", own)),
            ua.VariantType.LocalizedText)
        stats = await obj(production, "Production.Statistics", mt)
        await var(stats, "Production.Statistics.PartsProducedInLifetime", mt, 0, ua.VariantType.UInt32)
        notification = await obj(lathe, "Notification", mt)
        messages = await obj(notification, "Notification.Messages", mt)
        await messages.set_event_notifier([ua.EventNotifier.SubscribeToEvents])

    async def update(self, values: dict[str, float]) -> None:
        state = int(values.get("program_state", 0))
        now = {"Monitoring.Spindle.Override": float(values.get("spindle_override_pct", 100.0)),
               "Monitoring.Spindle.IsRotating": abs(values.get("spindle_rpm", 0.0)) > 0.5,
               "Monitoring.Channel1.ChannelState": CHANNEL_STATE.get(state, 1),
               "Monitoring.Channel1.FeedOverride": float(values.get("feed_override_pct", 100.0)),
               "Production.ActiveProgram.State.CurrentState": ua.LocalizedText(PROGRAM_STATE.get(state, "Interrupted")),
               "Production.Statistics.PartsProducedInLifetime": int(values.get("part_count", 0))}
        for path, v in now.items():
            if self._last.get(path) == v:
                continue
            self._last[path] = v
            node, vtype = self.vars[path]
            await self.server.write_attribute_value(node.nodeid, ua.DataValue(ua.Variant(v, vtype)))
