"""What suppression sends its machine through the safety guard: a speed, a modulation, the
release at the cut's end; and whether the spindle followed (docs/chatter.md). Not an entry
point: the suppression plugin owns one."""
from __future__ import annotations

import time

import numpy as np

from lathed.analysis.speed_selection import Decision
from lathed.analysis.speed_variation import ramp_time_s
from lathed.command import Command

FOLLOW_SLACK_S = 1.0      # a commanded speed not reached within the ramp and this: the CNC did not follow
FOLLOW_BAND = 0.02        # ... to within this share of it
# The alarm's speed (chatter_rpm) and the machine's last reading further apart than this: one of
# them is old (a stalled poll), and a speed computed from it is wrong. Held until they agree.
SPEEDS_AGREE = 0.05


class SpindleCommands:
    """One suppression analyzer's speed commands in the present cut."""

    def __init__(self, owner):
        self.owner = owner        # the SuppressionAnalyzer: ctx, machine, policy, strategy, rpm
        self.commanded = False    # a speed was sent in this cut: released at its end
        self.follow: tuple[float, float, float] | None = None   # (speed sent, when, reached by): wall s
        self.follow_told = False  # ... and the cut's spindle was said not to follow
        self.disagree_told = False  # the cut's speeds disagreed at an alarm, recorded

    async def send(self, d: Decision, source: str) -> dict:
        """The decision's speed, or its modulation's first speed, through the guard."""
        o = self.owner
        if d.variation is not None:
            # the modulation's first speed, asked here: refused, nothing modulates
            result = await o.ctx.command(Command(o.machine, "spindle_rpm", float(
                np.asarray(d.variation.profile(0.0, d.rpm_before))), source,
                reason=f"speed variation ({d.variation.kind})"))
            if result["sent"]:
                o.strategy.modulate(d, self.modulated)
                result = {**result, "reason": "modulating"}
            self.commanded = self.commanded or not result.get("interlock")
            return result
        result = await o.ctx.command(Command(o.machine, "spindle_rpm", float(d.rpm_after), source,
                                             reason=f"chatter suppression ({d.strategy})",
                                             context={"strategy": d.strategy}))
        if result.get("interlock"):
            return result
        if not result["sent"] and o.policy is not None:
            o.policy.ban(d.rpm_after)    # refused by the guard: never asked for again this part
        # a write that failed may still have reached the control: the cut's end asks the
        # driver, which releases only what it finds of lathed's
        self.commanded = True
        if result["sent"] and o.rpm is not None and not self.follow_told:
            now = time.time()
            # an override lands on the control's step: the speed it gives, not the one asked
            self.follow = (float(result.get("rpm_effective", d.rpm_after)), now, now + FOLLOW_SLACK_S
                           + ramp_time_s(o.rpm, d.rpm_after, o.limits.accel_rpm_per_s))
        return result

    async def modulated(self, rpm: float, kind: str) -> bool:
        """One speed of a running modulation; False: refused, it stops."""
        o = self.owner
        self.commanded = True       # as above: a failed write may have reached the control
        r = await o.ctx.command(Command(o.machine, "spindle_rpm", rpm, o.name, reason=f"speed variation ({kind})"))
        if not r["sent"]:
            o.ctx.log.warning("ssv_stopped", reason=r["reason"])
        return r["sent"]

    def speed(self, rpm: float, t: float) -> None:
        """Did the spindle reach the speed sent? A write the control accepts but does not obey (an
        override or clamp on the control, a program setting S again) is said once a cut."""
        if self.follow is None:
            return
        o = self.owner
        target, sent_t, by = self.follow
        if abs(rpm - target) <= FOLLOW_BAND * target:
            self.follow = None
        elif t > by:
            self.follow, self.follow_told = None, True
            if o.policy is not None:
                o.policy.ban(target)         # not asked for again this cut (a clamp on the control)
            o.ctx.record("spindle_not_following", {"machine": o.machine, "sent_rpm": round(target, 1),
                                                   "rpm": rpm, "after_s": round(t - sent_t, 2)})
            o.ctx.log.warning("spindle_not_following", machine=o.machine, sent_rpm=round(target, 1),
                              rpm=rpm, after_s=round(t - sent_t, 2))

    def disagree(self, alarm_rpm: float | None) -> bool:
        """The alarm's speed against the machine's last reading (an analyzer that publishes no
        chatter_rpm: nothing to compare). Apart, nothing is decided: recorded once a cut."""
        o = self.owner
        if alarm_rpm is None or abs(alarm_rpm - o.rpm) <= SPEEDS_AGREE * alarm_rpm:
            return False
        if not self.disagree_told:
            self.disagree_told = True
            why = (f"the alarm was judged at {alarm_rpm:.0f} r/min and the machine's last speed reading "
                   f"is {o.rpm:.0f} r/min: no speed is computed until they agree")
            o.ctx.record("suppression_held", {"machine": o.machine, "rpm": o.rpm, "alarm_rpm": alarm_rpm,
                                              "reason": why})
            o.ctx.log.warning("suppression_held", machine=o.machine, rpm=o.rpm, alarm_rpm=alarm_rpm)
        return True

    async def cut_ended(self) -> None:
        """The program sets the next pass's speed: a speed sent as an override, which holds part
        after part, goes back to the program's (through the guard)."""
        o = self.owner
        self.follow, self.follow_told, self.disagree_told = None, False, False
        if not self.commanded:
            return
        self.commanded = False
        r = await o.ctx.release(o.machine, "spindle_rpm", o.name)
        if r is not None and not r["sent"] and r.get("interlock"):
            # a thread begun: held back by the supervisor, sent at the thread's end
            o.ctx.log.info("speed_release_deferred", machine=o.machine, why=r["reason"])
        elif r is not None and not r["sent"]:
            # the next parts run at the override until someone resets it: said loudly
            payload = {"machine": o.machine, "why": r["reason"]}
            o.ctx.log.error("speed_not_released", **payload)
            o.ctx.record("speed_not_released", payload)
