"""Adopted stability models on disk: one JSON file per adoption, versioned.

    <state_dir>/stability-models/<machine>-v<N>.json

A file holds the model adopted (modes, Kf, process damping), the model it
was refitted from (``base``; null for a model learned from the cuts alone),
the set-up (tool, material) and the figures that justified it.  An adopted model is used only while the configured
model and set-up are the ones it was refitted from: a new tap test or
another material in the configuration supersedes it.  Written with
lathed.atomic (a power cut leaves the old or the new file).
"""
from __future__ import annotations

import json
import re
from pathlib import Path

from lathed.analysis.stability.model import StabilityModel
from lathed.atomic import write_atomic

FORMAT = "lathed-stability-model"


def versions(directory: Path, machine: str) -> list[Path]:
    """The machine's model files, oldest first."""
    pat = re.compile(rf"^{re.escape(machine)}-v(\d+)\.json$")
    found = [(int(m[1]), p) for p in directory.glob(f"{machine}-v*.json") if (m := pat.match(p.name))]
    return [p for _, p in sorted(found)]


def save(directory: Path, machine: str, doc: dict) -> Path:
    """Write ``doc`` (with ``model`` and ``base`` as StabilityModel.to_json) as the next version."""
    directory.mkdir(parents=True, exist_ok=True, mode=0o750)
    have = versions(directory, machine)
    n = 1 + (int(have[-1].stem.rsplit("-v", 1)[1]) if have else 0)
    path = directory / f"{machine}-v{n}.json"
    write_atomic(path, (json.dumps({"format": FORMAT, **doc}, indent=1) + "\n").encode())
    return path


def load(path: Path) -> tuple[StabilityModel, dict]:
    """(adopted model, the whole document); ValueError naming what is wrong."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{path.name} is not readable JSON: {e}") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ValueError(f"{path.name} is not a {FORMAT} file")
    try:
        model = StabilityModel.from_json(doc["model"])
        if doc["base"] is not None:          # null: learned from the cuts, no tap test
            StabilityModel.from_json(doc["base"])
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{path.name}: malformed model: {type(e).__name__}: {e}") from None
    return model, doc
