"""The suppression analyzer's stability model: adopted refits loaded at start, ``lathectl
stability`` refits and adoptions (docs/records.md, docs/stability.md). Not an entry point:
the suppression plugin owns one, as it owns its LearnedStability."""
from __future__ import annotations

import asyncio
import time

import numpy as np

from lathed.analysis.cut_log import cut_rows
from lathed.analysis.cuts import Cuts
from lathed.analysis.speed_selection import lobe_grid
from lathed.analysis.stability import StabilityModel, refit
from lathed.analysis.stability import files as stability_files
from lathed.args import Args
from lathed.caller import require_operator
from lathed.control import RequestError, offload


def setup_rows(records: list[dict], tool: str | None, material: str | None, tool_number: int | None,
               newest: int) -> tuple[Cuts | None, dict[str, int]]:
    """The set-up's cut speeds among a machine's cut records (the newest ``newest``), and what
    was left out and why."""
    mine = [r for r in records if (r.get("tool"), r.get("material")) == (tool, material)]
    setup = len(mine)
    if tool_number is not None:     # the turret's other tools cut with other dynamics
        mine = [r for r in mine if r.get("tool_number") in (None, tool_number)]
    cuts, skipped = cut_rows(mine)
    if setup < len(records):
        skipped["cuts of another tool or material"] = len(records) - setup
    if len(mine) < setup:
        skipped[f"cuts with another turret tool than {tool_number}"] = setup - len(mine)
    if cuts is not None and len(cuts) > newest:
        # the refit's time grows faster than the cuts (3 s on 1,000, 20 s on 3,000); the newest tell most
        skipped[f"older than the newest {newest} cut speeds"] = len(cuts) - newest
        cuts = cuts.take(np.arange(len(cuts) - newest, len(cuts)))
    return cuts, skipped


def left_out(skipped: dict[str, int]) -> str:
    return "; ".join(f"{n} {why}" for why, n in skipped.items()) or "none"


