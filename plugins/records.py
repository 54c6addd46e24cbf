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

import asyncio
import time
import uuid as uuidlib
from collections import deque
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any

from lathed import hookimpl, records
from lathed.analysis import taguchi
from lathed.analyzer import Analyzer
from lathed.args import Args
from lathed.caller import require_operator
from lathed.bus import Sample
from lathed.config import Section
from lathed.control import RequestError, offload
from lathed.store import EVENT_SQL

EXPORTS = tuple(records.EXPORT_TABLES)
MAX_UM = 1e6     # a measured roughness or diameter error beyond a metre is a typo, not a part
RETRY_S = (1.0, 60.0)   # a failed part write is tried again after 1 s, doubling up to a minute


@dataclass
class Unwritten:
    """A finished part not yet committed: its row, sampling queue entry and event."""
    part: records.Part
    row: dict[str, Any]          # with its uuid: a retry writes the same record
    t: float                     # when it finished, its time in the sampling queue
    fut: Future | None = None    # its write, queued in the store

    @property
    def due(self) -> bool:
        """Not queued in the store, or its write failed."""
        f = self.fut
        return f is None or (f.done() and not f.cancelled() and f.exception() is not None)


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
        # finished parts not yet committed, oldest first: written in order by _write_parts, kept
        # over a failed write (disk full) and a restart, retried until the store takes them
        self.unwritten: deque[Unwritten] = deque()
        self.write_failures = 0
        self.last_write_error: str | None = None
        self._finished: asyncio.Event | None = None
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
        self._finished = asyncio.Event()
        # as deep as the other analyzers': a burst (a stalled loop) must not cost a part_count step
        sub = self.ctx.bus.subscribe(self.machine, self.chatter, self.thermal, self.suppress, maxsize=4096,
                                     name=self.name)
        writer = asyncio.create_task(self._write_parts(), name=f"analyzer:{self.name}:writer")
        try:
            while True:
                msg = await sub.get()
                if writer.done():
                    writer.result()       # its fault is this analyzer's: reported, restarted
                if isinstance(msg, Sample):
                    # the bus is not held up by a commit (a slow fsync): the writer takes the parts
                    for part in self.tracker.feed_sample(msg.source, msg.quantity, msg.value, msg.t):
                        self.unwritten.append(Unwritten(part, {"uuid": str(uuidlib.uuid4()), **part.row()},
                                                        time.time()))
                        self._finished.set()
        finally:
            self.ctx.bus.unsubscribe(sub)
            writer.cancel()
            # stopping (or restarting): queued now, the parts are committed by the store's close
            # (or awaited by the next run); before any await, which a second cancel would cut short
            for u in self.unwritten:
                if u.due:
                    self._submit(u)
            await asyncio.gather(writer, return_exceptions=True)

    async def _write_parts(self) -> None:
        """Commit the finished parts in order, each as one transaction; a failed write
        is retried, backing off up to a minute, until it is committed."""
        wait = RETRY_S[0]
        while True:
            if not self.unwritten:
                self._finished.clear()
                await self._finished.wait()
                continue
            u = self.unwritten[0]
            if u.due:
                self._submit(u)
            try:
                # shielded: cancelled at a stop, the write stays queued and the store's close commits it
                pid = await asyncio.shield(asyncio.wrap_future(u.fut))
            except Exception as e:      # logged with the part by _submit; kept, and tried again
                self.write_failures += 1
                self.last_write_error = f"{type(e).__name__}: {e}"
                await asyncio.sleep(wait)
                wait = min(2 * wait, RETRY_S[1])
                continue
            wait, self.last_write_error = RETRY_S[0], None
            self.unwritten.popleft()
            self.parts_written += 1
            if u.part.abnormal:
                self.abnormal_written += 1
                self.ctx.log.warning("part_abnormal", part=pid, reason=u.row["reason"])

    def _submit(self, u: Unwritten) -> None:
        """Queue the part's row, and for an abnormal part its sampling queue entry and
        event, as one write: all or none, so no abnormal part goes uninspected."""
        store, part, row = self.ctx.store, u.part, u.row
        stmts = [store.row_statement("workpieces", row)]
        if part.abnormal:
            stmts.append(store.row_statement("sampling_queue", {"t": u.t, "part_uuid": row["uuid"],
                                                                "reason": row["reason"]}))
            payload = {"part_no": part.part_no, "machine": part.machine, "reason": row["reason"],
                       "max_chatter_index": part.max_chatter_index}
            # the event names the part's row id, known only as the row is inserted
            stmts.append((EVENT_SQL, lambda pid: store.event_statement(
                "part_abnormal", self.name, {"part": pid, **payload})[1]))
        try:
            u.fut = store.submit(stmts, ())
        except Exception as e:          # the store is closed: a failed write like any other
            u.fut = Future()
            u.fut.set_exception(e)
        # the log keeps the part while the store does not (the writer tries again)
        u.fut.add_done_callback(lambda f: not f.cancelled() and f.exception() is not None and self.ctx.log.error(
            "part_not_written", error=f"{type(f.exception()).__name__}: {f.exception()}", **row))

    def status(self) -> dict[str, Any]:
        p = self.tracker.part
        pending = len(self.unwritten)
        return {"parts": self.parts_written, "abnormal": self.abnormal_written, "unwritten": pending,
                "write_failures": self.write_failures, "last_write_error": self.last_write_error,
                "summary": f"{self.parts_written} parts, {self.abnormal_written} abnormal"
                           + (f"; {pending} not yet written, retrying: {self.last_write_error}"
                              if pending and self.last_write_error else "")
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
