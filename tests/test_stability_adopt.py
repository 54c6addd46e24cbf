"""The daemon side of the stability loop (issue 16): the cut record the
suppression analyzer leaves per cut, and the refit it adopts only when better,
keeps across a restart and falls back from when its file is damaged."""
from __future__ import annotations

import asyncio
import json
import time

import numpy as np
import pytest
import structlog

from lathed.analysis.cut_log import cut_rows
from lathed.analysis.speed_selection import LobeSelection, lobe_grid
from lathed.analysis.stability.cases import GIVEN, generate_cuts, true_dynamics
from lathed.analysis.stability import StabilityModel
from lathed.analyzer import AnalyzerContext
from lathed.bus import Bus, Sample
from lathed.config import Section
from lathed.store import Store
from lathed_plugins.suppression import SuppressionAnalyzer

MODES = [f"{m.fn_hz:g},{m.zeta:g},{m.k_n_per_m:g},{m.theta_deg:g}" for m in GIVEN.modes]


class Harness:
    """A suppression analyzer on a real store, its records and commands captured."""

    def __init__(self, tmp, **extra):
        self.store = Store(tmp / "state" / "lathed.db", machine_id="test")
        self.sent: list = []
        self.an = self.make(**extra)

    def make(self, **extra):
        data = {"chatter": "chatter", "machine": "lathe", "strategy": "lobes", "modes": MODES,
                "kf": GIVEN.kf, "tool": "T0101", "material": "C45", "settle_revs": 0.0,
                "accel_rpm_s": 1e6, "max_speed_ratio": 10.0, **extra}
        an = SuppressionAnalyzer("suppress", Section("t.toml", "analyzer.suppress", data))

        def record(kind, payload=None):
            self.store.record_future(kind, "suppress", payload).result()

        async def command(cmd):
            self.sent.append(cmd)
            return {"sent": True, "reason": None}
        an.ctx = AnalyzerContext(Bus(), structlog.get_logger("test"), record, command,
                                 lambda name, handler: None, self.store, lambda name: None, ".")
        return an

    def start(self, an=None):
        """What run() does before it reads the bus: the adopted model, the lobes' grid."""
        an = an or self.an
        an._load_adopted()
        an.grid = lobe_grid(an.lobes, an.limits)
        return an

    def events(self, kind):
        return [json.loads(r["payload"]) for r in
                self.store.query("SELECT payload FROM events WHERE kind = ? ORDER BY id", (kind,))]

    def add_cuts(self, cuts, **extra):
        """Cut records as the tracker writes them, one speed per cut (``extra``: more keys)."""
        for i in range(len(cuts)):
            ch = bool(cuts.chatter[i])
            f = float(cuts.chatter_frequency_hz[i])
            self.store.record_future("cut", "suppress", {
                "machine": "lathe", "tool": "T0101", "material": "C45", "depth_mm": float(cuts.depth_mm[i]),
                "depth_from": "register", "feed_mm_rev": 0.25, "outcome": "chatter" if ch else "stable",
                "speeds": [{"rpm": float(cuts.rpm[i]), "outcome": "chatter" if ch else "stable", "steady": True,
                            "chatter_frequency_hz": f if ch and np.isfinite(f) else None}], **extra}).result()


@pytest.fixture
def h(tmp_path):
    h = Harness(tmp_path)
    yield h
    h.store.close()


def cured_cut(h, index_growth: float | None = None) -> float:
    """A 1.3 mm pass at 2500 r/min, an alarm after 1 s, the lobes' move, 25 revolutions at the new
    speed without an alarm; ``index_growth``: the detector's judged index there, per window."""
    an = h.start()
    t0 = time.time()

    async def cut():
        await an._on_machine(Sample("lathe", "feed_mm_rev", 0.3, "mm/rev", t0))
        await an._on_machine(Sample("lathe", "spindle_rpm", 2500.0, "r/min", t0))
        # 1.3 mm: the lobes have speeds they call stable (at 2.2 they have none, and hold)
        await an._on_machine(Sample("lathe", "depth_of_cut_mm", 1.3, "mm", t0 + 0.01))
        await an._on_chatter(Sample("chatter", "cutting", 1.0, "", t0 + 0.01))   # the cut state's owner
        t = t0 + 0.01
        for _ in range(10):                      # 2500 r/min for 1 s: 41.7 revolutions
            t += 0.1
            await an._on_machine(Sample("lathe", "spindle_rpm", 2500.0, "r/min", t))
        await an._on_chatter(Sample("chatter", "chatter_frequency_hz", 655.0, "Hz", t))
        await an._on_chatter(Sample("chatter", "chatter_alarm", 1.0, "", t))
        assert len(h.sent) == 1                  # the lobes moved it
        target = h.sent[0].value
        t = max(t, time.time()) + 0.01
        for _ in range(int(25 * 60 / target / 0.1) + 1):     # 25 revolutions at the new speed, no alarm: cured
            t += 0.1
            await an._on_machine(Sample("lathe", "spindle_rpm", target, "r/min", t))
            if index_growth is not None:        # a window every 10 ms
                for k in range(10):
                    tk = t - 0.1 + 0.01 * (k + 1)
                    index = 0.2 * index_growth ** ((tk - t0) / 0.01)
                    await an._on_chatter(Sample("chatter", "chatter_index_judged", index, "", tk))
            await an._on_chatter(Sample("chatter", "chatter_alarm", 0.0, "", t))
        await an._on_machine(Sample("lathe", "depth_of_cut_mm", 0.0, "mm", t + 0.01))
        await an._on_chatter(Sample("chatter", "cutting", 0.0, "", t + 0.01))   # the cut state's owner
        return target
    return asyncio.run(cut())


