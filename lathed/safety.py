"""The one safety guard every command to a machine passes.

It refuses, never clamps: a command outside the configured limits is a bug
or a bad decision upstream, and quietly sending a different value would hide
it. Refusals are logged and recorded by the supervisor.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

from lathed.command import ACTIONS, Command
from lathed.config import Section


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
              runs_at: tuple[float, str] | None = None, interlock: str | None = None) -> str | None:
        """None if the command may be sent, else the reason it may not.

        ``current`` is the machine's present value of the commanded quantity
        (e.g. its commanded spindle speed), used for the step bound.  A release
        (``cmd.release``: back to what the program runs without lathed) is bounded
        by the range only: the way back may be a bigger step, or come sooner, than
        the steps that led away, and refusing it would leave lathed's value held.
        ``runs_at``: (the speed the machine will run for this value, why it differs),
        where the driver knows (an S word times the operator's override): held to the
        range too, for the range bounds the spindle, not the word written.
        ``interlock``: why the machine must take no such command now, from its own state (a
        thread being cut: the driver's ``interlock``), which refuses it, a release too.
        """
        lim = self.limits.get(cmd.machine)
        if lim is None:
            return f"no limits configured for machine {cmd.machine!r}"
        if cmd.action not in ACTIONS:
            return f"unknown action {cmd.action!r}"
        v = cmd.value
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            return f"{cmd.action} value {v!r} is not a finite number"
        if interlock is not None:
            return interlock
        now = self._clock()
        last = self._last.get((cmd.machine, cmd.action))
        ref = current if current is not None else (last[0] if last else None)
        # a NaN reference makes every "step > max" comparison False: refuse instead
        if ref is not None and (isinstance(ref, bool) or not isinstance(ref, (int, float))
                                or not math.isfinite(ref)):
            which = "machine's present value" if current is not None else "last command sent"
            return f"{cmd.action} reference ({which}) {ref!r} is not a finite number; cannot bound the step"
        if cmd.action == "spindle_rpm":
            if lim.rpm_max <= 0:
                return "spindle speed commands are not allowed on this machine (spindle_rpm_max not set)"
            if not lim.rpm_min <= v <= lim.rpm_max:
                return f"spindle speed {v:g} r/min outside [{lim.rpm_min:g}, {lim.rpm_max:g}]"
            if runs_at is not None and not lim.rpm_min <= runs_at[0] <= lim.rpm_max:
                return (f"spindle speed {v:g} r/min runs at {runs_at[0]:.0f} {runs_at[1]}, outside "
                        f"[{lim.rpm_min:g}, {lim.rpm_max:g}]")
            if ref is not None and not cmd.release and abs(v - ref) > lim.rpm_step_max:
                return f"spindle speed step {abs(v - ref):g} r/min exceeds {lim.rpm_step_max:g}"
            rate_max = lim.rpm_rate_max
            unit = "r/min per s"
        else:
            if lim.offset_max_um <= 0:
                return "offset commands are not allowed on this machine (offset_max_um not set)"
            if abs(v) > lim.offset_max_um:
                return f"offset {v:g} µm beyond ±{lim.offset_max_um:g} µm"
            # against the machine's present offset: the pace bound below knows only the commands
            # this daemon sent, so the first one after a start would otherwise jump unbounded
            if ref is not None and abs(v - ref) > lim.offset_step_max_um:
                return f"offset step {abs(v - ref):g} µm exceeds {lim.offset_step_max_um:g}"
            rate_max = lim.offset_rate_max_um_s
            unit = "µm/s"
        if last is not None and not cmd.release and math.isfinite(rate_max):
            dt = max(now - last[1], 1e-6)
            if abs(v - last[0]) > rate_max * dt:
                return f"{cmd.action} changing at {abs(v - last[0]) / dt:.3g} {unit}, above {rate_max:g}"
        return None

    def passed(self, cmd: Command) -> None:
        """Remember a command that was sent, for the pace bound."""
        self._last[(cmd.machine, cmd.action)] = (float(cmd.value), self._clock())
