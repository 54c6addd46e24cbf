"""Property-based fuzzing of every decoder a peer or a file feeds (issue 17 item 9, issue 18):
whatever bytes arrive, the result is the project's own error or a valid value, never
another exception, and nothing non-finite or implausible gets past the framework's gate."""
from __future__ import annotations

import math

import can
import numpy as np
import structlog
from hypothesis import HealthCheck, given, settings, strategies as st

from lathed.analysis.recording import RecordingError, read_signal
from lathed.analysis.thermal.csvfile import ThermalCsvError, load_thermal_csv
from lathed.bus import Bus, Sample
from lathed.config import Section
from lathed.driver import DriverContext
from lathed.wire import (VIB_HEADER, FrameError, LineError, format_temperature_line, parse_temperature_line,
                         unpack_vibration_header, vibration_header_problem)
from lathed_plugins.can_robot import CanRobot
from lathed_plugins.ds18b20_serial import DS18B20Serial
from lathed_plugins.modbus_cnc import TYPES, Register
from tests.conftest import ROOT

FUZZ = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def ds18b20() -> DS18B20Serial:
    d = DS18B20Serial("temps", Section("t.toml", "sensor.temps", {"port": "/dev/null"}))
    d.ctx = DriverContext(Bus(), structlog.get_logger(), lambda k, p=None: None)
    return d


def all_published_plausible(bus) -> bool:
    return all(math.isfinite(s.value) for s in bus.latest.values())


@FUZZ
@given(st.binary(max_size=600))
def test_temperature_line_bytes(raw):
    try:
        seq, uptime, readings, kind = parse_temperature_line(raw)
    except LineError:
        return
    assert seq >= 0 and uptime >= 0 and kind in ("crc16", "xor8")


@FUZZ
@given(st.lists(st.binary(max_size=120).map(lambda b: b + b"\n"), max_size=20))
def test_ds18b20_handle_line_never_raises(lines):
    d = ds18b20()
    for i, raw in enumerate(lines):
        assert d.handle_line(raw, float(i)) >= 0
    assert all_published_plausible(d.ctx.bus)


NAMES = st.text(alphabet=st.characters(min_codepoint=33, max_codepoint=126, exclude_characters=",=*"),
                min_size=1, max_size=30)


@FUZZ
@given(st.lists(st.tuples(st.integers(0, 2**64), st.integers(0, 2**40),
                          st.dictionaries(NAMES, st.floats(allow_nan=True, allow_infinity=True), max_size=6)),
                max_size=15))
def test_ds18b20_valid_crc_lines_with_any_content(lines):
    """Well-checksummed lines with any seq, uptime, names and values: counted, never a crash,
    never a non-finite or out-of-range value on the bus, and later lines are never locked out."""
    d = ds18b20()
    for i, (seq, uptime, readings) in enumerate(lines):
        d.handle_line(format_temperature_line(seq, uptime, readings), float(i))
    assert all_published_plausible(d.ctx.bus)
    assert all(-55 <= s.value <= 125 for s in d.ctx.bus.latest.values())
    assert len(d.readings) <= d.max_sensors
    # whatever came before, a fresh board's lines are taken (its first may replay the last line)
    last = len(lines)
    d.handle_line(format_temperature_line(0, 0, {"probe": 20.0}), last + 1000.0)
    assert d.handle_line(format_temperature_line(1, 6000, {"probe": 20.1}), last + 1006.0) == 1


@FUZZ
@given(st.binary(min_size=VIB_HEADER.size, max_size=VIB_HEADER.size))
def test_vibration_header_bytes(head):
    try:
        channels, n, rate, seq, t0, rpm = unpack_vibration_header(head)
    except FrameError:
        return
    assert channels >= 1 and n >= 1 and rate >= 1
    if vibration_header_problem(rate, rpm) is None:
        assert 100 <= rate <= 1_000_000 and math.isfinite(rpm) and rpm >= 0


