"""Chatter detection on a live accelerometer stream (numeric core: lathed.analysis.detectors).

    [analyzer.chatter]
    plugin = "chatter"
    input = "accel"            # the vibration sensor instance
    machine = "lathe"          # whose cut state (depth_of_cut_mm) and speed frame the analysis
    detector = "chaos_sync"    # any built-in or plugin detector
    tool = "T0101"             # recorded with every chatter event
    material = "C45"
    [analyzer.chatter.params]  # the detector's parameters (see lathed.analysis.detectors)
    threshold = 2.0

The detector runs only while the machine reports a depth of cut: it learns
its baseline at the start of each cut (air cutting would otherwise make the
entry look like chatter). For each analysis window it publishes, under its
own name, ``chatter_index``, ``chatter_threshold``, ``chatter_frequency_hz``
and then ``chatter_alarm`` (1/0); it records ``chatter_alarm`` and
``chatter_cleared`` events with the critical values.
"""
from __future__ import annotations

import math
import time

from lathed import hookimpl
from lathed.analysis.detectors import DEFAULT_DETECTOR, DETECTORS, make_detector
from lathed.analyzer import Analyzer
from lathed.bus import Block, Sample
from lathed.config import ConfigError, Section


class ChatterAnalyzer(Analyzer):
    def __init__(self, name: str, section: Section):
        super().__init__(name, section)
        self.input = section.getstr("input")
        self.machine = section.getstr("machine")
        self.detector_name = section.getstr("detector", DEFAULT_DETECTOR)
        self.tool = section.getstr("tool", "")
        self.material = section.getstr("material", "")
        psec = section.getsection("params", required=False)
        self.params = {k: psec.get(k) for k in psec.keys()}
        if self.detector_name in DETECTORS:   # plugin detectors are checked when they start
            try:
                make_detector(self.detector_name, 51200.0, **self.params)
            except ValueError as e:
                raise ConfigError(f"{section.file}: [{section.table}.params]: {e}") from None
        self.detector = None
        self.rate_hz: float | None = None
        self.cutting = False
        self.rpm: float | None = None
        self.depth_mm: float | None = None
        self.state = "idle"
        self.last = None
        self.alarms = 0
        self.windows = 0
        self.blocks = 0
        self.lag_ms: float | None = None
        self.alarm_started: float | None = None

    def inputs(self) -> list[str]:
        return [self.input, self.machine]

    def _new_detector(self, rate: float):
        extra = self.ctx.plugins.chatter_detectors() if getattr(self.ctx, "plugins", None) else None
        return make_detector(self.detector_name, rate, extra=extra, **self.params)

    async def run(self) -> None:
        sub = self.ctx.bus.subscribe(self.input, self.machine, maxsize=4096)
        try:
            while True:
                msg = await sub.get()
                if isinstance(msg, Sample):
                    self._on_machine(msg)
                elif isinstance(msg, Block) and self.cutting:
                    self._on_block(msg)
        finally:
            self.ctx.bus.unsubscribe(sub)

    def _on_machine(self, s: Sample) -> None:
        if s.source != self.machine:
            return
        if s.quantity == "spindle_rpm":
            self.rpm = s.value
        elif s.quantity == "depth_of_cut_mm":
            cutting = s.value > 0
            self.depth_mm = s.value if cutting else self.depth_mm
            if cutting and not self.cutting:
                if self.detector is not None:
                    self.detector.reset()     # a new cut: learn its baseline afresh
                self.state = "learning"
            elif self.cutting and not cutting:
                if self.detector is not None and self.detector.alarm:
                    self._cleared("cut ended")
                self.state = "idle"
            self.cutting = cutting

    def _on_block(self, b: Block) -> None:
        rpm = b.rpm if b.rpm else self.rpm
        if not rpm or rpm <= 0:
            return
        if self.detector is None or self.rate_hz != b.rate_hz:
            self.detector = self._new_detector(b.rate_hz)
            self.rate_hz = b.rate_hz
        self.blocks += 1
        was = self.detector.alarm
        windows = self.detector.process(b.data, rpm)
        now = time.time()
        self.lag_ms = 1000 * (now - (b.t0 + len(b.data) / b.rate_hz))
        for w in windows:
            self.windows += 1
            self.last = w
            t = b.t0 + len(b.data) / b.rate_hz
            pub = self.ctx.bus.publish
            if not math.isnan(w.index):
                pub(Sample(self.name, "chatter_index", w.index, "", t))
            pub(Sample(self.name, "chatter_threshold", w.threshold, "", t))
            if w.chatter_frequency_hz is not None:
                pub(Sample(self.name, "chatter_frequency_hz", w.chatter_frequency_hz, "Hz", t))
            pub(Sample(self.name, "chatter_alarm", 1.0 if w.alarm else 0.0, "", t))
            self.state = "learning" if w.learning else ("chatter" if w.alarm else "watching")
            if w.alarm and not was:
                self.alarms += 1
                self.alarm_started = t
                self.ctx.log.warning("chatter_alarm", index=round(w.index, 3), threshold=w.threshold,
                                     frequency_hz=w.chatter_frequency_hz, rpm=rpm)
                self.ctx.record("chatter_alarm", {
                    "machine": self.machine, "index": w.index, "threshold": w.threshold,
                    "chatter_frequency_hz": w.chatter_frequency_hz, "rpm": rpm, "depth_mm": self.depth_mm,
                    "tool": self.tool, "material": self.material, "detector": self.detector_name,
                    "sample_t": t})
            elif was and not w.alarm:
                self._cleared("index back under the threshold", w)
            was = w.alarm

    def _cleared(self, why: str, w=None) -> None:
        self.ctx.bus.publish(Sample(self.name, "chatter_alarm", 0.0, "", time.time()))
        self.ctx.record("chatter_cleared", {"machine": self.machine, "why": why,
                                            "index": None if w is None else w.index,
                                            "duration_s": None if self.alarm_started is None
                                            else round(time.time() - self.alarm_started, 3)})
        if w is None and self.detector is not None:
            self.detector.reset()

    def status(self) -> dict:
        w = self.last
        idx = None if w is None or math.isnan(w.index) else round(w.index, 3)
        return {"detector": self.detector_name, "cut_state": self.state, "index": idx,
                "threshold": None if w is None else w.threshold,
                "chatter_frequency_hz": None if w is None else w.chatter_frequency_hz,
                "alarms": self.alarms, "windows": self.windows,
                "lag_ms": None if self.lag_ms is None else round(self.lag_ms, 1),
                "summary": f"{self.state}" + (f", index {idx} / threshold {w.threshold:g}" if idx else "")
                           + f", {self.alarms} alarm(s)"}


@hookimpl
def lathed_analyzer_types():
    return {"chatter": ChatterAnalyzer}
