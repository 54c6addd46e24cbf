"""Thermal model versions survive a power cut or a kill mid-save (issue 17 item 2)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

from lathed.analysis.thermal import eq14_model, load_model, save_model
from lathed.config import Section
from lathed_plugins.thermal import ThermalAnalyzer

KILLED_MID_SAVE = """
import os, signal, sys
from lathed.analysis.thermal import eq14_model, save_model
os.fsync = lambda fd: os.kill(os.getpid(), signal.SIGKILL)   # the power goes after the bytes are written
save_model(eq14_model(), sys.argv[1])
"""


class Log:
    def __init__(self):
        self.lines = []

    def error(self, event, **kw):
        self.lines.append((event, kw))


def analyzer(state: Path):
    a = ThermalAnalyzer("thermal", Section("f.toml", "analyzer.thermal", {"input": "temps", "machine": "lathe"}))
    records = []
    a.ctx = SimpleNamespace(store=SimpleNamespace(path=state / "lathed.db"), log=Log(), plugins=None,
                            record=lambda kind, payload: records.append((kind, payload)))
    return a, records


def test_a_save_killed_mid_write_leaves_the_previous_version_in_use(tmp_path):
    models = tmp_path / "thermal-models"
    models.mkdir()
    save_model(eq14_model(), models / "thermal-v1.toml", meta={"created": 1.0})
    r = subprocess.run([sys.executable, "-c", KILLED_MID_SAVE, str(models / "thermal-v2.toml")],
                       cwd=Path(__file__).parents[1])
    assert r.returncode == -9
    assert sorted(p.name for p in models.glob("thermal-v*.toml")) == ["thermal-v1.toml"]
    a, records = analyzer(tmp_path)
    a._load_newest()
    assert a.model_name == "thermal-v1.toml" and records == []


def test_a_damaged_newest_version_falls_back_to_the_previous_and_says_so(tmp_path):
    models = tmp_path / "thermal-models"
    models.mkdir()
    save_model(eq14_model(), models / "thermal-v1.toml")
    save_model(eq14_model(), models / "thermal-v2.toml")
    text = (models / "thermal-v2.toml").read_bytes()
    (models / "thermal-v2.toml").write_bytes(text[:len(text) // 2])    # what an in-place write leaves
    a, records = analyzer(tmp_path)
    a._load_newest()
    assert a.model_name == "thermal-v1.toml"
    assert load_model(models / "thermal-v1.toml").to_dict() == a.model.to_dict()
    assert [(k, p["file"], p["using"]) for k, p in records] == [("thermal_model_unreadable", "thermal-v2.toml",
                                                                 "thermal-v1.toml")]
    assert a.ctx.log.lines[0][0] == "thermal_model_unreadable"
