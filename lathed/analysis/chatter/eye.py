"""The paper's chaos eye: Lorenz error-dynamics features of a revolution difference
(PAPER.md, Loop 1; docs/chatter.md).  Drawn for the operator whatever detector decides."""
from __future__ import annotations

import math

import numpy as np

from lathed.analysis.fracdiff import fir, gl_weights


def eye_features(e: np.ndarray, a: float = 10.0, b: float = 28.0) -> tuple[np.ndarray, np.ndarray]:
    """(phi1, phi2), the chaos-eye coordinates, from a normalised error sequence."""
    e1, e2, e3 = e[:-2], e[1:-1], e[2:]
    return a * (e2 - e1), b * e1 - e2 - e1 * e3


def lorenz_features(e: np.ndarray, a: float = 10.0, b: float = 28.0, c: float = 8.0 / 3.0) -> np.ndarray:
    """phi (n-2, 3) from a normalised error sequence: e_i are three consecutive samples."""
    phi1, phi2 = eye_features(e, a, b)
    e1, e2, e3 = e[:-2], e[1:-1], e[2:]
    return np.stack([phi1, phi2, -c * e3 + e1 * e2], axis=1)


def eye_of_difference(d: np.ndarray, sigma: float | None = None, p: float = 0.5, memory: int = 64,
                      a: float = 10.0, b: float = 28.0) -> tuple[np.ndarray, np.ndarray, float]:
    """The chaos eye (phi1, phi2) of a stretch of revolution difference d, with
    the default detector's constants, and the scale it was normalised by (the
    error's rms when ``sigma`` is None): for drawing the paper's graph beside
    a detector that does not compute it.  The first ``memory`` samples only
    warm the GL filter up."""
    d = np.nan_to_num(np.asarray(d, dtype=float))
    w = gl_weights(p, memory)
    e = fir(w, d, np.zeros(len(w) - 1))[0][memory:]
    if sigma is None:
        sigma = math.sqrt(float(e @ e) / max(len(e), 1)) or 1e-300
    phi1, phi2 = eye_features(e / sigma, a, b)
    return phi1, phi2, sigma


def eye_radius(phi1: np.ndarray, phi2: np.ndarray) -> float:
    return float(np.sqrt(np.mean(phi1 * phi1 + phi2 * phi2)))
