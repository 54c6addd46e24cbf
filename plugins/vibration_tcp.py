"""An accelerometer DAQ streaming framed samples over TCP (format: lathed.wire).

    [sensor.accel]
    plugin = "vibration_tcp"
    host = "127.0.0.1"
    port = 15021
    timeout = "2s"          # no frame for this long: the link is re-opened
    rate_min = 100.0        # Hz: a frame claiming a sample rate outside
    rate_max = 1000000.0    #     rate_min..rate_max is refused

Publishes each frame as a Block (quantity "acceleration", m/s²) and its RMS
as a Sample. Gaps in the stream's sample counter are counted, never hidden.
A frame whose header is implausible (sample rate out of range, spindle speed
NaN or negative) is refused, counted by reason in ``refused_frames`` and
reported, and its samples skipped so the stream stays in step; a header
that is not one (bad magic) re-opens the link.
"""
from __future__ import annotations

import asyncio
import math
from collections import Counter

import numpy as np

from lathed import hookimpl
from lathed.bus import Block, Sample
from lathed.config import Section
from lathed.driver import Driver
from lathed.wire import VIB_HEADER, VIB_RATE_MAX, VIB_RATE_MIN, unpack_vibration_header, vibration_header_problem

MAX_FRAME_SAMPLES = 1 << 16


class VibrationTCP(Driver):
    role = "sensor"
    kind = "accelerometer"

    def __init__(self, name: str, section: Section):
        super().__init__(name, section)
        self.host = section.getstr("host")
        self.port = section.getint("port", minval=1, maxval=65535)
        self.timeout = section.getduration("timeout", 2.0, minval=0.05, maxval=600)
        self.rate_min = section.getfloat("rate_min", VIB_RATE_MIN, minval=1.0, maxval=VIB_RATE_MAX)
        self.rate_max = section.getfloat("rate_max", VIB_RATE_MAX, minval=1.0, maxval=100 * VIB_RATE_MAX)
        if self.rate_min > self.rate_max:
            raise section.error("rate_min", f"{self.rate_min:g} is above rate_max {self.rate_max:g}")
        self.refused_frames: Counter = Counter()
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None
        self.frames = 0
        self.samples = 0
        self.lost_samples = 0
        self.rate_hz: float | None = None
        self._next_seq: int | None = None

    async def connect(self) -> None:
        try:
            self.reader, self.writer = await asyncio.wait_for(
                asyncio.open_connection(self.host, self.port), self.timeout)
        except (OSError, asyncio.TimeoutError) as e:
            raise ConnectionError(f"no vibration stream at {self.host}:{self.port} ({e or 'timeout'})") from None
        self._next_seq = None

    async def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = self.reader = None

    async def run(self) -> None:
        while True:
            # asyncio.timeout, not wait_for: no extra task per read at 50 frames/s
            try:
                async with asyncio.timeout(self.timeout):
                    head = await self.reader.readexactly(VIB_HEADER.size)
                    channels, n, rate, seq, t0, rpm = unpack_vibration_header(head)
                    if n * channels > MAX_FRAME_SAMPLES:
                        raise ValueError(f"frame of {n}x{channels} samples is larger than {MAX_FRAME_SAMPLES}")
                    body = await self.reader.readexactly(4 * n * channels)
            except TimeoutError:
                raise TimeoutError(f"no vibration frame from {self.host}:{self.port} for {self.timeout:g} s "
                                   "(DAQ stopped or cable out?)") from None
            bad = vibration_header_problem(rate, rpm, self.rate_min, self.rate_max)
            if bad is not None:
                # well-formed but implausible: skip its samples, the stream stays in step
                self.refused_frames[bad[0]] += 1
                self.ctx.bus.report("acceleration", None, *bad)
                self._next_seq = None
                continue
            data = np.frombuffer(body, dtype="<f4").reshape(n, channels)[:, 0].astype(np.float64)
            if self._next_seq is not None and seq != self._next_seq:
                if seq > self._next_seq:
                    self.lost_samples += seq - self._next_seq
                self.ctx.log.warning("vibration_gap", expected_seq=self._next_seq, got_seq=seq)
            self._next_seq = seq + n
            self.rate_hz = float(rate)
            self.frames += 1
            self.samples += n
            self.mark_data()
            self.ctx.bus.publish(Block(self.name, "acceleration", float(rate), t0, seq, data, float(rpm)))
            self.ctx.bus.publish(Sample(self.name, "rms", math.sqrt(float(data @ data) / n), "m/s²", t0))

    def quantities(self) -> frozenset[str]:
        return frozenset({"rms"})      # the waveform itself is a block (subscribe's vibration), not a sample

    def status(self) -> dict:
        return {"rate_hz": self.rate_hz, "frames": self.frames, "lost_samples": self.lost_samples,
                "refused_frames": dict(self.refused_frames)}


@hookimpl
def lathed_driver_types():
    return {"vibration_tcp": VibrationTCP}
