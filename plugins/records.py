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
# the counter's last reading, saved only once every part not yet written when it was read is
# in the store (a save ahead of one, the process lost, would leave its step counted as seen
# and the part gone), and never over a later save of the same run (queued writes retried)
COUNTER_SQL = ("INSERT INTO last_part_count(machine, count, t, held, run, seq) SELECT ?,?,?,?,?,? "
               "WHERE (SELECT count(*) FROM workpieces WHERE uuid IN ({})) = ? "
               "ON CONFLICT(machine) DO UPDATE SET count = excluded.count, t = excluded.t, "
               "held = excluded.held, run = excluded.run, seq = excluded.seq "
               "WHERE excluded.run <> last_part_count.run OR excluded.seq > last_part_count.seq")


@dataclass
class Unwritten:
    """A finished part, or a gap's unobserved parts, not yet committed: rows,
    sampling queue entries and event."""
    parts: list[records.Part]
    rows: list[dict[str, Any]]   # with their uuids: a retry writes the same records
    t: float                     # when it finished, its time in the sampling queue
    gap: records.Gap | None = None
    fut: Future | None = None    # its write, queued in the store

    @classmethod
    def of(cls, item: records.Part | records.Gap, t: float) -> Unwritten:
        parts = item.parts if isinstance(item, records.Gap) else [item]
        return cls(parts, [{"uuid": str(uuidlib.uuid4()), **p.row()} for p in parts], t,
                   item if isinstance(item, records.Gap) else None)

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
        self.unobserved_written = 0
        self._watched = False         # run() has watched before: a restart, not a daemon start
        # finished parts not yet committed, oldest first: written in order by _write_parts, kept
        # over a failed write (disk full) and a restart, retried until the store takes them
        self.unwritten: deque[Unwritten] = deque()
        self.write_failures = 0
        self.last_write_error: str | None = None
        self._finished: asyncio.Event | None = None
        self._saved: tuple | None = None   # the part counter as last saved (count, time, held)
        self._resave = False               # ... maybe not taken: parts were still to be written
        self._run, self._seq = str(uuidlib.uuid4()), 0
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
        stopping = False
        try:
            await self._resume()
            while True:
                msg = await sub.get()
                if writer.done():
                    writer.result()       # its fault is this analyzer's: reported, restarted
                if isinstance(msg, Sample):
                    # the bus is not held up by a commit (a slow fsync): the writer takes the parts
                    for item in self.tracker.feed_sample(msg.source, msg.quantity, msg.value, msg.t):
                        self.unwritten.append(Unwritten.of(item, time.time()))
                        self._finished.set()
                    self._save_count()
        except asyncio.CancelledError:
            stopping = True           # the daemon stops (a fault restarts run() with the tracker kept)
            raise
        finally:
            self.ctx.bus.unsubscribe(sub)
            writer.cancel()
            # stopping (or restarting): queued now, the parts are committed by the store's close
            # (or awaited by the next run); before any await, which a second cancel would cut short
            if stopping:      # the part the program's stop left: as it stands, not lost
                self.unwritten.extend(Unwritten.of(p, time.time()) for p in self.tracker.stop())
            for u in self.unwritten:
                if u.due:
                    self._submit(u)
            self._save_count(force=self._resave)     # after them: taken once they are in
            await asyncio.gather(writer, return_exceptions=True)

    async def _resume(self) -> None:
        """Tell the tracker nothing was watched until now: the part counter's next reading
        gives the parts made meanwhile, recorded as not observed rather than merged."""
        if self._watched:
            self.tracker.resume("records analyzer restarting", time.time())
            return
        self._watched = True
        # a daemon start: the count last read, else (a store older than last_part_count) the last
        # part's number in the store
        last = None
        try:
            rows = await asyncio.to_thread(
                self.ctx.store.query, "SELECT count, t, held, 0 AS older FROM last_part_count WHERE machine = ? "
                "UNION ALL SELECT * FROM (SELECT part_no, end_t, 0, 1 FROM workpieces WHERE machine = ? "
                "AND part_no IS NOT NULL ORDER BY id DESC LIMIT 1) ORDER BY older LIMIT 1",
                (self.machine, self.machine))
            last = rows[0] if rows else None
        except Exception as e:     # unread, the parts made while lathed was down are not counted: said
            self.ctx.log.warning("last_part_unread", error=f"{type(e).__name__}: {e}")
        self.tracker.resume("lathed was not running", last["t"] if last else time.time(),
                            last["count"] if last else None, bool(last and last["held"]))

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
            if not self.unwritten:
                self._save_count(force=self._resave)     # read while parts were to be written
            self.parts_written += len(u.parts)
            if u.gap is not None:
                self.unobserved_written += len(u.parts)
                self.ctx.log.warning("part_unobserved", first_part=pid if u.parts else None, **u.gap.payload())
            elif u.parts[0].abnormal:
                self.abnormal_written += 1
                self.ctx.log.warning("part_abnormal", part=pid, reason=u.rows[0]["reason"])

    def _submit(self, u: Unwritten) -> None:
        """Queue the parts' rows, their sampling queue entries (a part cut under abnormal
        vibration or not watched whole) and the event, as one write: all or none, so no
        such part goes uninspected."""
        store = self.ctx.store
        stmts = []
        for part, row in zip(u.parts, u.rows):
            stmts.append(store.row_statement("workpieces", row))
            if part.queued:
                stmts.append(store.row_statement("sampling_queue", {"t": u.t, "part_uuid": row["uuid"],
                                                                    "reason": part.queue_reason()}))
        # the event names the (first) part's row id, known only as the row is inserted
        if u.gap is not None:
            payload = u.gap.payload()
            stmts.append((EVENT_SQL, lambda pid: store.event_statement(
                "part_unobserved", self.name, {"first_part": pid if u.parts else None, **payload})[1]))
        elif u.parts[0].abnormal:
            part, row = u.parts[0], u.rows[0]
            payload = {"part_no": part.part_no, "machine": part.machine, "reason": row["reason"],
                       "max_chatter_index": part.max_chatter_index}
            stmts.append((EVENT_SQL, lambda pid: store.event_statement(
                "part_abnormal", self.name, {"part": pid, **payload})[1]))
        try:
            u.fut = store.submit(stmts, ())
        except Exception as e:          # the store is closed: a failed write like any other
            u.fut = Future()
            u.fut.set_exception(e)
        # the log keeps the parts while the store does not (the writer tries again)
        said = u.gap.payload() if u.gap is not None else u.rows[0]
        u.fut.add_done_callback(lambda f: not f.cancelled() and f.exception() is not None and self.ctx.log.error(
            "part_not_written", error=f"{type(f.exception()).__name__}: {f.exception()}", **said))

    def _save_count(self, force: bool = False) -> None:
        """The part counter as last read, for the next start to count from, queued after the
        writes of the parts not yet written and taken only once they are all in the store
        (else saved again when the writer has written them). A save that fails leaves the
        next start counting a step already seen as a part not observed: said."""
        tr = self.tracker
        if tr.count is None or (not force and (tr.count, tr.count_t, int(tr.held_written)) == self._saved):
            return
        self._saved = state = (tr.count, tr.count_t, int(tr.held_written))
        if any(u.due for u in self.unwritten):      # the writer has them still to queue
            self._resave = True
            return
        uuids = [row["uuid"] for u in self.unwritten for row in u.rows]
        self._resave = bool(uuids)     # a write queued before it may fail and be retried after
        self._seq += 1
        try:
            fut = self.ctx.store.submit(COUNTER_SQL.format(",".join("?" * len(uuids)) or "NULL"),
                                        (self.machine, *state, self._run, self._seq, *uuids, len(uuids)))
        except Exception as e:          # the store is closed
            fut = Future()
            fut.set_exception(e)
        fut.add_done_callback(lambda f: not f.cancelled() and f.exception() is not None and self.ctx.log.warning(
            "part_count_not_saved", count=state[0], error=f"{type(f.exception()).__name__}: {f.exception()}"))

    def status(self) -> dict[str, Any]:
        p = self.tracker.part
        pending = len(self.unwritten)
        return {"parts": self.parts_written, "abnormal": self.abnormal_written,
                "unobserved": self.unobserved_written, "unwritten": pending,
                "write_failures": self.write_failures, "last_write_error": self.last_write_error,
                "summary": f"{self.parts_written} parts, {self.abnormal_written} abnormal"
                           + (f", {self.unobserved_written} not observed" if self.unobserved_written else "")
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
