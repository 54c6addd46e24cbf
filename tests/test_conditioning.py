"""lathed.analysis.conditioning (an audio sensor's calibration, DC removal, mains notches,
keyphasor), lathed.audio_device.SampleClock and lathed.sight, against known answers."""
from __future__ import annotations

import math

import numpy as np
import pytest

from lathed.analysis.conditioning import (G0, Calibration, Conditioner, ConditionerBank, Keyphasor, MainsComb,
                                         OnePole)
from lathed.audio_device import SampleClock
from lathed.sight import Sight


def test_calibrations_in_physical_units():
    # 100 mV/g into a 5 V interface: full scale is 50 g
    assert Calibration.iepe(100.0, 5.0).scale == pytest.approx(50 * G0)
    # a 24-bit word, 2**23 counts at full scale, 10000 counts per m/s²
    assert Calibration.digital(10000.0, 24).scale == pytest.approx(2 ** 23 / 1e4)
    mic = Calibration.microphone(50.0, 1.0)
    assert mic.scale == pytest.approx(20.0) and (mic.quantity, mic.unit) == ("sound_pressure", "Pa")
    assert Calibration.uncalibrated().unit == "FS"


def test_one_pole_in_blocks_is_the_recursion():
    from scipy import signal    # here, not at collection: every xdist worker collects this file
    rng = np.random.default_rng(0)
    u = rng.normal(size=30000)
    p = 0.9995
    ref = signal.lfilter([1.0], [1.0, -p], u)
    pole = OnePole(p)
    out = np.concatenate([pole.run(u[i:i + 1000]) for i in range(0, len(u), 1000)])
    assert np.allclose(out, ref, atol=1e-9)
    # a fast pole is worked in chunks short enough to stay exact
    fast = OnePole(0.5)
    assert fast.chunk < 100
    assert np.allclose(fast.run(u[:5000]), signal.lfilter([1.0], [1.0, -0.5], u[:5000]), atol=1e-9)


def test_highpass_removes_dc_from_the_first_sample_and_passes_the_band():
    from scipy import signal
    rate = 48000
    t = np.arange(2 * rate) / rate
    x = 0.3 + 0.2 * np.sin(2 * np.pi * 200 * t)
    c = Conditioner(rate, 10.0, highpass_hz=2.0)
    y = np.concatenate([c.process(x[i:i + 1024].astype(np.float32)) for i in range(0, len(x), 1024)])
    b, a = signal.butter(1, 2.0, "highpass", fs=rate)
    ref = signal.lfilter(b, a, 10.0 * x.astype(np.float32).astype(float), zi=signal.lfilter_zi(b, a) * 3.0)[0]
    assert np.allclose(y, ref, atol=1e-4)
    assert abs(y.mean()) < 0.01 and np.sqrt(2) * y[rate:].std() == pytest.approx(2.0, rel=0.01)


@pytest.mark.parametrize("rate, highpass, mains", [(51200, 2.0, 0.0), (48000, 2.0, 50.0), (1000, 2.0, 0.0),
                                                    (44100, 0.0, 0.0)])
