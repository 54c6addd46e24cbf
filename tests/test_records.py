"""The workpiece tracker and the part queries, with synthetic samples."""
from __future__ import annotations

import asyncio
import json
import time

import pytest

from lathed import records
from lathed.records import PartTracker
from lathed.store import Store
from tests.conftest import disk_free, disk_full


class Feed:
    """Samples in bus order with a clock, as the lathe driver and analyzers publish them."""

    def __init__(self, tracker: PartTracker):
        self.tr, self.t, self.done = tracker, 1000.0, []

    def lathe(self, **values):
        self.t += 0.1
        for q, v in values.items():
            self.done += self.tr.feed_sample("lathe", q, v, self.t)

    def chatter(self, index, alarm, threshold=1.0, hz=312.0):
        for q, v in (("chatter_threshold", threshold), ("chatter_index", index), ("chatter_index_judged", index),
                     ("chatter_frequency_hz", hz), ("chatter_alarm", alarm)):
            self.done += self.tr.feed_sample("chatter", q, v, self.t)

    def cutting(self, on):
        """The chatter analyzer's cut state (the one owner of it)."""
        self.done += self.tr.feed_sample("chatter", "cutting", 1.0 if on else 0.0, self.t)

    def cut(self, depth, rpm, index, alarm=0.0):
        self.lathe(spindle_rpm=rpm, feed_mm_rev=0.3, depth_of_cut_mm=0.0)
        for k in range(3):
            self.lathe(spindle_rpm=rpm, feed_mm_rev=0.3, depth_of_cut_mm=depth)
            if k == 0:
                self.cutting(True)
            self.chatter(index, alarm)
        self.chatter(0.1, 0.0)
        self.lathe(depth_of_cut_mm=0.0)
        self.cutting(False)


def tracker():
    return PartTracker("lathe", "chatter", "thermal", "T0101", "C45")


def test_parts_split_on_the_counter_and_chatter_flags_abnormal():
    f = Feed(tracker())
    f.lathe(part_count=7, program_state=1, program_number=1000)
    f.cut(1.0, 1500, 0.2)                   # the part in progress when tracking began
    f.lathe(part_count=8)
    f.cut(3.0, 2500, 2.7, alarm=1.0)        # chatters
    f.tr.feed_sample("thermal", "compensation_um", -12.5, f.t)
    f.lathe(part_count=9)
    f.cut(1.0, 2000, 0.3)
    f.lathe(part_count=10)
    assert [p.part_no for p in f.done] == [8, 9, 10]
    first, chat, calm = f.done
    assert first.outcome == "partial" and not first.abnormal
    assert chat.outcome == "finished" and chat.abnormal and chat.chatter_alarms == 1
    assert chat.max_chatter_index == 2.7 and chat.chatter_threshold == 1.0 and chat.chatter_frequency_hz == 312.0
    assert chat.rpm == 2500 and chat.depth_mm == 3.0 and chat.feed_mm_rev == 0.3 and chat.program == 1000
    assert chat.compensation_um == -12.5 and calm.compensation_um == -12.5   # the offset stays applied
    assert "chatter alarm" in chat.row()["reason"] and chat.row()["abnormal"] == 1
    assert not calm.abnormal and calm.row()["reason"] is None and calm.tool == "T0101"


def test_index_over_threshold_without_alarm_is_abnormal_too():
    f = Feed(tracker())
    f.lathe(part_count=0, program_state=1)
    f.lathe(part_count=1)
    f.cut(2.0, 2000, 1.4, alarm=0.0)
    f.lathe(part_count=2)
    partial, p = f.done
    assert partial.outcome == "partial" and not partial.abnormal
    assert p.abnormal and "reached the threshold" in p.row()["reason"]


def test_an_index_the_detector_did_not_judge_does_not_flag_the_part():
    """The ring of the tool leaving the work lifts the index of a window the detector does not
    count (a level step): not the part's vibration, so not its highest index."""
    f = Feed(tracker())
    f.lathe(part_count=0, program_state=1)
    f.lathe(part_count=1)
    f.cut(3.0, 2292, 0.8)
    f.done += f.tr.feed_sample("chatter", "chatter_index", 4.2, f.t)     # the release: not judged
    f.lathe(part_count=2)
    p = f.done[-1]
    assert p.max_chatter_index == 0.8 and not p.abnormal


def test_program_stop_aborts_a_part_that_cut_and_drops_one_that_did_not():
    f = Feed(tracker())
    f.lathe(part_count=3, program_state=1)
    f.lathe(part_count=4)
    f.cut(1.0, 1500, 0.2)
    f.lathe(program_state=0)                 # operator stopped mid-part
    f.lathe(program_state=1)                 # restarted
    f.lathe(program_state=0)                 # stopped again before cutting
    f.lathe(program_state=1)
    f.cut(1.0, 1500, 0.2)
    f.lathe(part_count=5)
    assert [(p.outcome, p.part_no) for p in f.done] == [("partial", 4), ("aborted", None), ("finished", 5)]


