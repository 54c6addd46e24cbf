"""can_robot: the DBC against an independent encoder (lathed.sim.can_peer),
python-can's virtual bus in-process, and slcan on a pseudo-terminal as the
simulator serves it."""
from __future__ import annotations

import asyncio
import os
import time

import can
import pytest
import structlog

from lathed.bus import Bus
from lathed.config import ConfigError, Section
from lathed.driver import DriverContext
from lathed.sim.can_peer import CanPeer, robot_frames
from lathed.sim.line import SimRobotArm
from lathed_plugins.can_robot import CanRobot, ReadAhead
from tests.conftest import ROOT

DBC = str(ROOT / "etc" / "robot_arm.dbc")


def robot(channel: str, interface: str = "virtual", **kw) -> tuple[CanRobot, list]:
    events = []
    d = CanRobot("robot", Section("t.toml", "machine.robot", {"interface": interface, "channel": channel,
                                                               "dbc": DBC, "timeout": "500ms", **kw}))
    d.ctx = DriverContext(Bus(), structlog.get_logger(), lambda k, p=None: events.append((k, p)))
    return d, events


def msgs(arm: SimRobotArm, counter: int) -> list[can.Message]:
    return [can.Message(arbitration_id=i, data=d, is_extended_id=False) for i, d in robot_frames(arm, counter)]


def test_dbc_decodes_what_the_simulated_arm_encodes():
    arm = SimRobotArm()
    arm.step(0.7)
    arm.cycle_count, arm.alarm_code = 1234, 0
    d, _ = robot("unused")
    d.model.link_up()
    assert d._handle(msgs(arm, 0)) == 4
    snap = d.model.snapshot()
    for k, v in enumerate(arm.joints, start=1):
        assert snap["axes"][f"j{k}"]["value"] == pytest.approx(v, abs=0.005)
    for axis, v in zip("xyz", arm.tool_mm()):
        assert snap["axes"][f"tool_{axis}"]["value"] == pytest.approx(v, abs=0.05)
    assert snap["part_count"]["value"] == 1234 and snap["program"]["value"] == 7
    assert snap["gripper"]["value"] == {0: "open", 1: "closed", 2: "moving"}[arm.gripper]
    assert snap["state"] == "running"


def test_counters_wraps_gaps_and_bad_frames():
    arm = SimRobotArm()
    d, events = robot("unused")
    d.model.link_up()
    arm.cycle_count = 65534
    d._handle(msgs(arm, 0))
    arm.cycle_count = 1                       # wrapped past 65535: three cycles, not a reset
    d._handle(msgs(arm, 3))                   # counters 1 and 2 never arrived
    arm.cycle_count = 2
    d._handle(msgs(arm, 4))
    assert d.model.snapshot()["cycle_time_s"] is None     # one full cycle not yet seen
    arm.cycle_count = 3
    d._handle(msgs(arm, 5))
    assert 0 <= d.model.snapshot()["cycle_time_s"]["value"] < 1
    parts = [p["part_count"] for k, p in events if k == "part_completed"]
    assert parts == [65535, 65536, 65537, 65538, 65539]
    assert d.counts["lost_frames"] == 4 * 2
    d._handle([can.Message(arbitration_id=0x103, data=b"\x01\x02", is_extended_id=False),
               can.Message(arbitration_id=0x555, data=b"", is_extended_id=False)])
    assert d.counts["malformed"] == 1 and d.counts["unknown_id"] == 1
    arm.alarm_code = 9
    d._handle(msgs(arm, 6))
    assert d.model.state() == "alarm" and ("alarm_raised", {"kind": "robot_arm", "alarm": "9"}) in events


def test_dbc_missing_signals_is_a_config_error(tmp_path):
    bad = tmp_path / "other.dbc"
    bad.write_text(open(DBC).read().replace("gripper", "grip"))
    with pytest.raises(ConfigError, match=r"\[machine.robot\] dbc: .* lacks signal\(s\) gripper"):
        CanRobot("robot", Section(str(tmp_path / "t.toml"), "machine.robot",
                                  {"interface": "virtual", "channel": "x", "dbc": "other.dbc"}))


@pytest.mark.parametrize("name, text, why", [
    # cantools goes by the extension: a .json gave "failed to start: ValueError: ... at .../cantools/..."
    ("robot.json", '{"a": 1}', "expected database format 'arxml', 'dbc', 'kcd', 'sym', 'cdd' or None, but got 'json'"),
    ("robot.dbc", "hello world\n", 'DBC: "Invalid syntax at line 1, column 1'),
])
def test_a_file_that_is_not_a_dbc_is_one_line_naming_it(tmp_path, name, text, why):
    (tmp_path / name).write_text(text)
    with pytest.raises(ConfigError) as e:
        CanRobot("robot", Section(str(tmp_path / "t.toml"), "machine.robot",
                                  {"interface": "virtual", "channel": "x", "dbc": name}))
    assert str(e.value).startswith(f"{tmp_path / 't.toml'}: [machine.robot] dbc: {tmp_path / name} is not a DBC "
                                   f"file ({why}"), str(e.value)
    assert "\n" not in str(e.value)


