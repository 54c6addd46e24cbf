"""load_scaled: the index read at the cutting load the baseline was learned at, so a deeper
stable pass in the same cut (a shoulder) is not chatter, while a step into chatter still is.
The load comes as a CNC's polled spindle-load register does: every 100 ms, late."""
from __future__ import annotations

import numpy as np
import pytest
import structlog

from lathed.analysis.chatter.registry import make_detector
from lathed.analysis.regen import Segment, simulate_cut
from lathed.analyzer import AnalyzerContext
from lathed.bus import Block, Bus, Sample
from lathed.config import Section
from lathed_plugins.chatter import ChatterAnalyzer

POLL_S = 0.1
IDLE_PCT, PCT_PER_MM = 5.0, 20.0     # the spindle's no-chip load; the chip's per mm of depth


def _shoulder(seed):
    # 0.5 -> 1.3 mm at 1000 r/min (limit ~1.5 mm): stable throughout, one cut
    rec = simulate_cut([Segment(1.2, 1000, 0.5), Segment(1.2, 1000, 1.3)], seed=seed)
    assert rec.label == "stable"
    return rec


def _polled(rec, block=512, phase=0.037):
    """(samples, load % of the last poll or None, rpm) per block; the poll is not aligned
    with the depth step, so the load shows it up to 100 ms late."""
    next_poll = phase
    for i in range(0, len(rec.signal), block):
        load = None
        while i / rec.rate_hz >= next_poll:
            depth = float(rec.depth_mm[min(int(next_poll * rec.rate_hz), len(rec.signal) - 1)])
            load = IDLE_PCT + PCT_PER_MM * depth
            next_poll += POLL_S
        yield rec.signal[i:i + block], load, float(rec.rpm[i])


def _alarms(rec, **params):
    det = make_detector("sync_cusum", rec.rate_hz, **params)
    wins = []
    for x, load, rpm in _polled(rec):
        if load is not None:
            det.set_load(load - IDLE_PCT)
        wins += det.process(x, rpm)
    return [w for w in wins if w.alarm]


@pytest.mark.parametrize("seed", [1, 2])
def test_a_shoulder_is_read_at_its_own_load(seed):
    rec = _shoulder(seed)
    # the defect, without the load, the shape gate or the shoulder rule (test_detectors.py)
    assert _alarms(rec, shape_min=0, rise_ratio=0)
    assert not _alarms(rec, load_scaled=1)


def test_a_step_into_chatter_still_alarms():
    # 1 -> 3 mm at 1500 r/min chatters at once: the index grows far past the load's ratio
    rec = simulate_cut([Segment(0.6, 1500, 1.0), Segment(0.8, 1500, 3.0)], seed=21)
    first = _alarms(rec, load_scaled=1)[0].t_s
    assert 0.6 < first < 0.6 + 10 / 25.0             # within 10 revolutions of the step


def test_without_load_readings_load_scaled_changes_nothing():
    rec = simulate_cut([Segment(0.6, 1500, 1.0), Segment(0.8, 1500, 3.0)], seed=21)
    det_on = make_detector("sync_cusum", rec.rate_hz, load_scaled=1)
    det_off = make_detector("sync_cusum", rec.rate_hz)
    for i in range(0, len(rec.signal), 4096):
        a = det_on.process(rec.signal[i:i + 4096], 1500.0)
        b = det_off.process(rec.signal[i:i + 4096], 1500.0)
        assert [(w.index, w.alarm) for w in a] == [(w.index, w.alarm) for w in b]


def _analyzer(load_scaled):
    # the shoulder rule off: the load alone must carry the deeper pass (rise_ratio is the
    # detector's own answer to it, tested in test_detectors.py)
    an = ChatterAnalyzer("chatter", Section("t.toml", "analyzer.chatter", {
        "input": "accel", "machine": "lathe", "cut_from": ["load"],
        "params": {"load_scaled": load_scaled, "rise_ratio": 0}}))
    records = []
    an.ctx = AnalyzerContext(Bus(), structlog.get_logger("test"), lambda kind, payload=None: records.append(kind),
                             None, None, None, lambda name: None, ".")
    return an, records


@pytest.mark.parametrize("load_scaled, alarms", [(0, True), (1, False)])
def test_the_analyzer_passes_the_polled_spindle_load(load_scaled, alarms):
    rec = _shoulder(1)
    an, records = _analyzer(load_scaled)
    an._on_machine(Sample("lathe", "spindle_rpm", 1000.0, "r/min", 0.0))
    an._on_machine(Sample("lathe", "spindle_load_pct", IDLE_PCT, "%", 0.0))   # turning, no chip
    t = 0.0
    for k, (x, load, rpm) in enumerate(_polled(rec)):
        if load is not None:
            an._on_machine(Sample("lathe", "spindle_load_pct", load, "%", t))
        an._on_block(Block("accel", "acceleration", rec.rate_hz, t, k * len(x), x, rpm))
        t += len(x) / rec.rate_hz
    assert an.cutting
    assert ("chatter_alarm" in records) is alarms