def test_a_counter_that_steps_after_the_program_stop_finishes_the_part():
    # a counter polled slower than the program state (1 s against 200 ms), or read after it in
    # the same poll, steps after the program has stopped: the part was finished, not aborted
    f = Feed(tracker())
    f.lathe(part_count=3, program_state=1)
    f.lathe(part_count=4)
    f.cut(1.0, 1500, 0.2)
    f.lathe(program_state=0)
    assert [(p.outcome, p.part_no) for p in f.done] == [("partial", 4)]     # held for the counter
    f.lathe(part_count=5)
    f.lathe(program_state=1)
    f.cut(1.0, 1500, 0.2)
    f.lathe(program_state=0)
    f.lathe(part_count=5)                    # read, not stepped: the operator stopped it
    assert [(p.outcome, p.part_no) for p in f.done] == [("partial", 4), ("finished", 5), ("aborted", None)]
    f.lathe(program_state=1)                 # a part whose cut nothing saw: its step still counts,
    f.lathe(program_state=0)                 # or the next start would call it not observed
    f.lathe(part_count=6)
    assert [(p.outcome, p.part_no) for p in f.done][3:] == [("finished", 6)]


def vibration_cut(f: Feed, rpm: float, index: float, alarm: float = 0.0) -> None:
    """A cut on a machine with no depth register: the chatter analyzer's cut state says it."""
    f.lathe(spindle_rpm=rpm, feed_mm_rev=0.3)
    f.done += f.tr.feed_sample("chatter", "cutting", 1.0, f.t)
    for _ in range(3):
        f.lathe(spindle_rpm=rpm)
        f.chatter(index, alarm)
    f.chatter(0.1, 0.0)
    f.done += f.tr.feed_sample("chatter", "cutting", 0.0, f.t)


def test_without_a_depth_register_the_cut_state_gives_speed_and_feed_and_an_aborted_part_that_cut_is_kept():
    f = Feed(tracker())
    f.lathe(part_count=3, program_state=1)
    f.lathe(part_count=4)
    vibration_cut(f, 2500, 2.7, alarm=1.0)
    f.lathe(spindle_rpm=2292)                # suppression moved it: the part keeps its entry speed
    f.lathe(program_state=0)                 # operator stopped mid-part: it cut, so it is kept
    f.lathe(program_state=1)
    f.lathe(program_state=0)                 # stopped again before cutting: nothing to keep
    f.lathe(program_state=1)
    vibration_cut(f, 1500, 0.2)
    f.lathe(part_count=5)
    assert [(p.outcome, p.part_no) for p in f.done] == [("partial", 4), ("aborted", None), ("finished", 5)]
    _, aborted, done = f.done
    assert (aborted.rpm, aborted.feed_mm_rev, aborted.depth_mm) == (2500, 0.3, None) and aborted.abnormal
    assert (done.rpm, done.feed_mm_rev) == (1500, 0.3) and not done.abnormal


def test_a_part_lists_the_turret_tools_that_cut_it_and_its_alarm_names_the_tool():
    f = Feed(tracker())
    f.lathe(part_count=1, program_state=1)
    f.lathe(part_count=2)
    f.lathe(tool_number=1)
    vibration_cut(f, 1500, 0.2)
    f.lathe(tool_number=2)                   # the turret indexes: the boring bar's pass chatters
    vibration_cut(f, 1500, 2.7, alarm=1.0)
    f.lathe(tool_number=1)                   # back to tool 1 for the next part, before it ends
    f.lathe(part_count=3)
    f.lathe(tool_number=3)
    f.lathe(tool_number=1)                   # an index without a cut is no tool of the part
    vibration_cut(f, 1500, 0.2)
    f.lathe(part_count=4)
    two, three = f.done[1:]
    assert (two.tools, three.tools) == ("1,2", "1")
    assert "chatter alarm during the cut at 312 Hz with tool 2" in two.row()["reason"]
    # a machine without the register: no tools, and the reason as before
    g = Feed(tracker())
    g.lathe(part_count=1, program_state=1)
    vibration_cut(g, 1500, 2.7, alarm=1.0)
    g.lathe(part_count=2)
    assert g.done[0].tools is None and "312 Hz: cut under" in g.done[0].row()["reason"]


def test_without_a_depth_register_the_part_takes_the_deepest_spindle_load_estimate():
    f = Feed(PartTracker("lathe", "chatter", "thermal", "T0101", "C45", suppress="suppress"))
    f.lathe(part_count=3, program_state=1)
    f.lathe(part_count=4)
    for est in (1.2, 2.9, 3.05, 0.6):                     # entry, cut, exit
        f.done += f.tr.feed_sample("suppress", "depth_est_mm", est, f.t)
        vibration_cut(f, 1500, 0.2)
    f.lathe(part_count=5)
    assert f.done[-1].depth_mm == 3.05
    # a machine that reports the depth: the register's is the part's, not an estimate
    f.lathe(depth_of_cut_mm=0.0)
    f.done += f.tr.feed_sample("suppress", "depth_est_mm", 2.7, f.t)
    f.cut(1.0, 1500, 0.2)
    f.lathe(part_count=6)
    assert f.done[-1].depth_mm == 1.0


