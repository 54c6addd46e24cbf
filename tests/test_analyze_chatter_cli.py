import argparse
import json
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.io.wavfile as wavfile

from lathed.analysis.recording import read_signal
from lathed.analysis.regen import Segment, simulate_cut
from lathed.cli import analyze_chatter

RATE = 51200


def _parser():
    ap = argparse.ArgumentParser(prog="lathectl analyze")
    analyze_chatter.register_analyze(ap.add_subparsers(dest="what"))
    return ap


def _cli(argv, capsys):
    args = _parser().parse_args(["chatter", *argv])
    code = args.func(args)
    out, err = capsys.readouterr()
    return code, out, err


def _wav_pcm24(path: Path, x: np.ndarray, channels: int = 1) -> None:
    """24-bit PCM WAV written by hand (scipy cannot write 24-bit)."""
    ints = np.clip(np.round(x * (2 ** 23 - 1)), -2 ** 23, 2 ** 23 - 1).astype(np.int32)
    frames = np.repeat(ints[:, None], channels, axis=1).ravel()
    b = frames.astype("<i4").view(np.uint8).reshape(-1, 4)[:, :3].tobytes()
    fmt = struct.pack("<HHIIHH", 1, channels, RATE, RATE * 3 * channels, 3 * channels, 24)
    body = b"WAVE" + b"fmt " + struct.pack("<I", len(fmt)) + fmt + b"data" + struct.pack("<I", len(b)) + b
    path.write_bytes(b"RIFF" + struct.pack("<I", len(body)) + body)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("rec")
    ch = simulate_cut([Segment(0.6, 2000, 1.0), Segment(0.6, 2000, 3.0)], seed=31)
    st = simulate_cut([Segment(1.0, 2000, 1.0)], seed=32)
    chs = ch.signal / np.abs(ch.signal).max() * 0.9
    sts = st.signal / np.abs(st.signal).max() * 0.5
    wavfile.write(d / "chatter_f32.wav", RATE, chs.astype(np.float32))
    _wav_pcm24(d / "stable_24.wav", sts)
    stereo = np.c_[np.zeros_like(chs) + 1e-3 * np.sin(np.arange(len(chs))), chs]
    wavfile.write(d / "stereo_i16.wav", RATE, (stereo * 32767).astype(np.int16))
    clipped = np.clip(chs * 3, -1, 1)
    wavfile.write(d / "clipped_i16.wav", RATE, np.round(clipped * 32767).astype(np.int16))
    t = np.arange(len(sts)) / RATE
    np.savetxt(d / "stable.csv", np.c_[t, sts], delimiter=",", header="time_s,accel_g", comments="")
    np.savetxt(d / "bare.csv", sts[:20000])
    (d / "empty.csv").write_text("")
    (d / "nan.csv").write_text("time_s,a\n" + "".join(f"{i / RATE},nan\n" for i in range(100)))
    (d / "badcell.csv").write_text("time_s,a\n0,1\n0.0001,x2\n")
    return d, ch, st


def test_json_contract_chatter(files, capsys):
    d, ch, _ = files
    code, out, err = _cli([str(d / "chatter_f32.wav"), "--rpm", "2000", "--json"], capsys)
    assert code == 0
    obj = json.loads(out)
    assert {"verdict", "first_alarm_s", "chatter_frequency_hz", "detector", "windows"} <= set(obj)
    assert obj["verdict"] == "chatter"
    assert ch.unstable_at_s <= obj["first_alarm_s"] <= ch.visible_at_s + 0.1
    assert 550 < obj["chatter_frequency_hz"] < 750
    assert obj["detector"] == analyze_chatter.DEFAULT_DETECTOR
    w = obj["windows"][0]
    assert set(w) == {"t_s", "index", "alarm"}
    assert any(w["alarm"] for w in obj["windows"])


