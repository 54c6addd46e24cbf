"""What a screen needs of a fast signal, small enough to send many times a second.

A 51.2 kS/s channel is never sent raw: a subscriber gets the envelope (min
and max per column) of the last window and its amplitude spectrum, a few
hundred points each. Pure numpy, no asyncio: the push hub calls it at most
once per frame period for all subscribers together.
"""
from __future__ import annotations

import base64
from collections import deque
from functools import lru_cache

import numpy as np

WINDOW = 8192          # samples in the window shown (0.16 s at 51.2 kS/s: a few revolutions)
COLUMNS = 400          # envelope columns: a panel's width in pixels, roughly
SPECTRUM_MAX_HZ = 5000.0   # chatter and the lathe's modes lie well below this
SPECTRUM_BINS = 400


class Ring:
    """The last ``size`` samples of a stream, as the blocks that hold them: adding a block
    keeps a reference to it (it arrives tens of times a second; the bus's blocks are never
    written after they are published), and the window is joined only when a view is drawn
    (a few times a second, and only while someone watches)."""

    def __init__(self, size: int = WINDOW):
        self.size = size
        self._blocks: deque[np.ndarray] = deque()
        self._held = 0         # samples in _blocks (up to a block more than size)
        self.rate_hz = 0.0
        self.t_end = 0.0       # time just after the last sample
        self.blocks = 0

    @property
    def filled(self) -> int:
        return min(self.size, self._held)

    def add(self, data: np.ndarray, rate_hz: float, t0: float) -> None:
        if rate_hz != self.rate_hz:   # a new rate: the old samples are another signal
            self._blocks.clear()
            self._held, self.rate_hz = 0, rate_hz
        n = len(data)
        self.t_end = t0 + n / rate_hz
        self.blocks += 1
        if not n:
            return
        blocks = self._blocks
        blocks.append(data)
        self._held += n
        while self._held - len(blocks[0]) >= self.size:   # the oldest block is wholly out of the window
            self._held -= len(blocks.popleft())

    def window(self) -> np.ndarray:
        """The samples held, oldest first (float)."""
        if not self._blocks:
            return np.zeros(0)
        x = np.concatenate(self._blocks) if len(self._blocks) > 1 else self._blocks[0]
        return np.asarray(x[-self.size:], dtype=float)

    def view(self, spec: dict | None = None) -> dict | None:
        """Envelope and spectrum of the window; ``spec``: a spectrum of this rate to show
        instead of computing one (its FFT is most of a view's cost)."""
        if self.filled < 64:
            return None
        x = self.window()
        return {"t_end": self.t_end, "rate_hz": self.rate_hz, **envelope(x, self.rate_hz),
                **(spec if spec is not None else spectrum(x, self.rate_hz))}


def packed(a: np.ndarray) -> dict:
    """``a`` as {"f32": base64 of its little-endian float32 bytes}: a plot needs no more than
    float32's 7 digits, and encoding is a copy, where JSON's float by float cost a subscriber
    a millisecond a frame (issue 14). Non-finite values stay NaN/inf: a page shows them as gaps."""
    return {"f32": base64.b64encode(np.ascontiguousarray(a, dtype="<f4").tobytes()).decode("ascii")}


def rounded(a: np.ndarray, digits: int = 4) -> list[float | None]:
    """``a`` as a list to ``digits`` significant digits of its largest value (a plot shows no
    finer; the JSON is a third the size), vectorised; a non-finite value becomes None (null).
    For what is sent once (a lobe chart); what changes every frame is ``packed``."""
    a = np.asarray(a, dtype=float)
    finite = np.isfinite(a)
    m = float(np.max(np.abs(a[finite]))) if finite.any() else 0.0
    out = np.round(a, digits - 1 - int(np.floor(np.log10(m)))) if m > 0 else a
    if finite.all():
        return out.tolist()
    return [v if ok else None for v, ok in zip(out.tolist(), finite.tolist())]


def unpacked(v: dict | list) -> np.ndarray:
    """A client's side of ``packed`` (a plain list passes as it is)."""
    if isinstance(v, dict):
        return np.frombuffer(base64.b64decode(v["f32"]), dtype="<f4").astype(float)
    return np.asarray(v, dtype=float)


def envelope(x: np.ndarray, rate_hz: float, columns: int = COLUMNS) -> dict:
    """Min and max of x per column, with each column's time from the window's start (s)."""
    starts, env_t = _columns(len(x), rate_hz, columns)
    return {"env_t": env_t, "env_min": packed(np.minimum.reduceat(x, starts)),
            "env_max": packed(np.maximum.reduceat(x, starts))}


@lru_cache(maxsize=8)
def _columns(n: int, rate_hz: float, columns: int) -> tuple[np.ndarray, dict]:
    """Where each envelope column starts, and their times packed: the same for every view of a
    full window, made once (and the same object each time: a frame leaves it out, unchanged)."""
    starts = np.linspace(0, n, min(columns, n) + 1).astype(int)[:-1]
    starts.flags.writeable = False
    return starts, packed(starts / rate_hz)


def spectrum(x: np.ndarray, rate_hz: float, max_hz: float = SPECTRUM_MAX_HZ, bins: int = SPECTRUM_BINS) -> dict:
    """Amplitude spectrum (Hann window, peak amplitude units of x) up to max_hz, as
    ``bins`` points each holding the largest line it covers (a peak is never averaged away)."""
    n = len(x)
    w, gain = _hann(n)
    m, group, spec_f = _bins(n, rate_hz, max_hz, bins)
    if m == 0:
        return {"spec_f": spec_f, "spec_a": packed(np.empty(0))}
    mag = np.abs(np.fft.rfft((x - x.mean()) * w)[:m])
    return {"spec_f": spec_f, "spec_a": packed(mag.reshape(-1, group).max(axis=1) * gain)}


@lru_cache(maxsize=8)
def _bins(n: int, rate_hz: float, max_hz: float, bins: int) -> tuple[int, int, dict]:
    """(lines kept, lines per point, the points' frequencies packed) of an n-point spectrum up to
    max_hz: made once per window length and rate, as the Hann window."""
    f = np.fft.rfftfreq(n, 1.0 / rate_hz)
    f = f[f <= max_hz]
    group = max(1, int(np.ceil(len(f) / bins)))
    m = len(f) // group * group
    return m, group, packed(f[:m].reshape(-1, group)[:, 0])


@lru_cache(maxsize=4)
def _hann(n: int) -> tuple[np.ndarray, float]:
    """The Hann window of n points and its amplitude gain: made once per window length
    (the window is full, and its length the same, but for a sensor's first 0.16 s), not
    per view; it cost as much as the FFT."""
    w = np.hanning(n)
    w.flags.writeable = False
    return w, 2.0 / w.sum()


def thin(a: np.ndarray, points: int) -> np.ndarray:
    """Every k-th point so at most ``points`` remain (for scatter plots)."""
    step = max(1, int(np.ceil(len(a) / points)))
    return a[::step]