def test_a_counter_jump_between_two_readings_is_parts_not_observed_not_one_part():
    """The lathe's link was down for three parts: the part being cut takes the first
    step, the other two are a gap of unobserved parts; the next part's start was not seen."""
    f = Feed(tracker())
    f.lathe(part_count=1, program_state=1)
    f.cut(1.0, 1500, 0.2)
    f.lathe(part_count=2)
    since = f.t                              # the count last read, before part 3's cut
    f.cut(3.0, 2500, 2.7, alarm=1.0)         # part 3 chatters, then the link goes down
    f.t += 20.0
    f.lathe(part_count=5)
    partial, three, gap = f.done
    assert (three.part_no, three.outcome, three.abnormal) == (3, "partial", True)
    assert three.unwatched == "part_count stepped by 3 between two readings" and three.queued
    assert "not watched whole" in three.queue_reason() and "chatter alarm" in three.queue_reason()
    assert isinstance(gap, records.Gap) and (gap.part_no_first, gap.count, gap.at_least) == (4, 2, False)
    assert [(p.part_no, p.outcome, p.start_t, p.end_t, p.abnormal, p.queued) for p in gap.parts] == [
        (4, "unobserved", since, f.t, False, True), (5, "unobserved", since, f.t, False, True)]
    f.cut(1.0, 1500, 0.2)
    f.lathe(part_count=6)
    six = f.done[-1]
    assert (six.part_no, six.outcome, six.unwatched) == (6, "partial", "part_count stepped by 3 between two readings")
    f.cut(1.0, 1500, 0.2)
    f.lathe(part_count=7)
    assert (f.done[-1].outcome, f.done[-1].unwatched, f.done[-1].queued) == ("finished", None, False)


def test_a_counter_reset_seen_goes_on_and_one_not_seen_is_parts_not_observed():
    f = Feed(tracker())
    f.lathe(part_count=57, program_state=1)
    f.cut(1.0, 1500, 0.2)
    f.lathe(part_count=0)                    # reset by the operator, mid-part: the part goes on
    f.lathe(part_count=1)
    assert [(p.part_no, p.outcome, p.unwatched) for p in f.done] == [(1, "partial", None)]
    g = Feed(tracker())
    g.lathe(part_count=40, program_state=1)
    g.cut(1.0, 1500, 0.2)
    g.t += 30.0
    g.lathe(part_count=3)                    # reset, and three parts made, between two readings
    one, gap = g.done
    assert (one.part_no, one.outcome, one.unwatched) == (1, "partial", records.RESET)
    assert (gap.part_no_first, gap.count, gap.at_least, gap.reason) == (2, 2, True, records.RESET)
    assert gap.payload()["part_no_last"] == 3 and gap.payload()["recorded"] == 2


def test_a_count_that_moves_faster_than_parts_are_made_is_a_counter_set_not_parts():
    # a counter set from 500 to 480 while watched was read as a reset and 480 parts made; a bad
    # read (500, 0, 500 in three polls) as 499: each queued for inspection
    f = Feed(tracker())
    f.lathe(part_count=500, program_state=1)
    f.cut(1.0, 1500, 0.2)
    f.lathe(part_count=480)
    f.lathe(part_count=0)
    f.lathe(part_count=480)
    (gap,) = f.done
    assert gap.parts == [] and gap.count == 480 and "faster than parts are made" in gap.reason
    f.cut(1.0, 1500, 0.2)
    f.lathe(part_count=481)                  # the part being cut went on
    assert (f.done[-1].part_no, f.done[-1].outcome) == (481, "partial")
    f.t += 100.0                             # a cycle watched whole: 100 s; 3 parts need 150 s
    f.lathe(part_count=482)
    f.t += 60.0
    f.lathe(part_count=485)
    assert f.done[-1].parts == [] and f.done[-1].count == 3


def test_the_next_program_may_start_before_the_counter_steps_for_the_part_before():
    # the part before was written aborted, and the next one's first instants finished in its place
    f = Feed(tracker())
    f.lathe(part_count=3, program_state=1)
    f.lathe(part_count=4)
    f.cut(1.0, 1500, 0.2)
    f.lathe(program_state=0)
    f.lathe(program_state=1)                 # the bar fed, the next cycle started
    f.lathe(part_count=5)                    # the counter, read a second late, steps for part 5
    f.cut(2.0, 2000, 0.2)
    f.lathe(part_count=6)
    assert [(p.part_no, p.outcome, p.depth_mm) for p in f.done] == [
        (4, "partial", None), (5, "finished", 1.0), (6, "finished", 2.0)]


def test_a_part_the_stop_left_takes_the_first_step_of_a_gap_not_a_row_of_its_own():
    # it was written aborted at the analyzer's restart, and its step again as a part not observed
    f = Feed(tracker())
    f.lathe(part_count=3, program_state=1)
    f.lathe(part_count=4)
    f.cut(1.0, 1500, 0.2)
    f.lathe(program_state=0)
    f.tr.resume("records analyzer restarting", f.t)
    f.t += 60.0
    f.lathe(part_count=6)
    assert [(p.part_no, p.outcome, p.unwatched) for p in f.done[1:2]] == [
        (5, "partial", "records analyzer restarting")]
    (gap,) = f.done[2:]
    assert [(p.part_no, p.outcome) for p in gap.parts] == [(6, "unobserved")]


def test_a_jump_beyond_any_production_is_told_not_written_part_by_part():
    f = Feed(tracker())
    f.lathe(part_count=5, program_state=1)
    f.t += 30_000.0                          # link down long enough, but another controller came back
    f.lathe(part_count=5 + records.MAX_LATE_PARTS + 2)
    _, gap = f.done
    assert gap.count == records.MAX_LATE_PARTS + 1 and gap.parts == [] and gap.payload()["recorded"] == 0


