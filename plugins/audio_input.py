"""An audio-class accelerometer or microphone: a USB digital accelerometer, an interface with
IEPE inputs, a microphone near the cut, read through PortAudio (ALSA, JACK...).

    [sensor.accel]
    plugin = "audio_input"
    device = "333D01"          # a part of the device's name, or its index
    channel = 1                # the interface's input, from 1
    rate = 48000               # Hz
    sensitivity_mv_g = 100.0   # the calibration (docs/sensors.md has the others)
    full_scale_v = 5.0

Publishes each block as a Block (quantity "acceleration", m/s²; a microphone's
"sound_pressure", Pa) dated on the host's clock and indexed on the device's, its rms
as a Sample, and with ``keyphasor_channel`` the spindle speed measured from a
once-per-revolution pulse (the block's rpm, and ``keyphasor_rpm``). Overruns, lost
samples and clipped samples are counted in the status and recorded; a device that
goes away is "device gone" and retried. Reference: docs/sensors.md.
"""
from __future__ import annotations

import asyncio
import math
import time

import numpy as np

from lathed import hookimpl
from lathed.audio_device import AudioDevice, DeviceGone, SampleClock
from lathed.analysis.conditioning import Calibration, Conditioner, Keyphasor
from lathed.bus import Block, Sample
from lathed.config import Section
from lathed.driver import Driver
from lathed.extras import missing

REPORT_EVERY_S = 60.0      # lost samples are logged and recorded at most this often
CLIP = 0.999               # a sample this near full scale: the converter saturated
CALIBRATIONS = ("sensitivity_mv_g", "counts_per_m_s2", "sensitivity_mv_pa", "uncalibrated")


