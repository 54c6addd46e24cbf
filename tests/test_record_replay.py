"""lathectl record's two halves without a daemon: the daemon's Recording (lathed.recorder) on
a real bus, the client's WAV and sidecar (lathed.cli.record), and `lathectl analyze chatter`
replaying such a recording as the live analyzer ran it (lathed.analysis.replay)."""
from __future__ import annotations

import asyncio
import base64
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lathed.analysis.chatter.registry import make_detector
from lathed.analysis.recording import read_signal
from lathed.bus import Block, Bus, Sample
from lathed.cli.record import Capture, sidecar
from lathed.control import RequestError
from lathed.recorder import Recorder

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "turning-chatter"
RATE = 48000.0
T0 = 1_800_000_000.0


def cut_signal() -> tuple[np.ndarray, int, int]:
    """Air, the real chatter recording c_425_020 (Khasawneh et al., CC BY 4.0) at 48 kS/s, air."""
    import scipy.io as sio
    from scipy.signal import resample_poly
    x = sio.loadmat(REAL / "c_425_020.mat")["tsDS"][:, 1]
    rec = resample_poly(x - x.mean(), 24, 5)
    air = np.random.default_rng(0).normal(0, rec.std() / 10, int(RATE))
    return np.concatenate([air, rec, air]).astype(np.float32), len(air), len(air) + len(rec)


def write_recording(path: Path, x: np.ndarray, cut: tuple[int, int], gap: tuple[int, int] | None = None,
                    alarms: list | None = None) -> dict:
    """What `lathectl record` writes, from blocks and samples as the daemon streams them."""
    cap = Capture(path)
    seq = 5000
    for i in range(0, len(x), 1024):
        if gap and i == gap[0]:
            seq += gap[1]                 # samples the stream lost here
        b = x[i:i + 1024]
        cap.block(seq, T0 + (seq - 5000) / RATE, None, RATE, base64.b64encode(b.astype("<f4").tobytes()).decode())
        seq += len(b)
    t = lambda i: T0 + i / RATE       # noqa: E731  (host time of WAV sample i, no gap before it)
    samples = [[T0 - 0.05 + k * 0.1, "lathe", "spindle_rpm", 425.0] for k in range(int(len(x) / RATE * 10))]
    samples += [[t(cut[0]), "chatter", "cutting", 1.0], [t(cut[1]), "chatter", "cutting", 0.0]]
    samples += alarms or []
    samples.sort()
    cap.wav.close()
    first = {"source": "accel", "plugin": "audio_input", "daemon": "test",
             "sensor": {"calibration": "100 mV/g, interface full scale 5 V", "quantity": "acceleration",
                        "unit": "m/s²"},
             "context": {"analyzer": "chatter", "machine": "lathe", "tool": "T0101", "material": "C45",
                         "detector": "sync_cusum", "params": {}, "cut_from": ["vibration"]}}
    meta = sidecar(first, cap, samples, "1 cut(s) recorded")
    path.with_suffix(".json").write_text(json.dumps(meta))
    return meta


def analyze(*args: str) -> tuple[int, str, str]:
    r = subprocess.run([sys.executable, "-m", "lathed.cli.main", "analyze", "chatter", *args],
                       capture_output=True, text=True, timeout=120)
    return r.returncode, r.stdout, r.stderr


need_real = pytest.mark.skipif(not (REAL / "README.md").exists(), reason=f"no shared recordings at {REAL}")


