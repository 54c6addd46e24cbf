"""Reading and validating lathed.toml.

One table per machine, sensor or analyzer instance (``[machine.lathe]``,
``[sensor.temps]``, ``[analyzer.chatter]``). Each plugin reads its own table
through the typed getters of :class:`Section`; whatever it did not read is an
unknown key and refused (as Klipper does), so a typo never silently falls
back to a default. Every error is one line naming file, table, key and what
is allowed.
"""
from __future__ import annotations

import difflib
import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

EX_CONFIG = 78

_REQUIRED = object()
CATEGORIES = ("machine", "sensor", "analyzer")
TOP_TABLES = ("daemon", "simulator", "store") + CATEGORIES


class ConfigError(Exception):
    """A configuration problem, already phrased as one line for the user."""


_DURATION = re.compile(r"^\s*([0-9]*\.?[0-9]+)\s*(ms|s|min|h)?\s*$")
_UNIT_S = {"ms": 1e-3, "s": 1.0, "min": 60.0, "h": 3600.0, None: 1.0}


def parse_duration(text: str) -> float:
    m = _DURATION.match(text)
    if not m:
        raise ValueError(text)
    return float(m.group(1)) * _UNIT_S[m.group(2)]


def finite(v: int | float) -> bool:
    """A finite float, or an integer a float can hold (math.isfinite overflows on 10**400)."""
    try:
        return math.isfinite(v)
    except OverflowError:
        return False


def _range_text(minval: Any, maxval: Any) -> str:
    if minval is not None and maxval is not None:
        return f" in [{minval}, {maxval}]"
    if minval is not None:
        return f" >= {minval}"
    if maxval is not None:
        return f" <= {maxval}"
    return ""


def _close(word: str, words: list[str]) -> str | None:
    """The one of ``words`` that ``word`` most likely misspells, if any."""
    near = difflib.get_close_matches(word, words, n=1, cutoff=0.75)
    return near[0] if near else None


