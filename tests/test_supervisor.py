"""Stopping: a task whose cancellation is swallowed once (as Python 3.11's
asyncio.wait_for does when the cancel lands as its inner await completes)
is cancelled again, so the daemon stops instead of waiting on a driver that
polls on."""
from __future__ import annotations

import asyncio

from lathed.supervisor import cancel_and_wait


def test_a_swallowed_cancellation_is_repeated():
    async def main():
        polls = 0
        swallowed = 0

        async def driver():
            nonlocal polls, swallowed
            while True:
                try:
                    await asyncio.sleep(0.01)
                except asyncio.CancelledError:
                    if swallowed == 0:      # what wait_for does to the first cancel
                        swallowed += 1
                        continue
                    raise
                polls += 1

        async def well_behaved():
            await asyncio.sleep(3600)

        tasks = [asyncio.create_task(driver()), asyncio.create_task(well_behaved())]
        await asyncio.sleep(0.05)
        await asyncio.wait_for(cancel_and_wait(tasks, every_s=0.2), 5.0)
        assert all(t.cancelled() for t in tasks) and swallowed == 1
        # a plain cancel-and-gather would still be waiting here
        return polls
    assert asyncio.run(main()) > 0


def test_a_command_to_a_machine_not_there_is_refused_not_raised():
    # the interlock was asked only for a connected machine, then read for every refusal
    from lathed.bus import Bus
    from lathed.command import Command
    from lathed.supervisor import Plan, Supervisor
    from tests.test_plausible import FakeStore
    store = FakeStore()
    sup = Supervisor(None, Plan(drivers={}, limits={}), Bus(), store, lambda *a: None)
    r = asyncio.run(sup.command(Command("nosuch", "spindle_rpm", 1000.0, "t")))
    assert r == {"sent": False, "reason": "no machine named 'nosuch'"}
    assert [k for k, _, _ in store.records] == ["command_refused"]
