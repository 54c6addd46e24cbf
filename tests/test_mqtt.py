"""The MQTT sink against a real Mosquitto broker (tests/mqtt_fixtures.py):
the documented topics and payloads, a broker outage that loses nothing, the
last will, and bad configuration."""
from __future__ import annotations

import asyncio
import gc
import json
import re
import shutil
import signal
import sqlite3
import subprocess
import time
from pathlib import Path

import pytest
import structlog

from lathed.bus import Bus
from lathed.config import ConfigError, Section
from lathed.store import Store
from lathed_plugins.mqtt_sink import MqttSink
from tests.conftest import BIN, Daemon, disk_full, shipped_config, wait_until
from tests.mqtt_fixtures import Broker, Subscriber, check_message, schema_validator

HERE = Path(__file__).resolve().parent
OUTAGE_S = 10.0


@pytest.fixture
def broker(tmp_path):
    b = Broker(tmp_path / "broker")
    b.start()
    yield b
    b.stop()


def _sink_section(port: int, **keys) -> str:
    extra = "".join(f"{k} = {json.dumps(v)}\n" for k, v in keys.items())
    return f"""
[analyzer.mqtt]
plugin = "mqtt_sink"
host = "127.0.0.1"
port = {port}
interval = "50ms"
timeout = "2s"
retry_initial = "100ms"
retry_max = "500ms"
{extra}"""


def _local(db: Path, sql: str):
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=10)
    try:
        return con.execute(sql).fetchall()
    finally:
        con.close()


def _enable_shipped_sink(cfg: Path, port: int) -> None:
    """Uncomment etc/lathed.toml's [analyzer.mqtt] as a plant would, pointed at the test broker."""
    text = cfg.read_text()
    head, _, rest = text.partition("# [analyzer.mqtt]\n")
    block, sep, tail = rest.partition("\n\n")
    block = "\n".join(line[2:] for line in ("# [analyzer.mqtt]\n" + block).splitlines())
    for key, value in (("port", port), ("live_every", '"200ms"'),
                       ("live", '["lathe.spindle_rpm", "chatter.chatter_index", "lathe.spindle_rmp"]')):
        block = re.sub(rf"^{key} = .*$", f"{key} = {value}", block, count=1, flags=re.M)
    cfg.write_text(head + block + '\nretry_initial = "100ms"\nretry_max = "500ms"\n' + sep + tail)


