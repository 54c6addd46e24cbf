"""Room kept for the audit record of every command (docs/safety.md).

Before a command is sent, room for its record is claimed here; the record then goes
to the store, and if the store refuses it (a full disk, an I/O error) it is written
into this reserve: a file whose blocks were allocated when the daemon started, so a
full disk cannot refuse it. When no room can be claimed the command is not sent.
What the reserve keeps goes into the store as soon as the store takes records again,
with its own time, and at the next start if the daemon stopped first.
"""
from __future__ import annotations

import errno
import json
import os
import threading
from pathlib import Path

import structlog

from lathed.store import dumps

RESERVE_BYTES = 1 << 20     # ~2000 command records of ~500 bytes
MARGIN = 1024               # claimed beyond a payload: the driver's detail, the caller, the envelope

log = structlog.get_logger("lathed.audit")


class ReserveError(OSError):
    pass


class AuditReserve:
    def __init__(self, path: Path | None, size: int = RESERVE_BYTES):
        """``path`` None: kept in memory only (tests with a store that never refuses)."""
        self.path, self.size = path, size
        self._lock = threading.Lock()
        self._claimed = 0           # bytes claimed by commands whose records are not settled
        self._used = 0              # bytes of kept records at the head of the file
        self._memory = bytearray()
        self.kept_total = 0         # records this process kept here
        self.fd: int | None = None
        if path is None:
            return
        try:
            self.fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o640)
            if os.fstat(self.fd).st_size < size:
                os.posix_fallocate(self.fd, 0, size)
            head = os.pread(self.fd, size, 0)
        except OSError as e:
            if self.fd is not None:
                os.close(self.fd)
            raise ReserveError(e.errno or errno.EIO, f"cannot keep the audit reserve {path}: "
                                                     f"{e.strerror or e}") from None
        end = head.find(b"\0")
        self._used = len(head) if end < 0 else end     # a previous run's records, not yet stored

    # -- commands ---------------------------------------------------------------------
    def claim(self, n: int) -> bool:
        """Room for a record of ``n`` bytes, should the store refuse it; False: none left."""
        with self._lock:
            if self._used + self._claimed + n > self.size:
                return False
            self._claimed += n
            return True

    def settle(self, n: int, line: bytes | None) -> None:
        """A claimed record was stored (``line`` None) or refused by the store: kept here.
        Called from the store's writer thread."""
        with self._lock:
            self._claimed -= n
            if line is None:
                return
            line = line.rstrip(b"\n") + b"\n"
            if self._used + len(line) > self.size:        # longer than claimed and no room: said loudly
                log.critical("audit_reserve_overflow", record=line[:500].decode(errors="replace"))
                return
            if self.fd is None:
                self._memory += line
            else:
                os.pwrite(self.fd, line, self._used)
                os.fsync(self.fd)
            self._used += len(line)
            self.kept_total += 1
        log.warning("command_record_kept_in_reserve", reserve=str(self.path), used_bytes=self._used,
                    why="the store refused the command's record; it is stored when the store takes records again")

    @staticmethod
    def line(kind: str, source: str, payload: dict, t: float) -> bytes:
        return dumps({"kind": kind, "source": source, "t": t, "payload": payload}).encode() + b"\n"

    # -- draining ------------------------------------------------------------------------
    def kept(self) -> tuple[int, list[dict]]:
        """(bytes, records) kept now, oldest first; a line that does not parse (a record cut by
        a crash mid-write) is kept as its text."""
        with self._lock:
            data = bytes(self._memory) if self.fd is None else os.pread(self.fd, self._used, 0)
        out = []
        for raw in data.splitlines():
            try:
                rec = json.loads(raw)
                if not isinstance(rec, dict) or not {"kind", "source", "t", "payload"} <= rec.keys():
                    raise ValueError("not a record")
            except ValueError:
                rec = {"kind": "command_record_damaged", "source": "lathed", "t": None,
                       "payload": {"text": raw.decode(errors="replace")}}
            out.append(rec)
        return len(data), out

    def drop(self, n: int) -> None:
        """The first ``n`` bytes are stored now: taken out, what was kept after them moved up."""
        with self._lock:
            if self.fd is None:
                del self._memory[:n]
            else:
                rest = os.pread(self.fd, self._used - n, n)
                os.pwrite(self.fd, rest + b"\0" * n, 0)
                os.fsync(self.fd)
            self._used -= n

    @property
    def kept_bytes(self) -> int:
        return self._used

    def stats(self) -> dict:
        with self._lock:
            return {"path": None if self.path is None else str(self.path), "size_bytes": self.size,
                    "kept_bytes": self._used, "claimed_bytes": self._claimed, "kept_total": self.kept_total}

    def close(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None
