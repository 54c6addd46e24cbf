"""The simulated spindle's thermal physics (lathed.sim.thermal)."""
import csv

import numpy as np
import pytest

from lathed.sim.thermal import (CSV_COLUMNS, EFFECTS, SpindleThermal, ThermalParams, generate_run,
                                random_schedule)


def test_heats_at_speed_and_cools_when_stopped():
    still_room = ThermalParams(room_daily_amp_c=0.0, room_drift_c_per_h=0.0)
    sim = SpindleThermal(seed=1, params=still_room)
    start = sim.true_temperatures()
    for _ in range(600):                        # 1 h at 4000 r/min
        sim.step(6.0, 4000)
    hot = sim.true_temperatures()
    assert hot["front_bearing"] - start["front_bearing"] > 5.0
    assert hot["motor"] - start["motor"] > 3.0
    hot_growth = sim.displacement_um
    assert hot_growth > 10.0
    for _ in range(1800):                       # 3 h stopped
        sim.step(6.0, 0)
    cold = sim.true_temperatures()
    assert abs(cold["front_bearing"] - cold["room"]) < 0.5     # the slowest mode is still settling
    assert abs(sim.displacement_um) < 0.1 * hot_growth


def test_exact_steps_do_not_depend_on_step_length():
    a, b = SpindleThermal(seed=3, room_phase_h=6.0), SpindleThermal(seed=3, room_phase_h=6.0)
    for _ in range(100):
        a.step(6.0, 3000)
        for _ in range(60):
            b.step(0.1, 3000)
    ta, tb = a.true_temperatures(), b.true_temperatures()
    for k in ta:
        # Only the room, held at mid-step, differs slightly between the two.
        assert ta[k] == pytest.approx(tb[k], abs=2e-3)


def test_readings_are_ds18b20_like():
    sim = SpindleThermal(seed=2)
    sim.step(60.0, 2000)
    vals = [sim.readings() for _ in range(200)]
    assert set(vals[0]) == {"front_bearing", "rear_bearing", "motor", "room"}
    fb = np.array([v["front_bearing"] for v in vals])
    assert np.allclose(fb / 0.0625, np.round(fb / 0.0625))     # 1/16 °C steps
    true = sim.true_temperatures()["front_bearing"]
    assert abs(fb.mean() - true) < 0.05 and fb.std() < 0.1


def test_without_effects_growth_is_static_linear_in_the_bodies():
    p = ThermalParams()
    sim = SpindleThermal(seed=4, params=p)
    t0 = sim.true_temperatures()
    for rpm in (4000, 1000, 0, 2500):
        for _ in range(100):
            sim.step(6.0, rpm)
        t = sim.true_temperatures()
        rise = {k: t[k] - t0[k] for k in t}
        expect = (p.k_fb * rise["front_bearing"] + p.k_rb * rise["rear_bearing"] + p.k_mot * rise["motor"]
                  + p.k_body * rise["spindle_body"] + p.k_room * rise["room"])
        assert sim.displacement_um == pytest.approx(expect, abs=1e-9)


@pytest.mark.parametrize("effect", EFFECTS)
def test_each_effect_changes_the_growth(effect):
    sched = [(1800, 4000), (1200, 0), (1800, 2000)]
    a = generate_run(sched, (), seed=5, noise_um=0.0)
    b = generate_run(sched, (effect,), seed=5, noise_um=0.0)
    diff = b.columns["displacement_um"] - a.columns["displacement_um"]
    assert np.max(np.abs(diff)) > 2.0
    # Temperatures are the same physics either way.
    assert np.array_equal(a.columns["t_front_bearing_c"], b.columns["t_front_bearing_c"])


def test_speed_effect_is_instantaneous_and_quadratic():
    sim0 = SpindleThermal(seed=6, room_phase_h=0.0)
    sim1 = SpindleThermal(seed=6, room_phase_h=0.0, effects=("speed",))
    for s in (sim0, sim1):
        s.step(0.1, 3000)
    assert sim1.displacement_um - sim0.displacement_um == pytest.approx(ThermalParams().k_speed_um_per_krpm2 * 9)


def test_hysteresis_differs_between_heating_and_cooling():
    sim = SpindleThermal(seed=7, room_phase_h=0.0, effects=("hysteresis",))
    ref = SpindleThermal(seed=7, room_phase_h=0.0)
    for _ in range(300):
        sim.step(6.0, 4000)
        ref.step(6.0, 4000)
    heating = sim.displacement_um - ref.displacement_um
    for _ in range(300):
        sim.step(6.0, 0)
        ref.step(6.0, 0)
    cooling = sim.displacement_um - ref.displacement_um
    assert heating < 0 < cooling


def test_unknown_effect_is_refused():
    with pytest.raises(ValueError, match="unknown thermal effect"):
        SpindleThermal(effects=("vibration",))


def test_generate_run_and_csv(tmp_path):
    sched = random_schedule(1, total_s=1200)
    assert sum(d for d, _ in sched) == pytest.approx(1200)
    run = generate_run(sched, ("drift",), seed=1)
    assert len(run) == 200
    assert np.all(np.diff(run.columns["time_s"]) == 6.0)
    path = tmp_path / "run.csv"
    run.write_csv(path)
    with open(path) as f:
        rows = list(csv.reader(f))
    assert tuple(rows[0]) == CSV_COLUMNS and len(rows) == 201
    assert float(rows[-1][0]) == 1200.0


def test_the_sensors_on_parts_further_out_start_cold_and_follow_each_heated_part():
    """many_sensors' lagged copies: a part further out is at the room's
    temperature at a cold start, not at the first reading of the part it
    follows (a minute into a run at speed that reading has warmed), and the
    copies follow the front bearing, the rear bearing and the motor in turn
    (they all followed the front bearing). Which part a copy follows: the
    one whose lagged, scaled rise fits it best over the run (the rear
    bearing's and the motor's rises have nearly one shape, so they are one
    class here)."""
    from lathed.sim.thermal import many_sensors
    run = generate_run([(3600.0, 4000.0), (3600.0, 0.0)], seed=2, dt_s=60.0)
    heated = {k: run.columns[f"t_{k}_c"].copy() for k in ("front_bearing", "rear_bearing", "motor")}
    c = many_sensors(run, 2).columns
    room0 = c["t_room_c"][0]
    assert heated["front_bearing"][0] - room0 > 0.3          # warmed by the first row

    def misfit(x: np.ndarray, v: np.ndarray) -> float:
        best = np.inf
        for tau in np.geomspace(300.0, 3000.0, 40):
            a, acc, lagged = 1.0 - np.exp(-60.0 / tau), room0, np.empty(len(v))
            for k, u in enumerate(v):
                acc += a * (u - acc)
                lagged[k] = acc
            lagged -= room0
            s = lagged @ (x - room0) / (lagged @ lagged)
            best = min(best, float(np.sqrt(np.mean((x - room0 - s * lagged) ** 2))))
        return best

    followed = {}
    for i in (1, 4, 7, 10):                                   # the lagged copies
        x = c[f"t_extra{i:02d}_c"]
        if i in (4, 10):                                      # those without an oscillation of their own
            assert abs(x[0] - room0) < 0.15, (i, x[0], room0)
        r = {k: misfit(x, v) for k, v in heated.items()}
        followed[i] = min(r, key=r.get)
    assert followed[1] == followed[10] == "front_bearing", followed
    assert {followed[4], followed[7]} <= {"rear_bearing", "motor"}, followed