def test_first_enable_on_the_shipped_config_publishes_from_now_to_the_schemas(tmp_path, broker):
    """The plant's case: lathed has run without MQTT, then the shipped [analyzer.mqtt] is
    uncommented. Nothing stored before is published, everything after is, on the documented
    topics (the cell once), each message valid against its JSON Schema."""
    cfg, sock = shipped_config(tmp_path)
    db = tmp_path / "state" / "lathed.db"
    d = Daemon(cfg, sock)
    try:
        d.wait_ready()
        wait_until(lambda: _local(db, "SELECT count(*) FROM events WHERE kind = 'daemon_started'")[0][0], 20,
                   what="the first run's records")
    finally:
        d.stop()
    history = _local(db, "SELECT max(id) FROM outbox")[0][0]
    assert history >= 2                                  # at least daemon_started and daemon_stopped
    _enable_shipped_sink(cfg, broker.port)
    sub = Subscriber(broker.port)
    try:
        d = Daemon(cfg, sock)
        d.wait_ready()
        for topic in ("lathed/sim-cell-1/lathe/events/part_completed", "lathed/sim-cell-1/lathe/events/cut",
                      "lathed/sim-cell-1/lathe/records/workpieces", "lathed/sim-cell-1/chatter/values/chatter_index"):
            wait_until(lambda: sub.received(topic), 60, what=topic)
        topic, msg = sub.json("lathed/sim-cell-1/lathe/events/part_completed")[0]
        uuid, seq = msg["id"].split("/")
        assert (msg["uuid"], msg["seq"]) == (uuid, int(seq))
        assert msg["cell"] == "sim-cell-1" and msg["daemon"] == "web-test" and msg["machine"] == "lathe"
        assert msg["kind"] == "part_completed" and msg["source"] == "lathe" and msg["table"] == "events"
        assert msg["payload"]["kind"] == "lathe" and msg["payload"]["part_count"] >= 1
        assert msg["time"].endswith("Z") and abs(msg["t"] - time.time()) < 60
        # the message is the local record: same uuid, and its outbox id as seq
        row = _local(db, f"SELECT o.id, e.kind FROM events e JOIN outbox o ON o.tbl = 'events' AND o.row_id = e.id "
                         f"WHERE e.uuid = '{uuid}'")
        assert row == [(int(seq), "part_completed")]
        # this start's daemon_started is the first record after the history, and published
        started = sub.json("lathed/sim-cell-1/events/daemon_started")
        assert len(started) == 1 and started[0][1]["payload"]["pid"] == d.proc.pid
        assert started[0][1]["seq"] == history + 1 and started[0][1]["machine"] is None

        wait_until(lambda: sub.received("lathed/sim-cell-1/lathe/values/spindle_rpm"), 10, what="a live spindle speed")
        _, live = sub.json("lathed/sim-cell-1/lathe/values/spindle_rpm")[-1]
        assert live["unit"] == "r/min" and live["quantity"] == "spindle_rpm" and isinstance(live["value"], float)

        assert sub.received("lathed/sim-cell-1/state")[-1][1] == b"online"
        late = Subscriber(broker.port, "lathed/+/state")   # retained: a late subscriber learns it too
        wait_until(lambda: late.received(), 10, what="the retained state")
        late.close()
        assert late.received() == [("lathed/sim-cell-1/state", b"online", True)]
        st = d.item("analyzers", "mqtt")
        assert st["connected"] and st["published"] >= 2 and st["live_published"] >= 1
        # a misspelt live value is named, not silently never sent
        assert st["live_unseen"] == ["lathe.spindle_rmp"] and "no value yet on the bus for lathe.spindle_rmp" \
            in st["summary"]
        d.stop()                                   # a clean stop says "offline" itself
        wait_until(lambda: sub.received("lathed/sim-cell-1/state")[-1][1] == b"offline", 10,
                   what="offline state after a clean stop")
    finally:
        d.stop()
        sub.close()
    got = sub.received()
    seqs = [json.loads(p)["seq"] for t, p, _ in got if "/events/" in t or "/records/" in t]
    assert min(seqs) == history + 1, f"{sum(s <= history for s in seqs)} record(s) from before the enable published"
    # every message a real daemon on the shipped config published fits the tree and its JSON Schema
    validators = {k: schema_validator(k) for k in ("event", "record", "value")}
    kinds = [check_message(t, p, validators) for t, p, _ in got]
    assert {"state", "event", "record", "value"} <= set(kinds), kinds
    print(f"{len(got)} messages valid; kinds of event: "
          f"{sorted({json.loads(p)['kind'] for t, p, _ in got if '/events/' in t})}")


def _writer_config(tmp: Path, port: int, total: int, every: str = "5ms") -> tuple[Path, Path]:
    plugins = tmp / "plugins"
    plugins.mkdir(exist_ok=True)
    shutil.copy(HERE / "writer_plugin.py", plugins / "test_writer.py")
    cfg = tmp / "lathed.toml"
    cfg.write_text(f"""
[daemon]
name = "cell-mq"
state_dir = "{tmp / 'state'}"
runtime_dir = "{tmp / 'run'}"
plugin_dirs = ["{plugins}"]

[analyzer.writer]
plugin = "test_writer"
total = {total}
every = "{every}"
{_sink_section(port, batch=50)}""")
    return cfg, tmp / "run" / "lathed.sock"


def _records(sub: Subscriber) -> list[dict]:
    return [json.loads(p) for t, p, _ in sub.received("lathed/cell-mq/") if not t.endswith("/state")]