def test_after_a_gap_in_the_watch_the_next_reading_tells_the_parts_made_meanwhile():
    f = Feed(tracker())
    f.tr.resume("lathed was not running", 500.0, count=3)     # the last part recorded: no. 3 at t 500
    f.lathe(part_count=3, program_state=1)   # none made meanwhile: the part on the machine is partial
    f.cut(1.0, 1500, 0.2)
    f.lathe(part_count=4)
    f.cut(1.0, 1500, 0.2)
    f.tr.resume("records analyzer restarting", 0.0)    # mid-part 5: not watched whole
    for n in (5, 6, 7):                      # part 6's start may have been in the gap too
        f.lathe(part_count=n)
        f.cut(1.0, 1500, 0.2)
    assert [(p.part_no, p.outcome, p.unwatched) for p in f.done] == [
        (4, "partial", "lathed was not running"), (5, "partial", "records analyzer restarting"),
        (6, "partial", "records analyzer restarting"), (7, "finished", None)]
    g = Feed(tracker())
    g.tr.resume("lathed was not running", 500.0, count=3)
    g.lathe(program_state=1, part_count=5)
    (gap,) = g.done
    assert (gap.part_no_first, gap.count, gap.from_t, gap.to_t) == (4, 2, 500.0, g.t)


def test_machine_alarm_during_a_part_flags_it():
    f = Feed(tracker())
    f.lathe(part_count=0, program_state=1)
    f.lathe(part_count=1)
    f.cut(1.0, 1500, 0.2)
    f.lathe(program_state=2)
    f.lathe(program_state=1)
    f.lathe(part_count=2)
    assert f.done[-1].abnormal and "machine alarm" in f.done[-1].row()["reason"]


def test_parts_join_their_inspection_and_leave_the_queue(tmp_path):
    store = Store(tmp_path / "r.db", machine_id="cell")
    f = Feed(tracker())
    f.lathe(part_count=0, program_state=1)
    f.lathe(part_count=1)
    f.cut(3.0, 2500, 2.5, alarm=1.0)
    f.lathe(part_count=2)
    f.cut(1.0, 1500, 0.2)
    f.lathe(part_count=3)

    async def write():
        for p in f.done:
            row = p.row()
            await store.add("workpieces", {"uuid": f"u{p.part_no}", **row})
            if p.abnormal:
                await store.add("sampling_queue", {"t": p.end_t, "part_uuid": f"u{p.part_no}",
                                                   "reason": row["reason"]})
    asyncio.run(write())
    q = store.query
    assert [r["part_no"] for r in records.parts(q, abnormal=True)] == [2]
    assert [r["part_no"] for r in records.parts(q, pending=True)] == [2]
    part = records.find_part(q, "u2")
    asyncio.run(store.add("inspections", {"t": 1.0, "part_uuid": part["uuid"], "ra_um": 4.5,
                                          "diameter_error_um": -32.0, "measured": {"roundness_um": 4},
                                          "inspector": "anna"}))
    assert records.parts(q, pending=True) == []
    joined = records.find_part(q, str(part["id"]))
    assert (joined["ra_um"], joined["diameter_error_um"], joined["measured"], joined["inspector"]) == \
        (4.5, -32.0, {"roundness_um": 4}, "anna")
    assert joined["max_chatter_index"] == 2.5 and joined["queued_t"] is not None
    assert records.find_part(q, "u") is None          # ambiguous prefix
    assert [r["part_no"] for r in records.parts(q)] == [1, 2, 3]
    store.close()


@pytest.mark.parametrize("run", [10 ** 30, -1, 0, "3", 2.5, True])
def test_experiment_run_must_be_a_sane_integer(run):
    # issue 18 D1: a run of 10**30 reached the store writer and killed it
    from lathed.config import Section
    from lathed.control import RequestError
    from lathed_plugins.records import Records
    r = Records("records", Section("f.toml", "analyzer.records", {"tool": "T", "material": "M"}))
    with pytest.raises(RequestError, match=r"^experiment_add: run: .*an integer in \[1, 10000\]"):
        asyncio.run(r._cmd_experiment_add({"levels": {"A": 1}, "ra_um": 1.0, "run": run}))


# -- the records analyzer writing parts: on the bus, against the real store --------------------

class BusFeed(Feed):
    """The same samples published on a bus, for the records analyzer."""

    def __init__(self, bus):
        self.bus, self.t = bus, 1000.0

    def lathe(self, **values):
        from lathed.bus import Sample
        self.t += 0.1
        for q, v in values.items():
            self.bus.publish(Sample("lathe", q, float(v), "", self.t))

    def chatter(self, index, alarm, threshold=1.0, hz=312.0):
        from lathed.bus import Sample
        for q, v in (("chatter_threshold", threshold), ("chatter_index", index), ("chatter_index_judged", index),
                     ("chatter_frequency_hz", hz), ("chatter_alarm", alarm)):
            self.bus.publish(Sample("chatter", q, float(v), "", self.t))

    def cutting(self, on):
        from lathed.bus import Sample
        self.bus.publish(Sample("chatter", "cutting", 1.0 if on else 0.0, "", self.t))


class Log:
    """The analyzer's logger: what it said, and a threading.Event per message name."""

    def __init__(self):
        import threading
        self.lines, self.said = [], {}
        self._lock = threading.Lock()

    def heard(self, event: str):
        import threading
        with self._lock:
            return self.said.setdefault(event, threading.Event())

    def _log(self, event, **kw):
        self.lines.append((event, kw))
        self.heard(event).set()
    info = warning = error = _log


def records_analyzer(tmp_path):
    import structlog  # noqa: F401  (AnalyzerContext's annotations)
    from lathed.analyzer import AnalyzerContext
    from lathed.bus import Bus
    from lathed.config import Section
    from lathed_plugins.records import Records
    store, bus, log = Store(tmp_path / "r.db", machine_id="cell"), Bus(), Log()
    r = Records("records", Section("t.toml", "analyzer.records", {"tool": "T", "material": "M"}))
    r.ctx = AnalyzerContext(bus, log, lambda kind, payload=None: store.record_future(kind, "records", payload),
                            None, lambda cmd, handler: None, store, lambda n: None, ".")
    return store, bus, r, log


