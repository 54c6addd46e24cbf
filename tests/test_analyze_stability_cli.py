import argparse
import json
import re
import subprocess
import sys

import pytest

from lathed.analysis.cuts import write_cuts_csv
from lathed.analysis.stability.cases import generate_cuts, true_dynamics
from lathed.cli import analyze_stability

MODEL = ["--mode", "620,0.035,3e7,30", "--mode", "1450,0.05,9e7,60", "--kf", "2e9"]
HEADER = "machine,tool,material,rpm,depth_mm,feed_mm_rev,outcome,chatter_frequency_hz\n"


def _run(argv, capsys):
    p = argparse.ArgumentParser(prog="lathectl analyze")
    sub = p.add_subparsers(dest="what", required=True)
    analyze_stability.register_analyze(sub)
    args = p.parse_args(["stability", *argv])
    code = args.func(args)
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def pd_csv(tmp_path_factory):
    path = tmp_path_factory.mktemp("cuts") / "pd.csv"
    write_cuts_csv(generate_cuts(true_dynamics("process_damping"), 300, seed=11), path)
    return path


def test_json_names_the_effect_and_plot_is_written(pd_csv, tmp_path, capsys):
    png = tmp_path / "lobes.png"
    code, out, err = _run([str(pd_csv), *MODEL, "--json", "--plot", str(png)], capsys)
    assert code == 0, err
    doc = json.loads(out)
    assert [e["effect"] for e in doc["effects"]] == ["process_damping"]
    assert doc["effects"][0]["c_rpm"] == pytest.approx(20.0, rel=0.25)
    assert doc["after"]["accuracy"] > doc["before"]["accuracy"]
    assert doc["after"]["false_stable_rate"] <= 0.05
    assert doc["train"] == 210 and doc["heldout"] == 90
    assert doc["residual_all_cuts"]["misclassified"], "the given model misses low-speed cuts"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_text_report_on_matching_dynamics(tmp_path, capsys):
    path = tmp_path / "none.csv"
    write_cuts_csv(generate_cuts(true_dynamics("none"), 200, seed=12), path)
    code, out, err = _run([str(path), *MODEL], capsys)
    assert code == 0, err
    assert "before: held-out accuracy" in out and "after: held-out accuracy" in out
    assert "no effect added" in out


def test_bad_rows_one_line_each_exit_65(tmp_path, capsys):
    p = tmp_path / "bad.csv"
    p.write_text(HEADER + "l1,T1,C45,1850,1.2,0.25,stable,\nl1,T1,C45,1850,deep,0.25,stable,\n"
                          "l1,T1,C45,1900,1.2,0.25,stable,\nl1,T1,C45,1850,1.2,0.25,chattr,\n")
    code, out, err = _run([str(p), *MODEL], capsys)
    assert code == 65 and out == ""
    lines = err.splitlines()
    assert len(lines) == 2 and all(ln.startswith("lathectl: ") for ln in lines)
    assert f"{p}:3" in lines[0] and "column depth_mm" in lines[0]
    assert f"{p}:5" in lines[1] and "column outcome" in lines[1]


def test_missing_file_exit_66(tmp_path, capsys):
    code, _, err = _run([str(tmp_path / "nope.csv"), *MODEL], capsys)
    assert code == 66 and err.count("\n") == 1 and "nope.csv" in err


def test_several_setups_must_be_chosen(tmp_path, capsys):
    p = tmp_path / "two.csv"
    rows = "".join(f"l1,T{1 + i % 2},C45,{1000 + 10 * i},1.0,0.25,stable,\n" for i in range(30))
    p.write_text(HEADER + rows)
    code, _, err = _run([str(p), *MODEL], capsys)
    assert code == 65 and err.count("\n") == 1
    assert "2 set-ups" in err and "l1/T1/C45" in err and "--tool" in err
    # choosing one leaves 15 cuts: too few to hold any out
    code, _, err = _run([str(p), *MODEL, "--tool", "T2"], capsys)
    assert code == 65 and "too few" in err and err.count("\n") == 1


def test_module_import_stays_light():
    code = ("import sys; import lathed.cli.analyze_stability; "
            "print(sorted(m for m in ('numpy', 'matplotlib', 'scipy') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_mode_at_right_angle_is_invalid_data(pd_csv, capsys):
    code, out, err = _run([str(pd_csv), "--mode", "620,0.035,3e7,90", "--kf", "2e9"], capsys)
    assert code == 65 and out == "" and err.count("\n") == 1
    assert err.startswith("lathectl: ") and "90 deg" in err


def test_a_misspelled_optional_column_is_said(tmp_path, capsys):
    # chatter_freq_hz for chatter_frequency_hz: read as "no chatter frequency measured" before, silently
    src = tmp_path / "none.csv"
    write_cuts_csv(generate_cuts(true_dynamics("none"), 200, seed=12), src)
    p = tmp_path / "typo.csv"
    p.write_text(src.read_text().replace("chatter_frequency_hz", "chatter_freq_hz", 1))
    code, out, err = _run([str(p), *MODEL], capsys)
    assert code == 0 and err.count("\n") == 1
    assert err.startswith(f"lathectl: warning: {p}:1: column(s) 'chatter_freq_hz' ignored (known: machine,"), err


@pytest.fixture(scope="module")
def lathe_csv(tmp_path_factory):
    from lathed.analysis.stability import StabilityModel
    from lathed.sim.lathe import LATHE_KF, LATHE_MODES
    lathe = StabilityModel(LATHE_MODES, LATHE_KF)
    path = tmp_path_factory.mktemp("cuts") / "lathe.csv"
    write_cuts_csv(generate_cuts(lathe, 80, given=lathe, seed=5), path)
    return path


def test_without_a_modal_model_it_learns_one_from_the_cuts_and_says_how_sure(lathe_csv, tmp_path, capsys):
    png = tmp_path / "learned.png"
    code, out, err = _run([str(lathe_csv), "--plot", str(png)], capsys)
    assert code == 0, err
    assert "no modal model given, learned from the first 56 cuts alone" in out
    assert re.search(r"^mode 1: 1[89]\d\.\d Hz", out, re.M), out
    assert "minimum stable depth:" in out and "90 %:" in out
    assert "trusted: classifies the later cuts well" in out and out.count("best speed:") >= 1
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    code, out, err = _run([str(lathe_csv), "--json"], capsys)
    doc = json.loads(out)["learned"]
    assert code == 0 and doc["trusted"] is True and doc["why_not"] == [] and doc["cuts"] == 80
    assert doc["model"]["modes"][0]["fn_hz"] == pytest.approx(190.0, rel=0.02)
    lo_hi = doc["b_min_mm"]
    assert lo_hi[1] <= lo_hi[0] <= lo_hi[2] and all(p["rpm"][1] <= p["rpm"][0] <= p["rpm"][2] for p in doc["best_rpm"])


def test_without_a_modal_model_too_few_cuts_is_one_line_exit_65(tmp_path, capsys):
    path = tmp_path / "few.csv"
    write_cuts_csv(generate_cuts(true_dynamics("none"), 30, seed=12), path)
    code, out, err = _run([str(path)], capsys)
    assert code == 65 and out == "" and err.count("\n") == 1
    assert "30 cut speeds; a model needs at least 40" in err


def test_a_modal_model_without_its_kf_is_a_usage_error(lathe_csv, capsys):
    code, out, err = _run([str(lathe_csv), "--mode", "190,0.03,7.5e7,0"], capsys)
    assert code == 2 and err.startswith("lathectl: --kf is needed with --mode")
