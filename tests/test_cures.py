"""Remembered cures (lathed.analysis.cures and suppression's remember = true): a pass that
chattered at the speed it entered at and was cured at another gets the cure at its next entry."""
from __future__ import annotations

import asyncio
import time

import pytest

from lathed.analysis.cures import CureMemory
from lathed.bus import Sample
from tests.test_stability_adopt import Harness


def rec(speeds, rpm_start=2500.0, depth=3.0, tool="T0101", actions=()):
    return {"tool": tool, "material": "C45", "rpm_start": rpm_start, "depth_mm": depth, "end_t": 100.0,
            "actions": list(actions),
            "speeds": [{"rpm": r, "outcome": o, "trigger": t} for r, o, t in speeds]}


CURED = [(2500.0, "chatter", "entry"), (2292.0, "stable", "alarm")]


def test_a_cure_is_learned_found_for_the_same_pass_and_dropped_when_it_chatters_anyway():
    m = CureMemory("T0101", "C45")
    assert m.learn(rec([(2500.0, "stable", "entry")])) is None              # nothing to cure
    assert m.learn(rec([(2500.0, "chatter", "entry")])) is None             # chattered, not cured
    assert m.learn(rec(CURED, tool="T0202")) is None                        # another tool's
    assert m.learn(rec(CURED)) == "learned"
    assert m.find(2510.0, 3.0).rpm == 2292.0                                # within 2 % of the speed
    assert m.find(2500.0, 2.8).rpm == 2292.0                                # about as deep
    assert m.find(2500.0, 1.0) is None                                      # shallower: may be stable
    assert m.find(2600.0, 3.0) is None and m.find(2500.0, None) is None     # another speed; depth unknown
    # a pass given the cure at entry (its entry stretch too short to judge) that chatters there
    # anyway, and is cured at a third speed: that one is remembered instead
    given = [(None, None, "entry"), (2292.0, "chatter", "remembered"), (1950.0, "stable", "alarm")]
    assert m.learn(rec(given, rpm_start=None, actions=[{"rpm_before": 2500.0}])) == "learned"
    assert [(c.rpm_entry, c.rpm) for c in m.cures] == [(2500.0, 1950.0)]
    # ... and one that is not cured at all drops it
    failed = [(None, None, "entry"), (1950.0, "chatter", "remembered")]
    assert m.learn(rec(failed, rpm_start=None, actions=[{"rpm_before": 2500.0}])) == "forgotten"
    assert m.cures == [] and m.find(2500.0, 3.0) is None


def cut(h, an, depth, rpm=2500.0, alarm=False):
    """One pass through the Harness's analyzer, depth register: returns the commands it sent."""
    sent0 = len(h.sent)

    async def go():
        t = time.time()
        await an._on_machine(Sample("lathe", "feed_mm_rev", 0.3, "mm/rev", t))
        await an._on_machine(Sample("lathe", "spindle_rpm", rpm, "r/min", t))
        await an._on_machine(Sample("lathe", "depth_of_cut_mm", depth, "mm", t + 0.01))
        await an._on_chatter(Sample("chatter", "cutting", 1.0, "", t + 0.01))   # the cut state's owner
        speed = h.sent[-1].value if len(h.sent) > sent0 else rpm
        t += 0.01
        for _ in range(10):
            t += 0.1
            await an._on_machine(Sample("lathe", "spindle_rpm", speed, "r/min", t))
        if alarm:
            await an._on_chatter(Sample("chatter", "chatter_frequency_hz", 655.0, "Hz", t))
            await an._on_chatter(Sample("chatter", "chatter_alarm", 1.0, "", t))
            speed = h.sent[-1].value
        t = max(t, time.time()) + 0.01
        for _ in range(int(25 * 60 / speed / 0.1) + 1):        # 25 revolutions, no alarm: stable
            t += 0.1
            await an._on_machine(Sample("lathe", "spindle_rpm", speed, "r/min", t))
            await an._on_chatter(Sample("chatter", "chatter_alarm", 0.0, "", t))
        await an._on_machine(Sample("lathe", "depth_of_cut_mm", 0.0, "mm", t + 0.01))
        await an._on_chatter(Sample("chatter", "cutting", 0.0, "", t + 0.01))
    asyncio.run(go())
    return h.sent[sent0:]


@pytest.fixture
def h(tmp_path):
    h = Harness(tmp_path, remember=True)
    yield h
    h.store.close()


def test_the_next_pass_gets_the_cure_at_entry_and_a_restart_keeps_it_until_forgotten(h):
    an = h.start()
    (cured,) = cut(h, an, 1.3, alarm=True)                     # detection, then the lobes' move
    assert an.memory.find(2500.0, 1.3).rpm == cured.value
    (given,) = cut(h, an, 1.3)                                 # the same pass: moved at entry, no alarm
    assert given.value == cured.value
    act = h.events("suppression_action")[-1]
    assert act["trigger"] == "remembered" and act["sent"] and act["chatter_index"] is None
    assert "remembered: a pass entering at 2500 r/min, 1.3 mm deep," in act["reason"]
    assert h.events("cut")[-1]["speeds"][1]["trigger"] == "remembered"
    assert cut(h, an, 0.5) == []                               # a shallower pass: not the same evidence
    assert an.status()["cures"] == [{"rpm_entry": 2500.0, "rpm": round(cured.value, 3), "depth_mm": 1.3,
                                     "t": pytest.approx(h.events("cut")[-1]["end_t"], abs=60),
                                     "tool_number": None}]
    # a restart rebuilds the memory from the store's cut records
    an2 = h.start(h.make(remember=True))
    asyncio.run(asyncio.to_thread(an2._load_memory))
    assert [(c.rpm_entry, c.rpm) for c in an2.memory.cures] == [(2500.0, round(cured.value, 1))]
    # forgotten (a new tool): recorded, so the next restart does not bring it back
    st = asyncio.run(an2._control({"action": "forget", "by": "test"}))
    assert st["cures"] == [] and h.events("suppression_cures_forgotten")[-1]["cures"] == 1
    an3 = h.start(h.make(remember=True))
    an3._load_memory()
    assert an3.memory.cures == [] and cut(h, an3, 1.3) == []


def test_a_cure_is_the_tool_number_s_where_the_machine_reports_one(h):
    """A turret holds several tools: a cure learned with tool 1 is not tool 2's, and a cure
    learned before the machine reported its tool is no tool's."""
    an = h.start()

    async def tool(n):
        await an._on_machine(Sample("lathe", "tool_number", float(n), "", time.time()))
    asyncio.run(tool(1))
    (cured,) = cut(h, an, 1.3, alarm=True)
    assert h.events("cut")[-1]["tool_number"] == 1
    asyncio.run(tool(2))
    assert cut(h, an, 1.3) == []                               # another tool: nothing given
    asyncio.run(tool(1))
    (given,) = cut(h, an, 1.3)
    assert given.value == cured.value
    m = CureMemory("T0101", "C45")
    m.learn(rec(CURED))                                        # an older record: no tool number
    assert m.find(2500.0, 3.0, 1) is None and m.find(2500.0, 3.0).rpm == 2292.0


def test_without_remember_nothing_is_given(tmp_path):
    h = Harness(tmp_path, remember=False)
    try:
        an = h.start()
        assert len(cut(h, an, 1.3, alarm=True)) == 1
        assert cut(h, an, 1.3) == [] and an.status()["remember"] is False
    finally:
        h.store.close()
