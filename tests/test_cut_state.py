"""Cut state without a depth register: from the vibration and from the spindle load."""
from __future__ import annotations

import numpy as np
import pytest

from lathed.analysis.cut_state import LoadCutDetector, SlidingQuantile, VibrationCutDetector
from lathed.analysis.regen import Segment as S, simulate_cut
from lathed.sim.lathe import LATHE_KF, LATHE_MODES, SimLathe
from lathed.sim.program import Cut

RATE = 51200.0
FRAME = 1024        # the vibration stream's 20 ms frames


def cut_events(signal: np.ndarray, gain: float = 1.0) -> list[tuple[int, bool]]:
    det = VibrationCutDetector(RATE)
    out = []
    for i in range(0, len(signal), FRAME):
        at = det.process(gain * signal[i:i + FRAME])
        if at is not None:
            out.append((i + at, bool(det.cutting)))
    return out


@pytest.mark.parametrize("gain", [1.0, 10.0, 0.01])
def test_vibration_sees_entry_within_one_revolution_at_3000_rpm(gain):
    air, cut = 0.4, 1.0
    rec = simulate_cut([S(air, 3000, 0.0), S(cut, 3000, 0.8), S(0.5, 3000, 0.0)], modes=LATHE_MODES,
                       kf_n_per_m2=LATHE_KF, seed=4)
    ev = cut_events(rec.signal, gain)
    entry = int(air * RATE)
    rev = int(RATE * 60 / 3000)
    assert ev and ev[0][1] is True, ev
    assert entry <= ev[0][0] <= entry + rev, (ev, entry, rev)
    # and the end of the cut once the tool is out (the ringing decays first)
    assert len(ev) == 2 and ev[1][1] is False and ev[1][0] > int((air + cut) * RATE), ev


def test_interrupted_cut_stays_one_cut():
    # a 30 % flat takes the tool out every revolution: still one cut
    rec = simulate_cut([S(0.4, 1000, 0.0), S(1.5, 1000, 1.0)], modes=LATHE_MODES, kf_n_per_m2=LATHE_KF,
                       flat_fraction=0.3, seed=2)
    ev = cut_events(rec.signal)
    assert [on for _, on in ev] == [True], ev


def test_no_cut_while_the_spindle_only_turns():
    rec = simulate_cut([S(1.0, 2000, 0.0), S(0.5, 2600, 0.0, 0.3)], modes=LATHE_MODES,
                       kf_n_per_m2=LATHE_KF, seed=3)
    assert cut_events(rec.signal) == []


def test_load_learns_the_spindles_no_chip_load():
    det = LoadCutDetector(margin_pct=5.0)
    assert det.update(2.0, 1500) is False          # bearings and seals only
    assert det.update(8.0, 1500) is True           # 6 % over the no-chip load: a chip
    assert det.update(2.5, 1500) is False
    assert det.update(0.0, 0.0) is False           # spindle stopped
    assert det.update(20.0, 2500) is True


def test_load_keeps_a_cut_whose_speed_runs_through_new_bands():
    """Constant surface speed: the spindle runs up from 2016 to 2900 r/min while it cuts,
    through speed bands whose no-chip load was never seen: the nearest band's stands."""
    det = LoadCutDetector(margin_pct=5.0)
    assert det.update(2.0, 2016) is False
    rpms = np.linspace(2016, 2900, 30)
    assert all(det.update(load, rpm) for rpm, load in zip(rpms, np.linspace(9.4, 7.5, 30)))
    assert det.cutting_load(7.5, 2900) == pytest.approx(5.5)
    assert det.update(2.1, 2900) is False      # the tool out: that band's own no-chip load


