"""Optional dependencies: each comes with an extra (``pip install 'lathed[plots]'``).

Code that needs one asks here first, so a missing one is one line naming the
extra, not an ImportError traceback; and imports it only when used, so the
daemon and lathectl do not pay its import time when it is not. In the service's
own venv (``make install`` leaves INSTALL_MARK in it) the line says how to add
the extra there: ``make install EXTRAS=...`` again, keeping those it has.
"""
from __future__ import annotations

import importlib
import importlib.util
import sys
from pathlib import Path
from types import ModuleType

EXTRAS = {"psycopg": "postgres", "matplotlib": "plots", "asyncua": "opcua", "aiomqtt": "mqtt",
          "h5py": "recordings", "nptdms": "recordings", "sounddevice": "audio"}   # module -> extra that installs it


INSTALL_MARK = "lathed-install"   # in sys.prefix: "prefix=/usr" of the `make install` that made this venv


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
    extra = EXTRAS[module]
    mark = Path(sys.prefix) / INSTALL_MARK
    if not mark.is_file():
        return f"pip install 'lathed[{extra}]'"
    # the service's venv: pip there would leave it out of step with `make install`, which
    # rebuilds the venv with only the extras it is given; so name those it has already
    fields = dict(line.split("=", 1) for line in mark.read_text().splitlines() if "=" in line)
    have = {x for m, x in EXTRAS.items() if _found(m) and all(_found(o) for o, y in EXTRAS.items() if y == x)}
    unit = Path(sys.argv[0]).name if Path(sys.argv[0]).name.startswith("lathed") else "lathed"
    return (f"in the service's venv ({sys.prefix}) add it from the lathed source with `sudo make install "
            f"PREFIX={fields.get('prefix', '/usr')} EXTRAS={','.join(sorted(have | {extra}))}`, "
            f"then `sudo systemctl restart {unit}`")
