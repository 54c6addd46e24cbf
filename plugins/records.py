"""Production records: one row per workpiece, inspections, Taguchi experiments.

    [analyzer.records]
    plugin = "records"
    machine = "lathe"        # the lathe whose parts are tracked
    chatter = "chatter"      # chatter analyzer instance (its samples flag parts)
    thermal = "thermal"      # thermal analyzer instance (compensation applied)
    tool = "T0101"           # tool holder in use, for records and recommendations
    material = "C45"

Adds the control commands ``parts``, ``inspect``, ``experiment_add``,
``experiments``, ``recommend`` and ``export`` (see ``lathectl parts -h``).
"""
from __future__ import annotations

import asyncio
import math
import time
import uuid as uuidlib
from typing import Any

from lathed import hookimpl, records
from lathed.analysis import taguchi
from lathed.analyzer import Analyzer
from lathed.bus import Sample
from lathed.config import Section
from lathed.control import RequestError

EXPORTS = ("events", "parts", "inspections", "experiments")


class Records(Analyzer):
    def __init__(self, name: str, section: Section):
        super().__init__(name, section)
        self.machine = section.getstr("machine", "lathe")
        self.chatter = section.getstr("chatter", "chatter")
        self.thermal = section.getstr("thermal", "thermal")
        self.tool = section.getstr("tool", "")
        self.material = section.getstr("material", "")
        self.tracker = records.PartTracker(self.machine, self.chatter, self.thermal,
                                           self.tool or None, self.material or None)
        self.parts_written = 0
        self.abnormal_written = 0
        self._registered = False

    def inputs(self) -> list[str]:
        return [self.machine]

    async def run(self) -> None:
        if not self._registered:   # run() is restarted after a fault; commands stay registered
            for cmd in ("parts", "inspect", "experiment_add", "experiments", "recommend", "export"):
                self.ctx.register_control(cmd, getattr(self, f"_cmd_{cmd}"))
            self._registered = True
        sub = self.ctx.bus.subscribe(self.machine, self.chatter, self.thermal)
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
        limit = _int(args, "limit", 100, 1, 100_000)
        return await asyncio.to_thread(records.parts, self._query, bool(args.get("abnormal")),
                                       bool(args.get("pending")), limit)

    async def _cmd_inspect(self, args: dict) -> Any:
        ref = str(args.get("part", ""))
        part = await asyncio.to_thread(records.find_part, self._query, ref)
        if part is None:
            raise RequestError(f"no part {ref!r} (give its number from `lathectl parts` or a unique uuid prefix)")
        ra = _num(args, "ra_um", minval=0.0)
        err = _num(args, "diameter_error_um")
        values = args.get("values") or {}
        if not isinstance(values, dict) or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                   for v in values.values()):
            raise RequestError("values must map names to numbers")
        if ra is None and err is None and not values:
            raise RequestError("nothing measured: give ra_um, diameter_error_um or values")
        await self.ctx.store.add("inspections", {
            "t": time.time(), "part_uuid": part["uuid"], "ra_um": ra, "diameter_error_um": err,
            "measured": values, "inspector": str(args.get("by") or "") or None})
        return await asyncio.to_thread(records.find_part, self._query, str(part["id"]))

    async def _cmd_experiment_add(self, args: dict) -> Any:
        tool, material = _text(args, "tool", self.tool), _text(args, "material", self.material)
        levels = args.get("levels")
        if not isinstance(levels, dict) or not levels or not all(
                isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in levels.values()):
            raise RequestError("levels must map each factor to its level number (1, 2, 3...)")
        settings = args.get("settings") or {}
        if not isinstance(settings, dict):
            raise RequestError("settings must map factors to their values")
        run = args.get("run")   # the run number in the array; SQLite stores at most 64 bits
        if run is not None and (isinstance(run, bool) or not isinstance(run, int) or not 1 <= run <= 1_000_000):
            raise RequestError(f"run must be an integer in [1, 1000000], got {str(run)[:40]}")
        row = {"t": time.time(), "tool": tool, "material": material, "levels": levels, "settings": settings,
               "run": run,
               "ra_um": _num(args, "ra_um", minval=0.0), "diameter_error_um": _num(args, "diameter_error_um"),
               "removal_rate": _num(args, "removal_rate", minval=0.0), "part_uuid": args.get("part_uuid")}
        if row["ra_um"] is None and row["diameter_error_um"] is None and row["removal_rate"] is None:
            raise RequestError("nothing measured: give ra_um, diameter_error_um or removal_rate")
        existing = await asyncio.to_thread(records.experiments, self._query, tool, material)
        if existing and sorted(existing[0]["levels"]) != sorted(levels):
            raise RequestError(f"experiments for {tool}/{material} use the factors "
                               f"{', '.join(sorted(existing[0]['levels']))}, not {', '.join(sorted(levels))}")
        return {"id": await self.ctx.store.add("experiments", row)}

    async def _cmd_experiments(self, args: dict) -> Any:
        tool, material = _text(args, "tool", self.tool), _text(args, "material", self.material)
        return await asyncio.to_thread(records.experiments, self._query, tool, material)

    async def _cmd_recommend(self, args: dict) -> Any:
        tool, material = _text(args, "tool", self.tool), _text(args, "material", self.material)
        trials = await asyncio.to_thread(records.experiments, self._query, tool, material)
        if not trials:
            raise RequestError(f"no experiment records for tool {tool} and material {material}; "
                               "add them with `lathectl experiment add`")
        try:
            rec = await asyncio.to_thread(taguchi.recommend, trials)
        except ValueError as e:
            raise RequestError(str(e)) from None
        return {"tool": tool, "material": material, **rec}

    async def _cmd_export(self, args: dict) -> Any:
        what = args.get("what")
        if what not in EXPORTS:
            raise RequestError(f"cannot export {what!r}; allowed: {', '.join(EXPORTS)}")
        limit = _int(args, "limit", 100_000, 1, 1_000_000)
        q = self._query
        if what == "events":
            fn = lambda: q("SELECT id, uuid, machine_id, t, source, kind, payload FROM events "  # noqa: E731
                           "ORDER BY id DESC LIMIT ?", (limit,))[::-1]
        elif what == "parts":
            fn = lambda: records.parts(q, limit=limit)  # noqa: E731
        elif what == "inspections":
            fn = lambda: records.inspections(q, limit)  # noqa: E731
        else:
            fn = lambda: q("SELECT * FROM experiments ORDER BY id DESC LIMIT ?", (limit,))[::-1]  # noqa: E731
        return await asyncio.to_thread(fn)


def _int(args: dict, key: str, default: int, lo: int, hi: int) -> int:
    v = args.get(key, default)
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise RequestError(f"{key} must be an integer in [{lo}, {hi}]")
    return v


def _num(args: dict, key: str, minval: float | None = None) -> float | None:
    v = args.get(key)
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
            or (minval is not None and v < minval):
        raise RequestError(f"{key} must be a finite number" + (f" >= {minval:g}" if minval is not None else ""))
    return float(v)


def _text(args: dict, key: str, default: str) -> str:
    v = args.get(key) or default
    if not isinstance(v, str) or not v:
        raise RequestError(f"{key} is required (no default {key} configured in [analyzer.records])")
    return v


@hookimpl
def lathed_analyzer_types():
    return {"records": Records}