def test_stable_24bit_and_csv(files, capsys):
    d, _, _ = files
    for f in ("stable_24.wav", "stable.csv"):
        code, out, _ = _cli([str(d / f), "--rpm", "2000", "--json", "--detector", "chaos_sync"], capsys)
        obj = json.loads(out)
        assert code == 0 and obj["first_alarm_s"] is None and obj["chatter_frequency_hz"] is None
        # without a reference, no onset alone is not "stable" (a recording that chatters from its
        # first sample shows none either, issue 12): the whole recording's evidence says so
        # (broadband, Gaussian, its level held: lathed.analysis.chatter.verdict)
        assert obj["verdict"] == "stable" and obj["baseline"] == "recording start"
        assert obj["evidence"]["verdict"] == "stable" and "level held" in obj["reason"]
    ref = d / "stable.csv"
    code, out, _ = _cli([str(d / "stable_24.wav"), "--rpm", "2000", "--json", "--reference", str(ref)], capsys)
    obj = json.loads(out)
    assert code == 0 and obj["verdict"] == "stable" and obj["baseline"] == "reference", obj["notes"]


def test_24bit_reader_matches_values(files):
    d, _, st = files
    sig = read_signal(d / "stable_24.wav")
    ref = st.signal / np.abs(st.signal).max() * 0.5
    np.testing.assert_allclose(sig.data, ref, atol=2 ** -22)
    assert sig.rate_hz == RATE and sig.clipped == 0


def test_channel_selection(files, capsys):
    d, _, _ = files
    code, out, _ = _cli([str(d / "stereo_i16.wav"), "--rpm", "2000", "--channel", "1", "--json"], capsys)
    assert code == 0 and json.loads(out)["verdict"] == "chatter"
    code, _, err = _cli([str(d / "stereo_i16.wav"), "--rpm", "2000", "--channel", "2"], capsys)
    assert code == 65 and "channel 2 does not exist (file has 2" in err


def test_clipping_reported(files, capsys):
    d, _, _ = files
    code, out, err = _cli([str(d / "clipped_i16.wav"), "--rpm", "2000", "--json"], capsys)
    assert code == 0
    assert json.loads(out)["clipped_samples"] > 0
    assert err.startswith("lathectl: warning:") and "clipped samples" in err


@pytest.mark.parametrize("name,argv,code,msg", [
    ("missing.wav", ["--rpm", "2000"], 66, "no such file"),
    ("empty.csv", ["--rpm", "2000"], 65, "is empty"),
    ("nan.csv", ["--rpm", "2000"], 65, "every sample is NaN"),
    ("bare.csv", ["--rpm", "2000"], 65, "give --rate"),
    ("badcell.csv", ["--rpm", "2000"], 65, "line 3, column 'a': 'x2' is not a number"),
    ("bare.csv", ["--rpm", "2000", "--rate", "51200", "--detector", "nope"], 2, "unknown chatter detector"),
    # both were taken without a word: --var means something in a .mat or TDMS file only, and a
    # --param given twice kept the last
    ("chatter_f32.wav", ["--rpm", "2000", "--var", "accel"], 2,
     "chatter_f32.wav: --var names a variable of a .mat file or a channel of a TDMS file; a WAV file has none"),
    ("stable.csv", ["--rpm", "2000", "--var", "accel"], 2, "a CSV file has none"),
    ("chatter_f32.wav", ["--rpm", "2000", "--param", "threshold=2", "--param", "threshold=50"], 2,
     "--param threshold given twice"),
])
def test_bad_input_one_line(files, capsys, name, argv, code, msg):
    d, _, _ = files
    got, out, err = _cli([str(d / name), *argv], capsys)
    assert got == code
    assert msg in err and err.startswith("lathectl: ") and err.count("\n") == 1
    assert "Traceback" not in err and out == ""


def test_var_names_the_mat_files_variable_and_a_wav_reference_is_read_without_it(files, capsys, tmp_path):
    from scipy.io import savemat
    d, _, _ = files
    rate, x = wavfile.read(d / "chatter_f32.wav")
    savemat(tmp_path / "cut.mat", {"accel": x.astype(float), "other": np.arange(3.0)})
    code, out, err = _cli([str(tmp_path / "cut.mat"), "--var", "accel", "--rate", str(rate), "--rpm", "2000",
                           "--reference", str(d / "stable_24.wav"), "--json"], capsys)
    assert code == 0, err
    assert json.loads(out)["verdict"] == "chatter"


def test_rpm_must_be_positive(files, capsys):
    d, _, _ = files
    with pytest.raises(SystemExit) as e:
        _parser().parse_args(["chatter", str(d / "bare.csv"), "--rpm", "0"])
    assert e.value.code == 2
    assert "must be a positive number" in capsys.readouterr().err


