"""The one safety guard every command to a machine passes.

It refuses, never clamps: a command outside the configured limits is a bug
or a bad decision upstream, and quietly sending a different value would hide
it. Refusals are logged and recorded by the supervisor.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

from lathed.command import ACTIONS, Command, short_repr, as_number
from lathed.config import Section

# a value within this fraction of the program's own is a release: the driver's programmed speed is
# read from two registers, and moves by their rounding between a release's reading and its check
RELEASE_TOL = 5e-4


@dataclass(frozen=True)
class Limits:
    rpm_min: float = 0.0
    rpm_max: float = 0.0          # 0: spindle speed commands refused
    rpm_step_max: float = math.inf  # largest change in one command
    rpm_rate_max: float = math.inf  # r/min per s between successive commands
    offset_max_um: float = 0.0    # |offset| bound; 0: offsets refused
    offset_rate_max_um_s: float = math.inf
    offset_step_max_um: float = math.inf   # largest change from the machine's present offset in one command

    @classmethod
    def from_section(cls, sec: Section) -> Limits:
        rpm_max = sec.getfloat("spindle_rpm_max", 0.0, minval=0.0, maxval=100_000.0)
        lim = cls(
            rpm_min=sec.getfloat("spindle_rpm_min", 0.0, minval=0.0, maxval=100_000.0),
            rpm_max=rpm_max,
            rpm_step_max=sec.getfloat("spindle_rpm_step_max", math.inf, above=0.0),
            rpm_rate_max=sec.getfloat("spindle_rpm_rate_max", math.inf, above=0.0),
            offset_max_um=sec.getfloat("offset_max_um", 0.0, minval=0.0, maxval=10_000.0),
            offset_rate_max_um_s=sec.getfloat("offset_rate_max_um_s", math.inf, above=0.0),
            offset_step_max_um=sec.getfloat("offset_step_max_um", math.inf, above=0.0),
        )
        if lim.rpm_max and lim.rpm_min > lim.rpm_max:
            raise sec.error("spindle_rpm_min", f"{lim.rpm_min:g} is above spindle_rpm_max {lim.rpm_max:g}")
        sec.check_unused()
        return lim


class SafetyGuard:
    """Checks commands against per-machine limits and the pace of change."""

    def __init__(self, limits: dict[str, Limits], clock=time.monotonic):
        self.limits = limits
        self._clock = clock
        self._last: dict[tuple[str, str], tuple[float, float]] = {}   # (machine, action) -> (value, t)

    def check(self, cmd: Command, current: float | None = None,
              runs_at: tuple[float, str] | None = None, interlock: str | None = None,
              program: float | None = None) -> str | None:
        """None if the command may be sent, else the reason it may not.

        Every command is judged by its value against what the machine runs, never by a flag
        its caller sets. ``current``: the machine's present value of the commanded quantity
        (its commanded spindle speed, the offset it holds), read from it lately; the step
        bound is taken from it, and where a step bound is set and it is not known (not read
        lately) the command is refused. ``program``: the value the machine's program runs
        for this action without lathed (the programmed speed under lathed's override), as
        its driver reads it: a command of that value is a release, bounded by the range only
        (the way back may be a bigger step, or come sooner, than the steps that led away,
        and refusing it would leave lathed's value held). ``runs_at``: (the speed the
        machine will run for this value, why it differs), where the driver knows (an S word
        times the operator's override): held to the range too. ``interlock``: why the
        machine must take no such command now, from its own state (a thread being cut),
        which refuses it, a release too.
        """
        lim = self.limits.get(cmd.machine)
        if lim is None:
            return f"no limits configured for machine {cmd.machine!r}"
        if cmd.action not in ACTIONS:
            return f"unknown action {cmd.action!r}"
        v = as_number(cmd.value)
        if v is None:
            return f"{cmd.action} value {short_repr(cmd.value)} is not a finite number"
        if interlock is not None:
            return interlock
        now = self._clock()
        last = self._last.get((cmd.machine, cmd.action))
        # a NaN reference makes every "step > max" comparison False: refuse instead
        if current is not None and as_number(current) is None:
            return (f"{cmd.action} reference (machine's present value) {short_repr(current)} is not a finite "
                    "number; cannot bound the step")
        release = self.is_release(cmd, program)
        if cmd.action == "spindle_rpm":
            if lim.rpm_max <= 0:
                return "spindle speed commands are not allowed on this machine (spindle_rpm_max not set)"
            if not lim.rpm_min <= v <= lim.rpm_max:
                return f"spindle speed {v:g} r/min outside [{lim.rpm_min:g}, {lim.rpm_max:g}]"
            if runs_at is not None and not lim.rpm_min <= runs_at[0] <= lim.rpm_max:
                return (f"spindle speed {v:g} r/min runs at {runs_at[0]:.0f} {runs_at[1]}, outside "
                        f"[{lim.rpm_min:g}, {lim.rpm_max:g}]")
            step_max, what, key = lim.rpm_step_max, "spindle speed step", "spindle_rpm_step_max"
            unit_step = "r/min"
            rate_max = lim.rpm_rate_max
            unit = "r/min per s"
        else:
            if lim.offset_max_um <= 0:
                return "offset commands are not allowed on this machine (offset_max_um not set)"
            if abs(v) > lim.offset_max_um:
                return f"offset {v:g} µm beyond ±{lim.offset_max_um:g} µm"
            # against the machine's present offset: the pace bound below knows only the commands
            # this daemon sent, so the first one after a start would otherwise jump unbounded
            step_max, what, key = lim.offset_step_max_um, "offset step", "offset_step_max_um"
            unit_step = "µm"
            rate_max = lim.offset_rate_max_um_s
            unit = "µm/s"
        if not release and math.isfinite(step_max):
            if current is None:
                # nothing sent yet, or sent long ago: neither says what the machine runs now
                return (f"{cmd.action}: the machine's present value is not known (not read lately), so the "
                        f"step to {v:g} cannot be bounded ({key} {step_max:g})")
            if abs(v - current) > step_max:
                return f"{what} {abs(v - current):g} {unit_step} exceeds {step_max:g}"
        if last is not None and not release and math.isfinite(rate_max):
            dt = max(now - last[1], 1e-6)
            if abs(v - last[0]) > rate_max * dt:
                return f"{cmd.action} changing at {abs(v - last[0]) / dt:.3g} {unit}, above {rate_max:g}"
        return None

    def is_release(self, cmd: Command, program: float | None) -> bool:
        """Whether ``cmd`` asks for the value the machine's program runs (read by its driver)."""
        v = as_number(cmd.value)
        return v is not None and program is not None and as_number(program) is not None and \
            abs(v - program) <= RELEASE_TOL * max(abs(program), 1.0)

    def passed(self, cmd: Command) -> None:
        """Remember a command that was sent, for the pace bound."""
        self._last[(cmd.machine, cmd.action)] = (as_number(cmd.value), self._clock())
