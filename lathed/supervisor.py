"""The one place that wires sensors -> analyzers -> actuators.

``build()`` turns the config into driver and analyzer objects (constructors
validate, no I/O). ``Supervisor`` runs each in its own supervised task,
retries failures with capped backoff and jitter, and routes every command
through the safety guard to the machine's driver.
"""
from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field, replace
from typing import Any

import structlog

from lathed import caller
from lathed.analyzer import Analyzer, AnalyzerContext
from lathed.args import Args
from lathed.audit import MARGIN, AuditReserve
from lathed.bus import Bus
from lathed.command import Command, as_number, short_repr
from lathed.config import Config, ConfigError, Instance
from lathed.control import RequestError
from lathed.driver import Driver, DriverContext
from lathed.plugins import PluginLoader, _one_line
from lathed.runner import Runner
from lathed.safety import Limits, SafetyGuard
from lathed.store import dumps

__all__ = ["Plan", "Runner", "Supervisor", "build", "cancel_and_wait", "record_sinks"]

OWED_RELEASE_POLL_S = 0.1   # how often a release an interlock held back asks again (a register poll)
DRAIN_EVERY_S = 2.0         # how often records kept in the audit reserve are offered to the store again

log = structlog.get_logger("lathed.supervisor")


@dataclass
class Plan:
    """Everything built from a config, before anything runs."""
    drivers: dict[str, tuple[Instance, Driver]] = field(default_factory=dict)
    analyzers: dict[str, tuple[Instance, Analyzer]] = field(default_factory=dict)
    limits: dict[str, Limits] = field(default_factory=dict)
    skipped: dict[str, tuple[Instance, str]] = field(default_factory=dict)   # name -> reason
    errors: list[str] = field(default_factory=list)
    loader: PluginLoader | None = None


