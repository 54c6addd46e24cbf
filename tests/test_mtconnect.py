"""mtconnect: the read-only driver against the simulator's MTConnect agent (a real HTTP
server on loopback): the map checked against /probe, every observation in sequence order,
a restart of the agent and a client fallen out of its buffer recorded as gaps."""
from __future__ import annotations

import asyncio

import pytest
import structlog

from lathed.bus import Bus
from lathed.config import ConfigError, Section
from lathed.driver import DriverContext
from lathed.sim import mtconnect_agent
from lathed.sim.mtconnect_agent import MTConnectAgent
from lathed.supervisor import cancel_and_wait
from tests.test_modbus_cnc import until
from lathed_plugins.mtconnect import MTConnect

ITEMS = {"spindle_rpm": "Sspeed", "spindle_load_pct": "Sload", "program_state": "execution",
         "alarm_code": "system", "part_count": "part_count", "tool_number": "tool", "x_mm": "Xpos",
         "program_number": "program"}
REGS = {"spindle_rpm": 1500.0, "spindle_load_pct": 12.5, "program_state": 1, "alarm_code": 0, "part_count": 7,
        "tool_number": 1, "x_mm": 14.0, "program_number": 1000, "feed_mm_rev": 0.3, "spindle_override_pct": 100.0}


def driver(port: int, **kw) -> MTConnect:
    sec = Section("t.toml", "machine.m", {"url": f"http://127.0.0.1:{port}", "poll": "20ms",
                                          "items": ITEMS, **kw})
    d = MTConnect("m", sec)
    sec.check_unused()
    return d


async def _with_agent(check, **kw):
    agent = MTConnectAgent("127.0.0.1", 0)
    agent.update(REGS)
    await agent.start()
    d = driver(agent.port, **kw)
    events, seen = [], []
    bus = Bus()
    d.ctx = DriverContext(bus, structlog.get_logger(), lambda k, p=None: events.append((k, p)))
    bus.tap("m", seen.append)
    try:
        await check(agent, d, events, seen)
    finally:
        await d.close()
        await agent.stop()


async def _running(d):
    await d.connect()
    return asyncio.create_task(d.run())


def test_values_every_observation_and_the_machine_model():
    async def check(agent, d, events, seen):
        task = await _running(d)
        try:
            snap = d.model.snapshot()
            assert snap["spindle_rpm"]["value"] == 1500.0 and snap["program"]["value"] == 1000
            assert d.model.state() == "running" and snap["axes"]["x"]["value"] == 14.0
            # a load that rises and falls back between two polls is still seen
            n = len(seen)
            agent.update({"spindle_load_pct": 40.0})
            agent.update({"spindle_load_pct": 12.5})
            await until(lambda: [s.value for s in seen[n:] if s.quantity == "spindle_load_pct"] == [40.0, 12.5],
                        what="both loads")
            agent.update({"alarm_code": 77, "program_state": 2})
            await until(lambda: d.model.state() == "alarm", what="alarm")
            assert ("alarm_raised", {"kind": "lathe", "alarm": "77"}) in events
            agent.update({"part_count": 8})
            await until(lambda: any(k == "part_completed" for k, _ in events), what="part")
            assert d.status()["link"]["gaps"] == 0
            # a speed the agent does not observe again holds: live past stale_after (300 ms here)
            n = len(seen)
            await until(lambda: sum(s.quantity == "spindle_rpm" for s in seen[n:]) * d.poll > 2 * d.stale_after,
                        what="polls past stale_after")
            assert d.model.live("spindle_rpm") == 1500.0 and d.current("spindle_rpm") == 1500.0
        finally:
            await cancel_and_wait([task])
    asyncio.run(asyncio.wait_for(_with_agent(check, stale_after="300ms"), 30))


