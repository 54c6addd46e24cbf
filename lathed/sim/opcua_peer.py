"""The simulated lathe's control as an OPC UA server of its own (a real asyncua server).

The same machine as its Modbus face (lathed.sim.registers), in a vendor-style namespace:
string node ids that name the control's variables by path, as SINUMERIK's OPC UA server and
others do ("/Channel/Spindle/actSpeed"). Security on: Basic256Sha256 (and the two newer RSA
policies), Sign or SignAndEncrypt, no endpoint without security; a client application
certificate opens a channel only if it is in the trust list; a session needs the account's
password or the user certificate. The spindle speed (an S word), the spindle override and the
heartbeat are writable nodes; the X wear offset is written by a method, as some controls take
tool data. Beside it, the machine as OPC 40501 lays it out (lathed.sim.opcua_40501). Shipped
maps: etc/lathed-cell-opcua.toml, etc/lathed-opc40501.toml; docs/machines.md.
"""
from __future__ import annotations

import asyncio
import logging
from typing import Callable

from asyncua import Server, ua
from asyncua.crypto.permission_rules import User, UserRole
from asyncua.crypto.truststore import TrustStore
from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions
from cryptography.hazmat.primitives.serialization import Encoding

from lathed.sim.opcua_40501 import Tree40501
from lathed.sim.pki import SERVER_URI, USERNAME, Pki

log = logging.getLogger("lathed.sim.opcua")
NAMESPACE = "urn:lathed:sim:cnc"
D, F, B = ua.VariantType.Double, ua.VariantType.Float, ua.VariantType.Boolean
U16, U32, I32 = ua.VariantType.UInt16, ua.VariantType.UInt32, ua.VariantType.Int32
# lathed's register name -> (node id, type, writable by a client)
NODES: dict[str, tuple[str, ua.VariantType, bool]] = {
    "spindle_rpm":           ("/Channel/Spindle/actSpeed", D, False),
    # the S word: the program takes the speed from this variable when a client sets it
    "spindle_rpm_cmd":       ("/Channel/Spindle/cmdSpeed", D, True),
    "spindle_override_pct":  ("/Channel/Spindle/speedOvr", D, True),
    "spindle_load_pct":      ("/Channel/Spindle/driveLoad", F, False),
    "feed_override_pct":     ("/Channel/State/feedRateIpoOvr", D, False),
    "x_mm":                  ("/Channel/GeometricAxis/actToolBasePos[X]", D, False),
    "y_mm":                  ("/Channel/GeometricAxis/actToolBasePos[Z]", D, False),
    "b_deg":                 ("/Channel/GeometricAxis/actToolBasePos[B]", D, False),
    "part_count":            ("/Channel/State/actParts", U32, False),
    "cycle_time_s":          ("/Channel/State/cycleTime", D, False),
    "program_state":         ("/Channel/State/progStatus", I32, False),   # 0 idle, 1 running, 2 alarm
    "program_number":        ("/Channel/ProgramInfo/progNumber", U16, False),
    "block_number":          ("/Channel/ProgramInfo/actBlockNo", U32, False),
    "offset_x_um":           ("/Tool/Compensation/wearX", D, False),      # written by SetWearX
    "feed_mm_rev":           ("/Channel/State/actFeedRate", D, False),
    "alarm_code":            ("/Nck/State/alarmNo", U16, False),
    "tool_number":           ("/Channel/State/actTNumber", U16, False),
    "probe_displacement_um": ("/Channel/Probe/displacement", D, False),
    "probe_seq":             ("/Channel/Probe/seq", U16, False),
    "depth_of_cut_mm":       ("/Channel/Process/depthOfCut", D, False),
    "cutting_feed":          ("/Plc/Signals/CUT", B, False),
    "css_active":            ("/Plc/Signals/CSS", B, False),
    "threading":             ("/Plc/Signals/THRD", B, False),
    "heartbeat":             ("/Plc/Client/heartbeat", U16, True),
}
WEAR_OBJECT, WEAR_METHOD = "/Tool/Compensation", "/Tool/Compensation/SetWearX"
# the nameplate (etc/lathed.toml's [machine.lathe.identification]): a driver checks it before commanding
IDENTIFICATION = {"manufacturer": ("/Machine/Identification/Manufacturer", "lathed simulator"),
                  "model": ("/Machine/Identification/Model", "MC4200-class lathe (simulated)"),
                  "serial_number": ("/Machine/Identification/SerialNumber", "SIM-LATHE-0001")}