def test_plot_written(files, capsys, tmp_path):
    d, _, _ = files
    out_png = tmp_path / "eye.png"
    code, _, _ = _cli([str(d / "chatter_f32.wav"), "--rpm", "2000", "--plot", str(out_png)], capsys)
    assert code == 0 and out_png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_through_lathectl(files):
    d, _, _ = files
    r = subprocess.run([sys.executable, "-m", "lathed.cli.main", "analyze", "chatter",
                        str(d / "chatter_f32.wav"), "--rpm", "2000", "--json"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["verdict"] == "chatter"
    r = subprocess.run([sys.executable, "-m", "lathed.cli.main", "analyze", "chatter",
                        str(d / "nothere.wav"), "--rpm", "2000"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 66 and r.stderr.startswith("lathectl: no such file")


def test_csv_flat_tops_reported_as_clipping(tmp_path):
    x = np.sin(np.linspace(0, 40 * np.pi, 4000)) * 1.5
    x = np.clip(x, -1.0, 1.0)
    f = tmp_path / "clip.csv"
    np.savetxt(f, x)
    sig = read_signal(f, rate_hz=RATE)
    assert sig.clipped > 100 and sig.first_clip_s is not None
    np.savetxt(f, np.sin(np.linspace(0, 40 * np.pi, 4001)))
    assert read_signal(f, rate_hz=RATE).clipped == 0


def test_a_valid_1hz_wav_is_one_line_not_a_traceback(tmp_path, capsys):
    """issue 18 D5: a 1 Hz recording raised ZeroDivisionError (a zero-sample window)."""
    p = tmp_path / "slow.wav"
    wavfile.write(p, 1, (np.sin(np.arange(200) * 0.3) * 10000).astype(np.int16))
    code, out, err = _cli([str(p), "--rpm", "1000"], capsys)
    assert code == 65 and out == ""
    assert err == f"lathectl: sample rate 1 Hz is outside the 100..1e+06 Hz of an accelerometer recording ({p})\n"


def test_rpm_beyond_any_spindle_is_a_usage_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        _parser().parse_args(["chatter", str(tmp_path / "x.wav"), "--rpm", "1e308"])
    assert e.value.code == 2 and "1e308 r/min is beyond any spindle" in capsys.readouterr().err


def test_float_wav_in_physical_units_is_not_clipped_and_nan_is_not_a_clip(tmp_path):
    """issue 18 D12: a float WAV in m/s² peaking above 1.0 got "clipped samples" warnings; inf counted as clips."""
    x = (np.sin(np.arange(RATE) * 0.05) * 30.0).astype(np.float32)
    x[100:110] = np.inf
    p = tmp_path / "ms2.wav"
    wavfile.write(p, RATE, x)
    sig = read_signal(p)
    assert sig.clipped == 0 and "10 NaN/infinite samples filled" in sig.notes[0]
    # a float recording that did saturate still shows it: flat tops at its extremes
    x = np.clip(np.sin(np.arange(RATE) * 0.05) * 30.0, -20.0, 20.0).astype(np.float32)
    wavfile.write(p, RATE, x)
    assert read_signal(p).clipped > 0


def test_params_lists_a_detectors_options_without_a_file(capsys):
    with pytest.raises(SystemExit) as e:
        _parser().parse_args(["chatter", "--params"])
    out = capsys.readouterr().out
    assert e.value.code == 0
    assert out.startswith("sync_cusum options") and "follow_quantile  0.9" in out and "threshold" in out
    with pytest.raises(SystemExit) as e:
        _parser().parse_args(["chatter", "--params", "chaos_sync"])
    assert e.value.code == 0 and "follow_quantile  0 " in capsys.readouterr().out


def test_param_reaches_the_detector(files, capsys):
    d, _, _ = files
    argv = [str(d / "chatter_f32.wav"), "--rpm", "2000", "--json"]
    code, out, _ = _cli(argv, capsys)
    assert code == 0 and json.loads(out)["verdict"] == "chatter"
    # a threshold no window reaches, no CUSUM and no growth test: the same recording shows no onset
    code, out, _ = _cli(argv + ["--param", "threshold=1000", "--param", "cusum_ratio=0",
                                "--param", "growth_ratio=0"], capsys)
    obj = json.loads(out)
    assert code == 0 and obj["first_alarm_s"] is None and obj["alarm_spans_s"] == []
    # the recording chatters throughout: its evidence says so without an onset
    assert obj["verdict"] == "chatter" and obj["evidence"]["verdict"] == "chatter"


@pytest.mark.parametrize("param, msg", [
    ("threshold=0.5", "threshold = 0.5 is outside [1.05, 1000] (--param)"),
    ("nope=1", "unknown parameter(s) nope"),
    # a count of 4.7 windows was taken (and used as 4 or 5)
    ("learn_windows=4.7", "learn_windows: expected a whole number (a count), got 4.7 (--param)"),
])
def test_a_bad_param_is_one_usage_line(files, capsys, param, msg):
    d, _, _ = files
    code, out, err = _cli([str(d / "chatter_f32.wav"), "--rpm", "2000", "--param", param], capsys)
    assert code == 2 and msg in err and err.count("\n") == 1 and out == ""


def test_param_not_key_value_is_refused_by_the_parser(capsys):
    with pytest.raises(SystemExit) as e:
        _parser().parse_args(["chatter", "x.wav", "--rpm", "2000", "--param", "threshold"])
    assert e.value.code == 2 and "is not KEY=NUMBER" in capsys.readouterr().err


def test_alarm_spans_say_when_each_alarm_was_raised_and_cleared(files, capsys):
    """An alarm that clears and comes back is two spans, not one from the first alarm on
    (the plot shaded everything after the first alarm)."""
    from lathed.analysis.chatter.windows import Window
    wins = [Window(t, 1.0, 2.0, a) for t, a in [(1, False), (2, True), (3, True), (4, False), (5, True)]]
    assert analyze_chatter._alarm_spans(wins) == [(2, 4), (5, None)]
    assert analyze_chatter._alarm_spans(wins[:1]) == []
    d, _, _ = files
    code, out, _ = _cli([str(d / "chatter_f32.wav"), "--rpm", "2000", "--json"], capsys)
    obj = json.loads(out)
    on = [w["t_s"] for w in obj["windows"] if w["alarm"]]
    assert obj["alarm_spans_s"] and obj["alarm_spans_s"][0][0] == obj["first_alarm_s"] == on[0]
    inside = [w["t_s"] for w in obj["windows"]
              if any(a <= w["t_s"] < (b if b is not None else float("inf")) for a, b in obj["alarm_spans_s"])]
    assert inside == on
    code, out, _ = _cli([str(d / "chatter_f32.wav"), "--rpm", "2000"], capsys)
    assert "alarm on " in out


def test_a_csv_of_only_comments_after_its_header_is_one_line(tmp_path, capsys):
    p = tmp_path / "comments.csv"
    p.write_text("time_s,a\n# exported by the logger\n#\n")
    code, _, err = _cli([str(p), "--rpm", "1000"], capsys)
    assert code == 65 and err.count("\n") == 1 and "no data rows" in err and "Warning" not in err


@pytest.mark.parametrize("rows, msg", [
    (["0,1", "0.0001,2,7", "0.0002,3"], "line 3 has 3 fields, the header 2"),
    (["0,1", "nan,2", "0.0002,3"], "line 3, column 'time_s': nan is not a time"),
    (["0,1", "0.0001,2", "0.0003,3", "0.0004,1"], "line 4: step 0.0002 s"),     # a dropped sample
])
def test_a_csv_row_that_would_be_misread_is_one_line(tmp_path, capsys, rows, msg):
    p = tmp_path / "rows.csv"
    p.write_text("time_s,a\n" + "\n".join(rows) + "\n")
    code, _, err = _cli([str(p), "--rpm", "1000"], capsys)
    assert code == 65 and err.count("\n") == 1 and msg in err, err


def test_times_printed_to_the_microsecond_at_51_2_khz_are_evenly_spaced(tmp_path):
    # 19.53125 us printed as 0.000020, 0.000039, 0.000059...: the last digit steps unevenly
    n = 51200
    x = np.sin(2 * np.pi * 190 * np.arange(n) / 51200) + 0.01 * np.random.default_rng(1).standard_normal(n)
    p = tmp_path / "us.csv"
    np.savetxt(p, np.c_[np.arange(n) / 51200, x], delimiter=",", fmt=["%.6f", "%.6g"], header="time_s,a",
               comments="")
    sig = read_signal(p)
    assert sig.rate_hz == pytest.approx(51200, rel=1e-6)