class Section:
    """One TOML table with typed, range-checked getters.

    Keys read through a getter are remembered; :meth:`check_unused` then
    refuses the rest as unknown keys.
    """

    def __init__(self, file: str | Path, table: str, data: dict[str, Any]):
        self.file = str(file)
        self.table = table
        self._data = data
        self._read: set[str] = set()

    # -- errors ---------------------------------------------------------
    def error(self, key: str | None, problem: str) -> ConfigError:
        where = f"{self.file}: [{self.table}]"
        return ConfigError(f"{where} {key}: {problem}" if key else f"{where}: {problem}")

    # -- presence -------------------------------------------------------
    @property
    def name(self) -> str:
        return self.table.rsplit(".", 1)[-1]

    def __contains__(self, key: str) -> bool:
        return key in self._data

    def raw(self) -> dict[str, Any]:
        """The table as read (a reload compares old and new)."""
        return dict(self._data)

    def keys(self) -> list[str]:
        return list(self._data)

    def _raw(self, key: str, default: Any) -> Any:
        self._read.add(key)
        if key in self._data:
            return self._data[key]
        if default is _REQUIRED:
            # "hots" where "host" is required is a misspelling, not two problems: name the key written
            typo = _close(key, [k for k in self._data if k not in self._read])
            if typo is not None:
                raise self.error(typo, f"unknown key; did you mean {key} (required here, and missing)?")
            raise self.error(key, "missing required key")
        return default

    # -- typed getters --------------------------------------------------
    def get(self, key: str, default: Any = _REQUIRED) -> Any:
        return self._raw(key, default)

    def getstr(self, key: str, default: Any = _REQUIRED, choices: tuple[str, ...] | None = None,
               empty: bool = False) -> str:
        """A string; "" only where the caller allows it (``empty``, a default of "", a choice of "")."""
        v = self._raw(key, default)
        if v is default and default is not _REQUIRED:
            return v
        if not isinstance(v, str):
            raise self.error(key, f"expected a string, got {type(v).__name__} {v!r}")
        if choices is not None and v not in choices:
            raise self.error(key, f"{v!r} is not allowed; allowed: {', '.join(choices)}")
        # name = "" or host = "" was taken: a machine with no name, a link to nowhere
        if v == "" and not (empty or default == "" or choices):
            raise self.error(key, "expected a non-empty string, got ''")
        return v

    def getint(self, key: str, default: Any = _REQUIRED, minval: int | None = None,
               maxval: int | None = None) -> int:
        v = self._raw(key, default)
        if v is default and default is not _REQUIRED:
            return v
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.error(key, f"expected an integer{_range_text(minval, maxval)}, got {v!r}")
        if (minval is not None and v < minval) or (maxval is not None and v > maxval):
            raise self.error(key, f"{v} is out of range; allowed: an integer{_range_text(minval, maxval)}")
        return v

    def getfloat(self, key: str, default: Any = _REQUIRED, minval: float | None = None,
                 maxval: float | None = None, above: float | None = None) -> float:
        v = self._raw(key, default)
        if v is default and default is not _REQUIRED:
            return v
        want = f"a number{_range_text(minval, maxval)}" + (f" > {above}" if above is not None else "")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not finite(v):
            raise self.error(key, f"expected {want}, got {v!r}")
        v = float(v)
        if ((minval is not None and v < minval) or (maxval is not None and v > maxval)
                or (above is not None and v <= above)):
            raise self.error(key, f"{v:g} is out of range; allowed: {want}")
        return v

    def getbool(self, key: str, default: Any = _REQUIRED) -> bool:
        v = self._raw(key, default)
        if not isinstance(v, bool):
            raise self.error(key, f"expected true or false, got {v!r}")
        return v

    def getduration(self, key: str, default: Any = _REQUIRED, minval: float | None = None,
                    maxval: float | None = None) -> float:
        """A duration in seconds, written "50ms", "6s", "2min", "1h" or a number of seconds."""
        v = self._raw(key, default)
        if v is default and default is not _REQUIRED:
            return v
        want = 'a duration like "50ms", "6s", "2min", "1h"'
        if isinstance(v, bool):
            raise self.error(key, f"expected {want}, got {v!r}")
        if isinstance(v, (int, float)):
            secs = float(v)
        elif isinstance(v, str):
            try:
                secs = parse_duration(v)
            except ValueError:
                raise self.error(key, f"expected {want}, got {v!r}") from None
        else:
            raise self.error(key, f"expected {want}, got {v!r}")
        # nan compares false with every bound and asyncio.sleep(nan) returns at once: a busy loop
        if not finite(secs):
            raise self.error(key, f"expected a finite duration, got {v!r}")
        if (minval is not None and secs < minval) or (maxval is not None and secs > maxval):
            raise self.error(key, f"{v!r} is out of range; allowed: {_range_text(minval, maxval).strip()} s")
        return secs

    def getlist(self, key: str, default: Any = _REQUIRED, item: type = str) -> list:
        v = self._raw(key, default)
        if v is default and default is not _REQUIRED:
            return v
        def ok(x: Any) -> bool:
            if isinstance(x, bool):
                return item is bool
            if item is float:   # nan/inf pass every range check that follows
                return isinstance(x, (int, float)) and finite(x)
            return isinstance(x, item)
        if not isinstance(v, list) or not all(ok(x) for x in v):
            raise self.error(key, f"expected a list of {item.__name__}, got {v!r}")
        return list(v)

    # -- sub-tables -----------------------------------------------------
    def has_section(self, key: str) -> bool:
        return isinstance(self._data.get(key), dict)

    def getsection(self, key: str, required: bool = True) -> Section | None:
        self._read.add(key)
        v = self._data.get(key)
        if v is None:
            if required:
                raise self.error(key, "missing required table")
            return Section(self.file, f"{self.table}.{key}", {})
        if not isinstance(v, dict):
            raise self.error(key, f"expected a table, got {v!r}")
        return Section(self.file, f"{self.table}.{key}", v)

    def subsections(self) -> list[Section]:
        """Every sub-table, each marked as read."""
        out = []
        for k, v in self._data.items():
            if isinstance(v, dict):
                self._read.add(k)
                out.append(Section(self.file, f"{self.table}.{k}", v))
        return out

    def without(self, *keys: str) -> Section:
        """A copy minus framework-owned keys, for the plugin to read."""
        return Section(self.file, self.table, {k: v for k, v in self._data.items() if k not in keys})

    def check_unused(self) -> None:
        unknown = [k for k in self._data if k not in self._read]
        if unknown:
            allowed = ", ".join(sorted(self._read)) or "none"
            near = _close(unknown[0], sorted(self._read))
            hint = f"did you mean {near}? " if near is not None else ""
            raise self.error(unknown[0], f"unknown key; {hint}allowed keys here: {allowed}")


