"""Finding and loading plugins: entry points and drop-in directories.

Built-in plugins are installed under the ``lathed.plugins`` entry-point group
exactly like third-party ones. A ``.py`` file in a drop-in directory named by
``[daemon] plugin_dirs`` is loaded the same way. Whatever fails to import is
reported and skipped; it never stops the daemon.
"""
from __future__ import annotations

import contextlib
import importlib.util
import signal
import sys
import threading
import traceback
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

import pluggy

from lathed import hookspecs
from lathed.analysis.chatter.base import RevolutionDetector
from lathed.analyzer import Analyzer
from lathed.driver import Driver

GROUP = "lathed.plugins"
BASES = {"lathed_driver_types": Driver, "lathed_analyzer_types": Analyzer,
         "lathed_chatter_detectors": RevolutionDetector}
IMPORT_TIMEOUT_S = 30.0   # per plugin; numpy/scipy imports on a busy 2-core PC take seconds


class ImportTimeout(BaseException):
    """A plugin did not finish importing in time. A BaseException, so the
    plugin's own ``except Exception`` does not swallow it."""


@contextlib.contextmanager
def _deadline(seconds: float, what: str):
    """Interrupt the main thread if the body runs longer than ``seconds``
    (a plugin looping at import). Elsewhere than the main thread there are
    no signals to do it with, and the body runs unbounded."""
    if not seconds or threading.current_thread() is not threading.main_thread():
        yield
        return

    def expired(signum, frame):
        raise ImportTimeout(f"{what} did not finish importing within {seconds:g} s")
    old = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


@dataclass
class PluginInfo:
    name: str
    origin: str                 # "entry point module:attr" or a file path
    provides: list[str] = field(default_factory=list)
    error: str | None = None


def _one_line(exc: BaseException) -> str:
    """The exception as one line, with the plugin file and line where it arose."""
    from lathed.driver import LinkDown
    if isinstance(exc, LinkDown):
        return str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    where = ""
    tb = traceback.extract_tb(exc.__traceback__)
    if tb:
        last = tb[-1]
        where = f" at {last.filename}:{last.lineno}"
    if isinstance(exc, SystemExit):   # sys.exit() in a plugin must not end the daemon, nor pass unnoticed
        return f"SystemExit: the plugin called sys.exit({exc.code!r}){where}"
    if isinstance(exc, ImportTimeout):
        return str(exc) + where
    msg = str(exc).splitlines()[0] if str(exc) else ""
    return f"{type(exc).__name__}: {msg}{where}"


class PluginLoader:
    def __init__(self, import_timeout: float = IMPORT_TIMEOUT_S) -> None:
        self.import_timeout = import_timeout
        self.pm = pluggy.PluginManager("lathed")
        self.pm.add_hookspecs(hookspecs)
        self.plugins: list[PluginInfo] = []
        self._types: dict[str, dict[str, tuple[Any, str]]] = {}

    # -- loading ----------------------------------------------------------
    def load_entry_points(self, group: str = GROUP) -> None:
        for ep in sorted(entry_points(group=group), key=lambda e: e.name):
            info = PluginInfo(ep.name, f"entry point {ep.value}")
            try:
                with _deadline(self.import_timeout, f"plugin {ep.name}"):
                    self._register(ep.load(), info)
            except KeyboardInterrupt:
                raise
            except BaseException as e:   # a broken plugin is reported, never fatal, even sys.exit()
                info.error = _one_line(e)
            self.plugins.append(info)

    def load_dir(self, directory: str | Path) -> None:
        directory = Path(directory)
        if not directory.is_dir():
            self.plugins.append(PluginInfo(str(directory), str(directory),
                                           error="plugin directory does not exist"))
            return
        for path in sorted(directory.glob("*.py")):
            info = PluginInfo(path.stem, str(path))
            modname = f"lathed_dropin_{path.stem}"
            try:
                with _deadline(self.import_timeout, f"plugin {path.stem} ({path})"):
                    spec = importlib.util.spec_from_file_location(modname, path)
                    module = importlib.util.module_from_spec(spec)
                    sys.modules[modname] = module
                    spec.loader.exec_module(module)
                    self._register(module, info)
            except KeyboardInterrupt:
                raise
            except BaseException as e:
                sys.modules.pop(modname, None)
                info.error = _one_line(e)
            self.plugins.append(info)

    def _register(self, module: Any, info: PluginInfo) -> None:
        self.pm.register(module, name=info.name)
        try:
            provided = []
            for hook in ("lathed_driver_types", "lathed_analyzer_types", "lathed_chatter_detectors"):
                impl = getattr(module, hook, None)
                if impl is None:
                    continue
                types = impl() or {}
                if not isinstance(types, dict):
                    raise TypeError(f"{hook} must return a dict, got {type(types).__name__}")
                table = self._types.setdefault(hook, {})
                base = BASES.get(hook)
                for tname, obj in types.items():
                    if base is not None and not (isinstance(obj, type) and issubclass(obj, base)):
                        # the contract: every optional method has the base class's default
                        raise TypeError(f"{hook}: type {tname!r} is {obj!r}, not a subclass of "
                                        f"{base.__module__}.{base.__name__}")
                    if tname in table:
                        raise ValueError(f"{hook}: type {tname!r} is already provided by plugin "
                                         f"{table[tname][1]!r}")
                for tname, obj in types.items():
                    table[tname] = (obj, info.name)
                    provided.append(tname)
            if getattr(module, "lathed_thermal_candidates", None):
                provided.append("thermal candidates")
            if (kinds := getattr(module, "lathed_event_kinds", None)) is not None:
                declared = kinds() or []
                if not isinstance(declared, (list, tuple, set)) or not all(isinstance(k, str) and k
                                                                           for k in declared):
                    raise TypeError(f"lathed_event_kinds must return a list of names, got {declared!r}")
                provided.append("event kinds")
            info.provides = provided
        except BaseException:
            self.pm.unregister(module)
            raise

    # -- lookups ------------------------------------------------------------
    def types(self, hook: str) -> dict[str, Any]:
        return {name: obj for name, (obj, _) in self._types.get(hook, {}).items()}

    def driver_types(self) -> dict[str, Any]:
        return self.types("lathed_driver_types")

    def analyzer_types(self) -> dict[str, Any]:
        return self.types("lathed_analyzer_types")

    def chatter_detectors(self) -> dict[str, Any]:
        return self.types("lathed_chatter_detectors")

    def event_kinds(self) -> set[str]:
        return {k for lst in self.pm.hook.lathed_event_kinds() for k in (lst or [])}

    def thermal_candidates(self) -> list[Any]:
        return [c for lst in self.pm.hook.lathed_thermal_candidates() for c in (lst or [])]

    def summary(self) -> list[dict[str, Any]]:
        return [{"name": p.name, "origin": p.origin, "state": "failed" if p.error else "loaded",
                 "provides": p.provides, "error": p.error} for p in self.plugins]


def load_all(plugin_dirs: list[Path], import_timeout: float = IMPORT_TIMEOUT_S) -> PluginLoader:
    loader = PluginLoader(import_timeout)
    loader.load_entry_points()
    for d in plugin_dirs:
        loader.load_dir(d)
    return loader
