"""What is left in a thermal model's residual: noise, a spectral line, sudden steps. See docs/thermal.md."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from lathed.analysis.forward import rmse

if TYPE_CHECKING:
    from lathed.analysis.thermal.data import ThermalData


@dataclass
class ResidualReport:
    structured: bool
    note: str
    noise_um: float
    lag1: float
    period_s: float | None = None
    sensor: str | None = None       # an input sensor oscillating at that period
    steps_h: list[float] = field(default_factory=list)   # sudden steps in the residual (h into the run)



def spectral_line(t_s: np.ndarray, x: np.ndarray, min_share: float = 0.2) -> tuple[float | None, float]:
    """The period of a spectral line in ``x`` (sampled at ``t_s``) and the
    share of the variance it carries; None when there is none. A line stands
    above the bins either side of it; a slow trend's spectrum only falls
    from the slowest bin, so it is never taken for a period (it used to be
    called one of a third of the run)."""
    x = np.asarray(x, float)
    n = len(x)
    if n < 32:
        return None, 0.0
    dt = float(np.median(np.diff(t_s)))
    tt = np.arange(n) * dt
    # A quadratic off: a warm-up's curve is trend, not a cycle.
    det = x - np.polyval(np.polyfit(tt / tt[-1], x, 2), tt / tt[-1])
    p = np.abs(np.fft.rfft(det * np.hanning(n))) ** 2
    f = np.fft.rfftfreq(n, dt)
    if len(p) < 12 or p[1:].sum() <= 0:
        return None, 0.0
    def stands_out(k: int) -> bool:
        sides = np.r_[p[max(k - 5, 1):k - 2], p[k + 3:k + 6]]
        return bool(len(sides) and p[k] > 10 * sides.max() and p[k] > 20 * np.median(p[1:]))

    if min_share > 0:
        k = 4 + int(np.argmax(p[4:]))           # four cycles in the run at least
    else:   # any line, however small beside the rest: the strongest that stands out
        peaks = [k for k in range(4, len(p) - 1) if p[k] >= p[k - 1] and p[k] >= p[k + 1] and stands_out(k)]
        k = max(peaks, key=lambda j: p[j]) if peaks else 4
    band = p[k - 1:k + 2].sum()
    share = float(band / p[1:].sum())
    if share > min_share and stands_out(k):
        # the peak between bins: a parabola through the log power
        a, b, c = np.log(p[k - 1:k + 2] + 1e-300)
        off = 0.5 * (a - c) / (a - 2 * b + c) if (a - 2 * b + c) != 0 else 0.0
        return 1.0 / ((k + float(np.clip(off, -0.5, 0.5))) * (f[1] - f[0])), share
    return None, share


def residual_structure(t_s: np.ndarray, e: np.ndarray, data: ThermalData | None = None) -> ResidualReport:
    """Is there more in the residual than noise? Compares its rms with the
    sample-to-sample scatter (which smooth structure does not inflate) and
    looks for a spectral line; with ``data``, says which input sensor
    oscillates at the same period, if one does."""
    e = np.asarray(e, float) - np.mean(e)
    n = len(e)
    if n < 16:
        return ResidualReport(False, f"only {n} rows: too few to judge the residual", rmse(e), 0.0)
    d = np.diff(e)
    noise = float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2))
    total = rmse(e)
    lag1 = float((e[1:] @ e[:-1]) / (e @ e)) if total > 0 else 0.0
    period, share = spectral_line(t_s, e)
    sensor = None
    if period is not None and data is not None:
        span = float(t_s[-1] - t_s[0]) or 1.0
        for s in data.sensors:
            ps, _ = spectral_line(data.time_s, data.rise(s))
            if ps is not None and abs(1 / ps - 1 / period) * span <= 1.5:   # within 1.5 bins
                sensor = s
                break
    steps = _steps(t_s, e, noise)
    ratio = total / noise if noise > 0 else (1.0 if total < 1e-12 else math.inf)
    structured = ratio > 1.3 or period is not None or bool(steps)
    if not structured:
        note = (f"residual looks like measurement noise: rms {total:.2f} µm vs {noise:.2f} µm "
                f"sample-to-sample, lag-1 autocorrelation {lag1:.2f}")
    else:
        note = (f"structure left that no candidate explains: residual rms {total:.2f} µm is "
                f"{ratio:.1f}x the sample-to-sample noise ({noise:.2f} µm), lag-1 autocorrelation {lag1:.2f}")
        if period is not None:
            note += f"; a periodicity of {period / 60:.1f} min carries {100 * share:.0f}% of its variance"
            if sensor is not None:
                note += f", the period at which {sensor} oscillates"
        if steps:
            h = [round((t_s[k] - t_s[0]) / 3600.0, 2) for k, _ in steps]
            size = float(np.median([abs(d) for _, d in steps]))
            note += (f"; {len(steps)} sudden step(s) of ~{size:.1f} µm with no temperature change, at "
                     f"{', '.join(f'{v:g}' for v in h[:6])}{' ...' if len(h) > 6 else ''} h")
            if data is not None and data.rpm is None:
                note += " (speed or program changes? with a spindle_rpm column they are fitted as speed steps)"
    rep = ResidualReport(structured, note, noise, lag1, period, sensor)
    rep.steps_h = [float((t_s[k] - t_s[0]) / 3600.0) for k, _ in steps]
    return rep


def _steps(t_s: np.ndarray, e: np.ndarray, noise: float) -> list[tuple[int, float]]:
    """Sudden steps in a residual: where the mean of the next few rows differs
    from that of the previous few by much more than the noise, and more than
    a smooth curve moves over so few rows."""
    n = len(e)
    w = max(5, n // 200)
    if n < 4 * w or noise <= 0:
        return []
    cs = np.concatenate([[0.0], np.cumsum(e)])
    k = np.arange(w, n - w + 1)
    d = (cs[k + w] - cs[k]) / w - (cs[k] - cs[k - w]) / w
    # a smooth curve moves about as much from one window to the next as over
    # the two windows before: a step stands out from both neighbours
    big = np.abs(d) > max(6.0 * noise * math.sqrt(2.0 / w), 3.0 * noise)
    out: list[tuple[int, float]] = []
    for i in np.flatnonzero(big):
        lo, hi = max(i - w, 0), min(i + w + 1, len(d))
        if abs(d[i]) < np.abs(d[lo:hi]).max():
            continue
        side = np.r_[np.abs(d[max(i - 3 * w, 0):max(i - 2 * w, 0)]), np.abs(d[i + 2 * w:i + 3 * w])]
        if len(side) and abs(d[i]) > 3 * side.max():
            out.append((int(k[i]), float(d[i])))
    return out


