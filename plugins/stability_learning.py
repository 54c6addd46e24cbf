"""The stability model learned from a machine's own cut records, for a
suppression analyzer with strategy "lobes" and no modal model configured
(numeric core: lathed.analysis.stability.learn; docs/stability.md).

Until a learn is trusted the analyzer has no lobes and answers chatter
model-free; each time the set-up's usable cut speeds have grown by a quarter
(at least MIN_CUTS, then 10 more at least) the model is learned again in a
worker process, off the loop.  A trusted learn is saved as a new version
(lathed.analysis.stability.files, ``base`` null), recorded as
``stability_model_learned`` and used from the next cut; a learn that is not
trusted is recorded as ``stability_learn_not_trusted`` with why and about
how many cut speeds it needs; a model in use that the newest later cuts
judge surely below the bar is recorded as ``stability_model_withdrawn`` and the
analyzer goes back to model-free.  Not an entry point: the suppression
plugin owns one.
"""
from __future__ import annotations

import asyncio
import functools
import time

from lathed.analysis.cut_log import cut_rows
from lathed.analysis.speed_selection import lobe_grid
from lathed.analysis.stability import files as stability_files
from lathed.analysis.stability.learn import Learned, Learner, learn
from lathed.control import RequestError
from lathed.worker import in_process


class LearnedStability:
    """One suppression analyzer's learned model: when to learn, and what it says."""

    def __init__(self, owner, kf: float):
        self.owner = owner            # the SuppressionAnalyzer: its records, set-up and lobes
        self.kf = kf
        self.learner = Learner()
        self.speeds = 0               # usable cut speeds of the set-up recorded
        self.task: asyncio.Task | None = None
        self.last: dict | None = None

    async def start(self) -> None:
        """Count the cut speeds recorded before this start; learn at once when there are enough."""
        try:
            cuts, _, _ = await asyncio.to_thread(self.owner._setup_cuts, "stability learn")
            self.speeds = len(cuts)
        except RequestError:
            self.speeds = 0
        self.maybe_learn()

    def cut_recorded(self, rec: dict) -> None:
        if self.owner._mine(rec):
            cuts, _ = cut_rows([rec])
            self.speeds += 0 if cuts is None else len(cuts)
        self.maybe_learn()

    def maybe_learn(self) -> None:
        if (self.task is None or self.task.done()) and self.learner.due(self.speeds):
            self.task = asyncio.create_task(self._learn_logged())

    async def _learn_logged(self) -> None:
        try:
            await self.learn_now()
        except RequestError as e:         # no usable cut yet: said, and tried again later
            self.owner.ctx.log.info("stability_learn_skipped", why=str(e))
            self.learner.next_at = self.speeds + Learner.STEP
        except Exception as e:            # the analyzer goes on model-free or with its model
            self.owner.ctx.log.error("stability_learn_failed", error=f"{type(e).__name__}: {e}")
            self.learner.next_at = self.speeds + Learner.STEP

    async def learn_requested(self, by: str | None) -> dict:
        """An operator's ``lathectl stability learn``: one learn now, unless one runs."""
        if self.task is not None and not self.task.done():
            raise RequestError("stability learn: a learn is already running; its result is recorded as "
                               "stability_model_learned or stability_learn_not_trusted")
        self.task = asyncio.create_task(self.learn_now(by))
        return await self.task

    async def learn_now(self, by: str | None = None) -> dict:
        """Learn from the recorded cuts now; use the model if it is trusted.  The report."""
        o = self.owner
        cuts, skipped, n_records = await asyncio.to_thread(o._setup_cuts, "stability learn")
        self.speeds = max(self.speeds, len(cuts))
        o.ctx.log.info("stability_learn_started", cuts=len(cuts), records=n_records)
        # a process, not a thread: seconds of numpy in small steps would hold the GIL from the
        # loop that answers chatter
        learned: Learned = await in_process(functools.partial(learn, cuts, kf=self.kf), "lathed-stability-learn")
        what = self.learner.consider(learned, cuts, seen=self.speeds)
        out = {"machine": o.machine, "setup": o._setup_json(include_base=False), "cut_records": n_records,
               "left_out": skipped, "verdict": what, "summary": learned.summary(), **learned.to_json(),
               "model_name": o.model_name}
        payload = {"machine": o.machine, "cuts": learned.cuts, "summary": learned.summary(), "by": by}
        if what == "adopted":
            name = await asyncio.to_thread(self._save, learned, by)
            grid = await asyncio.to_thread(lobe_grid, learned.model, o.limits)
            before = o.model_name
            o.use_model(learned.model, grid, name)       # from the next cut on
            out["model_name"] = name
            o.ctx.log.warning("stability_model_learned", file=name, cuts=learned.cuts)
            o.ctx.record("stability_model_learned", {**payload, "file": name, "model_before": before,
                                                     "learned": learned.to_json()})
        elif what == "withdrawn":
            before = o.model_name
            o.use_model(None, None, "none")
            out["model_name"] = "none"
            o.ctx.log.warning("stability_model_withdrawn", file=before, why=learned.summary())
            o.ctx.record("stability_model_withdrawn", {**payload, "file": before})
        else:
            o.ctx.log.info("stability_learn_not_trusted", cuts=learned.cuts, kept=o.model_name,
                           why="; ".join(learned.why_not))
            o.ctx.record("stability_learn_not_trusted", {**payload, "why_not": learned.why_not,
                                                         "cuts_needed": learned.cuts_needed, "kept": o.model_name})
        self.last = {"t": time.time(), "verdict": what, "cuts": learned.cuts, "trusted": learned.trusted,
                     "summary": learned.summary(), "cuts_needed": learned.cuts_needed}
        return out

    def _save(self, learned: Learned, by: str | None) -> str:
        o = self.owner
        doc = {**o._setup_json(), "machine": o.machine, "model": learned.model.to_json(), "refitted_from": None,
               "created": time.time(), "by": by or "learning", "learned": learned.to_json()}
        return stability_files.save(o.models_dir, o.machine, doc).name

    async def stop(self) -> None:
        """A learn running is given up (its process ended): the records are all still there."""
        if self.task is not None and not self.task.done():
            self.task.cancel()
            try:
                await self.task
            except asyncio.CancelledError:
                pass

    def status(self) -> dict:
        return {"cut_speeds": self.speeds, "next_learn_at": self.learner.next_at,
                "running": self.task is not None and not self.task.done(), "last": self.last}

