"""The control socket under hostile requests and clients (issue 18 D3, D8, D9):
wrong argument types and sizes answered in one line before any work, and
connections bounded in number, time and line length."""
from __future__ import annotations

import asyncio
import errno
import json
import socket
import time

import pytest
import structlog

from lathed import client
from lathed.analysis import taguchi
from lathed.control import MAX_LINE, AcceptErrorLog, ControlServer
from tests.conftest import wait_until
from tests.inproc_daemon import InProcessDaemon


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    d = InProcessDaemon(tmp_path_factory.mktemp("control"))
    yield d
    d.close()


def ask(d: InProcessDaemon, req) -> tuple[dict, list[dict]]:
    line = req if isinstance(req, bytes) else json.dumps(req).encode() + b"\n"
    with structlog.testing.capture_logs() as logs:
        reply = d.handle(line)
    return reply, logs


def assert_refused(reply: dict, logs: list[dict], *wanted: str) -> None:
    assert reply["ok"] is False, reply
    err = reply["error"]
    assert "\n" not in err and len(err) < 400, err
    assert "internal error" not in err, err
    for w in wanted:
        assert w in err, err
    bad = [e for e in logs if e["log_level"] in ("error", "critical", "exception") or e.get("exc_info")]
    assert not bad, bad


def test_a_misspelt_event_kind_is_refused_naming_the_known_ones(daemon):
    # it listed no events, without a word
    reply, logs = ask(daemon, {"cmd": "events", "args": {"kind": "chatter_alram"}})
    assert reply["ok"] is False and reply["usage"] is True and "\n" not in reply["error"], reply
    assert reply["error"].startswith("events: kind: 'chatter_alram' is not a kind of event (did you mean "
                                     "'chatter_alarm'?); known: alarm_cleared, "), reply
    assert ask(daemon, {"cmd": "events", "args": {"kind": "chatter_alarm"}})[0]["ok"] is True


# -- D9: wrong argument types -------------------------------------------------------
@pytest.mark.parametrize("req, wanted", [
    ({"cmd": "events", "args": {"since_id": "abc"}}, ["events: since_id: expected an integer", "'abc'"]),
    ({"cmd": "events", "args": {"since_id": float("nan")}}, ["events: since_id", "nan"]),
    ({"cmd": "events", "args": {"since_id": 1e30}}, ["events: since_id", "1e+30"]),
    ({"cmd": "events", "args": {"since_id": 10 ** 30}}, ["events: since_id", "larger than any stored id"]),
    ({"cmd": "events", "args": {"kind": [1]}}, ["events: kind: expected a string, got list [1]"]),
    ({"cmd": "suppress", "args": {"analyzer": ["x"]}}, ["suppress: analyzer: expected a string"]),
    ({"cmd": "suppress", "args": {"action": "auto", "by": {"x": 1}}}, ["suppress: by: expected a string"]),
    ({"cmd": "thermal", "args": {"action": 3}}, ["thermal: action: expected a string"]),
    ({"cmd": "inspect", "args": {"part": "1", "ra_um": 10 ** 400}},
     ["inspect: ra_um: expected a finite number", "(401 characters)"]),
    ({"cmd": "inspect", "args": {"part": "1", "values": {"a": "x"}}}, ["inspect: values.a: expected a finite number"]),
    ({"cmd": "inspect", "args": {"part": "1", "ra_um": 1.0, "by": "\ud800"}}, ["inspect: by: not valid text"]),
    ({"cmd": "suppress", "args": {"action": "off", "by": "me\nERROR fake log line"}},
     ["suppress: by: not printable text"]),
    ({"cmd": "parts", "args": {"abnormal": "yes"}}, ["parts: abnormal: expected true or false"]),
    ({"cmd": "export", "args": {"what": "parts", "limit": 10 ** 7}}, ["export: limit", "in [1, 100000]"]),
    ({"cmd": "experiment_add", "args": {"levels": {"A": 1}, "ra_um": 1.0, "run": 10 ** 30}},
     ["experiment_add: run"]),
    ({"cmd": "experiment_add", "args": {"levels": {"A": 1}, "ra_um": 1.0, "tool": "x" * 10_000}},
     ["experiment_add: tool: 10000 characters; at most 256"]),
    ({"cmd": "recommend", "args": {"material": 7}}, ["recommend: material: expected a string"]),
])
def test_wrong_argument_types_get_one_line_errors(daemon, req, wanted):
    reply, logs = ask(daemon, req)
    assert_refused(reply, logs, *wanted)
    assert reply["usage"] is True       # lathectl exits 2 for it, as for its own argument errors


