"""Optional dependencies: each comes with an extra (``pip install 'lathed[plots]'``).

Code that needs one asks here first, so a missing one is one line naming the
extra, not an ImportError traceback; and imports it only when used, so the
daemon and lathectl do not pay its import time when it is not.
"""
from __future__ import annotations

import importlib
import importlib.util
from types import ModuleType

EXTRAS = {"psycopg": "postgres", "matplotlib": "plots", "asyncua": "opcua", "aiomqtt": "mqtt",
          "h5py": "recordings", "nptdms": "recordings", "sounddevice": "audio"}   # module -> extra that installs it


class MissingExtra(ImportError):
    pass


def missing(module: str) -> str | None:
    """None when ``module`` can be imported; else one line naming the extra to install."""
    return None if _found(module) else f"{module} is not installed: {_install(module)}"


def need(module: str, what: str) -> ModuleType:
    """Import ``module``, or raise MissingExtra: '<what> needs <module>, which is not installed: pip install ...'."""
    if not _found(module):
        raise MissingExtra(f"{what} needs {module}, which is not installed: {_install(module)}")
    return importlib.import_module(module)


def _found(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except ValueError:     # in sys.modules without a spec: it is there
        return True


def _install(module: str) -> str:
    return f"pip install 'lathed[{EXTRAS[module]}]'"
