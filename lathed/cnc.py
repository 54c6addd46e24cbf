"""What a CNC control means, whatever the protocol that reaches it (docs/machines.md).

A machine driver for a CNC (Modbus registers, OPC UA nodes) holds the control's values by
their lathed names (spindle_rpm, spindle_rpm_cmd, spindle_override_pct, threading, ...), each
with the time it was last known to hold, and fills the machine model from them. The rest is
the same for every protocol and lives here, once: which commands the map allows, a speed
written as a spindle override (a percentage of the programmed speed, released back to 100 %),
the speed an S word runs at under the operator's override, the threading interlock, the
values the guard takes as the machine's present ones (fresh only), an override found held.
"""
from __future__ import annotations

import math
import time
from collections import deque

from lathed.bus import Sample
from lathed.command import Command
from lathed.config import Section
from lathed.driver import Driver
from lathed.machine import MachineModel

# the action -> the value it writes, by its lathed name
ACTION_TARGETS = {"spindle_rpm": "spindle_rpm_cmd", "offset_x_um": "offset_x_um"}


class CncDriver(Driver):
    """A CNC control's driver. A protocol's subclass reads its map, then calls ``setup_cnc``
    with the names it reads and those it may write; it puts each value read through
    ``take``, and says in ``linked`` whether its link is up."""

    role = "machine"

    def setup_cnc(self, section: Section, names: set[str] | frozenset[str], writable: set[str], what: str,
                  stale_after: float, threading_max_age: float, alarms_elsewhere: bool = False) -> None:
        """``what``: the map's table ("registers", "nodes"), for the errors; ``alarms_elsewhere``:
        the driver fills the model's alarms itself (a control's alarm events)."""
        self.names = frozenset(names)
        # without an alarm code or events, the program state's 2 is the alarm
        self.alarm_from_state = "alarm_code" not in self.names and not alarms_elsewhere
        self.stale_after = stale_after
        # how old a threading reading may be for a command to pass
        self.threading_max_age = threading_max_age
        self.actions = tuple(a for a, target in ACTION_TARGETS.items() if target in writable)
        # a control that takes the spindle speed only as an override (Fanuc's SOV through the
        # PMC, Siemens' DBB19): the spindle_rpm action is written as a percentage of the
        # programmed speed, and released (back to 100 %) when the analysis is done with it
        self.speed_by_override = "spindle_rpm" not in self.actions and "spindle_override_pct" in writable
        self.override_range = (section.getfloat("override_min_pct", 50.0, minval=1.0, maxval=100.0),
                               section.getfloat("override_max_pct", 150.0, minval=100.0, maxval=254.0))
        self.override_step = section.getfloat("override_step_pct", 1.0, minval=0.01, maxval=50.0)
        if self.speed_by_override:
            if "spindle_rpm_cmd" not in self.names:
                # the measured speed lags a write and a ramp (the override just written over a
                # speed not yet reached gives a wrong programmed speed), and a G96 drift is seen
                # only in the commanded one: an override beyond the speed the guard checked
                raise section.error(what, "a writable spindle_override_pct needs spindle_rpm_cmd (the "
                                          "commanded speed) mapped: the override is a percentage of the "
                                          "programmed speed, which the measured speed does not give")
            self.actions += ("spindle_rpm",)
        self._cmd_seen: deque = deque(maxlen=4)   # (commanded speed, override) of the last readings
        self._ours: float | None = None           # the override lathed wrote and has not released
        self._pending: float | None = None        # one written whose answer never came (it may hold)
        self._released_rpm: float | None = None   # the speed released() last gave: written as 100 %
        self.values: dict[str, tuple[float, float]] = {}     # name -> (value, t it was last known to hold)
        self.model = MachineModel(self.kind, self.stale_after, self._record)

    def linked(self) -> bool:
        """The link to the control is up (values read through it may be fresh)."""
        raise NotImplementedError

    def _record(self, kind: str, payload: dict) -> None:
        if self.ctx is not None:
            self.ctx.record(kind, payload)

    def take(self, name: str, v: float, unit: str, t: float) -> bool:
        """A value read: checked for plausibility as it is published, then the guard's and the
        model's. False: refused (it reaches neither; its last good value goes stale)."""
        if not self.ctx.bus.publish(Sample(self.name, name, v, unit, t)):
            return False
        if name == "spindle_rpm_cmd" and self.speed_by_override:
            self._cmd_seen.append((v, self.values.get("spindle_override_pct", (None, 0))[0]))
        self.values[name] = (v, t)
        self.model.reading(name, v, t, alarm_from_state=self.alarm_from_state)
        return True

    def held_at_connect(self) -> None:
        """An override the link comes up to that lathed did not write is the operator's, or an
        earlier process's (one that died on a control without the heartbeat): said, never undone."""
        ovr = self._fresh("spindle_override_pct") if self.speed_by_override else None
        if ovr is None or ovr == 100.0 or (self._ours is not None and abs(ovr - self._ours) <= 1e-3 * self._ours):
            return
        payload = {"machine": self.name, "override_pct": ovr}
        if self.ctx is not None:
            self.ctx.log.warning("override_found_held", **payload)
        self._record("override_found_held", payload)

    def _programmed(self) -> tuple[float, float] | None:
        """(present override %, programmed speed): the commanded speed over the override."""
        ovr, now = self._fresh("spindle_override_pct"), self.current("spindle_rpm")
        if ovr is None or now is None or not ovr > 0 or not now > 0:
            return None
        return ovr, now * 100.0 / ovr

    def override_for(self, rpm: float) -> tuple[float, float]:
        """(override %, the speed it gives) for a speed the guard passed: a percentage of the
        programmed speed on the control's step, rounded towards the present override, so the
        spindle lands between its present speed and the one asked, never beyond."""
        p = self._programmed()
        if p is None:
            raise ConnectionError("no fresh spindle override and speed to take the programmed speed from")
        ovr, base = p
        exact = 100.0 * rpm / base
        released, self._released_rpm = self._released_rpm, None
        if abs(exact - 100.0) < 0.05 or rpm == released:
            # a release is 100 %: the programmed speed it was worked out from may have moved on
            # since (the next pass's S word), and that speed over the new one would hold part
            # after part
            return 100.0, base       # the programmed speed (a release; G96 drifts between the reads)
        if self._speed_drifting():
            # an override scales the programmed speed, and under G96 that moves on its own: the
            # spindle would leave the speed the guard checked, by as much as the face drifts
            raise ValueError(f"the control's programmed speed is moving on its own (constant surface "
                             f"speed, G96): an override would take the spindle past the {rpm:.0f} r/min "
                             f"the guard checked; not written")
        q = exact / self.override_step
        q = (math.floor(q + 1e-9) if exact >= ovr else math.ceil(q - 1e-9)) * self.override_step
        lo, hi = self.override_range
        if not lo <= q <= hi:
            raise ValueError(f"{rpm:.0f} r/min is a spindle override of {q:g} % of the programmed "
                             f"{base:.0f} r/min, beyond the control's {lo:g}..{hi:g} %")
        return q, base * q / 100.0

    def _speed_drifting(self) -> bool:
        """The control in constant surface speed: its css_active signal (Fanuc's CSS, F2.2)
        where mapped, else the commanded speed changed at each of the last two readings while
        the override held (a new S word changes it once): slower, a G96 face's first
        revolutions are not seen so."""
        css = self._fresh("css_active")
        if css is not None:
            return css >= 0.5
        seen = list(self._cmd_seen)[-3:]
        return len(seen) == 3 and all(b[1] == a[1] and abs(b[0] - a[0]) > 5e-4 * max(a[0], 1.0)
                                      for a, b in zip(seen, seen[1:]))

    def override_written(self, value: float | None, rpm: float | None, pending: bool = False) -> None:
        """An override is being written (``pending``: the answer not back yet; it may hold) or was."""
        if pending:
            self._pending = value
            return
        now = time.time()
        self.values["spindle_override_pct"] = (value, now)
        self._ours, self._pending = (None if value == 100.0 else value), None
        if "spindle_rpm_cmd" in self.names:
            self.values["spindle_rpm_cmd"] = (rpm, now)      # the commanded speed it gives

    def released(self, action: str) -> float | None:
        """What ``action`` goes back to when the analysis is done with it: the programmed
        speed (an override of 100 %) where the speed is written as an override, which holds
        part after part; None where the program's next speed word takes over anyway, and
        where the override there is not the one lathed wrote (the operator's, or one left
        by an earlier run, which the control's heartbeat watchdog takes back)."""
        p = self._programmed() if action == "spindle_rpm" and self.speed_by_override else None
        if p is None or not any(v is not None and abs(p[0] - v) <= 1e-3 * v for v in (self._ours, self._pending)):
            return None
        self._released_rpm = p[1]
        return p[1]

    def runs_at(self, cmd: Command) -> tuple[float, str] | None:
        """The speed an S word runs at where the operator's spindle override, read, is not
        100 %: the control multiplies the two (the guard holds that to the range too)."""
        if cmd.action != "spindle_rpm" or self.speed_by_override:
            return None
        ovr = self._fresh("spindle_override_pct")
        if ovr is None or ovr == 100.0 or not math.isfinite(ovr):
            return None
        return float(cmd.value) * ovr / 100.0, f"with the control's spindle override at {ovr:g} %"

    def interlock(self, cmd: Command) -> str | None:
        """A thread being cut (the map's ``threading`` signal: 1 from a thread's first pass
        to its last, or a rigid tap's): no speed and no offset may change, a release neither;
        the passes must follow one helix at one speed (the control's lag follows the speed),
        and an offset would step the flank. Not read lately, a thread may be on: the same."""
        if "threading" not in self.names:
            return None
        read = self.values.get("threading")
        if read is None or not self.linked():
            return f"machine {self.name}'s threading signal not read yet: a thread may be being cut"
        v, t = read
        if time.time() - t > self.threading_max_age:
            return (f"machine {self.name}'s threading signal not read within {self.threading_max_age:g} s: "
                    f"a thread may be being cut")
        return threading_refusal(self.name, v)

    def _fresh(self, name: str) -> float | None:
        v = self.values.get(name)
        if v is None or not self.linked() or time.time() - v[1] > self.stale_after:
            return None
        return v[0]

    def quantities(self) -> frozenset[str]:
        return self.names      # every value the map reads is published

    def current(self, action: str) -> float | None:
        if action == "spindle_rpm":
            if "spindle_rpm_cmd" in self.names:
                return self._fresh("spindle_rpm_cmd")
            return self._fresh("spindle_rpm")
        if action == "offset_x_um":
            return self._fresh("offset_x_um")
        return None

    def value_status(self, units: dict[str, str]) -> dict:
        """The values with their ages, for status."""
        now = time.time()
        return {n: {"value": v, "unit": units.get(n, ""), "age_s": round(now - t, 3),
                    "stale": not self.linked() or now - t > self.stale_after}
                for n, (v, t) in self.values.items()}


def threading_refusal(machine: str, v: float) -> str | None:
    """Why no command may pass with the threading signal at ``v``, or None."""
    if v != 0:      # anything but 0 (a PLC's TRUE as -1, a scaled bit, the whole F2 byte)
        return (f"machine {machine} is cutting a thread (threading = {v:g}): its speed and offsets "
                f"must not change until the thread's last pass")
    return None