@pytest.mark.parametrize("usage, code", [(True, 2), (False, 1)])
def test_a_refusal_that_is_not_the_arguments_is_no_usage_error(daemon, monkeypatch, capsys, usage, code):
    reply, _ = ask(daemon, {"cmd": "inspect", "args": {"part": "999999", "ra_um": 1.0}})
    assert reply["ok"] is False and "usage" not in reply, reply
    # lathectl: 2 for an argument the daemon refused, 1 for what its state refuses
    from lathed.cli import records
    from lathed.client import RemoteError
    from lathed.cli.main import main

    def refuse(*a, **k):
        raise RemoteError("inspect: ra_um: expected a finite number" if usage else "no part 999999", usage)
    monkeypatch.setattr(records, "remote", refuse)
    assert main(["inspect", "999999", "--ra", "1"]) == code
    assert capsys.readouterr().err.startswith("lathectl: lathed refused: ")


def test_unknown_arguments_are_named_not_ignored(daemon):
    # a typo once fell back to the default silently (limitt: 50 events, not 3)
    assert_refused(*ask(daemon, {"cmd": "events", "args": {"limitt": 3, "kin": "x"}}),
                   "events: unknown arguments 'limitt', 'kin'; allowed: kind, limit, since_id, source")
    assert_refused(*ask(daemon, {"cmd": "ping", "args": {"x": 1}}), "ping: unknown argument 'x'; allowed: none")
    assert_refused(*ask(daemon, {"cmd": "suppress", "args": {"actoin": "off"}}), "suppress: unknown argument 'actoin'")
    assert_refused(*ask(daemon, {"cmd": "ping", "arg": {}}), "unknown key(s) 'arg'")


@pytest.mark.parametrize("line", [b"[" * 100_000 + b"\n", b'{"cmd": "events", "args": {"kind": '
                                  + b"[" * 900 + b"]" * 900 + b"}}\n", b"1" * 5000 + b"\n"])
def test_deep_or_huge_json_gets_a_reply(daemon, line):
    # 100k-deep: RecursionError out of _handle, no reply; 900-deep parsed, then repr() recursed;
    # a 5000-digit integer is a ValueError from json.loads
    assert_refused(*ask(daemon, line), "malformed request")


# -- D3: heavy work bounded ---------------------------------------------------------
def test_factor_levels_are_small_integers(daemon):
    # a level of 3e8 once made `recommend` run np.bincount over 3e8 bins on the loop (17.7 s)
    assert_refused(*ask(daemon, {"cmd": "experiment_add", "args": {"tool": "T9", "material": "M",
                                                                    "levels": {"A": 300_000_000}, "ra_um": 1.0}}),
                   f"experiment_add: levels.A: 300000000 is out of range [1, {taguchi.MAX_LEVEL}]")
    ok, _ = ask(daemon, {"cmd": "experiment_add", "args": {"tool": "T9", "material": "M", "levels": {"A": 2, "B": 1},
                                                           "settings": {"A": 2000, "B": "coated"}, "ra_um": 1.2}})
    assert ok == {"ok": True, "result": {"id": ok["result"]["id"]}}
    rec, _ = ask(daemon, {"cmd": "recommend", "args": {"tool": "T9", "material": "M"}})
    assert rec["ok"] and rec["result"]["objectives"]["surface"]["best"] == {"A": [2], "B": [1]}