def hold_first_part_commit(store):
    """The commit of the first part's transaction stalls (a slow fsync) until released."""
    import threading
    real, taken, release = store._commit, threading.Event(), threading.Event()

    def held(batch):
        if any("workpieces" in str(sql) for sql, _, _ in batch):
            store._commit = real
            taken.set()
            release.wait(10)
        real(batch)
    store._commit = held
    return taken, release


async def turns(pred, timeout_s: float = 30.0):
    """Loop turns until ``pred()``, up to a deadline.  Counted in turns alone, the wait lost a
    race on a busy machine: what it waits for is often the store's write, done in the store's
    thread (a commit with its fsync), and 20 000 turns of the loop pass in a fraction of a
    second (1 run in 6 failed so under load: "not reached in loop turns")."""
    end = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > end:
            raise AssertionError(f"not reached in {timeout_s:g} s")
        await asyncio.sleep(0)


def abnormal_part(f: BusFeed, count: int):
    f.lathe(spindle_rpm=2000, feed_mm_rev=0.3, depth_of_cut_mm=2.0)
    f.cutting(True)
    f.chatter(3.0, 1.0)
    f.chatter(0.1, 0.0)
    f.lathe(depth_of_cut_mm=0.0)
    f.cutting(False)
    f.lathe(part_count=count)


async def running_to_abnormal_part_2(r, bus):
    """The records analyzer running, fed part 1's start and an abnormal part 2: (its task, the feed)."""
    task = asyncio.create_task(r.run())
    await turns(lambda: bus._subs.get("lathe"))
    f = BusFeed(bus)
    f.lathe(part_count=1, program_state=1)
    abnormal_part(f, 2)
    return task, f


def written(path) -> tuple[list, list, list]:
    import sqlite3
    con = sqlite3.connect(path)
    try:
        parts = con.execute("SELECT id, part_no, abnormal, uuid FROM workpieces ORDER BY id").fetchall()
        queued = {u for (u,) in con.execute("SELECT part_uuid FROM sampling_queue")}
        events = [json.loads(p)["part"] for (p,) in
                  con.execute("SELECT payload FROM events WHERE kind = 'part_abnormal' ORDER BY id")]
    finally:
        con.close()
    return parts, queued, events


def test_a_stop_while_a_part_commits_leaves_no_abnormal_part_out_of_the_sampling_queue(tmp_path):
    store, bus, r, _ = records_analyzer(tmp_path)
    taken, release = hold_first_part_commit(store)

    async def main():
        task, f = await running_to_abnormal_part_2(r, bus)
        assert await asyncio.to_thread(taken.wait, 5)     # part 2 is being committed...
        task.cancel()                                      # ...when the daemon stops
        await asyncio.gather(task, return_exceptions=True)
    asyncio.run(main())
    release.set()
    store.close()
    parts, queued, events = written(tmp_path / "r.db")
    assert [(no, ab) for _, no, ab, _ in parts] == [(2, 1)]
    assert {u for *_, u in parts} == queued and events == [parts[0][0]]


def test_a_stalled_commit_holds_up_neither_the_bus_nor_the_parts_behind_it(tmp_path):
    from lathed.bus import Sample
    store, bus, r, _ = records_analyzer(tmp_path)
    taken, release = hold_first_part_commit(store)

    async def main():
        task, f = await running_to_abnormal_part_2(r, bus)
        assert await asyncio.to_thread(taken.wait, 5)     # part 2's commit stalls
        for _ in range(3):                                 # seconds of a machine polled at 10 Hz meanwhile
            for q in range(500):
                bus.publish(Sample("lathe", f"reg{q}", 1.0, "", f.t))
            await asyncio.sleep(0)
        abnormal_part(f, 3)
        f.lathe(part_count=4)
        await turns(lambda: not bus._subs["lathe"][0]._items)   # the bus loop read on
        task.cancel()                                      # stopped with parts 3 and 4 still unwritten
        await asyncio.gather(task, return_exceptions=True)
    asyncio.run(main())
    release.set()
    store.close()
    assert bus.stats()["dropped"] == {}
    parts, queued, events = written(tmp_path / "r.db")
    assert [(no, ab) for _, no, ab, _ in parts] == [(2, 1), (3, 1), (4, 0)]
    assert {u for _, _, ab, u in parts if ab} == queued and events == [p[0] for p in parts if p[2]]


def test_a_part_the_store_refused_is_kept_logged_and_written_once_it_takes_records(tmp_path, monkeypatch):
    import lathed_plugins.records as plugin
    monkeypatch.setattr(plugin, "RETRY_S", (0.001, 0.01), raising=False)
    store, bus, r, log = records_analyzer(tmp_path)
    disk_full(store, "workpieces")

    async def main():
        task, f = await running_to_abnormal_part_2(r, bus)
        assert await asyncio.to_thread(log.heard("part_not_written").wait, 5)
        event, kw = next(line for line in log.lines if line[0] == "part_not_written")
        assert kw["part_no"] == 2 and "chatter alarm" in kw["reason"] and "disk is full" in kw["error"]
        await turns(lambda: r.status()["last_write_error"])
        st = r.status()
        assert st["unwritten"] == 1 and "1 not yet written, retrying" in st["summary"] and not task.done()
        await asyncio.wrap_future(disk_free(store))   # space again
        assert await asyncio.to_thread(log.heard("part_abnormal").wait, 5)
        assert r.status()["unwritten"] == 0 and r.status()["parts"] == 1
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    asyncio.run(main())
    assert store.events_stored == 1           # the events poller hears of its event
    store.close()
    parts, queued, events = written(tmp_path / "r.db")
    assert [(no, ab) for _, no, ab, _ in parts] == [(2, 1)]
    assert {u for *_, u in parts} == queued and events == [parts[0][0]]