class AudioInput(Driver):
    role = "sensor"
    kind = "accelerometer"

    def __init__(self, name: str, section: Section):
        super().__init__(name, section)
        dev = section.get("device")
        if isinstance(dev, bool) or not isinstance(dev, (str, int)) or (isinstance(dev, int) and dev < 0):
            raise section.error("device", f"expected a device name (or a part of it) or its index, got {dev!r}")
        self.device = str(dev)
        self.hostapi = section.getstr("hostapi", None)
        self.rate = section.getfloat("rate", 48000.0, minval=1000.0, maxval=384000.0)
        self.block = section.getint("block", 1024, minval=64, maxval=16384)
        self.channel = section.getint("channel", 1, minval=1, maxval=64)
        self.kp_channel = section.getint("keyphasor_channel", 0, minval=0, maxval=64)
        if self.kp_channel == self.channel:
            raise section.error("keyphasor_channel", f"is the signal's own channel {self.channel}")
        self.timeout = section.getduration("timeout", 1.0, minval=0.1, maxval=60.0)
        self.highpass_hz = section.getfloat("highpass_hz", 2.0, minval=0.0, maxval=1000.0)
        self.mains_hz = section.getfloat("mains_hz", 0.0, minval=0.0, maxval=400.0)
        if 0 < self.mains_hz < 16:
            raise section.error("mains_hz", f"{self.mains_hz:g} Hz is no grid's frequency (50 or 60; 16.7 for "
                                            "railway supplies; 0: none)")
        self.calibration = _calibration(section)
        # found, not imported: importing it starts PortAudio in the daemon, which only the
        # capture helper may do (lathed.audio_capture)
        if (why := missing("sounddevice")) is not None:
            raise section.error("plugin", f"audio_input needs {why}")
        self.dev = AudioDevice.of(self.device, self.hostapi, self.rate, self.block)
        self.dev.claim(self, max(self.channel, self.kp_channel))
        # the device's channels with this conditioning are conditioned together, once a block
        self.bank = self.dev.bank(self.highpass_hz, self.mains_hz)
        self.clock = SampleClock(self.rate)
        self.info: dict = {}
        self.seq = 0                   # the next sample's index on the device clock, over reconnections
        self.blocks = self.overruns = self.lost_samples = self.gaps = self.clipped = self.silent_blocks = 0
        self._silent = False
        self.cond: Conditioner | None = None
        self.keyphasor: Keyphasor | None = None
        self._gone: asyncio.Future | None = None
        self._dropped0: int | None = None
        self._end_t: float | None = None          # host time of the last sample, for an outage's length
        self._reported = (0.0, 0, 0)              # when, overruns and lost samples said so far

    # -- the link -----------------------------------------------------------------------
    async def connect(self) -> None:
        self._gone = asyncio.get_running_loop().create_future()
        # fresh filters and clock fit: the stream starts anew (its state is not the last one's);
        # made before the first block can come
        self.cond = Conditioner(self.rate, self.calibration.scale, self.highpass_hz, self.mains_hz)
        self.bank.join(self, self.cond, self.channel - 1)
        self.keyphasor = Keyphasor(self.rate) if self.kp_channel else None
        self.clock.reset()
        self._dropped0 = None
        self._frame_t = time.monotonic()
        self.info = await self.dev.attach(self, self._on_block, self._on_gone, self.timeout)
        if self._end_t is not None:
            # the device clock ran on while it was gone: the index keeps the time between
            self.seq += max(0, int(round((time.time() - self._end_t) * self.rate)))

    async def run(self) -> None:
        while True:
            done, _ = await asyncio.wait({self._gone}, timeout=self.timeout)
            if done:
                raise DeviceGone(self._gone.result())
            age = time.monotonic() - self._frame_t
            if age > 3 * self.timeout + 1.0:      # the helper itself hung: close() stops it
                raise DeviceGone(f"device gone: no samples from {self.info.get('name', self.device)} "
                                 f"for {age:.1f} s")

    async def close(self) -> None:
        self.bank.leave(self)
        await self.dev.detach(self)

    def _on_gone(self, why: str) -> None:
        if self._gone is not None and not self._gone.done():
            self._gone.set_result(why)

    # -- each block ----------------------------------------------------------------------
    def _on_block(self, data: np.ndarray, meta: dict) -> None:
        self._frame_t = time.monotonic()
        frames = len(data)
        lost = self._lost(frames, meta)
        if meta["overflow"]:
            self.overruns += 1
        if lost:
            self.gaps += 1
            self.lost_samples += lost
            self.seq += lost
        if meta["overflow"] or lost:
            self._report()
        x, peak, y, shared = self.bank.take(self, data)
        self.clock.add(self.seq, meta["host_t"])
        if y is None:
            # exact digital silence is no sensor (an input with nothing plugged in, a stream
            # not yet fed): counted and said, not published, so an analyzer is blind, not calm
            self.silent_blocks += 1
            self.seq += frames
            if not self._silent:
                self._silent = True
                self.ctx.log.warning("audio_input_silent", device=self.info.get("name", self.device),
                                     channel=self.channel, why="digital silence: nothing connected to the input?")
            return
        self._silent = False
        if peak >= CLIP:
            self.clipped += int(np.count_nonzero(np.abs(x) >= CLIP))
        t0 = self.clock.t(self.seq)
        rpm = None
        if self.keyphasor is not None:
            self.keyphasor.process(data[:, self.kp_channel - 1], self.seq)
            rpm = self.keyphasor.rpm(self.seq + frames)
        self.mark_data()
        self._end_t = t0 + frames / self.rate
        bus = self.ctx.bus
        # the device block's rows beside its own: its channels' analyzers may work on them together
        rows, row = shared if shared is not None else (None, 0)
        bus.publish(Block(self.name, self.calibration.quantity, self.rate, t0, self.seq, y, rpm, rows, row))
        bus.publish(Sample(self.name, "rms", math.sqrt(float(np.dot(y, y)) / frames), self.calibration.unit, t0))
        if rpm is not None:
            bus.publish(Sample(self.name, "keyphasor_rpm", rpm, "r/min", t0))
        self.seq += frames
        self.blocks += 1

    def _lost(self, frames: int, meta: dict) -> int:
        """Samples known missing before this block: blocks the helper could not hand over.
        What an overrun discarded is not known (PortAudio says only that it did; the ADC
        stamps are the host's clock read at each period, jittering by a quarter of one):
        it is counted as an overrun, and the clock line steps over it (SampleClock)."""
        dropped = meta["dropped"]
        if self._dropped0 is None:
            self._dropped0 = dropped           # what the helper dropped before we attached
        lost = (dropped - self._dropped0) * frames
        self._dropped0 = dropped
        return lost

    def _report(self) -> None:
        now = time.monotonic()
        when, over, lost = self._reported
        if now - when < REPORT_EVERY_S and when:
            return
        payload = {"overruns": self.overruns - over, "lost_samples": self.lost_samples - lost,
                   "overruns_total": self.overruns, "lost_samples_total": self.lost_samples,
                   "device": self.info.get("name", self.device)}
        self._reported = (now, self.overruns, self.lost_samples)
        self.ctx.log.warning("audio_samples_lost", **payload)
        self.ctx.record("audio_samples_lost", payload)

    # -- what it tells ------------------------------------------------------------------
    def quantities(self) -> frozenset[str]:
        return frozenset({"rms", "keyphasor_rpm"} if self.kp_channel else {"rms"})

    def status(self) -> dict:
        measured = self.clock.measured_rate
        return {"device": self.info.get("name", self.device), "hostapi": self.info.get("hostapi"),
                "channel": self.channel, "keyphasor_channel": self.kp_channel or None, "rate_hz": self.rate,
                "rate_measured_hz": None if measured is None else round(measured, 3),
                "clock_drift_ppm": None if measured is None else round((measured / self.rate - 1) * 1e6, 1),
                "clock_steps": self.clock.steps, "clock_stepped_s": round(self.clock.stepped_s, 4),
                "quantity": self.calibration.quantity, "unit": self.calibration.unit,
                "calibration": self.calibration.text, "highpass_hz": self.highpass_hz,
                "mains_hz": self.mains_hz or None,
                "blocks": self.blocks, "samples": self.seq, "overruns": self.overruns,
                "lost_samples": self.lost_samples, "gaps": self.gaps, "clipped_samples": self.clipped,
                "silent_blocks": self.silent_blocks,
                "keyphasor_pulses": self.keyphasor.pulses if self.keyphasor else None,
                "latency_ms": None if self.info.get("latency_s") is None else round(1000 * self.info["latency_s"], 1),
                "helper_starts": self.dev.starts, "helper_pid": self.info.get("pid")}


