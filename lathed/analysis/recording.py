"""Reading vibration recordings: WAV (PCM 8/16/24/32-bit, float 32/64,
WAVE_FORMAT_EXTENSIBLE), CSV, MATLAB .mat (a named variable: one column of
samples, or time and value columns; v4-v7.2 through scipy, v7.3, which is
HDF5, through h5py) and NI TDMS (a named channel, its rate from the
waveform's ``wf_increment``, through npTDMS), with clipped-sample detection:
PCM samples at the converter's full scale; float WAV, CSV, .mat and TDMS (no
known full scale, often physical units) runs of equal samples at the
recording's extremes.  h5py and npTDMS come with the ``recordings`` extra.

The standard library's ``wave`` cannot read float WAV, so the RIFF chunks are
parsed here.  Errors are ``RecordingError`` carrying a one-line message that
says what is wrong and where, and whether the file was unreadable
(``missing=True``, exit 66 in lathectl) or its content invalid (exit 65).
"""
from __future__ import annotations

import csv
import io
import json
import math
import struct
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

_PCM, _FLOAT, _EXTENSIBLE = 1, 3, 0xFFFE


class RecordingError(Exception):
    def __init__(self, message: str, missing: bool = False, unavailable: bool = False,
                 usage: bool = False) -> None:
        super().__init__(message)
        self.missing = missing
        self.unavailable = unavailable     # a reader the install lacks (an extra)
        self.usage = usage                 # an option that does not apply to this file


@dataclass
class Signal:
    data: np.ndarray            # float64, one channel; PCM scaled to +-1 full scale
    rate_hz: float
    source: str
    channels: int = 1
    clipped: int = 0            # samples at the converter's full scale
    first_clip_s: float | None = None
    notes: list[str] = field(default_factory=list)

    @property
    def duration_s(self) -> float:
        return len(self.data) / self.rate_hz


def read_signal(path: str | Path, channel: int = 0, rate_hz: float | None = None,
                var: str | None = None) -> Signal:
    """Read ``path`` (.wav, .mat, .tdms, or anything else as CSV) and return one channel.
    ``var`` names the variable of a .mat file or the channel of a TDMS file (default:
    its only numeric one)."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except FileNotFoundError:
        raise RecordingError(f"no such file: {p}", missing=True) from None
    except IsADirectoryError:
        raise RecordingError(f"{p} is a directory, not a recording", missing=True) from None
    except OSError as e:
        raise RecordingError(f"cannot read {p}: {e.strerror}", missing=True) from None
    if not raw.strip():
        raise RecordingError(f"{p} is empty")
    fmt = _format(p, raw)
    if var is not None and fmt in ("WAV", "CSV"):     # it was ignored without a word
        raise RecordingError(f"{p}: --var names a variable of a .mat file or a channel of a TDMS file; "
                             f"a {fmt} file has none (its signal is chosen with --channel)", usage=True)
    if fmt == "TDMS":
        sig = _read_tdms(raw, str(p), channel, rate_hz, var)
    elif fmt == "MAT":
        sig = _read_mat(raw, str(p), channel, rate_hz, var)
    elif fmt == "WAV":
        sig = _read_wav(raw, str(p), channel)
        if rate_hz is not None and abs(rate_hz - sig.rate_hz) > 1e-6 * sig.rate_hz:
            sig.notes.append(f"--rate {rate_hz:g} ignored: the WAV header says {sig.rate_hz:g} Hz")
    else:
        sig = _read_csv(raw, str(p), channel, rate_hz)
    _check_values(sig)
    return sig


def _format(p: Path, head: bytes) -> str:
    """TDMS, MAT, WAV or CSV, from the file's first bytes or its name."""
    suffix = p.suffix.lower()
    if head[:4] == b"TDSm" or suffix == ".tdms":
        return "TDMS"
    if suffix == ".mat" or head[:6] == b"MATLAB":
        return "MAT"
    return "WAV" if head[:4] == b"RIFF" or suffix == ".wav" else "CSV"


