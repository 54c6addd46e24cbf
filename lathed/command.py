"""Commands to machines: what an analyzer asks for, before the safety guard."""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field

# The actions a machine driver may carry out, with their units.
ACTIONS = {
    "spindle_rpm": "r/min",    # commanded spindle speed
    "offset_x_um": "µm",       # X (diameter-direction) tool offset
}


@dataclass(frozen=True)
class Command:
    """What is asked of a machine. Nothing in it exempts it from a bound: the guard judges
    its value against what the machine runs (a release is the value the machine's program
    runs, as its driver reads it, not a flag)."""
    machine: str               # instance name of the machine
    action: str                # one of ACTIONS
    value: float
    source: str                # who asked: analyzer instance name or "operator"
    reason: str = ""
    context: dict = field(default_factory=dict)   # values to record with it, under "context"

    def describe(self) -> str:
        return f"{self.action}={short_repr(self.value)} on {self.machine} from {self.source}"


def as_number(v) -> float | None:
    """``v`` as a finite float, or None: any real number (numpy's float32 and int64 too),
    never a bool, a string, an int beyond a float's range or a NaN."""
    if isinstance(v, bool) or not isinstance(v, numbers.Real) or type(v).__name__ == "bool_":
        return None
    try:
        f = float(v)
    except (OverflowError, ValueError, TypeError):
        return None
    return f if math.isfinite(f) else None


def short_repr(v) -> str:
    text = repr(v)
    return text if len(text) <= 40 else text[:37] + "..."


class CommandRefused(Exception):
    """The safety guard (or the machine's state) refused a command."""
