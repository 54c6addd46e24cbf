"""A control request's arguments, read like a config table.

Every handler reads its ``args`` through :class:`Args`: the typed, ranged
getters of :class:`lathed.config.Section` (ints, finite floats, choices),
plus bounded strings, lists and maps, then :meth:`Args.check_unused`
refuses any key it did not read, so a typo never silently falls back to a
default. All of it runs before the handler does any work; a wrong argument
is one line back to the client (a :class:`RequestError`), never an
"internal error" with a traceback in the log.

JSON ``null`` counts as "not given" (lathectl sends its unset options as
null).
"""
from __future__ import annotations

import math
from typing import Any

from lathed.config import _REQUIRED, Section, _range_text, finite
from lathed.control import ArgumentError, RequestError

MAX_TEXT = 256        # names, tools, materials, inspectors: one line of text
MAX_ITEMS = 64        # entries of a list or map argument
MAX_INT = (1 << 63) - 1   # what SQLite stores; anything larger is no id or count
_SHOWN = 60           # characters of a bad value quoted back in the error


def shown(v: Any) -> str:
    """A bad value quoted in an error line, cut short: the line stays one short line."""
    try:
        text = repr(v)
    except (RecursionError, ValueError):   # a 5000-digit int, a structure nested too deep
        return f"a {type(v).__name__}"
    return text if len(text) <= _SHOWN else text[:_SHOWN] + f"... ({len(text)} characters)"


class Args(Section):
    """The ``args`` of one request to command ``cmd``."""

    def __init__(self, cmd: str, data: dict[str, Any]):
        super().__init__("", cmd, data)

    def error(self, key: str | None, problem: str) -> RequestError:
        return ArgumentError(f"{self.table}: {key}: {problem}" if key else f"{self.table}: {problem}")

    def _raw(self, key: str, default: Any) -> Any:
        self._read.add(key)
        v = self._data.get(key)
        if v is None:
            if default is _REQUIRED:
                raise self.error(key, "missing; it is required")
            return default
        return v

    # The base getters quote the value with repr(); keep those lines short.
    def getint(self, key: str, default: Any = _REQUIRED, minval: int | None = 0,
               maxval: int | None = None) -> int:
        v = self._short(super().getint, key, default, f"an integer{_range_text(minval, maxval)}",
                        minval=minval, maxval=maxval)
        if v is not None and abs(v) > MAX_INT:
            raise self.error(key, f"{shown(v)} is larger than any stored id or count (at most 2**63 - 1)")
        return v

    def getfloat(self, key: str, default: Any = _REQUIRED, minval: float | None = None,
                 maxval: float | None = None, above: float | None = None) -> float:
        want = f"a finite number{_range_text(minval, maxval)}" + (f" > {above}" if above is not None else "")
        return self._short(super().getfloat, key, default, want, minval=minval, maxval=maxval, above=above)

    def getbool(self, key: str, default: Any = _REQUIRED) -> bool:
        return self._short(super().getbool, key, default, "true or false")

    def _short(self, getter, key: str, default: Any, want: str, **kw) -> Any:
        try:
            return getter(key, default, **kw)
        except RequestError as e:
            if len(str(e)) <= 200:
                raise
            raise self.error(key, f"expected {want}, got {shown(self._data.get(key))}") from None

    def getstr(self, key: str, default: Any = _REQUIRED, choices: tuple[str, ...] | None = None,
               maxlen: int = MAX_TEXT) -> str:
        v = self._raw(key, default)
        if v is default and default is not _REQUIRED:
            return v
        return self._text(key, v, choices, maxlen)

    def _text(self, key: str, v: Any, choices: tuple[str, ...] | None = None, maxlen: int = MAX_TEXT) -> str:
        if not isinstance(v, str):
            raise self.error(key, f"expected a string, got {type(v).__name__} {shown(v)}")
        if choices is not None:
            if v not in choices:
                raise self.error(key, f"{shown(v)} is not allowed; allowed: {', '.join(choices)}")
            return v
        if not v:
            raise self.error(key, "empty; give a name")
        if len(v) > maxlen:
            raise self.error(key, f"{len(v)} characters; at most {maxlen} allowed")
        try:
            v.encode("utf-8")
        except UnicodeEncodeError:   # a lone surrogate from a JSON \ud800 escape: not storable text
            raise self.error(key, f"not valid text: {shown(v)}") from None
        if not v.isprintable():      # newlines, NUL...: these end up in records, logs and CSV exports
            raise self.error(key, f"not printable text (control characters): {shown(v)}")
        return v

    def getlist(self, key: str, default: Any = _REQUIRED, item: type = str, maxitems: int = MAX_ITEMS) -> list:
        v = self._raw(key, default)
        if v is default and default is not _REQUIRED:
            return v
        if not isinstance(v, list):
            raise self.error(key, f"expected a list, got {type(v).__name__} {shown(v)}")
        if len(v) > maxitems:
            raise self.error(key, f"{len(v)} items; at most {maxitems} allowed")
        return [self._item(f"{key}[{i}]", x, item) for i, x in enumerate(v)]

    def getmap(self, key: str, default: Any = _REQUIRED, item: Any = float, minval: float | None = None,
               maxval: float | None = None, maxitems: int = MAX_ITEMS) -> dict[str, Any]:
        """An object {name: value}: names are short text, values ``item`` (float, int, str, or
        ``(float, str)`` for either) within [minval, maxval]."""
        v = self._raw(key, default)
        if v is default and default is not _REQUIRED:
            return v
        if not isinstance(v, dict):
            raise self.error(key, f"expected an object {{name: value}}, got {type(v).__name__} {shown(v)}")
        if len(v) > maxitems:
            raise self.error(key, f"{len(v)} entries; at most {maxitems} allowed")
        out = {}
        for name, x in v.items():
            self._text(f"{key} name", name, maxlen=64)
            out[name] = self._item(f"{key}.{name}", x, item, minval, maxval)
        return out

    def _item(self, where: str, x: Any, item: Any, minval: float | None = None, maxval: float | None = None) -> Any:
        kinds = item if isinstance(item, tuple) else (item,)
        if str in kinds and isinstance(x, str):
            return self._text(where, x)
        number = isinstance(x, (int, float)) and not isinstance(x, bool)
        if int in kinds and number and isinstance(x, int) or float in kinds and number and finite(x):
            lo = -math.inf if minval is None else minval
            hi = math.inf if maxval is None else maxval
            if lo <= x <= hi:
                return x if isinstance(x, int) and int in kinds else float(x)
            raise self.error(where, f"{shown(x)} is out of range [{minval}, {maxval}]")
        want = " or ".join({int: "an integer", float: "a finite number", str: "a string"}[k] for k in kinds)
        raise self.error(where, f"expected {want}, got {type(x).__name__} {shown(x)}")

    def check_unused(self) -> None:
        unknown = [k for k in self._data if k not in self._read]
        if unknown:
            allowed = ", ".join(sorted(self._read)) or "none"
            raise self.error(None, f"unknown argument{'s' if len(unknown) > 1 else ''} "
                                   f"{', '.join(shown(k) for k in unknown[:5])}; allowed: {allowed}")

