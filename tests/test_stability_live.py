"""The stability loop closed in the running daemon (issue 16): a simulated lathe
whose workpiece mode is 12 % higher than the tap test the daemon is configured
with; its cuts recorded, `lathectl cuts` and the CSV export, `lathectl
stability refit` naming the shifted mode and adopting it, and suppression's
next proposal taken from the adopted lobes."""
from __future__ import annotations

import json
import subprocess

import pytest

from lathed.analysis.cuts import load_cuts_csv
from lathed.analysis.stability import StabilityModel
from lathed.sim.lathe import LATHE_KF, LATHE_MODES
from tests.conftest import BIN, DEPTH_REGISTER, Daemon, running_daemon, sim_config, wait_until
from tests.test_suppression_live import default_table, events

TRUE_FN = round(LATHE_MODES[0].fn_hz * 1.12, 1)
MODES = [f"{m.fn_hz:g},{m.zeta:g},{m.k_n_per_m:g},{m.theta_deg:g}" for m in LATHE_MODES]
# 3 mm at speeds where the configured lobes and the true ones disagree: the tap test's model
# calls 2250, 2750 and 3500 r/min stable (limit 4.7-4.8 mm) where the lathe's limit is 2.4 mm,
# and 2500, 3250 and 4250 r/min unstable (2.4-2.7 mm) where it is 4.4-8.4 mm
PROGRAM = [f"{rpm},3.0,0.3,24" for rpm in (2250, 2500, 2750, 3250, 3500, 4250)]
SIMULATOR = (f'modes = {json.dumps([f"{TRUE_FN:g},0.03,7.5e7,0", MODES[1]])}\n'
             f'program = {json.dumps(PROGRAM)}\nload_s = 0.3\nretract_s = 0.2\n')


@pytest.fixture
def shifted(tmp_path):
    # without remembered cures: each pass then explores speeds from its entry on, the evidence
    # the refit needs (with them a pass goes straight to the speed that cured it before)
    suppress = default_table("suppress").replace("\nremember = true", "\nremember = false")
    assert "remember = false" in suppress
    cfg, paths = sim_config(tmp_path, analyzers=default_table("chatter") + "\n" + suppress,
                            simulator=SIMULATOR, registers=DEPTH_REGISTER)
    with running_daemon(cfg, paths) as d:
        yield d


def cuts(d) -> list[dict]:
    return json.loads(d.ctl("cuts", "--json", "--limit", "1000").stdout)


def judged(rows) -> int:
    """Judged cut speeds the export keeps (a steady speed with a known depth: a busy machine's
    speed ramps make some unsteady, a control that did not answer leaves a cut's depth unknown,
    and the export leaves those out and says so)."""
    return sum(s["outcome"] is not None and s.get("steady", False) and r["depth_mm"] is not None
               for r in rows for s in r["speeds"])