def test_broker_outage_and_daemon_crash_lose_nothing(tmp_path, broker):
    total = 600
    cfg, sock = _writer_config(tmp_path, broker.port, total, every="10ms")
    db = tmp_path / "state" / "lathed.db"
    # a persistent session: what the broker queued for us survives its restart
    sub = Subscriber(broker.port, "lathed/cell-mq/#", client_id="plant-historian")
    d = Daemon(cfg, sock)
    try:
        d.wait_ready()
        wait_until(lambda: len(sub.received("lathed/cell-mq/writer/events/tick")) >= 100, 30,
                   what="the first ticks through the broker")
        broker.stop()                               # the broker goes away mid-stream
        down = time.monotonic()
        at_stop = _local(db, "SELECT count(*) FROM events WHERE kind = 'tick'")[0][0]
        wait_until(lambda: "MQTT broker at 127.0.0.1" in (d.item("analyzers", "mqtt").get("last_error") or ""),
                   20, what="the sink to report the outage")
        assert not d.item("analyzers", "mqtt")["connected"]
        wait_until(lambda: _local(db, "SELECT count(*) FROM events WHERE kind = 'tick'")[0][0] >= at_stop + 100,
                   20, what="records written locally during the outage")
        d.proc.kill()                               # and the daemon crashes during the outage
        d.proc.wait(10)
        d.log.close()
        d = Daemon(cfg, sock)
        d.wait_ready()
        assert d.item("analyzers", "mqtt")["backlog"] > 100, "records should wait while the broker is down"
        # the outage lasts OUTAGE_S: this wait is the scenario's length, not a synchronisation
        wait_until(lambda: time.monotonic() - down >= OUTAGE_S, OUTAGE_S + 5, what="the outage's end")
        broker.start()                              # back on the same port
        wait_until(lambda: d.item("analyzers", "writer").get("done"), 60, what="the writer to finish")
        wait_until(lambda: d.item("analyzers", "mqtt")["backlog"] == 0, 60, what="the backlog to drain")
        d.stop()
        # a batch in flight is normal, not a warning per message (aiomqtt's default above 10)
        assert "pending publish calls" not in cfg.with_suffix(".log").read_text()
        local = dict(_local(db, "SELECT o.id, e.uuid FROM events e JOIN outbox o "
                                "ON o.tbl = 'events' AND o.row_id = e.id"))
        # everything published before the final stop reaches the subscriber (its daemon_stopped may trail)
        wait_until(lambda: len({m["seq"] for m in _records(sub)}) >= len(local) - 1, 20,
                   what="every record at the subscriber")
        got = _records(sub)
    finally:
        d.stop()
        sub.close()
    ids = [m["id"] for m in got]
    assert all(m["id"] == f"{local[m['seq']]}/{m['seq']}" for m in got), "a message id that is no local record"
    seqs = sorted({m["seq"] for m in got})
    assert seqs == list(range(min(local), min(local) + len(seqs))), "a gap in seq"
    assert set(local) - set(seqs) <= {max(local)}
    ticks = sorted({m["payload"]["seq"] for m in got if m.get("kind") == "tick"})
    assert ticks == list(range(total)), f"{total - len(ticks)} tick(s) lost"
    # QoS 1 may resend a batch the broker had but did not acknowledge: same id, so detectable
    print(f"{len(ids)} messages, {len(ids) - len(set(ids))} duplicate(s) by id")


def test_last_will_when_the_daemon_is_killed(tmp_path, broker):
    cfg, sock = _writer_config(tmp_path, broker.port, total=10)
    sub = Subscriber(broker.port, "lathed/+/state")
    d = Daemon(cfg, sock)
    try:
        d.wait_ready()
        wait_until(lambda: sub.received("lathed/cell-mq/state"), 20, what="the birth message")
        assert sub.received()[-1][1] == b"online"
        d.proc.send_signal(signal.SIGKILL)          # no clean disconnect: the broker sends the will
        d.proc.wait(10)
        wait_until(lambda: sub.received()[-1][1] == b"offline", 10, what="the last will")
    finally:
        d.stop()
        sub.close()
    late = Subscriber(broker.port, "lathed/+/state")   # retained: a late subscriber learns it too
    try:
        wait_until(lambda: late.received(), 10, what="the retained state")
        assert late.received() == [("lathed/cell-mq/state", b"offline", True)]
    finally:
        late.close()


def _check(tmp_path: Path, section: str) -> subprocess.CompletedProcess:
    cfg = tmp_path / "bad.toml"
    cfg.write_text(f'[daemon]\nname = "x"\nstate_dir = "{tmp_path / "s"}"\nruntime_dir = "{tmp_path / "r"}"\n'
                   + section)
    return subprocess.run([str(BIN / "lathed"), "--check-config", str(cfg)], capture_output=True, text=True,
                          timeout=60)


@pytest.mark.parametrize("keys, expect", [
    ('port = 70000', "[analyzer.mqtt] port: "),
    ('ca_file = "no-such-ca.crt"', "/no-such-ca.crt: no such file"),
])
def test_bad_config_is_one_clear_line(tmp_path, keys, expect):
    r = _check(tmp_path, f'[analyzer.mqtt]\nplugin = "mqtt_sink"\nhost = "127.0.0.1"\n{keys}\n')
    assert r.returncode == 78, r
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "[analyzer.mqtt]" in lines[0] and expect in lines[0], lines