# -- D8: bounded connections --------------------------------------------------------
class Server:
    """A ControlServer on a private loop in this thread, with ping registered."""

    def __init__(self, path, **kw):
        self.loop = asyncio.new_event_loop()
        self.srv = ControlServer(path, **kw)

        async def ping(args):
            return "pong"
        self.srv.register("ping", ping)
        self.loop.run_until_complete(self.srv.start())

    def spin(self, until, timeout: float = 10.0, what: str = "condition"):
        """Run the loop until ``until()`` holds (the server works only while its loop runs)."""
        async def poll():
            deadline = time.monotonic() + timeout
            while not until():
                assert time.monotonic() < deadline, f"timed out waiting for {what}"
                await asyncio.sleep(0.01)
        self.loop.run_until_complete(poll())

    def close(self):
        self.loop.run_until_complete(self.srv.close())
        self.loop.close()


@pytest.fixture
def server(tmp_path):
    made = []

    def make(**kw):
        made.append(Server(tmp_path / "c.sock", **kw))
        return made[-1]
    yield make
    for s in made:
        s.close()


def connect(srv: Server) -> socket.socket:
    s = socket.socket(socket.AF_UNIX)
    s.setblocking(False)
    s.connect(str(srv.srv.path))
    return s


def recv_all(srv: Server, s: socket.socket, what: str) -> bytes:
    """Everything the server sends until it closes the connection."""
    buf, closed = bytearray(), []

    def done():
        try:
            chunk = s.recv(1 << 16)
        except BlockingIOError:
            return False
        buf.extend(chunk)
        if not chunk:
            closed.append(True)
        return bool(closed)
    srv.spin(done, what=what)
    return bytes(buf)


def test_a_full_house_makes_room_by_closing_the_connection_waiting_longest(server):
    # issue 18 bench-hostile: 200 slow clients held every slot and valid requests were refused
    srv = server(max_clients=2)
    held = [connect(srv)]
    srv.spin(lambda: srv.srv.clients == 1, what="the first client served")
    held.append(connect(srv))
    srv.spin(lambda: srv.srv.clients == 2, what="two clients served")
    held[1].sendall(b'{"cmd": ')          # half a request: waiting too, but since later
    new = connect(srv)
    new.sendall(b'{"cmd": "ping"}\n')
    new.shutdown(socket.SHUT_WR)
    assert json.loads(recv_all(srv, new, "pong")) == {"ok": True, "result": "pong"}
    assert recv_all(srv, held[0], "the longest-waiting client closed") == b""
    assert (srv.srv.evicted, srv.srv.refused) == (1, 0)
    held[1].sendall(b'"ping"}\n')          # the other one is still served
    held[1].shutdown(socket.SHUT_WR)
    assert json.loads(recv_all(srv, held[1], "pong")) == {"ok": True, "result": "pong"}
    for c in (*held, new):
        c.close()


def test_connections_over_the_cap_are_refused_when_every_slot_is_busy(server):
    srv = server(max_clients=2)
    release = asyncio.Event()

    async def block(args):
        await release.wait()
        return "done"
    srv.srv.register("block", block)
    busy = [connect(srv), connect(srv)]
    for c in busy:
        c.sendall(b'{"cmd": "block"}\n')
    srv.spin(lambda: srv.srv.clients == 2 and not srv.srv._waiting, what="two requests in hand")
    extra = connect(srv)
    reply = json.loads(recv_all(srv, extra, "the third client refused and closed"))
    assert reply == {"ok": False, "error": "too many control connections (the daemon serves 2 at once); try again"}
    assert (srv.srv.refused, srv.srv.evicted) == (1, 0)
    release.set()
    for c in busy:
        c.shutdown(socket.SHUT_WR)
        assert json.loads(recv_all(srv, c, "done")) == {"ok": True, "result": "done"}
        c.close()
    extra.close()


def test_a_client_trickling_a_request_is_cut(server):
    srv = server(request_timeout=0.3, idle_timeout=60.0)
    s = connect(srv)
    s.sendall(b'{"cmd": ')       # then nothing: 1 byte a second would do the same
    t0 = time.monotonic()
    assert recv_all(srv, s, "the slow client closed") == b""
    assert time.monotonic() - t0 < 5.0
    assert srv.srv.clients == 0
    s.close()


