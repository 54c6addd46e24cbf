"""The residual loop on simulated runs: fit on one run, test on another with a
different speed schedule, and check the effect the simulator put in is the
one named, and that none is claimed where there is none."""
import functools

import numpy as np
import pytest

from lathed.analysis.thermal import Candidate, LinearTerm, ThermalData, analyze, fit_stage, refit
from lathed.sim.thermal import EFFECTS, generate_run, random_schedule

NOISE_UM = 0.5
TRAIN_SEED, TEST_SEED = 7, 107      # bench/bench_thermal.py sweeps many seeds
SHIFT_S = 8 * 3600                   # each run is a shift, as in the bench


def data(run) -> ThermalData:
    c = run.columns
    return ThermalData(c["time_s"], {k: v for k, v in c.items() if k.startswith("t_")},
                       c["displacement_um"], c["spindle_rpm"])


def pair(effects, extra=None, train_seed=TRAIN_SEED, test_seed=TEST_SEED):
    tr = generate_run(random_schedule(train_seed, SHIFT_S), effects, seed=train_seed, noise_um=NOISE_UM)
    te = generate_run(random_schedule(test_seed, SHIFT_S), effects, seed=test_seed, noise_um=NOISE_UM)
    tr, te = data(tr), data(te)
    if extra is not None:
        tr.displacement_um = tr.displacement_um + extra(tr.time_s)
        te.displacement_um = te.displacement_um + extra(te.time_s)
    return tr, te


@functools.cache
def analyzed(effects: tuple[str, ...]):
    """pair(effects) and its analysis, for the tests that check different things of the same
    fit (a fit costs seconds of CPU); the tests only read them."""
    tr, te = pair(effects)
    return tr, te, analyze(tr, te)


def test_schedules_differ():
    assert random_schedule(TRAIN_SEED, SHIFT_S) != random_schedule(TEST_SEED, SHIFT_S)


@pytest.mark.parametrize("effect", EFFECTS)
def test_the_effect_in_the_data_is_named_and_the_test_error_falls(effect):
    from lathed.analysis.thermal import residual_structure
    tr, te, a = analyzed((effect,))
    assert a.effects, f"nothing found; residual: {a.residual.note}"
    assert a.effects[0].term.effect == effect
    fall = 1 - a.loop.test_rmse_um / a.start.test_rmse_um
    assert fall >= 0.60, f"{effect}: {a.start.test_rmse_um:.2f} -> {a.loop.test_rmse_um:.2f} µm"
    # the effects found leave nothing on the next run; what is handed on is judged below
    left = residual_structure(te.time_s, te.displacement_um - a.loop.model.predict(te), te)
    assert not left.structured, left.note
    assert a.final is a.loop or a.final is a.best_baseline("rolling")


def test_a_drift_is_handed_on_once_the_runs_span_days():
    """Within one run the room's temperature and its lags make a clock too: the ridge baseline
    on them follows the drift on the newest rows of the training run (here within 15 % of the
    drift term, not beaten consistently), and is handed on; on the next day, its room on
    another course, it is 4x worse. Two days as training rows show it: the drift is handed on."""
    from lathed.analysis.thermal import ThermalRuns

    def run(seed):
        return data(generate_run(random_schedule(seed, SHIFT_S), ("drift",), seed=seed, noise_um=NOISE_UM))
    days = ThermalRuns([run(TRAIN_SEED), run(TRAIN_SEED + 50)])
    a = analyze(days, run(TEST_SEED))
    assert [e.term.effect for e in a.effects] == ["drift"]
    assert a.final is a.loop, a.notes
    assert a.final.test_rmse_um <= 1.10 * NOISE_UM
    ridge = next(b for b in a.baselines if b.model.source == "ridge_lags")
    assert ridge.forward_rmse_um > 2 * a.loop.forward_rmse_um