@dataclass
class Instance:
    category: str          # machine | sensor | analyzer
    name: str
    plugin: str            # driver or analyzer type name
    section: Section       # the plugin's own keys (framework keys stripped)
    framework: Section     # framework-owned keys: plugin, limits, retry...


@dataclass
class Config:
    path: Path
    daemon: Section
    simulator: Section | None
    store: Section
    instances: list[Instance] = field(default_factory=list)

    def instance(self, category: str, name: str) -> Instance | None:
        for inst in self.instances:
            if inst.category == category and inst.name == name:
                return inst
        return None


FRAMEWORK_KEYS = ("plugin", "limits", "retry_initial", "retry_max", "enabled")


def substitute(cfg: Config, name: str, value: str) -> None:
    """Replace ``{name}`` (e.g. ``{runtime_dir}``) in every string of the
    config, so a driver and the simulator can name one path in a directory
    only known at start-up."""
    token = "{" + name + "}"

    def walk(o: Any) -> Any:
        if isinstance(o, str):
            return o.replace(token, value)
        if isinstance(o, dict):
            for k, v in o.items():
                o[k] = walk(v)
        elif isinstance(o, list):
            o[:] = [walk(v) for v in o]
        return o
    sections = [cfg.daemon, cfg.store] + ([cfg.simulator] if cfg.simulator else [])
    for sec in sections + [s for inst in cfg.instances for s in (inst.section, inst.framework)]:
        walk(sec._data)


def load(path: str | Path) -> Config:
    """Parse and structure a config file; plugin keys are checked later by
    the plugins themselves (see :func:`lathed.supervisor.build`)."""
    path = Path(path)
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such config file") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: cannot read config file: {e}") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: not valid TOML: {e}") from None

    for key, value in raw.items():
        if key not in TOP_TABLES:
            raise ConfigError(f"{path}: [{key}]: unknown table; allowed: {', '.join(TOP_TABLES)}")
        if not isinstance(value, dict):
            raise ConfigError(f"{path}: {key}: expected a table, got {value!r}")

    cfg = Config(path=path, daemon=Section(path, "daemon", raw.get("daemon", {})),
                 simulator=Section(path, "simulator", raw["simulator"]) if "simulator" in raw else None,
                 store=Section(path, "store", raw.get("store", {})))
    for category in CATEGORIES:
        for name, table in raw.get(category, {}).items():
            tname = f"{category}.{name}"
            if not isinstance(table, dict):
                raise ConfigError(f"{path}: [{category}] {name}: expected a table [{tname}], got {table!r}")
            if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_-]*", name):
                raise ConfigError(f"{path}: [{tname}]: instance name must start with a letter and use "
                                  "letters, digits, '_' or '-'")
            full = Section(path, tname, table)
            fw = Section(path, tname, {k: v for k, v in table.items() if k in FRAMEWORK_KEYS})
            plugin = fw.getstr("plugin")
            cfg.instances.append(Instance(category, name, plugin, full.without(*FRAMEWORK_KEYS), fw))
    return cfg
