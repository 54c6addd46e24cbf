"""``lathectl analyze thermal``: output contract, plots, bad input."""
import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from lathed.cli import analyze_thermal
from lathed.sim.thermal import generate_run, random_schedule

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    d = tmp_path_factory.mktemp("thermal")
    # 2.5 h runs keep the tests quick; the effect is large enough to find.
    tr = generate_run(random_schedule(7, total_s=9000), ("speed",), seed=7)
    te = generate_run(random_schedule(107, total_s=9000), ("speed",), seed=107)
    tr.write_csv(d / "train.csv")
    te.write_csv(d / "test.csv")
    return d


def _run(argv, capsys):
    p = argparse.ArgumentParser(prog="lathectl analyze")
    sub = p.add_subparsers(dest="what", required=True)
    analyze_thermal.register_analyze(sub)
    args = p.parse_args(["thermal", *map(str, argv)])
    code = args.func(args)
    out, err = capsys.readouterr()
    return code, out, err


def test_json_contract_with_test_file(runs, capsys):
    code, out, err = _run([runs / "train.csv", "--test", runs / "test.csv", "--json"], capsys)
    assert code == 0, err
    doc = json.loads(out)
    assert {"start", "effects", "loop", "final", "baselines", "handed_on", "residual", "rows"} <= set(doc)
    assert [e["effect"] for e in doc["effects"]][:1] == ["speed"]
    assert doc["final"]["test_rmse_um"] < 0.4 * doc["start"]["test_rmse_um"]
    n_train = len((runs / "train.csv").read_text().splitlines()) - 1
    n_test = len((runs / "test.csv").read_text().splitlines()) - 1
    assert doc["rows"]["used"] == n_train and doc["rows"]["rejected"] == {}
    assert doc["rows"]["test"]["used"] == n_test
    assert isinstance(doc["residual"]["structured"], bool) and doc["residual"]["note"]


def test_human_output(runs, capsys):
    code, out, err = _run([runs / "train.csv"], capsys)
    assert code == 0, err
    lines = out.strip().splitlines()
    assert lines[0].startswith("before:") and "newest training rows" in lines[0]
    assert lines[1].startswith("found: speed") and "selected model:" in lines[1]
    assert lines[2].startswith("handed on: ")
    # every report carries the paper's equation, the selected model and the three baselines side by side
    assert lines[3].startswith("compared side by side (forward: the newest")
    rows = [ln.strip() for ln in lines[4:10]]
    assert [r.split(" ")[0] for r in rows] == ["paper", "linear", "selected:", "least", "least", "ridge"]
    assert [r for r in rows if "[baseline]" in r] == rows[3:]
    assert sum("(handed on)" in r for r in rows) == 1 and all("forward" in r and "later" in r for r in rows)
    assert lines[10].startswith("sensors: t_front_bearing_c")


def test_split_judges_every_model_on_the_held_out_tail(runs, capsys):
    code, out, err = _run([runs / "train.csv", "--split", "0.8", "--json"], capsys)
    assert code == 0, err
    doc = json.loads(out)
    n = len((runs / "train.csv").read_text().splitlines()) - 1
    cmp = doc["comparison"]
    assert cmp["rows"] == f"the last 20 % of train.csv ({n - round(0.8 * n)} rows)"
    by = {m["model"]: m for m in cmp["models"]}
    assert len(by) == 6 and all(m["rmse_um"] is not None for m in by.values())
    base = [m for m in by.values() if m["baseline"]]
    assert [m["model"].split(" ")[0] for m in base] == ["least", "least", "ridge"]
    # the selected model is handed on only if it beats every baseline on the newest training
    # rows, else the baseline with the least error over the later half of them; what the report
    # shows for it on the tail is its test error
    handed = by[doc["handed_on"]]
    assert handed.get("note") == "handed on" and handed["rmse_um"] == doc["final"]["test_rmse_um"]
    if handed["baseline"]:
        assert handed["rolling_rmse_um"] == min(m["rolling_rmse_um"] for m in base)
    else:
        assert handed["forward_rmse_um"] == min(m["forward_rmse_um"] for m in [*base, handed])
    assert handed["baseline"] == (doc["handed_on"] != doc["loop"]["model"])
    assert doc["baselines"][0]["test_rmse_um"] == base[0]["rmse_um"]


@pytest.mark.parametrize("argv, msg", [(["--split", "1.5"], "argument --split: 1.5: expected a fraction 0 < F < 1"),
                                      (["--split", "0"], "argument --split: 0: expected a fraction 0 < F < 1"),
                                      (["--max-sensors", "0"], "argument --max-sensors: 0 must be at least 1")])
def test_a_bad_argument_is_one_usage_line_exit_2(runs, capsys, argv, msg):
    with pytest.raises(SystemExit) as e:
        _run([runs / "train.csv", *argv], capsys)
    err = capsys.readouterr().err
    assert e.value.code == 2 and msg in err, err


