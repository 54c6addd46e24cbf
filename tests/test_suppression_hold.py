"""Suppression holds the speed when the cut's model has no stable speed within
reach: no command, a ``suppression_advice`` record naming the limit and the
cure, the cut record saying so (the lobes are the refit tests' GIVEN model:
its b_lim is 1.48-2.06 mm over 100-3250 r/min, so at 2.2 mm every speed within
1.3 x 2500 r/min chatters and at 1.3 mm none does)."""
from __future__ import annotations

import asyncio
import time

import pytest

from lathed.bus import Sample
from lathed.config import ConfigError
from lathed.control import RequestError
from tests.test_stability_adopt import Harness


@pytest.fixture
def make(tmp_path):
    made = []

    def make(**extra):
        h = Harness(tmp_path / str(len(made)), max_speed_ratio=1.3, **extra)
        h.start()
        made.append(h)
        return h
    yield make
    for h in made:
        h.store.close()


async def _cut(an, depth_mm, alarms=3, rpm=2500.0, register=True, leave=True, vibration_first=False):
    """A cut at ``depth_mm`` that chatters from entry: ``alarms`` alarm windows, then the exit."""
    t = time.time()
    await an._on_machine(Sample("lathe", "feed_mm_rev", 0.3, "mm/rev", t))
    await an._on_machine(Sample("lathe", "spindle_rpm", rpm, "r/min", t))
    # the cut is the chatter analyzer's cut state (the depth register among its sources where
    # cut_from names it); the register gives the depth
    if vibration_first:        # the chatter analyzer sees the chip before the depth register is read
        await an._on_chatter(Sample("chatter", "cutting", 1.0, "", t))
    if register:
        await an._on_machine(Sample("lathe", "depth_of_cut_mm", depth_mm, "mm", t))
    if not vibration_first:
        await an._on_chatter(Sample("chatter", "cutting", 1.0, "", t))
    await an._on_chatter(Sample("chatter", "chatter_frequency_hz", 655.0, "Hz", t))
    await an._on_chatter(Sample("chatter", "chatter_index", 3.5, "", t))
    await an._on_chatter(Sample("chatter", "chatter_threshold", 1.0, "", t))
    for _ in range(alarms):
        t += 0.5
        await an._on_machine(Sample("lathe", "spindle_rpm", rpm, "r/min", t))
        await an._on_chatter(Sample("chatter", "chatter_alarm", 1.0, "", t))
    if not leave:
        return
    if register:
        await an._on_machine(Sample("lathe", "depth_of_cut_mm", 0.0, "mm", t + 0.1))
    await an._on_chatter(Sample("chatter", "cutting", 0.0, "", t + 0.1))


def test_no_stable_speed_within_reach_holds_the_speed_and_advises(make):
    h = make()
    asyncio.run(_cut(h.an, 2.2))
    assert h.sent == []                              # no speed command at all
    assert h.events("suppression_action") == []
    (a,) = h.events("suppression_advice")            # once per cut, not per alarm window
    assert a["machine"] == "lathe" and a["trigger"] == "alarm" and a["model"] == "configured"
    assert a["rpm"] == 2500.0 and a["depth_mm"] == pytest.approx(2.2) and a["depth_from"] == "register"
    assert a["limit_mm"] == pytest.approx(float(h.an.lobes.b_lim_at(2500.0)[0][0]) * 1e3, rel=1e-3)
    assert a["limit_mm"] < a["best_limit_mm"] < 2.2
    assert a["safe_depth_mm"] == pytest.approx(h.an.predicted_unstable(2500.0, 2.2)[1] / 1.15)
    assert a["max_rpm"] <= 1.3 * 2500 and a["chatter_frequency_hz"] == 655.0 and a["chatter_index"] == 3.5
    assert a["advice"].startswith("no stable speed within ") and " at 2.20 mm: " in a["advice"]
    assert f"reduce the depth of cut below {a['safe_depth_mm']:.2f} mm" in a["advice"]
    (cut,) = h.events("cut")
    assert cut["advice"] == a["advice"] and cut["outcome"] == "chatter" and cut["cured"] is False
    st = h.an.status()
    assert st["advisories"] == 1 and st["last_advice"]["advice"] == a["advice"] and st["actions"] == 0
    assert st["last_was_advice"] is True
    assert "1 held with advice" in st["summary"] and st["when_no_stable_speed"] == "hold"
    # a shallower cut on the same lathe: the lobes have a stable speed, and it moves
    asyncio.run(_cut(h.an, 1.3, alarms=1))
    assert len(h.sent) == 1 and h.events("suppression_action")[0]["expected_stable"] is True
    assert len(h.events("suppression_advice")) == 1