def test_a_bank_conditions_each_channel_as_its_own_conditioner_would(rate, highpass, mains):
    # a device's channels in one pass: each the numbers of its own Conditioner, bit for bit
    # (1000 S/s: the pole is worked in chunks shorter than a block)
    rng = np.random.default_rng(3)
    scales, columns = [490.3, 10.0, 3.3], [0, 4, 2]
    alone = [Conditioner(rate, s, highpass, mains) for s in scales]
    bank, members = ConditionerBank(), ["a", "b", "c"]
    for m, s, col in zip(members, scales, columns):
        bank.join(m, Conditioner(rate, s, highpass, mains), col)
    for b in range(12):
        data = (rng.normal(0.3, 0.1, (1024, 6))).astype(np.float32)
        if b in (4, 5):
            data[:, 4] = 0.0           # digital silence: not conditioned, its state as it was
        for m, col, own in zip(members, columns, alone):
            x, peak, y, shared = bank.take(m, data)
            assert np.array_equal(x, data[:, col]) and peak == float(np.abs(data[:, col]).max())
            if b in (4, 5) and col == 4:
                assert y is None
                continue
            assert y.dtype == np.float32 and y.base is None     # its own array, not a view of all
            assert y.tobytes() == own.process(np.ascontiguousarray(data[:, col])).tobytes()
            if shared is not None:
                # the gate's extremes, made for all rows at once: the row's own reductions, to the
                # bit (with a mains notch not made: the gate reduces the row itself)
                rows, row = shared
                got = rows.extremes(row, y)
                assert got is None if mains else got == (float(np.minimum.reduce(y)), float(np.maximum.reduce(y)))
                assert rows.extremes(row, y.copy()) is None     # another array than the row: not its
        if b == 7:     # one that joins after a block's pass is conditioned alone, once
            bank.join("d", Conditioner(rate, 7.0, highpass, mains), 1)
            alone.append(Conditioner(rate, 7.0, highpass, mains))
            for _ in range(2):
                y = bank.take("d", data)[2]
            assert y.tobytes() == alone[-1].process(np.ascontiguousarray(data[:, 1])).tobytes()
            members.append("d")
            columns.append(1)
        if b == 9:
            bank.leave("a")
            del alone[0], members[0], columns[0]


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("highpass, mains", [(2.0, 0.0), (2.0, 50.0), (0.0, 50.0)])
def test_a_non_finite_sample_spoils_its_block_alone(bad, highpass, mains):
    # one NaN or inf stayed in the high-pass's state (and came back every mains period in the
    # notch's): every later block of the channel was non-finite, refused at the gate, the
    # channel blind until a restart. Its own block is refused; the next starts afresh, as the
    # first did, alone and in a bank alike.
    rng = np.random.default_rng(6)
    blocks = [rng.normal(0.3, 0.1, (1024, 2)).astype(np.float32) for _ in range(3)]
    blocks[0][500, 1] = bad
    alone = Conditioner(51200, 10.0, highpass, mains)
    bank = ConditionerBank()
    for k in range(2):
        bank.join(k, Conditioner(51200, 10.0, highpass, mains), k)
    fresh = Conditioner(51200, 10.0, highpass, mains)      # started at block 1
    for b, data in enumerate(blocks):
        y = alone.process(np.ascontiguousarray(data[:, 1]))
        assert bank.take(1, data)[2].tobytes() == y.tobytes()
        assert np.isfinite(bank.take(0, data)[2]).all()
        if b == 0:
            assert not np.isfinite(y).all()
        else:
            assert y.tobytes() == fresh.process(np.ascontiguousarray(data[:, 1])).tobytes()


def test_a_bank_member_whose_column_a_block_lacks_fails_alone():
    # one sensor's channel beyond the device's: its own IndexError, the others' blocks as ever
    bank = ConditionerBank()
    bank.join("in", Conditioner(51200, 10.0, 2.0), 0)
    bank.join("out", Conditioner(51200, 10.0, 2.0), 5)
    alone = Conditioner(51200, 10.0, 2.0)
    rng = np.random.default_rng(4)
    for _ in range(3):
        data = rng.normal(0.0, 0.1, (1024, 2)).astype(np.float32)
        with pytest.raises(IndexError):
            bank.take("out", data)
        assert bank.take("in", data)[2].tobytes() == alone.process(np.ascontiguousarray(data[:, 0])).tobytes()


@pytest.mark.parametrize("rate, mains", [(48000, 50.0), (44100, 60.0), (51200, 60.0)])
def test_mains_comb_takes_every_harmonic_and_leaves_what_is_between(rate, mains):
    t = np.arange(3 * rate) / rate
    hum = sum(0.1 * np.sin(2 * np.pi * mains * k * t + k) for k in (1, 2, 3, 5, 8))
    tone = 0.3 * np.sin(2 * np.pi * mains * 7.5 * t)          # between two harmonics
    comb = MainsComb(rate, mains)
    y = np.concatenate([comb.run(x) for x in np.array_split(hum + tone, 37)])[rate:]
    f = np.fft.rfftfreq(len(y), 1 / rate)
    spec = np.abs(np.fft.rfft(y * np.hanning(len(y)))) * 4 / len(y)
    for k in (1, 2, 3, 5, 8):
        # 51.2 kS/s over 60 Hz is 853.3 samples: the fraction read by interpolation, shallower
        assert spec[np.argmin(np.abs(f - mains * k))] < 0.1 * (1e-3 if rate % mains == 0 else 3e-2), k
    assert spec[np.argmin(np.abs(f - mains * 7.5))] == pytest.approx(0.3, rel=0.06)


def pulse_train(revolution: float, n: int, start: float = 5.0) -> np.ndarray:
    """Marks every ``revolution`` samples (fractional): a pulse a few samples wide, as an
    AC-coupled input shows an edge through its converter's anti-aliasing filter."""
    x = np.zeros(n)
    at = start
    while at < n - 30:
        i = int(at)
        k = np.arange(i, i + 16)
        x[i:i + 16] += 0.8 * np.exp(-((k - at - 6.0) / 2.0) ** 2)
        at += revolution
    return x