@FUZZ
@given(st.sampled_from(sorted(TYPES)), st.sampled_from(["big", "little"]),
       st.lists(st.integers(0, 0xFFFF), min_size=2, max_size=2))
def test_modbus_register_decoding(type_, order, regs):
    """Any register contents decode to a float; a NaN or inf never reaches the bus."""
    r = Register("spindle_rpm", 0, type_, order, 1.0, "r/min", False, 0.1)
    v = r.decode(regs[:r.count])
    assert isinstance(v, float)
    ctx = DriverContext(Bus(), structlog.get_logger(), lambda k, p=None: None)
    published = ctx.bus.publish(Sample("m", "spindle_rpm", v, "r/min", 1.0))
    assert published == (math.isfinite(v) and 0 <= v <= 100_000)


@FUZZ
@given(st.lists(st.tuples(st.integers(0, 0x7FF), st.binary(max_size=8)), max_size=20))
def test_can_frames(frames):
    d = CanRobot("robot", Section("t.toml", "machine.robot", {"interface": "virtual", "channel": "fuzz",
                                                               "dbc": str(ROOT / "etc" / "robot_arm.dbc")}))
    d.ctx = DriverContext(Bus(), structlog.get_logger(), lambda k, p=None: None)
    d._handle([can.Message(arbitration_id=i, data=data, is_extended_id=False) for i, data in frames])
    assert all_published_plausible(d.ctx.bus)


def _riff(body: bytes) -> bytes:
    return b"RIFF" + len(body).to_bytes(4, "little") + b"WAVE" + body


@FUZZ
@given(st.one_of(st.binary(max_size=400), st.binary(max_size=400).map(_riff),
                 st.tuples(st.integers(0, 0xFFFF), st.integers(0, 8), st.integers(0, 2**32 - 1),
                           st.sampled_from([8, 16, 24, 32, 64, 0, 7]), st.binary(max_size=200)).map(
                     lambda a: _riff(b"fmt " + (16).to_bytes(4, "little") + a[0].to_bytes(2, "little")
                                     + a[1].to_bytes(2, "little") + a[2].to_bytes(4, "little")
                                     + b"\0\0\0\0" + (a[1] * a[3] // 8 % 65536).to_bytes(2, "little")
                                     + a[3].to_bytes(2, "little") + b"data" + len(a[4]).to_bytes(4, "little")
                                     + a[4]))),
       st.sampled_from([".wav", ".csv"]))
def test_recording_reader(tmp_path_factory, raw, suffix):
    p = tmp_path_factory.mktemp("rec") / f"x{suffix}"
    p.write_bytes(raw)
    try:
        sig = read_signal(p, rate_hz=1000.0)
    except RecordingError as e:
        assert "\n" not in str(e)
        return
    assert sig.rate_hz > 0 and np.isfinite(sig.data).all() and sig.clipped >= 0


CSV_CELLS = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr), st.text(max_size=6),
                      st.sampled_from(["85.0", "-127.0", "", "1e308", "nan"]))


@FUZZ
@given(st.one_of(st.binary(max_size=400),
                 st.lists(st.lists(CSV_CELLS, min_size=3, max_size=3), max_size=8).map(
                     lambda rows: ("time_s,t_front_bearing_c,displacement_um\n"
                                   + "".join(",".join(r) + "\n" for r in rows)).encode("utf-8", "replace"))))
def test_thermal_csv_reader(tmp_path_factory, raw):
    p = tmp_path_factory.mktemp("csv") / "run.csv"
    p.write_bytes(raw)
    try:
        data, report = load_thermal_csv(p)
    except ThermalCsvError as e:
        assert "\n" not in str(e)
        return
    assert np.isfinite(data.time_s).all() and all(np.isfinite(v).all() for v in data.temps_c.values())
    assert all((-55 <= v).all() and (v <= 150).all() for v in data.temps_c.values())
