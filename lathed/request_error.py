"""The errors a control request is answered with (one line back to the client)."""
from __future__ import annotations


class RequestError(Exception):
    """A request the daemon understood but cannot carry out; sent back as the error."""


class ArgumentError(RequestError):
    """A request whose argument is wrong (``Args``): a usage error, said as one (``usage``:
    lathectl exits 2 for it, 1 for a request the daemon's state refuses)."""