def build(cfg: Config, loader: PluginLoader, strict: bool) -> Plan:
    """Build every instance. Config errors are collected in ``plan.errors``.

    An instance whose plugin type is unknown while some plugin failed to load
    is skipped (``strict=False``, the running daemon) or an error
    (``strict=True``, ``--check-config``): the broken plugin may be the one
    that would have provided it.
    """
    plan = Plan(loader=loader)
    if not cfg.instances:
        plan.errors.append(f"{cfg.path}: nothing to run: no [machine.*], [sensor.*] or [analyzer.*] table")
        return plan
    drivers, analyzers = loader.driver_types(), loader.analyzer_types()
    failed = [p.name for p in loader.plugins if p.error]
    broken: set[str] = set()   # instances refused above: what refers to them is not a further error
    disabled: set[str] = set()
    for inst in cfg.instances:
        key = f"{inst.category}.{inst.name}"
        types = analyzers if inst.category == "analyzer" else drivers
        cls = types.get(inst.plugin)
        if cls is None:
            allowed = ", ".join(sorted(types)) or "none loaded"
            msg = f"{cfg.path}: [{key}] plugin: unknown {('analyzer' if inst.category == 'analyzer' else 'driver')} " \
                  f"type {inst.plugin!r}; allowed: {allowed}"
            if failed and not strict:
                plan.skipped[key] = (inst, f"plugin type {inst.plugin!r} not available "
                                           f"(failed plugins: {', '.join(failed)})")
            else:
                plan.errors.append(msg + (f" (failed plugins: {', '.join(failed)})" if failed else ""))
                broken.add(inst.name)
            continue
        try:
            if not inst.framework.getbool("enabled", True):
                disabled.add(inst.name)
                continue
            limits = None
            if inst.category != "machine" and "limits" in inst.framework:
                raise inst.framework.error("limits", "safety limits apply to machines only")
            if inst.category == "machine":
                limits = Limits.from_section(inst.framework.getsection("limits", required=False))
            cap = inst.framework.getduration("retry_max", 10.0, minval=0.01, maxval=3600)
            # the default at most the cap: a short retry_max alone is not an error
            first = inst.framework.getduration("retry_initial", min(0.5, cap), minval=0.01, maxval=60)
            if first > cap:     # the backoff caps every wait at retry_max: the first would be cut to it
                raise inst.framework.error("retry_initial", f"{first:g} s is above retry_max {cap:g} s, which "
                                                            "caps every wait; give retry_initial <= retry_max")
            obj = cls(inst.name, inst.section)
            inst.section.check_unused()
            if inst.category == "machine" and obj.role != "machine":
                raise inst.section.error("plugin", f"{inst.plugin!r} is a {obj.role} driver; "
                                                   "use it under [sensor.*]")
        except ConfigError as e:
            plan.errors.append(str(e))
            broken.add(inst.name)
            continue
        except KeyboardInterrupt:
            raise
        except BaseException as e:   # a plugin bug in a constructor (even sys.exit) is reported, not fatal
            if strict:
                plan.errors.append(f"{cfg.path}: [{key}]: plugin {inst.plugin!r} failed to start: {_one_line(e)}")
                broken.add(inst.name)
            else:
                plan.skipped[key] = (inst, f"failed to start: {_one_line(e)}")
            continue
        if inst.category == "analyzer":
            plan.analyzers[inst.name] = (inst, obj)
        else:
            if inst.name in plan.drivers:
                plan.errors.append(f"{cfg.path}: [{key}]: name {inst.name!r} is already used by another "
                                   "machine or sensor")
                continue
            plan.drivers[inst.name] = (inst, obj)
            if limits is not None:
                plan.limits[inst.name] = limits
    # wiring: analyzers may only read and command instances that exist
    # not built: nothing to say what they are
    skipped = {k.split(".", 1)[1] for k in plan.skipped} | disabled
    for name, (inst, an) in plan.analyzers.items():
        missing = set()
        for src in an.inputs():
            if src not in plan.drivers and src not in broken and f"machine.{src}" not in plan.skipped \
                    and f"sensor.{src}" not in plan.skipped:
                plan.errors.append(f"{cfg.path}: [analyzer.{name}]: input {src!r} is not a configured "
                                   f"machine or sensor; configured: {', '.join(plan.drivers) or 'none'}")
                missing.add(src)
        for m in an.machines():
            if m not in plan.limits and m not in broken and f"machine.{m}" not in plan.skipped:
                plan.errors.append(f"{cfg.path}: [analyzer.{name}]: machine {m!r} is not a configured machine")
                missing.add(m)
        # ... and be what the key needs (an accelerometer, a machine that takes the speed, an analyzer)
        for key, (ref, category, need) in an.refers().items():
            if ref not in missing and ref not in broken and ref not in skipped:
                problem = _reference_problem(plan, ref, category, need)
                if problem:
                    plan.errors.append(f"{cfg.path}: [analyzer.{name}] {key}: {problem}")
        # an offset phased in faster than the machine's guard passes is refused at every write
        pace = an.offset_pace()
        for m in an.machines() if pace is not None else ():
            lim, (per_write, per_s) = plan.limits.get(m), pace
            if lim is not None and per_write > lim.offset_step_max_um:
                plan.errors.append(f"{cfg.path}: [analyzer.{name}]: moves the offset up to {per_write:g} µm a write, "
                                   f"more than [machine.{m}.limits] offset_step_max_um {lim.offset_step_max_um:g}: "
                                   "every such write would be refused")
            elif lim is not None and per_s > lim.offset_rate_max_um_s:
                plan.errors.append(f"{cfg.path}: [analyzer.{name}]: moves the offset up to {per_s:g} µm/s, "
                                   f"more than [machine.{m}.limits] offset_rate_max_um_s "
                                   f"{lim.offset_rate_max_um_s:g}: such writes would be refused")
    # and a driver may listen only to instances that exist (a read_on trigger)
    for name, (inst, drv) in plan.drivers.items():
        for src, (table, key) in drv.listens().items():
            if src not in plan.analyzers and src not in plan.drivers and src not in broken \
                    and not any(k.endswith(f".{src}") for k in plan.skipped):
                plan.errors.append(f"{cfg.path}: [{inst.category}.{name}{table}] {key}: {src!r} is not a "
                                   f"configured analyzer, machine or sensor")
    return plan