def test_the_depth_register_read_after_the_cut_began_is_the_policys_depth(make):
    # the cut starts on the vibration's cut state, the register says 2.2 mm a poll later: the
    # policy judges at 2.2 mm (it judged at 0.01 mm, called every speed stable and moved)
    h = make()
    asyncio.run(_cut(h.an, 2.2, vibration_first=True))
    assert h.sent == [] and h.events("suppression_advice")[0]["depth_mm"] == pytest.approx(2.2)
    h = make(when_no_stable_speed="move")
    asyncio.run(_cut(h.an, 2.2, vibration_first=True, alarms=1))
    (act,) = h.events("suppression_action")
    assert act["expected_stable"] is False


def test_move_keeps_the_old_behaviour(make):
    h = make(when_no_stable_speed="move")
    asyncio.run(_cut(h.an, 2.2))
    assert h.sent and h.events("suppression_advice") == []
    assert h.events("suppression_action")[0]["expected_stable"] is False


def test_chatter_suppression_cannot_cure_is_said_once_with_the_reason(make):
    # the paper's rule with a rated speed above the speed cap (2500 x 1.3): nothing to send
    h = make(strategy="rated", rated_rpm=4000.0)
    asyncio.run(_cut(h.an, 2.2, alarms=4))
    assert h.sent == []
    (ex,) = h.events("suppression_exhausted")
    assert ex["rpm"] == 2500.0 and ex["changes"] == 0
    assert ex["reason"].startswith("no speed within 100-3250 r/min that the strategy or the rated speed would take")
    # held with advice: the advice is what it says, not this
    h = make()
    asyncio.run(_cut(h.an, 2.2, alarms=4))
    assert h.events("suppression_advice") and h.events("suppression_exhausted") == []


def test_a_speed_the_spindle_does_not_reach_is_said_once(make):
    """The control accepted the write but the spindle stays (an override or clamp on the
    control): suppression's later decisions assume the new speed, so the operator is told."""
    h = make(when_no_stable_speed="move")
    asyncio.run(_cut(h.an, 1.3, alarms=5))               # the harness's spindle never moves
    (nf,) = h.events("spindle_not_following")
    assert nf["sent_rpm"] == pytest.approx(h.sent[0].value, abs=0.1) and nf["rpm"] == 2500.0
    assert nf["after_s"] > 1.0
    # once said, the unreached speed is not asked for again: the lobes' next best, then the rule
    # (without the ban: the same speed at every alarm until the budget is spent)
    assert len({round(c.value) for c in h.sent}) == 3, [c.value for c in h.sent]
    h = make(when_no_stable_speed="move")

    async def follows():
        await _cut(h.an, 1.3, alarms=1, leave=False)
        await h.an._on_machine(Sample("lathe", "spindle_rpm", h.sent[0].value, "r/min", time.time() + 5))
    asyncio.run(follows())
    assert h.sent and h.events("spindle_not_following") == []


def test_a_cut_held_with_advice_that_gets_shallower_is_decided_afresh(make):
    """A profile's shallower part: at 1.3 mm the lobes have a stable speed within reach."""
    h = make()

    async def shallower(polls, via_load=False):
        await _cut(h.an, 2.2, alarms=2, leave=False)
        t = time.time()
        for k in range(polls):             # the register polled every 100 ms, chatter going on
            t += 0.1
            await h.an._on_machine(Sample("lathe", "depth_of_cut_mm", 1.3, "mm", t))
            await h.an._on_chatter(Sample("chatter", "cutting", 1.0, "", t))   # the cut state's owner
            await h.an._on_chatter(Sample("chatter", "chatter_alarm", 1.0, "", t))
        await h.an._on_machine(Sample("lathe", "depth_of_cut_mm", 0.0, "mm", t + 0.1))
        await h.an._on_chatter(Sample("chatter", "cutting", 0.0, "", t + 0.1))   # the cut state's owner
    asyncio.run(shallower(8))
    (adv,) = h.events("suppression_advice")
    (lifted,) = h.events("suppression_advice_lifted")
    assert lifted["advice_depth_mm"] == pytest.approx(2.2) and lifted["depth_mm"] == 1.3
    act = h.events("suppression_action")[0]         # (the harness's spindle never moves: re-sent)
    assert act["expected_stable"] is True and 1.3 < act["expected_b_lim_mm"] < 2.2    # stable at the new depth
    assert {c.value for c in h.sent} == {act["rpm_after"]}
    # the tool's exit: shallower for a poll or two, then out of the cut; no move
    h = make()
    asyncio.run(shallower(3))
    assert h.events("suppression_advice_lifted") == [] and h.sent == []


