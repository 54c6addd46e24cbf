"""The push API (lathed.push): `subscribe` on the control socket."""
from __future__ import annotations

import json
import socket
import subprocess

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lathed import push
from lathed.client import RemoteError, subscribe
from lathed.display import unpacked
from lathed.viewdelta import changed_keys, merge_view
from tests.conftest import BIN, SIM_RATE_HZ, Daemon, sim_config, wait_until
from tests.inproc_daemon import InProcessDaemon


@pytest.fixture(scope="module")
def inproc(tmp_path_factory):
    d = InProcessDaemon(tmp_path_factory.mktemp("push"))
    yield d
    d.close()


@pytest.mark.parametrize("args, wanted", [
    ({"samples": ["lathe"]}, "subscribe: samples[0]: 'lathe' is not SOURCE/QUANTITY"),
    ({"samples": ["spindle/*"]}, "subscribe: samples[0]: no machine, sensor or analyzer named 'spindle'"),
    # a quantity the driver's config does not give: lathectl watch waited for it forever
    ({"samples": ["lathe/spindle_rpm", "lathe/nosuch"]},
     "subscribe: samples[1]: 'lathe' publishes no quantity 'nosuch'; it publishes: alarm_code, "),
    ({"samples": ["lathe/rpm*"]}, "subscribe: samples[0]: 'lathe' publishes no quantity 'rpm*'; it publishes: "),
    ({"samples": ["vib/acceleration"]}, "subscribe: samples[0]: 'vib' publishes no quantity 'acceleration'; "
                                        "it publishes: rms"),
    ({"vibration": ["lathe"]}, "subscribe: vibration[0]: no sensor named 'lathe'"),
    ({"views": ["thermal"]}, "subscribe: views[0]: 'thermal' has no view"),
    ({"events": True, "rate_hz": 100}, "subscribe: rate_hz: 100 is out of range"),
    ({"kinds": ["chatter_alarm"]}, "subscribe: kinds: narrows events: give events = true too"),
    # followed nothing, forever
    ({"events": True, "kinds": ["chatter_alram"]}, "subscribe: kinds: 'chatter_alram' is not a kind of event "
                                                   "(did you mean 'chatter_alarm'?); known: alarm_cleared, "),
    ({}, "subscribe: nothing asked for"),
    ({"states": True, "colour": "red"}, "subscribe: unknown argument 'colour'"),
])
def test_bad_subscriptions_are_refused_in_one_line(inproc, args, wanted):
    reply = inproc.handle(json.dumps({"cmd": "subscribe", "args": args}).encode())
    assert reply["ok"] is False
    assert reply["error"].startswith(wanted), reply["error"]
    assert "\n" not in reply["error"]
    assert inproc.daemon.push.subscribers == set()


def test_a_quantity_that_may_still_come_is_watched(inproc):
    """A register not read yet (the machine is off), a probe a sensor without a ``sensors``
    list may report later, an analyzer's (not declared): taken, as they may come."""
    reply = inproc.handle(json.dumps({"cmd": "subscribe", "args": {
        "samples": ["lathe/spindle_*", "temps/t_spare", "watch/chatter_index", "*/nosuch"]}}).encode())
    assert reply["ok"] is True, reply
    reply["result"].close()
    assert inproc.daemon.push.subscribers == set()


def test_wildcards_that_match_nothing_are_not_an_error(inproc):
    """A line without such a sensor or analyzer: a pattern like lathed-web's "*" must still
    subscribe (an exact name that is not there is refused, above)."""
    reply = inproc.handle(json.dumps({"cmd": "subscribe", "args": {
        "samples": ["mill*/x_mm"], "vibration": ["accel*"], "views": ["chat*"], "states": True}}).encode())
    assert reply["ok"] is True, reply
    sub = reply["result"]
    assert sub.vibration == [] and sub.views == [] and sub.first["samples"] == {}
    assert inproc.daemon.push.subscribers == {sub}
    sub.close()
    assert inproc.daemon.push.subscribers == set()


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("push-live")
    cfg, paths = sim_config(tmp, analyzers="""
[analyzer.chatter]
plugin = "chatter"
input = "accel"
machine = "lathe"

[analyzer.suppress]
plugin = "suppression"
chatter = "chatter"
machine = "lathe"
mode = "auto"
strategy = "frequency"
""")
    d = Daemon(cfg, paths["socket"])
    try:
        d.wait_ready()
        wait_until(lambda: d.item("sensors", "accel")["state"] == "connected", what="accel connected")
        # the snapshot test expects temperatures: the first line comes after the serial link opens
        wait_until(lambda: d.item("sensors", "temps")["last_value"], what="temperatures")
        wait_until(lambda: d.item("machines", "lathe")["spindle_rpm"] is not None, what="lathe spindle speed")
        yield d
    finally:
        d.stop()