def test_two_messages_on_one_frame_id_are_refused(tmp_path):
    # cantools keeps the second (a warning on stderr): j1..j3 would never be decoded
    from pathlib import Path
    text = (Path(__file__).resolve().parents[1] / "etc" / "robot_arm.dbc").read_text()
    assert "BO_ 257 " in text
    (tmp_path / "dup.dbc").write_text(text.replace("BO_ 257 ", "BO_ 256 ", 1))
    with pytest.raises(ConfigError, match=r"\[machine.robot\] dbc: .*dup.dbc defines frame id 256 \(0x100\) twice"):
        CanRobot("robot", Section(str(tmp_path / "t.toml"), "machine.robot",
                                  {"interface": "virtual", "channel": "x", "dbc": "dup.dbc"}))


def test_virtual_bus_silent_then_back():
    channel = f"robot-test-{os.getpid()}"

    async def main():
        tx = can.Bus(interface="virtual", channel=channel)
        d, _ = robot(channel)
        arm, counter, silent = SimRobotArm(), 0, False

        async def controller():
            nonlocal counter
            while True:
                arm.step(0.02)
                if not silent:
                    for m in msgs(arm, counter):
                        tx.send(m)
                counter += 1
                await asyncio.sleep(0.02)
        c = asyncio.create_task(controller())
        try:
            await d.connect()
            run = asyncio.create_task(d.run())
            silent = True
            with pytest.raises(TimeoutError, match="robot silent on virtual"):
                await asyncio.wait_for(run, 3)
            await d.close()
            with pytest.raises(TimeoutError, match="no frames from the robot"):
                await d.connect()             # nobody on the bus: not connected
            await d.close()
            silent = False
            t0 = time.monotonic()
            await d.connect()
            assert time.monotonic() - t0 < 1 and d.model.state() == "running"
            await d.close()
        finally:
            c.cancel()
            tx.shutdown()
    asyncio.run(asyncio.wait_for(main(), 20))


def test_slcan_on_a_pty_as_the_simulator_serves_it(tmp_path):
    link = tmp_path / "ttyCAN"

    async def main():
        peer = CanPeer(link)
        peer.open()
        arm = SimRobotArm()
        d, _ = robot(str(link), interface="slcan")

        async def controller():
            while True:
                arm.step(0.05)
                peer.send_arm(arm)
                await asyncio.sleep(0.05)
        c = asyncio.create_task(controller())
        try:
            await d.connect()
            run = asyncio.create_task(d.run())
            os.write(peer.master, b"t10Z8ZZZZ\rgarbage\r")     # noise the adapter passes on
            end = time.monotonic() + 3
            while d.frames < 40:
                assert time.monotonic() < end, d.status()
                await asyncio.sleep(0.05)
            assert d.model.snapshot()["axes"]["j1"]["value"] == pytest.approx(arm.joints[0], abs=30)
            assert d.counts["malformed"] >= 1 and d.model.state() == "running"
            peer.close()                      # the adapter unplugged
            with pytest.raises(ConnectionError, match="adapter unplugged"):
                await asyncio.wait_for(run, 3)
        finally:
            c.cancel()
            await d.close()
            peer.close()
    asyncio.run(asyncio.wait_for(main(), 20))


def test_slcan_bytes_come_from_one_read_per_arrival():
    # python-can's slcan reader asks for one byte at a time: a select and a read each
    class Port:
        def __init__(self):
            self.arrivals, self.reads, self.write_timeout, self.resets = [], 0, None, 0

        @property
        def in_waiting(self):
            return len(self.arrivals[0]) if self.arrivals else 0

        def read(self, size=1):
            self.reads += 1
            if not self.arrivals:
                return b""                    # the port's timeout
            head = self.arrivals[0]
            out, rest = head[:size], head[size:]
            self.arrivals[0:1] = [rest] if rest else []
            return out

        def reset_input_buffer(self):
            self.resets += 1
            self.arrivals.clear()

    port = Port()
    ra = ReadAhead(port)
    port.arrivals = [b"t1018AABBCCDD00112233\r", b"t1021FF\r"]
    assert ra.in_waiting == 22
    got = []
    while (b := ra.read(1)):
        got.append(b)
    assert b"".join(got) == b"t1018AABBCCDD00112233\rt1021FF\r" and all(len(b) == 1 for b in got)
    assert port.reads == 3                     # one per arrival, and the timeout's empty one
    port.arrivals = [b"t1021FF\r"]
    assert ra.read(1) == b"t" and ra.in_waiting == 7
    ra.reset_input_buffer()
    assert ra.in_waiting == 0 and ra.read(1) == b"" and port.resets == 1
    ra.write_timeout = 0.5                     # python-can sets it on its port before a send
    assert port.write_timeout == 0.5 and ra.write_timeout == 0.5