def _calibration(section: Section) -> Calibration:
    """Exactly one way to say what full scale is: an analogue accelerometer's mV/g and the
    interface's full-scale volts, a digital one's counts per m/s², a microphone's mV/Pa, or none."""
    given = [k for k in CALIBRATIONS if k in section]
    if len(given) != 1:
        raise section.error(None, "give one calibration: sensitivity_mv_g with full_scale_v (an IEPE "
                                  "accelerometer into an interface), counts_per_m_s2 with bits (a digital "
                                  "accelerometer), sensitivity_mv_pa with full_scale_v (a microphone), or "
                                  f"uncalibrated = true; got {', '.join(given) or 'none'}")
    key = given[0]
    if key == "sensitivity_mv_g":
        return Calibration.iepe(section.getfloat("sensitivity_mv_g", above=0.0, maxval=1e5),
                                section.getfloat("full_scale_v", above=0.0, maxval=1000.0))
    if key == "counts_per_m_s2":
        return Calibration.digital(section.getfloat("counts_per_m_s2", above=0.0, maxval=1e12),
                                   section.getint("bits", 24, minval=16, maxval=32))
    if key == "sensitivity_mv_pa":
        return Calibration.microphone(section.getfloat("sensitivity_mv_pa", above=0.0, maxval=1e5),
                                      section.getfloat("full_scale_v", above=0.0, maxval=1000.0))
    if not section.getbool("uncalibrated"):
        raise section.error("uncalibrated", "false is no calibration: give one of the others, or true")
    return Calibration.uncalibrated()


@hookimpl
def lathed_driver_types():
    return {"audio_input": AudioInput}
