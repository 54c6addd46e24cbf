"""lathed-opcua with real peers: a daemon on the simulator running the shipped configuration,
lathed-opcua as its own process, and asyncua's client. One daemon and one loopback server for
the module (the suite's time budget is tight); the non-loopback server only where needed."""
from __future__ import annotations

import asyncio
import json
import os
import socket
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest
from asyncua import Client, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography.x509.oid import ExtendedKeyUsageOID

from lathed.config import ConfigError
from lathed.opcua.app import Settings
from lathed.opcua.nodesets import DI, MACHINE_TOOL, MACHINERY, UA
from lathed.opcua.space import NAMESPACE
from lathed.web import accounts
from tests.conftest import BIN, ROOT, Daemon, events, free_port, shipped_config, sim_call, wait_until

CLIENT_URI = "urn:lathed:test-client"
WATCHDOG_S = 10.0    # asyncua 2's client probes the server every 1 s and reconnects after a 1 s stall: a loaded CI has those
NODE = ROOT / "tests" / "node"       # node-opcua, installed by tests/ensure_node_opcua.sh


def ua_client(url: str, **kw) -> Client:
    return Client(url, watchdog_intervall=WATCHDOG_S, **kw)


def opcua_config(tmp: Path, name: str, sock: Path, listen: str = "127.0.0.1", writable: bool = True,
                 extra: str = "") -> Path:
    cfg = tmp / f"{name}.toml"
    cfg.write_text(f"""
[opcua]
{extra}
listen = "{listen}"
port = {free_port()}
socket = "{sock}"
state_dir = "{tmp / name}"
writable = {str(writable).lower()}
rate_hz = 20.0

[users.olga]
role = "operator"
password = "{accounts.hash_password('olga-pw')}"

[users.victor]
role = "viewer"
password = "{accounts.hash_password('victor-pw')}"
""")
    return cfg


class OpcUa:
    """lathed-opcua as a process; ``url`` is where a client on this PC reaches it."""

    def __init__(self, cfg: Path):
        self.cfg = cfg
        self.port = int(next(l for l in cfg.read_text().splitlines() if l.startswith("port")).split("=")[1])
        self.url = f"opc.tcp://127.0.0.1:{self.port}"
        self.log = open(cfg.with_suffix(".log"), "wb")
        self.proc = subprocess.Popen([str(BIN / "lathed-opcua"), "--config", str(cfg)], stdout=self.log,
                                     stderr=subprocess.STDOUT)

    def wait_serving(self) -> None:
        def up():
            assert self.proc.poll() is None, f"lathed-opcua exited {self.proc.returncode}: {self.output()}"
            with socket.create_connection(("127.0.0.1", self.port), timeout=1):
                return True
        wait_until(up, timeout=180, what="lathed-opcua listening")

    def output(self, tail: int | None = 4000) -> str:
        self.log.flush()
        text = self.cfg.with_suffix(".log").read_text(errors="replace")
        return text[-tail:] if tail else text

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.log.close()


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("opcua")
    cfg, sock = shipped_config(tmp)
    d = Daemon(cfg, sock)
    d.paths = {"sim": tmp / "run" / "sim.sock"}
    server = OpcUa(opcua_config(tmp, "ua", sock))
    try:
        d.wait_ready()
        server.wait_serving()
        asyncio.run(_until_good(server.url, ["mt:Monitoring", "Spindle", "RotationalSpeed"]))
        stack = {"daemon": d, "server": server, "tmp": tmp, "sock": sock}
        yield stack
    finally:
        server.stop()
        stack["daemon"].stop() if "stack" in locals() else d.stop()


# -- helpers --------------------------------------------------------------------------
async def until(fn, timeout: float, what: str):
    """Poll an async condition (wait_until's asyncio twin)."""
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        try:
            if v := await fn():
                return v
        except (ua.UaError, KeyError) as e:   # not there yet
            last = e
        await asyncio.sleep(0.05)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}" + (f" (last: {last!r})" if last else ""))


PREFIX = {"mt": MACHINE_TOOL, "di": DI, "mc": MACHINERY, "ua": UA, "": NAMESPACE}


async def machine_node(c: Client, machine: str, *path: str):
    """A machine's node by its browse path from the Machinery Machines folder: "mt:Monitoring"
    is a child of a standard model's (mt 40501, mc Machinery, di DI, ua the base), a bare name
    lathed's own."""
    ns = await c.get_namespace_array()

    def q(p: str) -> ua.QualifiedName:
        prefix, _, name = p.rpartition(":")
        return ua.QualifiedName(name, ns.index(PREFIX[prefix]))
    folder = c.get_node(ua.NodeId(1001, ns.index(MACHINERY)))
    return await folder.get_child([q(machine), *(q(p) for p in path)])


