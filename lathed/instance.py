"""One daemon per lathe: the directories it owns and the lock that says so.

A second daemon on the same state directory would write the same record
store, and on the same runtime directory would take over the control socket
and the simulator's links; an exclusive ``flock`` on ``lathed.lock`` in each
stops it before it does anything. The kernel drops the lock with the
process, so a killed daemon leaves nothing stale behind.
"""
from __future__ import annotations

import errno
import fcntl
import os
import tempfile
from pathlib import Path

LOCK_NAME = "lathed.lock"


class Locked(Exception):
    """Another daemon holds the lock; the message names its pid and the lock file."""


def dir_problem(path: Path, what: str, create: bool) -> str | None:
    """Why ``path`` cannot serve as the daemon's ``what`` directory, in one
    line naming it and the OS error; None when it can. With ``create`` a
    missing one is made 0750 (an existing one keeps the mode it was given:
    the files in it are 0640 anyway); without (``--check-config``), the same
    is tried and undone: a directory made and removed where it would be made,
    a file made and removed in an existing one (permission bits do not say
    it: root passes them, /proc and a read-only mount refuse all the same)."""
    try:
        if create:
            path.mkdir(parents=True, exist_ok=True, mode=0o750)
        probe = path
        while not probe.exists() and probe != probe.parent:
            probe = probe.parent          # the first existing ancestor decides whether it can be made
        if not probe.is_dir():
            raise NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), str(probe))
        _try_writing(probe, make_dir=probe != path)
    except OSError as e:
        where = f" ({e.filename})" if e.filename and str(e.filename) != str(path) else ""
        return f"{what} {path} is not usable: {e.strerror or e}{where}"
    return None


def _try_writing(directory: Path, make_dir: bool) -> None:
    """Make a directory (or a file) in ``directory`` and remove it; raise as the OS refuses."""
    try:
        if make_dir:
            os.rmdir(tempfile.mkdtemp(prefix=".lathed-check-", dir=directory))
        else:
            fd, name = tempfile.mkstemp(prefix=".lathed-check-", dir=directory)
            os.close(fd)
            os.unlink(name)
    except OSError as e:     # named by the directory, not by the trial's random name
        raise type(e)(e.errno, e.strerror, str(directory)) from None


def take_lock(directory: Path) -> int:
    """Lock ``directory`` for this process; returns the descriptor to keep open."""
    path = directory / LOCK_NAME
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o640)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        pid = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
        os.close(fd)
        raise Locked(f"another lathed (pid {pid}) holds {path}: not starting a second daemon "
                     "on the same directories") from None
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    return fd