def test_an_agent_restart_and_a_buffer_overrun_are_recorded_gaps(monkeypatch):
    monkeypatch.setattr(mtconnect_agent, "BUFFER", 16)

    async def check(agent, d, events, seen):
        await d.connect()
        # the client falls behind by more than the agent buffers (it is not polling)
        for i in range(40):
            agent.update({"spindle_rpm": 1000.0 + i})
        task = asyncio.create_task(d.run())
        try:
            await until(lambda: d.gaps == 1, what="the overrun gap")
            gap = [p for k, p in events if k == "mtconnect_gap"][0]
            assert "left the agent's buffer" in gap["why"] and gap["machine"] == "m"
            await until(lambda: d.model.live("spindle_rpm") == 1039.0, what="the current value after the gap")
            # the agent restarts: a new instanceId; the driver starts over from /current
            agent.instance_id += 1
            agent.update({"spindle_rpm": 2000.0})
            await until(lambda: d.gaps == 2 and d.model.live("spindle_rpm") == 2000.0, what="restart gap")
            assert "the agent restarted" in [p for k, p in events if k == "mtconnect_gap"][1]["why"]
        finally:
            await cancel_and_wait([task])
    asyncio.run(asyncio.wait_for(_with_agent(check), 30))


def test_unavailable_is_not_a_value():
    async def check(agent, d, events, seen):
        task = await _running(d)
        try:
            agent._observe("Sload", "UNAVAILABLE")
            agent.update({"spindle_rpm": 1234.0})
            await until(lambda: d.model.live("spindle_rpm") == 1234.0, what="the next value")
            assert "spindle_load_pct" in d.unavailable
            n = len(seen)
            await until(lambda: len([s for s in seen[n:] if s.quantity == "spindle_rpm"]) > 2, what="polls")
            # the speed is carried on every poll; the unavailable load is not, and goes stale
            assert [s for s in seen[n:] if s.quantity == "spindle_load_pct"] == []
        finally:
            await cancel_and_wait([task])
    asyncio.run(asyncio.wait_for(_with_agent(check), 30))


@pytest.mark.parametrize("items, problem", [
    ({"spindle_rpm": "Sspeedd"}, "items.spindle_rpm = 'Sspeedd' is not a data item of the agent"),
    ({"spindle_rpm": "Sload"}, "items.spindle_rpm = 'Sload' is in PERCENT, not REVOLUTION/MINUTE"),
])
def test_a_map_the_device_does_not_have_is_refused_at_connect(items, problem):
    async def check(agent, d, events, seen):
        with pytest.raises(ConnectionError, match=problem.replace(".", r"\.").replace("(", r"\(")):
            await d.connect()
    asyncio.run(asyncio.wait_for(_with_agent(check, items=items), 30))


@pytest.mark.parametrize("data, problem", [
    ({"url": "10.0.0.1:8082", "items": ITEMS}, "is not an http:// or https:// address"),
    ({"url": "http://a", "items": {"spindle_rpm": "x", "x_mm": "x"}}, "item 'x' is already mapped"),
    ({"url": "http://a", "items": ITEMS, "poll": "5s", "stale_after": "2s"}, "must be longer than the poll"),
])
def test_config_errors_name_the_key(data, problem):
    with pytest.raises(ConfigError, match=problem):
        sec = Section("t.toml", "machine.m", data)
        MTConnect("m", sec)


def test_no_agent_is_a_clear_connection_error():
    from tests.conftest import free_port
    d = driver(free_port())

    async def go():
        try:
            await d.connect()
        finally:
            await d.close()
    with pytest.raises(ConnectionError, match="agent down or network"):
        asyncio.run(go())


