"""Chatter detection on a live accelerometer stream (numeric core: lathed.analysis.chatter).

The detector runs only while the tool is in the cut (the cut state's sources:
lathed.analysis.cut) and learns its baseline at the start of each cut; per window it
publishes chatter_index, chatter_threshold, chatter_frequency_hz, chatter_rpm (the speed an
alarm was judged at) and chatter_alarm, and records chatter_alarm / chatter_cleared events. Keys, the cut's sources, dwells and what a
reload takes: docs/chatter.md and docs/configuration.md ([analyzer.chatter]).
"""
from __future__ import annotations

import asyncio
import math
import time

from lathed import hookimpl
from lathed.analysis.cut.sources import SOURCES
from lathed.analysis.cut.state import CutEvent, CutState
from lathed.analysis.chatter.registry import DEFAULT_DETECTOR, DETECTORS, make_detector
from lathed.analysis.chatter.windows import JudgedIndex
from lathed.analyzer import Analyzer
from lathed.bus import Block, Sample
from lathed.config import ConfigError, Section
from lathed.display import packed, thin
from lathed.sight import CHECK_EVERY_S, Sight

EYE_POINTS = 600   # chaos-eye points sent to a screen
EYE_MIN_S = 0.5    # a display eye (detectors other than chaos_sync) is drawn at most this often


# A speed change this early in a cut, before any alarm, restarts the baseline.
ENTRY_REVS = 20.0


# detector parameters a running cut takes at once on reload; the others (window
# lengths, band) shape the windows and apply from the next cut
LIVE_NOW = ("threshold", "on_windows", "off_windows", "off_ratio", "settle_revs", "jump_ratio")