def test_an_idle_connection_is_closed(server):
    srv = server(idle_timeout=0.3)
    s = connect(srv)
    srv.spin(lambda: srv.srv.clients == 1, what="client served")
    assert recv_all(srv, s, "the idle client closed") == b""
    srv.spin(lambda: srv.srv.clients == 0, what="slot freed")
    s.close()


def test_a_line_over_the_limit_is_refused_naming_the_limit(server):
    srv = server()
    assert MAX_LINE <= 64 << 10      # per connection x max_clients: the memory a crowd can pin
    s = connect(srv)
    s.setblocking(True)
    s.sendall(b"x" * (MAX_LINE + 10))
    s.setblocking(False)
    reply = json.loads(recv_all(srv, s, "the long line refused"))
    assert reply == {"ok": False, "error": f"request line longer than {MAX_LINE} bytes; closing the connection"}
    s.close()


def test_accept_errors_are_logged_once_per_period_with_a_count():
    loop = asyncio.new_event_loop()
    try:
        handler = AcceptErrorLog(every_s=3600.0)
        ctx = {"message": "socket.accept() out of system resource",
               "exception": OSError(errno.EMFILE, "Too many open files")}
        with structlog.testing.capture_logs() as logs:
            for _ in range(1000):
                handler(loop, ctx)
        assert [e["event"] for e in logs] == ["control_accept_failed"]
        assert logs[0]["times"] == 1 and "LimitNOFILE" in logs[0]["why"]
        assert handler.count == 999        # counted for the next line
    finally:
        loop.close()


def test_client_with_a_full_backlog_says_so_in_one_line(tmp_path):
    # a listener that never accepts: its backlog fills and connect() gets EAGAIN
    path = tmp_path / "full.sock"
    lst = socket.socket(socket.AF_UNIX)
    lst.bind(str(path))
    lst.listen(0)
    fillers = []
    try:
        while True:
            c = socket.socket(socket.AF_UNIX)
            c.setblocking(False)
            try:
                c.connect(str(path))
            except BlockingIOError:
                c.close()
                break
            fillers.append(c)
            assert len(fillers) < 1000
        with pytest.raises(client.DaemonUnavailable, match="not accepting connections now"):
            client.call("ping", sock_path=path, timeout=1.0)
    finally:
        for c in fillers:
            c.close()
        lst.close()


def test_client_reports_a_reply_that_is_not_json(tmp_path):
    path = tmp_path / "bad.sock"
    lst = socket.socket(socket.AF_UNIX)
    lst.bind(str(path))
    lst.listen(1)
    import threading

    def serve():
        conn, _ = lst.accept()
        conn.recv(1024)
        conn.sendall(b"garbage\n")
        conn.close()
    t = threading.Thread(target=serve)
    t.start()
    try:
        with pytest.raises(client.DaemonUnavailable, match="not JSON"):
            client.call("ping", sock_path=path, timeout=5.0)
    finally:
        t.join(5)
        lst.close()


def test_daemon_table_sets_the_control_bounds(tmp_path):
    d = InProcessDaemon(tmp_path, daemon='control_max_clients = 3\ncontrol_idle_timeout = "2min"\n'
                                          'control_request_timeout = "500ms"\ncontrol_max_subscribers = 2')
    try:
        assert (d.control.max_clients, d.control.idle_timeout, d.control.request_timeout) == (3, 120.0, 0.5)
        st = d.handle(b'{"cmd": "status"}\n')["result"]["daemon"]["control"]
        assert st == {"clients": 0, "max_clients": 3, "refused": 0, "evicted": 0, "subscribers": 0, "max_subscribers": 2,
                      "dropped": 0, "last_drop": None}
    finally:
        d.close()


def test_a_large_reply_is_encoded_in_chunks_as_one_json_line():
    from lathed.control import ENCODE_CHUNK, _encode, _encode_rows
    rows = [{"id": i, "payload": {"x": [i, 1.5]}, "t": None} for i in range(2 * ENCODE_CHUNK + 7)]
    assert _encode_rows(rows) == _encode({"ok": True, "result": rows})