@need_real
def test_a_recording_is_replayed_cut_by_cut_at_its_recorded_speed(tmp_path):
    x, a, b = cut_signal()
    wav = tmp_path / "rec.wav"
    live = [[T0 + (a + 40000) / RATE, "chatter", "chatter_alarm", 1.0]]
    meta = write_recording(wav, x, (a, b), alarms=live)
    assert meta["cuts"] == [[pytest.approx(a / RATE, abs=1e-5), pytest.approx(b / RATE, abs=1e-5)]]
    sig = read_signal(wav)
    assert sig.rate_hz == RATE and np.array_equal(sig.data, x.astype(float))
    code, out, err = analyze(str(wav), "--json")
    assert code == 0, err
    res = json.loads(out)
    # the detector the daemon ran, on the cut alone, from its start, at 425 r/min
    det = make_detector("sync_cusum", RATE)
    wins = [w for i in range(a, b, 1024) for w in det.process(x[i:min(i + 1024, b)].astype(float), 425.0)]
    first = next(w.t_s for w in wins if w.alarm) + a / RATE
    assert res["verdict"] == "chatter" and res["first_alarm_s"] == pytest.approx(first, abs=1e-5)
    assert res["speed_from"] == "lathe spindle_rpm" and res["detector"] == "sync_cusum"
    assert res["live_alarm_spans_s"] == [[pytest.approx((a + 40000) / RATE, abs=1e-5), None]]
    assert res["tool"] == "T0101" and res["sensitivity"].startswith("100 mV/g")
    # the air before and after is not judged: no window outside the cut
    assert all(a / RATE < w["t_s"] <= b / RATE + 1e-6 for w in res["windows"])
    # --rpm and --detector override what was recorded
    code, out, err = analyze(str(wav), "--json", "--rpm", "500", "--detector", "sync_residual")
    assert code == 0 and json.loads(out)["speed_from"] == "--rpm" and json.loads(out)["detector"] == "sync_residual"


def test_lost_samples_are_zeros_in_the_wav_and_listed(tmp_path):
    x = np.random.default_rng(1).normal(0, 1, 20 * 1024).astype(np.float32)
    wav = tmp_path / "gap.wav"
    meta = write_recording(wav, x, (1024, 18 * 1024), gap=(8 * 1024, 3000))
    assert meta["gaps"] == [[pytest.approx(8 * 1024 / RATE, abs=1e-5), 3000]]
    sig = read_signal(wav)
    assert len(sig.data) == len(x) + 3000
    assert not sig.data[8 * 1024:8 * 1024 + 3000].any()
    assert np.array_equal(sig.data[8 * 1024 + 3000:], x[8 * 1024:].astype(float))
    # a time on the host's clock lands where its sample is in the WAV, the gap counted: the
    # stream's samples are dated from their index, which runs on over the lost ones
    assert meta["cuts"][0][1] == pytest.approx(18 * 1024 / RATE, abs=1e-5)


@pytest.mark.parametrize("change, problem", [
    ({"format": "something/2"}, "is not 'lathed-recording/1'"),
    ({"speed": [[0.0, -5.0]]}, "speed[0]: [0.0, -5.0] is not [seconds, value] with a speed > 0"),
    ({"cuts": [[2.0, 1.0]]}, "cuts: expected a list of [start, end] seconds"),
    ({"rate_hz": "fast"}, "rate_hz: 'fast' is not a sample rate"),
])
def test_a_bad_sidecar_is_one_line_naming_it(tmp_path, change, problem):
    x = np.random.default_rng(1).normal(0, 1, 8 * 1024).astype(np.float32)
    wav = tmp_path / "bad.wav"
    meta = write_recording(wav, x, (0, 4096))
    wav.with_suffix(".json").write_text(json.dumps({**meta, **change}))
    code, out, err = analyze(str(wav))
    assert code == 65 and err.count("\n") == 1 and "bad.json" in err and problem in err, err


def test_without_a_sidecar_the_speed_is_asked_for(tmp_path):
    x = np.random.default_rng(1).normal(0, 1, 8 * 1024).astype(np.float32)
    wav = tmp_path / "plain.wav"
    write_recording(wav, x, (0, 4096))
    wav.with_suffix(".json").unlink()
    code, out, err = analyze(str(wav))
    assert code == 2 and "--rpm is required" in err and err.count("\n") == 1


# -- the daemon's side: what it streams ------------------------------------------------------
class Sensor:
    role, kind = "sensor", "accelerometer"


class Chatter:
    def recording_context(self, source):
        return {"machine": "lathe", "tool": "T1", "material": "C45", "detector": "sync_cusum",
                "params": {}, "cut_from": ["vibration"]} if source == "accel" else None