@pytest.mark.slow
def test_the_refit_names_the_shifted_mode_and_suppression_uses_it(shifted, tmp_path):
    # its held-out part is 12-14 cuts: two wrong cut records failed the refit's sign test (z 2.496
    # against 2.5). Both kinds are gone: a release alarm at a stable pass's end (issue 38) and a
    # cure above the limit regrowing too slowly to alarm, recorded stable (now null: cut_log's
    # RISING_RATIO); 8 of 8 runs adopted at 100 % held-out, three at once beside a live bench
    d = shifted
    wait_until(lambda: judged(cuts(d)) >= 40, timeout=240, interval=1.0, what="40 judged cut speeds")
    rows = cuts(d)
    assert all(r["machine"] == "lathe" and r["tool"] == "T0101" and r["material"] == "C45" for r in rows)
    # a cut cut while the control did not answer (a loaded machine: Modbus timeouts) has no depth,
    # and says so; the export leaves it out
    faults = [e["t"] for e in events(d, "machine_fault")]
    for r in rows:
        assert r["feed_mm_rev"] == 0.3, r
        if r["depth_mm"] is None:
            assert r["depth_from"] is None and any(r["start_t"] - 2 <= t <= r["end_t"] + 2 for t in faults), r
        else:
            assert r["depth_mm"] == 3.0 and r["depth_from"] == "register", r
    assert sum(r["depth_mm"] == 3.0 for r in rows) >= len(rows) - len(faults)
    chattered = [r for r in rows if r["outcome"] == "chatter"]
    assert chattered and all(r["first_alarm_s"] > 0 and r["chatter_frequency_hz"] > 0 for r in chattered)
    assert any(r["actions"] for r in chattered)
    text = d.ctl("cuts", "--machine", "lathe").stdout
    assert "T0101/C45 tool 1 depth 3 mm (register)" in text and "r/min" in text
    assert d.ctl("cuts", "--machine", "mill").stdout.strip() == "(no cuts)"

    # the export is what `lathectl analyze stability` reads
    csv = tmp_path / "cuts.csv"
    d.ctl("cuts", "--csv", str(csv))
    exported = load_cuts_csv(csv)
    assert len(exported) >= 40 and set(exported.depth_mm) == {3.0}

    r = json.loads(d.ctl("stability", "refit", "--machine", "lathe", "--json").stdout)
    assert r["adopt"] is True, r["reason"]
    e = r["effects"][0]
    assert e["effect"] == "natural_frequency" and e["mode"] == 1, r["effects"]
    assert r["after"]["accuracy"] > r["before"]["accuracy"]
    adopted = StabilityModel.from_json(r["model_after"])
    assert adopted.modes[0].fn_hz == pytest.approx(TRUE_FN, rel=0.04)
    (ev,) = events(d, "stability_model_adopted")
    assert ev["payload"]["file"] == r["model_after_name"] == "lathe-v1.json"
    assert ev["payload"]["caller"]["pid"] > 0          # who asked, from the kernel
    assert "model lathe-v1.json" in d.ctl("stability", "status").stdout

    offline = subprocess.run([str(BIN / "lathectl"), "analyze", "stability", str(csv), "--json",
                              *sum((["--mode", m] for m in MODES), []), "--kf", str(LATHE_KF)],
                             capture_output=True, text=True, timeout=120)
    assert offline.returncode == 0, offline.stderr
    assert json.loads(offline.stdout)["effects"][0]["effect"] == "natural_frequency"

    # from now on the proposals come from the adopted lobes
    t_adopt = ev["t"]
    # (a cut keeps the lobes it began with: the first action of a cut begun before the adoption
    # is still the configured model's, and says so)
    act = wait_until(lambda: [a for a in events(d, "suppression_action") if a["t"] > t_adopt
                              and a["payload"]["strategy"] == "sss_lobes"
                              and a["payload"]["model"] == "lathe-v1.json"],
                     timeout=60, interval=0.5, what="a lobe-selected action of the adopted model")[0]["payload"]
    # its limit is the adopted lobes' (at some speeds the old and new lobes agree within a
    # percent, so the limit alone could not tell which model chose)
    b_new = float(adopted.limit(act["rpm_after"])[0][0]) * 1e3
    assert act["expected_b_lim_mm"] == pytest.approx(b_new, rel=0.005)
    wait_until(lambda: any(c["model"] == "lathe-v1.json" for c in cuts(d)), timeout=30, interval=0.5,
               what="a cut recorded under the adopted model")


def test_the_simulators_true_dynamics_and_program_are_checked_and_passed_on(tmp_path):
    from lathed.config import ConfigError, Section
    from lathed.sim.__main__ import parse_args
    from lathed.sim.launch import SimulatorSettings
    s = SimulatorSettings(Section("t.toml", "simulator", {"modes": [f"{TRUE_FN:g},0.03,7.5e7,0", MODES[1]],
                                                           "kf": 2.9e9, "program": PROGRAM[:2], "load_s": 0.3}),
                          tmp_path)
    argv = s.argv()
    assert argv[1:3] == ["-m", "lathed.sim"]
    lathe = parse_args(argv[3:]).lathe
    assert lathe["modes"][0].fn_hz == TRUE_FN and lathe["kf"] == 2.9e9 and lathe["load_s"] == 0.3
    assert [(c.rpm, c.depth_mm, c.feed_mm_rev, c.length_mm) for c in lathe["program"]] == \
        [(2250, 3.0, 0.3, 24.0), (2500, 3.0, 0.3, 24.0)]
    assert parse_args([]).lathe["modes"] == LATHE_MODES        # by default the configured model is the truth
    for key, value, problem in (("modes", ["190,2,7.5e7"], "damping ratio"),
                                ("program", ["2250,30"], "outside"), ("program", ["fast,3"], "as numbers")):
        with pytest.raises(ConfigError) as e:
            SimulatorSettings(Section("t.toml", "simulator", {key: value}), tmp_path)
        assert "[simulator]" in str(e.value) and key in str(e.value) and problem in str(e.value), str(e.value)