async def lathe_node(c: Client, *path: str):
    return await machine_node(c, "lathe", *path)


async def _until_good(url: str, path: list[str], timeout: float = 60.0) -> None:
    async with ua_client(url, timeout=30) as c:     # the first status builds the machines meanwhile
        async def good():
            dv = await (await lathe_node(c, *path)).read_data_value()
            return dv.StatusCode.is_good()
        await until(good, timeout, f"{'/'.join(path)} good")


class Collect:
    """asyncua subscription handler: data changes and events into queues, stamped on arrival."""

    def __init__(self):
        self.changes: asyncio.Queue = asyncio.Queue()
        self.events: asyncio.Queue = asyncio.Queue()
        self.status: list = []      # the subscription's status changes (BadTimeout: it was dropped)

    def datachange_notification(self, node, val, data):
        self.changes.put_nowait((time.time(), data.monitored_item.Value))

    def event_notification(self, event):
        self.events.put_nowait((time.time(), event))

    def status_change_notification(self, status):
        self.status.append(status)


async def every_sample(sub, node, handle: int = 1) -> None:
    """Monitor ``node`` reporting every new sample (a new source time), not only a changed value."""
    rv = ua.ReadValueId()
    rv.NodeId, rv.AttributeId = node.nodeid, ua.AttributeIds.Value
    params = ua.MonitoringParameters()
    params.ClientHandle, params.SamplingInterval, params.QueueSize, params.DiscardOldest = handle, 0, 100, True
    params.Filter = ua.DataChangeFilter()
    params.Filter.Trigger = ua.DataChangeTrigger.StatusValueTimestamp
    req = ua.MonitoredItemCreateRequest()
    req.ItemToMonitor, req.MonitoringMode, req.RequestedParameters = rv, ua.MonitoringMode.Reporting, params
    (res,) = await sub.create_monitored_items([req])
    assert isinstance(res, int), res


def client_certificate(where: Path) -> tuple[Path, Path]:
    where.mkdir(parents=True, exist_ok=True)
    key, cert = where / "client-key.pem", where / "client-cert.der"
    asyncio.run(setup_self_signed_certificate(key, cert, CLIENT_URI, "localhost", [ExtendedKeyUsageOID.CLIENT_AUTH],
                                              {"commonName": "lathed test client"}))
    return key, cert


async def encrypted(url: str, key: Path, cert: Path, user: str | None = None, pw: str | None = None) -> Client:
    c = ua_client(url)
    c.application_uri = CLIENT_URI
    await c.set_security(SecurityPolicyBasic256Sha256, certificate=str(cert), private_key=str(key),
                         mode=ua.MessageSecurityMode.SignAndEncrypt)
    if user:
        c.set_user(user)
        c.set_password(pw)
    return c


