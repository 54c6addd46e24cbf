"""Commands to machines: what an analyzer asks for, before the safety guard."""
from __future__ import annotations

from dataclasses import dataclass, field

# The actions a machine driver may carry out, with their units.
ACTIONS = {
    "spindle_rpm": "r/min",    # commanded spindle speed
    "offset_x_um": "µm",       # X (diameter-direction) tool offset
}


@dataclass(frozen=True)
class Command:
    machine: str               # instance name of the machine
    action: str                # one of ACTIONS
    value: float
    source: str                # who asked: analyzer instance name or "operator"
    reason: str = ""
    context: dict = field(default_factory=dict)   # critical values to record with it
    release: bool = False      # back to the program's own value (an override's 100 %): no step or pace bound

    def describe(self) -> str:
        return f"{self.action}={self.value!r} on {self.machine} from {self.source}"


class CommandRefused(Exception):
    """The safety guard (or the machine's state) refused a command."""