# -- parts the records analyzer did not see made: recorded as not observed, never merged ------------

def rows(path) -> list[tuple]:
    """(part_no, outcome, unwatched, queued reason) of every part, in order; and the part_unobserved events."""
    import sqlite3
    con = sqlite3.connect(path)
    try:
        cols = {r[1] for r in con.execute("PRAGMA table_info(workpieces)")}
        unwatched = "w.unwatched" if "unwatched" in cols else "NULL"
        parts = con.execute(f"SELECT w.part_no, w.outcome, {unwatched}, q.reason FROM workpieces w "
                            "LEFT JOIN sampling_queue q ON q.part_uuid = w.uuid ORDER BY w.id").fetchall()
        events = [json.loads(p) for (p,) in
                  con.execute("SELECT payload FROM events WHERE kind = 'part_unobserved' ORDER BY id")]
    finally:
        con.close()
    return parts, events


def failing_on_fault(r, record):
    """A supervisor runner (no retry delay) for the records analyzer, which fails at a "fault"
    sample (a bug in it): the supervisor then records ``analyzer_fault`` and restarts it."""
    from lathed.supervisor import Runner
    real = r.tracker.feed_sample

    def feed(source, q, v, t):
        if q == "fault":
            raise RuntimeError("a bug in the records analyzer")
        return real(source, q, v, t)
    r.tracker.feed_sample = feed
    return Runner("analyzer", "records", r, 0.0, 0.0, record)


def test_parts_made_while_the_records_analyzer_restarts_are_recorded_not_merged(tmp_path):
    """The analyzer fails mid-part; the supervisor restarts it; meanwhile the lathe finishes that
    part and two more. Each is a row of its own: the one it was watching, partial; the two it
    never saw, unobserved; all three queued for inspection, and one event says so."""
    store, bus, r, _ = records_analyzer(tmp_path)
    f = BusFeed(bus)

    def record(kind, source, payload=None):
        if kind == "analyzer_fault":           # unsubscribed now, restarted after this: the gap
            for n in (4, 5, 6):
                f.lathe(part_count=n)
    runner = failing_on_fault(r, record)

    async def main():
        task = asyncio.create_task(runner.loop())
        await turns(lambda: bus._subs.get("lathe"))
        f.lathe(part_count=1, program_state=1)
        for n in (2, 3):
            f.cut(1.0, 1500, 0.2)
            f.lathe(part_count=n)
        f.cut(1.0, 1500, 0.2)                  # part 4 being cut...
        f.lathe(fault=1)                       # ...when the analyzer fails
        await turns(lambda: runner.failures and bus._subs.get("lathe"))    # running again
        f.lathe(part_count=6)                  # its first reading after the restart
        f.cut(1.0, 1500, 0.2)
        f.lathe(part_count=7)
        await turns(lambda: r.tracker.count == 7)
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    asyncio.run(main())
    store.close()
    parts, events = rows(tmp_path / "r.db")
    assert [(no, outcome) for no, outcome, *_ in parts] == [
        (2, "partial"), (3, "finished"), (4, "partial"), (5, "unobserved"), (6, "unobserved"), (7, "partial")]
    gap = [p for p in parts if p[0] in (4, 5, 6, 7)]
    assert all(why == "records analyzer restarting" and queued for _, _, why, queued in gap), gap
    assert parts[1][2:] == (None, None)        # watched whole and calm: not queued
    assert [(e["count"], e["part_no_first"], e["part_no_last"], e["reason"]) for e in events] == [
        (2, 5, 6, "records analyzer restarting")]


def lathed_down_for_parts_4_to_6(tmp_path, t0: float = 1000.0):
    """lathed stops after part 3; the lathe makes parts 4 to 6 in the hour before lathed starts
    again and sees part 7 made. Its store's path."""
    store, bus, r, _ = records_analyzer(tmp_path)

    async def first_run():
        task = asyncio.create_task(r.run())
        await turns(lambda: bus._subs.get("lathe"))
        f = BusFeed(bus)
        f.t = t0
        f.lathe(part_count=1, program_state=1)
        for n in (2, 3):
            f.cut(1.0, 1500, 0.2)
            f.lathe(part_count=n)
        await turns(lambda: r.tracker.count == 3)
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        return f.t
    t = asyncio.run(first_run())
    store.close()

    store, bus, r, _ = records_analyzer(tmp_path)    # the next start, on the same store

    async def second_run():
        task = asyncio.create_task(r.run())
        await turns(lambda: bus._subs.get("lathe"))
        f = BusFeed(bus)
        f.t = t + 3600.0
        f.lathe(part_count=6, program_state=1)
        f.cut(1.0, 1500, 0.2)
        f.lathe(part_count=7)
        await turns(lambda: r.tracker.count == 7)
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    asyncio.run(second_run())
    store.close()
    return tmp_path / "r.db"


