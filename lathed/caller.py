"""Who sent a control request, as the kernel says (SO_PEERCRED), not as the client claims.

The control server sets ``CALLER`` for each connection; events recorded while a request is
handled carry it (``Supervisor.record``), and a handler that changes something asks
``require_operator``. Operators: root, the daemon's own user, and, when ``[daemon]
control_operator_groups`` is set, members of those groups; without it everyone the socket's
0660 mode lets in may act (the behaviour before it existed).
"""
from __future__ import annotations

import contextvars
import grp
import os
import pwd
import socket
import struct
from dataclasses import dataclass, field

from lathed.request_error import RequestError


@dataclass(frozen=True)
class Caller:
    uid: int
    gid: int
    pid: int
    user: str
    operator: bool = True
    groups: frozenset[str] = field(default_factory=frozenset)

    def audit(self) -> dict:
        return {"uid": self.uid, "user": self.user, "pid": self.pid}


CALLER: contextvars.ContextVar[Caller | None] = contextvars.ContextVar("lathed_caller", default=None)


def _user(uid: int) -> str:
    try:
        return pwd.getpwuid(uid).pw_name
    except KeyError:
        return str(uid)


def _groups(user: str, gid: int) -> frozenset[str]:
    try:
        gids = set(os.getgrouplist(user, gid))
    except OSError:          # a uid with no passwd entry: its primary group only
        gids = {gid}
    names = set()
    for g in gids:
        try:
            names.add(grp.getgrgid(g).gr_name)
        except KeyError:
            names.add(str(g))
    return frozenset(names)


def peer(sock: socket.socket | None, operator_groups: list[str]) -> Caller | None:
    """The caller on a Unix socket; None where the kernel cannot say (not AF_UNIX)."""
    if sock is None or sock.family != socket.AF_UNIX:
        return None
    pid, uid, gid = struct.unpack("3i", sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED,
                                                        struct.calcsize("3i")))
    user = _user(uid)
    groups = _groups(user, gid) if operator_groups else frozenset()
    operator = (not operator_groups or uid in (0, os.geteuid()) or bool(groups & set(operator_groups)))
    return Caller(uid, gid, pid, user, operator, groups)


def current() -> Caller | None:
    return CALLER.get()


def require_operator(what: str) -> None:
    """Refuse ``what`` to a caller without the operator role (read-only callers may query)."""
    c = CALLER.get()
    if c is not None and not c.operator:
        raise RequestError(f"{what}: {c.user} (uid {c.uid}) may only read: not in [daemon] "
                           "control_operator_groups")
