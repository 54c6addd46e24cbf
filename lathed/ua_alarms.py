"""A control's alarms as OPC UA conditions (OPC 40501's Notification/Messages: AlertType).

``[machine.NAME.alarms]`` names the object whose events carry them (``events``, a path from
the map's root or a node id) and the event field with an alarm's code (``code``, e.g.
"mt:ErrorCode"; else its message). An alarm is a condition whose ActiveState is true, keyed
by its ConditionId; the set is rebuilt from a ConditionRefresh at every connect, so an alarm
raised or cleared while the link was down is told once, when it returns (the refresh's
conditions come in the publish after its answer, between a RefreshStart and a RefreshEnd). Plain events (no
ActiveState) are messages, not alarms: counted only. docs/machines.md: OPC UA.
"""
from __future__ import annotations

from asyncua import ua

from lathed.config import Section
from lathed.ua_map import Ref

BASE, CONDITION = ua.NodeId(ua.ObjectIds.BaseEventType), ua.NodeId(ua.ObjectIds.ConditionType)
REFRESH_START, REFRESH_END = ua.NodeId(ua.ObjectIds.RefreshStartEventType), ua.NodeId(ua.ObjectIds.RefreshEndEventType)
# the fields selected, in this order (the code's last, where configured)
FIELDS = (("EventType",), ("SourceName",), ("Message",), ("Severity",), ("ActiveState", "Id"), ("Retain",))


class AlarmEvents:
    def __init__(self, sec: Section):
        path, node = sec.getstr("events", ""), sec.getstr("node", "")
        if bool(path) == bool(node):
            raise sec.error(None, "give events (a path from root to the object whose events carry the alarms) "
                                  "or node (its node id), one of them")
        try:
            self.ref = Ref.parse(path or node, is_path=bool(path))
        except ValueError as e:
            raise sec.error("events" if path else "node", str(e)) from None
        code = sec.getstr("code", "")
        self.code: tuple[str | int, str] | None = None
        if code:
            ns, sep, name = code.rpartition(":")
            if not name:
                raise sec.error("code", f"{code!r}: expected ALIAS:Name (e.g. \"mt:ErrorCode\")")
            self.code = (int(ns) if ns.isdigit() else ns) if sep else 0, name
        sec.check_unused()
        self.node: ua.NodeId | None = None
        self.active: dict[str, str] = {}      # ConditionId -> the alarm's code
        self.refreshing = False
        self.refreshed = False
        self.requested = False                # ConditionRefresh answered: its events are queued
        self.messages = 0

    def event_filter(self, ns_index) -> ua.EventFilter:
        """``ns_index(alias)``: the code field's namespace on this server."""
        def operand(*names: str, ns: int = 0) -> ua.SimpleAttributeOperand:
            return ua.SimpleAttributeOperand(TypeDefinitionId=BASE, AttributeId=ua.AttributeIds.Value,
                                             BrowsePath=[ua.QualifiedName(n, ns) for n in names])
        select = [operand(*f) for f in FIELDS]
        select.append(ua.SimpleAttributeOperand(TypeDefinitionId=CONDITION, AttributeId=ua.AttributeIds.NodeId))
        if self.code is not None:
            select.append(operand(self.code[1], ns=ns_index(self.code[0])))
        return ua.EventFilter(SelectClauses=select)

    def reset(self) -> None:
        """A new subscription: the set is rebuilt by its ConditionRefresh."""
        self.active, self.refreshing, self.refreshed, self.requested = {}, False, False, False

    def settle(self) -> bool:
        """At a publish's end: True when the refresh is over with it. A server that sends its
        RefreshStart and RefreshEnd only to monitored items of its Server object (asyncua does)
        still sends the conditions themselves here, in the publish after its answer."""
        if self.requested and not self.refreshed and not self.refreshing:
            self.refreshed = True
            return True
        return False

    def take(self, fields: list) -> bool:
        """One event's fields; True when the set of active alarms is known anew (to be told)."""
        values = [f.Value if isinstance(f, ua.Variant) else f for f in fields]
        etype, source, message, _severity, active, _retain, cond = values[:7]
        code = values[7] if len(values) > 7 else None
        if etype == REFRESH_START:
            self.refreshing, self.active = True, {}
            return False
        if etype == REFRESH_END:
            self.refreshing, self.refreshed = False, True
            return True
        if active is None or cond is None:
            self.messages += 1       # a message, not a condition
            return False
        text = message.Text if isinstance(message, ua.LocalizedText) else message
        key = cond.to_string() if isinstance(cond, ua.NodeId) else str(cond)
        if active:
            self.active[key] = str(code if code not in (None, "") else text or source or key)
        else:
            self.active.pop(key, None)
        return self.refreshed and not self.refreshing

    def codes(self) -> list[str]:
        return sorted(set(self.active.values()))