def test_keyphasor_speed_to_a_fraction_of_a_sample():
    rate = 48000.0
    rev = rate * 60 / 1234.5                          # 2332.93 samples: not a whole number
    x = pulse_train(rev, int(5 * rate)) + np.random.default_rng(1).normal(0, 0.01, int(5 * rate))
    kp = Keyphasor(rate)
    rpms = []
    for i in range(0, len(x), 1024):
        kp.process(x[i:i + 1024], i)
        rpms.append(kp.rpm(i + 1024))
    assert kp.pulses == pytest.approx(5 * 1234.5 / 60, abs=1)
    assert all(r == pytest.approx(1234.5, rel=2e-4) for r in rpms[10:])
    assert kp.phase(kp.marks[-1] + rev / 4) == pytest.approx(math.pi / 2, abs=0.01)


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_keyphasor_goes_on_after_a_sample_that_is_not_a_number(bad):
    # an infinite sample made the running peak infinite for good: no pulse reached half of it.
    # The bad sample's block still gives its pulse (30 samples after it): every mark the same
    rate = 48000.0
    rev = rate * 60 / 1234.5
    x = pulse_train(rev, int(3 * rate)) + np.random.default_rng(2).normal(0, 0.01, int(3 * rate))
    spoiled = x.copy()
    spoiled[int(5.0 + 21 * rev) + 30] = bad
    assert int(5.0 + 21 * rev) // 1024 == (int(5.0 + 21 * rev) + 30) // 1024     # one block
    clean, kp = Keyphasor(rate), Keyphasor(rate)
    for i in range(0, len(x), 1024):
        clean.process(x[i:i + 1024], i)
        kp.process(spoiled[i:i + 1024], i)
        assert kp.rpm(i + 1024) == clean.rpm(i + 1024)
    assert kp.marks == clean.marks and kp.pulses == clean.pulses == pytest.approx(3 * 1234.5 / 60, abs=1)


def test_keyphasor_slows_down_then_loses_the_spindle():
    rate = 48000.0
    kp = Keyphasor(rate, min_rpm=30.0)
    x = pulse_train(rate * 60 / 600, int(2 * rate))
    kp.process(x, 0)
    last = kp.marks[-1]
    assert kp.rpm(int(last) + 100) == pytest.approx(600, rel=1e-3)
    # no pulse for twice a revolution: at most what the time since the last allows
    assert kp.rpm(int(last + 2 * 4800)) == pytest.approx(300, rel=1e-3)
    assert kp.rpm(int(last + 2.1 * rate)) is None          # a revolution at 30 r/min: stopped, or lost


def test_sample_clock_dates_jittered_stamps_and_measures_the_crystal():
    rate = 48000.0
    clock = SampleClock(rate, fit_s=20.0)
    rng = np.random.default_rng(2)
    true_rate = rate * (1 + 80e-6)                    # a crystal 80 ppm fast
    for k in range(0, int(60 * rate), 1024):
        clock.add(k, 1000.0 + k / true_rate + rng.uniform(0, 0.008))     # a callback is only ever late
    assert clock.measured_rate == pytest.approx(true_rate, rel=10e-6)
    k = int(59 * rate)
    assert clock.t(k) == pytest.approx(1000.0 + k / true_rate, abs=0.002)
    assert clock.steps == 0


def test_sample_clock_steps_over_a_stall():
    rate = 48000.0
    clock = SampleClock(rate)
    for k in range(0, int(5 * rate), 1024):
        clock.add(k, 1000.0 + k / rate)
    for k in range(int(5 * rate), int(10 * rate), 1024):
        clock.add(k, 1000.25 + k / rate)               # the device stood 250 ms
    assert clock.steps == 1 and clock.stepped_s == pytest.approx(0.25, abs=0.02)
    assert clock.t(int(9 * rate)) == pytest.approx(1009.25, abs=0.002)


def test_sight_blind_while_gone_and_back_on_a_block():
    s = Sight("accel", stale_s=2.0)
    assert s.blind == "accel: no block yet" and not s.check({"state": "connecting", "describe": "connecting"}, 0)
    assert not s.block(1.0) and s.blind is None
    assert not s.check({"state": "connected"}, 2.0)
    went = s.check({"state": "retrying", "error": "device gone: no samples for 1 s", "describe": "-"}, 2.5)
    assert went and s.blind == "accel: device gone: no samples for 1 s, retrying"
    assert not s.check({"state": "retrying", "error": "device gone: again", "describe": "-"}, 3.0)   # once
    assert s.block(4.0) and s.blind is None
    assert s.check({"state": "connected"}, 6.5) and s.blind == "accel: no signal for 2.5 s"