# -- the tests ------------------------------------------------------------------------
def test_a_client_finds_every_machine_in_the_40501_layout(stack):
    async def go():
        async with ua_client(stack["server"].url) as c:
            ns = await c.get_namespace_array()
            machines = c.get_node(ua.NodeId(1001, ns.index(MACHINERY)))      # Machinery's Machines folder
            assert (await machines.read_browse_name()) == ua.QualifiedName("Machines", ns.index(MACHINERY))
            names = {(await n.read_browse_name()).Name for n in await machines.get_children()}
            assert names == {"lathe", "mill", "grinder", "robot"}
            tool = ua.NodeId(13, ns.index(MACHINE_TOOL))                       # MachineToolType
            for name in ("lathe", "mill", "grinder"):
                assert await (await machine_node(c, name)).read_type_definition() == tool
            # the robot arm is a Machinery machine, not a machine tool
            robot = await machine_node(c, "robot")
            assert await robot.read_type_definition() == ua.NodeId(ua.ObjectIds.BaseObjectType)
            assert (await (await machine_node(c, "robot", "di:Identification", "di:Model")).read_value()).Text == \
                "6-axis arm on CAN (simulated)"
            lathe = await lathe_node(c)
            parts = {(await n.read_browse_name()).Name for n in await lathe.get_children()}
            assert parts == {"Identification", "MachineryBuildingBlocks", "Monitoring", "Production", "Equipment",
                             "Notification"}
            # Identification from [machine.lathe.identification]
            assert (await (await lathe_node(c, "di:Identification", "di:Manufacturer")).read_value()).Text == \
                "lathed simulator"
            assert await (await lathe_node(c, "di:Identification", "di:SerialNumber")).read_value() == "SIM-LATHE-0001"
            assert await (await lathe_node(c, "di:Identification", "mc:YearOfConstruction")).read_value() == 2026
            assert await (await lathe_node(c, "di:Identification", "di:ProductInstanceUri")).read_value() == \
                "urn:lathed%20simulator:SIM-LATHE-0001"
            # live values: 40501's, and lathed's own beside them with their units
            speed = await lathe_node(c, "mt:Monitoring", "Spindle", "RotationalSpeed")
            dv = await speed.read_data_value()
            assert dv.StatusCode.is_good() and dv.Value.Value > 0
            assert await speed.read_type_definition() == ua.NodeId(ua.ObjectIds.AnalogUnitType)
            eu = await (await speed.get_child("0:EngineeringUnits")).read_value()
            assert (eu.DisplayName.Text, eu.UnitId) == ("r/min", 0x52504D)   # UNECE "RPM"
            assert await (await lathe_node(c, "mt:Monitoring", "Spindle", "mt:IsRotating")).read_value() is True
            override = await lathe_node(c, "mt:Monitoring", "Spindle", "mt:Override")   # suppression may move it
            assert 0 < await override.read_value() <= 254
            assert (await (await override.get_child("0:EURange")).read_value()).High == 254
            state = await lathe_node(c, "mt:Monitoring", "Channel1", "mt:ChannelState")
            assert await state.read_value() in (0, 1, 2)
            assert await state.read_data_type() == ua.NodeId(64, ns.index(MACHINE_TOOL))   # the ChannelState enum
            assert (await (await lathe_node(c, "mt:Monitoring", "mt:MachineTool", "mc:MachineryItemState",
                                            "ua:CurrentState")).read_value()).Text in ("Executing", "NotExecuting")
            # the lathe's analyzers: chatter index, thermal growth and compensation, suppression mode
            for path in (("Chatter", "ChatterIndex"), ("Chatter", "ChatterThreshold"), ("Thermal", "ThermalGrowth"),
                         ("Thermal", "Compensation")):
                node = await until(lambda: lathe_node(c, "mt:Monitoring", *path), 20, "/".join(path))
                assert (await node.read_data_value()).StatusCode.is_good()
            eu = await (await (await lathe_node(c, "mt:Monitoring", "Thermal", "ThermalGrowth")).get_child(
                "0:EngineeringUnits")).read_value()
            assert eu.DisplayName.Text == "µm"
            assert await (await lathe_node(c, "mt:Monitoring", "Suppression", "Mode")).read_value() == "auto"
            # production: the active program and its state; lathed's part count and cycle time
            for path in (("mt:ActiveProgram", "mt:Name"), ("mt:ActiveProgram", "mt:State", "ua:CurrentState"),
                         ("PartCount",), ("CycleTime",)):
                assert (await (await lathe_node(c, "mt:Production", *path)).read_data_value()).StatusCode.is_good()
            # another machine of the line: the mill's Z axis
            z = await machine_node(c, "mill", "mt:Monitoring", "Axes", "Z")
            assert (await z.read_data_value()).StatusCode.is_good()
            assert await (await lathe_node(c, "mt:Notification", "mt:Messages")).read_event_notifier() == \
                {ua.EventNotifier.SubscribeToEvents}
    asyncio.run(go())


