"""CNC machines through their control's own OPC UA server; the node map in the config.

Every mapped value is read by one subscription (each publish a frame; a keep-alive confirms
them; none within ``stale_after``: stale, the link reopened). Commands and interlocks are
lathed.cnc's, as for modbus_cnc; the nameplate nodes must match ``[identification]`` before
the first command. Keys: docs/configuration.md; behaviour and security: docs/machines.md.
"""
from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections import Counter

from lathed import hookimpl
from lathed.cnc import ACTION_TARGETS, CncDriver
from lathed.command import Command
from lathed.config import ConfigError, Section
from lathed.extras import missing

# asyncua and lathed's OPC UA client, imported with the first machine of this type (seconds of
# import no daemon without one should pay); without the opcua extra the constructor says which
ua = ua_map = AlarmEvents = Refused = Security = close_quietly = None


def _import_opcua() -> None:
    global ua, ua_map, AlarmEvents, Refused, Security, close_quietly
    from asyncua import ua

    from lathed import ua_map
    from lathed.ua_alarms import AlarmEvents
    from lathed.ua_session import Refused, Security, close_quietly

HEARTBEAT_MAX = 32767
EVENTS_HANDLE = 0          # the alarms' monitored item; the values' are 1..n


class OpcUaCNC(CncDriver):
    def __init__(self, name: str, section: Section):
        super().__init__(name, section)
        if (why := missing("asyncua")) is not None:
            raise section.error("plugin", f"the opcua_cnc driver cannot run: {why}")
        _import_opcua()
        self.kind = section.getstr("kind", "lathe", choices=("lathe", "mill", "grinder"))
        self.security = Security(section)
        self.where = self.security.url
        self.timeout = section.getduration("timeout", 2.0, minval=0.1, maxval=60)
        self.publish_interval = section.getduration("publish_interval", 0.1, minval=0.01, maxval=10)
        self.keepalive = section.getduration("keepalive", max(0.5, self.publish_interval), minval=self.publish_interval,
                                             maxval=60)
        stale_after = section.getduration("stale_after", max(2.0, 3 * self.keepalive), minval=0.05)
        if stale_after <= 2 * self.keepalive:
            raise section.error("stale_after", f"must be longer than two keep-alives ({2 * self.keepalive:g} s): "
                                               "a quiet subscription would go stale between them")
        self.session_timeout = section.getduration("session_timeout", 60.0, minval=5, maxval=3600)
        self.aliases = ua_map.read_namespaces(section.getsection("namespaces", required=False))
        root = section.getstr("root", "")
        try:
            self.root = ua_map.Ref.parse(root, is_path="=" not in root) if root else None
        except ValueError as e:
            raise section.error("root", str(e)) from None
        self.entries = ua_map.read_node_map(section.getsection("nodes"), self.plausible)
        alarms = section.getsection("alarms", required=False)
        self.alarms = AlarmEvents(alarms) if alarms.keys() else None
        if self.root is None and (any(e.ref.path for e in self.entries.values())
                                  or (self.alarms is not None and self.alarms.ref.path)):
            raise section.error("root", "missing: the map names nodes by path, from this node "
                                        "(a node id, or a path from the Objects folder)")
        refs = [r for e in self.entries.values() for r in (e.ref, e.method, e.obj) if r is not None]
        refs += [r for r in (self.root, self.alarms and self.alarms.ref) if r]
        used = set().union(*(r.namespaces() for r in refs)) | {self.alarms.code[0] if self.alarms and
                                                               self.alarms.code else 0}
        for key in sorted(self.aliases.keys() - ua_map.BUILTIN_NAMESPACES.keys() - used):
            raise section.getsection("namespaces").error(key, "not used by any node: a typo?")
        self.identity = {n: e for n, e in self.entries.items() if n in ua_map.IDENTITY}
        self.readings = {n: e for n, e in self.entries.items() if n not in ua_map.IDENTITY}
        writable = {n for n, e in self.readings.items() if e.writable}
        self.setup_cnc(section, self.readings.keys(), writable, "nodes", stale_after,
                       threading_max_age=2 * self.keepalive + self.timeout, alarms_elsewhere=self.alarms is not None)
        hb = self.readings.get("heartbeat")
        if hb is not None and not hb.writable:
            raise section.error("nodes", "heartbeat must be writable: lathed writes it, the control watches it")
        self.heartbeat_every = (section.getduration("heartbeat_every", 0.5, minval=0.05, maxval=10.0)
                                if hb is not None else None)
        checked = [k for k in self.identity if k in self.identification]
        if self.actions and not checked:
            raise section.error("nodes", "this machine takes commands, so its control must say it is the configured "
                                         "one: map serial_number (or manufacturer, model) to the control's nameplate "
                                         "node and give it in [identification]")
        self.client = None
        self._lost: str | None = None
        self._wake = asyncio.Event()
        self._by_handle: dict[int, str] = {}
        self._image: dict[str, float] = {}         # the control's values now, by name
        self._reported: set[str] = set()           # names whose first notification came
        self._bad: dict[str, str] = {}             # name -> the status code that made it unusable
        self._last_publish: float | None = None    # monotonic time of the last publish (data or keep-alive)
        self._last_frame_t = 0.0
        self.subscription: dict = {}
        self.counts: Counter = Counter()
        self.errors: Counter = Counter()
        self.beats = 0
        self.reported_identity: dict[str, str | None] = {}

    def linked(self) -> bool:
        return self.client is not None and self._lost is None

    # -- connecting ------------------------------------------------------------
    async def connect(self) -> None:
        self._lost, self._last_publish = None, None
        self._image.clear()
        self._reported.clear()
        self._bad.clear()
        self._wake = asyncio.Event()      # this connect's loop (a test runs a driver in several)
        try:
            self.client = await self.security.open(self.name, self.timeout, self.session_timeout)
        except ConfigError:
            self.errors["config"] += 1
            raise
        except ConnectionError:
            self.errors["connect"] += 1
            raise
        self.client.connection_lost_callback = self._connection_lost
        step = "resolving the node map"
        try:
            await self._resolve()
            step = "reading the nameplate"
            await self._confirm_identity()
            step = "subscribing"
            await self._subscribe()
            # the first values prove the control answers: an open session is not a machine
            await self._first_values()
        except ua.UaStatusCodeError as e:
            self.errors["refused"] += 1
            raise ConnectionError(f"the OPC UA server at {self.where} refused a request while {step}: "
                                  f"{type(e).__name__}") from None
        except asyncio.TimeoutError:
            self.errors["timeout"] += 1
            raise TimeoutError(f"the OPC UA server at {self.where} did not answer within {self.timeout:g} s while "
                               f"{step} (server overloaded or link lost?)") from None
        await self._beat()          # the control's watchdog is armed as soon as the link is up
        self.held_at_connect()
        self.model.link_up()

    async def _resolve(self) -> None:
        r = ua_map.Resolver(self.client, self.aliases, self.root)
        try:
            await r.start()
            paths = any(e.ref.path for e in self.entries.values()) or (self.alarms and self.alarms.ref.path)
            start = await r.root_node() if paths else None
            if self.alarms is not None:
                where = self.section_name("alarms")
                self.alarms.node = ((await r.paths(start, [(self.alarms.ref, where)]))[0] if self.alarms.ref.path
                                    else r.node_id(self.alarms.ref, where))
                self._ns_index = lambda ns: r.ns_index(ns, f"{where} code")
            by_path = [(e, f"{self.section_name('nodes')}.{e.name}") for e in self.entries.values() if e.ref.path]
            for e, node in zip([e for e, _ in by_path], await r.paths(start, [(e.ref, w) for e, w in by_path])):
                e.node = node
            for e in self.entries.values():
                where = f"{self.section_name('nodes')}.{e.name}"
                if not e.ref.path:
                    e.node = r.node_id(e.ref, where)
                if e.method is not None:
                    e.method_node, e.obj_node = r.node_id(e.method, where), r.node_id(e.obj, where)
        except ua_map.MapError as err:
            self.errors["map"] += 1
            raise ConnectionError(str(err)) from None
        nodes = [e.node for e in self.entries.values()]
        classes = await self.client.uaclient.read_attributes(nodes, ua.AttributeIds.NodeClass)
        for e, dv in zip(self.entries.values(), classes):
            if not dv.StatusCode.is_good() or dv.Value.Value != ua.NodeClass.Variable:
                self.errors["map"] += 1
                what = "no such node" if not dv.StatusCode.is_good() else f"a {ua.NodeClass(dv.Value.Value).name}"
                raise ConnectionError(f"{self.section_name('nodes')}.{e.name}: {e.ref.text} is {what} on "
                                      f"{self.where}, not a variable: a map for another control?")
        for e in (e for e in self.readings.values() if e.writable):
            e.vtype = await self._write_type(e)

    async def _write_type(self, e):
        """The type a write (or the method's value argument) takes, from the server."""
        where = f"{self.section_name('nodes')}.{e.name}"
        if e.method is not None:
            method = self.client.get_node(e.method_node)
            try:
                args = await (await method.get_child("0:InputArguments")).read_value()
            except ua.UaStatusCodeError:
                raise ConnectionError(f"{where}: method {e.method.text} on {self.where} has no input arguments: "
                                      "a map for another control?") from None
            if len(args) != len(e.args) + 1:
                raise ConnectionError(f"{where}: method {e.method.text} takes {len(args)} arguments; the map gives "
                                      f"{len(e.args)} (args) and the value")
            e.arg_types = tuple(_builtin(a.DataType) for a in args[:-1])
            if None in e.arg_types:
                raise ConnectionError(f"{where}: method {e.method.text} takes an argument of a structured type: "
                                      "lathed passes numbers and texts only")
            dtype = args[-1].DataType
        else:
            dv = (await self.client.uaclient.read_attributes([e.node], ua.AttributeIds.AccessLevel))[0]
            if not dv.StatusCode.is_good() or not ua.ua_binary.test_bit(dv.Value.Value, ua.AccessLevel.CurrentWrite):
                raise ConnectionError(f"{where}: {e.ref.text} is read-only on {self.where}: this control takes "
                                      "no such command there")
            dtype = (await self.client.uaclient.read_attributes([e.node], ua.AttributeIds.DataType))[0].Value.Value
        vtype = _builtin(dtype)
        if vtype not in ua_map.WRITABLE_TYPES:
            raise ConnectionError(f"{where}: {e.ref.text} takes a {dtype.to_string()}, not a number lathed writes")
        return vtype

    def section_name(self, sub: str) -> str:
        return f"[machine.{self.name}.{sub}]"

    async def _confirm_identity(self) -> None:
        """The control's nameplate, as its server reports it, against the configured one: a
        different machine at this address (a swapped IP, a simulator left running) takes nothing."""
        if not self.identity:
            return
        dvs = await self.client.uaclient.read_attributes([e.node for e in self.identity.values()],
                                                         ua.AttributeIds.Value)
        self.reported_identity = {}
        for (key, e), dv in zip(self.identity.items(), dvs):
            v = dv.Value.Value if dv.StatusCode.is_good() and dv.Value is not None else None
            v = v.Text if isinstance(v, ua.LocalizedText) else v
            self.reported_identity[key] = v
            want = self.identification.get(key)
            if want is not None and (v is None or str(v).strip() != str(want).strip()):
                self.errors["identity"] += 1
                raise Refused(f"the control at {self.where} reports {key.replace('_', ' ')} {v!r}, "
                              f"[machine.{self.name}.identification] says {want!r}: not the configured machine, "
                              "nothing is sent to it")

    async def identify(self) -> dict | None:
        """The nameplate the control reported at this connect (its mapped nameplate nodes), for
        the supervisor's check of the peer (issue 35's Driver.identify)."""
        return {k: v for k, v in self.reported_identity.items() if v is not None} or None

    async def _subscribe(self) -> None:
        ka = max(1, math.ceil(self.keepalive / self.publish_interval - 1e-9))
        params = ua.CreateSubscriptionParameters(
            RequestedPublishingInterval=self.publish_interval * 1000, RequestedMaxKeepAliveCount=ka,
            RequestedLifetimeCount=max(3 * ka, math.ceil(self.session_timeout / self.publish_interval)),
            MaxNotificationsPerPublish=0, PublishingEnabled=True, Priority=0)
        client = self.client      # a late publish of a client closed since is not this link's
        res = await client.uaclient.create_subscription(params, lambda result: self._on_publish(client, result))
        revised_ka = res.RevisedPublishingInterval / 1000 * res.RevisedMaxKeepAliveCount
        self.subscription = {"id": res.SubscriptionId, "publish_interval_s": res.RevisedPublishingInterval / 1000,
                             "keepalive_s": round(revised_ka, 3)}
        if 2 * revised_ka >= self.stale_after:
            raise ConnectionError(f"the OPC UA server at {self.where} revised the subscription's keep-alive to "
                                  f"{revised_ka:g} s: stale_after ({self.stale_after:g} s) must be longer than two")
        items = []
        self._by_handle = {}
        for handle, (name, e) in enumerate(self.readings.items(), start=1):
            self._by_handle[handle] = name
            items.append(ua.MonitoredItemCreateRequest(
                ItemToMonitor=ua.ReadValueId(NodeId=e.node, AttributeId=ua.AttributeIds.Value),
                MonitoringMode=ua.MonitoringMode.Reporting,
                RequestedParameters=ua.MonitoringParameters(ClientHandle=handle, SamplingInterval=self.publish_interval
                                                             * 1000, QueueSize=1, DiscardOldest=True)))
        if self.alarms is not None:
            self.alarms.reset()
            items.append(ua.MonitoredItemCreateRequest(
                ItemToMonitor=ua.ReadValueId(NodeId=self.alarms.node, AttributeId=ua.AttributeIds.EventNotifier),
                MonitoringMode=ua.MonitoringMode.Reporting,
                RequestedParameters=ua.MonitoringParameters(ClientHandle=EVENTS_HANDLE, SamplingInterval=0,
                                                             QueueSize=1000, DiscardOldest=False,
                                                             Filter=self.alarms.event_filter(self._ns_index))))
        results = await self.client.uaclient.create_monitored_items(ua.CreateMonitoredItemsParameters(
            SubscriptionId=res.SubscriptionId, ItemsToCreate=items, TimestampsToReturn=ua.TimestampsToReturn.Both))
        for (name, what), r in zip([*((n, e.ref.text) for n, e in self.readings.items()),
                                    ("alarms", self.alarms and self.alarms.ref.text)], results):
            if not r.StatusCode.is_good():
                self.errors["map"] += 1
                raise ConnectionError(f"{self.section_name('nodes' if name != 'alarms' else 'alarms')}"
                                      f"{'.' + name if name != 'alarms' else ''}: the server refused to watch "
                                      f"{what}: {r.StatusCode.name}")
        if self.alarms is not None:
            # the conditions active now, each once: the set is told when the refresh ends
            refresh = ua.CallMethodRequest(ObjectId=ua.NodeId(ua.ObjectIds.ConditionType),
                                           MethodId=ua.NodeId(ua.ObjectIds.ConditionType_ConditionRefresh),
                                           InputArguments=[ua.Variant(res.SubscriptionId, ua.VariantType.UInt32)])
            status = (await self.client.uaclient.call([refresh]))[0].StatusCode
            self.alarms.requested = True
            if not status.is_good():
                # the alarms are then known as they change only: said, recorded, and the link goes on
                self.errors["alarm_refresh"] += 1
                self.alarms.refreshed = True
                payload = {"machine": self.name, "status": status.name,
                           "why": "the server cannot refresh its conditions: an alarm active before this "
                                  "connect is not known until it changes"}
                self.ctx.log.warning("alarm_refresh_refused", **payload)
                self._record("alarm_refresh_refused", payload)

    async def _first_values(self) -> None:
        deadline = time.monotonic() + max(self.stale_after, self.timeout)
        while (len(self._reported) < len(self.readings) or (self.alarms is not None and not self.alarms.refreshed)) \
                and self._lost is None:
            left = deadline - time.monotonic()
            if left <= 0:
                missing = sorted(set(self.readings) - self._reported) + (
                    ["the active alarms (ConditionRefresh)"] if self.alarms and not self.alarms.refreshed else [])
                raise ConnectionError(f"the OPC UA server at {self.where} sent no first value of "
                                      f"{', '.join(missing)} within {max(self.stale_after, self.timeout):g} s")
            self._wake.clear()
            with contextlib.suppress(asyncio.TimeoutError):
                async with asyncio.timeout(left):
                    await self._wake.wait()
        if self._lost is not None:
            raise ConnectionError(self._lost)

    # -- the subscription ----------------------------------------------------------
    async def _connection_lost(self, exc: Exception) -> None:
        self._drop(f"OPC UA link to {self.where} lost: {type(exc).__name__} {exc}".strip())

    def _drop(self, why: str) -> None:
        if self._lost is None:
            self._lost = why
        self.model.link_down()
        self._wake.set()

    def _on_publish(self, client, result) -> None:
        """One publish response: data changes, events, a status change, or a keep-alive. In
        the publish loop, synchronously: the notifications of one response are one frame."""
        if client is not self.client:
            return
        now = time.time()
        self._last_publish = time.monotonic()
        newest = None
        for notif in result.NotificationMessage.NotificationData or []:
            if isinstance(notif, ua.StatusChangeNotification):
                self.counts["status_changes"] += 1
                self._drop(f"the OPC UA server at {self.where} ended the subscription: {notif.Status.name}")
                return
            if isinstance(notif, ua.EventNotificationList):
                for ev in notif.Events:
                    self.counts["events"] += 1
                    if ev.ClientHandle == EVENTS_HANDLE and self.alarms.take(ev.EventFields):
                        self.model.set_alarms(self.alarms.codes(), now)
                continue
            if not isinstance(notif, ua.DataChangeNotification):
                continue
            for item in notif.MonitoredItems:
                name = self._by_handle.get(item.ClientHandle)
                if name is None:
                    continue
                self.counts["notifications"] += 1
                self._reported.add(name)
                dv = item.Value
                status = dv.StatusCode
                v = self.readings[name].number(dv.Value.Value if dv.Value is not None else None) \
                    if status is None or status.is_good() else None
                if v is None:
                    # unusable (Bad, Uncertain, a text the map does not know): its last value goes
                    # stale, never kept as if it held (a threading signal then refuses commands)
                    self._bad[name] = status.name if status is not None and not status.is_good() else "unmapped value"
                    self._image.pop(name, None)
                    self.values.pop(name, None)
                    self.counts["unusable"] += 1
                    continue
                self._bad.pop(name, None)
                self._image[name] = v
                ts = dv.SourceTimestamp
                if ts is not None:
                    newest = max(newest or 0.0, ts.timestamp())
        # one stamp for the frame: the newest change's own time where the clocks agree (a value
        # changed between the last frame and now), else the arrival
        t = newest if newest is not None and self._last_frame_t - 0.05 <= newest <= now + 0.05 else now
        t = max(t, self._last_frame_t)
        self._last_frame_t = t
        for name, v in self._image.items():
            if not self.take(name, v, self.readings[name].unit, t):
                self.counts["refused"] += 1
        # the frame above stamped every value the subscription holds: what was not sent again
        # still holds (the server reports each change); the alarms likewise, once the refresh told them
        if self.alarms is not None and (self.alarms.settle() or self.alarms.refreshed):
            self.model.set_alarms(self.alarms.codes(), t)
        self.counts["publishes"] += 1
        self.mark_data()
        self._wake.set()

    async def run(self) -> None:
        next_beat = time.monotonic() + (self.heartbeat_every or math.inf)
        while True:
            if self._lost is not None:
                raise ConnectionError(self._lost)
            now = time.monotonic()
            quiet = now - (self._last_publish or now)
            if quiet > self.stale_after:
                self.errors["stale"] += 1
                self._drop(f"no publish (data or keep-alive) from the OPC UA server at {self.where} for "
                           f"{quiet:.1f} s: subscription stale")
                raise TimeoutError(self._lost)
            if now >= next_beat:
                await self._beat()
                next_beat = now + self.heartbeat_every
            wake = min(next_beat, (self._last_publish or now) + self.stale_after + 0.01)
            self._wake.clear()
            with contextlib.suppress(asyncio.TimeoutError):
                async with asyncio.timeout(max(0.0, wake - time.monotonic())):
                    await self._wake.wait()

    async def _beat(self) -> None:
        e = self.readings.get("heartbeat")
        if e is None or self.client is None:
            return
        n = self.beats % HEARTBEAT_MAX + 1
        await self._write(e, float(n))
        self.beats = n

    async def close(self) -> None:
        client, self.client = self.client, None
        self.model.link_down()
        if client is not None:
            await close_quietly(client)

    # -- commands ------------------------------------------------------------------
    async def execute(self, cmd: Command) -> dict | None:
        detail = None
        if cmd.action == "spindle_rpm" and self.speed_by_override:
            value, rpm = self.override_for(float(cmd.value))
            e = self.readings["spindle_override_pct"]
            detail = {"override_pct": value, "rpm_effective": round(rpm, 1)}
        else:
            value, e = float(cmd.value), self.readings.get(ACTION_TARGETS.get(cmd.action, ""))
            if cmd.action not in self.actions or e is None or not e.writable:
                # only the supervisor calls this, after the guard; anything else is a bug
                raise PermissionError(f"{self.name}: no writable node for action {cmd.action!r}")
        if not self.linked():
            raise ConnectionError("not connected")
        # asked again as the write goes, nothing awaited in between: a publish handled since the
        # guard passed it may have brought a thread's start (the subscription sends the signal
        # within a publishing interval of its change, as a poll would read it)
        why = self.interlock(cmd)
        if why is not None:
            raise PermissionError(why)
        if detail is not None:
            self.override_written(value, None, pending=True)   # applied but answered late: still ours
        await self._write(e, value)
        self.counts["writes"] += 1
        if detail is not None:
            self.override_written(value, rpm)
        else:
            self.values[e.name] = (value, time.time())
        return detail

    async def _write(self, e, value: float) -> None:
        variant = e.variant(value)
        try:
            if e.method is not None:
                call = ua.CallMethodRequest(ObjectId=e.obj_node, MethodId=e.method_node,
                                            InputArguments=e.arguments(value))
                status = (await self.client.uaclient.call([call]))[0].StatusCode
            else:
                status = (await self.client.uaclient.write_attributes([e.node], [ua.DataValue(variant)]))[0]
        except asyncio.TimeoutError:
            self.errors["timeout"] += 1
            raise TimeoutError(f"the OPC UA server at {self.where} did not answer the write of {e.name} within "
                               f"{self.timeout:g} s") from None
        if not status.is_good():
            self.errors["write_refused"] += 1
            raise RuntimeError(f"the control refused {value:g} for {e.name} ({e.ref.text}): {status.name}")

    def status(self) -> dict:
        now = time.monotonic()
        return {"spindle_rpm": self.model.live("spindle_rpm"), "machine_state": self.model.state(),
                "model": self.model.snapshot(),
                "values": self.value_status({n: e.unit for n, e in self.readings.items()}),
                "unusable": dict(self._bad),
                **({"alarm_events": {"active": self.alarms.codes(), "messages": self.alarms.messages}}
                   if self.alarms is not None else {}),
                **({"heartbeat": {"every_s": self.heartbeat_every, "count": self.beats}}
                   if self.heartbeat_every else {}),
                "link": {"url": self.where, "security": self.security.describe(), "login": self.security.login,
                         "subscription": self.subscription, "counts": dict(self.counts), "errors": dict(self.errors),
                         "last_publish_age_s": None if self._last_publish is None
                         else round(now - self._last_publish, 3),
                         **({"lost": self._lost} if self._lost else {})}}


def _builtin(dtype) -> ua.VariantType | None:
    """A DataType node id's built-in type (Double, UInt16, String...), else None."""
    if dtype.NamespaceIndex == 0 and isinstance(dtype.Identifier, int) and 1 <= dtype.Identifier <= 25:
        return ua.VariantType(dtype.Identifier)
    return None


@hookimpl
def lathed_driver_types():
    return {"opcua_cnc": OpcUaCNC}