def test_parts_made_while_lathed_was_not_running_are_recorded_at_its_start(tmp_path):
    parts, events = rows(lathed_down_for_parts_4_to_6(tmp_path))
    assert [(no, outcome) for no, outcome, *_ in parts] == [
        (2, "partial"), (3, "finished"), (4, "unobserved"), (5, "unobserved"), (6, "unobserved"), (7, "partial")]
    assert all(why == "lathed was not running" and queued for no, _, why, queued in parts if no >= 4)
    (e,) = events
    assert (e["count"], e["part_no_first"], e["part_no_last"], e["reason"]) == (3, 4, 6, "lathed was not running")
    assert e["to_t"] - e["from_t"] == pytest.approx(3600.0, abs=1.0)


def test_a_jump_beyond_any_production_is_an_event_and_the_analyzer_goes_on(tmp_path):
    store, bus, r, log = records_analyzer(tmp_path)

    async def main():
        task = asyncio.create_task(r.run())
        await turns(lambda: bus._subs.get("lathe"))
        f = BusFeed(bus)
        f.lathe(part_count=5, program_state=1)
        f.t += 30_000.0
        f.lathe(part_count=5 + records.MAX_LATE_PARTS + 2)
        assert await asyncio.to_thread(log.heard("part_unobserved").wait, 5)
        f.cut(1.0, 1500, 0.2)
        f.lathe(part_count=5 + records.MAX_LATE_PARTS + 3)
        await turns(lambda: r.tracker.count == 5 + records.MAX_LATE_PARTS + 3)
        assert not task.done() and r.status()["unobserved"] == 0
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    asyncio.run(main())
    store.close()
    parts, events = rows(tmp_path / "r.db")
    assert [(no, outcome) for no, outcome, *_ in parts] == [
        (6, "partial"), (5 + records.MAX_LATE_PARTS + 3, "partial")]
    (e,) = events
    assert (e["count"], e["recorded"], e["first_part"]) == (records.MAX_LATE_PARTS + 1, 0, None)


def test_a_part_the_program_stop_closed_is_written_when_lathed_stops_before_the_counter_is_read(tmp_path):
    store, bus, r, _ = records_analyzer(tmp_path)

    async def main():
        task = asyncio.create_task(r.run())
        await turns(lambda: bus._subs.get("lathe"))
        f = BusFeed(bus)
        f.lathe(part_count=1, program_state=1)
        f.lathe(spindle_rpm=2000, feed_mm_rev=0.3, depth_of_cut_mm=2.0)
        f.cutting(True)
        f.lathe(depth_of_cut_mm=0.0)
        f.cutting(False)
        f.lathe(program_state=0)
        await turns(lambda: r.tracker._stopped is not None)
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    asyncio.run(main())
    store.close()
    parts, _ = rows(tmp_path / "r.db")
    assert [(no, outcome) for no, outcome, *_ in parts] == [(None, "aborted")]


def test_a_part_the_stop_left_is_one_row_across_a_records_analyzer_restart(tmp_path):
    # the restart wrote it aborted, and the counter's step after it again as a part not observed
    store, bus, r, _ = records_analyzer(tmp_path)
    f = BusFeed(bus)
    runner = failing_on_fault(r, lambda *a, **k: None)

    async def main():
        task = asyncio.create_task(runner.loop())
        await turns(lambda: bus._subs.get("lathe"))
        f.lathe(part_count=1, program_state=1)
        f.cut(1.0, 1500, 0.2)
        f.lathe(part_count=2)
        f.cut(1.0, 1500, 0.2)                  # part 3 cut...
        f.lathe(program_state=0)               # ...the program ends; the counter (slower) not yet read
        f.lathe(fault=1)                       # the analyzer fails now
        await turns(lambda: runner.failures and bus._subs.get("lathe"))
        f.lathe(part_count=3)                  # the counter's step for that part, after the restart
        await turns(lambda: r.tracker.count == 3 and not r.unwritten)
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    asyncio.run(main())
    store.close()
    parts, events = rows(tmp_path / "r.db")
    assert [(no, outcome, unwatched) for no, outcome, unwatched, _ in parts] == [
        (2, "partial", "lathed was not running"), (3, "partial", "records analyzer restarting")]
    assert events == []


def stopped_and_started(tmp_path, before, after):
    """lathed runs ``before(feed)``, stops, and starts again on the same store a minute later to
    run ``after(feed)``: the rows and part_unobserved events it wrote."""
    t = 1000.0
    for feed in (before, after):
        store, bus, r, _ = records_analyzer(tmp_path)

        async def run():
            task = asyncio.create_task(r.run())
            await turns(lambda: bus._subs.get("lathe"))
            f = BusFeed(bus)
            f.t = t
            feed(f)
            await turns(lambda: r.tracker.count == f.count and not bus._subs["lathe"][0]._items)
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
            return f.t
        t = asyncio.run(run()) + 60.0
        store.close()
    return rows(tmp_path / "r.db")


def test_a_part_the_stop_left_is_one_row_across_a_lathed_restart(tmp_path):
    # written aborted at lathed's stop, and the counter's step after it again as a part not observed
    def before(f):
        f.lathe(part_count=1, program_state=1)
        f.cut(1.0, 1500, 0.2)
        f.lathe(part_count=2)
        f.cut(1.0, 1500, 0.2)                  # part 3 cut, the program ends, lathed stops
        f.lathe(program_state=0)               # before the counter (slower) is read
        f.count = 2

    def after(f):
        f.lathe(part_count=3, program_state=0)   # the step for part 3
        f.lathe(program_state=1)
        f.cut(1.0, 1500, 0.2)
        f.lathe(part_count=4)
        f.count = 4
    parts, events = stopped_and_started(tmp_path, before, after)
    assert [(no, outcome) for no, outcome, *_ in parts] == [(2, "partial"), (None, "aborted"), (4, "finished")]
    assert events == []


