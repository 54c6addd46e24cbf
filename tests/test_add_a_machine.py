"""Does exactly what docs/plugins.md "Add a machine" says: the plugin file and the
config table taken from that page, the stand-in saw from it too, then
the daemon and lathectl as an operator would run them."""
from __future__ import annotations

import json
import re
import subprocess
import sys

from tests.conftest import BIN, ROOT, Daemon, free_port, wait_until


def readme_blocks() -> list[tuple[str, str]]:
    text = (ROOT / "docs" / "plugins.md").read_text()
    section = text.split("<!-- BEGIN add-a-machine", 1)[1].split("<!-- END add-a-machine -->", 1)[0]
    return re.findall(r"```(\w+)\n(.*?)```", section, re.S)


def test_dropin_plugin_from_the_readme(tmp_path):
    blocks = readme_blocks()
    assert [lang for lang, _ in blocks] == ["python", "toml", "python"]
    (_, plugin), (_, table), (_, fake) = blocks
    assert "etc/plugins.d/bandsaw.py" in (ROOT / "docs" / "plugins.md").read_text()
    dropin = tmp_path / "plugins.d"
    dropin.mkdir()
    (dropin / "bandsaw.py").write_text(plugin)
    (tmp_path / "fake_saw.py").write_text(fake)
    port = free_port()
    assert "port = 15030" in table
    cfg = tmp_path / "lathed.toml"
    cfg.write_text(f"""[daemon]
plugin_dirs = ["plugins.d"]
state_dir = "{tmp_path / 'state'}"
runtime_dir = "{tmp_path / 'run'}"

{table.replace("port = 15030", f"port = {port}")}""")
    check = subprocess.run([str(BIN / "lathed"), "--check-config", str(cfg)], capture_output=True, text=True)
    assert check.returncode == 0, check.stderr
    saw = subprocess.Popen([sys.executable, str(tmp_path / "fake_saw.py"), str(port)])
    d = Daemon(cfg, tmp_path / "run" / "lathed.sock")
    try:
        d.wait_ready()
        plugins = json.loads(d.ctl("plugins", "--json").stdout)
        mine = next(p for p in plugins if p["name"] == "bandsaw")
        assert mine["state"] == "loaded" and mine["provides"] == ["bandsaw"], mine

        def saw_entry():
            return json.loads(d.ctl("machines", "--json").stdout)[0]
        m = wait_until(lambda: (e := saw_entry())["model"]["state"] == "running" and e, timeout=10,
                       what="saw running")
        assert m["name"] == "saw" and m["kind"] == "saw" and m["spindle_rpm"] == 1450.0
        assert not m["model"]["spindle_rpm"]["stale"]
        assert "saw" in d.ctl("machines").stdout
        # the stand-in's count goes up every 5 s: a part completed is recorded
        wait_until(lambda: json.loads(d.ctl("events", "--json", "--kind", "part_completed").stdout),
                   timeout=10, what="part_completed event")
        # stop the saw: disconnected, values stale; start it: back
        saw.terminate()
        saw.wait(5)
        wait_until(lambda: saw_entry()["model"]["state"] == "disconnected", timeout=10, what="saw disconnected")
        line = next(x for x in d.ctl("machines").stdout.splitlines() if x.startswith("saw"))
        assert "?" in line
        saw = subprocess.Popen([sys.executable, str(tmp_path / "fake_saw.py"), str(port)])
        wait_until(lambda: saw_entry()["model"]["state"] == "running", timeout=10, what="saw back")
    finally:
        d.stop()
        saw.terminate()
        saw.wait(5)
