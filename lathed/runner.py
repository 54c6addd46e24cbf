"""A supervised task for one driver or analyzer: started, run, retried with capped
backoff and jitter; for a machine, its peer's identity confirmed at every connect.

Faults are recorded once per spell, not once per try (a switched-off machine is
retried every few seconds all day): one ``<category>_fault`` when it goes down, a
summary with the count of further failures every FAULT_SUMMARY_S while it stays
down, and one ``<category>_recovered`` with the count once it has run a while
again (a start that fails within the while does not end the spell).
"""
from __future__ import annotations

import asyncio
import random
import time
from collections import Counter
from typing import Any

import structlog

from lathed import identity
from lathed.driver import Driver
from lathed.plugins import _one_line

FAULT_SUMMARY_S = 600.0     # while down, the further failures are recorded together this often
SETTLED_S = 10.0            # running this long (at most retry_max) ends a spell of failures

log = structlog.get_logger("lathed.supervisor")


class Runner:
    """A supervised task for one driver or analyzer."""

    def __init__(self, category: str, name: str, obj: Any, retry_initial: float, retry_max: float,
                 record, summary_every: float = FAULT_SUMMARY_S):
        self.category, self.name, self.obj = category, name, obj
        self.retry_initial, self.retry_max = retry_initial, retry_max
        self.state = "starting"
        self.last_error: str | None = None
        self.retry_at: float | None = None
        self.connected_since: float | None = None
        self.failures = 0
        self.task: asyncio.Task | None = None
        # a machine: None once its peer is confirmed to be the configured machine, else why not
        self.identity: str | None = "not connected"
        self._record = record
        self.summary_every = summary_every
        self.log = log.bind(**{category: name})
        self._down_since: float | None = None     # monotonic time of the spell's first failure
        self._spell = 0                           # failures in this spell
        self._said_t = 0.0                        # when the spell was last recorded
        self._unsaid: Counter = Counter()         # errors since then
        self._up_t = 0.0                          # when it last started
        self._identity_said: str | None = None

    def describe(self) -> str:
        if self.state == "retrying" and self.retry_at is not None:
            return f"retrying in {max(0.0, self.retry_at - time.monotonic()):.1f} s ({self.last_error})"
        if self.state == "failed":
            return f"failed: {self.last_error}"
        return self.state

    async def _start(self) -> None:
        if isinstance(self.obj, Driver):
            await self.obj.connect()
            if self.obj.role == "machine":
                why = identity.judge(self.name, self.obj.identification, await self.obj.identify())
                if why is not None and self.obj.actions and why != self._identity_said:
                    self.log.warning("machine_identity_unconfirmed", why=why, effect="no command is sent to it")
                self._identity_said = why
                self.identity = why

    async def _close(self) -> None:
        if isinstance(self.obj, Driver):
            try:
                await asyncio.wait_for(self.obj.close(), 5.0)
            except Exception as e:   # close must not take the supervisor down
                self.log.warning("close_failed", error=_one_line(e))
            if self.obj.ctx is not None:
                self.obj.ctx.bus.link_lost()

    async def loop(self) -> None:
        delay = self.retry_initial
        loop = asyncio.get_running_loop()
        while True:
            started = time.monotonic()
            settled = None
            try:
                self.state = "connecting" if isinstance(self.obj, Driver) else "starting"
                await self._start()
                self.state = "connected" if isinstance(self.obj, Driver) else "running"
                self.connected_since = time.time()
                self._up_t = time.monotonic()
                settled = loop.call_later(min(self.retry_max, SETTLED_S), self._settled)
                await self.obj.run()
                raise RuntimeError("stopped without an error")
            except asyncio.CancelledError:
                if settled is not None:
                    settled.cancel()
                self.state = "stopped"
                self.identity = "not connected"
                await self._close()
                raise
            except Exception as e:
                if settled is not None:      # it did not run the while: the spell goes on
                    settled.cancel()
                self.failures += 1
                self.last_error = _one_line(e)
                self.connected_since = None
                self.identity = "not connected"
                await self._close()      # safe state: link released, commands refused
                if time.monotonic() - started > self.retry_max:
                    delay = self.retry_initial   # it ran a while: not a tight failure loop
                wait = min(delay, self.retry_max) * random.uniform(0.8, 1.2)
                self.retry_at = time.monotonic() + wait
                self.state = "retrying"
                self._failed(self.last_error, wait)
                await asyncio.sleep(wait)
                delay = min(delay * 2, self.retry_max)

    def _failed(self, error: str, wait: float) -> None:
        """A failure: recorded if it starts a spell or a summary is due, else counted."""
        now = time.monotonic()
        kind = f"{self.category}_fault"
        if self._down_since is None:
            self._down_since, self._spell, self._said_t = now, 1, now
            self.log.warning(kind, error=error, retry_in_s=round(wait, 2))
            self._record(kind, self.name, {"error": error, "retry_in_s": round(wait, 2)})
            return
        self._spell += 1
        self._unsaid[error] += 1
        if now - self._said_t < self.summary_every:
            self.log.debug(kind, error=error, retry_in_s=round(wait, 2), failures=self._spell)
            return
        payload = {"error": error, "retry_in_s": round(wait, 2), "still_down": True,
                   "failures": sum(self._unsaid.values()), "failures_since_down": self._spell,
                   "down_s": round(now - self._down_since, 1), "errors": dict(self._unsaid.most_common(5))}
        self.log.warning(kind, **payload)
        self._record(kind, self.name, payload)
        self._said_t = now
        self._unsaid.clear()

    def _settled(self) -> None:
        """It has run a while since its last start: a spell of failures is over."""
        if self._down_since is None:
            return
        # up_at: when it started again (wall clock, as records are dated), set in the step that
        # lets commands through: none of them went out before it
        payload = {"after_failures": self._spell, "unrecorded": sum(self._unsaid.values()),
                   "down_s": round(self._up_t - self._down_since, 1), "up_at": self.connected_since}
        self.log.info("recovered", **payload)
        self._record(f"{self.category}_recovered", self.name, payload)
        self._down_since = None
        self._spell = 0
        self._unsaid.clear()
