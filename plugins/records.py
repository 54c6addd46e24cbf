"""Production records: one row per workpiece, inspections, Taguchi experiments.

    [analyzer.records]
    plugin = "records"
    machine = "lathe"        # the lathe whose parts are tracked
    chatter = "chatter"      # chatter analyzer instance (its samples flag parts)
    thermal = "thermal"      # thermal analyzer instance (compensation applied)
    suppress = "suppress"    # suppression analyzer instance (depth estimated from the spindle load)
    tool = "T0101"           # tool holder in use, for records and recommendations
    material = "C45"

Adds the control commands ``parts``, ``inspect``, ``experiment_add``,
``experiments``, ``recommend`` and ``export`` (see ``lathectl parts -h``).
"""
from __future__ import annotations

import time
import uuid as uuidlib
from typing import Any

from lathed import hookimpl, records
from lathed.analysis import taguchi
from lathed.analyzer import Analyzer
from lathed.args import Args
from lathed.caller import require_operator
from lathed.bus import Sample
from lathed.config import Section
from lathed.control import RequestError, offload

EXPORTS = tuple(records.EXPORT_TABLES)
MAX_UM = 1e6     # a measured roughness or diameter error beyond a metre is a typo, not a part


class Records(Analyzer):
    def __init__(self, name: str, section: Section):
        super().__init__(name, section)
        self.machine = section.getstr("machine", "lathe")
        self.chatter = section.getstr("chatter", "chatter")
        self.thermal = section.getstr("thermal", "thermal")
        self.suppress = section.getstr("suppress", "suppress")
        self._given = [k for k in ("chatter", "thermal", "suppress") if k in section]
        self.tool = section.getstr("tool", "")
        self.material = section.getstr("material", "")
        self.tracker = records.PartTracker(self.machine, self.chatter, self.thermal,
                                           self.tool or None, self.material or None, self.suppress)
        self.parts_written = 0
        self.abnormal_written = 0
        self._registered = False

    def inputs(self) -> list[str]:
        return [self.machine]

    def refers(self) -> dict[str, tuple[str, str, str | None]]:
        # the defaults may name analyzers not configured (then nothing is read from them); a name
        # written out must exist, or a typo silently records no chatter, thermal or suppression
        return {k: (getattr(self, k), "analyzer", None) for k in self._given}

    async def run(self) -> None:
        if not self._registered:   # run() is restarted after a fault; commands stay registered
            for cmd in ("parts", "inspect", "experiment_add", "experiments", "recommend", "export"):
                self.ctx.register_control(cmd, getattr(self, f"_cmd_{cmd}"))
            self._registered = True
        sub = self.ctx.bus.subscribe(self.machine, self.chatter, self.thermal, self.suppress)
        try:
            while True:
                msg = await sub.get()
                if isinstance(msg, Sample):
                    for part in self.tracker.feed_sample(msg.source, msg.quantity, msg.value, msg.t):
                        await self._write(part)
        finally:
            self.ctx.bus.unsubscribe(sub)

    async def _write(self, part: records.Part) -> None:
        store = self.ctx.store
        row = {"uuid": str(uuidlib.uuid4()), **part.row()}
        pid = await store.add("workpieces", row)
        self.parts_written += 1
        if part.abnormal:
            await store.add("sampling_queue", {"t": time.time(), "part_uuid": row["uuid"],
                                               "reason": row["reason"]})
            self.abnormal_written += 1
            self.ctx.record("part_abnormal", {"part": pid, "part_no": part.part_no, "machine": part.machine,
                                              "reason": row["reason"],
                                              "max_chatter_index": part.max_chatter_index})
            self.ctx.log.warning("part_abnormal", part=pid, reason=row["reason"])

    def status(self) -> dict[str, Any]:
        p = self.tracker.part
        return {"parts": self.parts_written, "abnormal": self.abnormal_written,
                "summary": f"{self.parts_written} parts, {self.abnormal_written} abnormal"
                           + (f"; part in progress since {time.strftime('%H:%M:%S', time.localtime(p.start_t))}"
                              if p else "")}

    # -- control commands ---------------------------------------------------
    def _query(self, sql: str, params: tuple = ()) -> list[dict]:
        return self.ctx.store.query(sql, params)

    async def _cmd_parts(self, args: dict) -> Any:
        a = Args("parts", args)
        abnormal, pending = a.getbool("abnormal", False), a.getbool("pending", False)
        limit = a.getint("limit", 100, minval=1, maxval=100_000)
        a.check_unused()
        return await offload(records.parts, self._query, abnormal, pending, limit)

    async def _cmd_inspect(self, args: dict) -> Any:
        require_operator("inspect")
        a = Args("inspect", args)
        ref = a.getstr("part", maxlen=64)
        ra = a.getfloat("ra_um", None, minval=0.0, maxval=MAX_UM)
        err = a.getfloat("diameter_error_um", None, minval=-MAX_UM, maxval=MAX_UM)
        values = a.getmap("values", {}, item=float)
        by = a.getstr("by", None)
        a.check_unused()
        if ra is None and err is None and not values:
            raise RequestError("inspect: nothing measured: give ra_um, diameter_error_um or values")
        part = await offload(records.find_part, self._query, ref)
        if part is None:
            raise RequestError(f"no part {ref!r} (give its number from `lathectl parts` or a unique uuid prefix)")
        await self.ctx.store.add("inspections", {
            "t": time.time(), "part_uuid": part["uuid"], "ra_um": ra, "diameter_error_um": err,
            "measured": values, "inspector": by})
        # in the event log too, with who measured it (lathectl, the operator view)
        self.ctx.record("part_inspected", {"part": part["id"], "part_no": part["part_no"], "ra_um": ra,
                                           "diameter_error_um": err, "values": values, "by": by})
        return await offload(records.find_part, self._query, str(part["id"]))

    async def _cmd_experiment_add(self, args: dict) -> Any:
        require_operator("experiment_add")
        a = Args("experiment_add", args)
        tool, material = self._tool(a), self._material(a)
        # level numbers index the orthogonal array's columns: small integers (the analysis counts per level)
        levels = a.getmap("levels", item=int, minval=1, maxval=taguchi.MAX_LEVEL, maxitems=taguchi.MAX_FACTORS)
        if not levels:
            raise a.error("levels", "empty; give each factor's level number (1, 2, 3...)")
        settings = a.getmap("settings", {}, item=(float, str), maxitems=taguchi.MAX_FACTORS)
        row = {"t": time.time(), "tool": tool, "material": material, "levels": levels, "settings": settings,
               "run": a.getint("run", None, minval=1, maxval=taguchi.MAX_TRIALS),
               "ra_um": a.getfloat("ra_um", None, minval=0.0, maxval=MAX_UM),
               "diameter_error_um": a.getfloat("diameter_error_um", None, minval=-MAX_UM, maxval=MAX_UM),
               "removal_rate": a.getfloat("removal_rate", None, minval=0.0, maxval=1e9),
               "part_uuid": a.getstr("part_uuid", None, maxlen=64)}
        a.check_unused()
        if row["ra_um"] is None and row["diameter_error_um"] is None and row["removal_rate"] is None:
            raise RequestError("experiment_add: nothing measured: give ra_um, diameter_error_um or removal_rate")
        existing = await offload(records.experiments, self._query, tool, material)
        if existing and sorted(existing[0]["levels"]) != sorted(levels):
            raise RequestError(f"experiments for {tool}/{material} use the factors "
                               f"{', '.join(sorted(existing[0]['levels']))}, not {', '.join(sorted(levels))}")
        if len(existing) >= taguchi.MAX_TRIALS:
            raise RequestError(f"experiment_add: {tool}/{material} already has {len(existing)} trials, "
                               f"the most one analysis takes ({taguchi.MAX_TRIALS})")
        return {"id": await self.ctx.store.add("experiments", row)}

    async def _cmd_experiments(self, args: dict) -> Any:
        a = Args("experiments", args)
        tool, material = self._tool(a), self._material(a)
        a.check_unused()
        return await offload(records.experiments, self._query, tool, material)

    async def _cmd_recommend(self, args: dict) -> Any:
        a = Args("recommend", args)
        every = a.getbool("all", False)
        tool, material = self._tool(a), self._material(a)
        a.check_unused()
        if every:       # the operator view's table
            return await offload(records.recommendations, self._query, tool, material)
        try:
            return await offload(records.recommendation, self._query, tool, material)
        except ValueError as e:
            raise RequestError(str(e)) from None

    async def _cmd_export(self, args: dict) -> Any:
        a = Args("export", args)
        what = a.getstr("what", choices=EXPORTS)
        # one reply holds a page (100k events: ~25 MB of JSON); lathectl export pages with
        # after_id through everything, oldest first, so nothing is cut silently
        limit = a.getint("limit", 100_000, minval=1, maxval=100_000)
        after = a.getint("after_id", None, minval=0, maxval=2 ** 62)
        a.check_unused()
        return await offload(records.export_page, self._query, what, limit, after)

    def _tool(self, a: Args) -> str:
        return self._default(a, "tool", self.tool)

    def _material(self, a: Args) -> str:
        return self._default(a, "material", self.material)

    @staticmethod
    def _default(a: Args, key: str, default: str) -> str:
        v = a.getstr(key, default or None)
        if v is None:
            raise a.error(key, "required (no default configured in [analyzer.records])")
        return v


@hookimpl
def lathed_analyzer_types():
    return {"records": Records}
