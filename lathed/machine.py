"""The uniform machine model every machine driver fills, whatever its protocol.

A lathe on Modbus, a robot arm on CAN and a grinder on RS-485 all end up as
the same fields: state, spindle speed, axis positions, part count, cycle
time, alarms, program. Each value carries the time it was measured; a value
older than ``stale_after``, or any value while the link is down, is reported
as stale and never as live (``live()`` gives None for it).

The model also turns the controller's counters into events exactly once:
``part_completed`` for each new part count (parts made while the link was
down are recorded when it returns, marked ``late``), ``alarm_raised`` /
``alarm_cleared`` when the set of active alarms changes. The driver object
outlives its reconnects, so a reconnect neither repeats nor drops one. No
asyncio here.
"""
from __future__ import annotations

import re
import time
from dataclasses import dataclass
from typing import Any, Callable

STATES = ("running", "idle", "alarm", "disconnected")
SCALARS = ("spindle_rpm", "part_count", "cycle_time_s", "program", "gripper")
AXIS = re.compile(r"^([a-z])_(mm|deg)$")    # a controller value named for an axis: x_mm, b_deg
MAX_LATE_PARTS = 10_000   # a jump larger than this is a counter reset or a different controller


@dataclass(frozen=True)
class Stamped:
    value: Any
    t: float          # wall-clock time of the measurement, s since the epoch


class MachineModel:
    def __init__(self, kind: str, stale_after: float, record: Callable[[str, dict], None] | None = None,
                 clock: Callable[[], float] = time.time):
        self.kind = kind
        self.stale_after = stale_after
        self.record = record or (lambda kind, payload: None)
        self.clock = clock
        self.linked = False
        self.values: dict[str, Stamped] = {}
        self.axes: dict[str, Stamped] = {}
        self.run_state: Stamped | None = None      # "running" | "idle" as the controller says
        self.alarms: Stamped = Stamped((), 0.0)
        self._last_count: int | None = None

    # -- link ---------------------------------------------------------------
    def link_up(self) -> None:
        self.linked = True

    def link_down(self) -> None:
        # values are kept with their times, so the operator sees the last known
        # value and how old it is, marked stale
        self.linked = False

    # -- filling ------------------------------------------------------------
    def set(self, field: str, value: Any, t: float | None = None) -> None:
        if field not in SCALARS:
            raise KeyError(f"{field!r} is not a machine model field; fields: {', '.join(SCALARS)}")
        t = self.clock() if t is None else t
        if field == "part_count":
            self._count(int(value), t)
        self.values[field] = Stamped(value, t)

    def set_axis(self, axis: str, value: float, t: float | None = None) -> None:
        self.axes[axis] = Stamped(float(value), self.clock() if t is None else t)

    def set_running(self, running: bool, t: float | None = None) -> None:
        self.run_state = Stamped("running" if running else "idle", self.clock() if t is None else t)

    def set_alarms(self, codes, t: float | None = None) -> None:
        """The controller's active alarms now (codes or short texts; empty: none)."""
        t = self.clock() if t is None else t
        new = tuple(sorted({str(c) for c in codes}))
        old = set(self.alarms.value)
        for c in new:
            if c not in old:
                self.record("alarm_raised", {"kind": self.kind, "alarm": c})
        for c in sorted(old - set(new)):
            self.record("alarm_cleared", {"kind": self.kind, "alarm": c})
        self.alarms = Stamped(new, t)

    def reading(self, name: str, v: float, t: float, alarm_from_state: bool = False) -> None:
        """A controller value by its lathed name (a register, an MTConnect item): spindle_rpm,
        cycle_time_s, part_count, program_number, program_state (1 running; with
        ``alarm_from_state``, 2 an alarm: a controller without an alarm_code), alarm_code (0:
        none), <axis>_mm / <axis>_deg. Other names are not the model's."""
        if name in ("spindle_rpm", "cycle_time_s"):
            self.set(name, v, t)
        elif name == "part_count":
            self.set("part_count", int(v), t)
        elif name == "program_number":
            self.set("program", int(v), t)
        elif name == "program_state":
            self.set_running(int(v) == 1, t)
            if alarm_from_state:
                self.set_alarms(["controller_alarm"] if int(v) == 2 else [], t)
        elif name == "alarm_code":
            self.set_alarms([int(v)] if int(v) else [], t)
        elif (ax := AXIS.match(name)) is not None:
            self.set_axis(ax.group(1), v, t)

    def _count(self, count: int, t: float) -> None:
        last = self._last_count
        self._last_count = count
        if last is None or count == last:
            return   # the first reading is the baseline: parts made before we looked are not ours
        if count < last or count - last > MAX_LATE_PARTS:
            self.record("part_counter_reset", {"kind": self.kind, "from": last, "to": count})
            return
        for n in range(last + 1, count + 1):
            self.record("part_completed", {"kind": self.kind, "part_count": n, "late": n != count})

    # -- reading ------------------------------------------------------------
    def is_stale(self, s: Stamped | None, now: float | None = None) -> bool:
        if s is None or not self.linked:
            return True
        return (self.clock() if now is None else now) - s.t > self.stale_after

    def live(self, field: str) -> Any:
        """The value if it is live, else None."""
        s = self.values.get(field)
        return None if self.is_stale(s) else s.value

    def state(self, now: float | None = None) -> str:
        if not self.linked:
            return "disconnected"
        if self.alarms.value and not self.is_stale(self.alarms, now):
            return "alarm"
        if self.run_state is not None and not self.is_stale(self.run_state, now):
            return self.run_state.value
        rpm = self.values.get("spindle_rpm")
        if rpm is not None and not self.is_stale(rpm, now):
            return "running" if abs(rpm.value) > 0.5 else "idle"
        return "disconnected"   # linked but nothing fresh heard: as good as gone

    def _entry(self, s: Stamped | None, now: float) -> dict | None:
        if s is None:
            return None
        v = round(s.value, 6) if isinstance(s.value, float) else s.value
        return {"value": list(v) if isinstance(v, tuple) else v, "t": round(s.t, 3),
                "age_s": round(now - s.t, 3), "stale": self.is_stale(s, now)}

    def snapshot(self) -> dict[str, Any]:
        now = self.clock()
        out: dict[str, Any] = {"kind": self.kind, "state": self.state(now), "stale_after_s": self.stale_after}
        for f in SCALARS:
            out[f] = self._entry(self.values.get(f), now)
        out["axes"] = {a: self._entry(s, now) for a, s in sorted(self.axes.items())}
        out["alarms"] = self._entry(self.alarms, now) if self.alarms.t else None
        return out