def test_a_notch_does_not_stand_in_for_a_lag_not_yet_found():
    # Pair 5: the motor's rise has a line at 398 s (speed changes, no oscillation of its own).
    # Chosen before any effect, a notch there (half a period of delay) stood in for the shaft's
    # lag; the front bearing's lag then scored worse than the rear's, and the loop built on
    # stand-ins to three effects and 1.97 µm on the next run (0.53 µm with the true lag).
    tr, te = pair(("lag",), train_seed=5, test_seed=105)
    a = analyze(tr, te)
    assert [(e.term.effect, e.term.sensor) for e in a.effects] == [("lag", "t_front_bearing_c")], a.notes
    assert a.loop.test_rmse_um <= 1.10 * NOISE_UM, a.loop.test_rmse_um


def test_lag_time_constant_is_found():
    _, _, a = analyzed(("lag",))
    first = a.effects[0]
    assert first.term.sensor == "t_front_bearing_c"
    # The shaft's own time constant (C / sum of G) is ~1700 s; the grid is ~30 % apart.
    assert 900 < first.term.params["tau_s"] < 3000


# 3 and 6: the pairs whose 5-h runs ended just over the bar (rear bearing and
# motor warm nearly in step; their weights scattered).
@pytest.mark.parametrize("seed", [TRAIN_SEED, 3, 6])
def test_no_effect_is_claimed_on_data_without_one(seed):
    tr, te = pair((), train_seed=seed, test_seed=seed + 100)
    a = analyze(tr, te)
    assert a.effects == []
    assert a.loop.test_rmse_um <= 1.10 * NOISE_UM
    # handed on: the selected model only if it beats every baseline on the newest training rows
    assert a.final is a.loop or a.final is a.best_baseline("rolling")
    assert not a.residual.structured


def test_pure_noise_gets_no_effect():
    rng = np.random.default_rng(3)
    tr, te = pair(())
    tr.displacement_um = rng.normal(0, 1, len(tr))
    a = analyze(tr)
    assert a.effects == []


def test_a_periodicity_off_the_library_becomes_a_periodic_term():
    # A 20-min coolant-pump cycle no library effect explains: found in the
    # residual, it is modelled at its period (phase fitted), not only reported.
    tr, te = pair((), extra=lambda t: 3.0 * np.sin(2 * np.pi * t / 1200.0 + 0.7))
    a = analyze(tr, te)
    assert [e.term.effect for e in a.effects] == ["periodic"], a.notes
    assert a.effects[0].term.params["period_s"] == pytest.approx(1200.0, rel=0.01)
    fall = 1 - a.loop.test_rmse_um / a.start.test_rmse_um
    assert fall >= 0.60, (a.start.test_rmse_um, a.loop.test_rmse_um)
    assert not a.residual.structured, a.residual.note


class CoolantCycle(Candidate):
    """A plugin's candidate: a periodic term at a known pump period."""
    name = "coolant_cycle"

    def propose(self, data):
        return [CoolantTerm()]

    def make_term(self, sensor, params):
        return CoolantTerm()


class CoolantTerm:
    effect, sensor, params = "coolant_cycle", None, {"period_s": 1200.0}
    names = ("coolant_sin", "coolant_cos")

    def features(self, data):
        w = 2 * np.pi * data.time_s / 1200.0
        return np.column_stack([np.sin(w), np.cos(w)])

    def stream(self):
        return lambda t, rises, rpm: (np.sin(2 * np.pi * t / 1200.0), np.cos(2 * np.pi * t / 1200.0))


def test_a_plugin_candidate_is_tried_and_named():
    tr, te = pair((), extra=lambda t: 3.0 * np.sin(2 * np.pi * t / 1200.0))
    a = analyze(tr, te, extra_candidates=[CoolantCycle()])
    assert [e.term.effect for e in a.effects] == ["coolant_cycle"]
    assert a.loop.test_rmse_um <= 1.2 * NOISE_UM
    js = a.to_json()
    assert js["effects"][0]["effect"] == "coolant_cycle" and js["effects"][0]["sensor"] is None


