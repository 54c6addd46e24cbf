"""Give freed heap memory back to the system, once a minute.

A long-running daemon whose threads (the store writer, offloaded requests,
driver reads) allocate and free under load keeps that memory in glibc's
per-thread arenas: after a flood its resident set stays where the flood left
it although Python holds no more objects (make bench-hostile: RSS
7-13 % above its start after 10 min of load, all of it outside Python's own
allocations, measured with tracemalloc). ``malloc_trim(0)`` returns the free pages of every arena.
Where the C library has no malloc_trim (musl, macOS) this does nothing.
"""
from __future__ import annotations

import asyncio
import ctypes
import ctypes.util

INTERVAL_S = 60.0


def _load_trim():
    name = ctypes.util.find_library("c")
    try:
        fn = ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):
        return None
    if fn is not None:
        fn.argtypes, fn.restype = [ctypes.c_size_t], ctypes.c_int
    return fn


_TRIM = _load_trim()


def available() -> bool:
    return _TRIM is not None


def trim() -> bool:
    """Release free heap pages now; True if the C library gave any back."""
    return bool(_TRIM(0)) if _TRIM is not None else False


async def keep_trimmed(interval_s: float = INTERVAL_S) -> None:
    """Trim every ``interval_s`` in a worker thread. A trim walks every arena (about 8 ms on
    a 90 MB heap half freed): the event loop does not wait for it, but an allocation of its
    own can wait for the arena's lock that long, once a minute."""
    if _TRIM is None:
        return
    while True:
        await asyncio.sleep(interval_s)
        await asyncio.to_thread(trim)