def test_a_subscriber_gets_the_snapshot_then_live_values(live):
    frames = subscribe({"samples": ["lathe/spindle_rpm", "temps/*"], "vibration": ["accel"], "states": True,
                        "events": True, "events_limit": 100, "rate_hz": 10}, sock_path=live.socket)
    first = next(frames)
    # the snapshot: the latest of everything asked for, at once
    assert "lathe/spindle_rpm" in first["samples"]
    assert any(k.startswith("temps/t_") for k in first["samples"])
    assert all(k == "lathe/spindle_rpm" or k.startswith("temps/") for k in first["samples"])
    assert {m["name"] for m in first["status"]["machines"]} == {"lathe"}
    assert "daemon_started" in [e["kind"] for e in first["events"]]
    t0 = first["samples"]["lathe/spindle_rpm"][0]
    # then frames with newer values, a decimated vibration view and a new event
    live.ctl("suppress", "manual")
    seen: dict[str, object] = {}
    vib = first.get("vibration", {}).get("accel")
    spectra: list[float] = []      # when frames carried a new spectrum
    for n, f in enumerate(frames):
        assert n < 200, f"in 200 frames, saw only {sorted(seen)}"
        if f.get("samples", {}).get("lathe/spindle_rpm", [0])[0] > t0:
            seen["rpm"] = True
        if f.get("vibration", {}).get("accel"):
            # a frame carries the keys that changed: the envelope each time, the spectrum's
            # amplitudes when a new one was computed (at most every SPECTRUM_MIN_S)
            v = vib = merge_view(vib, f["vibration"]["accel"])
            assert v["rate_hz"] == SIM_RATE_HZ and len(unpacked(v["env_min"])) <= 400 and len(unpacked(v["spec_a"])) <= 400
            assert "env_min" in f["vibration"]["accel"]
            if "spec_a" in f["vibration"]["accel"]:
                spectra.append(f["t"])
            if len(spectra) >= 3:
                seen["vib"] = True
        if "status" in f:
            seen["status"] = True
        for e in f.get("events", []):
            if e["kind"] == "suppression_mode":
                seen["event"] = e
        if len(seen) == 4:
            break
    frames.close()
    assert seen["event"]["payload"]["to"] == "manual"
    # 10 frames a second, a new spectrum in at most 2 of them (a frame's t follows its view at once)
    assert min(b - a for a, b in zip(spectra, spectra[1:])) >= push.SPECTRUM_MIN_S - 0.02, spectra
    wait_until(lambda: live.status()["daemon"]["control"]["subscribers"] == 0, what="subscriber gone")


def test_a_subscriber_that_never_reads_is_dropped_and_the_loop_does_not_wait(live):
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    s.connect(str(live.socket))
    s.sendall(json.dumps({"cmd": "subscribe", "args": {"vibration": ["accel"], "samples": ["*/*"],
                                                       "rate_hz": 20}}).encode() + b"\n")
    # it never reads: the daemon gives it up within its bound (5 s for a write to drain)
    try:
        ctl = wait_until(lambda: (c := live.status()["daemon"]["control"])["dropped"] >= 1 and c, timeout=30,
                         interval=0.5, what="the silent subscriber dropped")
        assert ctl["subscribers"] == 0
        assert "read nothing for 5 s" in ctl["last_drop"]
        lag = live.status()["daemon"]["loop_lag_ms"]
        # a loop that waited on the silent client would lag by the 5 s drain bound; this
        # allows for the CPU contention of a shared test machine, not for waiting
        assert lag["p99"] is not None and lag["p99"] < 250, lag
    finally:
        s.close()
    # the daemon still serves subscribers after that
    frames = subscribe({"samples": ["lathe/*"]}, sock_path=live.socket)
    assert next(frames)["samples"]
    frames.close()


