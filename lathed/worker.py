"""Numeric work too long for the daemon's event loop, in a fresh process.

A thread is not enough: seconds of numpy in small steps hold the GIL from the loop that answers
chatter and the control socket (a thermal refit on a thread stalled both for 10 s). Used by the
stability learner and the thermal refit.
"""
from __future__ import annotations

import asyncio
import multiprocessing
from typing import Any, Callable


def _call(conn, fn) -> None:
    try:
        conn.send((True, fn()))
    except BaseException as e:      # noqa: BLE001 - sent back, raised in the daemon
        conn.send((False, e))
    finally:
        conn.close()


async def in_process(fn: Callable[[], Any], name: str = "lathed-worker") -> Any:
    """``fn()`` (picklable, with its arguments: a ``functools.partial``) in a fresh process,
    spawned: no copy of the daemon's threads and sockets. Its exception is raised here;
    cancelled, the process is ended."""
    ctx = multiprocessing.get_context("spawn")
    recv, send = ctx.Pipe(duplex=False)
    p = ctx.Process(target=_call, args=(send, fn), daemon=True, name=name)
    try:
        p.start()           # pickles fn: what cannot be sent is raised here
    except BaseException:
        recv.close()
        raise
    finally:
        send.close()
    try:
        ok, value = await asyncio.to_thread(recv.recv)
    except EOFError:
        raise RuntimeError(f"the {name} process ended without a result (exit code {p.exitcode})") from None
    finally:
        if p.is_alive():
            p.terminate()
        await asyncio.to_thread(p.join)
        recv.close()
    if not ok:
        raise value
    return value
