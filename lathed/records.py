"""Workpiece records: which part was cut when, under what vibration, and how
it measured afterwards ("two-time quality detection").

:class:`PartTracker` turns the lathe's samples (part counter, program state,
cutting conditions) and the analyzers' samples (chatter index and alarm,
thermal compensation) into one :class:`Part` per workpiece. A part cut under
abnormal vibration is flagged so it goes to sampling inspection, and so is a
part not watched whole: parts the counter says were made while nothing
watched (:class:`Gap`) are recorded one by one as not observed. The queries
below join each part with its inspection. No asyncio here: the records
plugin drives this from the bus.
"""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from typing import Any, Callable

from lathed.machine import MAX_LATE_PARTS

# program_state register values (lathed/sim/registers.py)
IDLE, RUNNING, ALARM = 0, 1, 2
# why parts were not watched (Part.unwatched); the plugin gives the causes of a gap in its watch
RESET = "part counter reset on the control"
# No machine makes a part faster (a bound on a counter's jump before a cycle has been watched)
MIN_CYCLE_S = 1.0


@dataclass
class Part:
    machine: str
    start_t: float
    end_t: float | None = None
    part_no: int | None = None
    program: int | None = None
    outcome: str = "finished"            # finished | aborted | partial (watched in part) | unobserved
    max_chatter_index: float | None = None
    chatter_threshold: float | None = None
    chatter_alarms: int = 0
    chatter_frequency_hz: float | None = None
    compensation_um: float | None = None
    rpm: float | None = None             # speed when the cut began
    depth_mm: float | None = None        # deepest cut
    feed_mm_rev: float | None = None
    tool: str | None = None
    material: str | None = None
    tools: str | None = None             # turret tools that cut it, in order ("1,2"): tool_number register
    reasons: list[str] = field(default_factory=list)
    unwatched: str | None = None         # why it was not watched whole: it cannot be judged normal

    @property
    def abnormal(self) -> bool:
        return bool(self.reasons)

    @property
    def queued(self) -> bool:
        """For sampling inspection: cut under abnormal vibration, or not watched whole."""
        return self.abnormal or self.unwatched is not None

    def queue_reason(self) -> str:
        seen = [] if self.unwatched is None else [
            f"{'not observed' if self.outcome == 'unobserved' else 'not watched whole'}: {self.unwatched}"]
        return "; ".join(self.reasons + seen)

    def row(self) -> dict[str, Any]:
        d = asdict(self)
        d["reason"] = "; ".join(d.pop("reasons")) or None
        d["abnormal"] = int(self.abnormal)
        return d


@dataclass
class Gap:
    """Steps of the part counter nobody watched: one unobserved Part each, made
    between ``from_t`` (the last reading before) and ``to_t`` (the first after)."""
    machine: str
    reason: str
    from_t: float
    to_t: float
    part_no_first: int
    count: int
    at_least: bool              # after a counter reset: parts made before it may be missing too
    parts: list[Part]           # none beyond MAX_LATE_PARTS: a reset or another controller, not parts

    def payload(self) -> dict[str, Any]:
        return {"machine": self.machine, "count": self.count, "part_no_first": self.part_no_first,
                "part_no_last": self.part_no_first + self.count - 1, "from_t": self.from_t, "to_t": self.to_t,
                "reason": self.reason, "at_least": self.at_least, "recorded": len(self.parts)}