@pytest.mark.parametrize("keys, expect", [
    ({"port": "1883"}, "port: expected an integer"),
    ({"cert_file": __file__}, "key_file: missing: a client certificate needs both"),
    ({"cert_file": __file__, "key_file": __file__}, "cert_file: " + __file__ + " with"),
    ({"ca_file": __file__}, "ca_file: " + __file__ + ": not a CA certificate file"),
    ({"ca_file": __file__, "tls": False}, "tls: is false but a ca_file"),
    ({"password": "p"}, "password: given without a username"),
    ({"live": ["spindle_rpm"]}, "live: 'spindle_rpm': expected SOURCE.QUANTITY"),
    ({"timeout": "0s"}, "timeout: "),
])
def test_bad_keys_are_refused_by_name(keys, expect):
    with pytest.raises(ConfigError) as e:
        MqttSink("mqtt", Section("lathed.toml", "analyzer.mqtt", {"host": "b", **keys}))
    assert str(e.value).startswith("lathed.toml: [analyzer.mqtt] ") and expect in str(e.value), str(e.value)
    assert "\n" not in str(e.value)


def test_the_password_comes_from_a_file_only_lathed_reads(tmp_path):
    pw = tmp_path / "mqtt.pass"
    pw.write_text("s3cret\n")
    pw.chmod(0o640)
    cfg = {"host": "b", "username": "lathed", "password_file": "mqtt.pass"}
    sink = MqttSink("mqtt", Section(str(tmp_path / "lathed.toml"), "analyzer.mqtt", cfg))
    assert sink.password == "s3cret"
    for mode, extra, expect in [(0o644, {}, "readable by every user (mode 0644): chmod 600"),
                                (0o600, {"password": "p"}, "password_file: and password are both given"),
                                (0o600, {"username": ""}, "password_file: given without a username")]:
        pw.chmod(mode)
        with pytest.raises(ConfigError, match=re.escape(expect)):
            MqttSink("mqtt", Section(str(tmp_path / "lathed.toml"), "analyzer.mqtt", {**cfg, **extra}))
    pw.write_text("")
    with pytest.raises(ConfigError, match="empty: the first line is the password"):
        MqttSink("mqtt", Section(str(tmp_path / "lathed.toml"), "analyzer.mqtt", cfg))


class Ctx:
    def __init__(self, store):
        self.store = store
        self.bus = Bus()
        self.log = structlog.get_logger("test")


def _sink(store: Store, name: str = "mqtt", **keys) -> MqttSink:
    # these tests store records, then start the sink: from the oldest unless told
    sec = Section("test.toml", f"analyzer.{name}", {"host": "127.0.0.1", "interval": "20ms", "timeout": "2s",
                                                    "start_from": "oldest", **keys})
    sink = MqttSink(name, sec)
    sec.check_unused()
    sink.ctx = Ctx(store)
    return sink


async def _until_drained(sink: MqttSink, timeout: float = 20) -> None:
    task = asyncio.create_task(sink.run())
    try:
        deadline = asyncio.get_running_loop().time() + timeout
        while sink.ctx.store.backlog(sink.name) > 0:
            if task.done():
                task.result()
            assert asyncio.get_running_loop().time() < deadline, f"backlog stuck at {sink.ctx.store.backlog('mqtt')}"
            await asyncio.sleep(0.02)
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)


def test_broker_down_is_a_fault_with_the_cause(tmp_path):
    from tests.conftest import free_port
    store = Store(tmp_path / "a.db", machine_id="cell-a")
    sink = _sink(store, port=free_port(), start_from="now")

    async def main():
        await store.record("tick", "w", {"seq": 0})
        with pytest.raises(ConnectionError, match="MQTT broker at 127.0.0.1:.* unreachable"):
            await sink.run()
        # "now" is the first start, broker up or not: what is stored after it waits for the broker
        assert store.backlog("mqtt") == 0
        await store.record("tick", "w", {"seq": 1})
        with pytest.raises(ConnectionError, match="MQTT broker at 127.0.0.1:.* unreachable"):
            await sink.run()

    asyncio.run(main())
    st = sink.status()
    assert not st["connected"] and st["backlog"] == 1 and "waiting for the broker" in st["summary"]
    store.close()