def test_a_cut_leaves_one_record_with_each_speed_its_verdict_and_the_action(h):
    target = cured_cut(h)
    (rec,) = h.events("cut")
    assert rec["machine"] == "lathe" and (rec["tool"], rec["material"]) == ("T0101", "C45")
    assert rec["depth_mm"] == 1.3 and rec["depth_from"] == "register" and rec["feed_mm_rev"] == 0.3
    assert rec["outcome"] == "chatter" and rec["cured"] is True and rec["alarms"] == 1
    assert rec["ended"] == "cut ended"
    assert rec["chatter_frequency_hz"] == 655.0
    assert rec["first_alarm_rev"] == pytest.approx(41.7, abs=0.5)
    assert rec["rpm_start"] == 2500.0 and rec["rpm_end"] == pytest.approx(target, abs=0.1)
    s0, s1 = rec["speeds"]
    assert (s0["rpm"], s0["outcome"], s0["trigger"]) == (2500.0, "chatter", "entry")
    assert s1["rpm"] == pytest.approx(target, abs=0.1) and s1["outcome"] == "stable" and s1["trigger"] == "alarm"
    assert [a["rpm_after"] for a in rec["actions"]] == [target] and rec["actions"][0]["sent"] is True
    assert rec["model"] == "configured"
    # the store's view and the CSV rows the refit reads
    (row,) = h.store.query("SELECT outcome, depth_mm, actions, cured FROM cuts")
    assert row == {"outcome": "chatter", "depth_mm": 1.3, "actions": 1, "cured": 1}
    cuts, skipped = cut_rows([rec])
    assert list(cuts.rpm) == [2500.0, pytest.approx(target, abs=0.1)] and list(cuts.chatter) == [True, False]
    assert skipped == {}


def test_a_move_whose_judged_index_keeps_rising_is_not_recorded_cured(h):
    # the chatter analyzer's judged index reaches the cut record: a speed it was rising at all
    # through (chatter regrowing too slowly to alarm) is not called stable, nor the cut cured
    target = cured_cut(h, index_growth=1.02)
    (rec,) = h.events("cut")
    s1 = rec["speeds"][1]
    assert s1["rpm"] == pytest.approx(target, abs=0.1) and s1["first_alarm_s"] is None
    assert s1["outcome"] is None and s1["rising"] > 1.2 and rec["cured"] is False, s1


def test_a_cut_the_daemon_stops_in_is_recorded_up_to_the_stop(h):
    an = h.start()
    an._models_loaded = an._memory_loaded = True     # run() then reads the bus at once, no thread hop

    async def main():
        t = time.time()
        await an._on_machine(Sample("lathe", "spindle_rpm", 1500.0, "r/min", t))
        await an._on_machine(Sample("lathe", "depth_of_cut_mm", 1.2, "mm", t + 0.01))
        await an._on_chatter(Sample("chatter", "cutting", 1.0, "", t + 0.01))   # the cut state's owner
        for _ in range(10):                      # 25 revolutions at 1500 r/min, stable so far
            t += 0.1
            await an._on_machine(Sample("lathe", "spindle_rpm", 1500.0, "r/min", t))
        task = asyncio.create_task(an.run())
        for _ in range(1000):                    # until it reads the bus
            if an.ctx.bus._subs.get("lathe"):
                break
            await asyncio.sleep(0)
        assert an.ctx.bus._subs.get("lathe") and h.events("cut") == []
        task.cancel()                            # the daemon stops
        await asyncio.gather(task, return_exceptions=True)
    asyncio.run(main())
    (rec,) = h.events("cut")
    assert rec["ended"] == "daemon stopped" and rec["depth_mm"] == 1.2
    assert rec["revs"] == pytest.approx(25.0, abs=0.5) and rec["outcome"] == "stable"


