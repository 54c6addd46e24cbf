"""A real PostgreSQL server for tests, from the distribution's binaries.

One server per test session (initdb once, loopback TCP on a free port),
stopped at the end; each test gets its own database. PostgreSQL refuses to
run as root, so under root (CI) the server runs as the ``postgres`` system
user on a directory it owns. ``tests/ensure_postgres.sh`` installs the
binaries when missing.

Use: ``from tests.pg_fixtures import postgres, pg_dsn  # noqa: F401``
"""
from __future__ import annotations

import glob
import os
import shutil
import subprocess
import tempfile
import uuid
from pathlib import Path

import psycopg
import pytest

from tests.conftest import free_port


def _bindir() -> Path:
    if os.environ.get("LATHED_PG_BINDIR"):
        return Path(os.environ["LATHED_PG_BINDIR"])
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"), key=lambda p: int(p.split("/")[4]))
    if found:
        return Path(found[-1]).parent
    if shutil.which("initdb"):
        return Path(shutil.which("initdb")).parent
    raise RuntimeError("no PostgreSQL server binaries (initdb); run `bash tests/ensure_postgres.sh`")


class PgServer:
    def __init__(self) -> None:
        self.bindir = _bindir()
        self.root = Path(tempfile.mkdtemp(prefix="lathed-pg-"))
        self.data = self.root / "data"
        self.port = free_port()
        self.as_root = os.geteuid() == 0
        if self.as_root:
            shutil.chown(self.root, "postgres", "postgres")
        self.admin_dsn = f"host=127.0.0.1 port={self.port} user=lathed dbname=postgres"
        self._run("initdb", "-D", str(self.data), "-A", "trust", "-U", "lathed", "-E", "UTF8", "--no-sync")

    def _run(self, tool: str, *args: str) -> None:
        cmd = [str(self.bindir / tool), *args]
        if self.as_root:
            cmd = ["runuser", "-u", "postgres", "--", *cmd]
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=self.root)
        if r.returncode != 0:
            log = (self.root / "server.log")
            tail = log.read_text(errors="replace")[-2000:] if log.exists() else ""
            raise RuntimeError(f"{tool} failed ({r.returncode}): {r.stderr.strip()}\n{tail}")

    def start(self) -> None:
        # fsync off: a throw-away server; the tests stop it cleanly, never crash the machine
        opts = f"-p {self.port} -k {self.root} -c listen_addresses=127.0.0.1 -c fsync=off"
        self._run("pg_ctl", "-D", str(self.data), "-o", opts, "-l", str(self.root / "server.log"),
                  "-w", "-t", "60", "start")

    def stop(self) -> None:
        self._run("pg_ctl", "-D", str(self.data), "-m", "fast", "-w", "-t", "60", "stop")

    def running(self) -> bool:
        return (self.data / "postmaster.pid").exists()

    def create_db(self) -> str:
        name = f"t_{uuid.uuid4().hex[:12]}"
        with psycopg.connect(self.admin_dsn, autocommit=True) as con:
            con.execute(f'CREATE DATABASE "{name}"')
        return f"host=127.0.0.1 port={self.port} user=lathed dbname={name}"

    def cleanup(self) -> None:
        if self.running():
            try:
                self.stop()
            except RuntimeError:
                pass
        shutil.rmtree(self.root, ignore_errors=True)


@pytest.fixture(scope="session")
def postgres():
    server = PgServer()
    server.start()
    yield server
    server.cleanup()


@pytest.fixture
def pg_dsn(postgres):
    """A fresh database on the session's server (started again if a test left it stopped)."""
    if not postgres.running():
        postgres.start()
    yield postgres.create_db()
    if not postgres.running():
        postgres.start()


def pg_count(dsn: str, table: str) -> int:
    with psycopg.connect(dsn, connect_timeout=5) as con:
        return con.execute(f'SELECT count(*) FROM "{table}"').fetchone()[0]