def test_node_opcua_reads_every_machine_by_the_standard_browse_paths(stack):
    """node-opcua, knowing only the companion specifications: the Machines folder by its NodeId,
    the machine tools by their type, their monitored elements by theirs."""
    r = subprocess.run(["node", str(NODE / "browse_machines.mjs"), stack["server"].url], capture_output=True,
                       text=True, timeout=120, cwd=NODE, env={**os.environ, "HOME": str(stack["tmp"])})
    assert r.returncode == 0, r.stderr[-3000:]
    (line,) = [ln for ln in r.stdout.splitlines() if ln.startswith("RESULT ")]   # node-opcua logs there too
    out = json.loads(line.removeprefix("RESULT "))
    machines = out["machines"]
    assert set(machines) == {"lathe", "mill", "grinder", "robot"}
    assert {n for n, m in machines.items() if m["machineTool"]} == {"lathe", "mill", "grinder"}
    mt = f"ns={out['namespaces']['machineTool']};i="
    for name, m in machines.items():
        v = m["values"]
        assert v["di:Identification/di:Manufacturer"] == {"value": "lathed simulator", "status": "Good",
                                                          "dataType": "ns=0;i=21"}, name
        assert v["di:Identification/di:SerialNumber"]["value"] == f"SIM-{name.upper()}-0001"
        assert v["mc:MachineryBuildingBlocks/mc:MachineryItemState/ua:CurrentState"]["value"] in (
            "Executing", "NotExecuting", "OutOfService", "NotAvailable")
        if not m["machineTool"]:
            continue
        assert m["parts"] == ["Equipment", "Identification", "MachineryBuildingBlocks", "Monitoring", "Notification",
                              "Production"]
        assert m["notification"] == ["Messages", "Prognoses"] and m["messagesEventNotifier"] == 1
        assert v["mt:Monitoring/mt:MachineTool/mt:OperationMode"]["dataType"] == mt + "65"
        assert v["mt:Production/mt:ActiveProgram/mt:Name"]["status"] == "Good"
        assert v["mt:Production/mt:ActiveProgram/mt:State/ua:CurrentState"]["value"] in (
            "Running", "Ended", "Interrupted")
        (spindle,) = m["elements"]["spindle"]
        assert spindle["values"]["mt:IsRotating"]["status"] == "Good"
        (channel,) = m["elements"]["channel"]
        c = channel["values"]
        assert (c["mt:ChannelState"]["dataType"], c["mt:ChannelMode"]["dataType"]) == (mt + "64", mt + "67")
        assert c["mt:ChannelState"]["value"] in (0, 1, 2) and c["mt:ChannelState"]["status"] == "Good"
        # no feed override register on the simulated controls: there, with no data
        assert c["mt:FeedOverride"]["status"] == "BadNoDataAvailable" and c["mt:FeedOverride"]["dataType"] == "ns=0;i=11"
    assert 0 < machines["lathe"]["elements"]["spindle"][0]["values"]["mt:Override"]["value"] <= 254


def test_the_live_address_space_conforms_to_the_nodesets(stack):
    from tests.nodeset_check import Checker, Model, default_files

    async def go():
        async with ua_client(stack["server"].url) as c:
            ns = await c.get_namespace_array()
            checker = Checker(Model(default_files(NODE / "node_modules", ROOT / "lathed" / "opcua" / "nodesets")), c)
            for m in await c.get_node(ua.NodeId(1001, ns.index(MACHINERY))).get_children():
                await checker.check_instance(m, (await m.read_browse_name()).Name)
            return checker
    checker = asyncio.run(go())
    assert checker.errors == []
    assert checker.checked > 150      # four machines, each element and variable with a type of these models


def test_a_subscribed_client_receives_the_spindle_speed_as_the_daemon_samples_it(stack):
    async def go():
        async with ua_client(stack["server"].url) as c:
            got = Collect()
            sub = await c.create_subscription(50, got)
            await every_sample(sub, await lathe_node(c, "mt:Monitoring", "Spindle", "RotationalSpeed"))
            stamps = []
            while len(stamps) < 6:    # the lathe is polled every 100 ms: a dozen a second
                _, dv = await asyncio.wait_for(got.changes.get(), 5.0)
                assert dv.StatusCode.is_good() and dv.Value.Value > 0
                stamps.append(dv.SourceTimestamp)
            assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
            # the sample's own time, not the server's: at most a second behind
            assert abs(stamps[-1].timestamp() - time.time()) < 1.0
    asyncio.run(go())


def test_every_node_bench_plant_opcua_watches_is_in_the_address_space(stack):
    """The benchmark named a node by a path the 40501 model no longer has (Spindle/Override, now
    mt:Override) and retried for minutes without saying why."""
    sys.path.insert(0, str(ROOT / "bench"))
    from bench_plant_opcua import WATCHED

    async def go():
        async with ua_client(stack["server"].url) as c:
            for machine, paths in WATCHED.items():
                for p in paths:
                    node = await until(lambda: machine_node(c, machine, "mt:Monitoring", *p.split("/")), 20,
                                       f"{machine} {p}")
                    assert await node.read_data_type() == ua.NodeId(ua.ObjectIds.Double), (machine, p)
    asyncio.run(go())