def test_without_a_depth_the_cut_is_recorded_and_the_refit_says_it_left_it_out(h):
    an = h.start()

    async def cut():
        t = time.time()
        await an._on_machine(Sample("lathe", "feed_mm_rev", 0.3, "mm/rev", t))
        await an._on_chatter(Sample("chatter", "cutting", 1.0, "", t))
        for _ in range(20):
            t += 0.1
            await an._on_machine(Sample("lathe", "spindle_rpm", 2000.0, "r/min", t))
        await an._on_chatter(Sample("chatter", "cutting", 0.0, "", t))
    asyncio.run(cut())
    (rec,) = h.events("cut")
    assert rec["depth_mm"] is None and rec["depth_from"] is None and rec["outcome"] == "stable"
    cuts, skipped = cut_rows([rec])
    assert cuts is None and list(skipped.values()) == [1] and "no depth" in next(iter(skipped))


def test_without_a_depth_register_the_spindle_load_gives_the_cut_its_depth(h):
    """A real CNC reports the spindle load, not the depth: the record takes the deepest the load
    showed (Kt b feed D/2 = torque over the no-chip load), so the refit can use the cut."""
    an = h.start()
    published = an.ctx.bus.subscribe(an.name)            # the estimate, for the parts' records
    torque = 1.5e9 * 0.3e-3 * 2.0e-3 * 0.015             # kt, feed, 2 mm, D/2 (the defaults): 13.5 N m
    loaded = 5.0 + 100 * torque / 35.8                    # % of the peak torque over a 5 % no-chip load

    async def cut():
        t = time.time()
        await an._on_machine(Sample("lathe", "feed_mm_rev", 0.3, "mm/rev", t))
        await an._on_machine(Sample("lathe", "spindle_rpm", 2000.0, "r/min", t))
        await an._on_machine(Sample("lathe", "spindle_load_pct", 5.0, "%", t))     # turning, no chip
        await an._on_chatter(Sample("chatter", "cutting", 1.0, "", t))
        for load in [5.0 + 0.5 * (loaded - 5.0)] + [loaded] * 20 + [5.0 + 0.2 * (loaded - 5.0)]:
            t += 0.1                                      # the entry's ramp, the cut, the exit's fall
            await an._on_machine(Sample("lathe", "spindle_rpm", 2000.0, "r/min", t))
            await an._on_machine(Sample("lathe", "spindle_load_pct", load, "%", t))
        await an._on_chatter(Sample("chatter", "cutting", 0.0, "", t))
    asyncio.run(cut())
    (rec,) = h.events("cut")
    assert rec["depth_mm"] == pytest.approx(2.0, abs=1e-3) and rec["depth_from"] == "spindle load"
    est = [m.value for m in published._items if getattr(m, "quantity", None) == "depth_est_mm"]
    assert len(est) == 22 and max(est) == pytest.approx(2.0, abs=1e-3)   # every load reading in the cut
    cuts, skipped = cut_rows([rec])
    assert list(cuts.depth_mm) == [pytest.approx(2.0, abs=1e-3)] and skipped == {}


@pytest.mark.parametrize("x_axis", ["radius", "diameter"])
def test_the_x_axis_gives_the_spindle_load_its_lever_on_a_part_of_another_diameter(h, x_axis):
    """diameter_mm is one number; the parts are not: a 60 mm part cut 2 mm deep loads the
    spindle twice what the configured 30 mm would, and read with the configured diameter its
    depth is twice the true one.  With x_axis the X register (the tool tip: 28 mm radius, or
    56 mm as most lathe controls give X) sets the lever, R = x + b."""
    torque = 1.5e9 * 0.3e-3 * 2.0e-3 * 0.030            # kt, feed, 2 mm, R = 30 mm: 27 N m
    loaded = 5.0 + 100 * torque / 35.8

    async def cut(an):
        t = time.time()
        x = 28.0 if x_axis == "radius" else 56.0
        await an._on_machine(Sample("lathe", "feed_mm_rev", 0.3, "mm/rev", t))
        await an._on_machine(Sample("lathe", "spindle_rpm", 1000.0, "r/min", t))
        await an._on_machine(Sample("lathe", "spindle_load_pct", 5.0, "%", t))
        await an._on_chatter(Sample("chatter", "cutting", 1.0, "", t))
        for _ in range(5):
            t += 0.1
            await an._on_machine(Sample("lathe", "x_mm", x, "mm", t))
            await an._on_machine(Sample("lathe", "spindle_load_pct", loaded, "%", t))
        diameter.append(an._cut().diameter_m)        # the torque check's diameter, in the cut
        await an._on_chatter(Sample("chatter", "cutting", 0.0, "", t))
    diameter = []
    an = h.start(h.make(x_axis=x_axis))
    asyncio.run(cut(an))
    assert h.events("cut")[-1]["depth_mm"] == pytest.approx(2.0, abs=1e-3)
    assert diameter == [pytest.approx(0.060)]
    plain = h.start(h.make())                             # diameter_mm = 30: the lever halved
    asyncio.run(cut(plain))
    assert h.events("cut")[-1]["depth_mm"] == pytest.approx(4.0, abs=1e-3)


