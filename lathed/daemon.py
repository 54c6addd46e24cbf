"""lathed: the daemon's entry point and lifecycle."""
from __future__ import annotations

import argparse
import asyncio
import logging
import os
import signal
import socket
import sqlite3
import sys
import threading
import time
from pathlib import Path
from typing import Any

import structlog

from lathed import __version__
from lathed import config as configmod
from lathed import instance
from lathed import log as logmod
from lathed.analyzer import Analyzer
from lathed.bus import Bus
from lathed.cli import EX_CANTCREAT
from lathed.client import SOCKET_NAME, default_runtime_dir, default_state_dir
from lathed.args import Args
from lathed.audit import AuditReserve, ReserveError
from lathed.control import AcceptErrorLog, ControlServer, SocketInUse, offload
from lathed.looplag import LagStats, watch
from lathed.memtrim import keep_trimmed
from lathed.push import PushHub
from lathed.recorder import Recorder
from lathed.plugins import PluginLoader, load_all
from lathed.sdnotify import notify, watchdog_interval
from lathed.store import MIGRATIONS, Store, connect
from lathed.supervisor import Plan, Supervisor, build, record_sinks

log = structlog.get_logger("lathed")
STOP_GRACE_S = 15.0   # below the unit's TimeoutStopSec
# sysexits: a configured simulator that did not start; a dead store writer; another daemon holds the lock
EX_UNAVAILABLE, EX_SOFTWARE, EX_TEMPFAIL = 69, 70, 75


class Settings:
    """The [daemon] table."""

    def __init__(self, cfg: configmod.Config):
        sec = cfg.daemon
        base = cfg.path.parent
        self.name = sec.getstr("name", socket.gethostname())
        self.state_dir = _path(base, sec.getstr("state_dir", ""), default_state_dir())
        self.runtime_dir = _path(base, sec.getstr("runtime_dir", ""), default_runtime_dir())
        self.plugin_dirs = [_path(base, d, None) for d in sec.getlist("plugin_dirs", [])]
        # a plugin still importing after this is reported as failed (one looping at import)
        self.plugin_import_timeout = sec.getduration("plugin_import_timeout", 30.0, minval=0.1, maxval=600.0)
        self.log_level = sec.getstr("log_level", "info", choices=("debug", "info", "warning", "error"))
        # The control socket: clients served at once (more are refused with a reply), how long an
        # idle connection is kept, and how long one request line may take to arrive.
        self.control_max_clients = sec.getint("control_max_clients", 64, minval=1, maxval=1024)
        self.control_idle_timeout = sec.getduration("control_idle_timeout", 60.0, minval=0.1, maxval=86400.0)
        self.control_request_timeout = sec.getduration("control_request_timeout", 5.0, minval=0.1, maxval=600.0)
        # groups whose members may change things over the socket; others read (empty: all may)
        self.control_operator_groups = sec.getlist("control_operator_groups", [])
        # `subscribe` connections (lathectl watch, lathed-web) at once, within control_max_clients
        self.control_max_subscribers = sec.getint("control_max_subscribers", 16, minval=0, maxval=1024)
        # a stop while an override lathed wrote holds mid-cut waits this long for the cut to end,
        # the cure held over the rest of the pass (0: released at once, under the chip)
        self.stop_wait = sec.getduration("stop_wait", 60.0, minval=0.0, maxval=600.0)
        sec.check_unused()
        st = cfg.store
        # 0: every record is kept. Otherwise records older than this are deleted,
        # but only once every configured sink has forwarded them.
        self.keep_days = st.getfloat("keep_days", 0.0, minval=0.0, maxval=36500.0)
        self.prune_every = st.getduration("prune_every", 3600.0, minval=1.0, maxval=7 * 86400.0)
        st.check_unused()

    @property
    def socket_path(self) -> Path:
        return self.runtime_dir / SOCKET_NAME


def _path(base: Path, text: str, default: Path | None) -> Path:
    if not text:
        return default
    p = Path(text)
    return p if p.is_absolute() else (base / p).resolve()