def takes_var(path: str | Path) -> bool:
    """Whether ``read_signal`` takes a ``var`` for this file (a .mat or TDMS file)."""
    p = Path(path)
    try:
        with p.open("rb") as f:
            head = f.read(8)
    except OSError:
        return False          # read_signal says what is wrong with it
    return _format(p, head) in ("TDMS", "MAT")


# -- WAV -----------------------------------------------------------------------------
def _read_wav(raw: bytes, src: str, channel: int) -> Signal:
    if len(raw) < 12 or raw[:4] != b"RIFF" or raw[8:12] != b"WAVE":
        raise RecordingError(f"{src} is not a RIFF/WAVE file (header bytes 0-11)")
    fmt = data = None
    pos = 12
    while pos + 8 <= len(raw):
        cid, size = raw[pos:pos + 4], struct.unpack("<I", raw[pos + 4:pos + 8])[0]
        body = raw[pos + 8:pos + 8 + size]
        if cid == b"fmt ":
            fmt = body
        elif cid == b"data":
            data = body     # a truncated last chunk keeps what is there
        pos += 8 + size + (size & 1)
    if fmt is None or len(fmt) < 16:
        raise RecordingError(f"{src}: WAV has no valid 'fmt ' chunk")
    if data is None:
        raise RecordingError(f"{src}: WAV has no 'data' chunk")
    tag, nch, rate, _, align, bits = struct.unpack("<HHIIHH", fmt[:16])
    if tag == _EXTENSIBLE and len(fmt) >= 26:
        tag = struct.unpack("<H", fmt[24:26])[0]
    if nch < 1 or rate < 1 or bits < 8:
        raise RecordingError(f"{src}: WAV header has {nch} channels, {rate} Hz, {bits} bits: not a signal")
    if not 0 <= channel < nch:
        raise RecordingError(f"{src}: channel {channel} does not exist (file has {nch}, numbered from 0)")
    width = bits // 8
    if align != width * nch:
        raise RecordingError(f"{src}: WAV block align {align} does not match {nch} x {bits}-bit samples")
    nframes = len(data) // align
    if nframes == 0:
        raise RecordingError(f"{src}: WAV data chunk holds no samples")
    buf = np.frombuffer(data[:nframes * align], dtype=np.uint8).reshape(nframes, nch, width)[:, channel, :]
    full = None
    if tag == _FLOAT and width in (4, 8):
        x = np.ascontiguousarray(buf).view("<f4" if width == 4 else "<f8").ravel().astype(float)
        # a float WAV may hold physical units (m/s²): no full scale is known, so
        # saturation is what it leaves, flat tops at the extremes (as in a CSV)
        clip_mask = _flat_tops(x)
    elif tag == _PCM and width in (1, 2, 3, 4):
        if width == 1:
            ints = buf[:, 0].astype(np.int64) - 128          # 8-bit WAV is unsigned
        elif width == 3:
            b = buf.astype(np.int32)
            ints = (b[:, 0] | (b[:, 1] << 8) | (b[:, 2] << 16)).astype(np.int64)
            ints = np.where(ints >= 1 << 23, ints - (1 << 24), ints)
        else:
            ints = np.ascontiguousarray(buf).view("<i2" if width == 2 else "<i4").ravel().astype(np.int64)
        full = 1 << (8 * width - 1)
        clip_mask = (ints >= full - 1) | (ints <= -full)
        x = ints / float(full)
    else:
        raise RecordingError(f"{src}: WAV format tag {tag} with {bits}-bit samples is not supported "
                             "(PCM 8/16/24/32-bit or IEEE float 32/64)")
    return _with_clips(Signal(x, float(rate), src, nch), clip_mask)


def _with_clips(sig: Signal, mask: np.ndarray) -> Signal:
    n = int(mask.sum())
    if n:
        sig.clipped = n
        sig.first_clip_s = float(np.argmax(mask)) / sig.rate_hz
    return sig