def record_sinks(cfg: Config, loader: PluginLoader) -> list[str]:
    """Every configured analyzer that forwards records, running or not: one skipped at start
    (its constructor failed) or with enabled = false forwards later, and until it has, what
    it has not forwarded is kept. One whose plugin type did not load may be a sink: counted."""
    types = loader.analyzer_types()
    return [inst.name for inst in cfg.instances if inst.category == "analyzer"
            and (inst.plugin not in types or types[inst.plugin].forwards_records)]


def _reference_problem(plan: Plan, ref: str, category: str, need: str | None) -> str | None:
    """Why ``ref`` is not the ``category`` instance (with ``need``) an analyzer's key asks for."""
    if category == "analyzer":
        if ref in plan.analyzers:
            return None
        return f"{ref!r} is not a configured analyzer; configured: {', '.join(plan.analyzers) or 'none'}"
    drv = plan.drivers.get(ref)
    if drv is None:
        return f"{ref!r} is not a configured {category}; configured: {', '.join(plan.drivers) or 'none'}"
    drv = drv[1]
    if drv.role != category or (category == "sensor" and need and drv.kind not in (need, "sensor")):
        return f"{ref!r} is a {drv.role} of kind {drv.kind!r}, not a {category}" + \
            (f" of kind {need!r}" if category == "sensor" and need else "")
    if category == "machine" and need and need not in drv.actions:
        return f"{ref!r} does not take {need!r} (takes: {', '.join(drv.actions) or 'none'})"
    return None


async def cancel_and_wait(tasks, every_s: float = 1.0) -> None:
    """Cancel the tasks and wait for them, cancelling again every ``every_s``
    those still running: Python 3.11's asyncio.wait_for (in our code and in
    libraries) returns the result instead of raising when the cancellation
    lands as its inner await completes, and a polling driver then polls on."""
    pending = {t for t in tasks if not t.done()}
    rounds = 0
    while pending:
        for t in pending:
            t.cancel()
        _, pending = await asyncio.wait(pending, timeout=every_s)
        rounds += 1
        if pending:
            log.warning("cancel_repeated", tasks=sorted(t.get_name() for t in pending), round=rounds)