def prepare(path: str | Path, strict: bool) -> tuple[configmod.Config, Settings, PluginLoader, Plan, Any]:
    """Load and validate everything; raises ConfigError with every problem, one per line."""
    cfg = configmod.load(path)
    settings = Settings(cfg)
    configmod.substitute(cfg, "runtime_dir", str(settings.runtime_dir))
    loader = load_all(settings.plugin_dirs, settings.plugin_import_timeout)
    plan = build(cfg, loader, strict=strict)
    sim = None
    if cfg.simulator is not None:
        from lathed.sim.launch import SimulatorSettings
        try:
            sim = SimulatorSettings(cfg.simulator, settings.runtime_dir)
        except configmod.ConfigError as e:
            plan.errors.append(str(e))
    # root cause first: a plugin that failed to load explains the types it would have provided
    failed = [f"{cfg.path}: plugin {p.name} ({p.origin}) failed to load: {p.error}"
              for p in loader.plugins if p.error]
    # the daemon runs on without a broken plugin; --check-config (strict) says the config is not ok
    if plan.errors or (strict and failed):
        raise configmod.ConfigError("\n".join(failed + plan.errors))
    return cfg, settings, loader, plan, sim


class Daemon:
    def __init__(self, cfg, settings: Settings, loader: PluginLoader, plan: Plan, sim, store: Store,
                 reserve: AuditReserve | None = None):
        self.cfg, self.settings, self.loader, self.plan, self.sim_settings = cfg, settings, loader, plan, sim
        self.reserve = reserve
        self.started = time.monotonic()
        self.state = "starting"
        self.exit_code = 0
        self.bus = Bus()
        self.store = store
        store.declared_kinds = loader.event_kinds()     # known to --kind before the first is recorded
        self.control = ControlServer(settings.socket_path, settings.control_max_clients,
                                     settings.control_idle_timeout, settings.control_request_timeout,
                                     settings.control_operator_groups)
        self.supervisor: Supervisor | None = None
        self.sim_process = None
        self._stop = asyncio.Event()
        self.last_prune: dict | None = None
        self._step = "starting"
        self.loop_lag = LagStats()
        self._pruning: asyncio.Task | None = None
        self._reloads: list[asyncio.Task] = []
        self._reload_lock = asyncio.Lock()

    async def run(self) -> int:
        loop = asyncio.get_running_loop()
        loop.set_exception_handler(AcceptErrorLog())
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, self._stop.set)
        loop.add_signal_handler(signal.SIGHUP, lambda: self._reloads.append(asyncio.create_task(self.reload())))
        self.supervisor = Supervisor(self.cfg, self.plan, self.bus, self.store, self.control.register,
                                     self.reserve)
        for name in ("status", "plugins", "events", "ping"):
            self.control.register(name, getattr(self, f"_cmd_{name}"))
        names = {**{n: r.category for n, r in self.supervisor.runners.items()},
                 **{n: "analyzer" for n in self.supervisor.analyzer_runners}}
        # an analyzer that keeps the base's live_view has nothing to draw
        views = {n: r.obj.live_view for n, r in self.supervisor.analyzer_runners.items()
                 if type(r.obj).live_view is not Analyzer.live_view}
        runners = self.supervisor.runners

        def quantities(name: str) -> frozenset[str] | None:
            # a driver's, where its config fixes them
            return runners[name].obj.quantities() if name in runners else None
        self.push = PushHub(self.bus, self.store, names, self.status, views, self.settings.control_max_subscribers,
                            quantities)
        self.control.register("subscribe", self.push.subscribe)
        sup = self.supervisor
        self.recorder = Recorder(self.bus, lambda: {n: r.obj for n, r in sup.runners.items()},
                                 lambda: {n: r.obj for n, r in sup.analyzer_runners.items()}, sup.machine_status,
                                 self.settings.name)
        self.control.register("record", self.recorder.request)
        try:
            await self.control.start()
        except (SocketInUse, OSError) as e:
            print(f"lathed: {e}", file=sys.stderr)
            await asyncio.to_thread(self.store.close)
            return EX_TEMPFAIL if isinstance(e, SocketInUse) else EX_CANTCREAT
        # Analyzers first, and one loop turn for them to register their
        # control commands (parts, suppress, thermal...) before READY.
        self.supervisor.start_draining()
        self.supervisor.start_analyzers()
        await asyncio.sleep(0)
        # READY as soon as we serve; the drivers start once the simulator (an
        # outside peer, however local) listens, so they do not begin in retry.
        starting = asyncio.create_task(self._start_drivers())
        self.state = "running"
        # the machines this daemon runs, by kind: a plant view (lathectl plant) lists them from the central store
        machines = {n: drv.kind for n, (inst, drv) in self.plan.drivers.items()
                    if inst.category == "machine"}
        self.supervisor.record("daemon_started", "lathed", {"version": __version__, "pid": os.getpid(),
                                                            "machines": machines})
        log.info("ready", socket=str(self.settings.socket_path), version=__version__,
                 startup_s=round(time.monotonic() - self.started, 3))
        notify(f"READY=1\nSTATUS=running: {len(self.plan.drivers)} drivers, {len(self.plan.analyzers)} analyzers")
        watchdog = asyncio.create_task(self._watchdog())
        lag_watch = asyncio.create_task(watch(self.loop_lag))
        trimming = asyncio.create_task(keep_trimmed())
        self._pruning = asyncio.create_task(self._prune()) if self.settings.keep_days > 0 else None
        await self._stop.wait()
        for t in [self._pruning, *self._reloads]:
            if t is not None:
                t.cancel()
                await asyncio.gather(t, return_exceptions=True)
        self.state = "stopping"
        notify("STOPPING=1")
        log.info("stopping")
        await self._finish_cuts()
        # what the next shift inherits: an X offset is the machine's, kept (the spindle is
        # warm now), but nobody follows the spindle's cooling until lathed runs again
        left = self.supervisor.offsets_left()
        if left:
            log.warning("offsets_left", offsets_um=left, why="kept on the machine; they go stale as the spindle "
                        "cools (the next start phases them from there)")
        # A driver stuck in a blocking read in a worker thread must not keep
        # the process alive: acknowledged records are already committed, so
        # past the grace period we leave (systemd would SIGKILL us anyway).
        guard = threading.Timer(STOP_GRACE_S, self._stop_overdue)
        guard.daemon = True
        guard.start()
        try:
            watchdog.cancel()
            lag_watch.cancel()
            trimming.cancel()
            starting.cancel()
            await asyncio.gather(starting, return_exceptions=True)
            self._step = "stopping analyzers and drivers"
            await self.supervisor.stop()
            self._step = "closing the control socket"
            await self.control.close()
            self._step = "stopping the simulator"
            if self.sim_process is not None:
                from lathed.sim.launch import stop
                await stop(self.sim_process)
            self.supervisor.record("daemon_stopped", "lathed", {"offsets_left_um": left} if left else {})
            self._step = "closing the store"
            await asyncio.to_thread(self.store.close)
            self.supervisor.reserve.close()
        finally:   # stopped in time: the guard must not fire later in a process that lives on
            guard.cancel()
        return self.exit_code

    async def reload(self) -> dict:
        """SIGHUP: re-read the config; apply what may change live, or refuse it all, naming why."""
        from lathed import reload as reloadmod
        async with self._reload_lock:
            path = self.cfg.path
            try:
                cfg, settings, _, plan, _ = await asyncio.to_thread(prepare, path, True)
            except configmod.ConfigError as e:
                problems = str(e).splitlines()
            else:
                live = {n: set(an.LIVE_KEYS) for n, (_, an) in self.plan.analyzers.items()}
                ch = reloadmod.diff(self.cfg, cfg, live)
                problems = ch.refused
            if problems:
                log.error("config_reload_refused", config=str(path), problems=problems)
                self.supervisor.record("config_reload_refused", "lathed", {"config": str(path), "problems": problems})
                return {"applied": False, "problems": problems}
            if "log_level" in ch.daemon:
                self.settings.log_level = settings.log_level
                logmod.setup(settings.log_level)
            if "stop_wait" in ch.daemon:
                self.settings.stop_wait = settings.stop_wait
            if ch.store:
                self.settings.keep_days, self.settings.prune_every = settings.keep_days, settings.prune_every
                if self.settings.keep_days > 0 and (self._pruning is None or self._pruning.done()):
                    self._pruning = asyncio.create_task(self._prune())
            for m in ch.limits:        # the guard's next check uses them
                self.plan.limits[m] = self.supervisor.guard.limits[m] = plan.limits[m]
            for a in ch.analyzers:
                self.plan.analyzers[a][1].reconfigure(cfg.instance("analyzer", a).section)
            self.cfg = cfg
            changed = ch.summary()
            log.info("config_reloaded", config=str(path), changed=changed)
            self.supervisor.record("config_reloaded", "lathed", {"config": str(path), "changed": changed})
            return {"applied": True, "changed": changed}

    async def _prune(self) -> None:
        """Retention: delete records older than keep_days that every configured sink has forwarded."""
        while True:
            await asyncio.sleep(self.settings.prune_every)
            if self.settings.keep_days <= 0:      # retention switched off by a reload
                return
            # the configured sinks, not the running ones: a sink that failed to start or is
            # disabled would otherwise lose its unforwarded backlog (none running: all of it)
            sinks = record_sinks(self.cfg, self.loader)
            # by the store's clock: a wall clock set ahead must not age every record at once
            cutoff = self.store.clock.now() - self.settings.keep_days * 86400.0
            try:
                removed = await asyncio.to_thread(self.store.prune, cutoff, sinks)
            except Exception as e:      # the store says why; keep every record and try again later
                log.error("prune_failed", error=str(e))
                continue
            self.last_prune = {"t": time.time(), "older_than_t": cutoff, "removed": removed}
            if any(removed.values()):
                self.supervisor.record("store_pruned", "lathed", {"older_than_t": cutoff, "removed": removed,
                                                                  "sinks": sinks})

    async def _finish_cuts(self) -> None:
        """A stop while an override lathed wrote holds mid-cut (a chatter cure) waits, up to
        stop_wait, for the cut to end: the analyses and drivers run on, the cure holds over
        the rest of the pass, and the cut's end releases it as after any cut.  Released at
        once, the pass would run on at the speed that chattered.  A second SIGTERM or SIGINT,
        or the wait's end, stops at once (the override then released mid-cut)."""
        sup = self.supervisor
        held = sup.held()
        wait = self.settings.stop_wait
        if not held or wait <= 0:
            return
        self._stop.clear()
        t0 = time.monotonic()
        self._step = f"waiting up to {wait:g} s for the cut to end ({', '.join(held)} held)"
        log.warning("stop_waiting", held=held, up_to_s=wait,
                    why="an override lathed wrote holds mid-cut; the cut's end releases it (signal again to stop now)")
        # systemd's TimeoutStopSec counts from the stop: extended by the wait and the grace after it
        notify(f"STATUS=stopping: {self._step}\nEXTEND_TIMEOUT_USEC={int((wait + STOP_GRACE_S + 5.0) * 1e6)}")
        ended = f"not within {wait:g} s"
        while True:
            sup.sent.clear()
            if not sup.held():
                ended = "the cut ended"
                break
            if self._stop.is_set():
                ended = "a second stop signal"
                break
            left = t0 + wait - time.monotonic()
            if left <= 0:
                break
            # a release is a command sent; a link lost on the way is seen within the second
            waiters = [asyncio.ensure_future(self._stop.wait()), asyncio.ensure_future(sup.sent.wait())]
            await asyncio.wait(waiters, timeout=min(left, 1.0), return_when=asyncio.FIRST_COMPLETED)
            for w in waiters:
                w.cancel()
        waited = round(time.monotonic() - t0, 3)
        log.info("stop_waited", held=held, waited_s=waited, ended=ended)
        sup.record("stop_waited", "lathed", {"held": held, "waited_s": waited, "ended": ended})

    def _stop_overdue(self) -> None:
        # what was still running, so the next hang names its culprit
        busy = [name for group in (self.supervisor.analyzer_runners, self.supervisor.runners)
                for name, r in group.items() if r.task is not None and not r.task.done()]
        threads = [t.name for t in threading.enumerate() if t is not threading.current_thread() and t.is_alive()]
        log.error("stop_overdue", grace_s=STOP_GRACE_S, why="a driver or worker thread did not stop; exiting",
                  step=self._step, runners_not_stopped=busy, threads=threads)
        logging.shutdown()
        os._exit(1)

    async def _start_drivers(self) -> None:
        if self.sim_settings is not None:
            from lathed.sim.launch import SimulatorFailed, spawn
            try:
                self.sim_process = await spawn(self.sim_settings)
            except SimulatorFailed as e:
                # the drivers would reach whatever answers at its addresses instead: stop, saying why
                self.sim_process = e.process
                log.critical("simulator_failed", why=str(e))
                print(f"lathed: {self.cfg.path}: [simulator] {e}", file=sys.stderr, flush=True)
                self.supervisor.record("simulator_failed", "lathed", {"why": str(e)})
                self.exit_code = EX_UNAVAILABLE
                self._stop.set()
                return
        self.supervisor.start_drivers()

    async def _watchdog(self) -> None:
        # Pinged from the event loop itself: if the loop hangs, the pings stop
        # and systemd restarts us.
        interval = watchdog_interval()
        last = None
        while True:
            await asyncio.sleep(interval or 5.0)
            if not self.store.writer_alive:
                # cannot happen short of a bug; then fail loudly, and the
                # restart (Restart=on-failure) brings a working writer back
                log.critical("store_writer_dead", error=self.store.writer_error,
                             why="records can no longer be written; stopping with an error")
                notify(f"STATUS=failed: store writer stopped ({self.store.writer_error})")
                self.exit_code = EX_SOFTWARE
                self._stop.set()
                return
            if interval:
                notify("WATCHDOG=1")
            runners = self.supervisor.runners.values()
            text = f"STATUS={self.status_state()}: {sum(r.state == 'connected' for r in runners)}/{len(runners)} " \
                   "drivers connected"
            if self.store.failing:
                text += f"; store: {self.store.last_error}"
            if text != last:
                notify(text)
                last = text

    # -- control commands -------------------------------------------------------
    async def _cmd_ping(self, args: dict) -> Any:
        Args("ping", args).check_unused()
        return "pong"

    def status_state(self) -> str:
        if self.state == "running" and self.store.stats()["failing"]:
            return "degraded: store failing"
        return f"stopping: {self._step}" if self.state == "stopping" else self.state

    async def _cmd_status(self, args: dict) -> Any:
        Args("status", args).check_unused()
        return self.status()

    def status(self) -> dict:
        return {"daemon": {"state": self.status_state(), "uptime_s": round(time.monotonic() - self.started, 3),
                           "version": __version__, "pid": os.getpid(), "name": self.settings.name,
                           "loop_lag_ms": self.loop_lag.summary(), "bus": self.bus.stats(),
                           "config": str(self.cfg.path), "store": {**self.store.stats(), "keep_days": self.settings.keep_days,
                                                                "last_prune": self.last_prune,
                                                                "audit_reserve": self.supervisor.reserve.stats()},
                           "simulator": None if self.sim_process is None else
                           {"pid": self.sim_process.pid, "returncode": self.sim_process.returncode},
                           "control": {"clients": self.control.clients, "max_clients": self.control.max_clients,
                                       "refused": self.control.refused, "evicted": self.control.evicted,
                                       **self.push.stats()},
                           "recordings": self.recorder.stats()},
                **self.supervisor.status()}

    async def _cmd_plugins(self, args: dict) -> Any:
        Args("plugins", args).check_unused()
        return self.loader.summary()

    async def _cmd_events(self, args: dict) -> Any:
        a = Args("events", args)
        limit = a.getint("limit", 50, minval=1, maxval=100_000)
        kind, source = a.getstr("kind", None), a.getstr("source", None)
        since_id = a.getint("since_id", 0)
        a.check_unused()
        if kind is not None and (why := await offload(self.store.unknown_kind, [kind])):
            raise a.error("kind", why)
        await self.store.settled()      # the events of a command answered just before are there
        return await offload(self.store.events, limit, kind, source, since_id)


