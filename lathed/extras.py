"""Optional dependencies: each comes with an extra (``pip install 'lathed[plots]'``).

Code that needs one asks here first, so a missing one is one line naming the
extra, not an ImportError traceback; and imports it only when used, so the
daemon and lathectl do not pay its import time when it is not.
"""
from __future__ import annotations

import importlib
import importlib.util
from types import ModuleType

EXTRAS = {"psycopg": "postgres", "matplotlib": "plots"}   # module -> extra that installs it


class MissingExtra(ImportError):
    pass


def missing(module: str) -> str | None:
    """None when ``module`` can be imported; else one line naming the extra to install."""
    try:
        found = importlib.util.find_spec(module) is not None
    except ValueError:     # in sys.modules without a spec: it is there
        found = True
    return None if found else f"{module} is not installed: pip install 'lathed[{EXTRAS[module]}]'"


def need(module: str, what: str) -> ModuleType:
    """Import ``module``, or raise MissingExtra: '<what> needs <module>, which is not installed: pip install ...'."""
    why = missing(module)
    if why:
        raise MissingExtra(f"{what} needs {why.replace(' is not installed', ', which is not installed')}")
    return importlib.import_module(module)