def recorder(bus: Bus) -> Recorder:
    return Recorder(bus, lambda: {"accel": Sensor(), "temps": type("T", (), {"role": "sensor", "kind": "temperature"})()},
                    lambda: {"chatter": Chatter()}, lambda name: {"state": "connected"}, "test")


@pytest.mark.parametrize("args, problem", [
    ({"source": "accel"}, "give seconds (a time) or cuts"),
    ({"source": "accel", "seconds": 5, "cuts": 1}, "give seconds (a time) or cuts"),
    ({"source": "temps", "seconds": 5}, "'temps' is not a vibration sensor; vibration sensors: accel"),
    ({"source": "accel", "seconds": -1}, "seconds"),
    ({"source": "accel", "seconds": 5, "speed": 3}, "unknown argument 'speed'"),
])
def test_record_requests_refused_with_the_reason(args, problem):
    with pytest.raises(RequestError, match=re.escape(problem)):
        asyncio.run(recorder(Bus()).request(args))


def test_cuts_without_an_analyzer_to_tell_them_are_refused():
    r = Recorder(Bus(), lambda: {"accel": Sensor()}, lambda: {}, lambda name: None, "test")
    with pytest.raises(RequestError, match="no analyzer reads 'accel' and says when the tool cuts"):
        asyncio.run(r.request({"source": "accel", "cuts": 1}))


def block(seq: int) -> Block:
    return Block("accel", "acceleration", RATE, T0 + seq / RATE, seq, np.full(1024, seq, np.float32))


def test_the_next_cut_with_the_air_before_and_after_it():
    bus = Bus()
    rec = asyncio.run(recorder(bus).request({"source": "accel", "cuts": 1, "pre_s": 0.1, "post_s": 0.05}))
    for k in range(20):                                   # air: kept 0.1 s back, not streamed
        bus.publish(block(1024 * k))
        bus.publish(Sample("lathe", "spindle_rpm", 1500.0, "r/min", T0 + 1024 * k / RATE))
    assert "blocks" not in rec.frame() and rec.first["context"]["tool"] == "T1"
    bus.publish(Sample("chatter", "cutting", 1.0, "", T0 + 20 * 1024 / RATE))
    for k in range(20, 30):
        bus.publish(block(1024 * k))
    bus.publish(Block("other", "acceleration", RATE, T0, 0, np.zeros(8)))     # another sensor: not ours
    f = rec.frame()
    seqs = [b[0] for b in f["blocks"]]
    # 0.1 s of air (5 blocks of 21 ms) before the cut's first block, then the cut
    assert seqs == [1024 * k for k in range(15, 30)]
    assert np.frombuffer(base64.b64decode(f["blocks"][-1][4]), "<f4")[0] == 29 * 1024
    assert [s[1:3] for s in f["samples"]][:1] == [["lathe", "spindle_rpm"]] and "end" not in f
    bus.publish(Sample("chatter", "cutting", 0.0, "", T0 + 30 * 1024 / RATE))
    for k in range(30, 40):
        bus.publish(block(1024 * k))
    f = rec.frame()
    # 0.05 s after the cut's end: 3 blocks more, then the end
    assert [b[0] for b in f["blocks"]] == [1024 * k for k in range(30, 33)]
    assert f["end"] == {"why": "1 cut(s) recorded"}
    rec.close()
    assert not bus._taps


def test_seconds_end_after_that_much_signal():
    bus = Bus()
    rec = asyncio.run(recorder(bus).request({"source": "accel", "seconds": 0.1}))
    for k in range(8):
        bus.publish(block(1024 * k))
    f = rec.frame()
    assert len(f["blocks"]) == 5 and f["end"] == {"why": "0.1 s recorded"}       # 5 x 1024 >= 4800
    rec.close()


def test_a_missing_file_is_said_before_the_missing_speed(tmp_path):
    code, out, err = analyze(str(tmp_path / "gone.wav"))
    assert code == 66 and "no such file" in err and "--rpm" not in err, err