class ChatterAnalyzer(Analyzer):
    LIVE_KEYS = {"params"}     # a configuration reload (SIGHUP) may change these

    def __init__(self, name: str, section: Section):
        super().__init__(name, section)
        self.input = section.getstr("input")
        self.machine = section.getstr("machine")
        self.detector_name = section.getstr("detector", DEFAULT_DETECTOR)
        self.tool = section.getstr("tool", "")
        self.material = section.getstr("material", "")
        self.cut_from = section.getlist("cut_from", ["load", "vibration"])
        bad = [c for c in self.cut_from if c not in SOURCES]
        if bad or not self.cut_from:
            raise section.error("cut_from", f"expected a non-empty list of {', '.join(SOURCES)}; "
                                            f"got {self.cut_from!r}")
        self.dwell_axes = section.getlist("dwell_axes", [])
        if self.dwell_axes and "feed" not in self.cut_from:
            raise section.error("dwell_axes", 'a dwell is told from the cutting-feed signal: needs "feed" in '
                                              f"cut_from (got {self.cut_from!r})")
        dwell_max = section.getduration("dwell_max", 2.0, minval=0.1, maxval=60.0)
        if "dwell_max" in section and not self.dwell_axes:
            raise section.error("dwell_max", "a dwell is told by the axes standing: needs dwell_axes (the "
                                             "machine's position registers, e.g. [\"x_mm\", \"z_mm\"])")
        # whether the tool is in the cut: the one owner (lathed.analysis.cut.state)
        self.cut = CutState(self.cut_from, self.dwell_axes, dwell_max,
                            section.getfloat("load_margin_pct", 5.0, above=0.0, maxval=100.0),
                            section.getfloat("contact_ratio", 1.3, above=1.0, maxval=4.0))
        # the machine's quantities read here or by the cut state (the rest of a poll passes by)
        self._reads = frozenset({"spindle_rpm", "tool_number", "depth_of_cut_mm", "spindle_load_pct"}) | \
            self.cut.quantities
        self._cut_rpm: float | None = None     # speed the cut started at (None: no cut)
        self._cut_revs = 0.0
        self._cut_alarmed = False
        psec = section.getsection("params", required=False)
        self.params = {k: psec.get(k) for k in psec.keys()}
        if self.detector_name in DETECTORS:   # plugin detectors are checked when they start
            try:
                make_detector(self.detector_name, 51200.0, **self.params)
            except ValueError as e:
                raise ConfigError(f"{section.file}: [{section.table}.params]: {e}") from None
        self.detector = None
        self._rebuild = False
        self.rate_hz: float | None = None
        self.tool_number: int | None = None    # the machine's tool_number register, where mapped
        self.rpm: float | None = None
        self.depth_mm: float | None = None
        self.load_pct: float | None = None
        self.state = "idle"
        self.last = None
        self._judged = JudgedIndex()
        self.alarms = 0
        self.windows = 0
        self._eye_view = None   # (detector, windows) -> the last view, reused until a new window
        self.blocks = 0
        self.unusable_blocks = 0
        self._bad_rates: set[float] = set()
        self.lag_ms: float | None = None
        self.sight = Sight(self.input)          # blind while the accelerometer is gone
        self.alarm_started: float | None = None

    def inputs(self) -> list[str]:
        return [self.input, self.machine]

    def refers(self) -> dict[str, tuple[str, str, str | None]]:
        return {"input": (self.input, "sensor", "accelerometer"), "machine": (self.machine, "machine", None)}

    def recording_context(self, source: str) -> dict | None:
        if source != self.input:
            return None
        return {"machine": self.machine, "tool": self.tool, "material": self.material,
                "detector": self.detector_name, "params": dict(self.params), "cut_from": list(self.cut_from)}

    def reconfigure(self, section: Section) -> None:
        """New detector parameters (checked by the reload): alarm levels at once, without
        dropping the cut; window shapes from the next cut (the next detector is built with them)."""
        psec = section.getsection("params", required=False)
        self.params = {k: psec.get(k) for k in psec.keys()}
        det = self.detector
        if det is None:
            return
        fresh = self._new_detector(det.rate)
        for k in LIVE_NOW:
            if k in det.params and k in fresh.params:
                det.params[k] = fresh.params[k]
        det.threshold = det.params.get("threshold", det.threshold)
        self._rebuild = True

    def _new_detector(self, rate: float):
        extra = self.ctx.plugins.chatter_detectors() if self.ctx.plugins is not None else None
        return make_detector(self.detector_name, rate, extra=extra, **self.params)

    async def run(self) -> None:
        # Taken as published (bus taps), in publish order, not through a queue and a task's
        # wake-up a block and channel: that was a tenth of a channel's cost. A failure here is
        # this analyzer's alone: it ends run() (the supervisor restarts it), the bus and the
        # sensor go on.
        bus = self.ctx.bus
        failed = asyncio.get_running_loop().create_future()

        def on_input(msg) -> None:           # the sensor's Blocks; its rms Samples are not read
            if isinstance(msg, Block) and not failed.done():
                try:
                    self._on_block(msg)
                except Exception as e:
                    failed.set_exception(e)

        reads, cut = self._reads, self.cut

        def on_machine(msg) -> None:
            if failed.done():
                return
            try:
                if isinstance(msg, Sample):
                    # a register neither this nor the cut state reads, and no dwell to time, passes
                    # by here (_on_machine's own test, without its call: most of each poll)
                    if msg.quantity in reads or cut.held is not None:
                        self._on_machine(msg)
                elif isinstance(msg, Block):
                    self._on_block(msg)
            except Exception as e:
                failed.set_exception(e)

        bus.tap(self.input, on_input)
        bus.tap(self.machine, on_machine)
        watch = asyncio.create_task(self._watch_sight())
        try:
            await failed
        finally:
            watch.cancel()
            bus.untap(self.input, on_input)
            bus.untap(self.machine, on_machine)

    def _on_machine(self, s: Sample) -> None:
        if s.source != self.machine:
            return
        if s.quantity not in self._reads and self.cut.held is None:
            return           # a register neither this nor the cut state reads, and no dwell to time
        if s.quantity == "spindle_rpm":
            self.rpm = s.value
        elif s.quantity == "tool_number":
            self.tool_number = int(s.value)     # the turret position cutting: recorded with the alarm
        elif s.quantity == "depth_of_cut_mm" and s.value > 0:
            self.depth_mm = s.value
        elif s.quantity == "spindle_load_pct":
            self.load_pct = s.value
        self._on_cut(self.cut.machine(s.quantity, s.value, s.t, self.rpm, time.monotonic()))
        if s.quantity == "spindle_load_pct" and self.cutting and self.detector is not None:
            # the static cutting force, for load_scaled (the detector ignores it otherwise)
            self.detector.set_load(self.cut.cutting_load(s.value, self.rpm))

    def _source(self, name: str, on: bool, t: float) -> None:
        """One source's verdict, as the cut state takes it."""
        ev: list[CutEvent] = []
        self.cut._source(name, on, t, ev)
        self._on_cut(ev)

    @property
    def cutting(self) -> bool:
        return self.cut.cutting

    @property
    def dwells(self) -> int:
        return self.cut.dwells

    def _on_cut(self, events: list[CutEvent]) -> None:
        """What the cut state said: published for suppression and records, and the detector
        learning afresh where the cut (or its chip) begins."""
        pub = self.ctx.bus.publish
        for e in events:
            if e.kind == "start":
                if self._rebuild:             # reloaded parameters shape this cut's windows
                    self.detector, self._rebuild = None, False
                self._learn_afresh()
                pub(Sample(self.name, "cutting", 1.0, "", e.t))
                self.ctx.log.info("cut_state", cutting=True, source=e.source)
            elif e.kind == "contact":
                # the chip, in a cut the feed started: what came before was the approach in air
                if self.detector is not None and self.detector.alarm:
                    self._cleared("the tool reached the stock")
                self._learn_afresh()
                pub(Sample(self.name, "cut_contact", 1.0, "", e.t))   # cut records count from it
                self.ctx.log.info("cut_contact", by=e.source)
            elif e.kind == "dwell":
                self.state = "dwell"
                # no chip: suppression's cut record judges no speed stable over it
                pub(Sample(self.name, "dwell", 1.0, "", e.t))
                self.ctx.log.info("dwell", source=e.source)
            elif e.kind == "dwell_over":
                self.state = "watching" if self.detector is not None and self.detector.learned else "learning"
                pub(Sample(self.name, "dwell", 0.0, "", e.t))
                self.ctx.log.info("dwell_over", source=e.source)
            elif e.kind == "end":
                if e.held:
                    pub(Sample(self.name, "dwell", 0.0, "", e.t))
                if self.detector is not None and self.detector.alarm:
                    self._cleared("cut ended")
                self.state = "idle"
                pub(Sample(self.name, "cutting", 0.0, "", e.t))
                self.ctx.log.info("cut_state", cutting=False, source=e.source)

    def _learn_afresh(self) -> None:
        """A new cut, or the chip in a cut the feed started in air: learn the baseline anew."""
        if self.detector is not None:
            self.detector.reset()
        self._judged.reset()
        self.state = "learning"
        self._cut_rpm = None

    async def _watch_sight(self) -> None:
        while True:
            await asyncio.sleep(CHECK_EVERY_S)
            if self.sight.check(self.ctx.machine_status(self.input), time.monotonic()):
                # the signal is gone, not calm: said, and the alarm left as it was
                why = self.sight.blind
                self.ctx.bus.publish(Sample(self.name, "blind", 1.0, "", time.time()))
                self.ctx.log.warning("chatter_blind", why=why, cutting=self.cutting)
                self.ctx.record("chatter_blind", {"machine": self.machine, "input": self.input, "why": why,
                                                  "cutting": self.cutting,
                                                  "alarm": bool(self.detector is not None and self.detector.alarm)})

    def _sight_back(self) -> None:
        """Blocks again after blindness: a cut's baseline and revolution history span the gap."""
        blind_s = None if self.sight.since is None else round(time.monotonic() - self.sight.since, 3)
        self.ctx.bus.publish(Sample(self.name, "blind", 0.0, "", time.time()))
        self.ctx.log.info("chatter_sight_back", blind_s=blind_s)
        self.ctx.record("chatter_sight_back", {"machine": self.machine, "input": self.input, "blind_s": blind_s})
        if self.cutting:
            if self.detector is not None and self.detector.alarm:
                self._cleared("the accelerometer came back: the baseline is learned again")
            self._learn_afresh()

    def _on_block(self, b: Block) -> None:
        if self.sight.block(time.monotonic()):
            self._sight_back()
        bc = self.cut.block(b.data, b.rate_hz, b.t0, b.rows, b.row, time.monotonic())
        if bc.events:
            self._on_cut(bc.events)
        data = bc.data
        if data is None:
            return           # not the cut's samples: air, a dwell
        rpm = b.rpm if b.rpm else self.rpm
        if not rpm or rpm <= 0:
            return
        if self.detector is None or self.rate_hz != b.rate_hz:
            try:
                self.detector = self._new_detector(b.rate_hz)
            except ValueError as e:
                # a stream at a rate the detector cannot window: counted and said once, never a crash loop
                self.unusable_blocks += 1
                if b.rate_hz not in self._bad_rates:
                    self._bad_rates.add(b.rate_hz)
                    self.ctx.log.error("unusable_vibration_rate", rate_hz=b.rate_hz, error=str(e))
                    self.ctx.record("unusable_vibration_rate", {"rate_hz": b.rate_hz, "error": str(e)})
                self.detector = None
                return
            self.rate_hz = b.rate_hz
        self.blocks += 1
        if self._cut_rpm is None:
            self._cut_rpm, self._cut_revs, self._cut_alarmed = rpm, 0.0, False
        elif (abs(rpm - self._cut_rpm) > 0.05 * self._cut_rpm and not self._cut_alarmed
              and self._cut_revs < ENTRY_REVS):
            # a speed change at entry that no alarm asked for (suppression's avoid, the
            # program): the baseline learned at the old speed does not hold at the new one
            self.detector.reset()
            self.state = "learning"
            self._cut_rpm = rpm
        self._cut_revs += len(data) / b.rate_hz * rpm / 60.0
        if bc.impulse_at is not None:
            # a release, a knock, or a dwell's join (its revolution difference spans the gap, and
            # the chip's re-entry rings the structure): its windows do not count
            self.detector.impulse(bc.impulse_at, rpm)
        was = self.detector.alarm
        windows = self.detector.process(data, rpm)
        t = b.t0 + len(b.data) / b.rate_hz      # the block's end: when its windows are dated
        self.lag_ms = 1000 * (time.time() - t)
        pub = self.ctx.bus.publish
        for w in windows:
            self.windows += 1
            self.last = w
            if not math.isnan(w.index):
                pub(Sample(self.name, "chatter_index", w.index, "", t))
            judged = self._judged.push(w, t)      # what a part's record keeps as its highest
            if judged is not None:
                pub(Sample(self.name, "chatter_index_judged", judged[0], "", judged[1]))
            pub(Sample(self.name, "chatter_threshold", w.threshold, "", t))
            if w.chatter_frequency_hz is not None:
                pub(Sample(self.name, "chatter_frequency_hz", w.chatter_frequency_hz, "Hz", t))
            if w.alarm:
                # the speed the alarm was judged at: suppression acts only where its own reading agrees
                pub(Sample(self.name, "chatter_rpm", rpm, "r/min", t))
            pub(Sample(self.name, "chatter_alarm", 1.0 if w.alarm else 0.0, "", t))
            self.state = "learning" if w.learning else ("chatter" if w.alarm else "watching")
            if w.alarm and not was:
                self._cut_alarmed = True
                self.alarms += 1
                self.alarm_started = t
                self.ctx.log.warning("chatter_alarm", index=round(w.index, 3), threshold=w.threshold,
                                     raised_by=w.raised_by, frequency_hz=w.chatter_frequency_hz, rpm=rpm)
                self.ctx.record("chatter_alarm", {
                    "machine": self.machine, "index": w.index, "threshold": w.threshold,
                    "raised_by": w.raised_by,
                    "chatter_frequency_hz": w.chatter_frequency_hz, "rpm": rpm, "depth_mm": self.depth_mm,
                    "load_pct": self.load_pct, "cut_seen_by": self.cut.cut_by,
                    "tool": self.tool, "tool_number": self.tool_number, "material": self.material,
                    "detector": self.detector_name,
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

    def live_view(self) -> dict | None:
        """The chaos eye for the operator view: the (phi1, phi2) points of the recent
        windows, and those at the start of the cut (the baseline), thinned for plotting.
        A detector other than chaos_sync has it drawn from its revolution difference
        when asked, at most every EYE_MIN_S (it costs the daemon only while a screen
        watches)."""
        det = self.detector
        if det is None:
            return None
        key, own = (id(det), self.windows), det.OWN_EYE
        now = time.monotonic()
        if self._eye_view is not None and (self._eye_view[0] == key or (
                not own and now - self._eye_view[2] < EYE_MIN_S)):
            return self._eye_view[1]     # no new window since (or too soon): the same points
        (p1, p2), base = det.eye_views()
        out = {"eye_phi1": packed(thin(p1, EYE_POINTS)), "eye_phi2": packed(thin(p2, EYE_POINTS)),
               "eye_from": det.name if own else "revolution difference"}
        if base is not None:
            out.update(base_phi1=packed(thin(base[0], EYE_POINTS)), base_phi2=packed(thin(base[1], EYE_POINTS)))
        self._eye_view = (key, out, now)
        return out

    def status(self) -> dict:
        w = self.last
        idx = None if w is None or math.isnan(w.index) else round(w.index, 3)
        blind = self.sight.blind
        cut_by, chip_by = self.cut.cut_by, self.cut.chip_by
        return {"detector": self.detector_name, "cut_state": "blind" if blind else self.state,
                "blind": blind, "cutting": self.cutting,
                "cut_from": self.cut_from, "cut_seen_by": self.cut.cut_by, "index": idx,
                "threshold": None if w is None else w.threshold,
                "chatter_frequency_hz": None if w is None else w.chatter_frequency_hz,
                "alarms": self.alarms, "windows": self.windows, "unusable_blocks": self.unusable_blocks,
                "lag_ms": None if self.lag_ms is None else round(self.lag_ms, 1),
                "chip_seen_by": self.cut.chip_by, "dwells": self.dwells,
                "summary": (f"blind ({blind})" if blind else f"{self.state}") + (f" (cut seen by {cut_by}" + (
                    "" if chip_by in (None, cut_by) else f", chip by {chip_by}") + ")"
                    if cut_by else "")
                           + (f", index {idx} / threshold {w.threshold:g}" if idx else "")
                           + f", {self.alarms} alarm(s)"}


@hookimpl
def lathed_analyzer_types():
    return {"chatter": ChatterAnalyzer}
