"""The turned surface a simulated cut leaves: roughness Ra and diameter along
the part, for comparing simulated parts with the paper's inspected ones.

Geometry: the tool advances ``feed`` per revolution along the axis z while
its tip sits at radial offset y(theta) from the nominal radius (y > 0 = tool
pushed away from the part, so more material is left; lathed.analysis.regen).
Its nose is a circle of radius r_eps.  At every angle phi the final surface
is the lower envelope of the nose circles of all passes:

    r(phi, z) = min_j [ y_j(phi) + r_eps - sqrt(r_eps^2 - (z - z_j(phi))^2) ]
    z_j(phi) = feed * (j + phi / 2 pi)

so feed marks, chatter marks and passes where the tool left the material
(whose circle lies above the surface) all come out of one envelope.  A stable
cut gives the classical Ra ~ feed^2 / (31.2 r_eps).

Ra is the arithmetic mean deviation from a least-squares line over
cut-off lengths (ISO 4287 style) along z, averaged over the angles.  The
diameter at z is the two-point crest diameter a micrometer reads (the highest
point within +-half an anvil width on each side), averaged around the part.
Everything is vectorised over (angle, z, pass); no asyncio.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class TurnedSurface:
    z_m: np.ndarray          # axial position from the start of the cut
    phi_rad: np.ndarray      # angles the profile was evaluated at
    r_m: np.ndarray          # (angles, z): radial deviation of the surface from nominal

    def ra_m(self, z_from_m: float | None = None, z_to_m: float | None = None,
             cutoff_m: float = 2.5e-3) -> float:
        """Arithmetic mean roughness over [z_from, z_to] (default: all of the
        cut), mean line fitted per ``cutoff_m`` length."""
        sel = np.ones(self.z_m.shape, bool)
        if z_from_m is not None:
            sel &= self.z_m >= z_from_m
        if z_to_m is not None:
            sel &= self.z_m <= z_to_m
        z = self.z_m[sel]
        r = self.r_m[:, sel]
        dz = z[1] - z[0] if len(z) > 1 else 0.0
        per = max(8, int(round(cutoff_m / dz))) if dz > 0 else len(z)
        n_seg = len(z) // per
        if n_seg == 0:
            raise ValueError(f"roughness needs at least one cut-off length ({cutoff_m * 1e3:g} mm) "
                             f"of surface, got {len(z) * dz * 1e3:.2f} mm")
        zs = z[:n_seg * per].reshape(n_seg, per)
        rs = r[:, :n_seg * per].reshape(r.shape[0], n_seg, per)
        # least-squares mean line per segment, vectorised
        zc = zs - zs.mean(axis=1, keepdims=True)
        rc = rs - rs.mean(axis=2, keepdims=True)
        slope = (rc * zc).sum(axis=2, keepdims=True) / (zc * zc).sum(axis=1)[None, :, None]
        dev = rc - slope * zc[None]
        return float(np.abs(dev).mean())

    def diameter_deviation_m(self, z_at_m: float, anvil_m: float = 1.0e-3) -> float:
        """Two-point crest diameter minus nominal, at axial position ``z_at_m``."""
        sel = np.abs(self.z_m - z_at_m) <= anvil_m / 2
        if not sel.any():
            raise ValueError(f"no surface at z = {z_at_m * 1e3:.2f} mm "
                             f"(cut spans {self.z_m[0] * 1e3:.2f}..{self.z_m[-1] * 1e3:.2f} mm)")
        crest = self.r_m[:, sel].max(axis=1)          # per angle
        half = len(crest) // 2
        # opposite angles pair up into two-point diameters
        return float((crest[:half] + crest[half:2 * half]).mean())


def turned_surface(y_m: np.ndarray, theta_rad: np.ndarray, feed_m_per_rev: float,
                   nose_radius_m: float = 0.8e-3, n_angles: int = 32,
                   dz_m: float | None = None) -> TurnedSurface:
    """Surface left by a tool path: ``y_m`` at cumulative spindle angles
    ``theta_rad`` (monotonic, from the simulator), constant feed per rev."""
    y = np.asarray(y_m, float)
    th = np.asarray(theta_rad, float)
    if y.shape != th.shape or y.size < 2:
        raise ValueError("tool displacement and spindle angle must be equal-length series")
    if not np.all(np.diff(th) > 0):
        raise ValueError("spindle angle must increase monotonically (spindle turning forward)")
    if not (feed_m_per_rev > 0 and nose_radius_m > feed_m_per_rev / 2):
        raise ValueError("feed must be > 0 and below the nose diameter, "
                         f"got feed {feed_m_per_rev * 1e3:g} mm, nose radius {nose_radius_m * 1e3:g} mm")
    if n_angles % 2:
        raise ValueError("n_angles must be even (two-point diameters pair opposite angles)")
    f, re = feed_m_per_rev, nose_radius_m
    th = th - th[0]
    n_rev = int(th[-1] // (2 * np.pi))
    if n_rev < 2:
        raise ValueError("the cut must last at least two spindle revolutions")
    phi = 2 * np.pi * np.arange(n_angles) / n_angles
    # tip offset at every (revolution, angle): Y[j, a]
    grid = 2 * np.pi * np.arange(n_rev)[:, None] + phi[None, :]
    Y = np.interp(grid, th, y)

    dz = dz_m if dz_m is not None else f / 40
    # evaluate where every z has passes on both sides
    z = np.arange(re, f * (n_rev - 1) - re, dz)
    if z.size == 0:
        raise ValueError("cut too short for the nose radius: no fully formed surface")
    span = int(np.ceil(re / f)) + 1
    m = np.arange(-span, span + 1)
    # nearest pass index at each (angle, z), then its neighbours
    j0 = np.floor(z[None, :] / f - phi[:, None] / (2 * np.pi)).astype(int)
    j = j0[:, :, None] + m[None, None, :]
    valid = (j >= 0) & (j < n_rev)
    jc = np.clip(j, 0, n_rev - 1)
    zj = f * (jc + phi[:, None, None] / (2 * np.pi))
    d = z[None, :, None] - zj
    inside = valid & (np.abs(d) < re)
    a_idx = np.broadcast_to(np.arange(n_angles)[:, None, None], jc.shape)
    h = Y[jc, a_idx] + re - np.sqrt(np.maximum(re * re - d * d, 0.0))
    r = np.where(inside, h, np.inf).min(axis=2)
    return TurnedSurface(z, phi, r)


def ideal_ra_m(feed_m_per_rev: float, nose_radius_m: float) -> float:
    """Ra of a perfectly stable cut, f^2 / (18*sqrt(3)*r_eps) (nose-circle
    marks; the usual f^2/(32 r) is the crude Rt/4 version)."""
    return feed_m_per_rev ** 2 / (18 * np.sqrt(3) * nose_radius_m)
