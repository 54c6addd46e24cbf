"""Plugin loading: entry points, drop-ins, broken plugins reported and skipped."""
from __future__ import annotations

import inspect
import json

from lathed import hookspecs
from lathed.plugins import PluginLoader, load_all
from lathed.analysis.chatter.registry import make_detector
from tests.conftest import wait_until

GOOD = '''
from lathed import hookimpl
from lathed.driver import Driver
from lathed.bus import Sample
import asyncio

class Counter(Driver):
    role = "sensor"
    kind = "counter"
    def __init__(self, name, section):
        super().__init__(name, section)
        self.step = section.getfloat("step", 1.0, above=0)
        self.n = 0.0
    async def run(self):
        while True:
            self.n += self.step
            self.mark_data()
            self.ctx.bus.publish(Sample(self.name, "count", self.n, "", 0.0))
            await asyncio.sleep(0.05)

@hookimpl
def lathed_driver_types():
    return {"counter": Counter}
'''

BROKEN_IMPORT = "import definitely_not_a_module\n"
BROKEN_HOOK = '''
from lathed import hookimpl
@hookimpl
def lathed_driver_types():
    return ["not", "a", "dict"]
'''
CLASH = '''
from lathed import hookimpl
from lathed.driver import Driver
class Other(Driver):
    pass
@hookimpl
def lathed_driver_types():
    return {"modbus_cnc": Other}
'''
NOT_A_DRIVER = '''
from lathed import hookimpl
class Loose:
    async def run(self):
        pass
@hookimpl
def lathed_driver_types():
    return {"loose": Loose}
'''


def test_builtins_load_through_entry_points():
    loader = PluginLoader()
    loader.load_entry_points()
    assert {"modbus_cnc", "ds18b20_serial", "vibration_tcp"} <= set(loader.driver_types())
    for p in loader.plugins:
        assert p.origin.startswith("entry point")
        assert p.error is None, p


def test_dropin_good_and_broken(tmp_path):
    (tmp_path / "a_counter.py").write_text(GOOD)
    (tmp_path / "b_broken.py").write_text(BROKEN_IMPORT)
    (tmp_path / "c_badhook.py").write_text(BROKEN_HOOK)
    (tmp_path / "d_clash.py").write_text(CLASH)
    (tmp_path / "e_loose.py").write_text(NOT_A_DRIVER)
    loader = load_all([tmp_path])
    by = {p.name: p for p in loader.plugins}
    assert by["a_counter"].error is None and by["a_counter"].provides == ["counter"]
    assert by["b_broken"].error.startswith("ModuleNotFoundError: No module named 'definitely_not_a_module' at ")
    assert "b_broken.py:1" in by["b_broken"].error
    assert by["c_badhook"].error.startswith("TypeError: lathed_driver_types must return a dict, got list")
    assert "already provided by plugin 'modbus_cnc'" in by["d_clash"].error
    assert loader.driver_types()["modbus_cnc"].__name__ == "ModbusCNC"   # the clash did not replace it
    assert "counter" in loader.driver_types()
    # the contract is the base class's: a type outside it is refused at load, naming the base
    assert by["e_loose"].error.startswith("TypeError: lathed_driver_types: type 'loose' is <class ")
    assert "not a subclass of lathed.driver.Driver" in by["e_loose"].error and "loose" not in loader.driver_types()


def test_missing_dropin_dir_is_reported(tmp_path):
    loader = load_all([tmp_path / "nope"])
    assert any(p.error == "plugin directory does not exist" for p in loader.plugins)


def test_every_hookspec_is_documented_and_exercised():
    """A hook without a test is a hook nobody knows works (pytest's habit)."""
    import pathlib
    tests = "".join(p.read_text() for p in pathlib.Path(__file__).parent.glob("test_*.py"))
    for name, fn in inspect.getmembers(hookspecs, inspect.isfunction):
        if name.startswith("lathed_"):
            assert fn.__doc__ and len(fn.__doc__) > 40, f"{name} has no documentation"
            assert tests.count(name) >= 2 or f"def {name}" in tests, f"no test implements {name}"


def test_detector_and_candidate_hooks_reach_the_loader(tmp_path):
    (tmp_path / "extras.py").write_text(
        "from lathed import hookimpl\n"
        "from lathed.analysis.chatter.detectors import SyncCusumDetector\n"
        "class Mine(SyncCusumDetector):\n    name = 'mine'\n"
        "@hookimpl\ndef lathed_chatter_detectors():\n    return {'mine': Mine}\n"
        "@hookimpl\ndef lathed_thermal_candidates():\n    return ['candidate-a', 'candidate-b']\n")
    # a detector outside the base class is refused at load, as a driver is
    (tmp_path / "loose_detector.py").write_text(
        "from lathed import hookimpl\n"
        "def make(rate_hz, **params):\n    return ('detector', rate_hz, params)\n"
        "@hookimpl\ndef lathed_chatter_detectors():\n    return {'loose': make}\n")
    loader = load_all([tmp_path])
    by = {p.name: p for p in loader.plugins}
    assert by["extras"].error is None and "mine" in by["extras"].provides
    det = make_detector("mine", 51200.0, extra=loader.chatter_detectors(), threshold=2.0)
    # the base class's defaults are what the chatter analyzer calls, with no probing
    assert det.threshold == 2.0 and det.OWN_EYE is False and callable(det.eye_views)
    assert "not a subclass of lathed.analysis.chatter.base.RevolutionDetector" in by["loose_detector"].error
    assert "loose" not in loader.chatter_detectors()
    assert loader.thermal_candidates() == ["candidate-a", "candidate-b"]