def test_start_from_now_publishes_nothing_old_and_keeps_its_place(tmp_path, broker):
    """A first enable on a store with history: "now" publishes none of it, then every
    new record, and after a restart what was stored while it was stopped; "oldest"
    publishes everything."""
    store = Store(tmp_path / "a.db", machine_id="cell-h")
    old, new, between = 40, 5, 3
    sub = Subscriber(broker.port)

    async def add(n: int) -> None:
        for i in range(n):
            await store.record("tick", "w", {"seq": i})

    async def running(sink: MqttSink, n: int) -> None:
        """Start the sink, store n records, wait until it has published them all."""
        task = asyncio.create_task(sink.run())
        try:
            deadline = asyncio.get_running_loop().time() + 20
            while not sink.connected:
                assert not task.done(), task.result()
                assert asyncio.get_running_loop().time() < deadline, "the sink never connected"
                await asyncio.sleep(0.01)
            await add(n)
            while store.backlog(sink.name) > 0:
                assert not task.done(), task.result()
                assert asyncio.get_running_loop().time() < deadline, f"backlog stuck at {store.backlog(sink.name)}"
                await asyncio.sleep(0.02)
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    try:
        async def main():
            await add(old)
            history = store.query("SELECT max(id) AS m FROM outbox")[0]["m"]
            now = _sink(store, "plant", port=broker.port, cell="now", start_from="now")
            await running(now, new)
            assert now.published == new
            await add(between)                  # stored while the sink is stopped
            again = _sink(store, "plant", port=broker.port, cell="now", start_from="now")
            await running(again, 0)
            assert again.published == between
            oldest = _sink(store, "historian", port=broker.port, cell="old", start_from="oldest")
            await running(oldest, 0)
            assert oldest.published == old + new + between
            return history

        history = asyncio.run(main())
        wait_until(lambda: len(sub.received("lathed/old/")) >= 2 + old + new + between, 10,
                   what="the oldest sink's messages")
        sent_now = sorted(json.loads(p)["seq"] for t, p, _ in sub.received("lathed/now/") if "/events/" in t)
        sent_old = sorted(json.loads(p)["seq"] for t, p, _ in sub.received("lathed/old/") if "/events/" in t)
    finally:
        sub.close()
        store.close()
    assert history == old
    assert sent_now == list(range(old + 1, old + new + between + 1)), sent_now
    assert sent_old == list(range(1, old + new + between + 1))


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True, timeout=60)


def test_tls_with_client_certificate_and_password(tmp_path):
    """The sink verifies the broker against ca_file, shows its client
    certificate, and logs in; a wrong password is refused with the cause."""
    pki = tmp_path / "pki"
    pki.mkdir()
    _openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1", "-subj", "/CN=test-ca",
             "-keyout", "ca.key", "-out", "ca.crt", cwd=pki)
    for name, cn in (("server", "127.0.0.1"), ("client", "lathed")):
        _openssl("req", "-newkey", "rsa:2048", "-nodes", "-subj", f"/CN={cn}", "-keyout", f"{name}.key",
                 "-out", f"{name}.csr", cwd=pki)
        ext = pki / f"{name}.ext"
        ext.write_text("subjectAltName = IP:127.0.0.1\n" if name == "server" else "basicConstraints = CA:FALSE\n")
        _openssl("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.crt", "-CAkey", "ca.key", "-CAcreateserial",
                 "-days", "1", "-extfile", ext.name, "-out", f"{name}.crt", cwd=pki)
    subprocess.run(["mosquitto_passwd", "-b", "-c", str(pki / "passwd"), "lathed", "s3cret"], check=True,
                   capture_output=True, timeout=30)
    broker = Broker(tmp_path / "broker", listener=(
        f"allow_anonymous false\npassword_file {pki / 'passwd'}\ncafile {pki / 'ca.crt'}\n"
        f"certfile {pki / 'server.crt'}\nkeyfile {pki / 'server.key'}\nrequire_certificate true\n"))
    broker.start()
    store = Store(tmp_path / "a.db", machine_id="cell-tls")
    tls = {"port": broker.port, "ca_file": str(pki / "ca.crt"), "cert_file": str(pki / "client.crt"),
           "key_file": str(pki / "client.key"), "username": "lathed"}
    try:
        async def main():
            await store.record("tick", "w", {"seq": 1})
            wrong = _sink(store, password="nope", **tls)
            with pytest.raises(ConnectionError, match="refused the connection.*(authori|password)"):
                await wrong.run()
            await _until_drained(_sink(store, password="s3cret", **tls))

        asyncio.run(main())
        assert store.backlog("mqtt") == 0
    finally:
        store.close()
        broker.stop()


