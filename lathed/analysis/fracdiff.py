"""Grünwald–Letnikov fractional derivative with finite memory.

    D^p x[n] ~= h^(-p) * sum_{j=0..L} w_j x[n-j],
    w_0 = 1,  w_j = w_{j-1} * (1 - (p+1)/j)

The weights decay like j^(-p-1), so keeping only the last L samples (the
short-memory principle) is a bounded error; the sum is an FIR filter, which
makes a streaming form with carried state exact: feeding a signal in blocks
gives the same output as feeding it at once.
"""
from __future__ import annotations

import numpy as np


def gl_weights(p: float, memory: int) -> np.ndarray:
    """Weights w_0..w_memory of the GL derivative of order ``p``."""
    if not 0.0 <= p <= 2.0:
        raise ValueError(f"fractional order p must be in [0, 2], got {p}")
    if memory < 0:
        raise ValueError(f"memory must be >= 0 samples, got {memory}")
    j = np.arange(1, memory + 1, dtype=float)
    return np.r_[1.0, np.cumprod(1.0 - (p + 1.0) / j)]


def fir(w: np.ndarray, x: np.ndarray, hist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """y[n] = sum_j w[j] x[n-j] over a block ``x`` whose predecessors are
    ``hist`` (the last len(w)-1 inputs, oldest first); returns (y, new hist).
    numpy's convolve, not scipy.signal: importing scipy.signal costs the
    daemon a second of start-up and tens of MB."""
    if len(w) == 1:
        return w[0] * x, hist
    full = np.concatenate([hist, x])
    return np.convolve(full, w, mode="valid"), full[len(full) - (len(w) - 1):]


def fracdiff(x: np.ndarray, p: float, memory: int, h: float = 1.0, axis: int = -1) -> np.ndarray:
    """Finite-memory GL derivative of order ``p`` of samples ``x`` spaced ``h``;
    samples before the start are taken as zero."""
    w = gl_weights(p, memory)
    x = np.asarray(x, dtype=float)
    return np.apply_along_axis(lambda v: np.convolve(v, w)[:len(v)], axis, x) * h ** (-p)


class GLDerivative:
    """Streaming GL derivative: call with consecutive blocks of one signal
    (or of several signals along axis 0 of a 2-D block, time on axis 1)."""

    def __init__(self, p: float, memory: int, h: float = 1.0, channels: int | None = None) -> None:
        self.p = float(p)
        self.memory = int(memory)
        self.h = float(h)
        self.weights = gl_weights(self.p, self.memory)
        self._scale = self.h ** (-self.p)
        self._channels = channels
        self.reset()

    def reset(self) -> None:
        n = max(len(self.weights) - 1, 0)
        self._zi = np.zeros((self._channels, n) if self._channels else n)

    def __call__(self, block: np.ndarray) -> np.ndarray:
        x = np.asarray(block, dtype=float)
        if len(self.weights) == 1:
            return x * self._scale
        if x.ndim == 1:
            y, self._zi = fir(self.weights, x, self._zi)
        else:
            out = [fir(self.weights, row, zi) for row, zi in zip(x, self._zi)]
            y = np.array([o[0] for o in out])
            self._zi = np.array([o[1] for o in out])
        return y * self._scale
