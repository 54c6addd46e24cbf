"""The sample bus: each subscriber's bounded FIFO (a deque and a waiter, not an asyncio.Queue)."""
from __future__ import annotations

import asyncio

from lathed.bus import Bus, Sample


def s(i: int, source: str = "lathe") -> Sample:
    return Sample(source, "spindle_rpm", float(i), "r/min", float(i))


def test_messages_come_in_order_to_every_subscriber_of_their_source():
    async def main():
        bus = Bus()
        a, b, other = bus.subscribe("lathe"), bus.subscribe("lathe", "accel"), bus.subscribe("mill")
        async def take(sub, n):
            return [(await sub.get()).value for _ in range(n)]
        got = asyncio.create_task(take(a, 3))
        await asyncio.sleep(0)                  # a waits on an empty queue
        for i in range(3):
            bus.publish(s(i))
        bus.publish(s(9, "accel"))
        assert await got == [0.0, 1.0, 2.0]
        assert await take(b, 4) == [0.0, 1.0, 2.0, 9.0]
        assert other.dropped == 0 and not other._items
    asyncio.run(main())


def test_a_full_subscriber_counts_what_it_missed_and_keeps_the_oldest():
    async def main():
        bus = Bus()
        sub = bus.subscribe("lathe", maxsize=3)
        for i in range(5):
            bus.publish(s(i))
        assert sub.dropped == 2
        assert [(await sub.get()).value for _ in range(3)] == [0.0, 1.0, 2.0]
    asyncio.run(main())


def test_a_cancelled_get_takes_nothing_and_unsubscribed_gets_nothing():
    async def main():
        bus = Bus()
        sub = bus.subscribe("lathe")
        waiting = asyncio.create_task(sub.get())
        await asyncio.sleep(0)
        waiting.cancel()
        await asyncio.gather(waiting, return_exceptions=True)
        bus.publish(s(1))
        assert (await asyncio.wait_for(sub.get(), 1)).value == 1.0
        bus.unsubscribe(sub)
        bus.publish(s(2))
        assert not sub._items
    asyncio.run(main())


def test_a_tap_sees_its_sources_messages_in_publish_and_a_raising_tap_is_removed_and_counted():
    bus = Bus()
    seen, other = [], []
    calls = {"bad": 0}

    def bad(msg):
        calls["bad"] += 1
        raise ValueError("broken listener")
    bus.tap("lathe", bad)
    bus.tap("lathe", seen.append)
    bus.tap("mill", other.append)
    sub = bus.subscribe("lathe")
    for i in range(3):
        bus.publish(s(i))                       # the raising tap neither stops publishing nor the next tap
    assert [m.value for m in seen] == [0.0, 1.0, 2.0] and not other
    assert calls["bad"] == 1 and len(sub._items) == 3
    st = bus.stats()
    assert st["tap_failures"] == 1 and st["taps"] == 2
    assert "lathe" in st["last_tap_failure"] and "ValueError: broken listener" in st["last_tap_failure"]
    bus.untap("lathe", seen.append)
    bus.publish(s(3))
    assert len(seen) == 3 and bus.stats()["taps"] == 1


def test_what_a_full_subscriber_missed_is_in_stats_by_subscriber_and_logged_once():
    import structlog
    bus = Bus()
    sub = bus.subscribe("lathe", maxsize=2, name="records")
    bus.subscribe("lathe", name="chatter").put = lambda msg: None     # keeps up
    with structlog.testing.capture_logs() as logs:
        for i in range(5):
            bus.publish(s(i))
    assert bus.stats()["dropped"] == {"records": 3}
    assert [(e["event"], e["subscriber"]) for e in logs] == [("bus_subscriber_behind", "records")]
    bus.unsubscribe(sub)                       # the analyzer restarts: its count goes on
    bus.subscribe("lathe", maxsize=0, name="records")
    bus.publish(s(9))
    assert bus.stats()["dropped"] == {"records": 4}


def test_a_blocks_only_source_gives_its_blocks_and_not_its_samples():
    """The chatter analyzer takes its sensor's waveform, not the rms published beside each
    block: a queue's put and get fewer a block (bench/bench_channel_path.py)."""
    import numpy as np

    from lathed.bus import Block

    async def main():
        bus = Bus()
        sub = bus.subscribe("accel", "lathe", blocks_only=("accel",), name="chatter")
        every = bus.subscribe("accel")
        block = Block("accel", "acceleration", 51200.0, 0.0, 0, np.zeros(4))
        bus.publish(block)
        bus.publish(s(1, "accel"))               # the sensor's rms: not for it
        bus.publish(s(2))                        # the machine's samples: all of them
        got = [await sub.get() for _ in range(2)]
        assert got[0] is block and got[1].value == 2.0 and not sub._items
        assert len(every._items) == 2
        bus.unsubscribe(sub)
        bus.publish(block)
        assert not sub._items and bus.stats()["dropped"] == {}
    asyncio.run(main())


def test_get_all_waits_for_one_then_takes_every_waiting_message_in_order():
    async def main():
        bus = Bus()
        sub = bus.subscribe("lathe", "accel")
        got = asyncio.create_task(sub.get_all())
        await asyncio.sleep(0)                  # waiting on an empty queue
        assert not got.done()
        bus.publish(s(1))
        bus.publish(s(2, "accel"))
        bus.publish(s(3))
        assert [m.value for m in await got] == [1.0, 2.0, 3.0] and not sub._items
        waiting = asyncio.create_task(sub.get_all())   # a cancelled wait takes nothing
        await asyncio.sleep(0)
        waiting.cancel()
        await asyncio.gather(waiting, return_exceptions=True)
        bus.publish(s(4))
        assert [m.value for m in await asyncio.wait_for(sub.get_all(), 1)] == [4.0]
    asyncio.run(main())