def test_a_chatter_alarm_arrives_as_an_event_within_a_second(stack):
    d = stack["daemon"]

    async def go():
        async with ua_client(stack["server"].url) as c:
            ns = await c.get_namespace_array()
            etype = await c.nodes.base_event_type.get_child([
                ua.QualifiedName("NotificationEventType", ns.index(MACHINE_TOOL)),
                ua.QualifiedName("RecordEventType", ns.index(NAMESPACE))])
            got = Collect()
            sub = await c.create_subscription(50, got)
            await sub.subscribe_events(await lathe_node(c, "mt:Notification", "mt:Messages"), etype)
            await sub.subscribe_events(c.nodes.server, etype)
            known = {e["id"] for e in events(d, "chatter_alarm", 20)}
            # every cut now goes 3 mm deep, past the lobes' limit: the next cut chatters
            wait_until(lambda: sim_call(d.paths["sim"], "set", {"depth_mm": 3.0}), what="simulator control")
            # The shipped program's own 3 mm parts alarm too: one of theirs recorded between the
            # subscription and `known` arrives as well (seen at four test workers). The first
            # new alarm seen on both notifiers, the lathe's Messages and the Server object:
            seen: dict[int, list] = {}
            while True:
                at, ev = await asyncio.wait_for(got.events.get(), 60.0)
                if ev.Identifier == "chatter_alarm" and ev.RecordId not in known:
                    seen.setdefault(ev.RecordId, []).append((at, ev))
                    if len(seen[ev.RecordId]) == 2:
                        return seen[ev.RecordId], known
    try:
        seen, known = asyncio.run(go())
    finally:
        sim_call(d.paths["sim"], "set", {"depth_mm": None})
    alarm = next(e for e in events(d, "chatter_alarm", 50) if e["id"] == seen[0][1].RecordId)
    for at, ev in seen:
        assert ev.RecordId == alarm["id"] and ev.Severity == 800 and ev.SourceName == "lathe"
        assert json.loads(ev.Payload)["chatter_frequency_hz"] == alarm["payload"]["chatter_frequency_hz"]
        assert abs(ev.Time.timestamp() - alarm["t"]) < 0.001
        assert "chatter_alarm on lathe" in ev.Message.Text
        # the bound, from the alarm's record to the OPC UA client
        assert at - alarm["t"] < 1.0, f"the chatter alarm took {at - alarm['t']:.2f} s to reach the client"


def test_the_suppression_mode_is_written_only_by_an_operator_and_through_the_daemon(stack):
    d = stack["daemon"]
    url = stack["server"].url

    async def write(user: str | None, pw: str | None, value) -> ua.StatusCode:
        c = ua_client(url)
        if user:
            c.set_user(user)
            c.set_password(pw)
        async with c:
            node = await lathe_node(c, "mt:Monitoring", "Suppression", "Mode")
            try:
                await node.write_value(ua.DataValue(ua.Variant(value, ua.VariantType.String)))
            except ua.UaStatusCodeError as e:
                return ua.StatusCode(e.code)
            return ua.StatusCode(ua.StatusCodes.Good)

    before = d.item("analyzers", "suppress")["mode"]
    assert before == "auto"
    denied = ua.StatusCodes.BadUserAccessDenied
    assert asyncio.run(write(None, None, "off")).value == denied            # anonymous
    assert asyncio.run(write("victor", "victor-pw", "off")).value == denied  # a viewer
    assert d.item("analyzers", "suppress")["mode"] == "auto"
    assert [e for e in events(d, "suppression_mode", 20) if e["payload"]["to"] == "off"] == []
    with pytest.raises(ua.uaerrors.BadUserAccessDenied):    # a wrong password: no session at all
        asyncio.run(write("olga", "wrong", "off"))
    assert asyncio.run(write("olga", "olga-pw", "fast")).value == ua.StatusCodes.BadOutOfRange
    try:
        assert asyncio.run(write("olga", "olga-pw", "manual")).is_good()
        assert d.item("analyzers", "suppress")["mode"] == "manual"
        # the daemon's own command, recorded with the OPC UA user's name (the store writes the
        # record after the mode changes: read at once on a loaded machine, it was not there yet)
        last = wait_until(lambda: [e for e in events(d, "suppression_mode", 20) if e["payload"]["to"] == "manual"],
                          timeout=10, interval=0.1, what="the suppression_mode record")[-1]["payload"]
        assert last["by"] == "olga"
    finally:
        d.ctl("suppress", "auto")


