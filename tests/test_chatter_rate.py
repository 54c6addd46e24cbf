"""A vibration stream at a rate the detector cannot window is counted and reported, never a crash loop."""
from __future__ import annotations

import numpy as np
import structlog

from lathed.analyzer import AnalyzerContext
from lathed.bus import Block, Bus, Sample
from lathed.config import Section
from lathed_plugins.chatter import ChatterAnalyzer


def _analyzer():
    an = ChatterAnalyzer("chatter", Section("t.toml", "analyzer.chatter",
                                            {"input": "accel", "machine": "lathe", "cut_from": ["depth"]}))
    records = []
    an.ctx = AnalyzerContext(Bus(), structlog.get_logger("test"), lambda kind, payload=None: records.append(kind),
                             None, None, None, lambda name: None, ".")
    return an, records


def test_a_stream_too_slow_for_the_window_is_counted_not_a_crash():
    an, records = _analyzer()
    an._on_machine(Sample("lathe", "depth_of_cut_mm", 1.0, "mm", 0.0))
    assert an.cutting
    for i in range(3):
        an._on_block(Block("accel", "acceleration", 50.0, float(i), 50 * i, np.ones(50), 3000.0))
    assert an.unusable_blocks == 3 and an.detector is None
    assert records == ["unusable_vibration_rate"]          # said once per rate, counted every time
    assert an.status()["unusable_blocks"] == 3
    # the stream comes back at a usable rate: detection goes on
    an._on_block(Block("accel", "acceleration", 10240.0, 3.0, 0, np.random.default_rng(1).normal(size=2048), 3000.0))
    assert an.detector is not None and an.blocks == 1