# -- MATLAB ---------------------------------------------------------------------------
def _extra(module: str, what: str, src: str):
    from lathed.extras import MissingExtra, need
    try:
        return need(module, f"reading {what} ({src})")
    except MissingExtra as e:
        raise RecordingError(str(e), unavailable=True) from None


_HDF5 = b"\x89HDF\r\n\x1a\n"   # a v7.3 .mat: MATLAB's 512-byte header, then an HDF5 file


def _read_mat(raw: bytes, src: str, channel: int, rate_hz: float | None, var: str | None) -> Signal:
    if raw[512:520] == _HDF5:
        h5py = _extra("h5py", "a MATLAB v7.3 .mat", src)
        try:
            f = h5py.File(io.BytesIO(raw), "r")
        except OSError as e:
            raise RecordingError(f"{src} is not a MATLAB v7.3 .mat (HDF5) file h5py can read ({e})") from None
        with f:
            # MATLAB writes column-major, so an N x K matrix is stored K x N: the rule below,
            # samples along the longer side, reads both layouts alike
            mat = {k: v for k, v in f.items() if isinstance(v, h5py.Dataset)
                   and v.attrs.get("MATLAB_class", b"double") not in (b"char", b"logical")}
            return _mat_signal(mat, src, channel, rate_hz, var)
    from scipy.io import loadmat     # only here: the daemon never reads .mat
    from scipy.io.matlab import MatReadError

    try:
        mat = loadmat(io.BytesIO(raw))
    except (MatReadError, ValueError, TypeError, IndexError, NotImplementedError, OSError,
            struct.error) as e:
        raise RecordingError(f"{src} is not a MATLAB v4-v7.3 .mat file scipy or h5py can read ({e})") from None
    return _mat_signal({k: v for k, v in mat.items() if not k.startswith("__") and isinstance(v, np.ndarray)},
                       src, channel, rate_hz, var)


def _mat_signal(mat: dict, src: str, channel: int, rate_hz: float | None, var: str | None) -> Signal:
    """One signal of a .mat's variables (arrays, or h5py datasets read only when chosen)."""
    names = [k for k, v in mat.items() if v.dtype.kind in "iuf" and v.size > 1]
    if var is None:
        if len(names) != 1:
            raise RecordingError(f"{src}: name the variable to read with --var "
                                 f"(numeric variables: {', '.join(names) or 'none'})")
        var = names[0]
    if var not in mat:
        raise RecordingError(f"{src}: no variable {var!r} (numeric variables: {', '.join(names) or 'none'})")
    a = np.asarray(mat[var])
    if a.dtype.kind not in "iuf" or a.ndim > 2 or a.size < 2:
        raise RecordingError(f"{src}: variable {var!r} is {a.dtype} of shape {a.shape}, "
                             "not a numeric vector or N x K matrix")
    if a.ndim == 1 or 1 in a.shape:
        a = a.reshape(-1, 1)
    elif a.shape[0] < a.shape[1]:
        a = a.T                       # one row per channel: samples along the rows
    a = a.astype(float)
    notes: list[str] = []
    # a first column that increases evenly is the time (the published sets' layout)
    t = a[:, 0]
    dt = np.diff(t)
    if a.shape[1] >= 2 and len(t) > 2 and np.all(dt > 0) \
            and np.max(np.abs(dt - np.median(dt))) <= 0.01 * np.median(dt):
        rate = 1.0 / float(np.median(dt))
        cols = a[:, 1:]
        if rate_hz is not None and abs(rate - rate_hz) > 0.01 * rate:
            notes.append(f"--rate {rate_hz:g} ignored: the time column of {var!r} gives {rate:g} Hz")
    else:
        if rate_hz is None:
            raise RecordingError(f"{src}: variable {var!r} has no time column, so the sample rate is "
                                 "unknown (give --rate HZ)")
        rate, cols = float(rate_hz), a
    if not 0 <= channel < cols.shape[1]:
        raise RecordingError(f"{src}: signal column {channel} of {var!r} does not exist "
                             f"({cols.shape[1]} signal column(s), numbered from 0)")
    x = np.ascontiguousarray(cols[:, channel])
    return _with_clips(Signal(x, rate, f"{src}:{var}", cols.shape[1], notes=notes), _flat_tops(x))