class PartTracker:
    """Feed it samples in bus order; it returns the parts they complete.

    A part starts when the program runs and ends when the part counter
    steps (finished) or the program stops first (aborted, kept only if it
    cut). The part in progress when tracking began is marked ``partial``.
    Steps of the counter not seen one by one (a reading that jumps by two or
    more, or one after :meth:`resume`, or a counter reset) are no part's end:
    the part being cut takes the first of them, the rest come as a
    :class:`Gap` of unobserved parts, in the list of parts returned.
    The cut is the chatter analyzer's cut state (``cutting``: its sources combined,
    lathed.analysis.cut.state): the part's speed and feed are those when its first
    cut began.  Its depth is
    the deepest the register showed, else the deepest the suppression
    analyzer's spindle-load estimate showed (``depth_est_mm``).
    """

    def __init__(self, machine: str, chatter: str | None = None, thermal: str | None = None,
                 tool: str | None = None, material: str | None = None, suppress: str | None = None):
        self.machine, self.chatter, self.thermal, self.suppress = machine, chatter, thermal, suppress
        self._depth_register = False  # the machine reports depth_of_cut_mm: estimates are not used
        self.tool, self.material = tool, material
        self.count: int | None = None
        self.state = RUNNING          # assumed running until the machine says otherwise
        self.program: int | None = None
        self.threshold: float | None = None
        self.compensation: float | None = None
        self.alarm_on = False
        self.chatter_hz: float | None = None
        self.rpm: float | None = None
        self.feed: float | None = None
        self.tool_number: int | None = None   # the turret position, where the machine maps it
        self.part: Part | None = None
        self._partial = True
        self._cut = False             # the part in progress has cut
        self.count_t: float | None = None        # when part_count was last read
        # the part the program's stop left was written aborted at lathed's stop, before the
        # counter stepped for it: the counter's next step is that part's, not one made unwatched
        self.held_written = False
        self._gap: tuple[str, float] | None = None   # (why, since when) nothing was watched
        # the part open when the program stopped (whether it cut, when it stopped): held for the
        # counter's next reading, which finishes it if it steps (a counter polled slower than
        # the program state, or read after it in the poll, steps after the stop)
        self._stopped: tuple[Part, bool, float] | None = None
        self._shortest: float | None = None      # the shortest cycle of a part watched whole
        self._out: list[Part] = []               # parts closed outside a counter or state sample

    def resume(self, reason: str, t: float, count: int | None = None, held_written: bool = False) -> None:
        """Nothing was watched for ``reason`` since part_count was last read (or ``t``, when
        ``count``, the last part count recorded, was); ``count`` and ``held_written`` (see
        :meth:`stop`) are for a tracker that has read none. The next part_count reading tells
        the parts made meanwhile; the part being cut was not watched whole."""
        if self.count is None and count is not None:      # recorded at t, as good as read then
            self.count, self.count_t, self.held_written = count, t, held_written
        if self._gap is None:
            # from the last reading of the count: a step later than that was not seen
            self._gap = (reason, t if self.count_t is None else self.count_t)
        if self.part is not None and self.part.unwatched is None:
            self.part.unwatched = reason

    def _open(self, t: float, unwatched: str | None = None) -> None:
        self.part = Part(self.machine, start_t=t, program=self.program, tool=self.tool,
                         material=self.material, chatter_threshold=self.threshold,
                         compensation_um=self.compensation, unwatched=unwatched)
        self._cut = False
        if self._partial or unwatched is not None:
            self.part.outcome = "partial"
            self._partial = False
        if self.alarm_on:   # an alarm still standing from the last part covers this one too
            self._alarm(self.part)

    def _close(self, t: float, outcome: str | None = None) -> Part | None:
        p, self.part = self.part, None
        if p is None:
            return None
        p.end_t = t
        if outcome is not None:
            p.outcome = outcome
        if p.outcome == "aborted" and not self._cut:
            return None          # the program stopped before anything was cut
        if (p.max_chatter_index is not None and p.chatter_threshold is not None
                and p.max_chatter_index >= p.chatter_threshold and not p.chatter_alarms):
            p.reasons.append(f"chatter index {p.max_chatter_index:.3g} reached the threshold "
                             f"{p.chatter_threshold:.3g} during the cut")
        return p

    def _alarm(self, p: Part) -> None:
        p.chatter_alarms += 1
        if p.chatter_alarms == 1:
            hz = f" at {self.chatter_hz:.0f} Hz" if self.chatter_hz else ""
            tool = f" with tool {self.tool_number}" if self.tool_number is not None else ""
            p.reasons.append(f"chatter alarm during the cut{hz}{tool}: cut under abnormal vibration")

    def feed_sample(self, source: str, quantity: str, value: float, t: float) -> list[Part | Gap]:
        done: list[Part | Gap] = []
        if source == self.machine:
            self._machine(quantity, value, t, done)
        elif source == self.chatter:
            self._chatter(quantity, value)
        elif (source == self.suppress and quantity == "depth_est_mm" and self.part is not None
              and not self._depth_register and value > 0):
            self.part.depth_mm = max(self.part.depth_mm or 0.0, value)
        elif source == self.thermal and quantity == "compensation_um":
            self.compensation = value
            if self.part is not None:
                self.part.compensation_um = value
        if self._out:
            done[:0], self._out = self._out, []
        return done

    def _machine(self, q: str, v: float, t: float, done: list) -> None:
        if q == "part_count":
            self._count(int(v), t, done)
        elif q == "program_state":
            s = int(v)
            if s == IDLE and self.state != IDLE and self.part is not None:
                done += self.flush()
                self._stopped, self.part = (self.part, self._cut, t), None
            elif s != IDLE and self.state == IDLE and self.count is not None:
                # the part the stop left stays held: the next program may start before a counter
                # polled slower is read; its first cut is later than that (see _cutting)
                self._partial = False
                self._open(t)
            if s == ALARM and self.part is not None and self.state != ALARM:
                self.part.reasons.append("machine alarm (program state 2) during the part")
            self.state = s
        elif q == "program_number":
            self.program = int(v)
            if self.part is not None:
                self.part.program = int(v)
        elif q == "spindle_rpm":
            self.rpm = v
        elif q == "feed_mm_rev":
            self.feed = v
        elif q == "tool_number":
            self.tool_number = int(v)      # the part's tools: those in the turret when a cut begins
        elif q == "depth_of_cut_mm":
            # the depth only: whether the tool is in the cut is the chatter analyzer's cut state's
            # (lathed.analysis.cut.state), the register among its sources where cut_from names it
            self._depth_register = True
            if self.part is not None and v > 0:
                self.part.depth_mm = max(self.part.depth_mm or 0.0, v)

    def flush(self) -> list[Part]:
        """The part the program's stop closed, as it stands (aborted), if the counter has not
        stepped since: the daemon is stopping, or the next part cuts."""
        return self._close_stopped("aborted")

    def stop(self) -> list[Part]:
        """lathed stops: :meth:`flush`, and the counter's next step (read at the next start,
        ``held_written`` given to :meth:`resume`) is the written part's own."""
        parts = self.flush()
        self.held_written = self.held_written or bool(parts)
        return parts

    def _close_stopped(self, outcome: str | None) -> list[Part]:
        held, self._stopped = self._stopped, None
        if held is None:
            return []
        running = self.part, self._cut        # the next program's part, where one has started
        self.part, self._cut = held[0], held[1]
        p = self._close(held[2], outcome)
        self.part, self._cut = running
        return [] if p is None else [p]

    def _count(self, n: int, t: float, done: list) -> None:
        if self._stopped is not None and self._gap is None:
            if self.count is not None and n == self.count + 1:
                # the counter stepped: the part was finished (cut or not, as a step in the watch is)
                for p in self._close_stopped(None):
                    p.part_no = n
                    self._timed(p)
                    done.append(p)
                self.count, self.count_t = n, t
                return
            done += self.flush()
        c, gap = self.count, self._gap
        if self.held_written and c is not None and n > c:
            c += 1      # the part written aborted at lathed's stop is that step's: not a part unobserved
        self.held_written = False
        since = self.count_t if gap is None else gap[1]
        self.count, self.count_t, self._gap = n, t, None
        reason, reset = (None if gap is None else gap[0]), False
        if c is not None and n < c:
            if gap is None and (n == 0 or since is None or n > self._most_parts(t - since)):
                return          # reset or set on the control as it was watched: the part being cut goes on
            # the parts counted since the reset (to 0) were not seen made
            c, reset, reason = 0, True, "; ".join(filter(None, (reason, RESET)))
        if c is not None and n > c:
            if reason is None and n - c == 1:    # the step seen: the part being cut is finished
                p = self._close(t)
                if p is not None:
                    p.part_no = n
                    self._timed(p)
                    done.append(p)
                if self.state != IDLE:
                    self._open(t)
                return
            if since is not None and n - c > self._most_parts(t - since):
                # faster than parts are made (a counter set, a bad read): no parts, but said
                done += self.flush()
                done.append(Gap(self.machine, f"part_count went from {c} to {n} in {t - since:.3g} s, faster "
                                f"than parts are made: taken as the counter set on the control, no parts "
                                "recorded", since, t, c + 1, n - c, reset, []))
                return
            reason = reason or f"part_count stepped by {n - c} between two readings"
            self._unseen(c, n, since if since is not None else t, t, reason, reset, done)
        done += self.flush()        # a part the stop left that no step took: aborted
        if (c is None or reason is not None) and self.part is None and self.state != IDLE:
            self._open(t, reason)   # its start was not seen

    def _timed(self, p: Part) -> None:
        """A part watched whole: its cycle bounds how fast parts can be made."""
        if p.outcome == "finished" and p.unwatched is None and p.end_t > p.start_t:
            self._shortest = min(self._shortest or math.inf, p.end_t - p.start_t)

    def _most_parts(self, dt: float) -> int:
        """The most parts a machine can make in ``dt`` s: at half its shortest cycle watched,
        or MIN_CYCLE_S before one is."""
        cycle = MIN_CYCLE_S if self._shortest is None else 0.5 * self._shortest
        return int(dt / cycle) + 1

    def _unseen(self, c: int, n: int, since: float, t: float, reason: str, reset: bool, done: list) -> None:
        """Steps c+1..n made between ``since`` and ``t``, none seen: never merged into one part."""
        first = c + 1
        p = self._close(t)
        if p is None and self._stopped is not None:     # the part the program's stop left
            p = next(iter(self._close_stopped(None)), None)
        if p is not None:       # the part being cut ended at the first of them, unwatched
            p.part_no, p.outcome, p.unwatched = first, "partial", p.unwatched or reason
            done.append(p)
            first += 1
        if first <= n:
            count = n - first + 1
            parts = [] if count > MAX_LATE_PARTS else [
                Part(self.machine, start_t=since, end_t=t, part_no=no, outcome="unobserved", tool=self.tool,
                     material=self.material, unwatched=reason) for no in range(first, n + 1)]
            done.append(Gap(self.machine, reason, since, t, first, count, reset, parts))

    def _cutting(self, p: Part) -> None:
        if not self._cut:
            self._cut = True
            p.rpm, p.feed_mm_rev = self.rpm, self.feed
            self._out += self.flush()       # the next part cuts: no step came for the one before
        self._tool(p)

    def _tool(self, p: Part) -> None:
        if self.tool_number is not None and str(self.tool_number) not in (p.tools or "").split(","):
            p.tools = f"{p.tools},{self.tool_number}" if p.tools else str(self.tool_number)

    def _chatter(self, q: str, v: float) -> None:
        p = self.part
        if q == "cutting":
            if p is not None and v >= 0.5:
                self._cutting(p)
        elif q == "chatter_index_judged":    # not the tool's entry or exit, nor a speed change
            if p is not None:
                p.max_chatter_index = v if p.max_chatter_index is None else max(p.max_chatter_index, v)
        elif q == "chatter_threshold":
            self.threshold = v
            if p is not None:
                p.chatter_threshold = v
        elif q == "chatter_frequency_hz":
            self.chatter_hz = v
            if p is not None and self.alarm_on:
                p.chatter_frequency_hz = v
        elif q == "chatter_alarm":
            on = v >= 0.5
            if on and not self.alarm_on and p is not None:
                p.chatter_frequency_hz = self.chatter_hz
                self._alarm(p)
            self.alarm_on = on