def test_json_contract():
    js = analyzed(("speed",))[2].to_json()
    stage = {"model", "terms", "rmse_um", "forward_rmse_um", "test_rmse_um"}
    assert set(js["start"]) == set(js["loop"]) == stage
    # least squares, with the speed, ridge; each with its error over the later half of the rows
    assert [set(b) for b in js["baselines"]] == [stage | {"rolling_rmse_um"}] * 3
    assert set(js["final"]) == (stage | {"rolling_rmse_um"} if js["handed_on"] != js["loop"]["model"] else stage)
    assert js["handed_on"] == js["final"]["model"]
    assert {"model", "forward_rmse_um", "rmse_um", "baseline"} <= set(js["comparison"]["models"][0])
    assert set(js["residual"]) == {"structured", "note"}
    e = js["effects"][0]
    assert set(e) == {"effect", "sensor", "params", "test_rmse_um"}
    assert e["effect"] == "speed" and e["sensor"] is None and "form" in e["params"]


def test_refit_keeps_the_better_model():
    tr, _ = pair(("hysteresis",))
    r = refit(tr)                          # against eq. 14, which does not fit this spindle
    assert r.better and r.model is r.candidate
    assert r.after_rmse_um < r.before_rmse_um
    # no baseline fitted on the same rows does better on the newest ones
    assert len(r.baselines_rmse_um) == 3 and r.after_rmse_um <= min(r.baselines_rmse_um.values()), r.why
    # A second refit against the model just fitted finds no real improvement.
    r2 = refit(tr, current=r.model)
    assert not r2.better and r2.model is r.model


def _day(seed, effects):
    """One day's probe data from a cold start: a probe every 5 min, touched off at the first readings."""
    r = generate_run(random_schedule(seed, SHIFT_S), effects, seed=seed, dt_s=60.0, noise_um=0.3)
    c = {k: v[::5] for k, v in r.columns.items()}
    temps = {k: v for k, v in c.items() if k.startswith("t_")}
    return c, temps, {k: float(v[0]) for k, v in temps.items()}


def test_days_from_their_own_cold_starts_fit_better_than_one_long_run():
    from lathed.analysis.thermal import ThermalRuns, rmse
    days = [_day(s, ("drift",)) for s in (21, 22, 23, 24)]
    runs = ThermalRuns([ThermalData(c["time_s"], t, c["displacement_um"], c["spindle_rpm"], reference_c=ref, t0_s=0.0)
                        for c, t, ref in days[:3]])
    # the same rows as one run: days end to end, rises from the first morning, one drift clock
    one = ThermalData(np.concatenate([c["time_s"] + k * 86400 for k, (c, _, _) in enumerate(days[:3])]),
                      {k: np.concatenate([t[k] for _, t, _ in days[:3]]) for k in days[0][1]},
                      np.concatenate([c["displacement_um"] for c, _, _ in days[:3]]),
                      np.concatenate([c["spindle_rpm"] for c, _, _ in days[:3]]))
    c4, t4, r4 = days[3]
    day4 = ThermalData(c4["time_s"], t4, c4["displacement_um"], c4["spindle_rpm"], reference_c=r4, t0_s=0.0)
    a_runs, a_one = analyze(runs), analyze(one)
    assert a_runs.effects[0].term.effect == "drift"
    e_runs = rmse(day4.displacement_um - a_runs.model.predict(day4))
    e_one = rmse(day4.displacement_um - a_one.model.predict(day4))
    print(f"day 4: {e_runs:.2f} µm as runs, {e_one:.2f} µm as one run")
    assert e_runs < 1.0 and e_runs < 0.5 * e_one, (e_runs, e_one)
    r = refit(runs)                       # the daemon's refit takes the same runs
    assert r.better and r.after_rmse_um < 1.0


# -- second pass: combined effects, steps, many sensors, honest structure -----

