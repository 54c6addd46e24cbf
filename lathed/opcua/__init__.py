"""lathed-opcua: the line as an OPC UA server beside the daemon (see lathed.opcua.app)."""
from __future__ import annotations

import sys


def main(argv: list[str] | None = None) -> int:
    """The program; without the ``opcua`` extra, one line naming it (exit 69), not a traceback."""
    from lathed.extras import missing
    why = missing("asyncua")
    if why:
        print(f"lathed-opcua: {why}", file=sys.stderr)
        return 69
    from lathed.opcua.app import main as run
    return run(argv)
