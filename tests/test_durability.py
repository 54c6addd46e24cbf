"""SIGKILL while the store writes at full rate: the file stays sound and
every record the daemon acknowledged is in it."""
from __future__ import annotations

import json
import shutil
import sqlite3
from pathlib import Path

from tests.conftest import Daemon, wait_until

HERE = Path(__file__).resolve().parent


def _acked(path: Path) -> list[tuple[int, int]]:
    if not path.exists():
        return []
    lines = path.read_text().split("\n")
    # the last line may have been cut by the kill: only whole lines count as acknowledged
    return [tuple(map(int, ln.split())) for ln in lines[:-1]]


def test_sigkill_at_full_rate_loses_no_acknowledged_record(tmp_path):
    plugins = tmp_path / "plugins"
    plugins.mkdir()
    shutil.copy(HERE / "writer_plugin.py", plugins / "test_writer.py")
    acks = tmp_path / "acks.txt"
    cfg = tmp_path / "lathed.toml"
    cfg.write_text(f"""
[daemon]
name = "cell-kill"
state_dir = "{tmp_path / 'state'}"
runtime_dir = "{tmp_path / 'run'}"
plugin_dirs = ["{plugins}"]

[analyzer.writer]
plugin = "test_writer"
every = "0ms"
concurrency = 64
ack_file = "{acks}"
""")
    d = Daemon(cfg, tmp_path / "run" / "lathed.sock")
    try:
        d.wait_ready()
        before = len(_acked(acks))
        wait_until(lambda: len(_acked(acks)) >= before + 3000, 60, what="3000 acknowledged records")
        d.proc.kill()
        d.proc.wait(10)
    finally:
        d.stop()
    acked = _acked(acks)
    assert len(acked) >= 3000

    con = sqlite3.connect(tmp_path / "state" / "lathed.db")   # recovers the WAL like a restart would
    try:
        assert con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        rows = dict(con.execute("SELECT id, payload FROM events WHERE kind = 'tick'").fetchall())
        outboxed = {r for (r,) in con.execute("SELECT row_id FROM outbox WHERE tbl = 'events'")}
    finally:
        con.close()
    missing = [rid for rid, _ in acked if rid not in rows]
    assert not missing, f"{len(missing)} acknowledged records lost, e.g. ids {missing[:5]}"
    assert all(json.loads(rows[rid])["seq"] == seq for rid, seq in acked)
    assert {rid for rid, _ in acked} <= outboxed   # and each will still be forwarded
