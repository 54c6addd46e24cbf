"""Chatter suppression: on a chatter alarm, change the spindle speed through the safety guard.
The strategies are in suppression_strategies.py, the stability model's refits in
suppression_models.py. Behaviour: docs/chatter.md; keys: docs/configuration.md."""
from __future__ import annotations

import asyncio
import time

import numpy as np

from lathed import hookimpl
from lathed.analysis.cures import TRIGGER as REMEMBERED, CureMemory
from lathed.analysis.cut_geometry import CutGeometry
from lathed.analysis.cut_log import CutTracker
from lathed.analysis.modal import parse_mode
from lathed.analysis.speed_selection import Advice, Cut, Decision, SuppressionPolicy, lobe_grid
from lathed.analysis.stability import StabilityModel
from lathed.analyzer import Analyzer
from lathed.args import Args
from lathed.caller import require_operator
from lathed.bus import Sample
from lathed.config import Section
from lathed.control import RequestError
from lathed.display import rounded
from lathed_plugins.stability_learning import LearnedStability
from lathed_plugins.suppression_commands import SpindleCommands
from lathed_plugins.suppression_models import ModelRefits, left_out, setup_rows
from lathed_plugins.suppression_strategies import STRATEGIES, check_keys, predicted_unstable

LOBE_POINTS = 600      # points of the lobe chart sent to a screen
LOBE_CAP_MM = 20.0

MODES = ("auto", "manual", "off")
MAX_REFIT_SPEEDS = 2000   # cut speeds a daemon refit uses: the newest
MEMORY_RECORDS = 5000     # cut records the remembered cures are rebuilt from at start: the newest
SHALLOWER = 0.9           # a cut held with advice that gets this much shallower ...
SHALLOWER_HELD_S = 0.5    # ... for this long (not the tool's exit, a poll or two) is decided afresh


