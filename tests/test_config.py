"""Config validation: every refusal is one line naming file, table, key and what is allowed."""
from __future__ import annotations

import gc
import logging
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from lathed.config import ConfigError, Section, load, parse_duration
from lathed.daemon import prepare
from tests.conftest import BIN, ROOT

BASE = """
[daemon]
name = "t"
state_dir = "state"
runtime_dir = "run"

[machine.lathe]
plugin = "modbus_cnc"
host = "127.0.0.1"
port = 15020
[machine.lathe.identification]
serial_number = "L-1"
[machine.lathe.identity]
serial_number = { address = 40, words = 8 }
[machine.lathe.registers]
spindle_rpm = { address = 2, type = "float32" }
spindle_rpm_cmd = { address = 0, type = "float32", writable = true }
"""


def check(tmp_path, text: str) -> tuple[int, str]:
    cfg = tmp_path / "lathed.toml"
    cfg.write_text(text)
    r = subprocess.run([str(BIN / "lathed"), "--check-config", str(cfg)], capture_output=True, text=True)
    return r.returncode, r.stderr.replace(str(cfg), "FILE").strip()


@pytest.fixture
def check_here(tmp_path, monkeypatch, capsys, caplog):
    """check() run in this process: lathed's main() with --check-config, its exit code and stderr
    (and no warning logged, which the program would print), without a process of imports. The
    program itself is run by test_default_config_is_valid, test_bad_toml_is_one_line and others."""
    import lathed.daemon
    monkeypatch.setattr(lathed.daemon.logmod, "setup", lambda *a, **k: None)   # keeps pytest's handlers

    def run(text: str, where: Path = tmp_path) -> tuple[int, str]:
        cfg = where / "lathed.toml"
        cfg.write_text(text)
        gc.collect()     # what an earlier test left to the collector is logged now, not in the check
        capsys.readouterr()
        caplog.clear()
        umask = os.umask(0)
        os.umask(umask)
        try:
            code = lathed.daemon.main(["--check-config", str(cfg)])
        finally:
            os.umask(umask)
        err = capsys.readouterr().err
        warned = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
        return code, (err + "".join(f"{w}\n" for w in warned)).replace(str(cfg), "FILE").strip()
    return run


def refused(tmp_path, text: str) -> tuple[int, str]:
    """check() for a config the check refuses, in this process: what main() exits with and prints
    for a ConfigError (its lines, each after "lathed: "), without a process of imports per case.
    test_bad_toml_is_one_line and the others run the program itself."""
    cfg = tmp_path / "lathed.toml"
    cfg.write_text(text)
    try:
        prepare(cfg, strict=True)
    except ConfigError as e:
        return 78, "\n".join(f"lathed: {line}" for line in str(e).splitlines()).replace(str(cfg), "FILE").strip()
    return 0, ""