def test_manual_mode_records_the_advice_and_suppress_now_says_the_speed_is_held(make):
    h = make(mode="manual")

    async def run():
        await _cut(h.an, 2.2, alarms=1, leave=False)      # still cutting, still chattering
        (a,) = h.events("suppression_advice")
        assert a["mode"] == "manual" and h.an.pending is None and h.events("suppression_proposed") == []
        with pytest.raises(RequestError, match="speed held: no stable speed within"):
            await h.an._control({"action": "now"})
    asyncio.run(run())
    assert h.sent == []


def test_predicted_at_cut_entry_holds_too(make):
    h = make(avoid=True)
    asyncio.run(_cut(h.an, 2.2, alarms=0))
    (a,) = h.events("suppression_advice")
    assert a["trigger"] == "predicted" and h.sent == []


def test_without_a_depth_it_cannot_know_no_speed_is_stable_and_moves(make):
    h = make()
    asyncio.run(_cut(h.an, None, register=False))
    assert h.sent and h.events("suppression_advice") == []
    # the programmed depth is a depth: with it the lobes can say, and hold
    h2 = make(depth_mm=2.2)
    asyncio.run(_cut(h2.an, None, register=False))
    assert h2.sent == [] and h2.events("suppression_advice")[0]["depth_from"] == "program"


def test_when_no_stable_speed_is_checked(make):
    with pytest.raises(ConfigError, match=r"when_no_stable_speed.*'stay' is not allowed; allowed: hold, move"):
        make(when_no_stable_speed="stay")


def test_a_speed_variation_that_would_swing_past_the_speed_cap_is_a_config_error(make):
    with pytest.raises(ConfigError, match=r"^t.toml: \[analyzer.suppress\] ssv_amplitude: 0.4 swings the speed "
                       r"above max_speed_ratio = 1.3 x the programmed speed$"):
        make(strategy="variation", ssv_amplitude=0.4)
    make(strategy="variation", ssv_amplitude=0.3)


def test_a_base_speed_above_the_top_speed_is_refused_and_constant_torque_is_base_equal_max(make):
    # was taken: the torque is flat to base_rpm, so above max_rpm the number only inflated the power
    # no speed in reach uses (or was max and base swapped)
    with pytest.raises(ConfigError, match=r"^t.toml: \[analyzer.suppress\] base_rpm: 8000 r/min is above max_rpm "
                       r"6000 r/min; a spindle with its peak torque over its whole range \(constant torque\) "
                       r"has base_rpm = max_rpm$"):
        make(base_rpm=8000.0)
    with pytest.raises(ConfigError, match=r"^t.toml: \[analyzer.suppress\] min_rpm: 6000 r/min is not below "
                       r"max_rpm 6000 r/min$"):
        make(min_rpm=6000.0)
    h = make(base_rpm=6000.0)
    assert h.an.limits.torque_available(6000.0) == pytest.approx(h.an.limits.peak_torque_nm)
    # a slow spindle's max_rpm alone: the base speed's default is at most it, not an error
    assert make(max_rpm=1200.0).an.limits.base_rpm == 1200.0


# -- in the running daemon -----------------------------------------------------------------

def test_the_running_daemon_holds_and_shows_the_advice(tmp_path):
    """4.5 mm at 1000 r/min on the simulated lathe (whose dynamics are the configured model's):
    its limit is 2.4 mm there and at most 4.1 mm anywhere in 100-1300 r/min (750, the rated
    speed, included), so every cut chatters and suppression holds."""
    import json

    from tests.conftest import DEPTH_REGISTER, Daemon, sim_config, wait_until
    from tests.test_suppression_live import ANALYZERS, events, spindle_commands
    cfg, paths = sim_config(tmp_path, analyzers=ANALYZERS, registers=DEPTH_REGISTER,
                            simulator='program = ["1000,4.5,0.3,24"]\nload_s = 0.3\nretract_s = 0.2\n')
    d = Daemon(cfg, paths["socket"])
    try:
        d.wait_ready()
        a = wait_until(lambda: events(d, "suppression_advice"), timeout=90, interval=0.5,
                       what="suppression_advice")[0]
        p = a["payload"]
        assert a["source"] == "suppress" and p["machine"] == "lathe" and p["trigger"] == "alarm"
        assert p["depth_mm"] == pytest.approx(4.5) and p["depth_from"] == "register" and p["model"] == "configured"
        assert p["rpm"] == pytest.approx(1000, rel=0.02) and p["best_limit_mm"] < 4.5 and p["max_rpm"] <= 1300
        # (the reach is 1.3 x the speed the cut began at, which may still be ramping up to 1000)
        assert p["advice"].startswith(f"no stable speed within 100-{p['max_rpm']:.0f} r/min at 4.50 mm: ")
        # the speed stays: no command, no action
        assert spindle_commands(d) == [] and events(d, "suppression_action") == []
        text = d.ctl("suppress", "status").stdout
        assert "held with advice; last: no stable speed within" in text, text
        assert "held with advice" in d.ctl("status").stdout
        assert "suppression_advice" in d.ctl("events", "--kind", "suppression_advice").stdout
        rows = wait_until(lambda: [c for c in json.loads(d.ctl("cuts", "--json").stdout) if c["advice"]],
                          timeout=60, interval=0.5, what="a held cut's record")
        assert rows[0]["outcome"] == "chatter" and rows[0]["cured"] is False and rows[0]["actions"] == []
        assert "speed held: no stable speed within reach" in d.ctl("cuts").stdout
    finally:
        d.stop()


