import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from lathed.cli import analyze_lobes

ROOT = Path(__file__).resolve().parents[1]


def _parser():
    p = argparse.ArgumentParser(prog="lathectl analyze")
    sub = p.add_subparsers(dest="what", required=True)
    analyze_lobes.register_analyze(sub)
    return p


def _run(argv, capsys):
    args = _parser().parse_args(argv)
    code = args.func(args)
    out, err = capsys.readouterr()
    return code, out, err


def test_json_contract(capsys):
    code, out, err = _run(["lobes", "--mode", "250,0.03,2e7", "--kf", "1e9",
                           "--rpm", "2000", "--range", "1000:4000", "--json"], capsys)
    assert code == 0, err
    doc = json.loads(out)
    assert doc["b_lim_min_mm"] == pytest.approx(2 * 2e7 * 0.03 * 1.03 / 1e9 * 1e3, rel=0.005)
    assert doc["chatter_frequency_hz"] == pytest.approx(250 * 1.06 ** 0.5, rel=0.005)
    assert doc["b_lim_mm_at_rpm"] >= doc["b_lim_min_mm"]
    assert doc["lobes"], "no lobes in range"
    for lobe in doc["lobes"]:
        assert set(lobe) == {"k", "rpm", "b_lim_mm"}
        assert len(lobe["rpm"]) == len(lobe["b_lim_mm"]) > 0
        assert min(lobe["rpm"]) >= 1000 and max(lobe["rpm"]) <= 4000
    # 250 Hz chatter at 1000..4000 r/min: about 60*250/n waves per revolution
    assert {lobe["k"] for lobe in doc["lobes"]} >= {4, 5, 6, 7, 8, 9, 10, 11, 12, 13}


def test_text_output_and_plot(tmp_path, capsys):
    png = tmp_path / "lobes.png"
    code, out, err = _run(["lobes", "--mode", "250,0.03,2e7", "--mode", "600,0.02,4e7,45",
                           "--kf", "1e9", "--plot", str(png)], capsys)
    assert code == 0, err
    assert "b_lim,min" in out
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_unwritable_plot_is_one_line_error(tmp_path, capsys):
    code, out, err = _run(["lobes", "--mode", "250,0.03,2e7", "--kf", "1e9",
                           "--plot", str(tmp_path / "missing" / "x.png")], capsys)
    assert code != 0
    assert err.startswith("lathectl: ") and err.count("\n") == 1
    assert "missing" in err


@pytest.mark.parametrize("argv,needle", [
    (["lobes", "--mode", "250,0.03", "--kf", "1e9"], "FN_HZ,ZETA,K_N_PER_M"),
    (["lobes", "--mode", "250,1.5,2e7", "--kf", "1e9"], "damping ratio"),
    # inf and nan passed the range checks (nan theta every one): lobes of nan
    (["lobes", "--mode", "250,0.03,inf", "--kf", "1e9"],
     "mode '250,0.03,inf': stiffness K_N_PER_M must be a finite number, got inf"),
    (["lobes", "--mode", "250,0.03,2e7,nan", "--kf", "1e9"],
     "mode '250,0.03,2e7,nan': angle THETA_DEG must be a finite number, got nan"),
    (["lobes", "--mode", "inf,0.03,2e7", "--kf", "1e9"], "natural frequency FN_HZ must be a finite number"),
    (["lobes", "--mode", "250,0.03,2e7", "--kf", "-3"], "positive"),
    (["lobes", "--mode", "250,0.03,2e7", "--kf", "1e9", "--range", "4000:1000"], "MIN must be below"),
])
def test_bad_arguments_are_usage_errors(argv, needle, capsys):
    with pytest.raises(SystemExit) as exc:
        _parser().parse_args(argv)
    assert exc.value.code == 2
    assert needle in capsys.readouterr().err


def test_mode_at_right_angle_is_invalid_data(capsys):
    code, out, err = _run(["lobes", "--mode", "250,0.03,2e7,90", "--kf", "1e9"], capsys)
    assert code == 65
    assert err.startswith("lathectl: ") and "90 deg" in err


def test_through_lathectl():
    proc = subprocess.run([sys.executable, "-m", "lathed.cli.main", "analyze", "lobes",
                           "--mode", "250,0.03,2e7", "--kf", "1e9", "--rpm", "1500", "--json"],
                          capture_output=True, text=True, timeout=60, cwd=ROOT,
                          env={**os.environ, "MPLBACKEND": "Agg"})
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    assert doc["b_lim_mm_at_rpm"] >= doc["b_lim_min_mm"] > 0


def test_depth_gives_how_fast_chatter_grows(capsys):
    # the live lathe's structure: 3 mm at 2000 r/min is above its 2.54 mm limit, 2 mm below
    argv = ["lobes", "--mode", "190,0.03,7.5e7", "--mode", "620,0.035,4e8,30", "--kf", "2e9", "--rpm", "2000"]
    code, out, err = _run(argv + ["--depth", "3", "--json"], capsys)
    assert code == 0, err
    g = json.loads(out)["growth_at_depth"]
    assert g["sigma_per_s"] > 0 and 1.0 < g["per_rev"] < 1.2 and 180 < g["frequency_hz"] < 210
    code, out, err = _run(argv + ["--depth", "2"], capsys)
    assert code == 0 and "stable, a disturbance at" in out and "halves in" in out, out
    code, out, err = _run(argv + ["--depth", "3"], capsys)
    assert "unstable, chatter at" in out and "doubles in" in out, out


def test_depth_without_rpm_is_one_line(capsys):
    code, out, err = _run(["lobes", "--mode", "250,0.03,2e7", "--kf", "1e9", "--depth", "1"], capsys)
    assert code == 64 and err.strip() == "lathectl: --depth needs --rpm (the growth is at one speed)"


def test_a_depth_beyond_a_turning_cut_is_refused(capsys):
    with pytest.raises(SystemExit) as e:
        _parser().parse_args(["lobes", "--mode", "250,0.03,2e7", "--kf", "1e9", "--rpm", "1000", "--depth", "150"])
    assert e.value.code == 2 and "a turning cut is at most 100 mm deep" in capsys.readouterr().err