@pytest.mark.parametrize("q,size", [(0.25, 50), (0.25, 4), (0.5, 7), (0.0, 5), (1.0, 5), (0.3, 1), (0.9, 13)])
def test_sliding_quantile_is_numpys_quantile_bit_for_bit(q, size):
    rng = np.random.default_rng(7)
    # rms-like values, with ties (rounded) and a range of scales
    values = np.round(rng.lognormal(0.0, 2.0, 600), 3) * 10.0 ** rng.integers(-6, 6, 600)
    sq, window = SlidingQuantile(q, size), []
    for i, v in enumerate(values):
        sq.push(v)
        window = (window + [float(v)])[-size:]
        assert len(sq) == len(window)
        assert sq.value() == float(np.quantile(window, q)), (i, window)
        if i == 300:
            sq.clear()
            window = []
            with pytest.raises(ValueError, match="no values"):
                sq.value()


def test_sliding_quantile_is_nan_while_a_nan_is_in_the_window_as_numpys_is():
    sq, window = SlidingQuantile(0.25, 4), []
    for v in [1.0, 2.0, float("nan"), 3.0, 4.0, 5.0, 6.0, 0.5]:
        sq.push(v)
        window = (window + [v])[-4:]
        want = float(np.quantile(window, 0.25))
        got = sq.value()
        assert got == want or (np.isnan(got) and np.isnan(want)), (window, got, want)


def contact_events(signal: np.ndarray, gain: float = 1.0) -> tuple[list[int], list[tuple[int, bool]]]:
    det = VibrationCutDetector(RATE)
    contacts, entries = [], []
    for i in range(0, len(signal), FRAME):
        at = det.process(gain * signal[i:i + FRAME])
        if det.contact is not None:
            contacts.append(i + det.contact)
        if at is not None:
            entries.append((i + at, bool(det.cutting)))
    return contacts, entries


def sim_pass(cut: Cut) -> tuple[np.ndarray, int]:
    """The simulated lathe's pass from its approach at feed (air) on: signal, and the sample the
    chip begins at."""
    lathe = SimLathe(program=(cut,), load_s=0.2, retract_s=0.2)
    out, start = [], None
    while lathe.phase != "retract":
        x = lathe.step(FRAME)
        if lathe.phase in ("approach", "cut"):
            if lathe.phase == "cut" and start is None:
                start = sum(map(len, out))
            out.append(x)
    return np.concatenate(out).astype(float), start


@pytest.mark.parametrize("gain", [1.0, 10.0, 0.01])
def test_a_light_chip_entering_gently_is_a_contact_not_an_entry(gain):
    """A 0.5 mm pass at a fine feed whose depth grows over three revolutions (a chamfer, the
    nose radius engaging) lifts the vibration 1.1-2.4 x over the air: no entry at 4 x, but a
    sustained step that a cut the feed started in air takes as the chip."""
    air, ramp = 0.3, 0.05
    rec = simulate_cut([S(air, 3500, 0.0), S(0.6, 3500, 0.5, ramp)], modes=LATHE_MODES, kf_n_per_m2=LATHE_KF,
                       feed_mm_rev=0.08, seed=5)
    contacts, entries = contact_events(rec.signal, gain)
    assert entries == [], entries
    assert len(contacts) == 1 and air * RATE <= contacts[0] <= (air + ramp) * RATE, contacts


def test_a_finishing_pass_is_seen_by_the_vibration_only_at_its_entry():
    """What the feed signal is for: the simulated lathe's 0.3 mm pass at 0.1 mm/rev rings the
    structure 6 x as the tool enters, then cuts at 1.1 x the air, so the vibration's cut ends
    while the tool still cuts."""
    signal, start = sim_pass(Cut(2000, 0.3, 0.1, 8.0))
    contacts, entries = contact_events(signal)
    assert [on for _, on in entries] == [True, False], entries
    assert start <= entries[0][0] <= start + FRAME and entries[1][0] < len(signal) - RATE, (start, entries)

def test_air_and_a_speed_change_are_no_contact():
    rec = simulate_cut([S(1.0, 2000, 0.0), S(0.5, 2600, 0.0, 0.3), S(0.5, 2600, 0.0)], modes=LATHE_MODES,
                       kf_n_per_m2=LATHE_KF, seed=3)
    assert contact_events(rec.signal) == ([], [])
