"""``record``: a vibration sensor's raw samples streamed to a client (``lathectl record``),
with what an analyst needs beside them.

    {"cmd": "record", "args": {"source": "accel", "seconds": 30}}
    {"cmd": "record", "args": {"source": "accel", "cuts": 2, "pre_s": 1.0, "post_s": 0.5, "wait_s": 3600}}

The first reply names the sensor (its status: device, calibration, rate) and what the
analyzers reading it say about it (Analyzer.recording_context: machine, tool, material,
detector). Then one line ``{"push": frame}`` every FLUSH_S: ``blocks`` [[seq, t0, rpm,
base64 float32], ...] (seq on the device's clock, t0 on the host's), ``samples`` [[t,
source, quantity, value], ...] (the machine's speed and tool, the analyzer's cut state,
alarm and index), until a frame with ``end`` {"why"}. With ``cuts`` it starts ``pre_s``
before the next cut (the air before it) and ends ``post_s`` after the Nth. A client that
does not read is dropped, as a subscriber is (lathed.push). Docs: docs/lathectl.md.
"""
from __future__ import annotations

import asyncio
import base64
import time
from collections import deque
from typing import Any, Callable

import numpy as np
import structlog

from lathed.args import Args
from lathed.bus import Block, Bus, Sample
from lathed.control import RequestError, Stream, _default

log = structlog.get_logger("lathed.recorder")

FLUSH_S = 0.2              # a frame this often
GONE_S = 10.0              # no block for this long: the recording ends, saying why
MAX_S = 3600.0             # the longest recording (a WAV of an hour at 51.2 kS/s is 740 MB)
SAMPLES = {"spindle_rpm", "tool_number", "cutting", "cut_contact", "dwell", "chatter_alarm", "chatter_index",
           "chatter_frequency_hz", "blind", "keyphasor_rpm"}


class Recorder:
    """The ``record`` command of one daemon."""

    def __init__(self, bus: Bus, drivers: Callable[[], dict[str, Any]], analyzers: Callable[[], dict[str, Any]],
                 state: Callable[[str], dict | None], daemon_name: str) -> None:
        self.bus, self.drivers, self.analyzers, self.state = bus, drivers, analyzers, state
        self.daemon_name = daemon_name
        self.active: set[Recording] = set()

    def stats(self) -> list[dict]:
        """The recordings being streamed now (lathectl status)."""
        return [{"source": r.source, "recording": r.recording, "samples": r.samples_recorded,
                 "seconds": r.seconds, "cuts": r.cuts, "cuts_ended": r.cuts_ended} for r in self.active]

    async def request(self, args: dict) -> Stream:
        a = Args("record", args)
        source = a.getstr("source", maxlen=64)
        seconds = a.getfloat("seconds", None, above=0.0, maxval=MAX_S)
        cuts = a.getint("cuts", None, minval=1, maxval=1000)
        pre_s = a.getfloat("pre_s", 1.0, minval=0.0, maxval=30.0)
        post_s = a.getfloat("post_s", 0.5, minval=0.0, maxval=30.0)
        wait_s = a.getfloat("wait_s", MAX_S, above=0.0, maxval=7 * 86400.0)
        a.check_unused()
        if (seconds is None) == (cuts is None):
            raise RequestError("record: give seconds (a time) or cuts (the next N cuts), one of them")
        drivers = self.drivers()
        drv = drivers.get(source)
        if drv is None or drv.role != "sensor" or drv.kind not in ("accelerometer", "sensor"):
            sensors = sorted(n for n, d in drivers.items() if d.role == "sensor" and d.kind == "accelerometer")
            raise RequestError(f"record: source: {source!r} is not a vibration sensor; vibration sensors: "
                               f"{', '.join(sensors) or 'none'}")
        context = None
        for name, an in self.analyzers().items():
            ctx = an.recording_context(source)
            if ctx is not None:
                context = {"analyzer": name, **ctx}
                break
        if cuts is not None and context is None:
            raise RequestError(f"record: cuts: no analyzer reads {source!r} and says when the tool cuts "
                               "(a chatter analyzer); record a time with seconds instead")
        state = self.state(source) or {}
        first = {"source": source, "plugin": type(drv).__module__.rsplit(".", 1)[-1], "daemon": self.daemon_name,
                 "sensor": {k: v for k, v in state.items() if k != "describe"}, "context": context,
                 "seconds": seconds, "cuts": cuts, "pre_s": pre_s if cuts else 0.0,
                 "post_s": post_s if cuts else 0.0, "started_t": time.time()}
        rec = Recording(self, first, source, context, seconds, cuts, pre_s, post_s, wait_s)
        return rec