# -- queries ------------------------------------------------------------------
Query = Callable[[str, tuple], list[dict[str, Any]]]

# The latest inspection of each part, joined to it; a part may be measured again.
_PARTS = """
SELECT w.id, w.uuid, w.machine_id, w.machine, w.part_no, w.program, w.start_t, w.end_t, w.outcome,
       w.max_chatter_index, w.chatter_threshold, w.chatter_alarms, w.chatter_frequency_hz,
       w.compensation_um, w.rpm, w.depth_mm, w.feed_mm_rev, w.tool, w.material, w.tools, w.abnormal, w.reason,
       w.unwatched, q.reason AS queued_reason,
       q.t AS queued_t, i.t AS inspected_t, i.ra_um, i.diameter_error_um, i.measured, i.inspector
FROM workpieces w
LEFT JOIN sampling_queue q ON q.part_uuid = w.uuid
LEFT JOIN inspections i ON i.id = (SELECT max(id) FROM inspections WHERE part_uuid = w.uuid)
"""


def decode(rows: list[dict]) -> list[dict]:
    """Inspection measurements back from their JSON text."""
    for r in rows:
        if r.get("measured") is not None:
            r["measured"] = json.loads(r["measured"])
    return rows


def parts(query: Query, abnormal: bool = False, pending: bool = False, limit: int = 100) -> list[dict]:
    """Parts, newest last, each with its latest inspection. ``pending``: only
    parts in the sampling queue not yet inspected."""
    where = []
    if abnormal:
        where.append("w.abnormal = 1")
    if pending:
        where.append("q.id IS NOT NULL AND i.id IS NULL")
    sql = _PARTS + (f" WHERE {' AND '.join(where)}" if where else "") + " ORDER BY w.id DESC LIMIT ?"
    return decode(query(sql, (limit,)))[::-1]