def test_off_loopback_only_encrypted_sessions_with_an_account(stack):
    """0.0.0.0 listens on every interface of the PC, the network's too, so lathed-opcua takes it as
    a network listener (only loopback addresses are not); the test reaches it through 127.0.0.1."""
    tmp = stack["tmp"]
    key, cert = client_certificate(tmp / "client")
    stranger_key, stranger_cert = client_certificate(tmp / "stranger")
    (tmp / "trusted").mkdir()
    (tmp / "trusted" / "client.der").write_bytes(cert.read_bytes())
    server = OpcUa(opcua_config(tmp, "ua-net", stack["sock"], listen="0.0.0.0", writable=False,
                                extra=f'trusted_clients = "{tmp / "trusted"}"'))
    try:
        server.wait_serving()

        async def go():
            endpoints = await ua_client(server.url).connect_and_get_server_endpoints()
            assert {(e.SecurityPolicyUri.rsplit("#", 1)[1], e.SecurityMode) for e in endpoints} == \
                {("Basic256Sha256", ua.MessageSecurityMode.SignAndEncrypt)}
            assert {t.TokenType for e in endpoints for t in e.UserIdentityTokens} == {ua.UserTokenType.UserName}
            with pytest.raises(Exception):              # no endpoint without security
                async with ua_client(server.url, timeout=5) as c:
                    await c.nodes.objects.get_children()
            with pytest.raises(ua.uaerrors.BadIdentityTokenRejected):   # encrypted, but anonymous
                async with await encrypted(server.url, key, cert):
                    pass
            with pytest.raises(ua.UaError):    # a client application not among the trusted ones
                async with await encrypted(server.url, stranger_key, stranger_cert, "victor", "victor-pw"):
                    pass
            async with await encrypted(server.url, key, cert, "victor", "victor-pw") as c:
                async def good():
                    dv = await (await lathe_node(c, "mt:Monitoring", "Spindle", "RotationalSpeed")).read_data_value()
                    return dv.StatusCode.is_good() and dv
                assert (await until(good, 20, "the spindle speed over the encrypted session")).Value.Value > 0
            # read-only unless configured: not even an operator writes here
            async with await encrypted(server.url, key, cert, "olga", "olga-pw") as c:
                mode = await lathe_node(c, "mt:Monitoring", "Suppression", "Mode")
                with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                    await mode.write_value(ua.DataValue(ua.Variant("off", ua.VariantType.String)))
        asyncio.run(go())
        assert stack["daemon"].item("analyzers", "suppress")["mode"] == "auto"
        # the certificate made on first start, its key for this user only
        state = tmp / "ua-net"
        assert stat.S_IMODE((state / "server-key.pem").stat().st_mode) == 0o600
        assert (state / "server-cert.der").stat().st_size > 500
    finally:
        server.stop()


def test_bad_config_is_one_line_and_exit_78(tmp_path):
    shipped = Settings(str(ROOT / "etc" / "lathed-opcua.toml"))   # what `make run` serves
    assert (shipped.url, shipped.loopback, shipped.writable, shipped.users) == \
        ("opc.tcp://127.0.0.1:4840", True, False, {})
    with pytest.raises(ConfigError, match=r"listen = '0.0.0.0' opens the server to the network: that needs accounts"):
        Settings(None, "0.0.0.0")
    cfg = tmp_path / "o.toml"
    cfg.write_text('[opcua]\nwritable = true\n')
    with pytest.raises(ConfigError, match=r"writable = true but no \[users.NAME\] has role = \"operator\""):
        Settings(str(cfg))
    cfg.write_text('[opcua]\nmax_connections = 1\n')
    with pytest.raises(ConfigError, match=r"\[opcua\] max_connections: 1 is out of range"):
        Settings(str(cfg))
    cfg.write_text('[opcua]\nport = 70000\n')
    r = subprocess.run([str(BIN / "lathed-opcua"), "--config", str(cfg)], capture_output=True, text=True, timeout=30)
    assert r.returncode == 78
    assert r.stderr.strip().splitlines() == \
        [f"lathed-opcua: {cfg}: [opcua] port: 70000 is out of range; allowed: an integer in [1, 65535]"]