# -- TDMS (National Instruments) ----------------------------------------------------------
def _read_tdms(raw: bytes, src: str, channel: int, rate_hz: float | None, var: str | None) -> Signal:
    nptdms = _extra("nptdms", "a TDMS file", src)
    try:
        f = nptdms.TdmsFile.read(io.BytesIO(raw))
        chans = {f"{g.name}/{c.name}": c for g in f.groups() for c in g.channels()
                 if c.dtype is not None and np.dtype(c.dtype).kind in "iuf" and len(c) > 1}
    except Exception as e:    # npTDMS raises what its parser meets (ValueError, KeyError, struct.error...)
        raise RecordingError(f"{src} is not a TDMS file npTDMS can read ({type(e).__name__}: {e})") from None
    listed = ", ".join(chans) or "none"
    if channel:
        raise RecordingError(f"{src}: a TDMS channel is one signal, so --channel does not apply: "
                             f"name it with --var (numeric channels: {listed})")
    if var is None:
        if len(chans) != 1:
            raise RecordingError(f"{src}: name the channel to read with --var GROUP/CHANNEL "
                                 f"(numeric channels: {listed})")
        var = next(iter(chans))
    picked = [k for k in chans if k == var] or [k for k in chans if k.split("/", 1)[1] == var]
    if len(picked) != 1:
        why = "is in more than one group" if picked else "is not a numeric channel"
        raise RecordingError(f"{src}: {var!r} {why} (numeric channels: {listed})")
    c = chans[picked[0]]
    notes: list[str] = []
    inc = c.properties.get("wf_increment")
    if inc is not None and float(inc) > 0:
        rate = 1.0 / float(inc)
        if rate_hz is not None and abs(rate - rate_hz) > 1e-6 * rate:
            notes.append(f"--rate {rate_hz:g} ignored: the channel's wf_increment gives {rate:g} Hz")
    elif rate_hz is None:
        raise RecordingError(f"{src}: channel {picked[0]!r} has no wf_increment, so the sample rate is "
                             "unknown (give --rate HZ)")
    else:
        rate = float(rate_hz)
    x = np.ascontiguousarray(c[:], dtype=float)
    return _with_clips(Signal(x, rate, f"{src}:{picked[0]}", len(chans), notes=notes), _flat_tops(x))