def test_every_record_table_has_its_topic_and_units(tmp_path, broker):
    store = Store(tmp_path / "a.db", machine_id="cell-a")
    sub = Subscriber(broker.port)
    part = "00000000-0000-0000-0000-000000000001"

    async def main():
        await store.record("chatter_alarm", "chatter", {"machine": "lathe", "index": 2.5, "rpm": 2500.0,
                                                        "chatter_frequency_hz": 197.0, "depth_mm": 3.0})
        await store.record("config_reloaded", "lathed", {"changed": []})
        await store.add("workpieces", {"uuid": part, "machine": "lathe", "start_t": 1.0, "end_t": 2.0,
                                       "outcome": "partial", "chatter_alarms": 1, "abnormal": 1,
                                       "unwatched": "lathed was not running"})
        await store.add("inspections", {"t": 3.0, "part_uuid": part, "ra_um": 4.2, "measured": {"roundness_um": 3.0}})
        await store.add("sampling_queue", {"t": 2.0, "part_uuid": part, "reason": "abnormal"})
        await store.add("experiments", {"t": 4.0, "tool": "T0101", "material": "C45", "run": 1,
                                        "levels": {"rpm": 1, "feed": 2}, "settings": {"rpm": 1800, "feed": 0.15},
                                        "ra_um": 1.6, "part_uuid": part})
        await _until_drained(_sink(store, port=broker.port, cell="hall-2"))

    try:
        asyncio.run(main())
        wait_until(lambda: len(sub.received("lathed/hall-2/")) >= 8, 10, what="six records, online and offline")
        got = {t: json.loads(p) for t, p, _ in sub.received("lathed/hall-2/") if not t.endswith("/state")}
        # each fits the tree and its kind's JSON Schema
        assert sorted(check_message(t, p) for t, p, _ in sub.received("lathed/hall-2/")) == \
            ["event", "event", "record", "record", "record", "record", "state", "state"]
    finally:
        sub.close()
        store.close()
    assert set(got) == {"lathed/hall-2/lathe/events/chatter_alarm", "lathed/hall-2/events/config_reloaded",
                        "lathed/hall-2/lathe/records/workpieces", "lathed/hall-2/records/inspections",
                        "lathed/hall-2/records/sampling_queue", "lathed/hall-2/records/experiments"}
    alarm = got["lathed/hall-2/lathe/events/chatter_alarm"]
    assert alarm["units"] == {"rpm": "r/min", "chatter_frequency_hz": "Hz", "depth_mm": "mm"}
    assert got["lathed/hall-2/events/config_reloaded"]["machine"] is None
    assert [m["seq"] for m in sorted(got.values(), key=lambda m: m["seq"])] == [1, 2, 3, 4, 5, 6]
    wp = got["lathed/hall-2/lathe/records/workpieces"]
    assert (wp["table"], wp["uuid"], wp["t"], wp["row"]["outcome"], wp["row"]["unwatched"]) == \
        ("workpieces", part, 2.0, "partial", "lathed was not running")
    insp = got["lathed/hall-2/records/inspections"]
    assert insp["row"]["measured"] == {"roundness_um": 3.0} and insp["units"] == {"ra_um": "µm"}
    assert insp["time"] == "1970-01-01T00:00:03.000Z"


def test_the_record_schema_has_every_column_of_every_table(tmp_path):
    """record.schema.json's rows are the store's tables: a column added to a table and not to
    the schema (or the reverse, or a wrong type or nullability) fails here."""
    from lathed.store import FORWARDED, JSON_COLUMNS
    store = Store(tmp_path / "a.db", machine_id="cell-s")
    try:
        tables = {t: store.query(f"PRAGMA table_info({t})") for t in FORWARDED if t != "events"}
    finally:
        store.close()
    schema = schema_validator("record").schema
    assert set(schema["properties"]["table"]["enum"]) == set(tables)
    sql_type = {"TEXT": "string", "REAL": "number", "INTEGER": "integer"}
    for table, cols in tables.items():
        row = schema["$defs"][table]
        cols = [c for c in cols if c["name"] not in ("id", "uuid", "machine_id")]
        assert set(row["properties"]) == {c["name"] for c in cols} == set(row["required"]), table
        for c in cols:
            prop = row["properties"][c["name"]]
            types = prop["type"] if "type" in prop else sorted({type(v).__name__ for v in prop["enum"]})
            types = [types] if isinstance(types, str) else types
            want = "object" if c["name"] in JSON_COLUMNS else sql_type[c["type"]]
            assert want in types or (types == ["int"] and want == "integer"), (table, c["name"], types)
            assert ("null" in types) == (not c["notnull"]), (table, c["name"], "nullability")


