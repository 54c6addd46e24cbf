"""A real Daemon (store, supervisor, every analyzer's control commands) run
in this process on a private event loop, with no machine to reach: the
control server's request handling is exercised against the real handlers,
far cheaper than a daemon on the simulator."""
from __future__ import annotations

import asyncio
import threading
from pathlib import Path

from lathed import daemon as daemonmod
from lathed.store import Store

CONFIG = """
[daemon]
name = "test-control"
state_dir = "{tmp}/state"
runtime_dir = "{tmp}/run"
{daemon}

[machine.lathe]
plugin = "modbus_cnc"
kind = "lathe"
host = "127.0.0.1"
port = 9              # nothing listens: the driver retries, the analyzers serve commands
retry_initial = "10s"
retry_max = "10s"

[machine.lathe.registers]
{registers}
{identity}

[sensor.temps]
plugin = "ds18b20_serial"
port = "{tmp}/no-tty"
retry_initial = "10s"
retry_max = "10s"

[sensor.vib]
plugin = "vibration_tcp"
host = "127.0.0.1"
port = 9
retry_initial = "10s"
retry_max = "10s"

# the analyzer suppression and records read the alarms from (a name that is not one is refused);
# named so that no test's "accel*" or "chat*" pattern finds it
[analyzer.watch]
plugin = "chatter"
input = "vib"
machine = "lathe"

[analyzer.suppress]
plugin = "suppression"
chatter = "watch"
machine = "lathe"
mode = "manual"
strategy = "frequency"

[analyzer.thermal]
plugin = "thermal"
input = "temps"
machine = "lathe"

[analyzer.records]
plugin = "records"
machine = "lathe"
chatter = "watch"
thermal = "thermal"
tool = "T0101"
material = "C45"
"""


class InProcessDaemon:
    def __init__(self, tmp: Path, daemon: str = ""):
        from tests.conftest import IDENTITY, REGISTERS, without_dangling_read_on
        cfg = tmp / "lathed.toml"
        cfg.write_text(without_dangling_read_on(CONFIG.format(tmp=tmp, daemon=daemon, registers=REGISTERS,
                                                              identity=IDENTITY)))
        self.loop = asyncio.new_event_loop()
        cfg, settings, loader, plan, sim = daemonmod.prepare(cfg, strict=True)
        settings.state_dir.mkdir(parents=True, exist_ok=True)
        store = Store(settings.state_dir / "lathed.db", machine_id=settings.name)
        self.daemon = daemonmod.Daemon(cfg, settings, loader, plan, sim, store)
        self.control = self.daemon.control
        self.task = self.loop.create_task(self.daemon.run())
        self.run(self._ready())

    async def _ready(self) -> None:
        for _ in range(1000):
            if self.task.done():
                self.task.result()
            if self.daemon.state == "running" and {"parts", "suppress", "thermal"} <= set(self.control.handlers):
                return
            await asyncio.sleep(0.01)
        raise AssertionError(f"in-process daemon not serving; commands: {sorted(self.control.handlers)}")

    def run(self, coro, timeout: float = 30.0):
        return self.loop.run_until_complete(asyncio.wait_for(coro, timeout))

    def handle(self, line: bytes) -> dict:
        return self.run(self.control._handle(line))

    def close(self) -> None:
        self.daemon._stop.set()
        self.loop.run_until_complete(asyncio.wait_for(self.task, 30))
        self.loop.close()
        # a stop guard left armed would os._exit the test process 15 s later
        timers = [t for t in threading.enumerate() if isinstance(t, threading.Timer)]
        for t in timers:
            t.join(5.0)     # a cancelled guard ends at once; an armed one would wait 15 s
        timers = [t for t in timers if t.is_alive()]
        assert not timers, f"threads left behind by a clean stop: {timers}"