# -- CSV -------------------------------------------------------------------------------
def _read_csv(raw: bytes, src: str, channel: int, rate_hz: float | None) -> Signal:
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise RecordingError(f"{src} is neither a WAV file nor UTF-8 text (CSV)") from None
    lines = text.splitlines()
    sample = "\n".join(lines[:5])
    try:
        delim = csv.Sniffer().sniff(sample, delimiters=",;\t ").delimiter
    except csv.Error:
        delim = ","
    first = [c.strip() for c in next(csv.reader([lines[0]], delimiter=delim))]
    header = any(not _is_number(c) for c in first if c)
    names = first if header else [f"column {i + 1}" for i in range(len(first))]
    body_start = 1 if header else 0
    if header and "time_s" in names:
        t_col = names.index("time_s")
        sig_cols = [i for i in range(len(names)) if i != t_col]
    else:
        t_col = None
        sig_cols = list(range(len(names)))
    if not sig_cols:
        raise RecordingError(f"{src}: CSV has a time_s column but no signal column (line 1)")
    if not 0 <= channel < len(sig_cols):
        raise RecordingError(f"{src}: signal column {channel} does not exist "
                             f"(signal columns: {', '.join(names[i] for i in sig_cols)})")
    col = sig_cols[channel]
    if t_col is None and rate_hz is None:
        raise RecordingError(f"{src}: CSV has no time_s column, so the sample rate is unknown "
                             "(give --rate HZ)")
    body = [ln for ln in lines[body_start:] if ln.strip()]
    if not body:
        raise RecordingError(f"{src}: CSV has a header but no data rows")
    want = [col] if t_col is None else [t_col, col]
    joined = "\n".join(body)
    _check_fields(body, joined, body_start, delim, len(names), src)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)     # rows that are all comments: said below
            arr = np.loadtxt(io.StringIO(joined), delimiter=None if delim == " " else delim,
                             usecols=want, ndmin=2)
    except (ValueError, IndexError):
        _locate_csv_error(body, body_start, delim, want, names, src)
        raise RecordingError(f"{src}: CSV could not be parsed") from None
    if arr.size == 0:
        raise RecordingError(f"{src}: CSV has a header but no data rows (only # comments after it)")
    x = arr[:, -1].astype(float)
    notes: list[str] = []
    if t_col is not None:
        t = arr[:, 0]
        if len(t) < 2:
            raise RecordingError(f"{src}: CSV needs at least two rows to know the sample rate")
        if not np.isfinite(t).all():
            i = int(np.argmin(np.isfinite(t)))
            raise RecordingError(f"{src}: line {body_start + i + 1}, column 'time_s': {float(t[i]):g} is not a time")
        dt = np.diff(t)
        step = float(np.median(dt))
        if not step > 0:
            raise RecordingError(f"{src}: column time_s does not increase (line {body_start + 2})")
        # times printed to a few decimals step unevenly by up to their last digit (51.2 kHz
        # to the microsecond: 19 and 20 us); a dropped or repeated sample steps by a whole step
        res = max(_resolution(r, delim, t_col) for r in body[:5])
        tol = max(0.01 * step, min(1.01 * res, 0.5 * step))
        bad = np.flatnonzero(np.abs(dt - step) > tol)
        if bad.size:
            raise RecordingError(f"{src}: samples are not evenly spaced in time_s "
                                 f"(line {body_start + int(bad[0]) + 2}: step {dt[bad[0]]:g} s, "
                                 f"median {step:g} s)")
        rate = (len(t) - 1) / float(t[-1] - t[0])    # the mean step: exact over the file, whatever the rounding
        if rate_hz is not None and abs(rate - rate_hz) > 0.01 * rate:
            notes.append(f"--rate {rate_hz:g} ignored: time_s gives {rate:g} Hz")
    else:
        rate = float(rate_hz)
    return _with_clips(Signal(x, rate, src, len(sig_cols), notes=notes), _flat_tops(x))


def _flat_tops(x: np.ndarray, run: int = 3) -> np.ndarray:
    """Samples in runs of >= ``run`` equal values at the recording's max or min:
    what a saturated converter leaves when the full scale is not known (CSV)."""
    fin = np.isfinite(x)
    if not fin.any():
        return np.zeros(len(x), dtype=bool)
    hi, lo = np.max(x[fin]), np.min(x[fin])
    at = ((x == hi) | (x == lo)) & fin      # a NaN or inf sample is missing, not clipped
    if at.sum() < run:
        return np.zeros(len(x), dtype=bool)
    edges = np.flatnonzero(np.r_[True, x[1:] != x[:-1], True])
    starts, lengths = edges[:-1], np.diff(edges)
    keep = at[starts] & (lengths >= run)
    return np.repeat(keep, lengths)


