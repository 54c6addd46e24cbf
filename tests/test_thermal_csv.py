"""Loading thermal runs from CSV: bad rows rejected by reason, bad files refused."""
import numpy as np
import pytest

from lathed.analysis.thermal.csvfile import ThermalCsvError, load_thermal_csv

HEADER = "time_s,spindle_rpm,t_front_bearing_c,t_rear_bearing_c,t_motor_c,t_room_c,displacement_um\n"


def write(tmp_path, text, name="run.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def good_rows(n, t0=0.0):
    return "".join(f"{t0 + 6 * k:.1f},2000,{20 + k * 0.0625},{20 + k * 0.03125},20.5,19.9375,{k * 0.5}\n"
                   for k in range(n))




def test_clean_file(tmp_path):
    d, rep = load_thermal_csv(write(tmp_path, HEADER + good_rows(20)))
    assert len(d) == 20 and rep.used == 20 and not rep.rejected
    assert d.sensors == ["t_front_bearing_c", "t_rear_bearing_c", "t_motor_c", "t_room_c"]
    assert d.rpm is not None and d.displacement_um[-1] == pytest.approx(9.5)


def test_bad_rows_are_rejected_and_counted_by_reason(tmp_path):
    rows = good_rows(10).splitlines(keepends=True)
    bad = [
        "60.0,2000,85.0,20.1,20.5,19.9,1.0\n",       # power-on value
        "66.0,2000,20.1,-127.0,20.5,19.9,1.0\n",     # disconnected
        "72.0,2000,20.1,,20.5,19.9,1.0\n",           # empty cell
        "78.0,2000,20.1,20.1,nan,19.9,1.0\n",        # NaN
        "84.0,2000,20.1,20.1,20.5,19.9,oops\n",      # not a number
        "54.0,2000,20.1,20.1,20.5,19.9,1.0\n",       # same time as the last good row
        "30.0,2000,20.1,20.1,20.5,19.9,1.0\n",       # backwards
        "90.0,2000,20.1,20.1,20.5,19.9\n",           # short row: empty cell
    ]
    d, rep = load_thermal_csv(write(tmp_path, HEADER + "".join(rows) + "".join(bad) + good_rows(3, 96.0)))
    assert rep.used == 13 and len(d) == 13
    assert dict(rep.rejected) == {"sensor_power_on_85": 1, "sensor_disconnected_-127": 1, "empty_cell": 2,
                                  "nan": 1, "not_a_number": 1, "duplicate_time": 1, "backwards_time": 1}
    assert rep.first_line["sensor_power_on_85"] == 12
    assert np.all(np.diff(d.time_s) > 0)
    js = rep.to_json()
    assert js["rejected_total"] == 8 and js["used"] == 13


def test_85_in_a_non_temperature_column_is_data(tmp_path):
    d, rep = load_thermal_csv(write(tmp_path, HEADER + "0,2000,20,20,20,20,85.0\n6,2000,20,20,20,20,1\n"))
    assert rep.used == 2 and d.displacement_um[0] == 85.0


def test_missing_required_column_names_it(tmp_path):
    p = write(tmp_path, "time_s,t_motor_c\n0,20\n")
    with pytest.raises(ThermalCsvError) as ei:
        load_thermal_csv(p)
    assert ei.value.exit_code == 65
    msg = str(ei.value)
    assert "displacement_um" in msg and str(p) in msg and "line 1" in msg and "\n" not in msg


def test_no_temperature_column(tmp_path):
    with pytest.raises(ThermalCsvError, match="t_<place>_c") as ei:
        load_thermal_csv(write(tmp_path, "time_s,displacement_um\n0,1\n"))
    assert ei.value.exit_code == 65


def test_missing_file_is_66(tmp_path):
    with pytest.raises(ThermalCsvError) as ei:
        load_thermal_csv(tmp_path / "nope.csv")
    assert ei.value.exit_code == 66 and "nope.csv" in str(ei.value)


@pytest.mark.parametrize("text", ["", HEADER, HEADER + "0,1,85.0,20,20,20,1\n6,1,20,-127,20,20,1\n"])
def test_empty_or_all_bad_is_65(tmp_path, text):
    with pytest.raises(ThermalCsvError) as ei:
        load_thermal_csv(write(tmp_path, text))
    assert ei.value.exit_code == 65


def test_unknown_columns_are_listed_not_silently_dropped(tmp_path):
    d, rep = load_thermal_csv(write(tmp_path, "time_s,part_id,t_motor_c,displacement_um\n0,a,20,0\n6,b,20.5,1\n"))
    assert rep.ignored_columns == ["part_id"] and rep.to_json()["ignored_columns"] == ["part_id"]


@pytest.mark.parametrize("col, value, allowed", [
    ("t_front_bearing_c", "1e308", "-55..150"), ("displacement_um", "-1e300", "-100000..100000"),
    ("spindle_rpm", "1e9", "0..100000"), ("time_s", "1e308", "-1e+10..1e+10")])
def test_physically_implausible_value_refused_naming_file_line_column(tmp_path, col, value, allowed):
    """issue 18 D12: a 1e308 reading gave "error nan µm" and an effect found, exit 0."""
    rows = {"time_s": ["0", "1", "2"], "spindle_rpm": ["1000"] * 3, "t_front_bearing_c": ["20", "21", "22"],
            "displacement_um": ["0", "1", "2"]}
    rows[col][1] = value
    text = "time_s,spindle_rpm,t_front_bearing_c,displacement_um\n" + "".join(
        ",".join(rows[c][i] for c in ("time_s", "spindle_rpm", "t_front_bearing_c", "displacement_um")) + "\n"
        for i in range(3))
    p = write(tmp_path, text)
    with pytest.raises(ThermalCsvError) as e:
        load_thermal_csv(p)
    assert str(e.value) == f"{col} = {value} is outside the physically plausible {allowed} ({p}, line 3, column {col})"