# the simulated program's phases as the block the control is in
BLOCKS = {"load": 10, "approach": 20, "cut": 30, "retract": 40}
POLICIES = [ua.SecurityPolicyType.Basic256Sha256_Sign, ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt,
            ua.SecurityPolicyType.Aes128Sha256RsaOaep_Sign, ua.SecurityPolicyType.Aes128Sha256RsaOaep_SignAndEncrypt,
            ua.SecurityPolicyType.Aes256Sha256RsaPss_Sign, ua.SecurityPolicyType.Aes256Sha256RsaPss_SignAndEncrypt]


def node_id(path: str, idx: int) -> ua.NodeId:
    return ua.NodeId(path, idx)


class Accounts:
    """The control's one account (its password in the PKI's file) and the user certificate."""

    def __init__(self, password: str, user_cert_der: bytes):
        self.password, self.user_cert = password, user_cert_der

    def get_user(self, iserver, username=None, password=None, certificate=None):
        if username is not None:
            pw = password.decode(errors="replace") if isinstance(password, bytes) else password
            if username == USERNAME and pw == self.password:
                return User(role=UserRole.User, name=username)
            log.warning("login refused: user %r, wrong password or no such account", username)
            return None
        if certificate is not None:
            der = certificate if isinstance(certificate, bytes) else certificate.public_bytes(Encoding.DER)
            if der == self.user_cert:
                return User(role=UserRole.User, name="certificate")
            log.warning("login refused: a user certificate the control does not know")
        return None       # anonymous: never


