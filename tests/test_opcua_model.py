"""lathed-opcua's address space built in this process from frames the tests write (no daemon),
served on loopback, and read back by the NodeSet-based type check (tests/nodeset_check.py).
The live server's check and node-opcua's reading are in tests/test_opcua.py."""
from __future__ import annotations

import asyncio
import gc
import time

import pytest
from asyncua import Client, Server, ua

from lathed.opcua import nodesets, spacecache
from lathed.opcua.machines import instance
from lathed.opcua.space import NAMESPACE, Space
from tests.conftest import ROOT, free_port
from tests.nodeset_check import Checker, Model, default_files

NODE_MODULES = ROOT / "tests" / "node" / "node_modules"


def model() -> Model:
    files = default_files(NODE_MODULES, ROOT / "lathed" / "opcua" / "nodesets")
    assert files[0].exists(), f"{files[0]} is missing: run bash tests/ensure_node_opcua.sh (make test does)"
    return Model(files)


async def served_space() -> tuple[Server, Space, str]:
    server = Server()
    ns = await spacecache.open_space(server, spacecache.default_dir())   # the run's cache (conftest)
    url = f"opc.tcp://127.0.0.1:{free_port()}"
    server.set_endpoint(url)
    space = Space(server, await server.register_namespace(NAMESPACE), nodesets.Types(server, ns))
    await space.build(writable=False)
    await server.start()
    return server, space, url


def frame(t: float) -> dict:
    return {"status": {"machines": [{"name": "lathe", "kind": "lathe", "state": "connected", "machine_state": "running",
                                     "identification": {"manufacturer": "M", "serial_number": "S1", "model": "X",
                                                        "year_of_construction": 2026}},
                                    {"name": "robot", "kind": "robot_arm", "state": "connected",
                                     "machine_state": "idle"}],
                       "sensors": [], "analyzers": [{"name": "chatter", "plugin": "chatter", "machine": "lathe"}]},
            "samples": {"lathe/spindle_rpm": [t, 1500.0, "r/min"], "lathe/spindle_override_pct": [t, 100.0, "%"],
                        "lathe/program_state": [t, 1, ""], "lathe/program_number": [t, 1000.0, ""],
                        "lathe/part_count": [t, 3, ""], "lathe/cycle_time_s": [t, 7.9, "s"],
                        "robot/j1_deg": [t, 10.0, ""]}}


@pytest.fixture(scope="module")
def served():
    """One in-process server for the module (building the models takes seconds), on its own loop."""
    loop = asyncio.new_event_loop()
    server, space, url = loop.run_until_complete(served_space())
    try:
        yield loop, server, space, url
    finally:
        loop.run_until_complete(server.stop())
        loop.close()
        gc.unfreeze()     # open_space froze what was alive (for a server process); a test worker goes on


def test_the_type_check_passes_and_finds_what_an_instance_lacks(served):
    loop, server, space, url = served

    async def go():
        await space.apply(frame(time.time()))
        assert space.failing == {}
        # a machine tool as the issue found it: no Equipment, ChannelState an Int32
        types = space.types
        bad = await instance(space.objects["Machines"], types.node(nodesets.MACHINE_TOOL_TYPE),
                             ua.NodeId("bad", space.idx), ua.QualifiedName("bad", space.idx))
        await server.delete_nodes([await bad.get_child(types.q(nodesets.MACHINE_TOOL, "Equipment"))], recursive=True)
        monitoring = await bad.get_child(types.q(nodesets.MACHINE_TOOL, "Monitoring"))
        channel = await instance(monitoring, types.node(nodesets.CHANNEL_MONITORING_TYPE),
                                 ua.NodeId("bad.Channel1", space.idx), ua.QualifiedName("Channel1", space.idx))
        state = await channel.get_child(types.q(nodesets.MACHINE_TOOL, "ChannelState"))
        await state.write_attribute(ua.AttributeIds.DataType, ua.DataValue(ua.Variant(ua.NodeId(ua.ObjectIds.Int32))))
        async with Client(url) as c:
            checker = Checker(model(), c)
            for m in await c.get_node(space.objects["Machines"].nodeid).get_children():
                await checker.check_instance(m, (await m.read_browse_name()).Name)
        return checker
    checker = loop.run_until_complete(go())
    assert checker.checked > 50
    mt = "http://opcfoundation.org/UA/MachineTool/"
    assert sorted(checker.errors) == sorted([
        f"bad: mandatory Equipment ({mt}) missing",
        f"bad/Monitoring/Channel1/ChannelState: DataType http://opcfoundation.org/UA/|i=6, declared {mt}|i=64"])


def test_a_value_that_cannot_be_shown_does_not_hold_back_the_rest_of_its_frame(served):
    loop, server, space, _ = served

    async def go():
        t = time.time()
        await space.apply({"status": {"machines": [{"name": "lathe", "kind": "lathe", "state": "connected"}],
                                      "sensors": [], "analyzers": [{"name": "chatter", "plugin": "chatter",
                                                                    "machine": "lathe"}]},
                           "samples": {"lathe/spindle_rpm": [t, 1500.0, "r/min"]}})
        space.last_event_id = 0
        await space.apply({"samples": {"chatter/chatter_frequency_hz": [t, None, "Hz"],   # no chatter: no frequency
                                       "lathe/spindle_rpm": [t, "not a number", "r/min"],
                                       "lathe/x_mm": [t, 3.0, "mm"]},
                           "events": [{"id": 5, "t": t, "source": "chatter", "kind": "chatter_alarm",
                                       "payload": {"machine": "lathe"}}]})

        def read(path: str) -> ua.DataValue:   # as stored (a client's read raises a bad status)
            return server.iserver.aspace.read_attribute_value(space.vars[path].node.nodeid,
                                                              ua.AttributeIds.Value)
        return (read("Machines/lathe/Monitoring/Axes/X"),
                read("Machines/lathe/Monitoring/Chatter/ChatterFrequency"),
                read("Machines/lathe/Monitoring/Spindle/RotationalSpeed").Value.Value, space.events_sent,
                space.failing)
    x, freq, speed, sent, failing = loop.run_until_complete(go())
    assert x.Value.Value == 3.0 and x.StatusCode.is_good()
    assert freq.Value.Value is None and freq.StatusCode.value == ua.StatusCodes.BadNoDataAvailable
    assert speed == 1500.0 and list(failing) == ["lathe/spindle_rpm"]   # said once (logged), the last good value kept
    assert sent == 1
