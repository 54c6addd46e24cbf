"""Opt-in (`-p tests.cpu_profile`): CPU seconds each test costs, this process and its children
(children count once reaped), the 30 dearest printed at the end, and the total. Finds what to
cut when the suite is CPU-bound (2 cores, `make test`)."""
from __future__ import annotations

import os
import resource
import time

import pytest

_costs: dict[str, float] = {}
_start = {}


def _cpu() -> float:
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime


def pytest_sessionstart(session):
    _start["cpu"], _start["wall"] = _cpu(), time.monotonic()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    before = _cpu()
    yield
    _costs[item.nodeid] = _cpu() - before


def pytest_terminal_summary(terminalreporter):
    tr = terminalreporter
    total = _cpu() - _start.get("cpu", 0.0)
    tr.write_sep("-", f"CPU seconds (self + reaped children), pid {os.getpid()}")
    for nodeid, cpu in sorted(_costs.items(), key=lambda kv: -kv[1])[:30]:
        tr.write_line(f"{cpu:8.2f}  {nodeid}")
    tr.write_line(f"{sum(_costs.values()):8.2f}  in tests, {total:.2f} in the session "
                  f"(collection, imports, session fixtures), {time.monotonic() - _start.get('wall', 0):.0f} s wall")