class Supervisor:
    def __init__(self, cfg: Config, plan: Plan, bus: Bus, store, register_control,
                 reserve: AuditReserve | None = None):
        self.cfg, self.plan, self.bus, self.store = cfg, plan, bus, store
        self.guard = SafetyGuard(plan.limits)
        # room for the record of every command sent, should the store refuse it
        self.reserve = reserve if reserve is not None else AuditReserve(None)
        self._draining: asyncio.Task | None = None
        self.runners: dict[str, Runner] = {}
        self.analyzer_runners: dict[str, Runner] = {}
        self._cmd_locks: dict[str, asyncio.Lock] = {}
        self.sent = asyncio.Event()      # set at every command sent (a stop waiting for a release)
        # releases a machine's interlock held back (a thread being cut): sent when it clears
        self._owed: dict[tuple[str, str], asyncio.Task] = {}
        self._register_control = register_control
        for name, (inst, drv) in plan.drivers.items():
            drv.ctx = DriverContext(bus, log.bind(driver=name), self._recorder(name),
                                    drv.plausible)
            self.runners[name] = Runner(inst.category, name, drv, *self._retry(inst), self.record)
        self._controls: dict[str, dict[str, Any]] = {}
        for name, (inst, an) in plan.analyzers.items():
            an.ctx = AnalyzerContext(bus, log.bind(analyzer=name), self._recorder(name), self.command,
                                     self._control_registrar(name), store, self.machine_status,
                                     cfg.path.parent, plugins=plan.loader, release=self.release,
                                     interlock=self.interlock)
            self.analyzer_runners[name] = Runner("analyzer", name, an, *self._retry(inst), self.record)

    def _control_registrar(self, analyzer: str):
        """Analyzers add control commands; two analyzers offering the same
        command (two lathes, two suppressors) are told apart by the
        request's ``analyzer`` argument. Registering again (after a restart)
        replaces the handler."""
        def register(cmd: str, handler) -> None:
            if cmd not in self._controls:
                self._controls[cmd] = {}
                self._register_control(cmd, lambda args, cmd=cmd: self._dispatch(cmd, args))
            self._controls[cmd][analyzer] = handler
        return register

    async def _dispatch(self, cmd: str, args: dict) -> Any:
        handlers = self._controls[cmd]
        target = Args(cmd, args).getstr("analyzer", None, maxlen=64)
        if target is None and len(handlers) == 1:
            target = next(iter(handlers))
        if target not in handlers:
            raise RequestError(f"{cmd}: name the analyzer (--analyzer); one of {', '.join(sorted(handlers))}")
        # the handler reads (and checks) its own arguments
        return await handlers[target]({k: v for k, v in args.items() if k != "analyzer"})

    @staticmethod
    def _retry(inst: Instance) -> tuple[float, float]:
        fw = inst.framework
        return fw.getduration("retry_initial", 0.5), fw.getduration("retry_max", 10.0)

    # -- records ------------------------------------------------------------
    def record(self, kind: str, source: str, payload: dict | None = None) -> None:
        """Record an event durably; a failure to record is logged, never silent. An event
        recorded while a control request is handled names its caller (``caller``: uid, user
        and pid from the kernel, beside any name the client gave, e.g. a web user)."""
        who = caller.current()
        if who is not None:
            payload = {**(payload or {}), "caller": who.audit()}
        try:
            fut = self.store.record_future(kind, source, payload)
        except Exception as e:
            log.error("record_failed", kind=kind, source=source, error=_one_line(e), payload=payload)
            return
        # the payload goes to the log: a refused audit (disk full) survives at least there
        fut.add_done_callback(lambda f: f.exception() and log.error(
            "record_failed", kind=kind, source=source, error=str(f.exception()), payload=payload))

    def _recorder(self, source: str):
        return lambda kind, payload=None: self.record(kind, source, payload)

    # -- running --------------------------------------------------------------
    def start_analyzers(self) -> None:
        for r in self.analyzer_runners.values():
            r.task = asyncio.create_task(r.loop(), name=f"analyzer:{r.name}")

    def start_drivers(self) -> None:
        for r in self.runners.values():
            r.task = asyncio.create_task(r.loop(), name=f"{r.category}:{r.name}")

    def start(self) -> None:
        self.start_analyzers()
        self.start_drivers()

    def start_draining(self) -> None:
        """Records the audit reserve keeps (this run's, or a run's that stopped first) go to
        the store as soon as it takes them."""
        self._draining = asyncio.create_task(self._drain(), name="audit-reserve")

    async def _drain(self) -> None:
        while True:
            # file reads and an fsync: off the loop, and only when something is kept
            n, records = (await asyncio.to_thread(self.reserve.kept)) if self.reserve.kept_bytes else (0, [])
            if records:
                stmts = [self.store.event_statement(r["kind"], r["source"], r["payload"], r["t"]) for r in records]
                try:
                    await asyncio.wrap_future(self.store.submit(stmts, ()))
                except Exception as e:      # still refused: kept, offered again
                    log.debug("audit_reserve_not_drained", kept=len(records), error=_one_line(e))
                else:
                    await asyncio.to_thread(self.reserve.drop, n)
                    log.info("audit_reserve_drained", records=len(records))
                    continue
            await asyncio.sleep(DRAIN_EVERY_S)

    async def stop(self) -> None:
        # analyzers first, so no command is asked for while drivers close; then what the
        # analyses left held on a machine beyond its cut (a spindle override) goes back
        await cancel_and_wait([r.task for r in self.analyzer_runners.values() if r.task])
        await self.release_held()
        await cancel_and_wait(list(self._owed.values()))
        left = self.held()
        if left:
            log.warning("override_left_held", held=left, why="its release was refused or failed (a thread being "
                        "cut holds every command); the control's heartbeat watchdog, where mapped, takes it back")
        await cancel_and_wait([r.task for r in self.runners.values() if r.task])
        if self._draining is not None:
            await cancel_and_wait([self._draining])

    def held(self) -> list[str]:
        """What the machines still hold from lathed's commands beyond their cut ("lathe
        spindle_rpm": an override the driver would release), connected machines only."""
        out = []
        for name, r in self.runners.items():
            if r.state == "connected":
                out += [f"{name} {a}" for a in r.obj.actions if r.obj.released(a) is not None]
        return out

    def offsets_left(self) -> dict[str, float]:
        """The offsets the connected machines hold (lathed's thermal compensation): they stay
        on the control when lathed stops, and go stale as the spindle cools."""
        out = {}
        for name, r in self.runners.items():
            if r.state == "connected" and "offset_x_um" in r.obj.actions:
                v = r.obj.current("offset_x_um")
                if v is not None:
                    out[name] = round(v, 2)     # a float32 register's -4.670000076 is -4.67 µm
        return out

    async def release_held(self) -> None:
        """Every action a machine still holds from lathed's commands back to its program's
        value, through the guard (``release``); a write that fails or hangs is logged and
        recorded by ``command``, and the stop goes on (the control's heartbeat watchdog,
        where mapped, takes the override back)."""
        for name, r in self.runners.items():
            for action in r.obj.actions:
                await self.release(name, action, "lathed", reason="released: the daemon is stopping")

    # -- commands -------------------------------------------------------------
    async def command(self, cmd: Command) -> dict:
        """Send a command through the safety guard. Never raises (short of the asker's own
        cancellation): whatever a plugin passes is refused and recorded with the cause."""
        try:
            return await self._command(cmd)
        except asyncio.CancelledError:
            raise
        except Exception as e:          # a bug here or in a driver's checks: refused, never sent
            why = f"command could not be checked: {_one_line(e)}"
            log.error("command_refused", command=short_repr(cmd), why=why)
            self.record("command_refused", str(getattr(cmd, "source", "?")), {"command": short_repr(cmd),
                                                                           "refused": why})
            return {"sent": False, "reason": why}

    async def _command(self, cmd: Command) -> dict:
        runner = self.runners.get(cmd.machine)
        drv = runner.obj if runner else None
        reason = _link_refusal(cmd, runner)
        value = as_number(cmd.value)
        if value is not None:           # the driver gets a float (not numpy's float32, not an int)
            cmd = replace(cmd, value=value)
        lock = self._cmd_locks.setdefault(cmd.machine, asyncio.Lock())
        interlock = release = None
        async with lock:
            if reason is None:
                # asked again in turn: behind a write that hung, the link may have dropped and be
                # coming back (the driver linked, its peer not yet identified)
                reason = _link_refusal(cmd, runner)
            if reason is None:
                interlock = _interlock(drv, cmd)
                program = drv.released(cmd.action)
                release = self.guard.is_release(cmd, program)
                reason = self.guard.check(cmd, drv.current(cmd.action), drv.runs_at(cmd), interlock, program)
            payload = _payload(cmd)
            if reason is None:
                # the record's room is claimed before the write: no command without its record
                need = len(dumps(payload)) + MARGIN
                if not self.reserve.claim(need):
                    reason = (f"no room to record it: the store is refusing records and the audit reserve "
                              f"({self.reserve.size} bytes) is full")
            if reason is not None:
                log.warning("command_refused", command=cmd.describe(), why=reason)
                self.record("command_refused", cmd.source, {**payload, "refused": reason})
                held_back = interlock is not None and reason == interlock
                if held_back and release:
                    self._owe_release(cmd)
                return {"sent": False, "reason": reason, **({"interlock": True} if held_back else {})}
            send = asyncio.ensure_future(self._send(cmd, drv, payload, need))
            try:
                return await asyncio.shield(send)
            except asyncio.CancelledError:
                # the asker was cancelled (a speed variation stopped at the cut's end, the
                # daemon stopping) with the write on its way: it may reach the machine, so it
                # is finished, paced and recorded all the same
                await asyncio.gather(send, return_exceptions=True)
                raise

    async def _send(self, cmd: Command, drv, payload: dict, need: int) -> dict:
        began, err = time.monotonic(), None
        try:
            detail = await asyncio.wait_for(drv.execute(cmd), 5.0)
        except Exception as e:
            detail, err = None, _one_line(e)
        # the record is dated when the machine answered; less this, when the write went out
        payload["write_ms"] = round(1000 * (time.monotonic() - began), 1)
        if err is not None:
            log.error("command_failed", command=cmd.describe(), error=err)
            # it may have reached the machine (an answer lost): audited as a command sent is
            self._audit("command_failed", cmd.source, {**payload, "error": err}, need)
            return {"sent": False, "reason": f"write failed: {err}"}
        self.guard.passed(cmd)
        detail = detail or {}
        # how the driver carried it (an override: its % and speed), never over the recorded fields
        payload.update({k: v for k, v in detail.items() if k not in payload})
        log.info("command_sent", command=cmd.describe(), **detail)
        self._audit("command_sent", cmd.source, payload, need)
        self.sent.set()
        return {"sent": True, "reason": None, **detail}

    def _audit(self, kind: str, source: str, payload: dict, need: int) -> None:
        """The record of a command that may have reached the machine: to the store, and if the
        store refuses it, into the audit reserve whose room ``need`` was claimed for it."""
        who = caller.current()
        if who is not None:
            payload = {**payload, "caller": who.audit()}
        t = time.time()
        line = self.reserve.line(kind, source, payload, t)
        try:
            fut = self.store.record_future(kind, source, payload, t)
        except Exception as e:
            log.error("record_failed", kind=kind, source=source, error=_one_line(e))
            self.reserve.settle(need, line)
            return
        fut.add_done_callback(lambda f: self.reserve.settle(
            need, line if f.cancelled() or f.exception() is not None else None))

    def interlock(self, machine: str, action: str) -> str | None:
        """Why ``machine`` would refuse ``action`` now by its own state (its driver's
        interlock), else None; the guard still checks every command."""
        runner = self.runners.get(machine)
        return None if runner is None else _interlock(runner.obj, Command(machine, action, 0.0, "lathed"))

    def _owe_release(self, cmd: Command) -> None:
        """A release the machine's interlock refused (a thread begun before it): held back,
        not dropped (the override would stay on for the parts after), and sent once the
        interlock clears; a stop waiting for the cut's end waits for it too."""
        key = (cmd.machine, cmd.action)
        if key in self._owed and not self._owed[key].done():
            return
        log.warning("release_deferred", machine=cmd.machine, action=cmd.action,
                    why="the machine's interlock holds every command; sent when it clears")
        self._owed[key] = asyncio.create_task(self._release_when_clear(cmd), name=f"release:{cmd.machine}")

    async def _release_when_clear(self, cmd: Command) -> None:
        while True:
            await asyncio.sleep(OWED_RELEASE_POLL_S)
            runner = self.runners.get(cmd.machine)
            if runner is not None and runner.state == "connected" and _interlock(runner.obj, cmd) is None:
                break
        del self._owed[(cmd.machine, cmd.action)]
        await self.release(cmd.machine, cmd.action, cmd.source, reason=cmd.reason)

    async def release(self, machine: str, action: str, source: str,
                      reason: str = "released: back to the programmed speed") -> dict | None:
        """``action`` back to what the machine's program sets, through the guard as any command:
        where the driver writes it as something that holds beyond the cut (a spindle override),
        the value that undoes it; None where there is nothing to undo."""
        runner = self.runners.get(machine)
        drv = runner.obj if runner else None
        if drv is None or action not in drv.actions or runner.state != "connected":
            return None
        value = drv.released(action)
        if value is None:
            return None
        return await self.command(Command(machine, action, float(value), source, reason=reason))

    # -- status ---------------------------------------------------------------
    def machine_status(self, name: str) -> dict | None:
        r = self.runners.get(name)
        if r is None:
            return None
        return {"state": r.state, "describe": r.describe(), "error": r.last_error if r.state != "connected" else None,
                **r.obj.status()}

    def status(self) -> dict[str, Any]:
        now = time.time()
        machines, sensors, analyzers = [], [], []
        for name, r in self.runners.items():
            drv: Driver = r.obj
            age = None if drv.last_data_t is None else round(now - drv.last_data_t, 3)
            base = {"name": name, "plugin": self.plan.drivers[name][0].plugin, "state": r.state,
                    "detail": r.describe(), "last_error": r.last_error, "failures": r.failures,
                    "age_s": age}
            extra = {**_safe(drv.ctx.bus.plausible.status), **_safe(drv.status)}
            if drv.role == "machine":
                machines.append({**base, "kind": drv.kind, "spindle_rpm": drv.current("spindle_rpm"),
                                 "identification": drv.identification,
                                 "identity": "confirmed" if r.identity is None else f"not confirmed: {r.identity}",
                                 "takes": list(drv.actions),
                                 **extra})
            else:
                last = {q: s.value for q, s in self.bus.latest_of(name).items()}
                sensors.append({**base, "kind": drv.kind, "last_value": last or None, **extra})
        for key, (inst, reason) in self.plan.skipped.items():
            entry = {"name": inst.name, "plugin": inst.plugin, "state": "failed",
                     "detail": f"failed: {reason}", "last_error": reason}
            if inst.category == "machine":
                machines.append({**entry, "kind": None, "spindle_rpm": None})
            elif inst.category == "sensor":
                sensors.append({**entry, "last_value": None, "age_s": None})
            else:
                analyzers.append(entry)
        for name, r in self.analyzer_runners.items():
            machine = r.obj.machine
            analyzers.append({"name": name, "plugin": self.plan.analyzers[name][0].plugin, "state": r.state,
                              "detail": r.describe(), "last_error": r.last_error,
                              "machine": machine if isinstance(machine, str) else None, **_safe(r.obj.status)})
        return {"machines": machines, "sensors": sensors, "analyzers": analyzers}