def refit(h, an=None, **args):
    return asyncio.run((an or h.an)._stability({"action": "refit", **args}))


def test_a_refit_that_adds_nothing_is_not_adopted_and_says_why(h):
    an = h.start()
    h.add_cuts(generate_cuts(true_dynamics("none"), 300, seed=3))
    grid = an.grid
    out = refit(h)
    assert out["adopt"] is False and out["effects"] == [] and "no effect added" in out["reason"]
    assert an.lobes is an.configured and an.grid is grid and an.model_name == "configured"
    assert not an.models_dir.exists()
    (ev,) = h.events("stability_refit_not_adopted")
    assert ev["reason"] == out["reason"] and ev["model"] == "configured"
    assert h.events("stability_model_adopted") == []


def test_a_better_refit_is_adopted_kept_over_a_restart_and_picks_the_speeds(h, tmp_path):
    an = h.start()
    true = true_dynamics("natural_frequency")
    h.add_cuts(generate_cuts(true, 300, seed=4))
    dry = refit(h, dry_run=True)
    assert dry["adopt"] is True and dry["dry_run"] is True
    assert an.model_name == "configured" and not an.models_dir.exists() and h.events("stability_model_adopted") == []
    out = refit(h)
    assert out["adopt"] is True and [e["effect"] for e in out["effects"]][:1] == ["natural_frequency"]
    assert out["after"]["accuracy"] > out["before"]["accuracy"]
    assert an.model_name == "lathe-v1.json" and (an.models_dir / "lathe-v1.json").is_file()
    (ev,) = h.events("stability_model_adopted")
    assert ev["file"] == "lathe-v1.json" and ev["model_before"] == "configured"
    assert ev["before"]["accuracy"] == out["before"]["accuracy"] and ev["after"]["accuracy"] == out["after"]["accuracy"]
    fn = ev["model"]["modes"][0]["fn_hz"]
    assert fn == pytest.approx(true.modes[0].fn_hz, rel=0.03)     # the shifted mode, found
    adopted = StabilityModel.from_json(ev["model"])
    # speed selection's proposal comes from the adopted lobes, not the configured ones
    depth = 1.3 * float(GIVEN.limit(np.geomspace(300, 6000, 2000))[0].min())
    an.depth_mm = depth * 1e3
    cut = an._cut()
    want = LobeSelection(adopted, cut, an.limits).select(4000.0, None)
    old = LobeSelection(an.configured, cut, an.limits).select(4000.0, None)
    pick = an._policy().strategy.select(4000.0, None)
    assert pick.rpm_after == pytest.approx(want.rpm_after) and want.rpm_after != pytest.approx(old.rpm_after)
    # a restart: the newest adopted model is loaded again
    again = h.start(h.make())
    assert again.model_name == "lathe-v1.json" and again.lobes.to_json() == adopted.to_json()


def test_a_damaged_model_file_falls_back_to_the_configured_model_with_an_event(h):
    an = h.start()
    h.add_cuts(generate_cuts(true_dynamics("natural_frequency"), 300, seed=4))
    assert refit(h)["adopt"] is True
    path = an.models_dir / "lathe-v1.json"
    path.write_text(path.read_text()[:100])       # a torn write, a disk fault
    again = h.start(h.make())
    assert again.model_name == "configured" and again.lobes is again.configured
    (ev,) = h.events("stability_model_unreadable")
    assert ev["file"] == "lathe-v1.json" and ev["using"] == "configured" and "not readable JSON" in ev["error"]


def test_a_new_tap_test_in_the_configuration_supersedes_the_adopted_model(h):
    h.start()
    h.add_cuts(generate_cuts(true_dynamics("natural_frequency"), 300, seed=4))
    assert refit(h)["adopt"] is True
    again = h.start(h.make(kf=2.2e9))
    assert again.model_name == "configured"
    (ev,) = h.events("stability_model_superseded")
    assert ev["file"] == "lathe-v1.json" and "base" in ev["why"]


def test_the_refit_takes_the_newest_cut_speeds_and_says_how_many_it_left(h, monkeypatch):
    import lathed_plugins.suppression as sup
    monkeypatch.setattr(sup, "MAX_REFIT_SPEEDS", 100)
    h.start()
    h.add_cuts(generate_cuts(true_dynamics("none"), 130, seed=3))
    out = refit(h, dry_run=True)
    assert out["cuts"] == 100 and out["left_out"] == {"older than the newest 100 cut speeds": 30}
