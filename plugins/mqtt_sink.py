"""Store-and-forward of every record, and a few live values, to an MQTT broker.

The topic tree, the payloads (JSON Schemas in lathed/schemas/mqtt/), start_from and
the delivery guarantees are in docs/mqtt.md; the keys in docs/configuration.md.
Records are committed locally first and published in outbox order at QoS 1; the
progress moves only once the broker has acknowledged a whole batch, so an outage
or a crash loses nothing and at worst sends a batch again (same ids). Live values
are not stored: while the broker is down they are dropped.
"""
from __future__ import annotations

import asyncio
import datetime as dt
import json
import ssl
import time
from pathlib import Path
from typing import Any

from lathed import hookimpl
from lathed.analyzer import Analyzer
from lathed.config import Section
from lathed.extras import MissingExtra, need
from lathed.store import JSON_COLUMNS, dumps

# A field's unit, from the suffix of its name (the records' naming convention).
_UNITS = (("_hz", "Hz"), ("_mm_rev", "mm/rev"), ("_mm", "mm"), ("_um", "µm"), ("_pct", "%"), ("_deg", "deg"),
          ("_s", "s"), ("_c", "°C"), ("rpm", "r/min"), ("_nm", "N·m"))
_ROW_META = ("id", "uuid", "machine_id")
INFLIGHT = 100     # QoS 1 messages awaiting their PUBACK at once


# aiomqtt (the mqtt extra) is imported by the first sink configured, never by a daemon without one
aiomqtt: Any = None
MqttConnectError: Any = None
Refused: Any = None
_Client: Any = None


def _import_aiomqtt() -> None:
    global aiomqtt, MqttConnectError, Refused, _Client
    if aiomqtt is not None:
        return
    mod = need("aiomqtt", "the mqtt_sink plugin")
    from aiomqtt.exceptions import MqttConnectError as connect_error

    class Refused_(mod.MqttError):
        """The broker acknowledged messages with a failure reason: it discarded them."""

    class Client(mod.Client):
        """aiomqtt drops a PUBACK's reason code, where an MQTT 5 broker says it
        discarded the message (not authorised by its ACL, quota exceeded...)."""

        def __init__(self, *args: Any, **kwargs: Any):
            self.refused: list[str] = []
            super().__init__(*args, **kwargs)

        def _on_publish(self, client, userdata, mid, reason_code, properties=None) -> None:
            if getattr(reason_code, "is_failure", False):
                self.refused.append(str(reason_code))
            super()._on_publish(client, userdata, mid, reason_code, properties)

        async def __aenter__(self) -> "Client":
            await super().__aenter__()
            # aiomqtt puts an unexpected disconnection on this future and its __aexit__ may not
            # read it: asyncio logged "Future exception was never retrieved" when it was collected.
            # The sink learns of the disconnection from its publish and watch instead.
            self._disconnected.add_done_callback(lambda f: f.cancelled() or f.exception())
            return self

    aiomqtt, MqttConnectError, Refused, _Client = mod, connect_error, Refused_, Client


