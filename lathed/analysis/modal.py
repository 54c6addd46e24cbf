"""Modal model of the tool/spindle structure, shared by the stability lobes
and the regenerative cutting simulator so both agree on one convention.

Convention (turning, one chip-thickness direction): the cutting force acts
along the surface normal, the chip thickness is measured along it too, and a
mode vibrating at angle ``theta_deg`` from that normal contributes
``u = cos(theta)**2`` of its compliance (force projected onto the mode, the
mode's motion projected back onto the normal).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Mode:
    fn_hz: float        # natural frequency
    zeta: float         # damping ratio (0 < zeta < 1)
    k_n_per_m: float    # modal stiffness
    theta_deg: float = 0.0

    def __post_init__(self) -> None:
        # inf passes the range checks below and nan theta passes none of them: lobes of nan
        for name, what in (("fn_hz", "natural frequency FN_HZ"), ("zeta", "damping ratio ZETA"),
                           ("k_n_per_m", "stiffness K_N_PER_M"), ("theta_deg", "angle THETA_DEG")):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"mode {what} must be a finite number, got {getattr(self, name)}")
        if not self.fn_hz > 0:
            raise ValueError(f"mode natural frequency must be > 0 Hz, got {self.fn_hz}")
        if not 0 < self.zeta < 1:
            raise ValueError(f"mode damping ratio must be in (0, 1), got {self.zeta}")
        if not self.k_n_per_m > 0:
            raise ValueError(f"mode stiffness must be > 0 N/m, got {self.k_n_per_m}")

    @property
    def u(self) -> float:
        """Directional factor onto the chip-thickness direction."""
        return math.cos(math.radians(self.theta_deg)) ** 2

    @property
    def wn(self) -> float:
        return 2 * math.pi * self.fn_hz

    @property
    def mass_kg(self) -> float:
        return self.k_n_per_m / self.wn**2

    def frf(self, f_hz: np.ndarray | float) -> np.ndarray:
        """Receptance (m/N) of the mode along its own direction."""
        r = np.asarray(f_hz, dtype=float) / self.fn_hz
        return 1.0 / (self.k_n_per_m * (1 - r**2 + 2j * self.zeta * r))


def oriented_frf(modes: list[Mode] | tuple[Mode, ...], f_hz: np.ndarray | float) -> np.ndarray:
    """Oriented receptance along the chip-thickness direction: sum of u_i*H_i."""
    return sum(m.u * m.frf(f_hz) for m in modes)


def parse_mode(text: str) -> Mode:
    """Parse ``FN,ZETA,K[,THETA_DEG]`` as used on the command line and in config."""
    parts = [p.strip() for p in text.split(",")]
    if len(parts) not in (3, 4):
        raise ValueError(f"mode {text!r}: expected FN_HZ,ZETA,K_N_PER_M[,THETA_DEG]")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise ValueError(f"mode {text!r}: every field must be a number") from None
    try:
        return Mode(*values)
    except ValueError as e:   # name the mode among several
        raise ValueError(f"mode {text!r}: {str(e).removeprefix('mode ')}") from None
