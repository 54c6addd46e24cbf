"""Recordings in the containers a DAQ or MATLAB writes besides WAV, CSV and v5 .mat: MATLAB
v7.3 (HDF5, through h5py) and National Instruments TDMS (through npTDMS), read to the same
samples and rate as the .mat they were converted from, and their refusals in one line.

The real recording used is Khasawneh, Otto, Yesilli, "Turning dataset for chatter diagnosis
using machine learning", Mendeley Data v1, doi:10.17632/hvm4wh3jzx.1, CC BY 4.0
(../shared/data/real/turning-chatter beside the checkout)."""
from __future__ import annotations

import json

import numpy as np
import pytest
import scipy.io as sio

from lathed.analysis.recording import RecordingError, read_signal
from tests.test_analyze_chatter_cli import _cli
from tests.test_real_recordings import REAL, need_real

h5py = pytest.importorskip("h5py")
nptdms = pytest.importorskip("nptdms")


def write_mat73(path, variables: dict) -> None:
    """A .mat as MATLAB's save -v7.3 writes it: a 512-byte header in the HDF5 user block, each
    variable a dataset stored column-major (an N x K matrix as K x N) with its MATLAB_class."""
    with h5py.File(path, "w", userblock_size=512) as f:
        for name, v in variables.items():
            text = isinstance(v, str)        # MATLAB's char: UTF-16 codes
            v = np.atleast_2d(np.frombuffer(v.encode("utf-16-le"), "<u2") if text else np.asarray(v))
            ds = f.create_dataset(name, data=v.T)
            ds.attrs["MATLAB_class"] = np.bytes_("char" if text else "double")
    with open(path, "r+b") as f:
        f.write(b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Thu Nov 26 10:00:00 2026 HDF5 schema 1.00 .")


def write_tdms(path, channels: dict, rate: float | None) -> None:
    """channels: "group/channel" -> samples; the rate as NI's waveform property wf_increment."""
    from nptdms import ChannelObject, TdmsWriter
    props = {} if rate is None else {"wf_increment": 1.0 / rate, "unit_string": "g"}
    with TdmsWriter(str(path)) as w:
        w.write_segment([ChannelObject(*k.split("/"), np.asarray(v), properties=props) for k, v in channels.items()])


@need_real
def test_the_same_recording_reads_the_same_from_v5_v73_and_tdms(tmp_path, capsys):
    tsds = sio.loadmat(REAL / "c_425_020.mat")["tsDS"]       # time, acceleration
    write_mat73(tmp_path / "c_425_020_v73.mat", {"tsDS": tsds})
    write_tdms(tmp_path / "c_425_020.tdms", {"Turning/accel": tsds[:, 1], "Turning/spare": tsds[:, 1] * 0}, 10000.0)
    v5 = read_signal(REAL / "c_425_020.mat", var="tsDS")
    v73 = read_signal(tmp_path / "c_425_020_v73.mat", var="tsDS")
    tdms = read_signal(tmp_path / "c_425_020.tdms", var="Turning/accel")
    for sig in (v73, tdms):
        assert np.array_equal(sig.data, v5.data) and sig.rate_hz == pytest.approx(v5.rate_hz, rel=1e-9)
    verdicts = []
    for args in ([str(REAL / "c_425_020.mat"), "--var", "tsDS"], [str(tmp_path / "c_425_020_v73.mat"), "--var", "tsDS"],
                 [str(tmp_path / "c_425_020.tdms"), "--var", "accel"]):
        code, out, err = _cli(args + ["--rpm", "425", "--json"], capsys)
        assert code == 0, err
        res = json.loads(out)
        verdicts.append((res["verdict"], res["first_alarm_s"]))
    assert verdicts[0] == verdicts[1] == verdicts[2] and verdicts[0][0] == "chatter"


def test_mat73_picks_numeric_variables_and_needs_a_rate_without_time(tmp_path):
    p = tmp_path / "x.mat"
    write_mat73(p, {"acc": np.sin(np.arange(5000) * 0.3)[:, None], "label": "stable"})
    sig = read_signal(p, rate_hz=2000.0)          # the char variable is not a signal
    assert len(sig.data) == 5000 and sig.source.endswith(":acc")
    with pytest.raises(RecordingError, match=r"no time column.*--rate"):
        read_signal(p)
    bad = tmp_path / "bad.mat"
    bad.write_bytes(p.read_bytes()[:600])
    with pytest.raises(RecordingError, match=r"bad\.mat is not a MATLAB v7\.3 \.mat \(HDF5\) file h5py can read"):
        read_signal(bad)


def test_tdms_channels_named_and_refused_in_one_line(tmp_path, capsys):
    p = tmp_path / "run.tdms"
    x = np.sin(np.arange(8000) * 0.2)
    write_tdms(p, {"Vib/accel_x": x, "Vib/accel_z": -x}, 20000.0)
    with pytest.raises(RecordingError, match=r"name the channel to read with --var GROUP/CHANNEL "
                                             r"\(numeric channels: Vib/accel_x, Vib/accel_z\)"):
        read_signal(p)
    sig = read_signal(p, var="accel_z", rate_hz=10000.0)
    assert sig.rate_hz == 20000.0 and np.array_equal(sig.data, -x) and sig.channels == 2
    assert sig.notes == ["--rate 10000 ignored: the channel's wf_increment gives 20000 Hz"]
    with pytest.raises(RecordingError, match="'accel_y' is not a numeric channel"):
        read_signal(p, var="accel_y")
    with pytest.raises(RecordingError, match="--channel does not apply"):
        read_signal(p, channel=1, var="accel_x")
    norate = tmp_path / "norate.tdms"
    write_tdms(norate, {"Vib/accel_x": x}, None)
    with pytest.raises(RecordingError, match=r"'Vib/accel_x' has no wf_increment.*--rate"):
        read_signal(norate)
    assert read_signal(norate, rate_hz=5000.0).rate_hz == 5000.0
    junk = tmp_path / "junk.tdms"
    junk.write_bytes(b"TDSm" + bytes(40))
    code, out, err = _cli([str(junk), "--rpm", "1000"], capsys)
    assert code == 65 and err.count("\n") == 1 and "junk.tdms is not a TDMS file npTDMS can read" in err, err


def test_a_reader_the_install_lacks_names_its_extra(tmp_path, capsys, monkeypatch):
    p = tmp_path / "run.tdms"
    write_tdms(p, {"Vib/accel_x": np.sin(np.arange(8000) * 0.2)}, 20000.0)
    import lathed.extras
    monkeypatch.setattr(lathed.extras, "_found", lambda module: module != "nptdms")
    code, out, err = _cli([str(p), "--rpm", "1000"], capsys)
    assert code == 69 and err.count("\n") == 1, err
    assert "needs nptdms, which is not installed: pip install 'lathed[recordings]'" in err, err
