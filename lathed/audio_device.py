"""An audio input device shared by the sensors that read its channels.

One capture helper process per device (lathed.audio_capture, which says why it is a
process); every ``[sensor.*]`` with ``plugin = "audio_input"`` naming the same device,
rate and block size attaches to it and is handed each block of all its channels. The
helper ending (the device unplugged, the audio server gone) detaches every sensor with
the reason; each retries on its own backoff and the first to reconnect starts a new
helper. Docs: docs/sensors.md.
"""
from __future__ import annotations

import asyncio
import json
import os
import signal
import sys
import weakref
from collections import deque
from typing import Callable

import numpy as np
import structlog

from lathed.analysis.conditioning import ConditionerBank
from lathed.audio_capture import FRAME, MAGIC, OVERFLOW
from lathed.driver import LinkDown

log = structlog.get_logger("lathed.audio")

START_TIMEOUT_S = 15.0     # PortAudio's first scan of ALSA devices can take seconds
STOP_TIMEOUT_S = 2.0       # the helper closes its stream within a second of its stdin's end


class DeviceGone(LinkDown):
    """The device (or the audio server behind it) went away; its message says why."""


class SampleClock:
    """The device's sample clock against the host's: a straight line through (sample index,
    host time of that sample) pairs, one kept every ``every_s`` over ``span_s``. The line
    dates a block from its index, without the scheduling jitter of each callback's stamp
    (a callback is only ever late: the line runs along the early stamps, a low quantile);
    once the pairs span ``fit_s`` its slope is the device's true rate (its crystal against
    the host's clock), before that the nominal one. Stamps away from the line by more than
    ``step_s`` several times in a row are a step between the clocks (samples an overrun
    discarded, a device that stalled): the line starts again from them (``steps``)."""

    def __init__(self, rate_hz: float, every_s: float = 0.5, span_s: float = 120.0, fit_s: float = 20.0,
                 step_s: float = 0.03) -> None:
        self.rate = float(rate_hz)
        self.every = int(every_s * rate_hz)
        self.fit_s, self.step_s = fit_s, step_s
        self._pts: deque[tuple[int, float]] = deque(maxlen=max(4, int(span_s / every_s)))
        self._line: tuple[float, float, int] | None = None     # host t at index i0, s per sample, i0
        self._fitted = False
        self._off = 0                 # stamps in a row off the line
        self.steps = 0
        self.stepped_s = 0.0          # the steps, added up (s; > 0: the host's clock went ahead)

    def reset(self) -> None:
        self._pts.clear()
        self._line = None
        self._fitted = False
        self._off = 0

    def add(self, index: int, host_t: float) -> None:
        if self._pts and index - self._pts[-1][0] < self.every:
            return
        off = None if self._line is None else host_t - self.t(index)
        if off is not None and abs(off) > self.step_s:
            self._off += 1
            if self._off < 3:
                return
            self.steps += 1
            self.stepped_s += off
            self.reset()
        else:
            self._off = 0
        self._pts.append((index, host_t))
        i = np.array([p[0] for p in self._pts], dtype=np.float64)
        t = np.array([p[1] for p in self._pts])
        i0 = int(i[0])
        di, dt = i - i0, t - t[0]
        slope = 1.0 / self.rate
        self._fitted = False
        if di[-1] >= self.fit_s * self.rate:
            # least squares, in closed form (np.polyfit's SVD costs a block's worth of time)
            mi, mt = di.mean(), dt.mean()
            fit = float(np.dot(di - mi, dt - mt) / np.dot(di - mi, di - mi))
            # a clock 1 % off is not a sound card's crystal: keep the nominal
            if abs(fit * self.rate - 1.0) < 0.01:
                slope, self._fitted = fit, True
        res = dt - di * slope
        k = len(res) // 10
        self._line = (t[0] + float(np.partition(res, k)[k]), slope, i0)

    def t(self, index: int) -> float | None:
        if self._line is None:
            return None
        t0, slope, i0 = self._line
        return t0 + (index - i0) * slope

    @property
    def measured_rate(self) -> float | None:
        return 1.0 / self._line[1] if self._fitted else None

Listener = Callable[[np.ndarray, dict], None]


