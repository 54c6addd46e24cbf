"""A turret holds tools the tap test did not measure: with ``tool_number`` set, a cut
with another tool (the machine's tool_number register) is not judged by the modal
model's lobes (no prediction at entry, no hold, model-free speed selection), and the
refit leaves its records out.  The lobes are the refit tests' GIVEN model: at 2.2 mm
every speed within 1.3 x 2500 r/min chatters (tests/test_suppression_hold.py)."""
from __future__ import annotations

import asyncio
import time

import pytest

from lathed.bus import Sample
from lathed.config import ConfigError
from lathed.control import RequestError
from lathed.analysis.stability.cases import generate_cuts, true_dynamics
from tests.test_suppression_hold import _cut, make  # noqa: F401  (make: the fixture)


def _with_tool(an, n, depth_mm, **kw):
    async def run():
        await an._on_machine(Sample("lathe", "tool_number", float(n), "", time.time()))
        await _cut(an, depth_mm, **kw)
    asyncio.run(run())


def test_another_turret_tool_is_not_held_by_the_models_lobes_but_moved_model_free(make):
    h = make(tool_number=1)
    _with_tool(h.an, 1, 2.2)                     # the modelled tool: every speed chatters, held
    assert h.sent == [] and len(h.events("suppression_advice")) == 1
    _with_tool(h.an, 2, 2.2, alarms=1)           # tool 2: the lobes are not its, so no advice
    assert len(h.events("suppression_advice")) == 1
    (act,) = h.events("suppression_action")
    assert act["strategy"] == "sss_frequency" and act["model"] is None and act["sent"] is True
    assert len(h.sent) == 1 and h.sent[0].value <= 1.3 * 2500.0
    first, second = h.events("cut")
    assert (first["tool_number"], first["model"]) == (1, "configured")
    assert (second["tool_number"], second["model"]) == (2, None)
    assert "tool 2 has no model: model-free" in h.an.status()["summary"]
    _with_tool(h.an, 1, 2.2)                     # back to the modelled tool: its lobes again
    assert len(h.events("suppression_advice")) == 2 and len(h.sent) == 1


def test_without_tool_number_the_model_is_every_tools(make):
    h = make()
    _with_tool(h.an, 2, 2.2)
    assert h.sent == [] and len(h.events("suppression_advice")) == 1
    assert h.events("cut")[0]["model"] == "configured"


def test_no_prediction_at_entry_for_another_tool(make):
    h = make(tool_number=1, avoid=True)
    _with_tool(h.an, 2, 2.2, alarms=0)
    assert h.sent == [] and h.events("suppression_advice") == [] and h.events("suppression_action") == []
    _with_tool(h.an, 1, 2.2, alarms=0)
    (a,) = h.events("suppression_advice")
    assert a["trigger"] == "predicted"


def test_the_refit_leaves_out_the_other_tools_cuts(make):
    h = make(tool_number=1)
    h.add_cuts(generate_cuts(true_dynamics("natural_frequency"), 60, seed=4), tool_number=2)
    with pytest.raises(RequestError, match=r"none usable \(left out: 60 cuts with another turret tool than 1\)"):
        asyncio.run(h.an._stability({"action": "refit"}))
    h.add_cuts(generate_cuts(true_dynamics("natural_frequency"), 300, seed=5), tool_number=1)
    out = asyncio.run(h.an._stability({"action": "refit", "dry_run": True}))
    assert out["left_out"]["cuts with another turret tool than 1"] == 60
    assert out["cuts"] <= 300 and out["setup"]["tool_number"] == 1


def test_tool_number_is_checked(make):
    with pytest.raises(ConfigError, match=r"tool_number.*-1 is out of range; allowed: an integer"):
        make(tool_number=-1)
    with pytest.raises(ConfigError, match=r"tool_number.*expected an integer"):
        make(tool_number="T1")


def test_a_model_refitted_for_one_turret_tool_is_not_loaded_for_another(make):
    h = make(tool_number=1)
    h.add_cuts(generate_cuts(true_dynamics("natural_frequency"), 300, seed=4), tool_number=1)
    out = asyncio.run(h.an._stability({"action": "refit"}))
    assert out["adopt"] is True and h.an.model_name == "lathe-v1.json"
    assert h.start(h.make(tool_number=1)).model_name == "lathe-v1.json"        # a restart keeps it
    again = h.start(h.make(tool_number=2))
    assert again.model_name == "configured"
    (ev,) = h.events("stability_model_superseded")
    assert "another tool_number than the configuration gives now" in ev["why"]


def test_a_tool_number_read_late_in_the_cut_gives_the_cut_its_tool(make):
    """The register is polled: after an index the cut can start before the new number is read.
    A turret indexes out of the cut, so the number seen in it is the whole cut's tool."""
    h = make(tool_number=1)
    _with_tool(h.an, 2, 0.5, alarms=0)           # the previous pass: tool 2

    async def late():
        t = time.time()
        await h.an._on_machine(Sample("lathe", "feed_mm_rev", 0.3, "mm/rev", t))
        await h.an._on_machine(Sample("lathe", "spindle_rpm", 2500.0, "r/min", t))
        await h.an._on_machine(Sample("lathe", "depth_of_cut_mm", 2.2, "mm", t))
        await h.an._on_chatter(Sample("chatter", "cutting", 1.0, "", t))
        await h.an._on_machine(Sample("lathe", "tool_number", 1.0, "", t + 0.05))   # read a poll late
        await h.an._on_chatter(Sample("chatter", "chatter_frequency_hz", 655.0, "Hz", t + 0.5))
        await h.an._on_chatter(Sample("chatter", "chatter_alarm", 1.0, "", t + 0.5))
        await h.an._on_machine(Sample("lathe", "depth_of_cut_mm", 0.0, "mm", t + 0.6))
        await h.an._on_chatter(Sample("chatter", "cutting", 0.0, "", t + 0.6))
    asyncio.run(late())
    last = h.events("cut")[-1]
    assert (last["tool_number"], last["model"]) == (1, "configured")
    # tool 1's lobes: no speed within reach is stable at 2.2 mm, so advice, not a model-free move
    assert h.sent == [] and len(h.events("suppression_advice")) == 1
