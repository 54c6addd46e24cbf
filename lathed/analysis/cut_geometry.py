"""The part and the chip as suppression knows them: the feed, the part's diameter (configured,
or from the X axis), and the depth of cut the spindle load implies where the machine has no
depth register (docs/chatter.md). Numeric only, no asyncio."""
from __future__ import annotations

import math
from dataclasses import dataclass

from lathed.analysis.speed_selection import Cut

MIN_DEPTH_MM = 0.05       # a load implying less is no chip (turning in air, the tool's approach)


@dataclass
class CutGeometry:
    kt: float                       # tangential cutting coefficient, N/m^2
    peak_torque_nm: float           # the spindle's: spindle_load_pct is a share of it
    diameter_m: float               # the configured diameter_mm, where the X axis says nothing
    x_axis: str = ""                # what the x_mm register is: "radius", "diameter" or not read ("")
    feed_mm: float = 0.3            # per revolution, from the feed register
    x_radius_m: float | None = None     # the tool tip's radius, from the x_mm register
    idle_load_pct: float | None = None  # the lowest load seen: the spindle's own, without a chip

    def x(self, x_mm: float) -> None:
        self.x_radius_m = x_mm / 1000 / (2.0 if self.x_axis == "diameter" else 1.0)

    def diameter(self, depth_m: float) -> float:
        """The part's diameter at the cut: the tool tip's radius plus the depth, twice (with
        x_axis), else the configured one."""
        if self.x_radius_m is not None and self.x_radius_m > 0:
            return 2.0 * (self.x_radius_m + depth_m)
        return self.diameter_m

    def cut(self, depth_mm: float | None) -> Cut:
        depth_m = max(depth_mm or 0.0, 0.01) / 1000
        return Cut(depth_m, self.feed_mm / 1000, self.diameter(depth_m), self.kt)

    def depth_from_load(self, load_pct: float) -> float | None:
        """The depth, mm, whose cutting torque is the load over the no-chip load: Kt b h r = T,
        solved for b (None: no chip). Call it only while the spindle turns."""
        self.idle_load_pct = load_pct if self.idle_load_pct is None else min(self.idle_load_pct, load_pct)
        torque = (load_pct - self.idle_load_pct) / 100.0 * self.peak_torque_nm
        c = torque / (self.kt * self.feed_mm / 1000)       # b times the lever arm, m^2
        x = self.x_radius_m
        if x is not None and x > 0:
            # the lever is the part's radius, x + b: Kt h b (x + b) = T, solved for b
            mm = (-x + math.sqrt(x * x + 4.0 * max(c, 0.0))) / 2.0 * 1000
        else:
            mm = c / (self.diameter_m / 2) * 1000
        return mm if mm > MIN_DEPTH_MM else None
