"""Opt-in (`-p tests.cpu_profile`): CPU seconds each test costs, this process and its children
(children count once reaped), the 30 dearest printed at the end, with the total per file. Under
xdist each worker writes its figures to a file the controller sums. Finds what to cut when the
suite is CPU-bound (2 cores, `make test`)."""
from __future__ import annotations

import json
import os
import resource
import tempfile
import time
from pathlib import Path

import pytest

_costs: dict[str, float] = {}
_start = {}
# the controller names a folder before it starts its workers, which inherit the environment
if "LATHED_CPU_PROFILE_DIR" not in os.environ:
    os.environ["LATHED_CPU_PROFILE_DIR"] = tempfile.mkdtemp(prefix="lathed-cpu-profile-")
_DIR = Path(os.environ["LATHED_CPU_PROFILE_DIR"])


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


# before xdist's own hook tells the controller this worker is done
@pytest.hookimpl(tryfirst=True)
def pytest_sessionfinish(session):
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    if worker:
        (_DIR / f"{worker}.json").write_text(json.dumps(
            {"tests": _costs, "session": _cpu() - _start.get("cpu", 0.0)}))


def pytest_terminal_summary(terminalreporter):
    if os.environ.get("PYTEST_XDIST_WORKER"):   # workers have a summary too; the controller prints
        return
    tr = terminalreporter
    costs, session = dict(_costs), _cpu() - _start.get("cpu", 0.0)
    for f in sorted(_DIR.glob("*.json")):
        d = json.loads(f.read_text())
        costs.update(d["tests"])
        f.unlink()
    tr.write_sep("-", "CPU seconds (self + reaped children)")
    for nodeid, cpu in sorted(costs.items(), key=lambda kv: -kv[1])[:30]:
        tr.write_line(f"{cpu:8.2f}  {nodeid}")
    files: dict[str, float] = {}
    for nodeid, cpu in costs.items():
        files[nodeid.split("::")[0]] = files.get(nodeid.split("::")[0], 0.0) + cpu
    tr.write_sep("-", "CPU seconds per file")
    for name, cpu in sorted(files.items(), key=lambda kv: -kv[1]):
        tr.write_line(f"{cpu:8.2f}  {name}")
    tr.write_line(f"{sum(costs.values()):8.2f}  in tests, {session:.2f} in the sessions "
                  f"(collection, imports, session fixtures), {time.monotonic() - _start.get('wall', 0):.0f} s wall")
