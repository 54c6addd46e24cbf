"""docs/configuration.md against the code: every key a table's code reads is in the reference's
sample block for that table, and every key of a block is one the code reads.

The code's keys are the string literals passed to a config Section's getters (found in the
source, so a key read only on a rare path still counts). Tables whose keys are names the user
chooses (a register map, MTConnect items, detector parameters, plausibility rules) are checked
by their entries' fields, not their names."""
from __future__ import annotations

import ast
import re
import tomllib
from pathlib import Path

from tests.conftest import ROOT

REFERENCE = ROOT / "docs" / "configuration.md"
GETTERS = {"get", "getstr", "getint", "getfloat", "getbool", "getduration", "getlist", "getsection", "has_section"}
SECTION_MAKERS = {"getsection", "subsections", "without"}
SECTION_ATTRS = {"daemon", "store", "simulator", "framework", "section"}
# tables named by the user's own keys: their entries' fields are keys, their names are not
USER_NAMED = {"registers", "items", "params", "plausible", "identity",   # identity: by [identification]'s keys
              "nodes", "namespaces", "states"}
# ... of which these also take keys of their own beside the named entries (plausible's confirm)
OWN_SCALARS = {"plausible"}
# keys a module reads through a helper with a computed name (a loop over a tuple of names)
INDIRECT = {"mqtt_sink": {"ca_file", "cert_file", "key_file"},
            "framework": {"manufacturer", "model", "serial_number"}}
# modules a plugin reads part of its table through (its identity registers, a protocol's session,
# its map, the CNC's shared keys, suppression's strategies)
HELPER_MODULES = {"modbus_cnc": ("lathed/cnc.py", "lathed/modbus_identity.py"),
                  "opcua_cnc": ("lathed/cnc.py", "lathed/ua_session.py", "lathed/ua_map.py", "lathed/ua_alarms.py"),
                  "suppression": ("plugins/suppression_strategies.py",)}
FRAMEWORK_MODULES = ("lathed/config.py", "lathed/supervisor.py", "lathed/safety.py", "lathed/plausible.py",
                     "lathed/driver.py", "lathed/analyzer.py")


def _section_names(fn: ast.AST) -> set[str]:
    """Names in a function bound to a config Section: annotated so, or made by a Section method."""
    names = {a.arg for a in fn.args.args + fn.args.kwonlyargs
             if a.annotation is not None and "Section" in ast.unparse(a.annotation)}
    changed = True
    while changed:
        changed = False
        for node in ast.walk(fn):
            if isinstance(node, ast.Assign) and len(node.targets) == 1:
                target, value = node.targets[0], node.value
            elif isinstance(node, ast.AnnAssign):
                target, value = node.target, node.value
            elif isinstance(node, (ast.For, ast.comprehension)):
                target, value = node.target, node.iter
            else:
                continue
            if not isinstance(target, ast.Name) or target.id in names or value is None:
                continue
            section = (isinstance(node, ast.AnnAssign) and "Section" in ast.unparse(node.annotation)) or (
                isinstance(value, ast.Attribute) and value.attr in SECTION_ATTRS)
            for sub in ast.walk(value):
                if isinstance(sub, ast.Call) and (
                        (isinstance(sub.func, ast.Attribute) and sub.func.attr in SECTION_MAKERS)
                        or (isinstance(sub.func, ast.Name) and sub.func.id == "Section")):
                    section = True
            if section:
                names.add(target.id)
                changed = True
    return names


def code_keys(path: Path) -> set[str]:
    """Every key a module reads from a config Section, as string literals in the source."""
    out: set[str] = set()
    for fn in ast.walk(ast.parse(path.read_text())):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        names = _section_names(fn)
        for node in ast.walk(fn):
            if not isinstance(node, ast.Call) or not node.args:
                continue
            literals = [a.value for a in node.args if isinstance(a, ast.Constant) and isinstance(a.value, str)]
            receiver = node.func.value if isinstance(node.func, ast.Attribute) else None
            getter = node.func.attr in GETTERS and (
                (isinstance(receiver, ast.Name) and receiver.id in names)
                or (isinstance(receiver, ast.Attribute) and receiver.attr in SECTION_ATTRS)) if receiver else False
            helper = isinstance(node.func, ast.Name) and isinstance(node.args[0], ast.Name) \
                and node.args[0].id in names
            if getter and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str):
                out.add(node.args[0].value)
            elif helper:
                out.update(literals)
    return out


