"""Chatter suppression: on a chatter alarm, change the spindle speed (numeric core:
lathed.analysis.speed_selection, lathed.analysis.speed_variation).

    [analyzer.suppress]
    plugin = "suppression"
    chatter = "chatter"          # the chatter analyzer it listens to
    machine = "lathe"            # the machine it commands (through the safety guard)
    mode = "auto"                # auto: act on alarms | manual: operator acts | off
    strategy = "lobes"           # lobes | frequency | rated | variation
    rated_rpm = 750.0            # the paper's rule; also the fallback of lobes/frequency
    modes = ["190,0.03,7.5e7,0"] # modal model FN,ZETA,K[,THETA] (a tap test); needed by "lobes"
    kf = 2.0e9                   # cutting coefficient along the chip thickness, N/m²
    kt = 1.5e9                   # tangential coefficient (spindle torque), N/m²
    diameter_mm = 30.0           # workpiece diameter, for torque and removal rate
    x_axis = "radius"            # the x_mm register is the tool tip's radius (or "diameter"):
                                 # the part's diameter read from it at every poll (default off: diameter_mm)
    max_rpm = 6000.0             # the spindle's envelope (min_rpm 100, below it)
    max_speed_ratio = 1.3        # never more than this times the programmed speed (tool life)
    peak_torque_nm = 35.8
    base_rpm = 1500.0            # torque flat up to here, constant power above; at most max_rpm
    accel_rpm_s = 3000.0
    settle_revs = 20.0           # revolutions at a new speed before judging again
    avoid = false                # also act at cut entry when the lobes predict chatter (strategy lobes)
    remember = true              # give a pass entering at a speed it chattered at the speed that cured it
    when_no_stable_speed = "hold" # lobes: every speed within reach chatters at this depth -> hold | move
    ssv = "sine"                 # variation: sine | triangle | square
    ssv_amplitude = 0.1          # variation: amplitude / mean speed
    ssv_period = "500ms"
    tool = "T0101"               # the set-up the modal model is for: recorded with every cut
    tool_number = 1              # its turret position (the machine's tool_number register); optional
    material = "C45"
    depth_mm = 1.2               # the programmed depth of cut, when the machine reports none

Every action is recorded as ``suppression_action`` with its critical values
(index and threshold, chatter frequency, speed before and after, strategy,
whether the guard let it through). ``lathectl suppress auto|manual|off``
changes the mode; ``lathectl suppress now`` acts on the present chatter
(manual mode). Policy: see SuppressionPolicy (never oscillates).

When the lobes (the cut's model: configured or adopted) say that every speed
within reach chatters at the cut's depth (b_lim below the depth at each), a
move would only trade one chatter for another.  With ``when_no_stable_speed
= "hold"`` (the default) the speed is kept, no command is sent, and
``suppression_advice`` is recorded once for the cut: the depth, the model's
limit here and at the best speed within reach, and the cure (a cut below the
depth the lobe rule calls stable here, or a stiffer set-up).  Where some
speed's limit is above the depth but not by the 1.15 margin, it still moves
there (most such moves cure the cut).  The chatter goes on, so the part is
flagged as any chattering part is.  "move" keeps the paper's behaviour (the
most stable speed, then the rated speed): for a model one suspects of being
pessimistic, or to gather cuts at other speeds for a refit.  Holding needs
the depth: with none known (no register, no spindle-load estimate yet, no
``depth_mm``) the lobes cannot say that every speed chatters, and
suppression moves as before.

The depth the lobes need comes from a depth_of_cut_mm register where the
machine has one, else from the spindle load (spindle_load_pct: the cutting
torque over the no-chip load, Kt * b * feed * D/2 = torque, solved for b;
it needs kt, peak_torque_nm, diameter_mm and the feed register right),
else the programmed ``depth_mm``.

With ``avoid = true`` the lobes are also used before any alarm: when a cut
starts at a depth the lobes call unstable at the programmed speed (the same
rule the lobes strategy picks speeds by: the worst b_lim within +-3 % of
the speed under 1.15 x depth), the speed is changed at once, through the
same policy and guard, and recorded with ``trigger = "predicted"``. A cut
unstable from entry grows its chatter from the first revolution, and a
detector that learns its baseline on that cut sees it only once it has
grown; the model sees it before. Off by default: it trusts the modal model
(a tap test) to move speeds no alarm has asked for.

With ``remember = true`` (any strategy) the cures are remembered
(lathed.analysis.cures): when a pass chattered at the speed it entered at
and suppression cured it at another, the next pass entering within 2 % of
that speed, at least 0.9 x as deep, with the configured tool and material
and the same tool number where the machine reports one (``tool_number``),
is moved to the cure as soon as its depth is measured (the depth register,
else the spindle load's estimate: a programmed depth_mm is not evidence),
through the same policy and guard, recorded with ``trigger =
"remembered"``.  A cure that chatters anyway is dropped and the one found
after it remembered.  The memory is rebuilt from the store's newest cut
records at start; ``lathectl suppress forget`` (operator) clears it, for a new tool or
set-up, and the clearing is recorded so a restart does not bring it back.

Every cut (entry to exit) leaves a ``cut`` record (lathed.analysis.cut_log):
the set-up, depth and feed, each speed it turned at with its verdict, the
first alarm (time, revolution, chatter frequency), the actions and whether
the cut ended cured.  ``lathectl cuts`` lists them, ``--csv`` exports them
for ``lathectl analyze stability``.  The depth is the machine's
depth_of_cut_mm register, else the deepest the spindle load showed during
the cut (``depth_from = "spindle load"``; the estimate is also published as
``depth_est_mm``, which the parts' records take), else the programmed ``depth_mm``,
else unknown (null): such cuts are recorded but the refit cannot use them
(it says how many it left out).

A turret holds tools of other dynamics than the one the tap test measured.
With ``tool_number`` set and the machine reporting its ``tool_number``
register, a cut with another tool is not judged by the lobes: no prediction
at entry (``avoid``), no hold with advice, and a chatter alarm is answered
model-free (the ``frequency`` strategy, the rated speed as its fallback);
its actions and cut record say ``model = null``, and the refit leaves it
out.  Without ``tool_number`` (or without the register) the model is taken
for every tool, as before.

``lathectl stability refit`` refits the modal model on this machine's
recorded cuts (lathed.analysis.stability.refit) and adopts the result only
when it classifies the held-out cuts better: saved as a new version
(lathed.analysis.stability.files), recorded as ``stability_model_adopted``,
and from then on (also after a restart) the lobes of speed selection and of
cut-entry avoidance are the adopted model's.  A refit that adds nothing is
recorded as ``stability_refit_not_adopted`` with the reason.

With strategy "lobes" and no ``modes`` the model is learned from these cut
records (lathed_plugins.stability_learning; docs/stability.md): model-free
until a learn is trusted, then its lobes.
"""
from __future__ import annotations

