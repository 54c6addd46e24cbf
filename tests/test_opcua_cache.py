"""lathed-opcua's address space cache (lathed.opcua.spacecache, docs/opcua.md): a start from the
cache serves the space a build makes, the data types registered alike; a damaged, stale or
untrusted cache is built again with a line saying why."""
from __future__ import annotations

import dataclasses
import gc
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("asyncua")
from lathed.opcua import spacecache  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def digest() -> str:
    """Every node of the space (attributes, references) and asyncua's registry of the NodeSets'
    data types, as JSON; times masked (a start writes its own)."""
    import asyncio

    from asyncua import Server, ua

    from lathed import log as logmod

    def cls(c) -> object:
        if dataclasses.is_dataclass(c):
            return [c.__name__, [[f.name, str(f.type)] for f in dataclasses.fields(c)]]
        if hasattr(c, "__members__"):
            return [c.__name__, c.__mro__[1].__name__, sorted([k, int(v.value)] for k, v in c.__members__.items())]
        return repr(c)

    async def go() -> dict:
        server = Server()
        ns = await spacecache.open_space(server, spacecache.default_dir())
        nodes = {}
        for nid, nd in server.iserver.aspace._nodes.items():
            attrs = {int(a): repr(av.value.Value) if av.value is not None else None for a, av in nd.attributes.items()}
            refs = sorted(repr((r.ReferenceTypeId, r.IsForward, r.NodeId, r.BrowseName, r.NodeClass, r.TypeDefinition))
                          for r in nd.references)
            nodes[nid.to_string()] = [attrs, refs]
        types = {name: sorted([k.to_string(), repr(cls(v))] for k, v in getattr(ua, name).items() if k.NamespaceIndex)
                 for name in ("extension_objects_by_datatype", "extension_objects_by_typeid", "enums_by_datatype",
                              "basetype_by_datatype")}
        return {"ns": ns, "namespaces": await server.get_namespace_array(), "nodes": nodes, "types": types}

    logmod.setup("info")
    return re.sub(r"datetime\.datetime\([^)]*\)", "T", json.dumps(asyncio.run(go()), sort_keys=True))


def start(cache: Path) -> tuple[str, str]:
    """A fresh process's address space over ``cache``: its digest and its log."""
    code = ("import sys; sys.path.insert(0, 'tests'); import test_opcua_cache as t; "
            "open(sys.argv[1], 'w').write(t.digest())")
    out = cache.parent / f"digest-{len(list(cache.parent.glob('digest-*')))}.json"
    r = subprocess.run([sys.executable, "-c", code, str(out)], cwd=ROOT, capture_output=True, text=True, timeout=300,
                       env={**os.environ, "CACHE_DIRECTORY": str(cache)})
    assert r.returncode == 0, r.stderr[-3000:]
    return out.read_text(), r.stdout + r.stderr


def cache_log(log: str) -> list[dict]:
    lines = [json.loads(ln) for ln in log.splitlines() if ln.startswith("{")]
    return [e for e in lines if e["event"].startswith("address_space")]


@pytest.fixture(scope="module")
def starts(tmp_path_factory):
    """A start over a damaged cache file (built again), then one from the cache it wrote."""
    cache = tmp_path_factory.mktemp("uacache") / "cache"
    cache.mkdir(mode=0o700)
    (cache / spacecache.NAME).write_bytes(spacecache.MAGIC + spacecache.key().encode() + b"\n" + b"\x80\x05garbage")
    cold, cold_log = start(cache)
    warm, warm_log = start(cache)
    return cache, cold, cold_log, warm, warm_log


def test_a_damaged_cache_is_built_again_with_a_line_saying_why(starts):
    cache, _, cold_log, _, warm_log = starts
    assert [(e["event"], e["why"].split(":")[:2]) for e in cache_log(cold_log)] == \
        [("address_space_built", ["corrupt", " UnpicklingError"])]
    assert [e["event"] for e in cache_log(warm_log)] == ["address_space_loaded"]
    assert [p.name for p in cache.iterdir()] == [spacecache.NAME]      # written in place, no temporary left


def test_a_start_from_the_cache_serves_what_a_build_makes(starts):
    _, cold, _, warm, _ = starts
    a, b = json.loads(cold), json.loads(warm)
    assert len(a["nodes"]) > 7000 and len(a["types"]["extension_objects_by_datatype"]) > 10
    assert a["ns"] == b["ns"] and a["namespaces"] == b["namespaces"]
    assert a["types"] == b["types"]       # the NodeSets' structures, enumerations, aliases registered alike
    assert a["nodes"].keys() == b["nodes"].keys()
    assert [k for k in a["nodes"] if a["nodes"][k] != b["nodes"][k]] == []


def test_a_stale_or_untrusted_cache_is_not_read(starts, tmp_path):
    cache = starts[0]
    body = (cache / spacecache.NAME).read_bytes()
    magic, made, rest = body.split(b"\n", 2)
    path = tmp_path / spacecache.NAME
    path.write_bytes(body)
    path.chmod(0o600)
    tmp_path.chmod(0o700)
    cached, why = spacecache.read(path, made.decode())
    gc.unfreeze()     # read froze what was alive (for a server process); this test worker goes on
    assert why == "" and set(cached) == {"nodes", "namespaces", "types"}
    assert spacecache.read(path, "0" * 64) == (None, "stale: made by another lathed, asyncua, Python or NodeSets")
    path.write_bytes(body[:len(body) // 2])
    assert spacecache.read(path, made.decode())[1].startswith("corrupt: ")
    path.write_bytes(b"something else\n")
    assert spacecache.read(path, made.decode()) == (None, "corrupt: not a lathed-opcua address space")
    path.write_bytes(body)
    path.chmod(0o666)    # anyone could have put code there for pickle to run
    assert spacecache.read(path, made.decode())[1].startswith("not trusted")
    assert spacecache.read(tmp_path / "none", made.decode()) == (None, "none yet")


def test_the_key_follows_what_the_space_is_made_of(monkeypatch):
    import asyncua
    k = spacecache.key()
    monkeypatch.setattr(asyncua, "__version__", asyncua.__version__ + ".1")
    assert spacecache.key() != k
    monkeypatch.undo()
    monkeypatch.setattr(spacecache.nodesets, "FILES", spacecache.nodesets.FILES[:-1])
    assert spacecache.key() != k


def test_the_cache_directory_is_systemds_else_the_users(monkeypatch, tmp_path):
    monkeypatch.setenv("CACHE_DIRECTORY", f"{tmp_path}/a:{tmp_path}/b")
    assert spacecache.default_dir() == tmp_path / "a"
    monkeypatch.delenv("CACHE_DIRECTORY")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert spacecache.default_dir() == tmp_path / "lathed"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path))
    assert spacecache.default_dir() == tmp_path / ".cache" / "lathed"
