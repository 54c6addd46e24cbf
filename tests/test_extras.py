"""PostgreSQL, plots, MQTT and OPC UA are extras (issue 17 item 5): without one, what
needs it says in one line which extra to install, and nothing else imports it."""
from __future__ import annotations

import subprocess
import sys

import pytest

from lathed.config import ConfigError, Section
from lathed.cli.main import main
from lathed_plugins import mqtt_sink
from lathed_plugins.mqtt_sink import MqttSink
from lathed_plugins.postgres_sink import PostgresSink
from tests.conftest import ROOT


@pytest.mark.parametrize("module, sink, table, keys, extra", [
    ("psycopg", PostgresSink, "analyzer.central", {"dsn": "host=db.plant dbname=lathed"}, "postgres"),
    ("aiomqtt", MqttSink, "analyzer.mqtt", {"host": "broker.plant"}, "mqtt"),
])
def test_a_sink_without_its_extra_is_one_config_line_naming_it(monkeypatch, module, sink, table, keys, extra):
    monkeypatch.setitem(sys.modules, module, None)      # as if the extra were not installed
    monkeypatch.setattr(mqtt_sink, "aiomqtt", None)     # and not imported by an earlier test
    sec = Section("plant.toml", table, keys)
    with pytest.raises(ConfigError) as e:
        sink("central", sec)
    msg = str(e.value)
    assert "\n" not in msg
    assert "plant.toml" in msg and f"[{table}]" in msg
    assert f"pip install 'lathed[{extra}]'" in msg


@pytest.mark.parametrize("what", [
    ["lobes", "--mode", "250,0.03,2e7", "--kf", "1e9"],
    ["thermal", str(ROOT / "tests" / "no_such_run.csv")],      # refused before the file is even read
])
def test_plot_without_matplotlib_is_one_line_naming_the_extra(what, monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "matplotlib", None)   # as if the plots extra were not installed
    png = tmp_path / "out.png"
    assert main(["analyze", *what, "--plot", str(png)]) == 69
    out, err = capsys.readouterr()
    assert out == ""
    assert err == "lathectl: --plot: matplotlib is not installed: pip install 'lathed[plots]'\n"
    assert not png.exists()


def test_plugins_load_without_importing_their_extras():
    # psycopg takes ~0.2 s to import: only a configured postgres_sink pays it (and aiomqtt, mqtt_sink)
    code = ("import sys; from lathed.plugins import load_all; loader = load_all([]);"
            "assert not [p.error for p in loader.plugins if p.error], loader.summary();"
            "print('postgres_sink' in loader.analyzer_types(), 'mqtt_sink' in loader.analyzer_types(),"
            "      'psycopg' in sys.modules, 'aiomqtt' in sys.modules)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT / "tests")
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["True", "True", "False", "False"]


def test_lathed_opcua_without_asyncua_is_one_line_naming_the_extra(monkeypatch, capsys):
    import lathed.opcua
    monkeypatch.setitem(sys.modules, "asyncua", None)    # as if the opcua extra were not installed
    assert lathed.opcua.main(["--port", "1"]) == 69
    out, err = capsys.readouterr()
    assert (out, err) == ("", "lathed-opcua: asyncua is not installed: pip install 'lathed[opcua]'\n")


def test_in_the_service_venv_a_missing_extra_says_make_install_with_those_it_has(monkeypatch, tmp_path):
    """Issue 39: an installed config's error said `pip install`, which the packaged venv is not
    meant for (`make install` rebuilds it with only the extras it is given)."""
    from lathed import extras
    (tmp_path / extras.INSTALL_MARK).write_text("prefix=/opt/plant\n")
    monkeypatch.setattr(sys, "prefix", str(tmp_path))
    monkeypatch.setattr(sys, "argv", ["/opt/plant/bin/lathed-opcua"])
    monkeypatch.setitem(sys.modules, "psycopg", None)
    # this venv has every extra but postgres: the line keeps them all
    assert extras.missing("psycopg") == (
        f"psycopg is not installed: in the service's venv ({tmp_path}) add it from the lathed source with "
        "`sudo make install PREFIX=/opt/plant EXTRAS=audio,mqtt,opcua,plots,postgres,recordings`, "
        "then `sudo systemctl restart lathed-opcua`")
    assert "pip install" not in extras.missing("psycopg")
    (tmp_path / extras.INSTALL_MARK).unlink()          # a venv of one's own: pip it is
    assert extras.missing("psycopg") == "psycopg is not installed: pip install 'lathed[postgres]'"