class OpcUaPeer:
    """The simulated control's OPC UA server; ``on_write(name, value)`` is the machine's own
    check of a written value (ValueError: refused, BadOutOfRange to the client)."""

    def __init__(self, host: str, port: int, pki: Pki, on_write: Callable[[str, float], None],
                 serial_number: str | None = None):
        self.host, self.port, self.pki, self.on_write = host, port, pki, on_write
        self.nameplate = {key: value for key, (_, value) in IDENTIFICATION.items()}
        if serial_number:
            self.nameplate["serial_number"] = serial_number
        self.server: Server | None = None
        self.up = False
        self._idx = 0
        self._last: dict[str, object] = {}
        self._writable: dict[ua.NodeId, str] = {}
        self.writes = 0

    @property
    def url(self) -> str:
        return f"opc.tcp://{self.host}:{self.port}"

    async def start(self) -> None:
        server = Server(user_manager=Accounts(self.pki.password(), self.pki.user_cert.read_bytes()))
        server.iserver.bind_condition_methods = True     # ConditionRefresh: a client learns the active alarms
        await server.init()
        server.set_endpoint(self.url)
        server.set_server_name("lathed simulated CNC")
        await server.set_application_uri(SERVER_URI)
        await server.load_certificate(str(self.pki.server_cert))
        await server.load_private_key(str(self.pki.server_key))
        server.set_security_policy(POLICIES)
        server.set_identity_tokens([ua.UserNameIdentityToken, ua.X509IdentityToken])
        store = TrustStore([self.pki.trusted_clients], [])
        await store.load()
        server.set_certificate_validator(CertificateValidator(
            CertificateValidatorOptions.TIME_RANGE | CertificateValidatorOptions.URI |
            CertificateValidatorOptions.TRUSTED | CertificateValidatorOptions.PEER_CLIENT, store))
        self._idx = idx = await server.register_namespace(NAMESPACE)
        objects = server.nodes.objects
        folders: dict[str, object] = {}

        async def folder(path: str):
            parent = objects
            for i, part in enumerate(path.strip("/").split("/")):
                key = "/" + "/".join(path.strip("/").split("/")[:i + 1])
                if key not in folders:
                    folders[key] = await parent.add_object(node_id(key, idx), ua.QualifiedName(part, idx))
                parent = folders[key]
            return parent

        for name, (path, vtype, writable) in NODES.items():
            parent = await folder(path.rsplit("/", 1)[0])
            var = await parent.add_variable(node_id(path, idx), ua.QualifiedName(path.rsplit("/", 1)[1], idx),
                                            ua.Variant(False if vtype == B else 0, vtype))
            if writable:
                await var.set_writable()
                self._writable[var.nodeid] = name
        for key, (path, _) in IDENTIFICATION.items():
            parent = await folder(path.rsplit("/", 1)[0])
            await parent.add_property(node_id(path, idx), ua.QualifiedName(path.rsplit("/", 1)[1], idx),
                                      self.nameplate[key])
        self.tree = Tree40501(server, idx)
        await self.tree.build(self.nameplate)
        wear = folders[WEAR_OBJECT]
        await wear.add_method(node_id(WEAR_METHOD, idx), ua.QualifiedName("SetWearX", idx), self._set_wear,
                              [ua.VariantType.Double], [])
        service = server.iserver.attribute_service
        inner = service.write

        async def write(params: ua.WriteParameters, user: User = User(role=UserRole.Admin)) -> list:
            if user.role == UserRole.Admin:
                return await inner(params, user)
            return [await self._client_write(wv, inner, user) for wv in params.NodesToWrite]
        service.write = write
        self._last = {}
        await server.start()
        self.server = server
        self.up = True

    async def _client_write(self, wv: ua.WriteValue, inner, user: User) -> ua.StatusCode:
        name = self._writable.get(wv.NodeId) if wv.AttributeId == ua.AttributeIds.Value else None
        if name is not None:
            v = wv.Value.Value.Value if wv.Value is not None and wv.Value.Value is not None else None
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                return ua.StatusCode(ua.StatusCodes.BadTypeMismatch)
            try:
                self.on_write(name, float(v))
            except (ValueError, KeyError) as e:
                log.warning("write refused by the machine: %s", e)
                return ua.StatusCode(ua.StatusCodes.BadOutOfRange)
            self.writes += 1
        return (await inner(ua.WriteParameters(NodesToWrite=[wv]), user))[0]

    async def _set_wear(self, parent, value: ua.Variant):
        # a coroutine: asyncua runs a plain function in a thread, and the machine is the loop's
        v = value.Value if isinstance(value, ua.Variant) else value
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            return ua.StatusCode(ua.StatusCodes.BadTypeMismatch)
        try:
            self.on_write("offset_x_um", float(v))
        except (ValueError, KeyError) as e:
            log.warning("wear offset refused by the machine: %s", e)
            return ua.StatusCode(ua.StatusCodes.BadOutOfRange)
        self.writes += 1
        return []

    async def update(self, values: dict[str, float], phase: str) -> None:
        """The machine's values into the address space; only those that changed (a client's
        monitored item reports each change once)."""
        if self.server is None:
            return
        values = {**values, "block_number": BLOCKS.get(phase, 0), "feed_override_pct": 100.0}
        for name, (path, vtype, _) in NODES.items():
            v = values.get(name)
            if v is None:
                continue
            v = bool(v) if vtype == B else (float(v) if vtype in (D, F) else int(round(v)))
            if self._last.get(name) == v:
                continue
            self._last[name] = v
            await self.server.write_attribute_value(node_id(path, self._idx), ua.DataValue(ua.Variant(v, vtype)))
        await self.tree.update(values)

    async def fault(self, name: str, status: str) -> None:
        """The control reports ``name`` unusable (a status code's name: a broken sensor behind
        it, BadSensorFailure; its PLC link down, BadNoCommunication): a client's value goes stale."""
        path, vtype, _ = NODES[name]
        self._last.pop(name, None)            # the next update writes a good value again
        await self.server.write_attribute_value(node_id(path, self._idx), ua.DataValue(
            ua.Variant(None, ua.VariantType.Null), StatusCode=ua.StatusCode(getattr(ua.StatusCodes, status))))

    async def stop(self) -> None:
        self.up = False
        server, self.server = self.server, None
        if server is not None:
            await server.stop()

    async def outage(self, seconds: float) -> None:
        """The control's OPC UA server restarted: every connection and subscription gone, the
        port closed for ``seconds``. The address space stays (a real control's comes back the
        same; asyncua takes seconds to build one)."""
        server = self.server
        if server is None or server.bserver is None:
            return
        self.up = False
        await server.bserver.stop()
        subs = server.iserver.subscription_service
        await subs.delete_subscriptions(list(subs.subscriptions))
        await asyncio.sleep(seconds)
        await server.bserver.start()
        self.up = True