def test_a_lag_and_a_speed_effect_together_are_both_named():
    # Seed 6: taken one at a time, a lag of ~1100 s half-explains both and a
    # speed term beside it then makes things worse; the pair cuts the error > 90 %.
    tr, te = pair(("lag", "speed"), train_seed=6, test_seed=106)
    a = analyze(tr, te)
    names = {(e.term.effect, e.term.sensor) for e in a.effects}
    assert ("lag", "t_front_bearing_c") in names and ("speed", None) in names, a.notes
    fall = 1 - a.loop.test_rmse_um / a.start.test_rmse_um
    assert fall >= 0.90, (a.start.test_rmse_um, a.loop.test_rmse_um)
    assert a.loop.test_rmse_um <= a.least_squares.test_rmse_um


def _lag_speed_pair(s):
    def run(seed):
        return data(generate_run(random_schedule(seed, SHIFT_S), ("lag", "speed"), seed=seed, noise_um=0.2))
    return run(s), run(s + 100)


def test_a_stand_in_that_entered_first_is_swapped_for_the_pair():
    # Seed 1008: a short lag of the rear bearing enters first (it half-explains
    # both effects); ranked beside it, speed and the front bearing's lag came
    # low, and the loop built on stand-ins to a test error 4x the baseline's.
    tr, te = _lag_speed_pair(1008)
    a = analyze(tr, te)
    names = {(e.term.effect, e.term.sensor) for e in a.effects}
    assert ("lag", "t_front_bearing_c") in names and ("speed", None) in names, a.notes
    assert 1 - a.loop.test_rmse_um / a.start.test_rmse_um >= 0.90, (a.start.test_rmse_um,
                                                                         a.loop.test_rmse_um)


def test_no_time_constant_the_run_cannot_tell_from_a_trend():
    # Seed 2006: a lag of speed at 4 h (on an 8-h run) took the slow wander of
    # this run beside the true pair and doubled the test error on the next.
    tr, te = _lag_speed_pair(2006)
    a = analyze(tr, te)
    span = float(tr.time_s[-1] - tr.time_s[0])
    taus = [t.tau_s for t in a.loop.model.terms if hasattr(t, "tau_s")]
    assert taus and max(taus) <= span / 4, taus
    assert 1 - a.loop.test_rmse_um / a.start.test_rmse_um >= 0.90, (a.start.test_rmse_um,
                                                                         a.loop.test_rmse_um)


def test_growth_steps_at_speed_changes_become_a_speed_step_term():
    from lathed.sim.thermal import add_speed_steps
    tr = data(add_speed_steps(generate_run(random_schedule(1, SHIFT_S), (), seed=1, dt_s=30.0)))
    te = data(add_speed_steps(generate_run(random_schedule(101, SHIFT_S), (), seed=101, dt_s=30.0)))
    a = analyze(tr, te)
    assert "speed_step" in [e.term.effect for e in a.effects], a.notes
    assert 1 - a.loop.test_rmse_um / a.start.test_rmse_um >= 0.6
    # without a speed column the steps cannot be fitted: they are named, with their times
    tr.rpm = None
    a = analyze(tr)
    assert a.residual.structured and "sudden step(s)" in a.residual.note, a.residual.note
    assert "with a spindle_rpm column" in a.residual.note
    assert len(a.residual.steps_h) >= 3


def test_a_switch_at_one_speed_is_one_step_not_a_column_per_level():
    # Seed 6 (rows 6 s apart, as in the bench): with a column per speed level,
    # levels run in one held-out block only made the step term lose the
    # held-out test, and speed x temperature stood in (4 % fall on the test run).
    from lathed.sim.thermal import add_speed_steps

    def run(seed):
        return data(add_speed_steps(generate_run(random_schedule(seed, SHIFT_S), (), seed=seed, noise_um=0.5)))
    tr, te = run(6), run(106)
    a = analyze(tr, te)
    steps = [e.term for e in a.effects if e.term.effect == "speed_step"]
    assert steps and steps[0].above_rpm is not None and 2500 <= steps[0].above_rpm <= 3000, a.notes
    assert 1 - a.loop.test_rmse_um / a.start.test_rmse_um >= 0.6, (a.start.test_rmse_um,
                                                                        a.loop.test_rmse_um)


