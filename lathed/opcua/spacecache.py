"""lathed-opcua's address space before its own nodes (asyncua's standard space and the companion
NodeSets), built once and then loaded from a cache file: a restart skips ~4 CPU-s of building.
See docs/opcua.md, "Start-up and its cache"."""
from __future__ import annotations

import copy
import dataclasses
import gc
import hashlib
import os
import pickle
import stat
import sys
import tempfile
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path

import asyncua
import structlog
from asyncua import Server, ua

from lathed import __version__
from lathed.opcua import nodesets

log = structlog.get_logger("lathed.opcua")
NAME = "opcua-address-space.pickle"
MAGIC = b"lathed-opcua address space\n"
FORMAT = "1"


def default_dir() -> Path | None:
    """systemd's CacheDirectory, else $XDG_CACHE_HOME/lathed or ~/.cache/lathed (None: no home)."""
    if os.environ.get("CACHE_DIRECTORY"):
        return Path(os.environ["CACHE_DIRECTORY"].split(":")[0])
    if os.environ.get("XDG_CACHE_HOME"):
        return Path(os.environ["XDG_CACHE_HOME"]) / "lathed"
    try:
        return Path.home() / ".cache" / "lathed"
    except RuntimeError:
        return None


def key() -> str:
    """What the cached space is made of: a change to any of these and it is built again."""
    h = hashlib.sha256()
    for part in (FORMAT, sys.version, asyncua.__version__, __version__):
        h.update(part.encode() + b"\0")
    for path in (Path(nodesets.__file__), Path(__file__), *(nodesets.NODESETS / n for n in nodesets.FILES)):
        h.update(path.read_bytes())
    return h.hexdigest()


@contextmanager
def _no_gc():
    # a pickle of the space is ~10^6 objects: the collector running through them, again and
    # again while they are made, costs five times the load itself
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


def read(path: Path, want: str) -> tuple[dict | None, str]:
    """The cached space, or None and why it cannot be used."""
    try:
        with open(path, "rb") as f:
            st, dst = os.fstat(f.fileno()), path.parent.stat()
            if st.st_uid != os.geteuid() or (st.st_mode | dst.st_mode) & (stat.S_IWGRP | stat.S_IWOTH):
                return None, "not trusted: it or its directory is another user's or writable by others"
            if f.readline() != MAGIC:
                return None, "corrupt: not a lathed-opcua address space"
            made = f.readline().strip().decode("ascii", "replace")
            if made != want:
                return None, "stale: made by another lathed, asyncua, Python or NodeSets"
            with _no_gc():
                cached = pickle.load(f)
                # it lives as long as the process: the collector need never go through it
                gc.freeze()
    except FileNotFoundError:
        return None, "none yet"
    except OSError as e:
        return None, f"unreadable: {e.strerror or e}"
    except Exception as e:    # any failure of unpickling: a truncated or damaged file
        return None, f"corrupt: {type(e).__name__}: {e}"
    if not isinstance(cached, dict) or set(cached) != {"nodes", "namespaces", "types"}:
        return None, "corrupt: not the expected content"
    return cached, ""


def write(path: Path, made: str, cached: dict) -> None:
    """Atomically: a reader sees the old file or the whole new one (several may start at once)."""
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    with _no_gc():
        body = pickle.dumps(cached, pickle.HIGHEST_PROTOCOL)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{NAME}.")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(MAGIC + made.encode() + b"\n" + body)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _snapshot(server: Server) -> dict:
    # method callbacks cannot be pickled; asyncua binds its own again in init (as its dump does)
    out = {}
    for nodeid, nd in server.iserver.aspace._nodes.items():
        if nd.call is not None:
            nd = copy.copy(nd)
            nd.call = None
        out[nodeid] = nd
    return out


def _install(server: Server, nodes: dict) -> None:
    """The cached nodes in place of asyncua's standard space, inside its init."""
    now = datetime.now(timezone.utc)

    async def load_standard_address_space(shelf_file=None) -> None:
        # a value's timestamps say when this start wrote it, as on a build
        for nd in nodes.values():
            av = nd.attributes.get(ua.AttributeIds.Value)
            dv = av.value if av is not None else None
            if dv is not None and (dv.SourceTimestamp or dv.ServerTimestamp):
                av.value = dataclasses.replace(dv, SourceTimestamp=dv.SourceTimestamp and now,
                                               ServerTimestamp=dv.ServerTimestamp and now)
        server.iserver.aspace._nodes = nodes     # what asyncua's AddressSpace.load does
    server.iserver.load_standard_address_space = load_standard_address_space


async def open_space(server: Server, directory: Path | None) -> dict[str, int]:
    """``server.init()`` and the NodeSets, from the cache in ``directory`` when it is good (else
    built and cached); the namespace index of each model."""
    path = directory / NAME if directory is not None else None
    made = key()
    cached, why = read(path, made) if path is not None else (None, "no cache directory (no home)")
    if cached is not None:
        _install(server, cached["nodes"])
        await server.init()
        for uri in cached["namespaces"]:
            await server.register_namespace(uri)
        array = await server.get_namespace_array()
        if array[2:] != cached["namespaces"]:
            raise RuntimeError(f"namespaces {array} registered before the cached NodeSets'")
        await nodesets.register_types(server, cached["types"])
        log.info("address_space_loaded", cache=str(path))
        return await nodesets.indexes(server)
    (log.info if why == "none yet" else log.warning)("address_space_built", cache=str(path), why=why)
    await server.init()
    types: list[nodesets.TypeRecord] = []
    ns = await nodesets.load(server, types)
    if path is not None:
        namespaces = (await server.get_namespace_array())[2:]
        try:
            write(path, made, {"nodes": _snapshot(server), "namespaces": namespaces, "types": types})
        except (OSError, pickle.PicklingError, TypeError, AttributeError) as e:
            log.warning("address_space_not_cached", cache=str(path), why=f"{type(e).__name__}: {e}")
    gc.freeze()     # as after a load
    return ns