def test_the_schemas_refuse_what_is_not_the_documented_payload():
    event = {"id": "4af4e243-0c32-45bb-9d17-0354f7a4a430/7", "uuid": "4af4e243-0c32-45bb-9d17-0354f7a4a430",
             "seq": 7, "cell": "c", "daemon": "c", "table": "events", "machine": None, "kind": "daemon_started",
             "source": "lathed", "t": 3.0, "time": "1970-01-01T00:00:03.000Z", "payload": {}, "units": {}}
    v = schema_validator("event")
    v.validate(event)
    for bad in ({"seq": 0}, {"time": "1970-01-01 00:00:03"}, {"units": {"x_mm": "inch"}}, {"extra": 1},
                {"payload": [1]}, {"id": "7"}):
        assert not v.is_valid({**event, **bad}), bad
    assert not v.is_valid({k: x for k, x in event.items() if k != "seq"})


def test_a_batch_whose_progress_the_store_refused_is_not_counted(tmp_path):
    """Acknowledged by the broker, its progress refused locally (disk full): the sink fails
    and the batch goes again at its restart, so it is not counted as published yet."""
    broker = Broker(tmp_path / "broker")
    broker.start()
    store = Store(tmp_path / "a.db", machine_id="cell-p")
    store.begin_progress("mqtt", at_end=False).result(5)     # the sink began before the disk filled
    disk_full(store, "forward_progress")
    sink = _sink(store, port=broker.port)
    try:
        async def main():
            await store.record("tick", "w", {"seq": 0})
            with pytest.raises(sqlite3.DatabaseError, match="disk is full"):
                await asyncio.wait_for(sink.run(), 10)

        asyncio.run(main())
        assert store.backlog("mqtt") == 1 and sink.published == 0
    finally:
        store.close()
        broker.stop()


def test_a_message_the_broker_discards_is_not_marked_sent(tmp_path, caplog):
    """An ACL that lets the sink connect but not publish: MQTT 5's PUBACK says
    so, the records stay in the backlog, and the cause is named. The client's end
    leaves no error behind: aiomqtt keeps the broker's disconnection on a future its
    __aexit__ may not read, and asyncio logged "Future exception was never retrieved"
    when it was collected, in whatever ran then."""
    acl = tmp_path / "acl"
    acl.write_text("topic read lathed/#\n")          # anonymous: read only
    broker = Broker(tmp_path / "broker", extra=f"acl_file {acl}\n")
    broker.start()
    store = Store(tmp_path / "a.db", machine_id="cell-acl")
    sink = _sink(store, port=broker.port)
    try:
        async def main():
            await store.record("tick", "w", {"seq": 0})
            with pytest.raises(ConnectionError, match=r"discarded 1 message\(s\): Not authorized .*lathed/cell-acl/#"):
                await asyncio.wait_for(sink.run(), 10)

        asyncio.run(main())
        assert store.backlog("mqtt") == 1 and sink.published == 0
        gc.collect()
        assert [r.getMessage() for r in caplog.records if r.name == "asyncio"] == []
    finally:
        store.close()
        broker.stop()


def test_a_caught_up_sink_notices_the_broker_going_away(tmp_path, broker):
    """Nothing to publish would not show the outage: the status must not say connected."""
    store = Store(tmp_path / "a.db", machine_id="cell-idle")
    sink = _sink(store, port=broker.port)

    async def main():
        task = asyncio.create_task(sink.run())
        while not sink.connected:
            assert not task.done(), task.result()
            await asyncio.sleep(0.01)
        await asyncio.to_thread(broker.stop)
        with pytest.raises(ConnectionError, match="closed the connection"):
            await asyncio.wait_for(task, 10)

    try:
        asyncio.run(main())
        assert not sink.status()["connected"] and "closed the connection" in sink.status()["summary"]
    finally:
        store.close()