class MqttSink(Analyzer):
    forwards_records = True     # retention (keep_days) waits for this sink's progress

    def __init__(self, name: str, section: Section):
        super().__init__(name, section)
        try:
            _import_aiomqtt()
        except MissingExtra as e:
            raise section.error("plugin", str(e)) from None
        self.host = section.getstr("host")
        if not self.host:
            raise section.error("host", "empty: name the MQTT broker's host")
        here = Path(section.file).parent
        files = {k: _file(section, here, k) for k in ("ca_file", "cert_file", "key_file")}
        self.tls = section.getbool("tls", any(files.values()))
        if not self.tls and any(files.values()):
            raise section.error("tls", "is false but a ca_file/cert_file/key_file is given: set tls = true")
        if bool(files["cert_file"]) != bool(files["key_file"]):
            raise section.error("cert_file" if not files["cert_file"] else "key_file",
                                "missing: a client certificate needs both cert_file and key_file")
        self.tls_context = _tls_context(section, files) if self.tls else None
        self.port = section.getint("port", 8883 if self.tls else 1883, minval=1, maxval=65535)
        self.cell = section.getstr("cell", "")
        # where a sink with no progress yet begins; "now": a first enable on a store of
        # months must not flood the plant's broker with history (docs/mqtt.md)
        self.start_from = section.getstr("start_from", "now", choices=("now", "oldest"))
        self._begun = False
        self.username = section.getstr("username", "") or None
        self.password = section.getstr("password", "") or None
        pw_file = _file(section, here, "password_file")
        if pw_file and self.password:
            raise section.error("password_file", "and password are both given: keep one (the file)")
        if pw_file:
            self.password = _read_secret(section, "password_file", pw_file)
        if self.password and not self.username:
            raise section.error("password_file" if pw_file else "password", "given without a username")
        self.live = [_live_key(section, s) for s in section.getlist("live", [])]
        self.live_every = section.getduration("live_every", 1.0, minval=0.05, maxval=3600)
        self.batch = section.getint("batch", 200, minval=1, maxval=10_000)
        self.interval = section.getduration("interval", 0.2, minval=0.01, maxval=3600)
        self.timeout = section.getduration("timeout", 10.0, minval=0.5, maxval=3600)
        self.keepalive = int(section.getduration("keepalive", 30.0, minval=5, maxval=3600))
        # MQTT 5 by default: only there does a PUBACK say that the broker discarded the message
        self.protocol = section.getstr("protocol", "5", choices=("5", "3.1.1"))
        self.where = f"{self.host}:{self.port}"
        self.published = 0
        self.live_published = 0
        self.connected = False
        self.last_error: str | None = None
        self.last_publish_t: float | None = None

    # -- topics and payloads -------------------------------------------------
    def _cell(self) -> str:
        return _seg(self.cell or self.ctx.store.machine_id)

    def state_topic(self) -> str:
        return f"lathed/{self._cell()}/state"

    def record_message(self, oid: int, table: str, r: dict[str, Any]) -> tuple[str, str]:
        """The topic and JSON payload of one record row."""
        cell = self._cell()
        fields = {k: (json.loads(v) if k in JSON_COLUMNS and isinstance(v, str) else v)
                  for k, v in r.items() if k not in _ROW_META}
        msg: dict[str, Any] = {"id": f"{r['uuid']}/{oid}", "uuid": r["uuid"], "seq": oid, "cell": cell,
                               "daemon": r["machine_id"], "table": table}
        if table == "events":
            payload = fields["payload"] if isinstance(fields["payload"], dict) else {"value": fields["payload"]}
            # the daemon's own events (source "lathed") are the cell's: no machine level
            machine = payload.get("machine") or (None if fields["source"] == "lathed" else fields["source"])
            topic = f"{_under(cell, machine)}/events/{_seg(fields['kind'])}"
            msg.update(machine=machine, kind=fields["kind"], source=fields["source"], t=fields["t"],
                       time=_iso(fields["t"]), payload=payload, units=_units(payload))
        else:
            machine = fields.get("machine") or None
            topic = f"{_under(cell, machine)}/records/{table}"
            t = next((fields[k] for k in ("t", "end_t") if isinstance(fields.get(k), (int, float))), None)
            msg.update(machine=machine, t=t, time=_iso(t), row=fields, units=_units(fields))
        return topic, dumps(msg)

    def live_message(self, s) -> tuple[str, str]:
        cell = self._cell()
        return (f"lathed/{cell}/{_seg(s.source)}/values/{_seg(s.quantity)}",
                dumps({"cell": cell, "source": s.source, "quantity": s.quantity, "value": s.value,
                       "unit": s.unit, "t": s.t, "time": _iso(s.t)}))

    # -- running -------------------------------------------------------------
    async def run(self) -> None:
        if not self._begun:
            await self._begin()
        try:
            await self._run()
        except (aiomqtt.MqttError, OSError, asyncio.TimeoutError) as e:
            self.last_error = self._cause(e)
            raise ConnectionError(self.last_error) from None
        finally:
            self.connected = False

    async def _begin(self) -> None:
        """The progress a sink starts from, written at its first start, broker up or not:
        from then on a restart resumes from the progress, whatever start_from says."""
        store = self.ctx.store
        first = not store.query("SELECT 1 FROM forward_progress WHERE sink = ?", (self.name,))
        # submitted before the first await: the daemon starts its analyzers before it records
        # daemon_started, so that record is this start's, published even from "now"
        done = store.begin_progress(self.name, at_end=self.start_from == "now")
        await asyncio.wrap_future(done)
        self._begun = True
        if first:
            self.ctx.log.info("mqtt_first_start", start_from=self.start_from,
                              after_outbox_id=store.progress(self.name), backlog=store.backlog(self.name))

    async def _run(self) -> None:
        daemon = self.ctx.store.machine_id
        state = self.state_topic()
        session = ({"protocol": aiomqtt.ProtocolVersion.V5, "clean_start": True} if self.protocol == "5" else
                   {"protocol": aiomqtt.ProtocolVersion.V311, "clean_session": True})
        client = _Client(
            self.host, self.port, identifier=f"lathed-{_seg(daemon)}-{self.name}", username=self.username,
            password=self.password, will=aiomqtt.Will(state, "offline", qos=1, retain=True), **session,
            timeout=self.timeout, keepalive=self.keepalive, tls_context=self.tls_context,
            max_inflight_messages=INFLIGHT)
        client.pending_calls_threshold = INFLIGHT + len(self.live) + 2   # a full window is no warning
        async with client:
            await client.publish(state, "online", qos=1, retain=True)
            self._check(client)
            self.connected, self.last_error = True, None
            self.ctx.log.info("mqtt_connected", broker=self.where, backlog=self.ctx.store.backlog(self.name))
            tasks = [asyncio.create_task(self._records(client)), asyncio.create_task(self._watch(client))]
            if self.live:
                tasks.append(asyncio.create_task(self._live(client)))
            try:
                done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
                for t in done:
                    t.result()
            except asyncio.CancelledError:
                # a clean stop: say so (a clean disconnect does not fire the will)
                try:
                    await client.publish(state, "offline", qos=1, retain=True, timeout=min(self.timeout, 2.0))
                except aiomqtt.MqttError:
                    pass
                raise
            finally:
                for t in tasks:
                    t.cancel()
                await asyncio.gather(*tasks, return_exceptions=True)

    async def _records(self, client: aiomqtt.Client) -> None:
        store = self.ctx.store
        window = asyncio.Semaphore(INFLIGHT)
        batch = await asyncio.to_thread(store.pending, self.name, self.batch)
        while True:
            if not batch:
                await asyncio.sleep(self.interval)
                batch = await asyncio.to_thread(store.pending, self.name, self.batch)
                continue
            sends = [asyncio.create_task(self._send(client, window, *self.record_message(*e))) for e in batch]
            counted = False
            # read the next batch while the broker acknowledges this one
            ahead = asyncio.create_task(asyncio.to_thread(store.pending, self.name, self.batch, batch[-1][0]))
            try:
                await asyncio.gather(*sends)    # every PUBACK of the batch...
                self._check(client)
                # counted at the acknowledgement, so a reader who sees the progress saved sees the
                # count; uncounted below if the progress is not saved, as the batch goes again
                self.published += len(batch)
                counted = True
                self.last_publish_t = time.time()
                # ... before the progress moves: a crash before this line only sends the batch again
                await asyncio.wrap_future(store.set_progress(self.name, batch[-1][0]))
            except BaseException:
                if counted:
                    self.published -= len(batch)
                for t in (*sends, ahead):
                    t.cancel()
                raise
            batch = await ahead

    @staticmethod
    async def _send(client: aiomqtt.Client, window: asyncio.Semaphore, topic: str, payload: str) -> None:
        # at most INFLIGHT publishes in the clients at once: both keep per-message lists they scan
        async with window:
            await client.publish(topic, payload, qos=1)

    @staticmethod
    async def _watch(client: aiomqtt.Client) -> None:
        """Raises when the connection drops: caught up, the sink publishes
        nothing that would notice, and the status would say connected."""
        async for _ in client.messages:   # nothing is subscribed: this only ends
            pass
        raise aiomqtt.MqttError("Disconnected during message iteration")

    def _check(self, client: _Client) -> None:
        if client.refused:
            raise Refused(f"MQTT broker at {self.where} discarded {len(client.refused)} message(s): "
                          f"{client.refused[0]} (its ACL must let this client publish under "
                          f"lathed/{self._cell()}/#)")

    async def _live(self, client: aiomqtt.Client) -> None:
        sent: dict[tuple[str, str], float] = {}
        while True:
            await asyncio.sleep(self.live_every)
            for key in self.live:
                s = self.ctx.bus.latest.get(key)
                if s is None or sent.get(key) == s.t:
                    continue
                sent[key] = s.t
                await client.publish(*self.live_message(s), qos=1)
                self.live_published += 1

    def _cause(self, e: BaseException) -> str:
        if isinstance(e, Refused):
            return str(e)
        if isinstance(e, MqttConnectError):
            return f"MQTT broker at {self.where} refused the connection: {_reason(e)}"
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        if "Disconnected during message iteration" in msg:
            return f"MQTT broker at {self.where} closed the connection (broker down or network)"
        if "timed out" in msg.lower() or isinstance(e, asyncio.TimeoutError):
            return (f"MQTT broker at {self.where} did not answer within {self.timeout:g} s "
                    "(broker down or overloaded, or the network)")
        if "certificate" in msg.lower() or isinstance(e, ssl.SSLError):
            return f"MQTT broker at {self.where}: TLS failed: {msg}"
        return f"MQTT broker at {self.where} unreachable (broker down or network): {msg}"

    def status(self) -> dict[str, Any]:
        backlog = self.ctx.store.backlog(self.name) if self.ctx else None
        # a live value no source has published: a misspelt source.quantity, or a source not running
        unseen = [f"{s}.{q}" for s, q in self.live if self.ctx and (s, q) not in self.ctx.bus.latest]
        state = "publishing" if self.connected else "waiting for the broker"
        return {"broker": self.where, "connected": self.connected, "backlog": backlog,
                "published": self.published, "live_published": self.live_published, "live_unseen": unseen,
                "last_error": self.last_error, "last_publish_t": self.last_publish_t,
                "summary": f"{state} ({self.where}), backlog {backlog}"
                           + (f", no value yet on the bus for {', '.join(unseen)}" if unseen else "")
                           + (f", last error: {self.last_error}" if self.last_error else "")}