def test_lathectl_events_follow_and_watch(live):
    follow = subprocess.Popen([str(BIN / "lathectl"), "--socket", str(live.socket), "events", "--follow",
                               "--limit", "1", "--kind", "suppression_mode", "--json"],
                              stdout=subprocess.PIPE, text=True)
    watch = subprocess.Popen([str(BIN / "lathectl"), "--socket", str(live.socket), "watch", "lathe/spindle_rpm",
                              "--rate", "5"], stdout=subprocess.PIPE, text=True)
    try:
        wait_until(lambda: live.status()["daemon"]["control"]["subscribers"] == 2, what="two subscribers")
        live.ctl("suppress", "off")
        line = json.loads(follow.stdout.readline())
        if line["payload"]["to"] != "off":   # the one before, from the snapshot
            line = json.loads(follow.stdout.readline())
        assert line["kind"] == "suppression_mode" and line["payload"]["to"] == "off"
        out = watch.stdout.readline()
        assert "lathe/spindle_rpm" in out and "r/min" in out
    finally:
        for p in (follow, watch):
            p.terminate()
            p.wait(10)


def test_a_refused_subscription_raises_remote_error(live):
    with pytest.raises(RemoteError, match="no sensor named 'nope'"):
        next(subscribe({"vibration": ["nope"]}, sock_path=live.socket))


def test_subscribers_beyond_the_configured_cap_are_refused(tmp_path):
    d = InProcessDaemon(tmp_path, daemon="control_max_subscribers = 0")
    try:
        reply = d.handle(b'{"cmd": "subscribe", "args": {"states": true}}\n')
        assert reply == {"ok": False, "error": "subscribe: 0 subscribers already (the daemon's [daemon] "
                                               "control_max_subscribers); try again later"}
    finally:
        d.close()


def test_the_hub_keeps_one_view_per_sensor_however_many_blocks_pass(monkeypatch):
    """A cache keyed by the block count grew by an entry per block: the daemon's memory, forever."""
    import asyncio

    import numpy as np

    from lathed.bus import Block, Bus
    from lathed import push
    from lathed.push import PushHub
    monkeypatch.setattr(push, "VIEW_MIN_S", 0.0)   # every block makes a new view

    async def scenario():
        bus = Bus()
        hub = PushHub(bus, None, {"accel": "sensor"}, dict, {}, max_subscribers=4)
        sub = await hub.subscribe({"vibration": ["accel"]})
        views = []
        for i in range(300):
            bus.publish(Block("accel", "acceleration", 51200.0, i * 0.01, i * 512, np.ones(512)))
            await asyncio.sleep(0)
            views.append(hub.vibration_view("accel"))
        sizes = len(hub._cache) + len(getattr(hub, "_vib", {}))
        sub.close()
        await asyncio.sleep(0)   # the ring's reader ends before the loop does
        return views, sizes, hub

    views, sizes, hub = asyncio.run(scenario())
    assert sizes <= 2
    assert views[-1]["t_end"] == 299 * 0.01 + 512 / 51200.0   # the newest block's view, not a stale one
    assert hub.subscribers == set() and hub._rings == {}


def test_a_failing_store_is_said_once_and_its_recovery_too(monkeypatch):
    """The events poller runs 5 times a second: a failing store was logged at that rate."""
    import asyncio

    import structlog

    from lathed import push
    from lathed.bus import Bus
    from lathed.push import PushHub
    monkeypatch.setattr(push, "EVENT_POLL_S", 0.0)

    class FlakyStore:
        calls = 0
        events_stored = property(lambda self: self.calls)    # new events all the time

        def events(self, *args):
            self.calls += 1
            if self.calls <= 5:
                raise OSError("disk I/O error")
            return []

    async def scenario(store):
        hub = PushHub(Bus(), store, {}, dict, {}, max_subscribers=4)
        task = asyncio.create_task(hub._poll_events())
        while store.calls < 8:
            await asyncio.sleep(0)
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)

    with structlog.testing.capture_logs() as logs:
        asyncio.run(scenario(FlakyStore()))
    said = [(e["event"], e.get("failed_polls")) for e in logs if e["event"].startswith("push_events")]
    assert said == [("push_events_failed", None), ("push_events_recovered", 5)]