class Recording(Stream):
    def __init__(self, rec: Recorder, first: dict, source: str, context: dict | None, seconds: float | None,
                 cuts: int | None, pre_s: float, post_s: float, wait_s: float) -> None:
        self.rec, self.first, self.source = rec, first, source
        self.seconds, self.cuts, self.pre_s, self.post_s, self.wait_s = seconds, cuts, pre_s, post_s, wait_s
        self.watched = [source] + ([context["machine"], context["analyzer"]] if context else [])
        self.analyzer = context["analyzer"] if context else None
        self.recording = cuts is None          # seconds: at once; cuts: from the next cut's start
        self.pre: deque[Block] = deque()       # the air before the next cut, while waiting for it
        self.blocks: list[Block] = []
        self.samples: list[list] = []
        self.samples_recorded = 0
        self.cuts_ended = 0
        self.stop_at: float | None = None      # host time the recording ends (post_s after the last cut)
        self.last_block_t = time.monotonic()
        self.started = time.monotonic()
        self.end: str | None = None
        self._taps: list[tuple[str, Callable]] = []
        for src in dict.fromkeys(self.watched):
            fn = self._tap
            rec.bus.tap(src, fn)
            self._taps.append((src, fn))
        rec.active.add(self)

    def _tap(self, msg) -> None:
        if isinstance(msg, Block):
            if msg.source != self.source or self.end is not None:
                return
            self.last_block_t = time.monotonic()
            if not self.recording:
                self.pre.append(msg)
                while self.pre and self.pre[0].t0 < msg.t0 - self.pre_s:
                    self.pre.popleft()
                return
            if self.stop_at is not None and msg.t0 >= self.stop_at:
                self.end = self.end or f"{self.cuts} cut(s) recorded"
                return
            self.blocks.append(msg)
            self.samples_recorded += len(msg.data)
            if self.seconds is not None and self.samples_recorded >= self.seconds * msg.rate_hz:
                self.end = self.end or f"{self.seconds:g} s recorded"
            return
        if not isinstance(msg, Sample) or msg.quantity not in SAMPLES:
            return
        if msg.source == self.analyzer and msg.quantity == "cutting" and self.cuts is not None:
            if msg.value and not self.recording:
                self.recording = True          # the cut starts: the air before it first
                self.blocks.extend(self.pre)
                self.samples_recorded += sum(len(b.data) for b in self.pre)
                self.pre.clear()
            elif not msg.value and self.recording and self.stop_at is None:
                self.cuts_ended += 1
                if self.cuts_ended >= self.cuts:
                    self.stop_at = msg.t + self.post_s
        if self.recording or msg.quantity in ("spindle_rpm", "tool_number"):
            self.samples.append([msg.t, msg.source, msg.quantity, msg.value])
            if not self.recording and len(self.samples) > 64:
                del self.samples[:-32]       # while waiting: the latest speed and tool only

    def frame(self) -> dict:
        f: dict[str, Any] = {"t": time.time()}
        if self.blocks:
            f["blocks"] = [[b.seq, b.t0, b.rpm, b.rate_hz,
                            base64.b64encode(np.asarray(b.data, dtype="<f4").tobytes()).decode()]
                           for b in self.blocks]
            self.blocks = []
        if self.samples and self.recording:
            f["samples"], self.samples = self.samples, []
        now = time.monotonic()
        if self.end is None and now - self.last_block_t > GONE_S:
            st = self.rec.state(self.source) or {}
            self.end = f"{self.source} sent nothing for {now - self.last_block_t:.0f} s ({st.get('describe')})"
        if self.end is None and not self.recording and now - self.started > self.wait_s:
            self.end = f"no cut within {self.wait_s:g} s"
        if self.end is None and now - self.started > MAX_S + self.wait_s:
            self.end = f"the longest recording is {MAX_S:g} s"
        if self.end is not None:
            f["end"] = {"why": self.end}
        return f

    async def run(self, writer: asyncio.StreamWriter, write_timeout: float) -> str | None:
        import json
        try:
            while True:
                await asyncio.sleep(FLUSH_S)
                f = self.frame()
                writer.write(json.dumps({"push": f}, default=_default).encode() + b"\n")
                try:
                    async with asyncio.timeout(write_timeout):
                        await writer.drain()
                except TimeoutError:
                    return f"the client read nothing for {write_timeout:g} s"
                if "end" in f:
                    log.info("recording_ended", source=self.source, why=f["end"]["why"])
                    return None
        except ConnectionError:
            return None
        finally:
            self.close()

    def close(self) -> None:
        for src, fn in self._taps:
            self.rec.bus.untap(src, fn)
        self._taps = []
        self.rec.active.discard(self)