def test_a_lost_daemon_marks_values_bad_and_the_server_comes_back_with_it(stack):
    d = stack["daemon"]
    url = stack["server"].url

    async def status() -> ua.StatusCode:
        async with ua_client(url) as c:
            node = await lathe_node(c, "mt:Monitoring", "Spindle", "RotationalSpeed")
            try:
                return (await node.read_data_value()).StatusCode
            except ua.UaStatusCodeError as e:    # asyncua raises a bad one
                return ua.StatusCode(e.code)

    d.proc.kill()          # not a clean stop: the socket is left behind, the simulator too
    d.proc.wait()
    wait_until(lambda: asyncio.run(status()).value == ua.StatusCodes.BadNoCommunication, timeout=15,
               interval=0.2, what="BadNoCommunication while the daemon is gone")
    assert stack["server"].proc.poll() is None
    again = Daemon(d.cfg, d.socket)
    again.paths = d.paths
    stack["daemon"] = again
    d.log.close()
    again.wait_ready(timeout=60)
    wait_until(lambda: asyncio.run(status()).is_good(), timeout=30, interval=0.2, what="good values again")


def test_a_machine_nameplate_is_checked_like_any_key(tmp_path):
    from tests.conftest import sim_config
    for extra, wanted in (
            ("[machine.lathe.identification]\nyear_of_construction = 1800\n",
             "[machine.lathe.identification] year_of_construction: 1800 is out of range; allowed: an integer in "
             "[1900, 2200]"),
            ("[sensor.temps.identification]\nmodel = \"DS18B20\"\n", "[sensor.temps] identification: unknown key")):
        cfg, _ = sim_config(tmp_path, extra=extra)
        r = subprocess.run([str(BIN / "lathed"), "--check-config", str(cfg)], capture_output=True, text=True,
                           timeout=60)
        assert r.returncode == 78 and wanted in r.stderr, r.stderr


def test_password_guessing_cannot_stall_the_server(monkeypatch):
    from lathed.opcua.app import Accounts
    checks = []
    real = accounts.verify
    monkeypatch.setattr(accounts, "verify", lambda pw, h: checks.append(pw) or real(pw, h))
    now = [100.0]
    users = Accounts({"olga": ("operator", accounts.hash_password("olga-pw"))}, anonymous=False,
                     clock=lambda: now[0])
    assert users.get_user(None) is None                          # no anonymous off loopback
    for i in range(Accounts.FAILS_MAX):
        assert users.get_user(None, "olga", f"guess{i}") is None
    assert len(checks) == Accounts.FAILS_MAX
    # the next guesses, even the right password, are refused without the ~50 ms check
    assert users.get_user(None, "olga", "guess9") is None and users.get_user(None, "olga", "olga-pw") is None
    assert len(checks) == Accounts.FAILS_MAX
    now[0] += Accounts.FAILS_WINDOW_S
    assert users.get_user(None, "olga", "olga-pw").name == "olga"
    assert users.get_user(None, "olga", "olga-pw").name == "olga" and len(checks) == Accounts.FAILS_MAX + 1


# -- limits (issue 35, defect 6): a second server on the same daemon, with small limits ------
LIMITS = """max_connections = 8
hello_timeout = "1s"
activation_timeout = "3s"
max_subscriptions_per_session = 3
max_monitored_items_per_session = 20
min_publishing_interval = "100ms"
"""


@pytest.fixture(scope="module")
def limited(stack):
    server = OpcUa(opcua_config(stack["tmp"], "ua-limits", stack["sock"], writable=False, extra=LIMITS))
    try:
        server.wait_serving()
        yield server
    finally:
        server.stop()


def idle_sockets(port: int, n: int) -> list[socket.socket]:
    """``n`` TCP connections that never send a Hello."""
    out = []
    for _ in range(n):
        s = socket.create_connection(("127.0.0.1", port), timeout=5)
        s.setblocking(False)
        out.append(s)
    return out


def closed(s: socket.socket) -> bool:
    try:
        return s.recv(1) == b""
    except BlockingIOError:
        return False
    except OSError:       # reset
        return True


def test_connections_that_never_say_hello_are_closed_and_lock_no_client_out(limited):
    """4,187 silent connections once held lathed-opcua: each is closed after hello_timeout, and at
    max_connections a new connection closes the oldest that has no session."""
    socks = idle_sockets(limited.port, 8)          # the cap, filled
    try:
        async def fresh_client_reads() -> str:
            async with ua_client(limited.url, timeout=10) as c:
                return (await (await lathe_node(c, "di:Identification", "di:Manufacturer")).read_value()).Text
        assert asyncio.run(fresh_client_reads()) == "lathed simulator"
        # every silent one is closed within the Hello timeout (1 s here; asyncua alone waits 30 s)
        wait_until(lambda: all(closed(s) for s in socks), timeout=10, what="the silent connections closed")
    finally:
        for s in socks:
            s.close()
    out = limited.output(tail=None)
    # the client got in by closing the oldest silent one; the others went at their Hello timeout
    assert "the connection cap: the oldest without a session gives way" in out and "no Hello within 1 s" in out


