"""The uniform machine model: time stamps, staleness, events exactly once;
and the default line of four simulated machines in ``lathectl machines``."""
from __future__ import annotations

import json

import pytest

from lathed.machine import MachineModel
from tests.conftest import ROOT, Daemon, free_port, sim_call, sim_config, wait_until


class Clock:
    def __init__(self):
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def model(stale_after=2.0):
    clock, events = Clock(), []
    m = MachineModel("mill", stale_after, lambda k, p: events.append((k, p)), clock=clock)
    m.link_up()
    return m, clock, events


def test_values_go_stale_with_age_and_with_the_link():
    m, clock, _ = model()
    m.set("spindle_rpm", 1500.0)
    m.set_axis("x", 12.5)
    assert m.live("spindle_rpm") == 1500.0 and m.state() == "running"
    clock.t += 1.9
    assert m.snapshot()["spindle_rpm"]["stale"] is False
    clock.t += 0.2
    snap = m.snapshot()
    assert snap["spindle_rpm"] == {"value": 1500.0, "t": 1000.0, "age_s": 2.1, "stale": True}
    assert snap["axes"]["x"]["stale"] and m.live("spindle_rpm") is None
    assert snap["state"] == "disconnected"      # nothing fresh: never shown as running
    m.set("spindle_rpm", 0.0)
    assert m.state() == "idle"
    m.link_down()                                # fresh by age, but the link is gone
    snap = m.snapshot()
    assert snap["state"] == "disconnected" and snap["spindle_rpm"]["stale"] and m.live("spindle_rpm") is None
    assert snap["spindle_rpm"]["value"] == 0.0   # the last known value is kept, marked stale


def test_state_from_controller_and_alarms():
    m, clock, events = model()
    m.set_running(False)
    m.set("spindle_rpm", 900.0)
    assert m.state() == "idle"                   # the controller's word beats the spindle's
    m.set_alarms([1042])
    assert m.state() == "alarm"
    m.set_alarms([1042])
    m.set_alarms([])
    assert events == [("alarm_raised", {"kind": "mill", "alarm": "1042"}),
                      ("alarm_cleared", {"kind": "mill", "alarm": "1042"})]


def test_parts_recorded_once_across_a_reconnect():
    m, clock, events = model()
    m.set("part_count", 41)                      # baseline: not ours to record
    m.set("part_count", 42)
    m.set("part_count", 42)
    m.link_down()
    m.link_up()
    m.set("part_count", 42)                      # same count after the reconnect: nothing new
    m.set("part_count", 45)                      # three made while the link was down
    parts = [(p["part_count"], p["late"]) for k, p in events if k == "part_completed"]
    assert parts == [(42, False), (43, True), (44, True), (45, False)]
    m.set("part_count", 3)
    assert events[-1] == ("part_counter_reset", {"kind": "mill", "from": 45, "to": 3})
    m.set("part_count", 4)
    assert events[-1][1]["part_count"] == 4


def test_unknown_field_is_refused():
    m, _, _ = model()
    with pytest.raises(KeyError, match="not a machine model field"):
        m.set("spindle_speed", 1.0)


def test_default_line_shows_four_machines_live(tmp_path):
    """The default run's line (lathe, mill, grinder, robot) in `lathectl machines`;
    a robot powered off goes stale, not live, and comes back."""
    mill_port = free_port()
    extra = f"""
[machine.mill]
plugin = "modbus_cnc"
kind = "mill"
host = "127.0.0.1"
port = {mill_port}
poll = "100ms"
retry_initial = "200ms"
retry_max = "1s"

[machine.mill.registers]
spindle_rpm_cmd = {{ address = 0, type = "float32", writable = true, unit = "r/min" }}
spindle_rpm = {{ address = 2, type = "float32", unit = "r/min" }}
x_mm = {{ address = 4, type = "float32", unit = "mm" }}
part_count = {{ address = 10, type = "int32", poll = "500ms" }}
program_state = {{ address = 14, type = "uint16" }}
alarm_code = {{ address = 16, type = "uint16" }}

[machine.mill.identification]
serial_number = "SIM-MILL-0001"

[machine.mill.identity]
serial_number = {{ address = 20, words = 8 }}

[machine.grinder]
plugin = "modbus_cnc"
kind = "grinder"
transport = "rtu"
device = "{tmp_path / 'ttyGRINDER'}"
baudrate = 115200
poll = "200ms"
retry_initial = "200ms"
retry_max = "1s"

[machine.grinder.registers]
spindle_rpm = {{ address = 2, type = "float32", unit = "r/min" }}
part_count = {{ address = 10, type = "int32" }}
program_state = {{ address = 14, type = "uint16" }}

[machine.robot]
plugin = "can_robot"
interface = "slcan"
channel = "{tmp_path / 'ttyCAN'}"
dbc = "{ROOT / 'etc' / 'robot_arm.dbc'}"
timeout = "500ms"
retry_initial = "200ms"
retry_max = "1s"
"""
    cfg, paths = sim_config(tmp_path, extra)
    # the simulator serves the neighbours only when its table names them
    cfg.write_text(cfg.read_text().replace(
        "[simulator]\n", f'[simulator]\nmill_port = {mill_port}\ngrinder_link = "{tmp_path / "ttyGRINDER"}"\n'
                         f'robot_link = "{tmp_path / "ttyCAN"}"\n', 1))
    d = Daemon(cfg, paths["socket"])
    d.paths = paths
    try:
        d.wait_ready()
        check_line(d)
    finally:
        d.stop()


def check_line(d: Daemon) -> None:
    def machines():
        return json.loads(d.ctl("machines", "--json").stdout)

    ms = wait_until(lambda: (m := machines()) and all(
        x["state"] == "connected" and x["model"]["state"] == "running" for x in m) and m,
        timeout=20, what="four machines running")
    assert [m["name"] for m in ms] == ["lathe", "mill", "grinder", "robot"]
    for m in ms:
        assert {"name", "kind", "state", "spindle_rpm"} <= set(m)
        assert not m["model"]["part_count"]["stale"]
    robot = ms[3]["model"]
    assert set(robot["axes"]) == {"j1", "j2", "j3", "j4", "j5", "j6", "tool_x", "tool_y", "tool_z"}
    assert robot["gripper"]["value"] in ("open", "closed", "moving")
    table = d.ctl("machines").stdout
    assert all(n in table for n in ("lathe", "mill", "grinder", "robot")) and "?" not in table
    sim_call(d.paths["sim"], "outage", {"peer": "robot", "seconds": 6})
    r = wait_until(lambda: (m := machines()[3])["model"]["state"] == "disconnected" and m, timeout=5,
                   what="robot shown disconnected")
    assert r["model"]["axes"]["j1"]["stale"] and r["spindle_rpm"] is None
    robot_line = next(x for x in d.ctl("machines").stdout.splitlines() if x.startswith("robot"))
    assert "disconnected" in robot_line and "?" in robot_line
    wait_until(lambda: machines()[3]["model"]["state"] == "running", timeout=8, what="robot back")
    sim_call(d.paths["sim"], "alarm", {"machine": "mill", "code": 1042})
    wait_until(lambda: machines()[1]["model"]["state"] == "alarm", timeout=5, what="mill alarm")
    events = json.loads(d.ctl("events", "--json", "--kind", "alarm_raised").stdout)
    assert [(e["source"], e["payload"]["alarm"]) for e in events] == [("mill", "1042")]