def parts_where(query: Query, where: str) -> list[dict]:
    """Parts matching a condition on ``w`` (made by the caller, never from a request's text), oldest first."""
    return decode(query(_PARTS + f" WHERE {where} ORDER BY w.id"))


def find_part(query: Query, ref: str) -> dict | None:
    """A part by its number in this store (``12``) or by uuid (or a unique prefix of it)."""
    if ref.isdigit():
        rows = query(_PARTS + " WHERE w.id = ?", (int(ref),))
    else:
        rows = query(_PARTS + " WHERE w.uuid LIKE ? LIMIT 2", (ref.replace("%", "") + "%",))
        if len(rows) > 1:
            return None
    return decode(rows)[0] if rows else None


def experiment_pairs(query: Query) -> list[tuple[str, str]]:
    """Every (tool holder, material) with experiment trials, most recently tried first."""
    rows = query("SELECT tool, material, MAX(id) AS last FROM experiments GROUP BY tool, material "
                 "ORDER BY last DESC")
    return [(r["tool"], r["material"]) for r in rows]


def experiments(query: Query, tool: str, material: str) -> list[dict]:
    rows = query("SELECT * FROM experiments WHERE tool = ? AND material = ? ORDER BY id", (tool, material))
    for r in rows:
        r["levels"], r["settings"] = json.loads(r["levels"]), json.loads(r["settings"])
    return rows