def test_the_cut_is_the_chatter_analyzers_cut_state_not_the_depth_register(make):
    """One owner of the cut (the chatter analyzer's, lathed.analysis.cut.state): the depth
    register alone, which suppression read as a cut of its own before, gives the depth, not a cut."""
    h = make()

    async def register_only():
        t = time.time()
        await h.an._on_machine(Sample("lathe", "spindle_rpm", 2500.0, "r/min", t))
        await h.an._on_machine(Sample("lathe", "depth_of_cut_mm", 2.2, "mm", t))
        assert not h.an.in_cut and h.an.depth_mm == 2.2
        await h.an._on_machine(Sample("lathe", "depth_of_cut_mm", 0.0, "mm", t + 0.5))
    asyncio.run(register_only())
    assert h.events("cut") == [] and h.events("suppression_advice") == []
    asyncio.run(_cut(h.an, 2.2))                 # with the cut state: a cut, held with advice
    assert len(h.events("cut")) == 1 and len(h.events("suppression_advice")) == 1


async def _alarm_at(an, rpm: float, t: float) -> None:
    """One alarm window, as the chatter analyzer publishes it: the speed it was judged at first."""
    await an._on_chatter(Sample("chatter", "chatter_rpm", rpm, "r/min", t))
    await an._on_chatter(Sample("chatter", "chatter_alarm", 1.0, "", t))


@pytest.mark.parametrize("mode", ["auto", "manual"])
def test_an_alarm_judged_at_another_speed_than_the_machine_reads_moves_nothing(make, mode):
    # a stalled poll: the machine's last reading says 2000 r/min while the spindle (and the alarm's
    # stream) run 2500; a cure computed from 2000 is a speed nobody chose for a 2500 r/min cut
    h = make(mode=mode)

    async def run():
        an, t = h.an, time.time()
        await an._on_machine(Sample("lathe", "feed_mm_rev", 0.3, "mm/rev", t))
        await an._on_machine(Sample("lathe", "spindle_rpm", 2000.0, "r/min", t))
        await an._on_machine(Sample("lathe", "depth_of_cut_mm", 1.3, "mm", t))
        await an._on_chatter(Sample("chatter", "cutting", 1.0, "", t))
        await an._on_chatter(Sample("chatter", "chatter_frequency_hz", 655.0, "Hz", t))
        for i in range(3):
            await _alarm_at(an, 2500.0, t + 0.5 * i)
        assert h.sent == [] and an.pending is None and h.events("suppression_proposed") == []
        (held,) = h.events("suppression_held")            # once for the cut, not per window
        assert held["rpm"] == 2000.0 and held["alarm_rpm"] == 2500.0
        assert "judged at 2500 r/min" in held["reason"] and "reading is 2000 r/min" in held["reason"]
        if mode == "manual":
            with pytest.raises(RequestError, match="speed held: the alarm was judged at 2500 r/min"):
                await an._control({"action": "now"})
        # the poll catches up: the cure is computed from the speed the spindle runs
        await an._on_machine(Sample("lathe", "spindle_rpm", 2500.0, "r/min", t + 2))
        await _alarm_at(an, 2500.0, t + 2)
        if mode == "manual":
            await an._control({"action": "now"})
        (act,) = h.events("suppression_action")
        assert act["rpm_before"] == 2500.0 and len(h.sent) == 1
    asyncio.run(run())