def doc_keys(table: dict, named: str | None = None) -> set[str]:
    """The keys of a sample table; ``named``: it is a table of user-named entries (USER_NAMED)."""
    out: set[str] = set()
    for k, v in table.items():
        if named is None or (named in OWN_SCALARS and not isinstance(v, dict)):
            out.add(k)
        if isinstance(v, dict):
            out |= doc_keys(v) if named else doc_keys(v, k if k in USER_NAMED else None)
    return out


def blocks() -> list[dict]:
    text = REFERENCE.read_text()
    return [tomllib.loads(b) for b in re.findall(r"```toml\n(.*?)```", text, re.S)]


def instances(block: dict) -> list[dict]:
    return [t for cat in ("machine", "sensor", "analyzer") for t in block.get(cat, {}).values()]


def plugin_modules() -> dict[str, Path]:
    """The built-in plugin types, from the entry points the package declares."""
    eps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["entry-points"]["lathed.plugins"]
    return {name: ROOT / "plugins" / (target.rsplit(".", 1)[1] + ".py") for name, target in eps.items()}


FRAMEWORK_TABLES = {"limits", "plausible", "identification"}


def framework_block() -> dict:
    for b in blocks():
        for inst in instances(b):
            if FRAMEWORK_TABLES <= set(inst):
                return inst
    raise AssertionError("docs/configuration.md has no block of the framework's keys (limits, plausible, ...)")


def test_every_plugin_has_a_block_with_exactly_the_keys_its_code_reads():
    framework = set().union(*(code_keys(ROOT / m) for m in FRAMEWORK_MODULES)) | {"plugin"}
    documented: dict[str, set[str]] = {}
    for b in blocks():
        for inst in instances(b):
            if FRAMEWORK_TABLES <= set(inst):
                continue
            documented.setdefault(inst["plugin"], set()).update(doc_keys(inst))
    problems = []
    for name, module in sorted(plugin_modules().items()):
        if name not in documented:
            problems.append(f"{name}: no sample block in docs/configuration.md")
            continue
        code = code_keys(module) | INDIRECT.get(name, set()) | set().union(
            *(code_keys(ROOT / m) for m in HELPER_MODULES.get(name, ())))
        doc = documented[name] - {"plugin"}
        if missing := sorted(code - doc - framework):
            problems.append(f"{name}: read by {module.relative_to(ROOT)} but not in the reference: {missing}")
        if unknown := sorted(doc - code - framework):
            problems.append(f"{name}: in the reference but read nowhere: {unknown}")
    assert not problems, "\n".join(problems)


def test_the_framework_block_has_exactly_the_frameworks_keys():
    code = set().union(*(code_keys(ROOT / m) for m in FRAMEWORK_MODULES)) | {"plugin"} | INDIRECT["framework"]
    doc = doc_keys(framework_block())
    assert not (code - doc), f"framework keys missing from docs/configuration.md: {sorted(code - doc)}"
    assert not (doc - code), f"framework keys in docs/configuration.md read nowhere: {sorted(doc - code)}"


def test_the_daemon_store_and_simulator_tables_are_documented_exactly():
    doc = {}
    for b in blocks():
        for table in ("daemon", "store", "simulator"):
            if table in b:
                doc.setdefault(table, set()).update(doc_keys(b[table]))
    daemon = code_keys(ROOT / "lathed" / "daemon.py")
    assert doc.get("daemon", set()) | doc.get("store", set()) == daemon
    assert doc.get("simulator") == code_keys(ROOT / "lathed" / "sim" / "launch.py")


def test_the_extractor_finds_keys_read_through_a_section():
    src = ("from lathed.config import Section\n"
           "def f(section: Section, other):\n"
           "    a = section.getstr('host')\n"
           "    sub = section.getsection('limits')\n"
           "    sub.getfloat('rpm_max')\n"
           "    other.get('not_a_key')\n"
           "    _file(section, here, 'ca_file')\n")
    import tempfile
    with tempfile.NamedTemporaryFile("w", suffix=".py", delete=False) as f:
        f.write(src)
    assert code_keys(Path(f.name)) == {"host", "limits", "rpm_max", "ca_file"}