def test_one_session_gets_its_share_of_subscriptions_and_monitored_items(limited):
    """One anonymous client with 50 subscriptions x 200 monitored items at 10 ms once stalled every
    other client: a session gets max_subscriptions_per_session, max_monitored_items_per_session,
    and no interval below min_publishing_interval."""
    async def go():
        async with ua_client(limited.url) as c, ua_client(limited.url) as other:
            speed = await lathe_node(c, "mt:Monitoring", "Spindle", "RotationalSpeed")
            # the service itself, to see the interval the server revised
            raw = await c.uaclient.create_subscription(ua.CreateSubscriptionParameters(
                RequestedPublishingInterval=10, RequestedLifetimeCount=300, RequestedMaxKeepAliveCount=10,
                PublishingEnabled=False), callback=lambda result: None)
            revised = raw.RevisedPublishingInterval
            subs = [await c.create_subscription(10, Collect()) for _ in range(2)]
            with pytest.raises(ua.uaerrors.BadTooManySubscriptions):
                await c.create_subscription(10, Collect())
            handles = []
            for i in range(30):      # 30 asked, 20 given
                try:
                    handles.append(await subs[i % 2].subscribe_data_change(speed, sampling_interval=0))
                except ua.uaerrors.BadTooManyMonitoredItems:
                    handles.append(None)
            # another session has its own share
            sub = await other.create_subscription(100, Collect())
            theirs = await sub.subscribe_data_change([speed] * 20)
            return revised, handles, theirs, subs
    revised, handles, theirs, subs = asyncio.run(go())
    assert revised == 100.0
    assert sum(h is not None for h in handles) == 20 and handles[20:] == [None] * 10
    assert all(isinstance(h, int) for h in theirs) and len(theirs) == 20


def test_a_flood_of_bad_connections_is_counted_in_the_log_not_written_line_by_line(limited):
    """The probe's silent connections wrote 97 MB of log: each kind of line is written a few times
    a window, then counted."""
    from lathed.opcua.guard import LOG_BURST
    bad = b"HELF" + (8).to_bytes(4, "little")        # a header announcing no body: asyncua's "malformed header"
    for _ in range(60):
        with socket.create_connection(("127.0.0.1", limited.port), timeout=5) as s:
            s.sendall(bad)
            s.settimeout(5)
            try:
                s.recv(1)         # closed by the server
            except OSError:
                pass
    def shown_and_counted() -> tuple[int, int]:
        lines = limited.output(tail=None).splitlines()
        shown = sum("malformed header" in ln and "log_suppressed" not in ln for ln in lines)
        counted = sum(int(ln.split("log_suppressed: ")[1].split()[0]) for ln in lines
                      if "log_suppressed: " in ln and "malformed header" in ln)
        return shown, counted
    # every one of the 60 is either written or counted (the count comes when its window closes)
    wait_until(lambda: sum(shown_and_counted()) == 60, timeout=40, interval=0.5, what="60 lines written or counted")
    shown, counted = shown_and_counted()
    assert 1 <= shown <= 2 * LOG_BURST and counted >= 60 - 2 * LOG_BURST


def test_frames_queued_while_busy_are_applied_as_one_in_order():
    from lathed.opcua.app import coalesced
    link_down = {"type": "link", "connected": False}
    batch = [{"type": "frame", "samples": {"lathe/spindle_rpm": [1.0, 2000.0, "r/min"]}, "events": [{"id": 1}]},
             {"type": "frame", "samples": {"lathe/spindle_rpm": [2.0, 2100.0, "r/min"],
                                           "lathe/x_mm": [2.0, 5.0, "mm"]}, "events": [{"id": 2}],
              "status": {"machines": []}},
             link_down,
             {"type": "init", "samples": {}},
             {"type": "frame", "samples": {"lathe/x_mm": [3.0, 6.0, "mm"]}}]
    out = coalesced(batch)
    assert [m["type"] for m in out] == ["frame", "link", "init", "frame"]
    assert out[0]["samples"] == {"lathe/spindle_rpm": [2.0, 2100.0, "r/min"], "lathe/x_mm": [2.0, 5.0, "mm"]}
    assert out[0]["events"] == [{"id": 1}, {"id": 2}] and out[0]["status"] == {"machines": []}
    assert batch[0]["samples"] == {"lathe/spindle_rpm": [1.0, 2000.0, "r/min"]}    # the queue's own untouched