def test_heavy_request_work_runs_two_at_a_time_off_the_loop():
    # a crowd of exports once took every worker thread at once (the store's and drivers' too)
    import threading
    from lathed.control import HEAVY_AT_ONCE, offload
    gate, lock, running, peak = threading.Event(), threading.Lock(), [0], [0]

    def work(i):
        with lock:
            running[0] += 1
            peak[0] = max(peak[0], running[0])
        gate.wait(10)
        with lock:
            running[0] -= 1
        return i

    async def crowd():
        tasks = [asyncio.create_task(offload(work, i)) for i in range(6)]
        while running[0] < HEAVY_AT_ONCE:        # the loop stays free while they work
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.05)
        assert running[0] == HEAVY_AT_ONCE
        gate.set()
        return await asyncio.gather(*tasks)
    assert asyncio.run(crowd()) == list(range(6))
    assert peak[0] == HEAVY_AT_ONCE == 2


def test_args_bound_lists_and_maps():
    from lathed.args import Args
    from lathed.control import RequestError
    a = Args("cmd", {"names": ["a"] * 65, "m": {"x" * 65: 1.0}, "ok": ["a", "b"]})
    with pytest.raises(RequestError, match="^cmd: names: 65 items; at most 64 allowed$"):
        a.getlist("names")
    with pytest.raises(RequestError, match="^cmd: m name: 65 characters; at most 64 allowed$"):
        a.getmap("m")
    assert a.getlist("ok") == ["a", "b"]
    with pytest.raises(RequestError, match=r"^cmd: ok\[1\]: expected an integer, got str 'b'$"):
        Args("cmd", {"ok": [1, "b"]}).getlist("ok", item=int)


def test_the_kernel_names_the_caller_and_only_operator_groups_may_act():
    # issue 17 item 3: who did it comes from SO_PEERCRED, not from what the client types;
    # with control_operator_groups set, others (here: nobody) may read but not act
    import os
    import shutil
    import subprocess
    import sys
    import tempfile
    from pathlib import Path
    tmp = Path(tempfile.mkdtemp(prefix="lathed-caller-"))
    tmp.chmod(0o755)                  # nobody must reach the socket (pytest's tmp is 0700)
    d = InProcessDaemon(tmp, daemon='control_operator_groups = ["lathed-operators-test"]')
    try:
        for p in (tmp / "run", d.control.path):
            p.chmod(0o777)

        async def lathectl(cmd: str, args: dict, user: int | None = None) -> tuple[int, str, str, int]:
            # the interpreter lives under /root: exec as root, then become `user` before connecting
            drop = "" if user is None else f"os.setgroups([]); os.setgid({user}); os.setuid({user}); "
            code = ("import json, os, sys; from lathed import client; " + drop +
                    "print(json.dumps(client.call(sys.argv[1], json.loads(sys.argv[2]), sys.argv[3])))")
            proc = await asyncio.create_subprocess_exec(
                sys.executable, "-c", code, cmd, json.dumps(args), str(d.control.path),
                cwd=Path(__file__).parents[1], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
            out, err = await proc.communicate()
            return proc.returncode, out.decode(), err.decode(), proc.pid
        code, out, err, _ = d.run(lathectl("status", {}, user=65534))
        assert code == 0 and '"daemon"' in out, err
        code, out, err, _ = d.run(lathectl("suppress", {"action": "off", "by": "root"}, user=65534))
        assert code != 0 and "suppress off: nobody (uid 65534) may only read" in err, err
        # root is an operator; the event names root's uid and pid, beside the name the client typed
        code, out, err, pid = d.run(lathectl("suppress", {"action": "manual", "by": "someone"}))
        assert code == 0, err
        # recorded through the store's writer thread: polled until committed, not assumed
        ev = wait_until(lambda: d.handle(b'{"cmd": "events", "args": {"kind": "suppression_mode"}}\n')["result"],
                        timeout=10, what="the suppression_mode event committed")
        assert [(e["payload"]["to"], e["payload"]["by"], e["payload"]["caller"]) for e in ev] == [
            ("manual", "someone", {"uid": os.getuid(), "user": "root", "pid": pid})]
    finally:
        d.close()
        shutil.rmtree(tmp, ignore_errors=True)
