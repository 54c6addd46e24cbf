"""Thermal model versions survive a power cut or a kill mid-save (issue 17 item 2)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from lathed.analysis.thermal import eq14_model, load_model, save_model
from lathed.config import ConfigError, Section
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


MODEL = """format = 1
source = "fit"
intercept_um = -221.94
notes = []
[[terms]]
effect = "linear"
coef = [-9.11]
sensor = "t_front_bearing_c"
params = {}
[[terms]]
effect = "lag"
coef = [6.06]
sensor = "t_motor_c"
params = { tau_s = 600.0 }
"""


@pytest.mark.parametrize("edit, problem", [
    # each gave a traceback (AttributeError), a bare KeyError 'sensor', or was taken (nan, format 2)
    ((MODEL, 'format = 1\nintercept_um = 0.0\nterms = [1]\n'), "term 1: expected a table, got 1"),
    (('sensor = "t_front_bearing_c"\n', ""), "term 1 (linear): missing key 'sensor'"),
    (("intercept_um = -221.94", "intercept_um = nan"), "intercept_um: expected a finite number, got nan"),
    (("coef = [-9.11]", "coef = [inf]"), "term 1 (linear) coef[0]: expected a finite number, got inf"),
    (("tau_s = 600.0", "tau_s = nan"), "term 2 (lag) params.tau_s: expected a finite number, got nan"),
    (("tau_s = 600.0", "tau = 600.0"), "term 2 (lag): missing key 'tau_s'"),
    (("format = 1", "format = 2"), "format: 2 is not a thermal model format this lathed reads (1)"),
    (("intercept_um = -221.94\n", ""), "intercept_um: missing key"),
])
def test_a_malformed_model_file_is_one_line_naming_the_key(tmp_path, capsys, edit, problem):
    path = tmp_path / "model.toml"
    path.write_text(MODEL)
    assert len(load_model(path).terms) == 2
    text = MODEL.replace(*edit, 1)
    assert text != MODEL
    path.write_text(text)
    with pytest.raises(ValueError) as e:
        load_model(path)
    assert str(e.value) == problem
    # the config and lathectl name the file, in one line
    with pytest.raises(ConfigError) as e:
        ThermalAnalyzer("thermal", Section(str(tmp_path / "f.toml"), "analyzer.thermal",
                                           {"input": "temps", "machine": "lathe", "model": "model.toml"}))
    assert str(e.value) == f"{tmp_path / 'f.toml'}: [analyzer.thermal] model: cannot load thermal model {path}: {problem}"
    from lathed.cli.analyze_thermal import run
    csv = tmp_path / "run.csv"
    csv.write_text("time_s,t_front_bearing_c,t_motor_c,displacement_um\n" +
                   "".join(f"{i * 60},{20 + i * 0.1},{20 + i * 0.2},{-i * 0.5}\n" for i in range(100)))
    args = SimpleNamespace(train=[str(csv)], test=None, model=str(path), max_sensors=2, split=None)
    assert run(args) == 65
    assert capsys.readouterr().err == f"lathectl: cannot load thermal model {path}: {problem}\n"


@pytest.mark.parametrize("sign", [0.3, 0.0, -0.5])
def test_sign_is_a_direction_not_a_scale(sign):
    # 0.3 passed the [-1, 1] range and compensated 30 % of the growth without a word
    with pytest.raises(ConfigError, match=r"\[analyzer.thermal\] sign: expected -1 or 1 \(the offset's direction"):
        ThermalAnalyzer("thermal", Section("f.toml", "analyzer.thermal", {"input": "temps", "machine": "lathe",
                                                                          "sign": sign}))
    assert ThermalAnalyzer("thermal", Section("f.toml", "analyzer.thermal",
                                              {"input": "temps", "machine": "lathe", "sign": 1.0})).sign == 1.0
