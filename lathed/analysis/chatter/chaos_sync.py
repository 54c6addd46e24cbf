"""The paper's chatter detector: fractional-order Lorenz chaos synchronisation.

Master and slave are fed from the signal (PAPER.md, Loop 1, our reading):
the slave gets three consecutive samples of the current signal, the master
the same three samples one spindle revolution earlier (or, with a reference
recording, nothing changes here: the reference only sets the baseline).  The
dynamic error is then the revolution difference d[n] = x[n] - x[n - rev],
small for anything that repeats every revolution and large for chatter.

    e~  = GL derivative of order p of d (finite memory L), divided by the
          baseline rms of e~ so the features do not depend on the gain
    e   = (e~[n], e~[n+1], e~[n+2])
    phi1 = -a e1 + a e2
    phi2 =  b e1 - e2 - e1 e3
    phi3 = -c e3 + e1 e2

The (phi1, phi2) scatter is the chaos eye.  Its size about the origin,
R = sqrt(mean(phi1^2 + phi2^2)) (spread and centroid offset together), over
the baseline R is the chatter index.  The bilinear terms grow with the square
of the amplitude, which is what sharpens chatter against a stable cut.
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

from lathed.analysis.chatter.base import RevolutionDetector
from lathed.analysis.chatter.eye import eye_features, eye_radius
from lathed.analysis.fracdiff import fir, gl_weights


class ChaosSyncDetector(RevolutionDetector):
    name = "chaos_sync"
    OWN_EYE = True
    RAW_POWER = 2.0   # the eye's radius is bilinear in the error
    PARAMS = {
        "a": (10.0, 0.01, 1000.0, "Lorenz a (the paper prints 28; chaotic set is 10)"),
        "b": (28.0, 0.01, 1000.0, "Lorenz b (the paper prints 10; chaotic set is 28)"),
        "c": (8.0 / 3.0, 0.01, 100.0, "Lorenz c (the paper prints 2.66)"),
        "p": (0.5, 0.0, 1.0, "Grünwald–Letnikov order of the error derivative (0 = none)"),
        "memory": (64, 0, 4096, "GL memory L in samples (short-memory principle)"),
        "threshold": (1.8, 1.05, 1000.0, "eye-size index above which a window counts as chatter"),
        "eye_windows": (8, 1, 1000, "recent windows whose chaos-eye points are kept for plotting"),
        "eye_points": (256, 16, 100000, "points kept per window for plotting"),
    }

    def _reset_extra(self) -> None:
        self._w = gl_weights(self.params["p"], int(self.params["memory"]))
        self._zi = np.zeros(len(self._w) - 1)
        self._history()
        if self._fixed_baseline is None:
            self.sigma = None
        self._sig_learn: list[float] = []
        self._e_learn: list[np.ndarray] = []
        self.eye: deque[tuple[float, np.ndarray, np.ndarray]] = deque(maxlen=int(self.params["eye_windows"]))
        self.eye_baseline: tuple[np.ndarray, np.ndarray] | None = None

    def _lead(self) -> int:
        return int(self.params["memory"])

    def _history(self) -> dict[str, np.ndarray]:
        if not hasattr(self, "_e"):
            self._e = np.empty_like(self._x)
        return {**super()._history(), "_e": self._e}

    def _new_samples(self, start: int, end: int) -> None:
        # the GL derivative of the revolution difference, once per sample, state carried
        d = self._d[start:end]
        if not np.isfinite(d).all():     # NaN before a revolution of history; nan_to_num costs 20 us
            d = np.nan_to_num(d)
        self._e[start:end], self._zi = fir(self._w, d, self._zi)

    def _error(self, start: int, end: int) -> np.ndarray:
        return self._e[start:end]

    def _measure(self, start: int, end: int, rpm: float) -> float:
        e = self._error(start, end)
        rms = math.sqrt(float(e @ e) / len(e)) or 1e-300
        if self.sigma is None:
            # still learning: normalise by what has been seen so far
            self._sig_learn.append(rms)
            self._e_learn.append(e.copy())
            sigma = float(np.median(self._sig_learn))
        else:
            sigma = self.sigma
        # the eye needs only phi1, phi2 (phi3 is not computed)
        phi1, phi2 = eye_features(e * (1.0 / sigma), self.params["a"], self.params["b"])
        r = math.sqrt((float(phi1 @ phi1) + float(phi2 @ phi2)) / len(phi1))
        step = max(1, len(phi1) // int(self.params["eye_points"]))
        pts = (phi1[::step].copy(), phi2[::step].copy())
        t_s = (self._total - (self._n - end)) / self.rate
        self.eye.append((t_s, *pts))
        if self.sigma is None and self.eye_baseline is None:
            self.eye_baseline = pts
        return r

    def _on_learned(self) -> None:
        # scale and eye size from the same low quantile of the learning windows,
        # so chatter already growing at the start of the cut does not set them
        q = self.params["learn_quantile"]
        self.sigma = float(np.quantile(self._sig_learn, q)) or 1e-300
        a, b = self.params["a"], self.params["b"]
        radii = []
        for e in self._e_learn:
            phi1, phi2 = eye_features(e / self.sigma, a, b)
            radii.append(eye_radius(phi1, phi2))
        self.baseline = max(float(np.quantile(radii, q)), 1e-300)
        self._e_learn = []

    def _ref_hook(self) -> None:
        # a reference is a stable cut throughout: its median scale and eye size
        self._fixed_sigma = self.sigma = float(np.median(self._sig_learn)) or 1e-300
        a, b = self.params["a"], self.params["b"]
        radii = [eye_radius(*eye_features(e / self.sigma, a, b)) for e in self._e_learn]
        self.set_baseline(max(float(np.median(radii)), 1e-300))
        self._e_learn = []

    def reset(self) -> None:  # keep a reference's sigma with its baseline
        fixed = getattr(self, "_fixed_sigma", None)
        super().reset()
        if self._fixed_baseline is not None and fixed is not None:
            self.sigma = fixed

    def eye_points(self) -> tuple[np.ndarray, np.ndarray]:
        """(phi1, phi2) of the recent windows, concatenated, for the chaos-eye plot."""
        if not self.eye:
            return np.empty(0), np.empty(0)
        return (np.concatenate([p[1] for p in self.eye]), np.concatenate([p[2] for p in self.eye]))

    def eye_views(self):
        """This detector's own eye: the recent windows' points and the cut's first."""
        return self.eye_points(), self.eye_baseline