def test_a_lathe_read_over_mtconnect_raises_chatter_alarms_and_flags_parts_live(tmp_path):
    """The daemon reading the simulated lathe through its MTConnect agent alone (no Modbus
    for this machine): the spindle speed, the load as the cut source, the part count; a 3 mm
    pass chatters, the alarm is raised and the part flagged. No command goes to it."""
    import json
    import re

    from tests.conftest import Daemon, free_port, sim_call, sim_config, wait_until
    from tests.conftest import default_table, events

    port = free_port()
    items = "".join(f'{k} = "{v}"\n' for k, v in ITEMS.items())
    # no cutting-feed signal over this agent: nor a dwell told from it
    chatter = re.sub(r"cut_from = \[[^]]*\]", 'cut_from = ["load", "vibration"]',
                     re.sub(r"^dwell_\w+ = .*\n", "", default_table("chatter"), flags=re.M)
                     .replace('machine = "lathe"', 'machine = "mt"'))
    records = "\n".join(line for line in default_table("records").replace('machine = "lathe"', 'machine = "mt"')
                        .splitlines() if not line.startswith(("thermal", "suppress")))
    cfg, paths = sim_config(tmp_path, extra=f'\n[machine.mt]\nplugin = "mtconnect"\nurl = "http://127.0.0.1:{port}"\n'
                                            f'[machine.mt.items]\n{items}',
                            analyzers=chatter + "\n\n" + records + "\n",
                            simulator=f'mtconnect_port = {port}\nprogram = ["2000,3.0,0.3,20"]\n'
                                      'load_s = 0.3\nretract_s = 0.2\n')
    d = Daemon(cfg, paths["socket"])
    try:
        d.wait_ready()
        alarms = wait_until(lambda: events(d, "chatter_alarm"), timeout=60, interval=0.2, what="a chatter alarm")
        p = alarms[0]["payload"]
        assert p["machine"] == "mt" and p["cut_seen_by"] in ("load", "vibration")
        # the load the agent reports reaches the analyzer: an alarm within a revolution or two of
        # the chip's entry may come before the agent's next observation of it (100 ms), a later one not
        wait_until(lambda: [a for a in events(d, "chatter_alarm") if a["payload"]["load_pct"] > 20], timeout=60,
                   interval=0.3, what="an alarm with the cut's spindle load read over MTConnect")
        assert p["tool_number"] == 1 and round(p["rpm"]) == 2000
        wait_until(lambda: sim_call(paths["sim"], "status")["part"] >= 3, timeout=60, interval=0.3,
                   what="three parts")
        parts = wait_until(lambda: [q for q in json.loads(d.ctl("parts", "--json").stdout)
                                    if q["machine"] == "mt" and q["outcome"] == "finished"],
                           timeout=10, what="a finished part on mt")
        assert all(q["abnormal"] and "chatter alarm" in q["reason"] and q["tools"] == "1" for q in parts), parts
        mt = d.item("machines", "mt")
        assert mt["state"] == "connected" and mt["link"]["transport"] == "mtconnect" and mt["link"]["gaps"] == 0
        assert mt["observations"] > 100 and mt["model"]["part_count"]["value"] >= 2
        assert re.search(r"^\s+mt\s+lathe\s+\d+ r/min\s+connected", d.ctl("status").stdout, re.M)
        assert events(d, "command_sent") == []
    finally:
        d.stop()


def test_the_agents_device_description_identifies_the_machine():
    """Issue 35 case 3: the device's Description in /probe is what the machine says it is; a
    machine configured as another is refused at connect, naming both."""
    from lathed.identity import NotTheMachine, judge

    async def check(agent, d, events, seen):
        await d.connect()
        said = await d.identify()
        assert said == {"manufacturer": "lathed simulator", "model": "MC4200-class lathe (simulated)",
                        "serial_number": "SIM-LATHE-0001"}
        assert judge("m", d.identification, said) is None
        with pytest.raises(NotTheMachine, match="the peer says its serial_number is 'SIM-LATHE-0001', not "
                                                "'SIM-LATHE-0002'"):
            judge("m", {"serial_number": "SIM-LATHE-0002"}, said)
    asyncio.run(_with_agent(check, identification={"serial_number": "SIM-LATHE-0001"}))
