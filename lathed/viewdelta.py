"""A view sent as what changed: the subscriber's side and the daemon's (lathed.push).

Pure Python, no imports: lathed-web merges with it without loading the daemon's modules.
"""
from __future__ import annotations

from typing import Any


def changed_keys(last: Any, view: Any) -> tuple[bool, Any]:
    """(changed, part): what a subscriber that has ``last`` needs to have ``view``: the
    keys whose value changed (a key gone as None), or the whole view when either is not
    a dict (None: no view). The unchanged values are the long ones (a spectrum's
    frequencies, a lobe chart), sent only once."""
    if not isinstance(last, dict) or not isinstance(view, dict):
        return view != last or type(view) is not type(last), view
    out = {k: x for k, x in view.items() if k not in last or (last[k] is not x and last[k] != x)}
    out.update((k, None) for k in last if k not in view)
    return bool(out), out


def merge_view(last: Any, delta: Any) -> Any:
    """A client's side of ``changed_keys``: the view after a frame's part of it."""
    if isinstance(last, dict) and isinstance(delta, dict):
        return {k: v for k, v in {**last, **delta}.items() if v is not None}
    return delta
