"""Spindle speed variation (SSV): the commanded speed profile.

The speed is modulated around its mean n0 by a sine, triangle or square wave
of amplitude ratio RVA = amplitude / n0 and period P.  The paper's drive could
not follow its modulation, so the profile here is shaped to what the spindle
can do: its slope never exceeds the acceleration limit a (r/min per s).

  sine      peak slope 2*pi*RVA*n0/P  -> amplitude reduced until it fits
  triangle  slope 4*RVA*n0/P          -> amplitude reduced until it fits
  square    edges become ramps of slope a (a trapezoid); if the ramps take
            more than half a period it degenerates to the fitting triangle

Reducing the amplitude keeps the period (which sets how fast the regenerative
phase is disturbed) and the mean speed (which sets the removal rate), and the
profile stays a smooth function of time, evaluated vectorised.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

KINDS = ("sine", "triangle", "square")


@dataclass(frozen=True)
class SpeedVariation:
    kind: str
    amplitude_ratio: float      # RVA, amplitude / mean speed
    period_s: float
    accel_rpm_per_s: float      # spindle acceleration limit

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"speed variation kind {self.kind!r}: expected one of {', '.join(KINDS)}")
        if not 0 < self.amplitude_ratio < 1:
            raise ValueError(f"speed variation amplitude ratio must be in (0, 1), got {self.amplitude_ratio}")
        if not self.period_s > 0:
            raise ValueError(f"speed variation period must be > 0 s, got {self.period_s}")
        if not self.accel_rpm_per_s > 0:
            raise ValueError(f"spindle acceleration limit must be > 0 r/min/s, got {self.accel_rpm_per_s}")

    def required_accel(self, n0: float) -> float:
        """Peak slope (r/min per s) of the unlimited modulation; inf for square."""
        amp = self.amplitude_ratio * n0
        if self.kind == "sine":
            return 2 * np.pi * amp / self.period_s
        if self.kind == "triangle":
            return 4 * amp / self.period_s
        return float("inf")

    def achieved_amplitude_ratio(self, n0: float) -> float:
        """Amplitude ratio of the commanded profile after the acceleration limit."""
        a, p = self.accel_rpm_per_s, self.period_s
        if self.kind == "sine":
            cap = a * p / (2 * np.pi * n0)
        else:   # triangle, and square whose ramps fill the half period
            cap = a * p / (4 * n0)
        return min(self.amplitude_ratio, cap)

    def profile(self, t_s: np.ndarray | float, n0: float) -> np.ndarray:
        """Commanded speed (r/min) at times ``t_s`` (s) from the start of the
        modulation, around the mean speed ``n0``."""
        if not n0 > 0:
            raise ValueError(f"mean spindle speed must be > 0 r/min, got {n0}")
        t = np.asarray(t_s, dtype=float)
        phase = np.mod(t / self.period_s, 1.0)
        amp = self.achieved_amplitude_ratio(n0) * n0
        if self.kind == "sine":
            return n0 + amp * np.sin(2 * np.pi * phase)
        # triangle starting upward from the mean, like the sine
        tri = 1 - np.abs(4 * np.mod(phase + 0.75, 1.0) - 2)
        if self.kind == "triangle":
            return n0 + amp * tri
        # square: ramps of slope a, clipped at +-amplitude
        ramp_amp = self.amplitude_ratio * n0
        if amp < ramp_amp:       # ramps fill the half period: the fitting triangle
            return n0 + amp * tri
        # triangle of slope a around the same crossings, clipped: a trapezoid
        steep = self.accel_rpm_per_s * self.period_s / 4
        return n0 + np.clip(steep * tri, -ramp_amp, ramp_amp)


def ramp(n_from: float, n_to: float, accel_rpm_per_s: float, t_s: np.ndarray | float) -> np.ndarray:
    """Speed of a spindle stepping from ``n_from`` to ``n_to`` at its
    acceleration limit, ``t_s`` seconds after the command."""
    t = np.maximum(np.asarray(t_s, dtype=float), 0.0)
    step = n_to - n_from
    return n_from + np.sign(step) * np.minimum(abs(step), accel_rpm_per_s * t)


def ramp_time_s(n_from: float, n_to: float, accel_rpm_per_s: float) -> float:
    """Time the spindle needs to reach ``n_to`` from ``n_from``."""
    return abs(n_to - n_from) / accel_rpm_per_s
