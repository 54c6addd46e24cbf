"""Several runs as training rows: cold starts told by the machine's own sensors, not the room."""
import numpy as np
import pytest

from lathed.analysis.thermal import ThermalData, ThermalRuns, join_runs, reference_test
from lathed.sim.thermal import generate_run, random_schedule

SHIFT_S = 4 * 3600


def data(run) -> ThermalData:
    c = run.columns
    return ThermalData(c["time_s"], {k: v for k, v in c.items() if k.startswith("t_")},
                       c["displacement_um"], c["spindle_rpm"])


def _another_day(d: ThermalData, machine_c: float, room_c: float) -> ThermalData:
    """The same run on another day: the iron soaked ``machine_c`` warmer overnight, the shop's air
    ``room_c`` warmer (it warms up in the morning faster than the iron, or not yet)."""
    temps = {k: v + (room_c if "room" in k else machine_c) for k, v in d.temps_c.items()}
    return ThermalData(d.time_s, temps, d.displacement_um, d.rpm)


def _warm(d: ThermalData) -> ThermalData:
    """The second half of a run, its clock restarted: it starts warm."""
    h = len(d) // 2
    return ThermalData(d.time_s[h:] - d.time_s[h], {k: v[h:] for k, v in d.temps_c.items()},
                       d.displacement_um[h:], d.rpm[h:])


@pytest.fixture(scope="module")
def days():
    return [data(generate_run(random_schedule(s, SHIFT_S), (), seed=s, dt_s=dt)) for s, dt in ((1, 6.0), (101, 6.0),
                                                                                                   (2, 60.0), (102, 60.0))]


@pytest.mark.parametrize("room_c", [-1.5, -1.0, 1.0, 1.5])
def test_a_cold_run_whose_room_air_differs_from_the_machine_is_accepted(days, room_c):
    # the machine's sensors agree with each other (all 2 °C warmer than on the training day);
    # the room's air reads 1-1.5 °C off them: the old check took that for a warm start
    for tr, te in (days[:2], days[2:]):
        day2 = _another_day(te, 2.0, 2.0 + room_c)
        test, note = reference_test(tr, day2)
        assert note is None and all(test.temps_c[k] is v for k, v in day2.temps_c.items())    # its rows, cold
        rows, notes = join_runs([("a.csv", tr), ("b.csv", day2)])
        assert isinstance(rows, ThermalRuns) and len(rows.runs) == 2 and notes == []


def test_a_really_warm_run_is_still_told_apart(days):
    for tr, te in (days[:2], days[2:]):
        for warm in (_warm(te), _another_day(_warm(te), 2.0, 2.0)):
            with pytest.raises(ValueError, match="the test run does not start cold: t_"):
                reference_test(tr, warm)
            with pytest.raises(ValueError, match=r"^b.csv does not start cold: t_.*\(b.csv\)$"):
                join_runs([("a.csv", tr), ("b.csv", warm)])


def test_a_run_continuing_the_clock_continues_the_run_before_it(days):
    tr = days[0]
    h = len(tr) // 2
    first = tr.slice(0, h)
    rest = ThermalData(tr.time_s[h:], {k: v[h:] for k, v in tr.temps_c.items()}, tr.displacement_um[h:], tr.rpm[h:])
    rows, notes = join_runs([("a.csv", first), ("b.csv", rest)])
    assert isinstance(rows, ThermalData) and len(rows) == len(tr) and "b.csv continues" in notes[0]
    # one run from the one cold start: the same rises as the whole run read at once
    for s in tr.sensors:
        assert rows.rise(s) == pytest.approx(tr.rise(s), abs=1e-9)


def test_runs_need_the_same_temperature_columns(days):
    tr, te = days[:2]
    less = ThermalData(te.time_s, {k: v for k, v in te.temps_c.items() if k != "t_motor_c"}, te.displacement_um)
    with pytest.raises(ValueError, match=r"b.csv has temperature columns .* every run needs the same"):
        join_runs([("a.csv", tr), ("b.csv", less)])


def test_with_one_machine_sensor_the_room_stands_in():
    t = np.arange(0, 3 * 3600.0, 6.0)
    hot = 5 * (1 - np.exp(-t / 1500))
    tr = ThermalData(t, {"t_motor_c": 20 + hot, "t_room_c": 20 + 0 * t}, hot)
    shifted = ThermalData(t, {"t_motor_c": 21.5 + hot, "t_room_c": 21.5 + 0 * t}, hot)
    assert reference_test(tr, shifted) == (shifted, None)
    warm = ThermalData(t, {"t_motor_c": 24 + hot, "t_room_c": 20 + 0 * t}, hot)
    with pytest.raises(ValueError, match="t_motor_c starts at 24.00 °C, 4.00 °C further above the room"):
        reference_test(tr, warm)


def test_live_cold_again_judges_only_a_standing_spindle():
    from lathed.analysis.thermal.start import cold_again
    cold = {"front_bearing": 19.25, "rear_bearing": 19.25, "motor": 19.31, "room": 19.19}
    morning = {p: v + 2.0 for p, v in cold.items()} | {"room": cold["room"] + 0.5}
    assert cold_again(cold, morning) and cold_again(cold, morning, 0.0, 0.0)
    assert not cold_again(cold, morning, rpm_now=1500.0)      # turning: heating its bearings now
    assert not cold_again(cold, morning, rpm_then=1500.0)     # the stored "cold" start was taken at speed
    assert not cold_again(cold, cold)                          # not moved: the same cold start goes on


@pytest.mark.parametrize("room_c", [-1.5, 1.5])
def test_a_cold_run_whose_room_air_differs_is_predicted_as_well(days, room_c):
    # Rows a minute apart take every rise from the room's start (the first row is a minute into
    # the warm-up): from the air of a morning 1.5 °C off the iron, every rise of that run was off
    # by as much, and the test run's error 10.9 µm for 0.48. The iron's own sensors say where it
    # stands.
    from lathed.analysis.thermal import LinearTerm, fit_stage
    tr, te = days[2:]
    assert tr.rises_from == "t_room_c"

    def error(day):
        test, _ = reference_test(tr, day)
        return fit_stage(tr, [LinearTerm(k) for k in tr.sensors], test, int(0.8 * len(tr)), "").test_rmse_um
    at_iron, off = error(_another_day(te, 2.0, 2.0)), error(_another_day(te, 2.0, 2.0 + room_c))
    assert off <= 1.05 * at_iron, (off, at_iron)
    # as training rows, the same: the machine's rises do not move with the room's air
    runs = [join_runs([("a.csv", tr), ("b.csv", _another_day(te, 2.0, 2.0 + r))])[0].runs[1] for r in (0.0, room_c)]
    for k in ("t_front_bearing_c", "t_rear_bearing_c", "t_motor_c"):
        assert runs[1].rise(k) == pytest.approx(runs[0].rise(k), abs=1e-9)