def test_default_config_is_valid():
    r = subprocess.run([str(BIN / "lathed"), "--check-config", str(ROOT / "etc" / "lathed.toml")],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "ok" in r.stdout


def test_valid_minimal(check_here):
    assert check_here(BASE) == (0, "")


@pytest.mark.parametrize("edit, message", [
    (("port = 15020", 'port = "15020"'),
     "lathed: FILE: [machine.lathe] port: expected an integer in [1, 65535], got '15020'"),
    (("port = 15020", "port = 70000"),
     "lathed: FILE: [machine.lathe] port: 70000 is out of range; allowed: an integer in [1, 65535]"),
    (("port = 15020", "port = 15020\nprot = 1"),
     "lathed: FILE: [machine.lathe] prot: unknown key; did you mean port? allowed keys here: host, *port, "
     "*registers"),
    (('host = "127.0.0.1"\n', ""),
     "lathed: FILE: [machine.lathe] host: missing required key"),
    # a required key misspelt is the key written, unknown, not the key meant, missing (issue 39)
    (('host = "127.0.0.1"\n', 'hots = "127.0.0.1"\n'),
     "lathed: FILE: [machine.lathe] hots: unknown key; did you mean host (required here, and missing)?"),
    (('plugin = "modbus_cnc"', 'plugin = "modbus_cn"'),
     "lathed: FILE: [machine.lathe] plugin: unknown driver type 'modbus_cn'; allowed: *modbus_cnc, "),
    (('name = "t"', 'name = "t"\nflavour = 1'),
     "lathed: FILE: [daemon] flavour: unknown key; allowed keys here: *log_level, name, plugin_dirs, "
     "plugin_import_timeout, runtime_dir, state_dir"),
    (('name = "t"', 'name = "t"\ncontrol_max_clients = 0'),
     "lathed: FILE: [daemon] control_max_clients: 0 is out of range; allowed: an integer in [1, 1024]"),
    (("writable = true }\n", "writable = true }\n[store]\nkeep_day = 30\n"),
     "lathed: FILE: [store] keep_day: unknown key; did you mean keep_days? allowed keys here: keep_days, "
     "prune_every"),
    # an integer too large for a float once raised OverflowError out of the getter (a traceback)
    (("writable = true }\n", "writable = true }\n[store]\nkeep_days = 1" + "0" * 400 + "\n"),
     "lathed: FILE: [store] keep_days: expected a number in [0.0, 36500.0], got 1000"),
    (("writable = true }\n", "writable = true }\n[store]\nkeep_days = -1\n"),
     "lathed: FILE: [store] keep_days: -1 is out of range; allowed: a number in [0.0, 36500.0]"),
    (("[daemon]", "[deamon]"),
     "lathed: FILE: [deamon]: unknown table; allowed: daemon, simulator, store, machine, sensor, analyzer"),
    (("port = 15020", "port = 15020\n[machine.lathe.limits]\nspindle_rpm_max = -5.0"),
     "lathed: FILE: [machine.lathe.limits] spindle_rpm_max: -5 is out of range; allowed: a number in [0.0, 100000.0]"),
    (('type = "float32" }', 'type = "float64" }'),
     "lathed: FILE: [machine.lathe.registers.spindle_rpm] type: 'float64' is not allowed; allowed: int16, "
     "uint16, int32, uint32, float32"),
])
def test_refusals_name_file_table_key(tmp_path, edit, message):
    old, new = edit
    text = BASE.replace(old, new, 1)
    assert text != BASE
    code, err = refused(tmp_path, text)
    assert code == 78
    # "*" stands for a list that grows as plugins add keys or types
    first = err.splitlines()[0]
    parts = message.split("*")
    assert first.startswith(parts[0]), first
    for p in parts[1:]:
        assert p in first, first


def test_bad_toml_is_one_line(tmp_path):
    code, err = check(tmp_path, BASE + "\nthis is not toml\n")
    assert code == 78
    assert len(err.splitlines()) == 1
    assert err.startswith("lathed: FILE: not valid TOML:") and "line" in err


def test_missing_file(tmp_path):
    r = subprocess.run([str(BIN / "lathed"), "--check-config", str(tmp_path / "nope.toml")],
                       capture_output=True, text=True)
    assert r.returncode == 78
    assert r.stderr.strip() == f"lathed: {tmp_path / 'nope.toml'}: no such config file"


def test_analyzer_input_must_exist(tmp_path):
    plugin = tmp_path / "plugins"
    plugin.mkdir()
    (plugin / "reader.py").write_text(
        "from lathed import hookimpl\nfrom lathed.analyzer import Analyzer\n"
        "class Reader(Analyzer):\n"
        "    def __init__(self, name, sec):\n"
        "        super().__init__(name, sec)\n"
        "        self.src = sec.getstr('input')\n"
        "    def inputs(self):\n        return [self.src]\n"
        "@hookimpl\ndef lathed_analyzer_types():\n    return {'reader': Reader}\n")
    text = BASE.replace('name = "t"', f'name = "t"\nplugin_dirs = ["{plugin}"]') + \
        '\n[analyzer.a]\nplugin = "reader"\ninput = "accelerometer"\n'
    code, err = check(tmp_path, text)
    assert code == 78
    assert err == ("lathed: FILE: [analyzer.a]: input 'accelerometer' is not a configured machine or sensor; "
                   "configured: lathe")


def test_getters_ranges_and_durations():
    s = Section("f.toml", "t", {"d": "50ms", "m": "2min", "n": 3, "x": 1.5, "b": True, "l": [1, 2.5]})
    assert s.getduration("d") == pytest.approx(0.05)
    assert s.getduration("m") == 120
    assert s.getduration("n") == 3
    assert s.getfloat("x", minval=1, maxval=2) == 1.5
    assert s.getbool("b") is True
    assert s.getlist("l", item=float) == [1, 2.5]
    with pytest.raises(ConfigError, match=r"^f.toml: \[t\] x: 1.5 is out of range; allowed: a number >= 2$"):
        s.getfloat("x", minval=2)
    with pytest.raises(ConfigError, match="expected true or false"):
        Section("f", "t", {"b": 1}).getbool("b")
    with pytest.raises(ConfigError, match="expected a duration"):
        Section("f", "t", {"d": "fast"}).getduration("d")
    with pytest.raises(ValueError):
        parse_duration("5 parsecs")


def test_prepare_collects_every_error(tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text(BASE.replace("port = 15020", "port = 0") + '\n[sensor.t]\nplugin = "ds18b20_serial"\n')
    with pytest.raises(ConfigError) as e:
        prepare(cfg, strict=True)
    lines = str(e.value).splitlines()
    assert len(lines) == 2
    assert "[machine.lathe] port" in lines[0] and "[sensor.t] port: missing required key" in lines[1]


def test_load_structures_instances(tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text(BASE)
    c = load(cfg)
    inst = c.instance("machine", "lathe")
    assert inst.plugin == "modbus_cnc" and "plugin" not in inst.section


def test_avoid_needs_the_lobes(tmp_path):
    text = BASE + """
[analyzer.chatter]
plugin = "chatter"
input = "accel"
machine = "lathe"

[analyzer.suppress]
plugin = "suppression"
chatter = "chatter"
machine = "lathe"
strategy = "frequency"
avoid = true
"""
    code, err = refused(tmp_path, text)
    assert code == 78 and err.splitlines()[0] == ('lathed: FILE: [analyzer.suppress] avoid: predicting chatter at '
                                                  'cut entry needs strategy = "lobes" (and its modes)'), err


ANALYZERS = """
[sensor.accel]
plugin = "vibration_tcp"
host = "127.0.0.1"
port = 15021

[analyzer.chatter]
plugin = "chatter"
input = "accel"
machine = "lathe"

[analyzer.records]
plugin = "records"
machine = "lathe"
"""


def test_one_bad_key_is_one_error_not_its_follow_ons(tmp_path):
    # issue 18 D10: the analyzers referring to the refused machine were each reported too
    code, err = refused(tmp_path, BASE.replace("port = 15020", "port = 15020\nprot = 1", 1) + ANALYZERS)
    assert code == 78
    assert err == "lathed: FILE: [machine.lathe] prot: unknown key; did you mean port? allowed keys here: " + \
        err.split("allowed keys here: ", 1)[1]
    assert len(err.splitlines()) == 1, err
    # an analyzer naming a machine that is not configured at all is still an error
    code, err = refused(tmp_path, BASE + ANALYZERS.replace('machine = "lathe"', 'machine = "lath"'))
    assert code == 78 and "'lath' is not a configured machine" in err


def test_a_config_with_nothing_to_run_is_refused(tmp_path):
    code, err = refused(tmp_path, '[daemon]\nname = "t"\nstate_dir = "state"\nruntime_dir = "run"\n')
    assert (code, err) == (78, "lathed: FILE: nothing to run: no [machine.*], [sensor.*] or [analyzer.*] table")


def test_an_unusable_state_dir_is_one_line_naming_it(tmp_path, check_here):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    text = BASE.replace('state_dir = "state"', f'state_dir = "{blocker / "state"}"')
    code, err = check_here(text)
    assert code == 73
    assert err == f"lathed: FILE: [daemon] state_dir {blocker / 'state'} is not usable: Not a directory ({blocker})"
    # the daemon itself says the same instead of a traceback
    cfg = tmp_path / "lathed.toml"
    r = subprocess.run([str(BIN / "lathed"), "--config", str(cfg)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 73 and "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines()[-1].endswith(f"[daemon] state_dir {blocker / 'state'} is not usable: "
                                                      "Not a directory")


def test_check_config_refuses_a_state_dir_the_daemon_cannot_make(tmp_path, check_here):
    # issue 35 case 13: permission bits said yes (root passes them) for a state_dir under
    # /proc; --check-config said ok and the daemon then refused it (73). Now both try it
    text = BASE.replace('state_dir = "state"', 'state_dir = "/proc/lathed/state"')
    code, err = check(tmp_path, text)
    assert (code, err) == (73, "lathed: FILE: [daemon] state_dir /proc/lathed/state is not usable: "
                               "No such file or directory (/proc)")
    r = subprocess.run([str(BIN / "lathed"), "--config", str(tmp_path / "lathed.toml")], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 73 and "state_dir /proc/lathed/state is not usable" in r.stderr
    # and nothing is left behind by the trial where it works
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    assert check_here(BASE, fresh) == (0, "") and sorted(p.name for p in fresh.iterdir()) == ["lathed.toml"]


def test_simulator_links_must_be_in_a_directory_only_we_can_write(tmp_path):
    # issue 18 D13: links in a fixed /tmp/lathed-sim made with exist_ok: whoever made it first chose the tty
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    code, err = refused(tmp_path, BASE + f'\n[simulator]\nserial_link = "{shared / "ttyARDUINO"}"\n')
    assert code == 78
    assert err == (f"lathed: FILE: [simulator] serial_link: unsafe place for the simulator's tty link: "
                   f"{shared} is writable by others (mode 0777)")
    from lathed.sim.serial_peer import _symlink
    with pytest.raises(PermissionError, match="refusing to put the tty link"):
        _symlink(shared / "ttyARDUINO", "/dev/null")
    assert not (shared / "ttyARDUINO").exists()


def test_default_config_puts_the_simulator_links_in_the_runtime_dir():
    _, settings, _, plan, sim = prepare(ROOT / "etc" / "lathed.toml", strict=True)
    assert sim.serial_link == str(settings.runtime_dir / "sim" / "ttyARDUINO")
    assert plan.drivers["temps"][1].port == sim.serial_link
    assert "{runtime_dir}" not in sim.grinder_link + sim.robot_link


def test_checking_the_default_config_imports_neither_scipy_nor_the_simulator():
    # a [simulator] table's program was checked with lathed.sim.lathe, whose physics pulls in
    # scipy.linalg: 0.35 s of every start and ~15 MB of the daemon's memory, for a parser
    code = ("import sys; from lathed.daemon import prepare; prepare(sys.argv[1], strict=True);"
            "print(sorted(m for m in ('scipy', 'lathed.sim.lathe') if m in sys.modules))")
    r = subprocess.run([str(BIN / "python"), "-c", code, str(ROOT / "etc" / "lathed.toml")],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]", r.stdout


def test_a_read_on_trigger_must_name_a_configured_instance(tmp_path):
    text = BASE.replace('spindle_rpm = { address = 2, type = "float32" }',
                        'spindle_rpm = { address = 2, type = "float32", read_on = ["chatr.cutting"] }')
    code, err = refused(tmp_path, text)
    assert (code, err) == (78, "lathed: FILE: [machine.lathe.registers.spindle_rpm] read_on: 'chatr' is not a "
                               "configured analyzer, machine or sensor")


def check_inproc(tmp_path, text: str) -> str:
    """The first problem prepare() reports, as --check-config prints it (in this process, so the
    code under test is this checkout's, not the installed console script's)."""
    cfg = tmp_path / "lathed.toml"
    cfg.write_text(text)
    with pytest.raises(ConfigError) as e:
        prepare(cfg, strict=True)
    return str(e.value).replace(str(cfg), "FILE").splitlines()[0]


@pytest.mark.parametrize("edit, line", [
    # nan passed every range check: asyncio.sleep(nan) returns at once (a busy loop)
    (("port = 15020", "port = 15020\npoll = nan"), "[machine.lathe] poll: expected a finite duration, got nan"),
    (("port = 15020", "port = 15020\nretry_initial = nan"),
     "[machine.lathe] retry_initial: expected a finite duration, got nan"),
    (("port = 15020", "port = 15020\nstale_after = inf"),
     "[machine.lathe] stale_after: expected a finite duration, got inf"),
    (("port = 15020", "port = 15020\nstale_after = nan"),
     "[machine.lathe] stale_after: expected a finite duration, got nan"),
    (("port = 15020", "port = 15020\ntimeout = nan"), "[machine.lathe] timeout: expected a finite duration, got nan"),
    (("port = 15020", 'port = 15020\nheartbeat_every = nan\n[machine.lathe.registers.heartbeat]\n'
                      'address = 9\ntype = "uint16"\nwritable = true'),
     "[machine.lathe] heartbeat_every: expected a finite duration, got nan"),
    (("writable = true }\n", "writable = true }\n[store]\nprune_every = nan\n"),
     "[store] prune_every: expected a finite duration, got nan"),
    # a string of digits too long for a float is inf too
    (("port = 15020", 'port = 15020\npoll = "' + "9" * 400 + 'ms"'),
     "[machine.lathe] poll: expected a finite duration, got '99"),
])
def test_non_finite_durations_are_refused(tmp_path, edit, line):
    text = BASE.replace(*edit, 1)
    assert text != BASE
    assert check_inproc(tmp_path, text).startswith("FILE: " + line)


def test_float_lists_refuse_non_finite_items():
    with pytest.raises(ConfigError, match=r"^f: \[t\] l: expected a list of float, got \[1, nan\]$"):
        Section("f", "t", {"l": [1, float("nan")]}).getlist("l", item=float)


def test_a_non_finite_mode_is_refused_naming_mode_and_field(tmp_path):
    text = BASE + ANALYZERS.replace('[analyzer.records]', """[analyzer.suppress]
plugin = "suppression"
chatter = "chatter"
machine = "lathe"
strategy = "lobes"
modes = ["190,0.03,7.5e7,0", "620,0.035,4e8,nan"]

[analyzer.records]""")
    assert check_inproc(tmp_path, text) == ("FILE: [analyzer.suppress] modes: mode '620,0.035,4e8,nan': "
                                            "angle THETA_DEG must be a finite number, got nan")
    text = text.replace("4e8,nan", "inf,30")
    assert check_inproc(tmp_path, text) == ("FILE: [analyzer.suppress] modes: mode '620,0.035,inf,30': "
                                            "stiffness K_N_PER_M must be a finite number, got inf")


def test_a_detector_parameter_must_be_a_number_not_a_string(tmp_path):
    text = BASE + ANALYZERS.replace('machine = "lathe"\n', 'machine = "lathe"\n[analyzer.chatter.params]\n'
                                    'threshold = "2"\n', 1)
    assert check_inproc(tmp_path, text) == ("FILE: [analyzer.chatter.params]: detector 'sync_cusum': threshold: "
                                            "expected a number, got '2'")


@pytest.mark.parametrize("edit, line", [
    # each passed: the analyzer then waited for messages that never came, or commanded nothing
    (('chatter = "chatter"\nmachine = "lathe"\nmode', 'chatter = "chattr"\nmachine = "lathe"\nmode'),
     "[analyzer.suppress] chatter: 'chattr' is not a configured analyzer; configured: chatter, suppress, "
     "thermal, records"),
    (('thermal = "thermal"', 'thermal = "thermall"'), "[analyzer.records] thermal: 'thermall' is not a configured "
     "analyzer; configured: chatter, suppress, thermal, records"),
    (('suppress = "suppress"', 'suppress = "supress"'), "[analyzer.records] suppress: 'supress' is not a "
     "configured analyzer; configured: chatter, suppress, thermal, records"),
    (('input = "accel"', 'input = "lathe"'),
     "[analyzer.chatter] input: 'lathe' is a machine of kind 'lathe', not a sensor of kind 'accelerometer'"),
    (('input = "temps"', 'input = "accel"'),
     "[analyzer.thermal] input: 'accel' is a sensor of kind 'accelerometer', not a sensor of kind 'temperature'"),
    (('chatter = "chatter"\nmachine = "lathe"', 'chatter = "chatter"\nmachine = "grinder"'),
     "[analyzer.suppress] machine: 'grinder' does not take 'spindle_rpm' (takes: none)"),
])
def test_an_analyzer_key_must_name_an_instance_of_the_right_kind(tmp_path, edit, line):
    shutil.copytree(ROOT / "etc", tmp_path / "etc")
    text = (ROOT / "etc" / "lathed.toml").read_text()
    assert edit[0] in text
    cfg = tmp_path / "etc" / "lathed.toml"
    cfg.write_text(text.replace(*edit, 1))
    with pytest.raises(ConfigError) as e:
        prepare(cfg, strict=True)
    assert str(e.value) == f"{cfg}: {line}"


@pytest.mark.parametrize("edit, line", [
    # every write was refused by the guard, recorded command_refused each time, and nothing compensated
    (('rate_um_s = 2.0\n', 'rate_um_s = 2.0\nstep = "10s"\n'),
     "[analyzer.thermal]: moves the offset up to 20 µm a write, more than [machine.lathe.limits] "
     "offset_step_max_um 10: every such write would be refused"),
    (('rate_um_s = 2.0\n', 'rate_um_s = 8.0\n'),
     "[analyzer.thermal]: moves the offset up to 8 µm/s, more than [machine.lathe.limits] "
     "offset_rate_max_um_s 5: such writes would be refused"),
])
def test_a_thermal_pace_the_machines_guard_refuses_is_a_config_error(tmp_path, edit, line):
    test_an_analyzer_key_must_name_an_instance_of_the_right_kind(tmp_path, edit, line)


def test_a_plugin_that_fails_to_load_fails_the_check(tmp_path):
    # --check-config printed a warning and "ok", exit 0, though the daemon would run without it
    missing = tmp_path / "nonexistent"
    text = BASE.replace('name = "t"', f'name = "t"\nplugin_dirs = ["{missing}"]')
    assert check_inproc(tmp_path, text) == (f"FILE: plugin {missing} ({missing}) failed to load: "
                                            "plugin directory does not exist")
    prepare(tmp_path / "lathed.toml", strict=False)     # the daemon runs on without it


@pytest.mark.parametrize("edit, line", [
    # both were taken: a daemon with no name in its records, a Modbus link to no host
    (('name = "t"', 'name = ""'), "[daemon] name: expected a non-empty string, got ''"),
    (('host = "127.0.0.1"', 'host = ""'), "[machine.lathe] host: expected a non-empty string, got ''"),
])
def test_an_empty_string_is_refused_where_a_name_is_needed(tmp_path, edit, line):
    assert check_inproc(tmp_path, BASE.replace(*edit, 1)) == "FILE: " + line


def test_an_empty_string_is_taken_where_it_is_the_default_or_allowed():
    s = Section("f", "t", {"tool": "", "a": "", "c": ""})
    assert s.getstr("tool", "") == "" and s.getstr("a", empty=True) == "" and s.getstr("c", "x", choices=("", "x")) == ""
    with pytest.raises(ConfigError, match=r"^f: \[t\] a: expected a non-empty string, got ''$"):
        s.getstr("a", "default")


def test_retry_initial_above_retry_max_is_refused_naming_both(tmp_path):
    # was taken and capped without a word: every wait was retry_max
    text = BASE.replace("port = 15020", 'port = 15020\nretry_initial = "10s"\nretry_max = "2s"', 1)
    assert check_inproc(tmp_path, text) == ("FILE: [machine.lathe] retry_initial: 10 s is above retry_max 2 s, "
                                            "which caps every wait; give retry_initial <= retry_max")
    prepare_ok = BASE.replace("port = 15020", 'port = 15020\nretry_initial = "2s"\nretry_max = "2s"', 1)
    (tmp_path / "lathed.toml").write_text(prepare_ok)
    prepare(tmp_path / "lathed.toml", strict=True)       # equal: a constant wait, allowed
    # a short retry_max alone: retry_initial's default is at most it, not an error
    (tmp_path / "lathed.toml").write_text(BASE.replace("port = 15020", 'port = 15020\nretry_max = "0.25s"', 1))
    prepare(tmp_path / "lathed.toml", strict=True)


def test_a_register_unit_lathed_does_not_know_is_refused_naming_register_unit_and_known(tmp_path):
    # "rpm" was taken, and the speed then had no plausible bounds: a 1e9 r/min read reached the bus
    text = BASE.replace('spindle_rpm = { address = 2, type = "float32" }',
                        'spindle_rpm = { address = 2, type = "float32", unit = "rpm" }', 1)
    assert check_inproc(tmp_path, text) == (
        "FILE: [machine.lathe.registers.spindle_rpm] unit: 'rpm' is not a unit lathed knows, so spindle_rpm would "
        "be checked only for being finite; known: °C, r/min, mm, µm, deg, m/s², %, s, mm/rev, Hz or none (or give "
        "spindle_rpm its min and max in [machine.lathe.plausible])")
    # a unit of one's own is taken where its bounds are given (a pressure lathed has no default for)
    own = BASE + ('coolant_bar = { address = 9, type = "float32", unit = "bar" }\n'
                  '[machine.lathe.plausible]\ncoolant_bar = { min = 0, max = 100 }\n')
    (tmp_path / "lathed.toml").write_text(own)
    prepare(tmp_path / "lathed.toml", strict=True)
    half = own.replace("min = 0, max = 100", "max = 100")
    assert check_inproc(tmp_path, half).startswith("FILE: [machine.lathe.registers.coolant_bar] unit: 'bar' is not")
