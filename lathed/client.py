"""The client side of the control socket, for lathectl and tests."""
from __future__ import annotations

import json
import os
import socket
import sys
from pathlib import Path
from typing import Any

SOCKET_NAME = "lathed.sock"


class DaemonUnavailable(Exception):
    pass


class RemoteError(Exception):
    """The daemon's one-line refusal; ``usage``: of an argument (a usage error)."""

    def __init__(self, message: str, usage: bool = False):
        super().__init__(message)
        self.usage = usage


def default_runtime_dir() -> Path:
    """Where the daemon puts its socket unless the config says otherwise:
    systemd's RuntimeDirectory, else a directory inside this environment,
    so `lathectl` from the same venv finds a `make run` daemon."""
    if os.environ.get("RUNTIME_DIRECTORY"):
        return Path(os.environ["RUNTIME_DIRECTORY"].split(":")[0])
    return Path(sys.prefix) / "var" / "run" / "lathed"


def default_state_dir() -> Path:
    """Where the daemon keeps its store unless the config says otherwise: systemd's
    StateDirectory, else a directory inside this environment."""
    if os.environ.get("STATE_DIRECTORY"):
        return Path(os.environ["STATE_DIRECTORY"].split(":")[0])
    return Path(sys.prefix) / "var" / "lib" / "lathed"


def default_db() -> Path:
    """The store lathectl reads when the daemon is down: $LATHED_DB, the service's, or this environment's."""
    if os.environ.get("LATHED_DB"):
        return Path(os.environ["LATHED_DB"])
    service = Path("/var/lib/lathed") / "lathed.db"
    return service if service.exists() else default_state_dir() / "lathed.db"


def default_socket() -> Path:
    if os.environ.get("LATHED_SOCKET"):
        return Path(os.environ["LATHED_SOCKET"])
    service = Path("/run/lathed") / SOCKET_NAME
    if service.exists():
        return service
    return default_runtime_dir() / SOCKET_NAME


def _connect(path: Path, timeout: float) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout)
    try:
        s.connect(str(path))
    except (FileNotFoundError, ConnectionRefusedError):
        s.close()
        raise DaemonUnavailable(f"lathed is not running (no daemon listening on {path})") from None
    except PermissionError:
        s.close()
        raise DaemonUnavailable(f"permission denied on {path}: join the lathed group") from None
    except BlockingIOError:   # EAGAIN: the listen backlog is full
        s.close()
        raise DaemonUnavailable(f"lathed on {path} is not accepting connections now (its backlog is full: "
                                "too many clients, or it is out of file descriptors); try again") from None
    except OSError:
        s.close()
        raise
    return s


def subscribe(args: dict[str, Any], sock_path: str | Path | None = None, timeout: float = 10.0,
              cmd: str = "subscribe"):
    """``subscribe`` (lathed.push), or another streaming command (``record``): yields the
    first reply, then each pushed frame. A daemon that goes silent for ``timeout`` (it sends
    a frame every second) or closes ends it with DaemonUnavailable; a refusal or a drop
    with RemoteError."""
    path = Path(sock_path) if sock_path else default_socket()
    s = _connect(path, timeout)
    try:
        s.sendall(json.dumps({"cmd": cmd, "args": args}).encode() + b"\n")
        f = s.makefile("rb")
        first = True
        while True:
            try:
                line = f.readline()
            except socket.timeout:
                raise DaemonUnavailable(f"lathed sent nothing for {timeout:g} s on {path}") from None
            except OSError as e:
                raise DaemonUnavailable(f"lost the connection to lathed on {path}: {e.strerror or e}") from None
            if not line:
                raise DaemonUnavailable(f"lathed closed the connection on {path}")
            try:
                msg = json.loads(line)
            except ValueError:
                raise DaemonUnavailable(f"lathed on {path} sent a line that is not JSON: {line[:80]!r}") from None
            if first:
                if not msg.get("ok"):
                    raise RemoteError(msg.get("error", "unknown error"), bool(msg.get("usage")))
                yield msg["result"]
                first = False
            elif "push" in msg:
                yield msg["push"]
            else:
                raise RemoteError(msg.get("error", "unknown error"))
    finally:
        s.close()


def call(cmd: str, args: dict[str, Any] | None = None, sock_path: str | Path | None = None,
         timeout: float = 10.0) -> Any:
    path = Path(sock_path) if sock_path else default_socket()
    try:
        s = _connect(path, timeout)
    except socket.timeout:
        raise DaemonUnavailable(f"lathed did not answer within {timeout:g} s on {path}") from None
    except OSError as e:
        raise DaemonUnavailable(f"lost the connection to lathed on {path}: {e.strerror or e}") from None
    try:
        s.sendall(json.dumps({"cmd": cmd, "args": args or {}}).encode() + b"\n")
        buf = b""
        while not buf.endswith(b"\n"):
            chunk = s.recv(1 << 16)
            if not chunk:
                raise DaemonUnavailable(f"lathed closed the connection on {path} without a reply")
            buf += chunk
    except socket.timeout:
        raise DaemonUnavailable(f"lathed did not answer within {timeout:g} s on {path}") from None
    except OSError as e:      # reset, broken pipe...: one line, not a traceback
        raise DaemonUnavailable(f"lost the connection to lathed on {path}: {e.strerror or e}") from None
    finally:
        s.close()
    try:
        reply = json.loads(buf)
    except ValueError:
        raise DaemonUnavailable(f"lathed on {path} sent a reply that is not JSON: {buf[:80]!r}") from None
    if not isinstance(reply, dict) or not reply.get("ok"):
        if not isinstance(reply, dict):
            raise RemoteError(repr(reply)[:200])
        raise RemoteError(reply.get("error", "unknown error"), bool(reply.get("usage")))
    return reply.get("result")
