"""Process damping: the tool's flank wear land ploughing the wavy surface.

Behind the cutting edge the flank wear land (width L = VB along the cutting
direction, residual clearance gamma to the cut surface) rides on the surface
the edge has just left.  Where that surface rises towards the land faster
than the clearance allows, the land indents it, with a force proportional
to the volume of material displaced (Wu 1989; Chiou & Liang 1998; Ahmadi &
Ismail 2010, 2011):

    F = K_sp * b * int_0^L max(0, u(t) - u(t - x/V) - x tan(gamma)) dx

u = tool motion into the part (u = -y in lathed.analysis.regen), V the
cutting speed, b the width of cut.  With the land short against the chatter
wavelength (L << V / f_chatter: 0.2 mm against 3.6 mm on a 30 mm bar at
1500 r/min and 650 Hz; at 500 r/min, 1.2 mm, the indented area
is overstated by about 10 %), u(t) - u(t - x/V) ~ x u'/V and

    F = K_sp b L^2/2 * max(0, u'/V - tan(gamma))

a one-sided dead-zone damper: it pushes the tool out of the part while the
tool moves into it faster than V tan(gamma).  For a harmonic vibration
(u' / V = a cos phi, a = peak surface slope) the describing function (mean
plus fundamental, as the harmonic-balance papers above use it) is

    F ~ F_dc - c_eq y'
    c_eq = K_sp b L^2 / (2V) * N(r),     r = a / tan(gamma)
    N(r) = (phi0 - sin(phi0) cos(phi0)) / pi,   phi0 = arccos(1/r)   (0 for r <= 1)
    F_dc = K_sp b L^2 / 2 * a / pi * (sin(phi0) - phi0 cos(phi0))

N rises from 0 at the threshold to 1/2, so c_eq grows with the amplitude up
to c_max = K_sp b L^2 / (4V).  Small vibrations never reach the threshold, so
the lobe limit is unchanged; a cut just above it chatters until c_eq supplies
the damping it lacks, and stops growing there (finite-amplitude stability:
mild chatter).  A cut that needs more than c_max chatters until the tool
leaves the cut, as without the land.  c_max falls as 1/V: process damping is
a low-speed effect.  Pure numpy, no asyncio.
"""
from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class FlankWear:
    """A worn flank land and the material it ploughs.

    ``land_mm``: wear land width VB, 0.05-0.6 mm (ISO 3685's end-of-life
    criterion is VB = 0.3 mm).  ``clearance_deg``: the land's residual
    clearance to the cut surface, 0-10 deg; a land worn by rubbing lies
    almost parallel to the surface (0-0.5 deg), and it sets the surface slope
    (chatter velocity over cutting speed) at which ploughing starts, hence
    the amplitude at which near-limit chatter saturates.  ``k_sp_n_per_m3``:
    indentation coefficient, force per volume of material displaced under
    the land, 1e12-1e15 N/m^3 (about 4e13 for carbon steel, Wu 1989).
    """
    land_mm: float = 0.2
    clearance_deg: float = 0.2
    k_sp_n_per_m3: float = 4.0e13

    def __post_init__(self) -> None:
        if not 0.01 <= self.land_mm <= 1.0:
            raise ValueError(f"flank wear land must be in [0.01, 1] mm, got {self.land_mm}")
        if not 0.0 <= self.clearance_deg <= 10.0:
            raise ValueError(f"flank land clearance must be in [0, 10] deg, got {self.clearance_deg}")
        if not 1e11 <= self.k_sp_n_per_m3 <= 1e16:
            raise ValueError(f"indentation coefficient must be in [1e11, 1e16] N/m^3, got {self.k_sp_n_per_m3}")

    def c_max(self, b_m: float, v_m_s: float) -> float:
        """Saturated equivalent damping K_sp b L^2 / (4V), N s/m."""
        return self.k_sp_n_per_m3 * b_m * (self.land_mm * 1e-3) ** 2 / (4.0 * v_m_s)

    def equivalent(self, b_m: float, v_m_s: float, vel_peak_m_s: float) -> tuple[float, float]:
        """(c_eq N s/m, F_dc N) for a vibration of peak velocity ``vel_peak_m_s``
        along the surface normal at cutting speed ``v_m_s``."""
        a = vel_peak_m_s / v_m_s                  # peak surface slope under the land
        tan_g = math.tan(math.radians(self.clearance_deg))
        if a <= tan_g or a <= 0.0:
            return 0.0, 0.0
        phi0 = math.acos(tan_g / a)
        s, c = math.sin(phi0), math.cos(phi0)
        k = self.k_sp_n_per_m3 * b_m * (self.land_mm * 1e-3) ** 2 / 2.0
        return k / v_m_s * (phi0 - s * c) / math.pi, k * a / math.pi * (s - phi0 * c)
