"""The chatter detectors by name, and building one from its parameters (docs/chatter.md)."""
from __future__ import annotations

from typing import Any, Callable

from lathed.analysis.chatter.base import BASE_PARAMS
from lathed.analysis.chatter.chaos_sync import ChaosSyncDetector
from lathed.analysis.chatter.detectors import SpectralRatioDetector, SyncCusumDetector, SyncResidualDetector

Factory = Callable[..., Any]


DETECTORS: dict[str, Factory] = {
    "sync_residual": SyncResidualDetector,
    "sync_cusum": SyncCusumDetector,
    "spectral_ratio": SpectralRatioDetector,
    "chaos_sync": ChaosSyncDetector,
}

# Chosen from bench/bench_chatter.py on stable cutting that wanders as a real
# cut does (regen.Wander): sync_cusum misses none of the 20 chatter cases
# (chaos_sync misses 3 mild ones) and alarms on no stable or trap case
# (chaos_sync on one trap), median delay 2.0 revolutions (chaos_sync 5.9);
# on the real recordings it finds both chatter files and no stable one; in
# the closed loop (bench/bench_loop.py) it alarms 5.9-7.3 revolutions after
# chatter is visible, chaos_sync 13.6-25.4.  Its false alarms in the closed
# loop came at the end of stable cuts whose baseline was learned after a
# speed change at entry (the tool's release rings the structure: jump_ratio).
# See docs/benchmarks.md, chatter detectors.
DEFAULT_DETECTOR = "sync_cusum"


def make_detector(name: str, rate_hz: float, extra: dict[str, Factory] | None = None, **params: Any):
    """Build detector ``name``; ``extra`` (from the lathed_chatter_detectors
    hook) is merged over the built-ins."""
    table = {**DETECTORS, **(extra or {})}
    if name not in table:
        raise ValueError(f"unknown chatter detector {name!r}; allowed: {', '.join(sorted(table))}")
    return table[name](rate_hz, **params)


def describe_params(name: str) -> dict[str, tuple[float, float, float, str]]:
    """Parameters of a built-in detector: name -> (default, min, max, meaning)."""
    cls = DETECTORS.get(name)
    if cls is None:
        raise ValueError(f"unknown chatter detector {name!r}; allowed: {', '.join(sorted(DETECTORS))}")
    return {**BASE_PARAMS, **cls.PARAMS}
