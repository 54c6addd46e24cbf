"""Test-only drop-in analyzer that writes records (copied into a temp plugin_dirs).

    [analyzer.writer]
    plugin = "test_writer"
    total = 600          # stop after this many "tick" records in the store (across restarts)
    every = "5ms"        # pause between records; 0 = as fast as possible
    concurrency = 1      # writers in flight at once
    ack_file = ""        # append "id seq" for every acknowledged record

Each record is acknowledged only when the store has durably committed it,
so what reaches ``ack_file`` must survive a SIGKILL.
"""
import asyncio
import itertools
import os

from lathed import hookimpl
from lathed.analyzer import Analyzer


class Writer(Analyzer):
    def __init__(self, name, section):
        super().__init__(name, section)
        self.total = section.getint("total", 1_000_000_000, minval=1)
        self.every = section.getduration("every", 0.005, minval=0)
        self.concurrency = section.getint("concurrency", 1, minval=1, maxval=1000)
        self.ack_file = section.getstr("ack_file", "")
        self.done = False

    async def run(self):
        store = self.ctx.store
        have = (await asyncio.to_thread(store.query, "SELECT count(*) AS n FROM events WHERE kind = 'tick'"))[0]["n"]
        seq = itertools.count(have)
        fd = os.open(self.ack_file, os.O_WRONLY | os.O_APPEND | os.O_CREAT) if self.ack_file else None

        async def one():
            while True:
                n = next(seq)
                if n >= self.total:
                    return
                rid = await store.record("tick", self.name, {"seq": n})
                if fd is not None:
                    os.write(fd, f"{rid} {n}\n".encode())
                if self.every:
                    await asyncio.sleep(self.every)

        await asyncio.gather(*(one() for _ in range(self.concurrency)))
        self.done = True
        await asyncio.Event().wait()   # finished: idle until stopped

    def status(self):
        return {"done": self.done, "summary": "done" if self.done else "writing"}


@hookimpl
def lathed_analyzer_types():
    return {"test_writer": Writer}
