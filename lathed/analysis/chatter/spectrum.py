"""Small spectral helpers the chatter detectors share (numpy only: the daemon does not import scipy)."""
from __future__ import annotations

from functools import lru_cache

import numpy as np

try:    # numpy 2's rfft kernels (gufuncs), which np.fft.rfft wraps; numpy 1 has none
    from numpy.fft import _pocketfft_umath as _pfu
except ImportError:
    _pfu = None


def _kernels_agree() -> bool:
    # a private module: used only while it gives np.fft.rfft's answer, bit for bit (a numpy
    # that changed it falls back to the public call, never to a wrong spectrum)
    x = np.random.default_rng(0).standard_normal(37)
    try:
        return all(np.array_equal(
            (_pfu.rfft_n_even if nf % 2 == 0 else _pfu.rfft_n_odd)(x, 1, out=np.empty(nf // 2 + 1, np.complex128)),
            np.fft.rfft(x, nf)) for nf in (37, 64, 75))
    except Exception:
        return False


if _pfu is not None and not _kernels_agree():
    _pfu = None


def rfft(x: np.ndarray, nf: int) -> np.ndarray:
    """np.fft.rfft(x, nf) of a 1-D float64 array at most nf long, bit for bit: numpy 2's own
    kernel called without the wrapper, whose checks cost a fifth of a window's FFT."""
    if _pfu is None or len(x) > nf:
        return np.fft.rfft(x, nf)
    kernel = _pfu.rfft_n_even if nf % 2 == 0 else _pfu.rfft_n_odd
    return kernel(x, 1, out=np.empty(nf // 2 + 1, np.complex128))


def median_abs(x: np.ndarray) -> float:
    """np.median(np.abs(x)), bit for bit, without np.median's checks and copies: the
    windowed detectors' largest cost (a third of sync_cusum's time went to its wrappers)."""
    a = np.abs(x)
    n = len(a)
    k = n // 2
    a.partition(k)
    if n % 2:
        return float(a[k])
    # the one below the middle is the largest of those before it: a pass, not a second selection
    return float((np.maximum.reduce(a[:k]) + a[k]) / 2)


def median(a: np.ndarray) -> float:
    """np.median of a 1-D float array, bit for bit (NaN if any element is), without its
    checks and copies: ``a`` is partitioned in place (a spectrum's band ratios each window)."""
    n = len(a)
    if n == 0:
        return float("nan")
    k = n // 2
    if n % 2:
        a.partition((k, n - 1))           # the last: NaN sorts there, as np.median checks
        m = float(a[k])
    else:
        a.partition((k - 1, k, n - 1))
        m = float((a[k - 1] + a[k]) / 2)
    return float("nan") if a[n - 1] != a[n - 1] else m


@lru_cache(maxsize=64)
def hann(n: int) -> np.ndarray:
    """np.hanning(n), made once per window length (it cost as much as the FFT it weights);
    read-only, shared. A window's length follows the speed: the last 64 are kept."""
    w = np.hanning(n)
    w.flags.writeable = False
    return w


def spectral_peak_hz(x: np.ndarray, rate: float, fmin: float, fmax: float) -> float | None:
    n = len(x)
    if n < 8:
        return None
    nf = fast_len(n)
    lo, hi = _band_bins(nf, rate, fmin, fmax)
    if hi - lo < 3:
        return None
    r = rfft(x * hann(n), nf)
    # the magnitudes of the band and a bin either side (the parabola's), not of every bin
    a0, top = max(lo - 1, 0), len(r) - 1
    spec = np.abs(r[a0:min(hi + 1, len(r))])
    i = lo + int(spec[lo - a0:hi - a0].argmax())      # the method: np.argmax's wrapper spared
    if 0 < i < top:
        # the three logs as Python floats: the parabola's arithmetic the same, without numpy scalars
        a, b, c = np.log(spec[i - 1 - a0:i + 2 - a0] + 1e-300).tolist()
        den = a - 2 * b + c
        off = 0.5 * (a - c) / den if den < 0 else 0.0
        return float((i + off) * rate / nf)
    return float(np.float64(i) * rate / nf)


@lru_cache(maxsize=256)
def _band_bins(nf: int, rate: float, fmin: float, fmax: float) -> tuple[int, int]:
    """The bins lo..hi (hi excluded) of an nf-point rfft within fmin..fmax, once per length."""
    f = np.arange(nf // 2 + 1) * rate / nf
    band = np.flatnonzero((f >= fmin) & (f <= min(fmax, rate / 2)))
    return (int(band[0]), int(band[-1]) + 1) if band.size else (0, 0)


@lru_cache(maxsize=256)
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
