"""Part-program features as simulated cuts, each stable and as a chatter control (docs/chatter.md).

A part program meets more than a steady pass: shoulders up and down, grooves the tool crosses,
flats and keyways (the cut interrupted for part of every revolution), tool changes, a facing
pass under constant surface speed (G96).  Each feature here is a list of regen.Segments on the
default lathe structure, at depths given as a share of the stability limit at the speed: stable
at <= 0.8 x the limit, and as a control the same feature taken above it (its deeper part at
1.6 x).  Every case starts with the spindle turning in air, as a pass does, so the cut state
sees the tool enter.  bench/bench_chatter.py's part-program table and tests/test_detectors.py and tests/test_verdict.py use it.
"""
from __future__ import annotations

import numpy as np

from lathed.analysis.lobes import StabilityLobes
from lathed.analysis.modal import Mode
from lathed.analysis.regen import DEFAULT_KF, DEFAULT_MODES, Segment as S

AIR_S = 0.4          # the spindle turning in air before the pass: the cut state's floor
STABLE = 0.8         # the deeper part of a stable feature, x the limit at its speed
CONTROL = 1.6        # ... of its control
SPEEDS = (1000.0, 2000.0, 3000.0)
# a second turret tool: a slender boring bar, its own mode far softer than the tool post's
TOOL2 = (DEFAULT_MODES[0], Mode(350.0, 0.02, 3.0e7, 0.0))
FEATURES = ("shoulder up", "shoulder down", "groove", "flat at entry", "keyway mid-cut",
            "tool change", "facing G96")


def b_lim_mm(rpm: float, modes=DEFAULT_MODES, kf: float = DEFAULT_KF) -> float:
    return float(StabilityLobes(modes, kf).b_lim_at(np.array([rpm]))[0][0]) * 1e3


def segments(feature: str, rpm: float, deep: float) -> list[S]:
    """The feature at ``rpm``, its deeper part ``deep`` x the limit (STABLE or CONTROL)."""
    b = b_lim_mm(rpm)
    mm = lambda share: round(share * b, 2)      # noqa: E731
    air = S(AIR_S, rpm, 0.0)
    if feature == "shoulder up":                 # the tool meets a larger diameter mid-pass
        return [air, S(1.3, rpm, mm(0.4)), S(1.7, rpm, mm(deep))]
    if feature == "shoulder down":               # ... a smaller one: the chip halves
        return [air, S(1.3, rpm, mm(deep)), S(1.7, rpm, mm(deep / 2))]
    if feature == "groove":                      # a groove cut before: the tool leaves and re-enters
        return [air, S(1.2, rpm, mm(0.5)), S(0.25, rpm, 0.0), S(1.55, rpm, mm(deep))]
    if feature == "flat at entry":               # a flat along the bar: 25 deg of every revolution
        return [air, S(3.0, rpm, mm(deep), flat_deg=25.0)]
    if feature == "keyway mid-cut":              # the tool reaches a keyway: 15 deg a revolution
        return [air, S(1.3, rpm, mm(deep)), S(1.7, rpm, mm(deep), flat_deg=15.0)]
    if feature == "tool change":                 # retract, index the turret, the boring bar cuts
        b2 = b_lim_mm(rpm, TOOL2)
        return [air, S(1.2, rpm, mm(0.5)), S(0.5, rpm, 0.0),
                S(1.3, rpm, round(deep * b2, 2), modes=TOOL2)]
    if feature == "facing G96":                  # the spindle speeds up as the diameter falls
        top = rpm * 1.4
        share = min(b, b_lim_mm(top), b_lim_mm(0.5 * (rpm + top)))
        return [air, S(0.3, rpm, round(deep * share, 2)), S(2.7, top, round(deep * share, 2), 2.7)]
    raise ValueError(f"unknown part-program feature {feature!r}; allowed: {', '.join(FEATURES)}")


def feature_cases(seeds: int = 2, speeds=SPEEDS, seed_base: int = 0):
    """(name, feature, kind, segments, seed) for every feature, speed and seed; kind "stable" or
    "chatter" (the control)."""
    out = []
    for i, feature in enumerate(FEATURES):
        for j, rpm in enumerate(speeds):
            for kind, deep in (("stable", STABLE), ("chatter", CONTROL)):
                for k in range(seeds):
                    seed = seed_base + 9000 + 100 * i + 10 * j + k + (5 if kind == "chatter" else 0)
                    out.append((f"{feature} {rpm:.0f} r/min {kind} #{k}", feature, kind,
                                segments(feature, rpm, deep), seed))
    return out