@pytest.mark.slow
@pytest.mark.timeout(600)     # a learn takes seconds of one core; a loaded CI machine gives less
def test_with_no_modal_model_the_daemon_answers_model_free_learns_from_its_cuts_and_then_uses_the_lobes(tmp_path):
    # issue 41: no tap test. The store holds the cuts of earlier shifts (recorded as the daemon
    # records them, on the simulated lathe's true lobes); the daemon learns from them at start.
    import numpy as np
    from lathed.analysis.stability.cases import generate_cuts
    from lathed.store import Store
    lathe = StabilityModel(LATHE_MODES, LATHE_KF)
    earlier = generate_cuts(lathe, 100, given=lathe, seed=8)
    store = Store(tmp_path / "state" / "lathed.db", machine_id="test-cell")
    for i in range(len(earlier)):
        ch = bool(earlier.chatter[i])
        f = float(earlier.chatter_frequency_hz[i])
        store.record_future("cut", "suppress", {
            "machine": "lathe", "tool": "T0101", "material": "C45", "tool_number": 1,
            "depth_mm": float(earlier.depth_mm[i]), "depth_from": "register", "feed_mm_rev": 0.3,
            "outcome": "chatter" if ch else "stable",
            "speeds": [{"rpm": float(earlier.rpm[i]), "outcome": "chatter" if ch else "stable", "steady": True,
                        "chatter_frequency_hz": f if ch and np.isfinite(f) else None}]}).result()
    store.close()
    suppress = default_table("suppress").replace("\nremember = true", "\nremember = false")
    suppress = "\n".join(line for line in suppress.splitlines() if not line.startswith("modes ="))
    assert 'strategy = "lobes"' in suppress and not any(line.startswith("modes") for line in suppress.splitlines())
    program = [f"{rpm},3.0,0.3,24" for rpm in (2250, 2500, 3250)]
    cfg, paths = sim_config(tmp_path, analyzers=default_table("chatter") + "\n" + suppress,
                            simulator=f"program = {json.dumps(program)}\nload_s = 0.3\nretract_s = 0.2\n",
                            registers=DEPTH_REGISTER)
    d = Daemon(cfg, paths["socket"])
    try:
        d.wait_ready()
        learned = wait_until(lambda: events(d, "stability_model_learned"), timeout=480, interval=1.0,
                             what="a model learned from the recorded cuts")[0]
        name = learned["payload"]["file"]
        assert name == "lathe-v1.json" and learned["payload"]["model_before"] == "none"
        model = StabilityModel.from_json(learned["payload"]["learned"]["model"])
        assert model.modes[0].fn_hz == pytest.approx(LATHE_MODES[0].fn_hz, rel=0.02)
        # from then on a chatter alarm is answered from the learned lobes
        act = wait_until(lambda: [a for a in events(d, "suppression_action") if a["t"] > learned["t"]
                                  and a["payload"]["model"] == name], timeout=90, interval=0.5,
                         what="an action chosen by the learned lobes")[0]["payload"]
        assert act["strategy"] == "sss_lobes"
        assert act["expected_b_lim_mm"] == pytest.approx(float(model.limit(act["rpm_after"])[0][0]) * 1e3, rel=0.005)
        # before it, any answer was model-free, and said so
        assert all(a["payload"]["model"] is None and a["payload"]["strategy"] in ("sss_frequency", "rated_speed")
                   for a in events(d, "suppression_action") if a["t"] < learned["t"])
        st = d.ctl("stability", "status").stdout
        assert f"model {name}" in st and "learning from the cuts" in st
    finally:
        d.stop()