def recommendation(query: Query, tool: str, material: str) -> dict:
    """The Taguchi recommendation from the trials of one tool and material;
    ValueError (one line) when there is none to make."""
    from lathed.analysis import taguchi    # numpy: not for every reader of records
    trials = experiments(query, tool, material)
    if not trials:
        raise ValueError(f"no experiment records for tool {tool} and material {material}; "
                         "add them with `lathectl experiment add`")
    try:
        rec = taguchi.recommend(trials)
    except ValueError as e:
        raise ValueError(f"recommend: {tool}/{material}: {e}") from None
    return {"tool": tool, "material": material, **rec}


def recommendations(query: Query, tool: str, material: str) -> dict:
    """One recommendation per tool holder and material tried, most recent first, each
    with its own error: a pair whose trials cannot be analysed does not hide the others.
    ``tool``/``material``: the ones in use, marked."""
    out = []
    for t, m in experiment_pairs(query):
        try:
            out.append(recommendation(query, t, m))
        except ValueError as e:
            out.append({"tool": t, "material": m, "error": str(e)})
    return {"current": {"tool": tool, "material": material}, "pairs": out}


# what `lathectl export` names -> the record table it is read from
EXPORT_TABLES = {"events": "events", "parts": "workpieces", "inspections": "inspections", "experiments": "experiments"}


def export_page(query: Query, what: str, limit: int, after: int | None = None) -> list[dict]:
    """One page of rows to export, oldest first: the newest ``limit`` (``after`` None),
    else the first ``limit`` with an id above ``after`` (to page through every row)."""
    table = EXPORT_TABLES[what]
    limit = int(limit)     # ints, checked by the caller: they go into the SQL text
    if after is None:
        page = f"id IN (SELECT id FROM {table} ORDER BY id DESC LIMIT {limit})"
    else:
        page = f"id IN (SELECT id FROM {table} WHERE id > {int(after)} ORDER BY id LIMIT {limit})"
    if what == "events":
        return query(f"SELECT id, uuid, machine_id, t, source, kind, payload FROM events WHERE {page} ORDER BY id")
    if what == "parts":
        return parts_where(query, "w." + page)
    if what == "inspections":
        return decode(query(f"SELECT * FROM inspections WHERE {page} ORDER BY id"))
    return query(f"SELECT * FROM experiments WHERE {page} ORDER BY id")