class AudioDevice:
    """The helper process of one device and the sensors attached to it."""

    _devices: dict[tuple, AudioDevice] = {}

    @classmethod
    def of(cls, device: str, hostapi: str | None, rate: float, block: int) -> AudioDevice:
        key = (device, hostapi, float(rate), int(block))
        if key not in cls._devices:
            cls._devices[key] = cls(*key)
        return cls._devices[key]

    def __init__(self, device: str, hostapi: str | None, rate: float, block: int) -> None:
        self.device, self.hostapi, self.rate, self.block = device, hostapi, rate, block
        # sensor -> channels it needs (highest index + 1); weak: a sensor a reload built to
        # compare and dropped claims nothing
        self.claims: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
        self.listeners: dict[object, tuple[Listener, Callable[[str], None]]] = {}
        self.proc: asyncio.subprocess.Process | None = None
        self.info: dict | None = None
        self.channels = 0
        self._reader: asyncio.Task | None = None
        self._lock = asyncio.Lock()
        self.starts = 0
        self.last_stderr: deque[str] = deque(maxlen=4)
        self._banks: dict[tuple[float, float], ConditionerBank] = {}

    def bank(self, highpass_hz: float, mains_hz: float) -> ConditionerBank:
        """The conditioners of this device's sensors with this high-pass and mains frequency,
        run as one pass a block (its channels in one set of numpy calls)."""
        return self._banks.setdefault((highpass_hz, mains_hz), ConditionerBank())

    def claim(self, sensor: object, channels: int) -> None:
        """At construction: the device is opened with every claimed sensor's channels."""
        self.claims[sensor] = channels

    async def attach(self, sensor: object, on_block: Listener, on_gone: Callable[[str], None],
                     stall_s: float) -> dict:
        """Start the helper if it is not running (with enough channels), then hand
        ``on_block(frames x channels float32, meta)`` each block until ``on_gone(why)``."""
        async with self._lock:
            need = max(self.claims.values(), default=1)
            if self.proc is not None and (self.channels < need or self.proc.returncode is not None
                                          or self._reader is None or self._reader.done()):
                await self._stop("reopened with more channels" if self.channels < need else "helper ended")
            if self.proc is None:
                await self._start(need, stall_s)
            self.listeners[sensor] = (on_block, on_gone)
            return dict(self.info)

    async def detach(self, sensor: object) -> None:
        self.listeners.pop(sensor, None)
        if not self.listeners:
            async with self._lock:
                if not self.listeners:
                    await self._stop(None)

    async def _start(self, channels: int, stall_s: float) -> None:
        args = [sys.executable, "-m", "lathed.audio_capture", "--device", self.device, "--rate", repr(self.rate),
                "--channels", str(channels), "--block", str(self.block), "--stall", repr(stall_s)]
        if self.hostapi:
            args += ["--hostapi", self.hostapi]
        self.proc = await asyncio.create_subprocess_exec(
            *args, stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.PIPE, start_new_session=True)
        self.starts += 1
        self.channels = channels
        self.last_stderr.clear()
        try:
            async with asyncio.timeout(START_TIMEOUT_S):
                line = await self.proc.stdout.readline()
        except TimeoutError:
            await self._stop(None)
            raise DeviceGone(f"device gone: {self.device!r} did not open within {START_TIMEOUT_S:g} s") from None
        word, _, rest = line.decode(errors="replace").partition(" ")
        try:
            info = json.loads(rest) if rest.strip() else {}
        except ValueError:
            info = {"error": rest.strip()}
        if word != "READY":
            err = await self._stop(None)
            why = info.get("error") or err or f"capture helper exited {self.proc and self.proc.returncode}"
            raise DeviceGone(f"device gone: {why}") if info.get("gone") or not info else ConnectionError(why)
        self.info = info
        self._reader = asyncio.create_task(self._read(self.proc), name=f"audio:{self.device}")
        asyncio.create_task(self._errors(self.proc))
        log.info("audio_device_open", device=info.get("name"), hostapi=info.get("hostapi"), rate_hz=self.rate,
                 channels=channels, block=self.block, latency_s=info.get("latency_s"), pid=info.get("pid"))

    async def _errors(self, proc) -> None:
        while line := await proc.stderr.readline():
            text = line.decode(errors="replace").strip()
            self.last_stderr.append(text)
            log.warning("audio_capture", device=self.device, message=text)

    async def _read(self, proc) -> None:
        why = None
        try:
            while True:
                head = await proc.stdout.readexactly(FRAME.size)
                magic, frames, nch, flags, adc, host_t, dropped = FRAME.unpack(head)
                if magic != MAGIC or nch != self.channels:
                    why = f"capture helper sent a bad frame header ({magic!r}, {nch} channels)"
                    break
                body = await proc.stdout.readexactly(4 * frames * nch)
                data = np.frombuffer(body, dtype="<f4").reshape(frames, nch)
                meta = {"adc": adc, "host_t": host_t, "overflow": bool(flags & OVERFLOW), "dropped": dropped}
                for sensor, (on_block, on_gone) in list(self.listeners.items()):
                    try:
                        on_block(data, meta)
                    except Exception as e:      # one sensor's bug is its own: it is detached, said
                        self.listeners.pop(sensor, None)
                        on_gone(f"{type(e).__name__}: {e}")
        except asyncio.CancelledError:
            why = "the device was closed"
            raise
        except (asyncio.IncompleteReadError, ConnectionError):
            try:
                await asyncio.wait_for(proc.wait(), STOP_TIMEOUT_S)
            except TimeoutError:
                pass
            await asyncio.sleep(0.05)       # its last stderr line says why
            why = self.last_stderr[-1] if self.last_stderr else f"capture helper exited {proc.returncode}"
        finally:
            if not why.startswith("device gone"):
                why = f"device gone: {why}"
            for _, on_gone in list(self.listeners.values()):
                on_gone(why)
            self.listeners.clear()

    async def _stop(self, why: str | None) -> str | None:
        """End the helper: its stdin closed, then killed if it does not go (a hung PortAudio)."""
        proc, self.proc = self.proc, None
        reader, self._reader = self._reader, None
        if reader is not None and reader is not asyncio.current_task():
            reader.cancel()
            await asyncio.gather(reader, return_exceptions=True)
        if proc is None:
            return None
        if proc.returncode is None:
            try:
                proc.stdin.close()
                await asyncio.wait_for(proc.wait(), STOP_TIMEOUT_S)
            except (TimeoutError, ConnectionError):
                try:
                    os.killpg(proc.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                await proc.wait()
        if why:
            log.info("audio_device_closed", device=self.device, why=why)
        return self.last_stderr[-1] if self.last_stderr else None
