"""Test-only drop-in analyzer that puts the record store in trouble, on command.

    [analyzer.faults]
    plugin = "test_store_fault"

Control commands: ``poison`` (a record SQLite cannot bind), ``disk_full``
(caps the database at its current size, through the writer: real SQLITE_FULL
from then on), ``disk_free``, ``write`` (N records, awaited), ``queue`` (N
records, not awaited) and ``kill_writer`` (the writer thread ends, as a bug
in it would end it).
"""
from lathed import hookimpl
from lathed.analyzer import Analyzer


class StoreFault(Analyzer):
    async def run(self):
        for cmd in ("poison", "disk_full", "disk_free", "write", "queue", "kill_writer"):
            self.ctx.register_control(cmd, getattr(self, f"_{cmd}"))
        await __import__("asyncio").Event().wait()

    async def _poison(self, args):
        try:
            await self.ctx.store.add("experiments", {"t": 1.0, "tool": "T", "material": "M", "levels": {"A": 1},
                                                     "settings": {}, "run": 10 ** 30})
        except Exception as e:
            return str(e)
        return "stored"

    async def _disk_full(self, args):
        store = self.ctx.store
        pages = store.query("PRAGMA page_count")[0]["page_count"]
        await __import__("asyncio").wrap_future(store.submit(f"PRAGMA max_page_count = {pages}", ()))
        # and the room left in those pages taken, as on a full disk: else a small record of the
        # daemon's own (a driver's recovery) still fits, and the store is no longer failing
        for pad in (4000, 1000, 200, 50, 0):
            while True:
                try:
                    await self.ctx.store.record("fill", self.name, {"pad": "x" * pad})
                except Exception:
                    break
        return pages

    async def _disk_free(self, args):
        await __import__("asyncio").wrap_future(self.ctx.store.submit("PRAGMA max_page_count = 1073741823", ()))
        return True

    async def _write(self, args):
        errors = []
        for k in range(args.get("n", 1)):
            try:
                await self.ctx.store.record("fill", self.name, {"k": k, "pad": "x" * args.get("pad", 0)})
            except Exception as e:
                errors.append(str(e))
        return errors

    async def _queue(self, args):
        for k in range(args.get("n", 1)):
            self.ctx.store.record_future("command_sent", self.name, {"k": k})
        return True

    async def _kill_writer(self, args):
        store = self.ctx.store

        def dying(batch):
            del store._commit            # the class's own again, for the drain at close
            raise SystemExit("injected writer death")
        store._commit = dying
        store.record_future("tick", self.name, {})
        return True


@hookimpl
def lathed_analyzer_types():
    return {"test_store_fault": StoreFault}
