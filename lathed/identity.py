"""Is the peer on a machine's link the machine its config names? (docs/safety.md)

A driver reads what its peer says it is (``Driver.identify``: an identity register,
the agent's device description); this compares it with the machine's
``[identification]`` table. Another machine answering at the address is a link
failure (``NotTheMachine``); a peer whose serial number is not read, or not
configured, is not confirmed, and the supervisor sends it no command.
"""
from __future__ import annotations

from typing import Any

KEYS = ("manufacturer", "model", "serial_number")


class NotTheMachine(ConnectionError):
    """The peer says it is another machine than the configured one."""


def judge(name: str, configured: dict[str, Any], reported: dict[str, Any] | None) -> str | None:
    """None when the peer is confirmed to be machine ``name``; else why it is not confirmed.
    Raises NotTheMachine when what it says differs from what is configured."""
    reported = {k: str(v).strip() for k, v in (reported or {}).items() if k in KEYS and v is not None}
    for key in KEYS:
        if key in reported and key in configured and reported[key] != str(configured[key]).strip():
            raise NotTheMachine(f"the peer says its {key} is {reported[key]!r}, not {configured[key]!r} as "
                                f"[machine.{name}.identification] says: another machine answers at this "
                                "address; nothing is commanded")
    if not reported:
        return "its driver cannot ask the peer what it is (no identity register or description)"
    if "serial_number" not in reported:
        return "the peer does not say its serial number"
    if "serial_number" not in configured:
        return f"[machine.{name}.identification] gives no serial_number to compare with the peer's"
    return None
