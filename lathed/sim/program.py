"""The simulated lathe's cut program: one ``Cut`` per pass, and its text form.

Apart from lathed.sim.lathe (whose physics imports scipy) so the daemon can
check a [simulator] program in its config without importing the simulator.
"""
from __future__ import annotations

from dataclasses import dataclass

MAX_DEPTH_MM = 10.0   # deepest pass the simulated lathe takes (program, override, config)


@dataclass(frozen=True)
class Cut:
    """One part of the program: a turning pass along the bar."""
    rpm: float
    depth_mm: float
    feed_mm_rev: float = 0.3
    length_mm: float = 40.0
    diameter_mm: float = 30.0


def parse_cut(text: str) -> Cut:
    """``RPM,DEPTH_MM[,FEED_MM_REV[,LENGTH_MM]]``: one part of a cut program."""
    try:
        vals = [float(x) for x in text.split(",")]
    except ValueError:
        raise ValueError(f"cut {text!r}: expected RPM,DEPTH_MM[,FEED_MM_REV[,LENGTH_MM]] as numbers") from None
    if not 2 <= len(vals) <= 4:
        raise ValueError(f"cut {text!r}: expected RPM,DEPTH_MM[,FEED_MM_REV[,LENGTH_MM]]")
    c = Cut(*vals)
    if not (60 <= c.rpm <= 20_000 and 0 <= c.depth_mm <= MAX_DEPTH_MM and 0 < c.feed_mm_rev <= 2
            and 0 < c.length_mm <= 1000):
        raise ValueError(f"cut {text!r}: outside 60..20000 r/min, 0..{MAX_DEPTH_MM:g} mm deep, "
                         "0..2 mm/rev, 0..1000 mm long")
    return c
