"""A plant of two cells: two lathed daemons (two identities, each on its own
simulator) forward to one central PostgreSQL and publish to one MQTT broker;
``lathectl plant`` lists both cells' machines and open alarms from the
database, a subscriber sees both cells on the broker."""
from __future__ import annotations

import json
import subprocess

import psycopg

from tests.conftest import BIN, Daemon, free_port, sim_call, sim_config, wait_until
from tests.mqtt_fixtures import Broker, Subscriber
from tests.pg_fixtures import pg_dsn, postgres  # noqa: F401


def _cell(tmp, name: str, dsn: str, broker_port: int, mill: bool) -> Daemon:
    tmp.mkdir()
    sink = f"""
[analyzer.central]
plugin = "postgres_sink"
dsn = "{dsn}"
interval = "100ms"

[analyzer.mqtt]
plugin = "mqtt_sink"
host = "127.0.0.1"
port = {broker_port}
"""
    mill_port = free_port()
    extra = f"""
[machine.mill]
plugin = "modbus_cnc"
kind = "mill"
host = "127.0.0.1"
port = {mill_port}
poll = "200ms"
retry_initial = "200ms"
retry_max = "1s"

[machine.mill.registers]
spindle_rpm = {{ address = 2, type = "float32", unit = "r/min" }}
program_state = {{ address = 14, type = "uint16" }}
alarm_code = {{ address = 16, type = "uint16" }}
""" if mill else ""
    cfg, paths = sim_config(tmp, extra, sink)
    text = cfg.read_text().replace('name = "test-cell"', f'name = "{name}"', 1)
    if mill:   # the simulator serves the mill only when its table names it
        text = text.replace("[simulator]\n", f"[simulator]\nmill_port = {mill_port}\n", 1)
    cfg.write_text(text)
    d = Daemon(cfg, paths["socket"])
    d.paths = paths
    return d


def _plant(dsn: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(BIN / "lathectl"), "plant", "--dsn", dsn, *args], capture_output=True, text=True,
                          timeout=60)


def _central(dsn: str, sql: str, args=()) -> list:
    with psycopg.connect(dsn) as con:
        return con.execute(sql, args).fetchall()


def test_two_cells_one_database_plant_lists_both(tmp_path, pg_dsn):  # noqa: F811
    r = _plant(pg_dsn)
    assert r.returncode == 66 and "holds no lathed records" in r.stderr, r
    broker = Broker(tmp_path / "broker")
    broker.start()
    sub = a = b = None
    try:
        sub = Subscriber(broker.port)
        a = _cell(tmp_path / "a", "cell-a", pg_dsn, broker.port, mill=True)
        b = _cell(tmp_path / "b", "cell-b", pg_dsn, broker.port, mill=False)
        a.wait_ready()
        b.wait_ready()
        wait_until(lambda: {"mill"} <= {m["name"] for m in json.loads(a.ctl("machines", "--json").stdout)
                                        if m["state"] == "connected"}, 20, what="cell-a's mill connected")
        # a machine that has recorded nothing yet (the mill maps no part counter) is listed from daemon_started
        wait_until(lambda: _central(pg_dsn, "SELECT 1 FROM events WHERE machine_id = 'cell-a' AND "
                                            "kind = 'daemon_started'"), 20, what="cell-a's start centrally")
        mill = next(m for c in json.loads(_plant(pg_dsn, "--json").stdout) if c["cell"] == "cell-a"
                    for m in c["machines"] if m["name"] == "mill")
        assert (mill["kind"], mill["parts"], mill["open_alarms"]) == ("mill", None, [])
        sim_call(a.paths["sim"], "alarm", {"machine": "mill", "code": 1042})
        wait_until(lambda: _central(pg_dsn, "SELECT 1 FROM events WHERE machine_id = 'cell-a' AND "
                                            "kind = 'alarm_raised'"), 20, what="cell-a's mill alarm centrally")
        wait_until(lambda: len(_central(pg_dsn, "SELECT DISTINCT machine_id FROM events WHERE kind = "
                                                "'part_completed'")) == 2, 30, what="parts of both cells centrally")

        r = _plant(pg_dsn, "--json")
        assert r.returncode == 0, r.stderr
        cells = {c["cell"]: c for c in json.loads(r.stdout)}
        assert set(cells) == {"cell-a", "cell-b"}
        machines = {cid: {m["name"]: m for m in c["machines"]} for cid, c in cells.items()}
        assert {n: m["kind"] for n, m in machines["cell-a"].items()} == {"lathe": "lathe", "mill": "mill"}
        assert {n: m["kind"] for n, m in machines["cell-b"].items()} == {"lathe": "lathe"}
        assert [x["alarm"] for x in machines["cell-a"]["mill"]["open_alarms"]] == ["1042"]
        assert machines["cell-a"]["lathe"]["open_alarms"] == machines["cell-b"]["lathe"]["open_alarms"] == []
        assert machines["cell-b"]["lathe"]["parts"] >= 1
        assert not cells["cell-a"]["stopped"] and cells["cell-b"]["version"]

        text = _plant(pg_dsn).stdout
        assert "cell cell-a: running" in text and "cell cell-b: running" in text
        mill_line = next(x for x in text.splitlines() if x.strip().startswith("mill"))
        assert "1042 since" in mill_line

        sim_call(a.paths["sim"], "alarm", {"machine": "mill", "code": 0})   # cleared: no longer open
        wait_until(lambda: _central(pg_dsn, "SELECT 1 FROM events WHERE machine_id = 'cell-a' AND "
                                            "kind = 'alarm_cleared'"), 20, what="the clearing centrally")
        mill = next(m for c in json.loads(_plant(pg_dsn, "--json").stdout) if c["cell"] == "cell-a"
                    for m in c["machines"] if m["name"] == "mill")
        assert mill["open_alarms"] == []

        # and both on the one broker, each under its own cell
        for cell in ("cell-a", "cell-b"):
            assert sub.received(f"lathed/{cell}/state")[-1][1] == b"online"
            assert sub.received(f"lathed/{cell}/lathe/events/part_completed")
        assert sub.received("lathed/cell-a/mill/events/alarm_raised")
    finally:
        for cell in (a, b):
            if cell is not None:
                cell.stop()
        if sub is not None:
            sub.close()
        broker.stop()