def test_a_frame_is_encoded_as_plain_json_whatever_its_views_share_with_the_last():
    """Views are encoded once and their unchanged values reused: the line must still be exactly
    what json makes of the frame, after a value changes, comes back, or a view goes to None."""
    import numpy as np

    from lathed.bus import Bus
    from lathed.control import _encode
    from lathed.display import Ring
    from lathed.push import PushHub
    hub = PushHub(Bus(), None, {}, dict, {}, max_subscribers=4)
    ring = Ring()
    rng = np.random.default_rng(5)
    eye = {"eye_phi1": [0.5, 1.5], "base_phi1": [1.0, 2.0]}
    frames = []
    for i in range(6):
        ring.add(rng.normal(size=3000), 51200.0, float(i))
        if i == 3:
            eye = {**eye, "base_phi1": [1.0, 2.5]}   # a new cut's baseline
        views = {"chatter": dict(eye, eye_phi1=[0.5 * i]), "suppress": None if i % 2 else {"lobes": [1, 2]}}
        frames.append({"samples": {"lathe/x_mm": [1.0 + i, 2.5, "mm"]}, "vibration": {"accel": ring.view()},
                       "views": views, "events": [{"id": i, "payload": {"a": np.float64(0.25)}}], "t": 10.0 + i})
    frames.append(frames[0])      # the very same objects again
    for f in frames:
        assert hub.encode_frame(f) == _encode({"push": f})


def test_the_events_poller_queries_the_store_only_after_an_event_is_committed(tmp_path, monkeypatch):
    """It queried the store (a hop to a thread and an SQL query) 5 times a second, events or not."""
    import asyncio

    from lathed import push
    from lathed.bus import Bus
    from lathed.push import PushHub
    from lathed.store import Store
    monkeypatch.setattr(push, "EVENT_POLL_S", 0.0)
    store = Store(tmp_path / "lathed.db")
    queries = []
    real_events = store.events
    monkeypatch.setattr(store, "events", lambda *a: queries.append(a) or real_events(*a))

    async def scenario():
        hub = PushHub(Bus(), store, {}, dict, {}, max_subscribers=4)
        sub = await hub.subscribe({"events": True, "events_limit": 0})
        await wait_until_async(lambda: len(queries) == 1)    # the first poll reads what came meanwhile
        for _ in range(200):
            await asyncio.sleep(0)
        idle = len(queries)
        await store.record("inspection", "lathe", {"ok": True})
        await wait_until_async(lambda: sub._events)
        sub.close()
        return idle, sub._events

    try:
        idle, got = asyncio.run(scenario())
    finally:
        store.close()
    assert idle == 1
    assert [(e["kind"], e["payload"]) for e in got] == [("inspection", {"ok": True})]


async def wait_until_async(cond, timeout: float = 10.0) -> None:
    import asyncio
    import time
    end = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < end, "timed out"
        await asyncio.sleep(0.001)


def test_a_burst_of_events_larger_than_a_batch_reaches_subscribers_whole_and_in_order(tmp_path, monkeypatch):
    """The poller asked for the newest batch after its cursor: a burst of more lost the older ones."""
    import asyncio

    from lathed import push
    from lathed.bus import Bus
    from lathed.push import PushHub
    from lathed.store import Store
    monkeypatch.setattr(push, "EVENT_POLL_S", 0.0)
    monkeypatch.setattr(push, "EVENT_BATCH", 5)
    monkeypatch.setattr(push, "EVENT_PAGES", 2)     # 23 events: three polls
    store = Store(tmp_path / "lathed.db")
    got = []

    async def scenario():
        hub = PushHub(Bus(), store, {}, dict, {}, max_subscribers=4)
        class Sub:
            events = True
            add_events = staticmethod(got.extend)
        hub.subscribers.add(Sub())
        for i in range(23):
            await store.record("burst", "test", {"i": i})
        task = asyncio.create_task(hub._poll_events())
        while len(got) < 23:
            await asyncio.sleep(0.01)
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    asyncio.run(asyncio.wait_for(scenario(), 20))
    store.close()
    assert [e["payload"]["i"] for e in got] == list(range(23))