def test_a_misspelled_column_is_said(runs, tmp_path, capsys):
    # spindle_rmp for spindle_rpm: the fit went on without the speed, said only in --json
    p = tmp_path / "typo.csv"
    p.write_text((runs / "train.csv").read_text().replace("spindle_rpm", "spindle_rmp", 1))
    code, _, err = _run([p, "--split", "0.8"], capsys)
    assert code == 0 and f"lathectl: warning: {p}:1: column(s) 'spindle_rmp' ignored" in err, err


def _rows(path):
    lines = path.read_text().splitlines()
    return lines[0], lines[1:]


def test_a_test_file_that_starts_warm_is_refused(runs, tmp_path, capsys):
    head, rows = _rows(runs / "test.csv")
    # the second half of a run, its clock restarted at 0: it starts warm
    half = rows[len(rows) // 2:]
    t0 = float(half[0].split(",")[0])
    shifted = [",".join([f"{float(r.split(',')[0]) - t0 + 6:.1f}", *r.split(",")[1:]]) for r in half]
    p = tmp_path / "warm.csv"
    p.write_text("\n".join([head, *shifted]) + "\n")
    code, out, err = _run([runs / "train.csv", "--test", p], capsys)
    assert code == 65 and out == ""
    assert err.startswith("lathectl: the test run does not start cold: t_"), err
    assert err.rstrip().endswith(f"({p})") and err.count("\n") == 1


def test_a_test_file_continuing_the_run_is_re_referenced(runs, tmp_path, capsys):
    head, rows = _rows(runs / "train.csv")
    cut = int(0.8 * len(rows))
    (tmp_path / "first.csv").write_text("\n".join([head, *rows[:cut]]) + "\n")
    (tmp_path / "rest.csv").write_text("\n".join([head, *rows[cut:]]) + "\n")
    code, out, err = _run([tmp_path / "first.csv", "--test", tmp_path / "rest.csv", "--json"], capsys)
    assert code == 0, err
    doc = json.loads(out)
    assert "continues the training run's clock" in doc["test_reference"] and "continues" in err
    # the same rows judged as --split 0.8 judges them: the rises from the one cold start
    code, out2, _ = _run([runs / "train.csv", "--split", str(cut / len(rows)), "--json"], capsys)
    assert json.loads(out2)["final"]["test_rmse_um"] == pytest.approx(doc["final"]["test_rmse_um"], rel=1e-6)


def test_plot_is_written(runs, tmp_path, capsys):
    png = tmp_path / "thermal.png"
    code, _, err = _run([runs / "train.csv", "--test", runs / "test.csv", "--plot", png], capsys)
    assert code == 0, err
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_rejected_rows_are_reported(runs, tmp_path, capsys):
    lines = (runs / "train.csv").read_text().splitlines()
    cells = lines[6].split(",")
    cells[2] = "85.0"                                 # front bearing at power-on, file line 7
    lines[6] = ",".join(cells)
    lines[9] = lines[8]                               # a repeated time stamp
    p = tmp_path / "glitchy.csv"
    p.write_text("\n".join(lines) + "\n")
    code, out, err = _run([p, "--json"], capsys)
    assert code == 0
    rows = json.loads(out)["rows"]
    assert rows["used"] == len(lines) - 1 - 2 and rows["rejected"] == {"sensor_power_on_85": 1, "duplicate_time": 1}
    assert "2 row(s)" in err and "line 7" in err


def test_missing_column_is_one_line_and_65(tmp_path, capsys):
    p = tmp_path / "bad.csv"
    p.write_text("time_s,t_motor_c\n0,20\n6,21\n")
    code, out, err = _run([p], capsys)
    assert code == 65 and out == ""
    assert err.count("\n") == 1 and err.startswith("lathectl: missing required column 'displacement_um'")
    assert str(p) in err


def test_missing_file_is_66(tmp_path, capsys):
    code, _, err = _run([tmp_path / "absent.csv"], capsys)
    assert code == 66 and "absent.csv" in err and err.count("\n") == 1


def test_test_file_without_a_training_sensor_is_65(runs, tmp_path, capsys):
    lines = (runs / "test.csv").read_text().splitlines()
    cut = [",".join(c for i, c in enumerate(l.split(",")) if i != 4) for l in lines]   # drop t_motor_c
    p = tmp_path / "test_nomotor.csv"
    p.write_text("\n".join(cut) + "\n")
    code, _, err = _run([runs / "train.csv", "--test", p], capsys)
    assert code == 65 and "t_motor_c" in err and err.count("\n") == 1


def test_too_few_rows_is_65(tmp_path, capsys):
    p = tmp_path / "short.csv"
    p.write_text("time_s,t_motor_c,displacement_um\n" + "".join(f"{6 * k},{20 + k / 16},{k}\n" for k in range(12)))
    code, _, err = _run([p], capsys)
    assert code == 65 and "too few" in err and "Traceback" not in err


@pytest.mark.skipif(not (ROOT / "lathed" / "cli" / "main.py").exists(), reason="lathectl not present")
def test_through_lathectl(runs):
    env = dict(os.environ, MPLBACKEND="Agg")
    r = subprocess.run([sys.executable, "-m", "lathed.cli.main", "analyze", "thermal",
                        str(runs / "train.csv"), "--test", str(runs / "test.csv"), "--json"],
                       capture_output=True, text=True, env=env, cwd=ROOT, timeout=60)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["effects"][0]["effect"] == "speed"
    bad = subprocess.run([sys.executable, "-m", "lathed.cli.main", "analyze", "thermal", "/nonexistent.csv"],
                         capture_output=True, text=True, env=env, cwd=ROOT, timeout=60)
    assert bad.returncode == 66 and "Traceback" not in bad.stderr


def test_temperatures_that_never_change_are_65(tmp_path, capsys):
    p = tmp_path / "flat.csv"
    p.write_text("time_s,t_motor_c,displacement_um\n" + "".join(f"{6 * k},20.0,{k % 3}\n" for k in range(100)))
    code, out, err = _run([p], capsys)
    assert code == 65 and out == "" and "no temperature column changed" in err and err.count("\n") == 1


def test_sim_thermal_run_writes_a_pair_the_analysis_reads(tmp_path):
    """The README's walk-through: two simulated shifts with an undeclared
    effect, written by lathectl, analysed by lathectl."""
    def ctl(*a):
        return subprocess.run([sys.executable, "-m", "lathed.cli.main", *map(str, a)], capture_output=True,
                              text=True, cwd=ROOT, timeout=120)
    for name, seed in (("train", 4), ("test", 104)):
        r = ctl("sim", "thermal-run", tmp_path / f"{name}.csv", "--effect", "nonlinear", "--hours", "4",
                "--seed", seed)
        assert r.returncode == 0 and "effects: nonlinear" in r.stdout, r.stderr
    r = ctl("analyze", "thermal", tmp_path / "train.csv", "--test", tmp_path / "test.csv", "--json")
    js = json.loads(r.stdout)
    assert js["effects"][0]["effect"] == "nonlinear" and js["rows"]["used"] == 2400
    assert js["final"]["test_rmse_um"] < 0.4 * js["start"]["test_rmse_um"]
    bad = ctl("sim", "thermal-run", tmp_path / "no" / "such" / "dir.csv")
    assert bad.returncode == 73 and bad.stderr.count("\n") == 1 and "cannot write" in bad.stderr


def test_sim_thermal_run_writes_the_second_pass_runs(tmp_path):
    """Many sensors and an off-library cycle, as `sim thermal-run` writes them for the README."""
    from lathed.cli import sim
    p = argparse.ArgumentParser(prog="lathectl")
    sub = p.add_subparsers(dest="cmd", required=True)
    sim.register(sub)
    out = tmp_path / "many.csv"
    args = p.parse_args(["sim", "thermal-run", str(out), "--sensors", "16", "--row-s", "60", "--hours", "2",
                         "--periodic-min", "20", "--speed-step-um", "3", "--seed", "5"])
    assert args.func(args) == 0
    head = out.read_text().splitlines()[0].split(",")
    temps = [c for c in head if c.startswith("t_") and c.endswith("_c")]
    assert len(temps) == 16 and head[0] == "time_s" and head[-1] == "displacement_um"
    assert len(out.read_text().splitlines()) == 1 + 120


def _shift(src, dst, machine_c, room_c):
    """``src`` on another day: the iron ``machine_c`` warmer, the room's air ``room_c`` warmer."""
    head, rows = _rows(src)
    cols = head.split(",")
    out = []
    for r in rows:
        cells = r.split(",")
        out.append(",".join(f"{float(c) + (room_c if 'room' in k else machine_c):.4f}" if k.startswith("t_") else c
                             for k, c in zip(cols, cells)))
    dst.write_text("\n".join([head, *out]) + "\n")
    return dst


def test_several_runs_each_from_its_own_cold_start(runs, tmp_path, capsys):
    # the second day's machine soaked 2 °C warmer, its room still 1.5 °C below it: a cold start
    day2 = _shift(runs / "test.csv", tmp_path / "day2.csv", 2.0, 0.5)
    code, out, err = _run([runs / "train.csv", day2, "--json"], capsys)
    assert code == 0, err
    doc = json.loads(out)
    n1 = len(_rows(runs / "train.csv")[1])
    assert set(doc["rows"]["runs"]) == {str(runs / "train.csv"), str(day2)}
    assert doc["rows"]["used"] == n1 and doc["effects"][0]["effect"] == "speed"
    # a really warm second run is refused, naming it
    head, rows = _rows(runs / "test.csv")
    half = rows[len(rows) // 2:]
    t0 = float(half[0].split(",")[0])
    warm = tmp_path / "warm.csv"
    warm.write_text("\n".join([head, *(",".join([f"{float(r.split(',')[0]) - t0:.1f}", *r.split(",")[1:]])
                                        for r in half)]) + "\n")
    code, out, err = _run([runs / "train.csv", warm], capsys)
    assert code == 65 and out == "" and err.startswith(f"lathectl: {warm} does not start cold: t_"), err
    assert err.count("\n") == 1