def _is_number(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def _check_fields(body, joined, start, delim, n, src) -> None:
    """Every row has the header's fields: a row with more is not read right (the columns
    taken by position would be someone else's).  One count over the text where it can."""
    if delim == " " or n < 1:
        return
    if joined.count(delim) == len(body) * (n - 1):
        return
    for i, row in enumerate(csv.reader(body, delimiter=delim)):
        if row and not row[0].lstrip().startswith("#") and len(row) != n:
            raise RecordingError(f"{src}: line {start + i + 1} has {len(row)} fields, the header {n}")


def _resolution(row: str, delim: str, col: int) -> float:
    """The last printed digit's step of a row's field: 0.000123 -> 1e-6 (0 when exponent form)."""
    cells = [c for c in row.split(None if delim == " " else delim)]
    text = cells[col].strip() if col < len(cells) else ""
    if "e" in text.lower() or "." not in text:
        return 0.0
    return 10.0 ** -len(text.split(".")[1])


def _locate_csv_error(body, start, delim, want, names, src) -> None:
    for i, row in enumerate(csv.reader(body, delimiter=delim)):
        cells = [c for c in row if c != ""] if delim == " " else row
        for c in want:
            line = start + i + 1
            if c >= len(cells):
                raise RecordingError(f"{src}: line {line} has {len(cells)} fields, "
                                     f"column '{names[c]}' is missing")
            if not _is_number(cells[c].strip()):
                raise RecordingError(f"{src}: line {line}, column '{names[c]}': "
                                     f"{cells[c].strip()!r} is not a number")


def _check_values(sig: Signal) -> None:
    x = sig.data
    if x.size == 0:
        raise RecordingError(f"{sig.source}: no samples")
    finite = np.isfinite(x)
    if not finite.any():
        raise RecordingError(f"{sig.source}: every sample is NaN or infinite")
    if not finite.all():
        n = int((~finite).sum())
        i = np.arange(len(x))
        sig.data = np.interp(i, i[finite], x[finite])
        sig.notes.append(f"{n} NaN/infinite samples filled by interpolation "
                         f"(first at {np.argmin(finite) / sig.rate_hz:.6g} s)")
    if np.ptp(sig.data) == 0:
        raise RecordingError(f"{sig.source}: the signal is constant ({sig.data[0]:g}); "
                             "sensor disconnected or the wrong column?")


# -- lathectl record's sidecar -----------------------------------------------------------------
SIDECAR_FORMAT = "lathed-recording/1"


def read_sidecar(path: str | Path) -> dict | None:
    """What ``lathectl record`` wrote beside a WAV (the same name, .json): calibration, the
    speed over time, the cuts, the live analyzer's alarms, tool, material, detector; every time
    in seconds from the WAV's first sample. None for a file without one; RecordingError (one
    line, naming the sidecar and the key) for one that cannot be used."""
    p = Path(path)
    side = p.with_suffix(".json")
    if p.suffix.lower() != ".wav" or not side.is_file():
        return None
    try:
        meta = json.loads(side.read_text())
    except (OSError, UnicodeDecodeError) as e:
        raise RecordingError(f"{side}: cannot read the recording's sidecar ({e})", missing=True) from None
    except ValueError as e:
        raise RecordingError(f"{side}: the recording's sidecar is not JSON ({e})") from None
    if not isinstance(meta, dict) or meta.get("format") != SIDECAR_FORMAT:
        raise RecordingError(f"{side}: format {meta.get('format') if isinstance(meta, dict) else meta!r} is not "
                             f"{SIDECAR_FORMAT!r} (lathectl record's sidecar)")
    rate = meta.get("rate_hz")
    if isinstance(rate, bool) or not isinstance(rate, (int, float)) or not (math.isfinite(rate) and rate > 0):
        raise RecordingError(f"{side}: rate_hz: {rate!r} is not a sample rate")
    for key, lo in (("speed", 0.0), ("speed_keyphasor", 0.0), ("alarms", None), ("index", None)):
        track = meta.get(key, [])
        if not isinstance(track, list):
            raise RecordingError(f"{side}: {key}: expected a list of [seconds, value]")
        for i, row in enumerate(track):
            if not (isinstance(row, list) and len(row) == 2 and all(_finite(v) for v in row)
                    and (lo is None or row[1] > lo)):
                raise RecordingError(f"{side}: {key}[{i}]: {row!r} is not [seconds, value]"
                                     + (" with a speed > 0" if lo is not None else ""))
    cuts = meta.get("cuts", [])
    if not isinstance(cuts, list) or not all(
            isinstance(c, list) and len(c) == 2 and _finite(c[0]) and (c[1] is None or _finite(c[1]) and c[1] >= c[0])
            for c in cuts):
        raise RecordingError(f"{side}: cuts: expected a list of [start, end] seconds (end null: still cutting)")
    return meta


def _finite(v) -> bool:
    return not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)
