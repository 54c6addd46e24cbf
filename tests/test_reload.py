"""Configuration reload on SIGHUP (issue 17 item 7): live values at once, structural changes refused."""
from __future__ import annotations

import signal
from types import SimpleNamespace

import numpy as np

from lathed.config import Section
from lathed_plugins.chatter import ChatterAnalyzer
from tests.conftest import events, wait_until
from tests.test_chatter_live import CHATTER


def test_sighup_applies_live_values_and_refuses_structural_changes(sim_daemon):
    d = sim_daemon(analyzers=CHATTER)
    cfg = d.cfg
    wait_until(lambda: d.item("analyzers", "chatter")["windows"] > 0, timeout=30, what="chatter windows")
    # live: a detector threshold and a machine limit
    text = cfg.read_text().replace("spindle_rpm_max = 6000.0", "spindle_rpm_max = 4000.0")
    cfg.write_text(text + "\n[analyzer.chatter.params]\nthreshold = 3.5\n")
    d.proc.send_signal(signal.SIGHUP)
    done = wait_until(lambda: events(d, "config_reloaded", 20), timeout=20, what="config_reloaded")
    assert sorted(done[-1]["payload"]["changed"]) == ["[analyzer.chatter]", "[machine.lathe.limits]"]
    wait_until(lambda: d.item("analyzers", "chatter")["threshold"] == 3.5, timeout=20, what="threshold 3.5 live")
    ch = d.item("analyzers", "chatter")
    assert ch["state"] == "running" and ch["last_error"] is None, ch      # not restarted
    # a driver's key changed beside a live one: the whole reload is refused, nothing applied
    text = cfg.read_text()
    assert 'stale_after = "5s"' in text
    cfg.write_text(text.replace("threshold = 3.5", "threshold = 5.0").replace('stale_after = "5s"',
                                                                            'stale_after = "7s"'))
    d.proc.send_signal(signal.SIGHUP)
    refused = wait_until(lambda: events(d, "config_reload_refused", 20), timeout=20, what="config_reload_refused")
    assert refused[-1]["payload"]["problems"] == ["[sensor.temps] stale_after changed (restart lathed to apply)"]
    assert d.item("analyzers", "chatter")["threshold"] == 3.5
    # a config that does not parse is refused with its error, the daemon goes on
    cfg.write_text("[daemon\n")
    d.proc.send_signal(signal.SIGHUP)
    wait_until(lambda: len(events(d, "config_reload_refused", 20)) == 2, timeout=20, what="second refusal")
    assert d.status()["daemon"]["state"] == "running"


def test_reconfigure_keeps_the_cut_and_its_baseline():
    a = ChatterAnalyzer("chatter", Section("f.toml", "analyzer.chatter", {"input": "accel", "machine": "lathe"}))
    a.ctx = SimpleNamespace(plugins=None)
    a.detector = a._new_detector(25600.0)
    rng = np.random.default_rng(1)
    for _ in range(20):
        a.detector.process(rng.normal(size=2048), 2000.0)
    det, baseline = a.detector, a.detector.baseline
    assert baseline is not None
    a.reconfigure(Section("f.toml", "analyzer.chatter", {"params": {"threshold": 3.5, "window_revs": 2.0,
                                                                    "jump_ratio": 5.0}}))
    assert a.detector is det and det.baseline == baseline        # the cut goes on, baseline kept
    assert det.threshold == 3.5 and det.params["threshold"] == 3.5
    assert det.params["jump_ratio"] == 5.0                       # the level step's test too
    assert det.params["window_revs"] == 1.0 and a._rebuild       # windows change from the next cut
    a.ctx = SimpleNamespace(plugins=None, bus=SimpleNamespace(publish=lambda s: None),
                            log=SimpleNamespace(info=lambda *x, **k: None))
    assert not a.cutting
    a._source("vibration", True, 1.0)
    assert a.detector is None and not a._rebuild                 # rebuilt with window_revs 2 at the next block


def test_diff_names_every_structural_change(tmp_path):
    from lathed import config as configmod
    from lathed.reload import diff
    base = ('[daemon]\nname = "t"\nlog_level = "info"\n[store]\nkeep_days = 0\n'
            '[machine.lathe]\nplugin = "modbus_cnc"\nport = 502\n[machine.lathe.limits]\nspindle_rpm_max = 3000\n'
            '[machine.mill]\nplugin = "modbus_cnc"\n'
            '[analyzer.chatter]\nplugin = "chatter"\ninput = "accel"\n')
    new = ('[daemon]\nname = "u"\nlog_level = "debug"\n[store]\nkeep_days = 30\n'
           '[machine.lathe]\nplugin = "modbus_cnc"\nport = 503\n[machine.lathe.limits]\nspindle_rpm_max = 2500\n'
           '[machine.saw]\nplugin = "modbus_cnc"\n'
           '[analyzer.chatter]\nplugin = "thermal"\ninput = "accel"\n')
    (tmp_path / "a.toml").write_text(base)
    (tmp_path / "b.toml").write_text(new)
    ch = diff(configmod.load(tmp_path / "a.toml"), configmod.load(tmp_path / "b.toml"), {"chatter": {"params"}})
    assert ch.daemon == {"log_level": "debug"} and ch.store == {"keep_days": 30} and ch.limits == ["lathe"]
    # each names what changed and what to do: a machine added is applied by a restart, not a reload
    assert ch.refused == ["[daemon] name changed (restart lathed to apply)",
                          "[machine.mill] removed (restart lathed to apply)",
                          "[machine.saw] added (restart lathed to apply)",
                          "[analyzer.chatter] plugin changed from 'chatter' to 'thermal' (restart lathed to apply)",
                          "[machine.lathe] port changed (restart lathed to apply)"]