import asyncio
import json
import math
import time
from dataclasses import replace

import numpy as np

from lathed import hookimpl
from lathed.analysis.cures import TRIGGER as REMEMBERED, CureMemory
from lathed.analysis.cut_log import CutTracker, cut_rows
from lathed.analysis.modal import parse_mode
from lathed.analysis.speed_selection import (WHEN_NO_STABLE_SPEED, Advice, Cut, Decision, FrequencySelection,
                                             LobeSelection, RatedSpeed, SpindleLimits, SuppressionPolicy,
                                             VariationSelection, lobe_grid, lobe_policy, model_free_policy, reach)
from lathed.analysis.speed_variation import KINDS, SpeedVariation, ramp_time_s
from lathed.analysis.stability import StabilityModel, refit
from lathed.analysis.stability import files as stability_files
from lathed.analyzer import Analyzer
from lathed.args import Args
from lathed.caller import require_operator
from lathed.bus import Sample
from lathed.command import Command
from lathed.config import Section
from lathed.control import RequestError, offload
from lathed.display import rounded
from lathed_plugins.stability_learning import LearnedStability

LOBE_POINTS = 600      # points of the lobe chart sent to a screen
LOBE_CAP_MM = 20.0

MODES = ("auto", "manual", "off")
STRATEGIES = ("lobes", "frequency", "rated", "variation")
SSV_STEP_S = 0.05     # speed commands while modulating
MAX_REFIT_SPEEDS = 2000   # cut speeds a daemon refit uses: the newest
MEMORY_RECORDS = 5000     # cut records the remembered cures are rebuilt from at start: the newest
FOLLOW_SLACK_S = 1.0      # a commanded speed not reached within the ramp and this: the CNC did not follow
FOLLOW_BAND = 0.02        # ... to within this share of it
SHALLOWER = 0.9           # a cut held with advice that gets this much shallower ...
SHALLOWER_HELD_S = 0.5    # ... for this long (not the tool's exit, a poll or two) is decided afresh


