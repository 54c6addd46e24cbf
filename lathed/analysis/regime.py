"""One linear regime of the regenerative simulator (lathed.analysis.regen): in or out of the cut,
its zero-order-hold response in closed form. docs/simulator.md."""
from __future__ import annotations

import numpy as np

_KEEP_POWERS = 1024    # lam^k kept per regime up to this k: 64 kB with two modes


class Regime:
    """Diagonalised ZOH discretisation of x' = A x + B*g*w.

    From the eigen-decomposition A = V diag(s) V^-1 (damped modes: distinct,
    non-zero s): A_d = V diag(e^(s dt)) V^-1 and B_d = V diag((e^(s dt) - 1)/s)
    V^-1 B g, the same as expm's ZOH at a fraction of its cost (a regime is
    built per flank damping level)."""

    def __init__(self, a: np.ndarray, bvec: np.ndarray, gain: float, dt: float) -> None:
        s, v = np.linalg.eig(a)
        self.loglam = s.astype(complex) * dt
        self.v = v
        self.vinv = np.linalg.inv(v)
        self.beta = np.expm1(self.loglam) / s * (self.vinv @ bvec) * gain
        # the closed form below divides by lam**k; keep |lam|**-k under e**30
        # so no precision is lost
        self.safe_len = int(min(1 << 20, 30.0 / max(1e-12, float(np.max(np.abs(self.loglam.real))))))
        self._powers = np.ones((len(s), 1), dtype=complex)

    def powers(self, m: int) -> np.ndarray:
        """lam^k for k = 0..m, each mode a row. The last ones (up to _KEEP_POWERS) are kept: a
        cut asks for the same chunk lengths block after block and the complex exp was half of
        ``response``'s time; a kept entry is the same exp of the same product."""
        if m < self._powers.shape[1]:
            return self._powers[:, :m + 1]
        p = np.exp(self.loglam[:, None] * np.arange(m + 1)[None, :])
        if m < _KEEP_POWERS:
            p.flags.writeable = False
            self._powers = p
        return p

    def response(self, z0: np.ndarray, w: np.ndarray | None, m: int) -> np.ndarray:
        """Modal states z[:, 0..m] from z0 with input w[0..m-1] (None: free).

        z[k] = lam^k z0 + sum_{i<k} lam^(k-1-i) beta w[i]
             = lam^k (z0 + sum_{i<k} beta w[i] lam^-(i+1)),
        all modes at once instead of one recursive filter per mode."""
        p = self.powers(m)
        if w is None:
            return z0[:, None] * p
        acc = np.empty_like(p)
        acc[:, 0] = z0
        np.cumsum(self.beta[:, None] * w[None, :] / p[:, 1:], axis=1, out=acc[:, 1:])
        acc[:, 1:] += z0[:, None]
        return acc * p