def test_a_plugins_own_event_kinds_are_known_before_the_first_is_recorded(tmp_path):
    # `events --kind robot_gripper_slip` (and a subscription following it) was refused until one
    # had been recorded: a plugin's own kinds were known only from the store
    from lathed import daemon as daemonmod
    from lathed.store import Store
    plugins = tmp_path / "plugins"
    plugins.mkdir()
    (plugins / "gripper.py").write_text(
        "from lathed import hookimpl\n"
        "@hookimpl\ndef lathed_event_kinds():\n    return ['robot_gripper_slip']\n")
    (plugins / "bad_kinds.py").write_text(
        "from lathed import hookimpl\n@hookimpl\ndef lathed_event_kinds():\n    return 'robot_slip'\n")
    loader = load_all([plugins])
    assert loader.event_kinds() == {"robot_gripper_slip"}
    (bad,) = [p for p in loader.plugins if p.name == "bad_kinds"]
    assert "lathed_event_kinds must return a list of names" in bad.error
    cfg = tmp_path / "lathed.toml"
    cfg.write_text(f'[daemon]\nstate_dir = "{tmp_path}/state"\nruntime_dir = "{tmp_path}/run"\n'
                   f'plugin_dirs = ["{plugins}"]\n[sensor.t]\nplugin = "ds18b20_serial"\nport = "/dev/null"\n')
    cfg, settings, loader, plan, sim = daemonmod.prepare(cfg, strict=False)
    store = Store(tmp_path / "a.db")
    daemonmod.Daemon(cfg, settings, loader, plan, sim, store)
    assert store.unknown_kind(["robot_gripper_slip"]) is None
    assert "did you mean 'robot_gripper_slip'" in store.unknown_kind(["robot_gripper_slp"])
    store.close()


def test_daemon_lists_failed_plugins_and_runs_dropin(sim_daemon, tmp_path):
    d_dir = tmp_path / "dropins"
    d_dir.mkdir()
    (d_dir / "counter.py").write_text(GOOD)
    (d_dir / "broken.py").write_text(BROKEN_IMPORT)
    d = sim_daemon(extra='\n[sensor.count]\nplugin = "counter"\nstep = 2.0\n',
                   daemon=f'plugin_dirs = ["{d_dir}"]')
    plugins = json.loads(d.ctl("plugins", "--json").stdout)
    by = {p["name"]: p for p in plugins}
    assert by["counter"]["state"] == "loaded"
    assert by["broken"]["state"] == "failed" and "definitely_not_a_module" in by["broken"]["error"]
    assert "FAILED  broken" in d.ctl("plugins").stdout
    wait_until(lambda: (d.item("sensors", "count")["last_value"] or {}).get("count", 0) >= 4,
               what="drop-in sensor values")


def _check(tmp_path, plugin_text: str, extra: str = "") -> "subprocess.CompletedProcess":
    import subprocess
    from tests.conftest import BIN
    d = tmp_path / "dropins"
    d.mkdir(exist_ok=True)
    (d / "bad.py").write_text(plugin_text)
    cfg = tmp_path / "lathed.toml"
    cfg.write_text(f'[daemon]\nstate_dir = "{tmp_path / "state"}"\nruntime_dir = "{tmp_path / "run"}"\n'
                   f'plugin_dirs = ["{d}"]\n{extra}\n[sensor.count]\nplugin = "counter"\n')
    return subprocess.run([str(BIN / "lathed"), "--check-config", str(cfg)], capture_output=True, text=True,
                          timeout=60)


def test_a_plugin_calling_sys_exit_at_import_is_a_plugin_failure(tmp_path):
    # issue 18 D10: it made lathed and --check-config exit 0 silently
    loader = load_all([_dropin(tmp_path, "import sys\nsys.exit(0)\n")])
    (bad,) = [p for p in loader.plugins if p.name == "bad"]
    assert bad.error.startswith("SystemExit: the plugin called sys.exit(0) at ") and "bad.py:2" in bad.error
    r = _check(tmp_path, "import sys\nsys.exit(0)\n")
    assert r.returncode == 78, r
    assert "plugin bad" in r.stderr and "sys.exit(0)" in r.stderr


def test_a_plugin_looping_at_import_is_stopped_and_reported(tmp_path):
    r = _check(tmp_path, "while True:\n    pass\n", 'plugin_import_timeout = "1s"')
    assert r.returncode == 78, r
    assert "plugin bad" in r.stderr and "did not finish importing within 1 s" in r.stderr


def _dropin(tmp_path, text: str):
    d = tmp_path / "one"
    d.mkdir()
    (d / "bad.py").write_text(text)
    return d


def test_the_daemon_runs_on_past_a_plugin_that_calls_sys_exit(sim_daemon, tmp_path):
    # issue 18 D10: lathed exited 0 at import, and Restart=on-failure left the service down
    d_dir = tmp_path / "exiting"
    d_dir.mkdir()
    (d_dir / "quitter.py").write_text("import sys\nsys.exit(0)\n")
    d = sim_daemon(daemon=f'plugin_dirs = ["{d_dir}"]')
    by = {p["name"]: p for p in json.loads(d.ctl("plugins", "--json").stdout)}
    assert by["quitter"]["state"] == "failed" and "sys.exit(0)" in by["quitter"]["error"]
    assert d.proc.poll() is None