@settings(max_examples=300, deadline=None)
@given(st.lists(st.one_of(st.none(), st.dictionaries(st.sampled_from("abcd"), st.one_of(
    st.integers(0, 3), st.lists(st.integers(0, 2), max_size=3), st.none()), max_size=4)), min_size=1, max_size=8))
def test_views_sent_as_changed_keys_merge_back_to_the_view(views):
    """A subscriber that merges each frame's part of a view has the view, whatever the
    sequence (keys appear, change, vanish, the view goes to None and back)."""
    def present(v):       # a key whose value is None is the same as a key not there
        return v if not isinstance(v, dict) else {k: x for k, x in v.items() if x is not None}
    have, last, first = None, None, True
    for v in views:
        changed, d = changed_keys(last, v)
        if changed or first:         # the first is always sent
            have = merge_view(have, d)
        last, first = v, False
        assert present(have) == present(v)
    # unchanged long values are not sent again
    big = {"spec_f": list(range(400)), "spec_a": [1.0] * 400}
    assert changed_keys(big, {"spec_f": list(range(400)), "spec_a": [2.0] * 400}) == (True, {"spec_a": [2.0] * 400})


def test_the_daemon_stops_cleanly_with_a_subscriber_connected(sim_daemon):
    """lathed-web and lathed-opcua stay subscribed while the daemon stops (systemctl stop, Ctrl-C
    on make run): the cancelled connection was logged as an "Exception in callback" traceback."""
    d = sim_daemon()
    frames = subscribe({"samples": ["lathe/*"], "rate_hz": 5}, sock_path=d.socket)
    next(frames)                                                   # the snapshot: subscribed
    wait_until(lambda: d.status()["daemon"]["control"]["subscribers"] == 1, what="the subscription")
    assert d.stop() == 0
    out = d.cfg.with_suffix(".log").read_text(errors="replace")
    assert "Traceback" not in out and "Exception in callback" not in out, out[-3000:]
    frames.close()


def test_events_a_poll_hands_a_new_subscriber_during_its_snapshot_are_not_sent_twice(tmp_path, monkeypatch):
    """A second events subscriber was in the hub from before its snapshot query; a poll landing
    meanwhile handed it events that the snapshot carried too."""
    import asyncio
    import threading

    from lathed import push
    from lathed.bus import Bus
    from lathed.push import PushHub
    from lathed.store import Store
    monkeypatch.setattr(push, "EVENT_POLL_S", 0.0)
    store = Store(tmp_path / "lathed.db")
    polled = threading.Event()
    real_add = push.Subscription.add_events

    async def scenario():
        tock = asyncio.Event()

        def add_events(self, rows):
            real_add(self, rows)
            polled.set()
            if any(r["kind"] == "tock" for r in rows):
                tock.set()
        monkeypatch.setattr(push.Subscription, "add_events", add_events)
        hub = PushHub(Bus(), store, {}, dict, {}, max_subscribers=4)
        first = await hub.subscribe({"events": True, "events_limit": 0})       # the poller runs
        real_recent = hub._recent

        def recent(limit, sub):             # a busy line: events come while the snapshot is taken...
            for k in range(3):
                store.record_future("tick", "lathe", {"k": k}).result(10)
            assert polled.wait(10)          # ...and a poll hands them over before it returns
            return real_recent(limit, sub)
        hub._recent = recent
        sub = await hub.subscribe({"events": True, "events_limit": 100})
        await store.record("tock", "lathe", {})             # after the snapshot: the poller's
        await asyncio.wait_for(tock.wait(), 10)
        first.close()
        sub.close()
        return [e["id"] for e in sub.first["events"]], [e["id"] for e in sub.frame()["events"]]

    try:
        snapshot, pushed = asyncio.run(scenario())
    finally:
        store.close()
    assert snapshot == [1, 2, 3] and pushed == [4]