def _seg(name: str) -> str:
    """One topic level: MQTT gives / + # meanings of their own."""
    return "".join("_" if c in "/+#" else c for c in str(name)) or "_"


def _under(cell: str, machine: str | None) -> str:
    """The topic a record's level hangs from: its machine's, or the cell's own."""
    return f"lathed/{cell}/{_seg(machine)}" if machine else f"lathed/{cell}"


def _iso(t: float | None) -> str | None:
    if t is None:
        return None
    return dt.datetime.fromtimestamp(t, dt.timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _units(fields: dict[str, Any]) -> dict[str, str]:
    out = {}
    for k, v in fields.items():
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            unit = next((u for suffix, u in _UNITS if k.endswith(suffix)), "r/min" if k.startswith("rpm") else None)
            if unit:
                out[k] = unit
    return out


def _reason(e: MqttConnectError) -> str:
    text = str(e)
    hint = " (check username and password)" if "authori" in text.lower() or "password" in text.lower() else ""
    return text + hint


def _file(section: Section, here: Path, key: str) -> Path | None:
    name = section.getstr(key, "")
    if not name:
        return None
    p = Path(name) if Path(name).is_absolute() else here / name
    if not p.is_file():
        raise section.error(key, f"{p}: no such file")
    return p


def _read_secret(section: Section, key: str, p: Path) -> str:
    """A secret alone in a file: its first line; refused when others may read it."""
    mode = p.stat().st_mode & 0o777
    if mode & 0o007:
        raise section.error(key, f"{p}: readable by every user (mode {mode:04o}): chmod 600 it "
                                 "(640 with the lathed group)")
    try:
        text = p.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise section.error(key, f"{p}: cannot be read ({e})") from None
    if not text or not text[0]:
        raise section.error(key, f"{p}: empty: the first line is the password")
    return text[0]


def _tls_context(section: Section, files: dict[str, Path | None]) -> ssl.SSLContext:
    try:
        ctx = ssl.create_default_context(cafile=files["ca_file"])
    except (ssl.SSLError, OSError) as e:
        raise section.error("ca_file", f"{files['ca_file']}: not a CA certificate file ({e})") from None
    if files["cert_file"]:
        try:
            ctx.load_cert_chain(files["cert_file"], files["key_file"])
        except (ssl.SSLError, OSError) as e:
            raise section.error("cert_file", f"{files['cert_file']} with {files['key_file']}: not a client "
                                             f"certificate and its key ({e})") from None
    return ctx


def _live_key(section: Section, text: str) -> tuple[str, str]:
    source, sep, quantity = text.partition(".")
    if not sep or not source or not quantity:
        raise section.error("live", f"{text!r}: expected SOURCE.QUANTITY (e.g. \"lathe.spindle_rpm\")")
    return source, quantity


@hookimpl
def lathed_analyzer_types():
    return {"mqtt_sink": MqttSink}