class SuppressionAnalyzer(Analyzer):
    def __init__(self, name: str, section: Section):
        super().__init__(name, section)
        self.chatter = section.getstr("chatter")
        self.machine = section.getstr("machine")
        self.mode = section.getstr("mode", "auto", choices=MODES)
        self.strategy_name = section.getstr("strategy", "frequency", choices=STRATEGIES)
        self.rated_rpm = section.getfloat("rated_rpm", 750.0, above=0)
        texts = section.getlist("modes", [])
        try:
            modes = tuple(parse_mode(t) for t in texts)
        except ValueError as e:
            raise section.error("modes", str(e)) from None
        kf = section.getfloat("kf", 2.0e9, above=0)
        self.kt = section.getfloat("kt", 1.5e9, above=0)
        self.diameter_m = section.getfloat("diameter_mm", 30.0, above=0) / 1000
        # the X axis tells the diameter being cut (a profile, another part) where diameter_mm is one number
        self.x_axis = section.getstr("x_axis", "", choices=("", "radius", "diameter"))
        self.x_radius_m: float | None = None     # the tool tip's radius, from the x_mm register
        max_rpm = section.getfloat("max_rpm", 6000.0, above=0)
        self.limits = SpindleLimits(
            max_rpm=max_rpm,
            min_rpm=section.getfloat("min_rpm", 100.0, minval=0),
            peak_torque_nm=section.getfloat("peak_torque_nm", 35.8, above=0),
            # the default at most the top speed: a slow spindle's max_rpm alone is not an error
            base_rpm=section.getfloat("base_rpm", min(1500.0, max_rpm), above=0),
            accel_rpm_per_s=section.getfloat("accel_rpm_s", 3000.0, above=0))
        lim = self.limits
        if lim.min_rpm >= lim.max_rpm:      # no speed would be within reach: every alarm exhausted
            raise section.error("min_rpm", f"{lim.min_rpm:g} r/min is not below max_rpm {lim.max_rpm:g} r/min")
        if lim.base_rpm > lim.max_rpm:
            # the torque is flat up to base_rpm: above max_rpm it only inflates the power, which no
            # speed in reach uses, so the number would be taken and mean nothing (or be a swap)
            raise section.error("base_rpm", f"{lim.base_rpm:g} r/min is above max_rpm {lim.max_rpm:g} r/min; "
                                            "a spindle with its peak torque over its whole range (constant "
                                            "torque) has base_rpm = max_rpm")
        self.settle_revs = section.getfloat("settle_revs", 20.0, minval=0, maxval=1000)
        self.max_speed_ratio = section.getfloat("max_speed_ratio", 1.3, minval=1.0, maxval=10.0)
        self.avoid = section.getbool("avoid", False)
        self.remember = section.getbool("remember", True)
        self.when_no_stable_speed = section.getstr("when_no_stable_speed", "hold", choices=WHEN_NO_STABLE_SPEED)
        try:
            self.variation = SpeedVariation(section.getstr("ssv", "sine", choices=KINDS),
                                            section.getfloat("ssv_amplitude", 0.1, above=0, maxval=0.5),
                                            section.getduration("ssv_period", 0.5, minval=0.05, maxval=60),
                                            self.limits.accel_rpm_per_s)
        except ValueError as e:
            raise section.error("ssv", str(e)) from None
        if self.strategy_name == "variation" and self.variation.amplitude_ratio > self.max_speed_ratio - 1:
            # its swing would pass the speed cap at every alarm: refused there, so refuse it here
            raise section.error("ssv_amplitude", f"{self.variation.amplitude_ratio:g} swings the speed above "
                                f"max_speed_ratio = {self.max_speed_ratio:g} x the programmed speed")
        # strategy "lobes" without a tap test: the model is learned from the cut records
        self.learning = self.strategy_name == "lobes" and not modes
        if self.avoid and self.strategy_name != "lobes":
            raise section.error("avoid", 'predicting chatter at cut entry needs strategy = "lobes" (and its modes)')
        self.tool = section.getstr("tool", "")
        # the turret position the modal model was measured at: other tools' cuts are not its
        self.tool_number: int | None = section.getint("tool_number", None, minval=0, maxval=9999)
        self.material = section.getstr("material", "")
        self.program_depth_mm = section.getfloat("depth_mm", 0.0, minval=0.0, maxval=50.0) or None
        # the tap test's model; the lobes in use are it or the adopted refit of it, or a learned one
        self.configured = StabilityModel(modes, kf) if modes else None
        self.lobes = self.configured
        self.model_name = "configured" if modes else "none"
        self.learned = LearnedStability(self, kf) if self.learning else None
        self.policy_model = self.model_name   # the model the running cut's policy was built with
        self._models_loaded = False
        self._refitting = False
        self.last_refit: dict | None = None
        self.cut = CutTracker(self.machine, self.tool, self.material)
        self.memory = CureMemory(self.tool, self.material)
        self._memory_loaded = False
        self._recalled = False                 # the pass in the cut has been given its cure
        self._told_exhausted: SuppressionPolicy | None = None   # the cut's policy said it had no speed left
        self._follow: tuple[float, float, float] | None = None   # (speed sent, when, reached by): wall s
        self._follow_told = False              # ... and the cut's spindle was said not to follow
        self._commanded = False                # a speed was sent in this cut: released at its end
        self.held_back: str | None = None      # the machine's interlock refused this cut's speed (a thread)
        self._shallower_since: float | None = None   # the cut held with advice is shallower since
        self.cuts_recorded = 0
        self.grid = None    # the lobes over the spindle's range, computed once at start
        self._lobe_view = None
        self.policy: SuppressionPolicy | None = None
        self.depth_mm = 0.0
        self.depth_from: str | None = None      # "register" | "spindle load"
        self.idle_load_pct: float | None = None
        self.in_cut: dict[str, bool] = {}
        self._avoided: set[str] = set()
        self.feed_mm = 0.3
        self.rpm: float | None = None
        self.part_count: float | None = None
        self.chat = {"index": None, "threshold": None, "frequency": None, "alarm": False, "t": None}
        self.actions = 0                       # a count: the records keep every action
        self.last_action: dict | None = None
        self.advisories = 0
        self.last_advice: dict | None = None
        self.last_was_advice = False     # which of last_action / last_advice came last (for a screen)
        self.pending: Decision | None = None
        self.pending_trigger = "alarm"
        self._ssv_task: asyncio.Task | None = None
        self.alarm_wall_t: float | None = None
        self.latency_ms: list[float] = []

    def inputs(self) -> list[str]:
        return [self.machine]

    def machines(self) -> list[str]:
        return [self.machine]

    def refers(self) -> dict[str, tuple[str, str, str | None]]:
        # what it reads the alarms from, and a machine it can slow or speed up
        return {"chatter": (self.chatter, "analyzer", None), "machine": (self.machine, "machine", "spindle_rpm")}

    # -- strategy ----------------------------------------------------------------
    def _depth_known_mm(self) -> float | None:
        """The cut's depth: the register or the spindle load's estimate, else the programmed depth_mm."""
        return self.depth_mm if self.depth_mm > 0 else self.program_depth_mm

    def _cut(self) -> Cut:
        depth_m = max(self._depth_known_mm() or 0.0, 0.01) / 1000
        return Cut(depth_m, self.feed_mm / 1000, self._diameter_m(depth_m), self.kt)

    def _diameter_m(self, depth_m: float) -> float:
        """The part's diameter at the cut: the tool tip's radius plus the depth, twice (the
        X axis, with x_axis set), else the configured diameter_mm."""
        if self.x_radius_m is not None and self.x_radius_m > 0:
            return 2.0 * (self.x_radius_m + depth_m)
        return self.diameter_m

    def _model_applies(self) -> bool:
        """The cut's tool is the one the modal model is for (or nothing says otherwise)."""
        return self.tool_number is None or self.cut.tool_number in (None, self.tool_number)

    def _policy(self) -> SuppressionPolicy:
        cut = self._cut()
        # a cut keeps the lobes it started with: an adoption mid-cut applies from the next cut;
        # another turret tool's cut has none (its dynamics are not the tap test's)
        lobes = self.lobes if self._model_applies() else None
        self.policy_model = self.model_name if lobes is not None else None
        if self.strategy_name == "lobes" and lobes is not None:
            # with no depth known the lobes cannot say that every speed chatters: no hold
            hold = self.when_no_stable_speed if self._depth_known_mm() is not None else "move"
            return lobe_policy(self.lobes, cut, self.limits, self.rpm, self.max_speed_ratio, self.rated_rpm,
                               grid=self.grid, settle_revs=self.settle_revs, when_no_stable_speed=hold)
        if self.strategy_name == "lobes":      # another turret tool; no model learned yet
            return model_free_policy(cut, self.limits, self.rpm, self.max_speed_ratio, self.rated_rpm,
                                     self.settle_revs)
        limits = reach(self.limits, self.rpm, self.max_speed_ratio)
        rated = RatedSpeed(self.rated_rpm, lobes, cut, limits=limits)
        strategy = {"frequency": lambda: FrequencySelection(limits, cut),
                    "rated": lambda: rated,
                    "variation": lambda: VariationSelection(self.variation)}[self.strategy_name]()
        fallback = None if self.strategy_name in ("rated", "variation") else rated
        return SuppressionPolicy(strategy, limits, fallback=fallback, settle_revs=self.settle_revs)

    # -- running -----------------------------------------------------------------
    async def run(self) -> None:
        self.ctx.register_control("suppress", self._control)
        self.ctx.register_control("stability", self._stability)
        if not self._models_loaded:
            self._models_loaded = True
            await asyncio.to_thread(self._load_adopted)
        if self.lobes is not None and self.grid is None:
            self.grid = await asyncio.to_thread(lobe_grid, self.lobes, self.limits)
        if self.remember and not self._memory_loaded:
            self._memory_loaded = True
            await asyncio.to_thread(self._load_memory)
        if self.learned is not None:
            await self.learned.start()
        sub = self.ctx.bus.subscribe(self.chatter, self.machine, maxsize=4096, name=self.name)
        ended = "analyzer failed"     # the supervisor restarts it; the cut so far is kept
        try:
            while True:
                s = await sub.get()
                if not isinstance(s, Sample):
                    continue
                if s.source == self.machine:
                    await self._on_machine(s)
                elif s.source == self.chatter:
                    await self._on_chatter(s)
        except asyncio.CancelledError:
            ended = "daemon stopped"
            raise
        finally:
            self.ctx.bus.unsubscribe(sub)
            self._stop_ssv()
            # a cut the daemon stops in is evidence too, up to now: recorded, never lost
            self._cut_ended(time.time(), ended=ended)
            if self.learned is not None:
                await self.learned.stop()

    async def _on_machine(self, s: Sample) -> None:
        if s.quantity == "spindle_rpm":
            self.rpm = s.value
            self.cut.speed(s.t, s.value)
            if self._follow is not None:
                self._followed(s.value, s.t)
        elif s.quantity == "feed_mm_rev" and s.value > 0:
            self.feed_mm = s.value
            self.cut.feed_mm_rev = s.value
        elif s.quantity == "tool_number":
            self.cut.tool_number = int(s.value)    # a tool change between passes: its own cures
        elif s.quantity == "x_mm" and self.x_axis:
            self.x_radius_m = s.value / 1000 / (2.0 if self.x_axis == "diameter" else 1.0)
        elif s.quantity == "depth_of_cut_mm":
            self.depth_from = "register"
            changed = s.value > 0 and s.value != self.depth_mm
            self.depth_mm = s.value
            if s.value > 0:
                self.cut.depth_mm, self.cut.depth_from = s.value, "register"
            if changed:
                self._depth_changed()      # the vibration may have seen the chip first
            await self._cut_seen("depth", s.value > 0, s.t)
            self._shallower(s.t if s.value > 0 else None)
        elif s.quantity == "spindle_load_pct" and self.depth_from != "register":
            est = self._depth_from_load(s.value)
            self._shallower(s.t if est is not None else None)
            if est is not None:
                # the parts' records take it (lathed.records.PartTracker): a real CNC has no depth register
                self.ctx.bus.publish(Sample(self.name, "depth_est_mm", est, "mm", s.t))
            # est None: no chip yet (a cut the cutting-feed signal started in air)
            if self.avoid and self.in_cut and self.depth_from == "spindle load" and est is not None \
                    and not self._avoided:
                self._avoided.add("load")
                await self._avoid()
            if self.remember and self.in_cut:
                await self._recall()

    def _depth_from_load(self, load_pct: float) -> float | None:
        """Without a depth register the lobes need the depth: the cutting torque the
        drive reports over the spindle's no-chip load, Kt b h r = T, solved for b.
        Returns the estimate in mm while cutting (None otherwise)."""
        if self.rpm is None or self.rpm <= 0:
            return None
        self.idle_load_pct = load_pct if self.idle_load_pct is None else min(self.idle_load_pct, load_pct)
        torque = (load_pct - self.idle_load_pct) / 100.0 * self.limits.peak_torque_nm
        c = torque / (self.kt * self.feed_mm / 1000)       # b times the lever arm, m^2
        x = self.x_radius_m
        if x is not None and x > 0:
            # the lever is the part's radius, x + b: Kt h b (x + b) = T, solved for b
            mm = (-x + math.sqrt(x * x + 4.0 * max(c, 0.0))) / 2.0 * 1000
        else:
            mm = c / (self.diameter_m / 2) * 1000
        if not (mm > 0.05 and self.in_cut):
            return None
        if abs(mm - self.depth_mm) > 0.1 * self.depth_mm:
            self.depth_mm = mm
            self.depth_from = "spindle load"
            self._depth_changed()
        if self.cut.active and (self.cut.depth_from != "spindle load" or mm > self.cut.depth_mm):
            # the cut's record (the refit's evidence): the deepest the load showed, over a
            # programmed depth_mm; the tool's entry and exit pass through lower loads
            self.cut.depth_mm, self.cut.depth_from = round(mm, 3), "spindle load"
        return round(mm, 3)

    def _depth_changed(self) -> None:
        """The depth became known, or changed, within a cut: its policy goes on (bans, budget, the
        lobes it began with) with that depth."""
        p = self.policy
        if p is None or not self.in_cut:
            return
        cut = self._cut()
        for attr in ("strategy", "fallback"):
            strategy = getattr(p, attr)
            if getattr(strategy, "cut", None) is not None:
                setattr(p, attr, replace(strategy, cut=cut))
        if self.strategy_name == "lobes" and self.policy_model is not None:
            p.when_no_stable_speed = self.when_no_stable_speed

    def _shallower(self, t: float | None) -> None:
        """A cut held with advice (every speed within reach chatters at its depth) that has been
        SHALLOWER x as deep for SHALLOWER_HELD_S (a profile's shallower part; not the tool's exit,
        which the spindle load reads shallower for a poll) is decided afresh at its next alarm:
        a stable speed may be within reach at the new depth.  ``t``: the depth's time (None: no
        depth now)."""
        p = self.policy
        if (t is None or p is None or p.advice is None or not self.in_cut
                or not 0 < self.depth_mm < SHALLOWER * p.advice.depth_mm):
            self._shallower_since = None
            return
        if self._shallower_since is None:
            self._shallower_since = t
        if t - self._shallower_since < SHALLOWER_HELD_S:
            return
        a = p.lift_advice()
        self._shallower_since = None
        payload = {"machine": self.machine, "rpm": self.rpm, "advice_depth_mm": a.depth_mm,
                   "depth_mm": round(self.depth_mm, 3), "depth_from": self.depth_from}
        self.ctx.log.info("suppression_advice_lifted", **payload)
        self.ctx.record("suppression_advice_lifted", payload)

    async def _cut_seen(self, by: str, on: bool, t: float | None = None) -> None:
        """The machine's depth register or the chatter analyzer's cut state
        (whichever this machine has; the first to see the chip starts the cut)."""
        was = bool(self.in_cut)
        self.in_cut[by] = on
        if not on:
            del self.in_cut[by]
        if self.in_cut and not was:
            self.policy = self._policy()    # a new cut: bans and budget start afresh
            self.pending = None
            self.held_back = None
            self._cut_started(time.time() if t is None else t)
        if self.avoid and by == "depth" and on and self.depth_mm > 0 and not self._avoided:
            self._avoided.add("depth")
            await self._avoid()
        if self.remember and self.in_cut:
            await self._recall()
        if was and not self.in_cut:
            self._follow, self._follow_told = None, False    # the program sets the next pass's speed
            self._cut_ended(time.time() if t is None else t)
            self._stop_ssv()
            if self._commanded:
                # a speed written as an override holds part after part: back to the program's
                # (through the guard; nothing to do where the next S word takes over)
                self._commanded = False
                r = await self.ctx.release(self.machine, "spindle_rpm", self.name)
                if r is not None and not r["sent"] and r.get("interlock"):
                    # a thread begun: held back by the supervisor, sent at the thread's end
                    self.ctx.log.info("speed_release_deferred", machine=self.machine, why=r["reason"])
                elif r is not None and not r["sent"]:
                    # the next parts run at the override until someone resets it: said loudly
                    payload = {"machine": self.machine, "why": r["reason"]}
                    self.ctx.log.error("speed_not_released", **payload)
                    self.ctx.record("speed_not_released", payload)
            if self.depth_from == "spindle load":
                self.depth_mm = 0.0
            self._avoided.clear()
            self._recalled = False
            self._shallower_since = None

    # -- cut records -----------------------------------------------------------------
    def _cut_started(self, t: float) -> None:
        self.cut.start(t, self.rpm)
        if self.depth_from == "register" and self.depth_mm > 0:
            self.cut.depth_mm, self.cut.depth_from = self.depth_mm, "register"
        elif self.program_depth_mm is not None:
            self.cut.depth_mm, self.cut.depth_from = self.program_depth_mm, "program"
        else:
            self.cut.depth_mm = self.cut.depth_from = None

    def _cut_ended(self, t: float, ended: str = "cut ended") -> None:
        if not self.cut.active:
            return
        rec = self.cut.end(t)
        rec["ended"] = ended
        rec["model"] = self.policy_model if self.policy is not None else self.model_name
        self.cuts_recorded += 1
        self.ctx.record("cut", rec)
        if self.learned is not None:
            self.learned.cut_recorded(rec)
        if self.remember:
            what = self.memory.learn(rec)
            if what:
                self.ctx.log.info(f"cure_{what}", rpm_entry=rec.get("rpm_start"), rpm_end=rec.get("rpm_end"))

    # -- remembered cures ------------------------------------------------------------
    def _load_memory(self) -> None:
        """The cures this machine's cut records teach, since the last ``suppress forget``."""
        # the newest records only: a cure older than them has been superseded or gone stale, and
        # the analyzer reads the bus once this is done
        rows = self.ctx.store.query("SELECT kind, payload FROM events WHERE source = ? AND kind IN "
                                    "('cut', 'suppression_cures_forgotten') ORDER BY id DESC LIMIT ?",
                                    (self.name, MEMORY_RECORDS))
        for r in reversed(rows):
            p = json.loads(r["payload"])
            if p.get("machine") != self.machine:
                continue
            if r["kind"] == "cut":
                self.memory.learn(p)
            else:
                self.memory.clear()
        if self.memory.cures:
            self.ctx.log.info("cures_remembered", cures=len(self.memory.cures))

    async def _recall(self) -> None:
        """The pass entering now: its remembered cure, once its depth is measured."""
        if (self._recalled or self.mode == "off" or self.policy is None or self.rpm is None
                or self.depth_from not in ("register", "spindle load") or not self.depth_mm > 0):
            return
        cure = self.memory.find(self.rpm, self.depth_mm, self.cut.tool_number)
        if cure is None:
            return          # none, or this pass is shallower than the one that chattered: wait
        self._recalled = True
        d = Decision(REMEMBERED, self.rpm, cure.rpm, None, None, None, cure.rpm / self.rpm,
                     f"remembered: a pass entering at {cure.rpm_entry:.0f} r/min"
                     + (f", {cure.depth_mm:g} mm deep," if cure.depth_mm else "")
                     + f" chattered there and was cured at {cure.rpm:.0f} r/min")
        drivable = bool(self._cut().drivable(np.array([cure.rpm]), self.limits)[0])
        taken = self.policy.take(time.monotonic(), self.rpm, d) if drivable else None
        if taken is None:
            self.ctx.log.info("cure_not_admissible", rpm=self.rpm, cure=cure.rpm,
                              why="beyond the spindle's torque at this depth" if not drivable else
                              "outside the speed cap, banned this part, or a change already holding")
            return
        await self._decided(taken, REMEMBERED)

    # -- the stability model: adopted refits ---------------------------------------------
    @property
    def models_dir(self):
        return self.ctx.store.path.parent / "stability-models"

    def _setup_json(self, include_base: bool = True) -> dict:
        out = {"tool": self.tool or None, "material": self.material or None}
        if self.tool_number is not None:
            out["tool_number"] = self.tool_number
        base = None if self.configured is None else self.configured.to_json()   # None: learned
        return {"base": base, **out} if include_base else out

    def _load_adopted(self) -> None:
        """The newest adopted model of this machine, if it was refitted from the model and set-up
        configured now; a damaged file is said (event) and the previous version tried."""
        if (self.configured is None and not self.learning) or not self.models_dir.is_dir():
            return
        files = stability_files.versions(self.models_dir, self.machine)
        for i, path in enumerate(reversed(files)):
            older = files[-2 - i].name if i + 1 < len(files) else "configured"
            try:
                model, doc = stability_files.load(path)
            except ValueError as e:
                self.ctx.log.error("stability_model_unreadable", file=path.name, error=str(e), using=older)
                self.ctx.record("stability_model_unreadable", {"machine": self.machine, "file": path.name,
                                                               "error": str(e), "using": older})
                continue
            want = self._setup_json()
            have = {k: doc.get(k) for k in want}
            if have != want:
                what = [k for k in want if have[k] != want[k]]
                why = (f"{path.name} was refitted from another {' and '.join(what)} than the configuration "
                       f"gives now (a new tap test or set-up supersedes it)")
                self.ctx.log.warning("stability_model_superseded", file=path.name, why=why)
                self.ctx.record("stability_model_superseded", {"machine": self.machine, "file": path.name,
                                                               "why": why, "using": "configured"})
                return
            self.lobes, self.model_name = model, path.name
            self.ctx.log.info("stability_model_loaded", file=path.name)
            return

    def use_model(self, model: StabilityModel | None, grid, name: str) -> None:
        """The lobes from the next cut on (the present cut finishes on the ones it began with)."""
        self.lobes, self.grid, self.model_name = model, grid, name

    def _mine(self, rec: dict) -> bool:
        """A cut record of this set-up (tool, material; the model's turret tool)."""
        return ((rec.get("tool"), rec.get("material")) == (self.tool or None, self.material or None)
                and (self.tool_number is None or rec.get("tool_number") in (None, self.tool_number)))

    def _cut_records(self) -> list[dict]:
        rows = self.ctx.store.query("SELECT payload FROM events WHERE kind = 'cut' AND source = ? ORDER BY id",
                                    (self.name,))
        return [p for r in rows if (p := json.loads(r["payload"])).get("machine") == self.machine]

    def _setup_cuts(self, what: str):
        """This set-up's recorded cuts as the refit's (the newest MAX_REFIT_SPEEDS cut speeds),
        what was left out and why, and how many records there were (a worker thread)."""
        records = self._cut_records()
        mine = [r for r in records if (r.get("tool"), r.get("material")) == (self.tool or None, self.material or None)]
        setup = len(mine)
        if self.tool_number is not None:     # the turret's other tools cut with other dynamics
            mine = [r for r in mine if r.get("tool_number") in (None, self.tool_number)]
        cuts, skipped = cut_rows(mine)
        if setup < len(records):
            skipped["cuts of another tool or material"] = len(records) - setup
        if len(mine) < setup:
            skipped[f"cuts with another turret tool than {self.tool_number}"] = setup - len(mine)
        left_out = "; ".join(f"{n} {why}" for why, n in skipped.items()) or "none"
        if cuts is None:
            raise RequestError(f"{what}: {len(records)} cut(s) of {self.machine} recorded, none usable "
                               f"(left out: {left_out})")
        if len(cuts) > MAX_REFIT_SPEEDS:
            # the refit's time grows faster than the cuts (3 s on 1,000, 20 s on 3,000); the newest tell most
            skipped[f"older than the newest {MAX_REFIT_SPEEDS} cut speeds"] = len(cuts) - MAX_REFIT_SPEEDS
            cuts = cuts.take(np.arange(len(cuts) - MAX_REFIT_SPEEDS, len(cuts)))
        return cuts, skipped, len(records)

    def _refit(self, holdout: float) -> tuple[dict, object]:
        """The refit of the model in use on this set-up's recorded cuts (a worker thread)."""
        cuts, skipped, n_records = self._setup_cuts("stability refit")
        try:
            r = refit(self.lobes, cuts, holdout_fraction=holdout)
        except ValueError as e:
            left_out = "; ".join(f"{n} {why}" for why, n in skipped.items()) or "none"
            raise RequestError(f"stability refit on {len(cuts)} cut speeds of {self.machine}: {e} "
                               f"(left out: {left_out})") from None
        out = {"machine": self.machine, "setup": self._setup_json(include_base=False),
               "model_before_name": self.model_name, "cut_records": n_records, "left_out": skipped,
               **r.to_json(), "adopt": bool(r.effects)}
        out["reason"] = r.conclusion if r.effects else "; ".join([r.conclusion, *r.rejected])
        return out, r

    def _adopt(self, out: dict, r, by: str | None) -> str:
        doc = {**self._setup_json(), "machine": self.machine, "model": r.model.to_json(),
               "refitted_from": self.model_name, "created": time.time(), "by": by,
               "effects": out["effects"], "before": out["before"], "after": out["after"],
               "cuts": out["cuts"], "heldout": out["heldout"]}
        path = stability_files.save(self.models_dir, self.machine, doc)
        return path.name

    async def _stability(self, args: dict) -> dict:
        a = Args("stability", args)
        action = a.getstr("action", "status", choices=("status", "refit", "learn"))
        dry = a.getbool("dry_run", False)
        holdout = a.getfloat("holdout", 0.3, minval=0.05, maxval=0.9)
        by = a.getstr("by", None)
        a.check_unused()
        if action == "status":
            return self.stability_status()
        if action == "learn":
            if self.learned is None:
                raise RequestError(f"stability learn: {self.name} has a modal model configured; refit it on the "
                                   f"cuts instead (lathectl stability refit)")
            require_operator("stability learn")
            return await self.learned.learn_requested(by)
        if not dry:
            require_operator("stability refit")
        if self.configured is None:
            raise RequestError(f"stability refit: {self.name} has no modal model (modes, kf) to refit"
                               + ("; it learns one from the cut records (lathectl stability learn)"
                                  if self.learned is not None else ""))
        if self._refitting:
            raise RequestError("stability refit: a refit is already running; wait for its result")
        self._refitting = True
        try:
            out, r = await offload(self._refit, holdout)
            out["dry_run"] = dry
            if dry:
                return out
            if not out["adopt"]:
                self.ctx.record("stability_refit_not_adopted", {
                    "machine": self.machine, "model": self.model_name, "reason": out["reason"],
                    "before": out["before"], "after": out["after"], "cuts": out["cuts"], "by": by})
                self.last_refit = out
                return out
            name = await asyncio.to_thread(self._adopt, out, r, by)
            model = StabilityModel.from_json(r.model.to_json())     # as the file holds it
            grid = await asyncio.to_thread(lobe_grid, model, self.limits)
            before = self.model_name
            # the next cut's policy takes the new lobes; the present cut finishes on the old
            self.lobes, self.grid, self.model_name = model, grid, name
            out["model_after_name"] = name
            self.ctx.log.warning("stability_model_adopted", file=name, effects=[e["effect"] for e in out["effects"]])
            self.ctx.record("stability_model_adopted", {
                "machine": self.machine, "file": name, "model_before": before, "model": out["model_after"],
                "effects": out["effects"], "before": out["before"], "after": out["after"],
                "cuts": out["cuts"], "heldout": out["heldout"], "by": by})
            self.last_refit = out
            return out
        finally:
            self._refitting = False

    def stability_status(self) -> dict:
        return {"machine": self.machine, "model": self.model_name,
                "lobes": None if self.lobes is None else self.lobes.to_json(),
                "configured": None if self.configured is None else self.configured.to_json(),
                "tool": self.tool or None, "material": self.material or None,
                "cuts_recorded": self.cuts_recorded,
                "learning": None if self.learned is None else self.learned.status(),
                "last_refit": None if self.last_refit is None else
                {k: self.last_refit.get(k) for k in ("adopt", "reason", "model_after_name", "dry_run")}}

    def predicted_unstable(self, rpm: float, depth_mm: float) -> tuple[bool, float]:
        """The lobes' verdict on a cut: (unstable, worst b_lim in mm within +-3 % of ``rpm``)."""
        n, _, worst = self.grid
        w = float(np.interp(rpm, n, worst))
        return w < LobeSelection.margin * depth_mm / 1000, w * 1000

    async def _avoid(self) -> None:
        if (self.mode == "off" or self.rpm is None or self.rpm <= 0 or self.grid is None
                or self.policy_model is None):     # another turret tool: the lobes are not its
            return
        unstable, b_mm = self.predicted_unstable(self.rpm, self.depth_mm)
        if not unstable:
            return
        d = self.policy.observe(time.monotonic(), self.rpm, True)
        if d is None:
            return
        if isinstance(d, Advice):
            await self._decided(d, "predicted")
            return
        await self._decided(replace(d, reason=f"predicted at cut entry: {self.depth_mm:g} mm deep, the lobes "
                                              f"allow {b_mm:.2f} mm at {self.rpm:.0f} r/min; {d.reason}"),
                            "predicted")

    async def _decided(self, d: Decision | Advice, trigger: str) -> None:
        """Auto: act. Manual: hold it for ``lathectl suppress now`` and record the proposal.
        Advice (no stable speed within reach): recorded in either mode; nothing to act on."""
        if isinstance(d, Advice):
            self._advise(d, trigger)
            return
        if self.mode == "auto":
            await self._act(d, trigger=trigger)
        else:
            self.pending, self.pending_trigger = d, trigger
            self.ctx.record("suppression_proposed", {**d.record(), "machine": self.machine, "mode": "manual",
                                                     "trigger": trigger})

    async def _on_chatter(self, s: Sample) -> None:
        key = {"chatter_index": "index", "chatter_threshold": "threshold",
               "chatter_frequency_hz": "frequency"}.get(s.quantity)
        if key:
            self.chat[key] = s.value
            return
        if s.quantity == "cutting":
            await self._cut_seen("chatter", s.value > 0.5, s.t)
            return
        if s.quantity == "cut_contact":      # the chip, after an approach at feed in air
            self.cut.contact(s.t)
            return
        if s.quantity == "dwell":            # the feed stopped mid-pass, or went on
            self.cut.dwell(s.t, s.value > 0.5)
            return
        if s.quantity != "chatter_alarm":
            return
        alarm = s.value > 0.5
        self.cut.chatter(s.t, alarm, self.chat["frequency"] if alarm else None)
        if alarm and not self.chat["alarm"]:
            self.alarm_wall_t = s.t
        self.chat["alarm"], self.chat["t"] = alarm, s.t
        if self.mode == "off" or self.policy is None or self.rpm is None or self.held_back is not None:
            return
        d = self.policy.observe(time.monotonic(), self.rpm, alarm, self.chat["frequency"] if alarm else None,
                                self.chat["index"], self.chat["threshold"])
        if d is None:
            p = self.policy
            if (alarm and p.exhausted and self._told_exhausted is not p and p.advice is None
                    and not any(c.variation is not None for c in p.changes)):   # advised, or modulating
                self._exhausted()
            return
        await self._decided(d, "alarm")

    def _followed(self, rpm: float, t: float) -> None:
        """Did the spindle reach the speed sent?  A write the control accepted but does not obey
        (an override or speed clamp on the control, a program that sets S again) is said once a cut:
        suppression's evidence assumes the new speed."""
        target, sent_t, by = self._follow
        if abs(rpm - target) <= FOLLOW_BAND * target:
            self._follow = None
        elif t > by:
            self._follow, self._follow_told = None, True
            if self.policy is not None:
                self.policy.ban(target)         # not asked for again this cut (a clamp on the control)
            self.ctx.record("spindle_not_following", {"machine": self.machine, "sent_rpm": round(target, 1),
                                                      "rpm": rpm, "after_s": round(t - sent_t, 2)})
            self.ctx.log.warning("spindle_not_following", machine=self.machine, sent_rpm=round(target, 1),
                                 rpm=rpm, after_s=round(t - sent_t, 2))

    def _exhausted(self) -> None:
        """Chatter goes on and suppression has no speed left to try in this cut: said once."""
        p = self._told_exhausted = self.policy
        why = (f"{len(p.changes)} speed changes in this cut, the most it makes" if len(p.changes) >= p.max_changes else
               f"no speed within {p.limits.min_rpm:.0f}-{p.limits.max_rpm:.0f} r/min that the strategy or "
               f"the rated speed would take (left or banned, beyond the speed cap or the spindle's torque)")
        self.ctx.record("suppression_exhausted", {"machine": self.machine, "rpm": self.rpm, "reason": why,
                                                  "changes": len(p.changes)})
        self.ctx.log.warning("suppression_exhausted", machine=self.machine, rpm=self.rpm, reason=why)

    async def _act(self, d: Decision, by: str | None = None, trigger: str = "alarm") -> dict:
        source = by or self.name
        payload = {**d.record(), "machine": self.machine, "mode": self.mode, "trigger": trigger,
                   # the stability model whose lobes chose the speed (a cut keeps the one it began with)
                   "model": self.policy_model if self.policy is not None else self.model_name}
        if d.variation is not None:
            # the modulation's first speed, asked here: refused, nothing modulates
            result = await self.ctx.command(Command(self.machine, "spindle_rpm", float(
                np.asarray(d.variation.profile(0.0, d.rpm_before))), source,
                reason=f"speed variation ({d.variation.kind})"))
            if result["sent"]:
                self._start_ssv(d)
                result = {**result, "reason": "modulating"}
            self._commanded = self._commanded or not result.get("interlock")
        else:
            result = await self.ctx.command(Command(self.machine, "spindle_rpm", float(d.rpm_after), source,
                                                    reason=f"chatter suppression ({d.strategy})",
                                                    context={"strategy": d.strategy}))
        if result.get("interlock"):
            # a thread being cut: its speed holds to its last pass; this cut asks nothing more
            self.held_back = result["reason"]
        elif d.variation is None:
            if not result["sent"] and self.policy is not None:
                self.policy.ban(d.rpm_after)    # refused by the guard: never asked for again this part
            # a write that failed may still have reached the control: the cut's end asks the
            # driver, which releases only what it finds of lathed's
            self._commanded = True
            if result["sent"] and self.rpm is not None and not self._follow_told:
                now = time.time()
                # an override lands on the control's step: the speed it gives, not the one asked
                self._follow = (float(result.get("rpm_effective", d.rpm_after)), now, now + FOLLOW_SLACK_S
                                + ramp_time_s(self.rpm, d.rpm_after, self.limits.accel_rpm_per_s))
            if result["sent"] and self.alarm_wall_t is not None and trigger == "alarm":
                # from the first alarm window's sample time to the write's return
                self.latency_ms.append(1000 * (time.time() - self.alarm_wall_t))
                payload["alarm_to_write_ms"] = round(self.latency_ms[-1], 1)
        payload.update(sent=result["sent"], refused=result["reason"], by=source)
        if self.cut.active:
            # alarms count against the new speed once the policy's hold (ramp, settle) is over
            hold = self.policy.hold_until() - time.monotonic() if self.policy is not None else 0.0
            now = time.time()
            self.cut.action(now, payload, now + max(0.0, hold))
        self.actions += 1
        self.last_action = payload
        self.last_was_advice = False
        self.ctx.log.info("suppression_action", strategy=d.strategy, rpm_before=d.rpm_before,
                          rpm_after=d.rpm_after, sent=result["sent"], trigger=trigger)
        self.ctx.record("suppression_action", payload)
        return payload

    def _advise(self, a: Advice, trigger: str) -> dict:
        """The speed is held: say why and what would cure the chatter (no command is sent)."""
        payload = {**a.record(), "machine": self.machine, "mode": self.mode, "trigger": trigger,
                   "model": self.policy_model if self.policy is not None else self.model_name,
                   "depth_from": self.depth_from if self.depth_mm > 0 else "program"}
        self.cut.advised(a.advice)
        self.advisories += 1
        self.last_advice = payload
        self.last_was_advice = True
        self.ctx.log.warning("suppression_advice", rpm=round(a.rpm), depth_mm=a.depth_mm,
                             limit_mm=round(a.limit_mm, 3), advice=a.advice, trigger=trigger)
        self.ctx.record("suppression_advice", payload)
        return payload

    # -- spindle speed variation ---------------------------------------------------
    def _start_ssv(self, d: Decision) -> None:
        self._stop_ssv()
        self._ssv_task = asyncio.create_task(self._ssv(d.rpm_before, d.variation))

    def _stop_ssv(self) -> None:
        if self._ssv_task is not None:
            self._ssv_task.cancel()
            self._ssv_task = None

    async def _ssv(self, n0: float, var: SpeedVariation) -> None:
        t0 = time.monotonic()       # its first speed was written by _act, just now
        while True:
            await asyncio.sleep(SSV_STEP_S)
            n = float(np.asarray(var.profile(time.monotonic() - t0, n0)))
            self._commanded = True       # as above: a failed write may have reached the control
            r = await self.ctx.command(Command(self.machine, "spindle_rpm", n, self.name,
                                               reason=f"speed variation ({var.kind})"))
            if not r["sent"]:
                self.ctx.log.warning("ssv_stopped", reason=r["reason"])
                return

    # -- operator ------------------------------------------------------------------
    async def _control(self, args: dict) -> dict:
        a = Args("suppress", args)
        action = a.getstr("action", "status", choices=(*MODES, "now", "forget", "status"))
        by = a.getstr("by", "operator")
        a.check_unused()
        if action != "status":
            require_operator(f"suppress {action}")
        if action in MODES:
            old, self.mode = self.mode, action
            self.ctx.record("suppression_mode", {"machine": self.machine, "from": old, "to": action,
                                                 "by": by})
            if action == "off":
                self._stop_ssv()
            return self.status()
        if action == "forget":
            n = self.memory.clear()
            self.ctx.record("suppression_cures_forgotten", {"machine": self.machine, "cures": n, "by": by})
            return self.status()
        if action == "now":
            d, trigger = self.pending, self.pending_trigger
            if d is None:
                trigger = "alarm"
                if not self.chat["alarm"]:
                    raise RequestError("no chatter alarm on this machine now; nothing to suppress")
                if self.rpm is None or self.policy is None:
                    raise RequestError("the machine is not cutting (no spindle speed or depth of cut known)")
                d = self.policy.observe(time.monotonic(), self.rpm, True, self.chat["frequency"],
                                        self.chat["index"], self.chat["threshold"])
                if isinstance(d, Advice):
                    self._advise(d, trigger)
                if isinstance(d, Advice) or (d is None and self.policy.advice is not None):
                    raise RequestError(f"speed held: {self.policy.advice.advice}")
                if d is None:
                    raise RequestError("no admissible speed: every candidate is banned for this part or "
                                       "the policy is holding after a change")
            self.pending = None
            return await self._act(d, by=by, trigger=trigger)
        return self.status()

    def live_view(self) -> dict | None:
        """The stability lobes for the operator view: limiting depth (mm) over the
        spindle's range, and where the cut is now (speed, depth)."""
        if self.grid is None:
            return None
        if self._lobe_view is None or self._lobe_view[0] is not self.grid:   # the curve is computed once
            n, b, _ = self.grid
            step = max(1, len(n) // LOBE_POINTS)
            blim = np.minimum(b[::step] * 1000, LOBE_CAP_MM)   # inf (no lobe below the cap) drawn at the cap
            self._lobe_view = (self.grid, rounded(n[::step], 5), rounded(blim))
        return {"rpm": self._lobe_view[1], "blim_mm": self._lobe_view[2], "now_rpm": self.rpm,
                "now_depth_mm": round(self.depth_mm, 3)}

    def status(self) -> dict:
        lat = sorted(self.latency_ms)
        return {"mode": self.mode, "strategy": self.strategy_name, "machine": self.machine,
                "model": self.model_name, "model_tool_number": self.tool_number,
                "cut_tool_number": self.cut.tool_number,
                "cuts_recorded": self.cuts_recorded, "chatter_alarm": self.chat["alarm"],
                "pending": None if self.pending is None else self.pending.record(),
                "actions": self.actions, "last_action": self.last_action, "held_back": self.held_back,
                "when_no_stable_speed": self.when_no_stable_speed if self.strategy_name == "lobes" else None,
                "advisories": self.advisories, "last_advice": self.last_advice,
                "last_was_advice": self.last_was_advice,
                "alarm_to_write_ms_median": lat[len(lat) // 2] if lat else None,
                "avoid": self.avoid, "depth_mm": round(self.depth_mm, 3), "depth_from": self.depth_from,
                "remember": self.remember, "cures": [c.to_json() for c in self.memory.cures],
                "summary": f"mode {self.mode}, strategy {self.strategy_name}"
                           + (", avoids predicted chatter at cut entry" if self.avoid else "")
                           + (f", remembers {len(self.memory.cures)} cure(s)" if self.remember else "")
                           + (f", model {self.model_name}" if self.lobes is not None else "")
                           + (", no model yet: learns one from the cuts" if self.learned is not None and self.lobes is None
                              else "")
                           + (f" (tool {self.tool_number})" if self.lobes is not None and self.tool_number is not None
                              else "")
                           + (f"; tool {self.cut.tool_number} has no model: model-free"
                              if self.lobes is not None and not self._model_applies() else "")
                           + f", {self.actions} action(s)"
                           + (f", {self.advisories} held with advice (no stable speed within reach)"
                              if self.advisories else "")}


@hookimpl
def lathed_analyzer_types():
    return {"suppression": SuppressionAnalyzer}