def open_store(db: Path, name: str) -> Store:
    """The record store, upgraded to this version's schema.  An upgrade rewrites tables
    (the outbox's ages: seconds per ten million records), so systemd is told it may take
    an hour: killed at the start timeout, each try would roll back and start again."""
    latest = MIGRATIONS[-1][0]
    if db.is_file():
        con = connect(db, readonly=True)
        try:
            version = con.execute("PRAGMA user_version").fetchone()[0]
        finally:
            con.close()
        if version < latest:
            log.info("store_upgrading", store=str(db), schema_from=version, schema_to=latest)
            notify(f"STATUS=upgrading the record store {db} from schema {version} to {latest}\n"
                   f"EXTEND_TIMEOUT_USEC={int(3600e6)}")
    return Store(db, machine_id=name)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="lathed", description="Monitoring and control daemon for CNC lathes.")
    p.add_argument("--config", "-c", default=os.environ.get("LATHED_CONFIG", "/etc/lathed/lathed.toml"),
                   help="config file (default: $LATHED_CONFIG or /etc/lathed/lathed.toml)")
    p.add_argument("--check-config", metavar="FILE", help="validate FILE and exit 0, or 78 with the problems")
    p.add_argument("--version", action="version", version=f"lathed {__version__}")
    args = p.parse_args(argv)

    # state files 0640 in 0750 directories also outside systemd (whose UMask
    # may be looser); only ever tightened. The socket sets its own 0660.
    os.umask(os.umask(0) | 0o027)
    logmod.setup("info")
    path = args.check_config or args.config
    try:
        cfg, settings, loader, plan, sim = prepare(path, strict=bool(args.check_config))
    except configmod.ConfigError as e:
        for line in str(e).splitlines():
            print(f"lathed: {line}", file=sys.stderr)
        return configmod.EX_CONFIG
    dirs = {"state_dir": settings.state_dir, "runtime_dir": settings.runtime_dir}
    problems = [p for what, d in dirs.items() if (p := instance.dir_problem(d, what, create=not args.check_config))]
    if problems:
        for line in problems:
            print(f"lathed: {path}: [daemon] {line}", file=sys.stderr)
        return EX_CANTCREAT
    if args.check_config:
        print(f"{path}: ok ({len(plan.drivers)} drivers, {len(plan.analyzers)} analyzers)")
        return 0
    logmod.setup(settings.log_level)
    for pl in loader.plugins:
        if pl.error:
            log.error("plugin_failed", plugin=pl.name, origin=pl.origin, error=pl.error)
    for key, (_, reason) in plan.skipped.items():
        log.error("instance_skipped", instance=key, reason=reason)
    try:   # before anything is written: one daemon per store and per socket
        locks = [instance.take_lock(d) for d in dict.fromkeys(p.resolve() for p in dirs.values())]
    except instance.Locked as e:
        print(f"lathed: {e}", file=sys.stderr)
        return EX_TEMPFAIL
    except OSError as e:
        print(f"lathed: cannot take the instance lock: {e.strerror or e} ({e.filename})", file=sys.stderr)
        return EX_CANTCREAT
    db = settings.state_dir / "lathed.db"
    try:
        store = open_store(db, settings.name)
    except (OSError, sqlite3.Error) as e:
        print(f"lathed: cannot open the record store {db}: {e}", file=sys.stderr)
        return EX_CANTCREAT
    try:
        reserve = AuditReserve(settings.state_dir / "audit-reserve")
    except ReserveError as e:
        print(f"lathed: {e}", file=sys.stderr)
        store.close()
        return EX_CANTCREAT
    try:
        return asyncio.run(Daemon(cfg, settings, loader, plan, sim, store, reserve).run())
    finally:
        for fd in locks:
            os.close(fd)


if __name__ == "__main__":
    sys.exit(main())
