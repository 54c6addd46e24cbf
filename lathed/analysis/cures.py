"""Remembered cures: the speed that cured chatter at a programmed speed, per set-up.

A production program cuts the same pass part after part.  When a pass chattered
at the speed it entered at and suppression cured it at another speed (its last
speed judged stable), the next pass entering at that speed, at least about as
deep, with the same tool and material (and the same tool number, where the
machine reports one: a turret holds several tools), can be given the cure at once, before its
chatter grows: the evidence is this machine's own cut, not a model.  A cure is
dropped when a pass given it chatters there anyway (the tool wore, the set-up
changed); suppression then finds another, which is remembered in its place.

Learned from the cut records (lathed.analysis.cut_log) in the order they were
written, so a daemon rebuilds the same memory from its store after a restart.
Numeric only, no asyncio.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

SPEED_BAND = 0.02     # a pass entering within +-2 % of a cure's entry speed is the same pass
DEPTH_SHARE = 0.9     # ... if at least this x the depth it chattered at (a shallower one may be stable)
TRIGGER = "remembered"


@dataclass(frozen=True)
class Cure:
    rpm_entry: float            # the speed the pass entered at and chattered at
    rpm: float                  # the speed that cured it
    depth_mm: float | None      # the pass's depth (None: not known)
    t: float                    # when the cut that taught it ended
    tool_number: int | None = None   # the machine's tool register at the pass (None: not reported)

    def to_json(self) -> dict:
        return {k: (round(v, 3) if isinstance(v, float) else v) for k, v in asdict(self).items()}


class CureMemory:
    """Cures of one machine's set-up (tool, material), keyed by entry speed."""

    def __init__(self, tool: str | None, material: str | None) -> None:
        self.setup = (tool or None, material or None)
        self.cures: list[Cure] = []

    def _index(self, rpm: float, tool_number: int | None) -> int | None:
        near = [(abs(c.rpm_entry - rpm), i) for i, c in enumerate(self.cures)
                if abs(c.rpm_entry - rpm) <= SPEED_BAND * c.rpm_entry and c.tool_number == tool_number]
        return min(near)[1] if near else None

    def learn(self, rec: dict) -> str | None:
        """One cut record (oldest first); returns "learned", "forgotten" or None."""
        if (rec.get("tool"), rec.get("material")) != self.setup:
            return None
        speeds = rec.get("speeds") or []
        actions = rec.get("actions") or []
        entry = rec.get("rpm_start")
        if entry is None and actions:
            entry = actions[0].get("rpm_before")    # left at once at entry: the speed it entered at
        if not speeds or not entry:
            return None
        given = any(s.get("trigger") == TRIGGER for s in speeds)
        last = speeds[-1]
        tn = rec.get("tool_number")
        i = self._index(float(entry), tn)
        if last.get("outcome") == "stable" and len(speeds) > 1 and last.get("rpm") and \
                (speeds[0].get("outcome") == "chatter" or given):
            cure = Cure(float(entry), float(last["rpm"]), rec.get("depth_mm"), float(rec.get("end_t") or 0.0), tn)
            if i is None:
                self.cures.append(cure)
            else:
                self.cures[i] = cure
            return "learned"
        if given and last.get("outcome") == "chatter" and i is not None:
            del self.cures[i]
            return "forgotten"
        return None

    def find(self, rpm: float, depth_mm: float | None, tool_number: int | None = None) -> Cure | None:
        """The cure for a pass entering at ``rpm``, ``depth_mm`` deep (None: unknown, no cure),
        with tool ``tool_number`` (a cure learned with another tool, or with none reported, is
        not this pass's)."""
        i = self._index(rpm, tool_number)
        if i is None or depth_mm is None:
            return None
        c = self.cures[i]
        if c.depth_mm is not None and depth_mm < DEPTH_SHARE * c.depth_mm:
            return None
        return c

    def clear(self) -> int:
        n = len(self.cures)
        self.cures.clear()
        return n
