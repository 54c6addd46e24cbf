"""Suppression with no modal model (issue 41): model-free until a model
learned from its own cut records is trusted, then that model's lobes; kept
over a restart; a learn it cannot trust recorded with why."""
from __future__ import annotations

import asyncio
import json

import numpy as np
import pytest

from lathed.analysis.cuts import Cuts
from lathed.analysis.speed_selection import FrequencySelection, LobeSelection, RatedSpeed
from lathed.analysis.stability import StabilityModel
from lathed.analysis.stability.cases import generate_cuts
from lathed.analysis.stability.learn import MIN_CUTS
from lathed.control import RequestError
from lathed.sim.lathe import LATHE_KF, LATHE_MODES
from tests.test_stability_adopt import MODES, Harness

LATHE = StabilityModel(LATHE_MODES, LATHE_KF)


@pytest.fixture
def h(tmp_path):
    h = Harness(tmp_path, modes=[])
    yield h
    h.store.close()


def start(an, learn: bool = False):
    """What run() does before it reads the bus; ``learn``: and the learn that starts (if due) to its end."""
    async def go():
        an._load_adopted()
        await an.learned.start()
        if an.learned.task is not None:
            assert learn, "a learn started"
            await an.learned.task
    asyncio.run(go())
    return an


def learned_now(an) -> dict:
    return asyncio.run(an._stability({"action": "learn", "by": "test"}))


def test_with_no_modal_model_suppression_is_model_free_and_learns_only_once_it_has_the_cuts(h):
    an = start(h.an)
    assert an.learning and an.lobes is None and an.model_name == "none"
    an.rpm, an.depth_mm, an.depth_from = 2000.0, 3.0, "register"
    p = an._policy()
    assert isinstance(p.strategy, FrequencySelection) and isinstance(p.fallback, RatedSpeed)
    assert p.fallback.lobes is None and an.policy_model is None
    assert "no model yet: learns one from the cuts" in an.status()["summary"]
    h.add_cuts(generate_cuts(LATHE, MIN_CUTS - 5, given=LATHE, seed=1))
    start(an)
    st = an.stability_status()["learning"]
    assert st["cut_speeds"] == MIN_CUTS - 5 and st["next_learn_at"] == MIN_CUTS and st["running"] is False
    assert an.learned.task is None


@pytest.mark.timeout(300)     # a learn is seconds of one core; a loaded machine gives less
def test_a_trusted_learn_is_used_saved_and_kept_over_a_restart_and_a_tap_test_supersedes_it(h):
    h.add_cuts(generate_cuts(LATHE, 100, given=LATHE, seed=5))
    an = start(h.an, learn=True)             # due at start: 100 >= MIN_CUTS
    (ev,) = h.events("stability_model_learned")
    assert ev["file"] == an.model_name == "lathe-v1.json" and ev["model_before"] == "none" and ev["cuts"] == 100
    assert ev["learned"]["trusted"] and ev["learned"]["best_rpm"]
    doc = json.loads((an.models_dir / "lathe-v1.json").read_text())
    assert doc["base"] is None and doc["learned"]["cuts"] == 100 and doc["tool"] == "T0101"
    model = StabilityModel.from_json(doc["model"])
    assert model.modes[0].fn_hz == pytest.approx(190.0, rel=0.02)
    # the next cut's policy takes the learned lobes
    an.rpm, an.depth_mm, an.depth_from = 2000.0, 3.0, "register"
    p = an._policy()
    assert isinstance(p.strategy, LobeSelection) and an.policy_model == "lathe-v1.json"
    want = LobeSelection(model, an._cut(), p.strategy.limits).select(2000.0, None)
    assert p.strategy.select(2000.0, None).rpm_after == pytest.approx(want.rpm_after)
    assert an.stability_status()["learning"]["last"]["verdict"] == "adopted"
    # a restart uses it at once (and learns again from the records, which may replace it)
    again = h.make(modes=[])
    again._load_adopted()
    assert again.model_name == "lathe-v1.json" and again.lobes.to_json() == model.to_json()
    # a tap test configured since: the learned model is not its refit
    tapped = h.make(modes=MODES)
    tapped._load_adopted()
    assert tapped.model_name == "configured"
    (sup,) = h.events("stability_model_superseded")
    assert sup["file"] == "lathe-v1.json" and "base" in sup["why"]


@pytest.mark.timeout(300)     # a learn is seconds of one core; a loaded machine gives less
def test_a_learn_it_cannot_trust_is_recorded_with_why_and_suppression_stays_model_free(h, monkeypatch, capsys):
    rng = np.random.default_rng(5)
    n = 80
    chatter = rng.random(n) < 0.5
    h.add_cuts(Cuts.from_arrays(np.exp(rng.uniform(np.log(500), np.log(5000), n)), rng.uniform(1, 4, n), chatter,
                                np.where(chatter, rng.uniform(195, 215, n), np.nan)))
    an = h.an
    an._load_adopted()
    out = learned_now(an)
    assert out["verdict"] == "not trusted" and out["trusted"] is False and out["best_rpm"] == []
    assert out["cuts_needed"] > n and out["why_not"]
    assert an.lobes is None and an.model_name == "none" and not an.models_dir.exists()
    (ev,) = h.events("stability_learn_not_trusted")
    assert ev["why_not"] == out["why_not"] and ev["kept"] == "none" and ev["by"] == "test"
    assert h.events("stability_model_learned") == []
    # lathectl stability learn prints it (the reply as the control socket sends it: JSON)
    import lathed.cli.cuts as cli
    from lathed.cli.main import main
    reply = json.loads(json.dumps(out))
    monkeypatch.setattr(cli, "call", lambda *a, **k: reply)
    assert main(["stability", "learn", "--analyzer", "suppress"]) == 0
    text = capsys.readouterr().out
    assert f"\ncuts: {n} cut speeds from {n} cut record(s) of lathe\n" in "\n" + text
    assert "not trusted: suppression stays model-free (about" in text and "best speed" not in text


def test_learn_and_refit_each_refuse_the_analyzer_they_are_not_for(h, tmp_path):
    with pytest.raises(RequestError, match="lathectl stability learn"):
        asyncio.run(h.an._stability({"action": "refit"}))
    tapped = Harness(tmp_path / "t")
    try:
        with pytest.raises(RequestError, match="has a modal model configured"):
            asyncio.run(tapped.an._stability({"action": "learn"}))
    finally:
        tapped.store.close()