class SuppressionAnalyzer(Analyzer):
    def __init__(self, name: str, section: Section):
        super().__init__(name, section)
        self.chatter = section.getstr("chatter")
        self.machine = section.getstr("machine")
        self.mode = section.getstr("mode", "auto", choices=MODES)
        kind = STRATEGIES[section.getstr("strategy", "frequency", choices=tuple(STRATEGIES))]
        check_keys(section, kind)      # a key of another strategy is refused, not ignored
        texts = section.getlist("modes", [])
        try:
            modes = tuple(parse_mode(t) for t in texts)
        except ValueError as e:
            raise section.error("modes", str(e)) from None
        kf = section.getfloat("kf", 2.0e9, above=0)
        kt = section.getfloat("kt", 1.5e9, above=0)
        diameter_m = section.getfloat("diameter_mm", 30.0, above=0) / 1000
        # the X axis tells the diameter being cut (a profile, another part) where diameter_mm is one number
        x_axis = section.getstr("x_axis", "", choices=("", "radius", "diameter"))
        self.strategy = kind(section)
        self.limits = self.strategy.limits
        self.geometry = CutGeometry(kt, self.limits.peak_torque_nm, diameter_m, x_axis)
        self.remember = section.getbool("remember", True)
        self.tool = section.getstr("tool", "")
        # the turret position the modal model was measured at: other tools' cuts are not its
        self.tool_number: int | None = section.getint("tool_number", None, minval=0, maxval=9999)
        self.material = section.getstr("material", "")
        self.program_depth_mm = section.getfloat("depth_mm", 0.0, minval=0.0, maxval=50.0) or None
        # the tap test's model; the lobes in use are it or the adopted refit of it, or a learned one
        self.configured = StabilityModel(modes, kf) if modes else None
        self.lobes = self.configured
        self.grid = None    # the lobes over the spindle's range, computed once at start
        self.model_name = "configured" if modes else "none"
        self.learning = self.strategy.learns and not modes     # lobes without a tap test
        self.learned = LearnedStability(self, kf) if self.learning else None
        self.refits = ModelRefits(self)
        self.policy_model = self.model_name   # the model the running cut's policy was built with
        self._models_loaded = False
        self.cut = CutTracker(self.machine, self.tool, self.material)
        self.memory = CureMemory(self.tool, self.material)
        self._memory_loaded = False
        self._recalled = False                 # the pass in the cut has been given its cure
        self._told_exhausted: SuppressionPolicy | None = None   # the cut's policy said it had no speed left
        self.commands = SpindleCommands(self)
        self.held_back: str | None = None      # the machine's interlock refused this cut's speed (a thread)
        self._shallower_since: float | None = None   # the cut held with advice is shallower since
        self.cuts_recorded = 0
        self._lobe_view = None
        self.policy: SuppressionPolicy | None = None
        self.depth_mm = 0.0
        self.depth_from: str | None = None      # "register" | "spindle load"
        self.in_cut = False                     # the chatter analyzer's cut state (its one owner)
        self._avoided: set[str] = set()
        self.rpm: float | None = None
        self.chat = {"index": None, "threshold": None, "frequency": None, "rpm": None, "alarm": False, "t": None}
        self.actions = 0                       # a count: the records keep every action
        self.last_action: dict | None = None
        self.advisories = 0
        self.last_advice: dict | None = None
        self.last_was_advice = False     # which of last_action / last_advice came last (for a screen)
        self.pending: Decision | None = None
        self.pending_trigger = "alarm"
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
        return self.geometry.cut(self._depth_known_mm())

    def _model_applies(self) -> bool:
        """The cut's tool is the one the modal model is for (or nothing says otherwise)."""
        return self.tool_number is None or self.cut.tool_number in (None, self.tool_number)

    def _policy(self) -> SuppressionPolicy:
        # a cut keeps the lobes it started with: an adoption mid-cut applies from the next cut;
        # another turret tool's cut has none (its dynamics are not the tap test's)
        lobes = self.lobes if self._model_applies() else None
        self.policy_model = self.model_name if lobes is not None else None
        return self.strategy.policy(self._cut(), self.rpm, lobes, self.grid, self._depth_known_mm() is not None)

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
            self.strategy.stop()
            # a cut the daemon stops in is evidence too, up to now: recorded, never lost
            self._cut_ended(time.time(), ended=ended)
            if self.learned is not None:
                await self.learned.stop()

    async def _on_machine(self, s: Sample) -> None:
        if s.quantity == "spindle_rpm":
            self.rpm = s.value
            self.cut.speed(s.t, s.value)
            self.commands.speed(s.value, s.t)
        elif s.quantity == "feed_mm_rev" and s.value > 0:
            self.geometry.feed_mm = self.cut.feed_mm_rev = s.value
        elif s.quantity == "tool_number":
            was, self.cut.tool_number = self.cut.tool_number, int(s.value)   # its own cures
            if self.in_cut and was != self.cut.tool_number:
                # a turret indexes out of the cut: a change seen in one is a late poll, and the
                # whole cut is the new tool's (its model, or none)
                self.policy = self._policy()
        elif s.quantity == "x_mm" and self.geometry.x_axis:
            self.geometry.x(s.value)
        elif s.quantity == "depth_of_cut_mm":
            self.depth_from = "register"
            changed = s.value > 0 and s.value != self.depth_mm
            self.depth_mm = s.value
            if s.value > 0:
                self.cut.depth_mm, self.cut.depth_from = s.value, "register"
            if changed:
                self._depth_changed()      # the vibration may have seen the chip first
            if self.in_cut and s.value > 0:
                # the cut's depth known: a new speed at entry, a cure remembered for it
                if self.strategy.avoid and not self._avoided:
                    self._avoided.add("depth")
                    await self._avoid()
                if self.remember:
                    await self._recall()
            self._shallower(s.t if s.value > 0 else None)
        elif s.quantity == "spindle_load_pct" and self.depth_from != "register":
            est = self._depth_from_load(s.value)
            self._shallower(s.t if est is not None else None)
            if est is not None:
                # the parts' records take it (lathed.records.PartTracker): a real CNC has no depth register
                self.ctx.bus.publish(Sample(self.name, "depth_est_mm", est, "mm", s.t))
            # est None: no chip yet (a cut the cutting-feed signal started in air)
            if self.strategy.avoid and self.in_cut and self.depth_from == "spindle load" and est is not None \
                    and not self._avoided:
                self._avoided.add("load")
                await self._avoid()
            if self.remember and self.in_cut:
                await self._recall()

    def _depth_from_load(self, load_pct: float) -> float | None:
        """Without a depth register the lobes need the depth: the spindle load's estimate, mm,
        while cutting (None otherwise)."""
        if self.rpm is None or self.rpm <= 0:
            return None
        mm = self.geometry.depth_from_load(load_pct)
        if mm is None or not self.in_cut:
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
        """The depth became known, or changed, within a cut: its policy goes on with it."""
        if self.policy is not None and self.in_cut:
            self.strategy.depth_changed(self.policy, self._cut(), self.policy_model is not None)

    def _shallower(self, t: float | None) -> None:
        """A cut held with advice that has been shallower for a while is decided afresh at its next
        alarm: a stable speed may be within reach now. ``t``: the depth's time (None: no depth)."""
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

    async def _cut_seen(self, on: bool, t: float | None = None) -> None:
        """The chatter analyzer's cut state (lathed.analysis.cut.state: it alone combines the
        sources, the depth register among them where cut_from names it)."""
        was, self.in_cut = self.in_cut, on
        if self.in_cut and not was:
            self.policy = self._policy()    # a new cut: bans and budget start afresh
            self.pending = None
            self.held_back = None
            self._cut_started(time.time() if t is None else t)
        if self.strategy.avoid and on and self.depth_from == "register" and self.depth_mm > 0 and not self._avoided:
            self._avoided.add("depth")
            await self._avoid()
        if self.remember and self.in_cut:
            await self._recall()
        if was and not self.in_cut:
            self._cut_ended(time.time() if t is None else t)
            self.strategy.stop()
            await self.commands.cut_ended()
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
        rows = self.ctx.store.events(limit=MEMORY_RECORDS, kind=["cut", "suppression_cures_forgotten"],
                                     source=self.name)
        for r in rows:
            p = r["payload"]
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

    # -- the stability model (refits: suppression_models.py) ----------------------------
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
        self.refits.load_adopted()

    def use_model(self, model: StabilityModel | None, grid, name: str) -> None:
        """The lobes from the next cut on (the present cut finishes on the ones it began with)."""
        self.lobes, self.grid, self.model_name = model, grid, name

    def _mine(self, rec: dict) -> bool:
        """A cut record of this set-up (tool, material; the model's turret tool)."""
        return ((rec.get("tool"), rec.get("material")) == (self.tool or None, self.material or None)
                and (self.tool_number is None or rec.get("tool_number") in (None, self.tool_number)))

    def _cut_records(self) -> list[dict]:
        rows = self.ctx.store.events(limit=None, kind="cut", source=self.name)
        return [p for r in rows if (p := r["payload"]).get("machine") == self.machine]

    def _setup_cuts(self, what: str):
        """This set-up's recorded cuts (the newest MAX_REFIT_SPEEDS cut speeds), what was left
        out and why, and how many records there were (a worker thread)."""
        records = self._cut_records()
        cuts, skipped = setup_rows(records, self.tool or None, self.material or None, self.tool_number,
                                   MAX_REFIT_SPEEDS)
        if cuts is None:
            raise RequestError(f"{what}: {len(records)} cut(s) of {self.machine} recorded, none usable "
                               f"(left out: {left_out(skipped)})")
        return cuts, skipped, len(records)

    async def _stability(self, args: dict) -> dict:
        return await self.refits.control(args)

    def stability_status(self) -> dict:
        return self.refits.status()

    def predicted_unstable(self, rpm: float, depth_mm: float) -> tuple[bool, float]:
        return predicted_unstable(self.grid, rpm, depth_mm)

    async def _avoid(self) -> None:
        if (self.mode == "off" or self.rpm is None or self.rpm <= 0 or self.grid is None
                or self.policy_model is None):     # another turret tool: the lobes are not its
            return
        d = self.strategy.predicted(self.policy, self.grid, self.rpm, self.depth_mm)
        if d is not None:
            await self._decided(d, "predicted")

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
               "chatter_frequency_hz": "frequency", "chatter_rpm": "rpm"}.get(s.quantity)
        if key:
            self.chat[key] = s.value
            return
        if s.quantity == "cutting":
            await self._cut_seen(s.value > 0.5, s.t)
            return
        if s.quantity == "cut_contact":      # the chip, after an approach at feed in air
            self.cut.contact(s.t)
            return
        if s.quantity == "dwell":            # the feed stopped mid-pass, or went on
            self.cut.dwell(s.t, s.value > 0.5)
            return
        if s.quantity == "chatter_index_judged":     # a speed still rising is not called stable
            self.cut.index(s.t, s.value)
            return
        if s.quantity != "chatter_alarm":
            return
        alarm = s.value > 0.5
        self.cut.chatter(s.t, alarm, self.chat["frequency"] if alarm else None)
        if alarm and not self.chat["alarm"]:
            self.alarm_wall_t = s.t
        self.chat["alarm"], self.chat["t"] = alarm, s.t
        if not alarm:
            self.chat["rpm"] = None
        if self.mode == "off" or self.policy is None or self.rpm is None or self.held_back is not None:
            return
        if alarm and not self.policy.settling(time.monotonic()) and self.commands.disagree(self.chat["rpm"]):
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
        result = await self.commands.send(d, source)
        if result.get("interlock"):
            # a thread being cut: its speed holds to its last pass; this cut asks nothing more
            self.held_back = result["reason"]
        elif d.variation is None and result["sent"] and self.alarm_wall_t is not None and trigger == "alarm":
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
                self.strategy.stop()
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
                if self.commands.disagree(self.chat["rpm"]):
                    raise RequestError(f"speed held: the alarm was judged at {self.chat['rpm']:.0f} r/min, "
                                       f"the machine reads {self.rpm:.0f} r/min; try again when they agree")
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
        return {"mode": self.mode, "strategy": self.strategy.name, "machine": self.machine,
                "model": self.model_name, "model_tool_number": self.tool_number,
                "cut_tool_number": self.cut.tool_number,
                "cuts_recorded": self.cuts_recorded, "chatter_alarm": self.chat["alarm"],
                "pending": None if self.pending is None else self.pending.record(),
                "actions": self.actions, "last_action": self.last_action, "held_back": self.held_back,
                "when_no_stable_speed": self.strategy.when_no_stable_speed,
                "advisories": self.advisories, "last_advice": self.last_advice,
                "last_was_advice": self.last_was_advice,
                "alarm_to_write_ms_median": lat[len(lat) // 2] if lat else None,
                "avoid": self.strategy.avoid, "depth_mm": round(self.depth_mm, 3), "depth_from": self.depth_from,
                "remember": self.remember, "cures": [c.to_json() for c in self.memory.cures],
                "summary": f"mode {self.mode}, strategy {self.strategy.name}"
                           + (", avoids predicted chatter at cut entry" if self.strategy.avoid else "")
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