def test_a_count_step_while_idle_is_not_reported_again_at_the_next_start(tmp_path):
    # the last count seen was not kept: the next start took the step for a part made while down
    def before(f):
        f.lathe(part_count=1, program_state=1)
        f.cut(1.0, 1500, 0.2)
        f.lathe(program_state=0)
        f.lathe(part_count=2)                  # the step after the stop: part 2 finished
        f.lathe(part_count=3)                  # the operator steps the counter, nothing running
        f.count = 3

    def after(f):
        f.lathe(part_count=3, program_state=0)
        f.lathe(program_state=1)
        f.cut(1.0, 1500, 0.2)
        f.lathe(part_count=4)
        f.count = 4
    parts, events = stopped_and_started(tmp_path, before, after)
    assert [(no, outcome) for no, outcome, *_ in parts] == [(2, "partial"), (4, "finished")]
    assert events == []


def test_the_count_is_kept_as_it_is_read_not_only_at_the_stop(tmp_path):
    # a power cut skips the stop: a count kept only there would be older than the parts written since
    store, bus, r, _ = records_analyzer(tmp_path)

    async def main():
        task = asyncio.create_task(r.run())
        await turns(lambda: bus._subs.get("lathe"))
        f = BusFeed(bus)
        f.lathe(part_count=1, program_state=0)
        f.lathe(part_count=2)                  # the part on the machine at the start, finished
        await turns(lambda: r.tracker.count == 2 and not r.unwritten)
        await asyncio.wrap_future(store.submit("SELECT 1", ()))     # committed in order: the count before it
        assert store.query("SELECT machine, count, held FROM last_part_count") == [
            {"machine": "lathe", "count": 2, "held": 0}]
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    asyncio.run(main())
    store.close()


def test_the_count_is_never_saved_ahead_of_a_part_not_yet_written(tmp_path, monkeypatch):
    # saved as read, the count ran ahead of a part whose row was refused (or still queued): a
    # process lost then left a count that said the part's step was seen, and the part was gone
    import lathed_plugins.records as plugin
    monkeypatch.setattr(plugin, "RETRY_S", (0.001, 0.01), raising=False)
    store, bus, r, log = records_analyzer(tmp_path)
    disk_full(store, "workpieces")

    async def main():
        task, f = await running_to_abnormal_part_2(r, bus)
        assert await asyncio.to_thread(log.heard("part_not_written").wait, 5)
        f.lathe(part_count=3)                  # part 3 finished while part 2 waits to be written
        await turns(lambda: r.tracker.count == 3)
        await asyncio.wrap_future(store.submit("SELECT 1", ()))
        # as the process would leave it, lost now: part 1's count, so part 2 is counted at the next start
        assert [c["count"] for c in store.query("SELECT count FROM last_part_count")] == [1]
        await asyncio.wrap_future(disk_free(store))   # space again
        await turns(lambda: not r.unwritten)   # parts 2 and 3 written: the count saved after them
        await asyncio.wrap_future(store.submit("SELECT 1", ()))
        assert [c["count"] for c in store.query("SELECT count FROM last_part_count")] == [3]
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    asyncio.run(main())
    store.close()


def test_a_count_read_while_the_last_part_is_being_written_is_saved_at_the_stop(tmp_path):
    # deferred until the writer had the part in, the save never came: the writer is cancelled
    # at the stop, and the next start took the hand step for a part made while lathed was down
    import threading
    store, bus, r, _ = records_analyzer(tmp_path)
    commit, taken, release = store._commit, threading.Event(), threading.Event()

    def slow(batch):                    # part 2's commit is slow (an fsync on a loaded SD card)
        if any("workpieces" in str(sql) for sql, *_ in batch):
            store._commit = commit
            taken.set()
            release.wait(10)
        commit(batch)
    store._commit = slow

    async def main():
        task, f = await running_to_abnormal_part_2(r, bus)
        assert await asyncio.to_thread(taken.wait, 5)
        f.lathe(program_state=0)        # the program ends, part 3 opened at the step: not cut
        f.lathe(part_count=2)           # the counter read again: no step, the uncut part dropped
        f.lathe(part_count=3)           # stepped by hand, idle
        await turns(lambda: r.tracker.count == 3)
        task.cancel()                   # lathed stops with part 2's write on its way
        await asyncio.gather(task, return_exceptions=True)
    asyncio.run(main())
    release.set()
    store.close()
    assert [(c["count"], c["held"]) for c in Store(tmp_path / "r.db").query(
        "SELECT count, held FROM last_part_count")] == [(3, 0)]


def test_the_cut_is_the_chatter_analyzers_cut_state_not_the_depth_register():
    """One owner of the cut (lathed.analysis.cut.state, published by the chatter analyzer): the
    depth register gives the part's depth, not whether it was cut; the part's speed and feed are
    those when the cut state said the first cut began."""
    f = Feed(tracker())
    f.lathe(part_count=1, program_state=1)
    f.lathe(part_count=2)
    f.lathe(spindle_rpm=1500, feed_mm_rev=0.3, depth_of_cut_mm=1.0)     # the register alone
    f.lathe(spindle_rpm=1800, depth_of_cut_mm=0.0)
    f.cutting(True)
    f.lathe(depth_of_cut_mm=2.0)
    f.cutting(False)
    f.lathe(part_count=3)
    partial, p = f.done
    assert p.rpm == 1800 and p.depth_mm == 2.0
