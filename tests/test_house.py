"""The house rules of issue 42, read from the code: no import circle, no file over 600 lines
in lathed/ or plugins/, no probe of a base class's method (docs/plugins.md)."""
from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MAX_LINES = 600


def _modules() -> dict[str, Path]:
    """Module name -> file, for lathed (its package) and plugins (installed as lathed_plugins)."""
    out = {}
    for top, pkg in (("lathed", "lathed"), ("plugins", "lathed_plugins")):
        for p in sorted((ROOT / top).rglob("*.py")):
            parts = list(p.relative_to(ROOT / top).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join([pkg, *parts])] = p
    return out


def _imports(name: str, path: Path, known: set[str]) -> set[str]:
    """The known modules ``name`` imports anywhere in its file (in a function too: a hidden
    import is still an import), a package's ``from x import y`` resolved to x.y where that is
    a module."""
    tree = ast.parse(path.read_text(), str(path))
    is_pkg = path.name == "__init__.py"
    base = name.split(".") if is_pkg else name.split(".")[:-1]
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                anchor = base[:len(base) - node.level + 1]
                mod = ".".join(anchor + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            targets = [mod] + [f"{mod}.{a.name}" for a in node.names]
        else:
            continue
        for t in targets:
            # an import of a.b.c runs a and a.b too; only the deepest known module is an edge of
            # this file's own making (a package's __init__ is its own node)
            while t and t not in known:
                t = t.rpartition(".")[0]
            if t and t != name:
                out.add(t)
    return out


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_circle():
    mods = _modules()
    known = set(mods)
    graph = {name: _imports(name, path, known) for name, path in mods.items()}
    # a package's __init__ re-exporting its submodules, which import their siblings through the
    # package, is the package's own business: an edge from a submodule to its own parent
    # package is dropped (it resolves to the sibling the parent names)
    for name in graph:
        graph[name] = {t for t in graph[name] if not name.startswith(t + ".")}
    assert _cycles(graph) == []


def test_no_file_over_600_lines():
    long = {str(p.relative_to(ROOT)): n for p in _modules().values()
            if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert long == {}, f"over {MAX_LINES} lines: {long}"


def test_no_probe_of_a_base_class_method():
    """Every optional method of a plugin's base class has a default there: calling it needs no
    getattr/hasattr probe (docs/plugins.md)."""
    from lathed.analysis.chatter.base import RevolutionDetector
    from lathed.analyzer import Analyzer
    from lathed.driver import Driver
    # a plugin's chatter detector subclasses RevolutionDetector (lathed.plugins checks): its
    # methods and the rules' it inherits are there to call
    names = {n for cls in (Driver, Analyzer, *RevolutionDetector.__mro__[:-1])
             for n in vars(cls) if not n.startswith("__")}
    probe = re.compile(r"\b(?:getattr|hasattr)\([^,()]+,\s*[\"'](\w+)[\"']")
    found = []
    for p in _modules().values():
        if p.name in ("driver.py", "analyzer.py") or p.parent.name == "chatter" and p.name in ("base.py", "rules.py"):
            continue
        for i, line in enumerate(p.read_text().splitlines(), 1):
            for m in probe.finditer(line):
                if m[1] in names:
                    found.append(f"{p.relative_to(ROOT)}:{i}: {m[0]}")
    assert found == []
