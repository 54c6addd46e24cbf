"""Thermal compensation holds its offset on stale readings and on a growth no spindle makes
(issue 35 case 1): the numeric core, and the analyzer asking nothing while it holds."""
from __future__ import annotations

import asyncio
import time
import types

import pytest
import structlog

from lathed.analysis.compensation_hold import CompensationHold


def hold():
    return CompensationHold(stale_after_s=20.0, growth_rate_max_um_s=1.0, step_s=1.0, tol_um=2.0)


def test_stale_readings_are_named_with_their_age():
    h = hold()
    assert h.stale({"motor": 100.0, "room": 95.0}, ["motor", "room"], 110.0) is None
    why = h.stale({"motor": 100.0, "room": 75.0}, ["motor", "room"], 110.0)
    assert why.startswith("temperature readings are stale (room 35 s old, more than 20 s)")


def test_a_growth_step_no_spindle_makes_is_held_until_the_prediction_comes_back():
    h = hold()
    assert h.judge(-0.13, 0.0) is None                  # the first is the reference
    assert h.judge(0.9, 1.0) is None                    # within tol + 1 µm/s x 1 s
    why = h.judge(-73.0, 2.0)                           # the probe's line: 73 µm in one step
    assert why.startswith("predicted growth moved -73.9 µm (from 0.9 to -73.0 µm)")
    # held against the last plausible value, however long: no credit accrues while held
    assert h.judge(-73.0, 60.0) is not None
    assert h.judge(-72.0, 61.0) is not None
    assert h.judge(1.5, 62.0) is None                   # back: acted on again
    # nor for a gap without readings: after 35 s away the step allowed is still one step's
    assert h.judge(8.0, 97.0) is not None
    h.reset()                                           # the operator touched off: taken as it is
    assert h.judge(8.0, 98.0) is None


def analyzer(monkeypatch, read_age_s: float, growth_um: float, ticks: int = 6):
    """The thermal analyzer for ``ticks`` steps (counted, not waited) with readings
    ``read_age_s`` old and a predicted growth of ``growth_um``; what it asked and recorded."""
    import lathed_plugins.thermal as thermal
    from lathed.analyzer import AnalyzerContext
    from lathed.bus import Bus
    from lathed.config import Section
    th = thermal.ThermalAnalyzer("thermal", Section("f.toml", "analyzer.thermal",
                                                    {"input": "temps", "machine": "lathe", "step": "1s"}))
    asked, records = [], []

    async def command(cmd):
        asked.append(cmd.value)
        return {"sent": True, "reason": None}
    th.ctx = AnalyzerContext(Bus(), structlog.get_logger("t"), lambda k, p=None: records.append((k, p)), command,
                             lambda *a: None, None, lambda n: None, ".")
    now = time.time()
    th.temps = {p: 30.0 for p in th._sensor_places()}
    th._read_at = {p: now - read_age_s for p in th._sensor_places()}
    th.touchoff, th.pred0, th.applied = {"base_um": 0.0, "t": now - 600, "reason": "t"}, 0.0, 0.0
    th.hold.judge(0.0, now - 1.0)           # the growth acted on a step ago: none
    th._predictor = types.SimpleNamespace(update=lambda *a: growth_um)
    n = []
    real_sleep = asyncio.sleep

    async def step(s):
        n.append(s)
        if len(n) > ticks:
            raise asyncio.CancelledError
        await real_sleep(0)
    monkeypatch.setattr(thermal.asyncio, "sleep", step)

    async def run():
        try:
            await th._tick()
        except asyncio.CancelledError:
            pass
    asyncio.run(run())
    return th, asked, records


def test_stale_readings_hold_the_offset_and_ask_nothing(monkeypatch):
    """Readings 35 s old: the analyzer phased 2 µm steps on to +60 µm. Now it asks nothing,
    and says so once."""
    th, asked, records = analyzer(monkeypatch, read_age_s=35.0, growth_um=-73.0)
    assert asked == []
    assert [k for k, _ in records] == ["thermal_held"] and "stale" in records[0][1]["why"]
    assert th.status()["held"].startswith("temperature readings are stale")


def test_an_impossible_growth_step_holds_the_offset(monkeypatch):
    th, asked, records = analyzer(monkeypatch, read_age_s=1.0, growth_um=-73.0)
    assert asked == []
    assert [k for k, _ in records] == ["thermal_held"] and "predicted growth moved" in records[0][1]["why"]


@pytest.mark.parametrize("growth_um", [2.5])
def test_a_plausible_growth_is_phased_in(monkeypatch, growth_um):
    th, asked, records = analyzer(monkeypatch, read_age_s=1.0, growth_um=growth_um)
    assert asked and th.held is None and records[0][0] == "compensation"
