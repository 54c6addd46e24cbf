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


def test_a_command_waiting_behind_a_hung_write_is_checked_again_in_its_turn():
    """Two cures in a row; the first write hangs as the control's server restarts. The second
    was checked (link up) before it queued for the machine's lock; by its turn the link had
    dropped and come back with the peer not yet identified. It was written all the same (seen
    as a command_sent inside a restart's down spell on a loaded fresh clone); now it is refused."""
    from lathed.bus import Bus
    from lathed.command import Command
    from lathed.config import Instance, Section
    from lathed.driver import Driver
    from lathed.safety import Limits
    from lathed.supervisor import Plan, Supervisor
    from tests.test_plausible import FakeStore

    class Lathe(Driver):
        role, kind, actions = "machine", "lathe", ("spindle_rpm",)

        def __init__(self):
            super().__init__("lathe", Section("t.toml", "machine.lathe", {}))
            self.hang, self.written = asyncio.Event(), []

        async def execute(self, cmd):
            self.written.append(cmd.value)
            if len(self.written) == 1:
                await self.hang.wait()

        def current(self, action):
            return 2000.0

    async def main():
        store, drv = FakeStore(), Lathe()
        inst = Instance("machine", "lathe", "lathe", Section("t.toml", "machine.lathe", {}),
                        Section("t.toml", "machine.lathe", {}))
        plan = Plan(drivers={"lathe": (inst, drv)}, limits={"lathe": Limits(rpm_min=100.0, rpm_max=6000.0)})
        sup = Supervisor(None, plan, Bus(), store, lambda *a: None)
        runner = sup.runners["lathe"]
        runner.state, runner.identity = "connected", None
        first = asyncio.create_task(sup.command(Command("lathe", "spindle_rpm", 2100.0, "cure", "suppress")))
        while not drv.written:
            await asyncio.sleep(0)
        second = asyncio.create_task(sup.command(Command("lathe", "spindle_rpm", 2200.0, "cure", "suppress")))
        for _ in range(5):                      # the second checked and queued behind the first
            await asyncio.sleep(0)
        runner.state, runner.identity = "connecting", "not connected"     # the link lost, coming back
        drv.hang.set()
        await first
        return await second, drv.written
    r, written = asyncio.run(main())
    assert r["sent"] is False and "held in safe state" in r["reason"], r
    assert written == [2100.0]