class ModelRefits:
    """Loads the adopted model at start; refits and adopts on ``lathectl stability``."""

    def __init__(self, owner):
        self.owner = owner            # the SuppressionAnalyzer: its model, set-up and records
        self.running = False
        self.last: dict | None = None

    def load_adopted(self) -> None:
        """The newest adopted model of this machine, if it was refitted from the model and set-up
        configured now; a damaged file is said (event) and the previous version tried."""
        o = self.owner
        if (o.configured is None and not o.learning) or not o.models_dir.is_dir():
            return
        files = stability_files.versions(o.models_dir, o.machine)
        for i, path in enumerate(reversed(files)):
            older = files[-2 - i].name if i + 1 < len(files) else "configured"
            try:
                model, doc = stability_files.load(path)
            except ValueError as e:
                o.ctx.log.error("stability_model_unreadable", file=path.name, error=str(e), using=older)
                o.ctx.record("stability_model_unreadable", {"machine": o.machine, "file": path.name,
                                                            "error": str(e), "using": older})
                continue
            want = o._setup_json()
            have = {k: doc.get(k) for k in want}
            if have != want:
                what = [k for k in want if have[k] != want[k]]
                why = (f"{path.name} was refitted from another {' and '.join(what)} than the configuration "
                       f"gives now (a new tap test or set-up supersedes it)")
                o.ctx.log.warning("stability_model_superseded", file=path.name, why=why)
                o.ctx.record("stability_model_superseded", {"machine": o.machine, "file": path.name,
                                                            "why": why, "using": "configured"})
                return
            o.lobes, o.model_name = model, path.name
            o.ctx.log.info("stability_model_loaded", file=path.name)
            return

    def _refit(self, holdout: float) -> tuple[dict, object]:
        """The refit of the model in use on this set-up's recorded cuts (a worker thread)."""
        o = self.owner
        cuts, skipped, n_records = o._setup_cuts("stability refit")
        try:
            r = refit(o.lobes, cuts, holdout_fraction=holdout)
        except ValueError as e:
            raise RequestError(f"stability refit on {len(cuts)} cut speeds of {o.machine}: {e} "
                               f"(left out: {left_out(skipped)})") from None
        out = {"machine": o.machine, "setup": o._setup_json(include_base=False),
               "model_before_name": o.model_name, "cut_records": n_records, "left_out": skipped,
               **r.to_json(), "adopt": bool(r.effects)}
        out["reason"] = r.conclusion if r.effects else "; ".join([r.conclusion, *r.rejected])
        return out, r

    def _save(self, out: dict, r, by: str | None) -> str:
        o = self.owner
        doc = {**o._setup_json(), "machine": o.machine, "model": r.model.to_json(),
               "refitted_from": o.model_name, "created": time.time(), "by": by,
               "effects": out["effects"], "before": out["before"], "after": out["after"],
               "cuts": out["cuts"], "heldout": out["heldout"]}
        return stability_files.save(o.models_dir, o.machine, doc).name

    async def control(self, args: dict) -> dict:
        """``lathectl stability status|refit|learn``."""
        o = self.owner
        a = Args("stability", args)
        action = a.getstr("action", "status", choices=("status", "refit", "learn"))
        dry = a.getbool("dry_run", False)
        holdout = a.getfloat("holdout", 0.3, minval=0.05, maxval=0.9)
        by = a.getstr("by", None)
        a.check_unused()
        if action == "status":
            return self.status()
        if action == "learn":
            if o.learned is None:
                raise RequestError(f"stability learn: {o.name} has a modal model configured; refit it on the "
                                   f"cuts instead (lathectl stability refit)")
            require_operator("stability learn")
            return await o.learned.learn_requested(by)
        if not dry:
            require_operator("stability refit")
        if o.configured is None:
            raise RequestError(f"stability refit: {o.name} has no modal model (modes, kf) to refit"
                               + ("; it learns one from the cut records (lathectl stability learn)"
                                  if o.learned is not None else ""))
        if self.running:
            raise RequestError("stability refit: a refit is already running; wait for its result")
        self.running = True
        try:
            return await self._refit_and_adopt(holdout, dry, by)
        finally:
            self.running = False

    async def _refit_and_adopt(self, holdout: float, dry: bool, by: str | None) -> dict:
        o = self.owner
        out, r = await offload(self._refit, holdout)
        out["dry_run"] = dry
        if dry:
            return out
        if not out["adopt"]:
            o.ctx.record("stability_refit_not_adopted", {
                "machine": o.machine, "model": o.model_name, "reason": out["reason"],
                "before": out["before"], "after": out["after"], "cuts": out["cuts"], "by": by})
            self.last = out
            return out
        name = await asyncio.to_thread(self._save, out, r, by)
        model = StabilityModel.from_json(r.model.to_json())     # as the file holds it
        grid = await asyncio.to_thread(lobe_grid, model, o.limits)
        before = o.model_name
        o.use_model(model, grid, name)     # the next cut's policy takes it; the present cut keeps the old
        out["model_after_name"] = name
        o.ctx.log.warning("stability_model_adopted", file=name, effects=[e["effect"] for e in out["effects"]])
        o.ctx.record("stability_model_adopted", {
            "machine": o.machine, "file": name, "model_before": before, "model": out["model_after"],
            "effects": out["effects"], "before": out["before"], "after": out["after"],
            "cuts": out["cuts"], "heldout": out["heldout"], "by": by})
        self.last = out
        return out

    def status(self) -> dict:
        o = self.owner
        return {"machine": o.machine, "model": o.model_name,
                "lobes": None if o.lobes is None else o.lobes.to_json(),
                "configured": None if o.configured is None else o.configured.to_json(),
                "tool": o.tool or None, "material": o.material or None,
                "cuts_recorded": o.cuts_recorded,
                "learning": None if o.learned is None else o.learned.status(),
                "last_refit": None if self.last is None else
                {k: self.last.get(k) for k in ("adopt", "reason", "model_after_name", "dry_run")}}