def test_a_trend_is_not_a_period():
    from lathed.analysis.thermal import residual_structure
    t = np.arange(3000) * 6.0
    rng = np.random.default_rng(0)
    # a warm-up and cool-down the model missed: one slow bump over the run (the old
    # check called it a periodicity of a third of the run)
    for slow in (3 * np.exp(-((t - 0.5 * t[-1]) / (0.15 * t[-1])) ** 2),
                 4 * np.tanh((t - 0.4 * t[-1]) / (0.05 * t[-1]))):
        rep = residual_structure(t, slow + rng.normal(0, 0.3, len(t)))
        assert rep.structured and rep.period_s is None and "periodicity" not in rep.note, rep.note


def test_a_residual_period_is_tied_to_the_sensor_oscillating_at_it():
    from lathed.analysis.thermal import residual_structure
    t = np.arange(2400) * 6.0
    rng = np.random.default_rng(1)
    warm = 8 * (1 - np.exp(-t / 5000.0))
    osc = np.sin(2 * np.pi * t / 270.0)
    d = ThermalData(t, {"t_motor_c": 20 + warm + 0.3 * osc + rng.normal(0, 0.02, len(t)),
                        "t_front_bearing_c": 20 + 0.7 * warm + rng.normal(0, 0.02, len(t))})
    rep = residual_structure(t, 1.5 * osc + rng.normal(0, 0.3, len(t)), d)
    assert rep.period_s == pytest.approx(270.0, rel=0.01)
    assert rep.sensor == "t_motor_c" and "the period at which t_motor_c oscillates" in rep.note


def _ls4(tr, te):
    """Least squares on the simulation's four true sensors, fitted on the training run."""
    from lathed.sim.thermal import TRUE_SENSORS
    true4 = list(TRUE_SENSORS)
    return fit_stage(tr.select(true4), [LinearTerm(k) for k in true4], te.select(true4), int(0.8 * len(tr)), "",
                     raw=True)


def test_sixteen_sensors_of_which_four_carry_the_growth():
    from lathed.sim.thermal import many_sensors

    def run(seed):
        return data(many_sensors(generate_run(random_schedule(seed, SHIFT_S), (), seed=seed, dt_s=60.0,
                                              noise_um=0.3), seed))
    tr, te = run(3), run(103)
    assert len(tr.sensors) == 16
    a = analyze(tr, te)
    ls4 = _ls4(tr, te)
    assert a.loop.test_rmse_um <= 1.10 * ls4.test_rmse_um, (a.loop.test_rmse_um, ls4.test_rmse_um)
    assert a.loop.test_rmse_um < a.least_squares.test_rmse_um       # all 16 as read: far worse
    kept = {k.sensor: k for k in a.sensors}
    assert len(kept) <= 8 and {"t_front_bearing_c", "t_rear_bearing_c"} <= set(kept)
    # the motor's own 4.5-min oscillation is notched out, at fit and at prediction alike
    assert kept["t_motor_c"].notch_s == pytest.approx(270.0, abs=3.0)
    m = a.model
    pred = m.predictor(reference_c=te.reference_c, t0_s=te.t0_s)
    live = [pred.update({k: te.temps_c[k][i] for k in m.sensors}, rpm=te.rpm[i], t_s=te.time_s[i])
            for i in range(len(te))]
    assert live == pytest.approx(m.predict(te), abs=1e-6)


@pytest.mark.xfail(strict=True, reason="issue 36 regression: chosen on forward folds (the later half of the run "
                   "only), the decoy t_extra10_c and the front bearing are kept; 2.1x least squares on the 4 true")
