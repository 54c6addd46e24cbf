"""constraints.txt, the tested set of exact versions for field installs, pins
every runtime dependency of pyproject.toml, and those of the optional extras a
field install may take (postgres, plots), within its declared range."""
from __future__ import annotations

import tomllib
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parent.parent


def pins() -> dict[str, str]:
    found: dict[str, str] = {}
    for n, line in enumerate((ROOT / "constraints.txt").read_text().splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        name, sep, version = line.partition("==")
        assert sep and version.strip(), f"constraints.txt:{n}: {line!r} is not an exact pin (name==version)"
        key = canonicalize_name(name.strip())
        assert key not in found, f"constraints.txt:{n}: {name.strip()} pinned twice"
        found[key] = version.strip()
    return found


FIELD_EXTRAS = ("postgres", "plots", "opcua", "mqtt", "recordings", "audio")     # not "test": a field install has no test tools


def test_every_runtime_dependency_is_pinned_within_its_range():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    pinned = pins()
    extras = project["optional-dependencies"]
    assert set(FIELD_EXTRAS) <= set(extras), f"pyproject.toml lacks the extras {FIELD_EXTRAS}"
    for spec in project["dependencies"] + [s for e in FIELD_EXTRAS for s in extras[e]]:
        req = Requirement(spec)
        key = canonicalize_name(req.name)
        assert key in pinned, f"{req.name} (pyproject.toml) has no pin in constraints.txt"
        assert req.specifier.contains(pinned[key], prereleases=True), \
            f"constraints.txt pins {req.name}=={pinned[key]}, outside pyproject.toml's {req.specifier}"
