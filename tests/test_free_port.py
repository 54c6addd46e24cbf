"""The suite's free_port(): a port is never handed out twice, and each xdist worker draws from
its own slice (a stack's web server was given its own simulator's Modbus port, and the stack
never came up)."""
from __future__ import annotations

from tests import conftest


def test_a_port_is_never_handed_out_twice_and_workers_draw_apart(monkeypatch):
    monkeypatch.setattr(conftest, "_HANDED_OUT", set())
    drawn = {}
    for worker in ("gw0", "gw5"):
        monkeypatch.setenv("PYTEST_XDIST_WORKER", worker)
        monkeypatch.setenv("PYTEST_XDIST_WORKER_COUNT", "6")
        drawn[worker] = [conftest.free_port() for _ in range(300)]
        assert len(set(drawn[worker])) == 300
    assert max(drawn["gw0"]) < min(drawn["gw5"])