def _payload(cmd: Command) -> dict:
    """The record of a command: what was asked, of which machine, by whom; the asker's
    context under its own key, so that it can never stand for a recorded field."""
    value = as_number(cmd.value)
    payload = {"machine": cmd.machine, "action": cmd.action,
               "value": value if value is not None else short_repr(cmd.value),
               "reason": cmd.reason, "by": cmd.source}
    if cmd.context:
        try:
            dumps(cmd.context)
            payload["context"] = cmd.context
        except (TypeError, ValueError):     # not recordable as given: its text, so it is not lost
            payload["context"] = short_repr(cmd.context)
    return payload


def _link_refusal(cmd: Command, runner) -> str | None:
    """Why ``cmd`` cannot go to its machine as the link stands now (None: it may)."""
    drv = runner.obj if runner else None
    if drv is None or drv.role != "machine":
        return f"no machine named {cmd.machine!r}"
    if runner.state != "connected":
        return f"machine {cmd.machine} is {runner.describe()}: held in safe state"
    if cmd.action not in drv.actions:
        return f"machine {cmd.machine} does not take {cmd.action!r} (takes: {', '.join(drv.actions) or 'none'})"
    if runner.identity is not None:
        return (f"machine {cmd.machine}: the peer at its address is not confirmed to be this machine "
                f"({runner.identity}); no command is sent to it")
    return None


def _interlock(drv, cmd: Command) -> str | None:
    """The driver's interlock on ``cmd``; one that fails is a refusal: a machine whose driver
    cannot vouch for its state takes nothing."""
    try:
        return drv.interlock(cmd)
    except Exception as e:
        return f"machine {cmd.machine}'s interlock could not be read: {_one_line(e)}"


def _safe(fn) -> dict:
    try:
        return fn() or {}
    except Exception as e:   # a status bug must not break `lathectl status`
        return {"status_error": _one_line(e)}
