"""Small spectral helpers the chatter detectors share (numpy only: the daemon does not import scipy)."""
from __future__ import annotations

import numpy as np

def median_abs(x: np.ndarray) -> float:
    """np.median(np.abs(x)), bit for bit, without np.median's checks and copies: the
    windowed detectors' largest cost (a third of sync_cusum's time went to its wrappers)."""
    a = np.abs(x)
    n = len(a)
    k = n // 2
    if n % 2:
        a.partition(k)
        return float(a[k])
    a.partition((k - 1, k))
    return float((a[k - 1] + a[k]) / 2)


def spectral_peak_hz(x: np.ndarray, rate: float, fmin: float, fmax: float) -> float | None:
    n = len(x)
    if n < 8:
        return None
    nf = fast_len(n)
    spec = np.abs(np.fft.rfft(x * np.hanning(n), nf))
    f = np.arange(len(spec)) * rate / nf
    band = np.flatnonzero((f >= fmin) & (f <= min(fmax, rate / 2)))
    if band.size < 3:
        return None
    i = int(band[np.argmax(spec[band])])
    if 0 < i < len(spec) - 1:
        a, b, c = np.log(spec[i - 1:i + 2] + 1e-300)
        den = a - 2 * b + c
        off = 0.5 * (a - c) / den if den < 0 else 0.0
        return float((i + off) * rate / nf)
    return float(f[i])


def fast_len(n: int) -> int:
    """The smallest 2^a 3^b 5^c >= n: an FFT length numpy's pocketfft does fast
    (scipy.fft would do, but costs the daemon a quarter second to import)."""
    best = 1 << max(n - 1, 0).bit_length()
    p5 = 1
    while p5 < best:
        p35 = p5
        while p35 < best:
            m = p35
            while m < n:
                m *= 2
            best = min(best, m)
            p35 *= 3
        p5 *= 5
    return best