def test_a_decoy_lagging_a_heated_sensor_does_not_keep_the_true_ones_out():
    # Pair 7: a sensor on a part that lags the front bearing (t_extra07_c) stands
    # in for the front bearing and the motor at once; a forward pass took it
    # second and then saw no gain in either true one (6x least squares on the
    # four true sensors on the next run). The floating search finds the true set.
    from lathed.analysis.thermal import select_sensors
    from lathed.sim.thermal import TRUE_SENSORS, many_sensors

    def run(seed):
        return data(many_sensors(generate_run(random_schedule(seed, SHIFT_S), (), seed=seed, dt_s=60.0,
                                              noise_um=0.3), seed))
    tr, te = run(7), run(107)
    chosen, _, _ = select_sensors(tr, prune=False)
    names = {t.sensor for t in chosen}
    assert names <= set(TRUE_SENSORS) and "t_front_bearing_c" in names, names
    sel = fit_stage(tr, chosen, te, int(0.8 * len(tr)), "")
    ls4 = _ls4(tr, te)
    assert sel.test_rmse_um <= 1.10 * ls4.test_rmse_um, (sel.test_rmse_um, ls4.test_rmse_um)


def test_two_days_keep_the_decoy_out():
    """The decoy of pair 7 (above) predicts the later rows of its own run as well as the true
    sensors; a second day, its heat on another course, tells them apart."""
    from lathed.analysis.thermal import ThermalRuns, select_sensors
    from lathed.sim.thermal import TRUE_SENSORS, many_sensors

    def run(seed):
        return data(many_sensors(generate_run(random_schedule(seed, SHIFT_S), (), seed=seed, dt_s=60.0,
                                              noise_um=0.3), seed))
    chosen, _, _ = select_sensors(ThermalRuns([run(7), run(57)]), prune=False)
    names = {t.sensor for t in chosen}
    assert names <= set(TRUE_SENSORS) and "t_front_bearing_c" in names, names


@pytest.mark.parametrize("seed", [6, 7])
def test_sensors_that_only_wander_do_not_enter(seed):
    # Twelve cabinet sensors on random walks carry no growth; within one run a
    # walk can still follow the residual's slow course. The old test (a z of 1
    # over rows, Newey-West window sqrt(rows)) took one to three of them in.
    from lathed.analysis.thermal import select_sensors
    r = generate_run(random_schedule(seed, SHIFT_S), (), seed=seed, dt_s=60.0, noise_um=0.3).columns
    rng = np.random.default_rng(seed)
    temps = {k: v for k, v in r.items() if k.startswith("t_")}
    for i in range(12):
        temps[f"t_cabinet{i:02d}_c"] = np.round((20 + np.cumsum(rng.normal(0, 0.01, len(r["time_s"])))) * 16) / 16
    d = ThermalData(r["time_s"], temps, r["displacement_um"], r["spindle_rpm"])
    chosen, _, _ = select_sensors(d, prune=False)
    assert {t.sensor for t in chosen} == {"t_front_bearing_c", "t_rear_bearing_c", "t_motor_c"}


def test_a_warm_test_run_is_refused_with_rows_a_minute_apart_too():
    """With rows a minute apart every rise starts at the room's temperature, so
    the references no longer tell a warm start: the check reads each sensor's
    own first rows."""
    from lathed.analysis.thermal import reference_test
    tr = data(generate_run(random_schedule(1, SHIFT_S), (), seed=1, dt_s=60.0))
    te = data(generate_run(random_schedule(101, SHIFT_S), (), seed=101, dt_s=60.0))
    assert tr.rises_from == te.rises_from == "t_room_c"
    test, note = reference_test(tr, te)                 # a cold start passes
    assert note is None and all(test.temps_c[k] is v for k, v in te.temps_c.items())
    half = len(te) // 2
    warm = ThermalData(te.time_s[half:] - te.time_s[half], {k: v[half:] for k, v in te.temps_c.items()},
                       te.displacement_um[half:], te.rpm[half:])
    with pytest.raises(ValueError, match="does not start cold"):
        reference_test(tr, warm)
