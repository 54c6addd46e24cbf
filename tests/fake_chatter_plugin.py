"""Test-only stand-in for the chatter analyzer (copied into a temp plugin_dirs):
publishes its bus contract, the index high while the lathe cuts deeper than `depth_mm`."""
import time

from lathed import hookimpl
from lathed.analyzer import Analyzer
from lathed.bus import Sample


class FakeChatter(Analyzer):
    def __init__(self, name, section):
        super().__init__(name, section)
        self.machine = section.getstr("machine", "lathe")
        self.depth = section.getfloat("depth_mm", 2.0)

    def inputs(self):
        return [self.machine]

    async def run(self):
        sub = self.ctx.bus.subscribe(self.machine)
        alarm = 0.0
        while True:
            m = await sub.get()
            if getattr(m, "quantity", None) != "depth_of_cut_mm":
                continue
            now = time.time()
            chatter = m.value >= self.depth
            pub = self.ctx.bus.publish
            pub(Sample(self.name, "chatter_threshold", 1.0, "", now))
            pub(Sample(self.name, "chatter_index", 3.0 if chatter else 0.2, "", now))
            pub(Sample(self.name, "chatter_index_judged", 3.0 if chatter else 0.2, "", now))
            pub(Sample(self.name, "chatter_frequency_hz", 312.0, "Hz", now))
            if chatter != bool(alarm):
                alarm = 1.0 if chatter else 0.0
                self.ctx.record("chatter_alarm" if chatter else "chatter_cleared",
                                {"machine": self.machine, "index": 3.0, "threshold": 1.0,
                                 "chatter_frequency_hz": 312.0, "rpm": None, "depth_mm": m.value,
                                 "tool": "T0101", "material": "C45"})
            pub(Sample(self.name, "chatter_alarm", alarm, "", now))


@hookimpl
def lathed_analyzer_types():
    return {"fake_chatter": FakeChatter}
