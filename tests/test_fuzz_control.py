"""Property-based fuzzing of the control socket's request handling (issue 17
item 9, issue 18): arbitrary byte lines and JSON requests with random
commands and arguments, against the real handler set of a daemon (store,
records, suppression, thermal) run in this process. Whatever arrives, the
reply is ``ok`` true or false with a one-line error, nothing raises, nothing
is logged at error level (bad input is the client's problem, not a daemon
fault), and ``ping`` still answers."""
from __future__ import annotations

import asyncio
import json

import pytest
import structlog
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from tests.inproc_daemon import InProcessDaemon

FUZZ = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
# the nested JSON requests: drawing one costs hypothesis tens of ms, handling it about 1 ms; 150 a run
# (1.5x hypothesis's default), fresh ones every run
FUZZ_JSON = settings(FUZZ, max_examples=150)

# every argument name some handler reads, so the fuzz reaches past the unknown-key check
ARG_NAMES = ["limit", "kind", "source", "since_id", "abnormal", "pending", "part", "ra_um", "diameter_error_um",
             "values", "by", "tool", "material", "levels", "settings", "run", "removal_rate", "part_uuid", "what",
             "action", "analyzer"]
# values near the edges that broke handlers: NaN, huge ints, bools for ints, surrogates, deep nests
SCALARS = (st.none() | st.booleans() | st.integers() | st.integers(min_value=10 ** 18, max_value=10 ** 400)
           | st.floats() | st.text(max_size=300) | st.sampled_from(["status", "auto", "off", "now", "refit",
                                                                    "touchoff", "events", "parts", "1", "\ud800"]))
JSONISH = st.recursive(SCALARS, lambda inner: st.lists(inner, max_size=5)
                       | st.dictionaries(st.text(max_size=10) | st.sampled_from(["A", "B"]), inner, max_size=5),
                       max_leaves=20)


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    d = InProcessDaemon(tmp_path_factory.mktemp("fuzz"))
    yield d
    d.close()


def check_reply(reply: dict) -> None:
    assert isinstance(reply, dict) and isinstance(reply.get("ok"), bool), reply
    if reply["ok"]:
        assert "result" in reply
        json.dumps(reply, default=str)        # what _reply sends: must encode
    else:
        err = reply["error"]
        assert isinstance(err, str) and err and "\n" not in err and len(err) < 1000, err
        assert "internal error" not in err, err


def handle(d: InProcessDaemon, line: bytes) -> dict:
    with structlog.testing.capture_logs() as logs:
        reply = d.handle(line)
    bad = [e for e in logs if e["log_level"] in ("error", "critical", "exception") or e.get("exc_info")]
    assert not bad, (line[:200], bad)
    check_reply(reply)
    assert d.handle(b'{"cmd": "ping"}\n') == {"ok": True, "result": "pong"}
    return reply


@FUZZ
@given(st.binary(max_size=2000))
@example(b"[" * 100_000)          # beyond the line limit of a socket, but _handle must answer it too
@example(b'{"cmd": "ping", "args": {"a": ' + b"[" * 990 + b"]" * 990 + b"}}")
def test_any_bytes_get_a_reply(daemon, data):
    handle(daemon, data + b"\n")


@FUZZ_JSON
@given(cmd=st.sampled_from(["events", "ping", "status", "plugins", "parts", "inspect", "experiment_add",
                            "experiments", "recommend", "export", "suppress", "thermal"]) | st.text(max_size=20),
       args=st.dictionaries(st.sampled_from(ARG_NAMES) | st.text(max_size=12), JSONISH, max_size=6)
       | JSONISH)
def test_any_request_to_any_command_gets_a_reply(daemon, cmd, args):
    line = json.dumps({"cmd": cmd, "args": args}).encode() + b"\n"
    handle(daemon, line)


@FUZZ_JSON
@given(st.sampled_from(["suppress", "thermal", "events", "export", "inspect", "experiment_add", "recommend"]),
       st.fixed_dictionaries({}, optional={k: JSONISH for k in ARG_NAMES}))
def test_known_arguments_with_any_values(daemon, cmd, args):
    # the arguments a handler reads, each with any value: type and range checks, not the unknown-key refusal
    handle(daemon, json.dumps({"cmd": cmd, "args": args}).encode() + b"\n")


@settings(max_examples=40, deadline=None)
@given(st.lists(st.binary(max_size=500).map(lambda b: b.replace(b"\n", b"")), min_size=1, max_size=10))
def test_a_connection_survives_any_lines(daemon, lines):
    """Over the real socket: one reply per line, in order, and the same connection still answers ping."""
    async def session():
        reader, writer = await asyncio.open_unix_connection(str(daemon.control.path))
        try:
            replies = []
            for line in lines + [b'{"cmd": "ping"}']:
                writer.write(line + b"\n")
                await writer.drain()
                replies.append(json.loads(await reader.readline()))
            return replies
        finally:
            writer.close()
    with structlog.testing.capture_logs() as logs:
        replies = daemon.run(session())
    assert not [e for e in logs if e["log_level"] in ("error", "critical")], logs
    for r in replies[:-1]:
        check_reply(r)
    assert replies[-1] == {"ok": True, "result": "pong"}
