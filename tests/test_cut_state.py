"""Cut state without a depth register: from the vibration and from the spindle load."""
from __future__ import annotations

import re

import numpy as np
import pytest

from lathed.analysis.cut.sources import FeedStop, LoadCutDetector, VibrationCutDetector
from lathed.analysis.quantile import SlidingQuantile
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


def test_a_feed_stop_with_the_axes_standing_is_a_dwell():
    """A pass along Z (1 mm a 100 ms poll, X standing): the feed stops between two polls, the
    tool where the feed left it, the axes standing after: a dwell, until an axis moves."""
    fs = FeedStop(["x_mm", "z_mm"])
    for i in range(4):
        fs.feed(True, i * 0.1)
        fs.position("x_mm", 14.0, i * 0.1)
        fs.position("z_mm", -1.0 * i, i * 0.1)
    assert not fs.standing and not fs.left           # feeding: no stop yet
    fs.feed(False, 0.4)
    fs.position("x_mm", 14.0, 0.4)
    fs.position("z_mm", -3.6, 0.4)                   # stopped 60 % of the way to the next poll
    assert fs.standing
    for t in (0.5, 0.6, 0.7):
        fs.feed(False, t)
        fs.position("x_mm", 14.004, t)               # a thermal offset's step: still standing
        fs.position("z_mm", -3.6, t)
        assert fs.standing
    fs.feed(False, 0.8)
    fs.position("x_mm", 16.0, 0.8)                   # the retract
    assert fs.left and not fs.standing
    fs.feed(True, 0.9)                               # the next move under feed: judged afresh
    assert not fs.left and not fs.standing


@pytest.mark.parametrize("feed_first", [True, False])
def test_a_retract_seen_in_the_feeds_own_poll_is_the_tool_leaving(feed_first):
    """The pass ends, the tool retracts and stands clear before the next poll: the first
    reading after the feed stopped is off the feed's path, whichever of the poll's samples
    comes first (a driver publishes a poll's registers in its own order)."""
    fs = FeedStop(["x_mm", "z_mm"])
    for i in range(3):
        fs.feed(True, i * 0.1)
        fs.position("x_mm", 14.0, i * 0.1)
        fs.position("z_mm", -1.0 * i, i * 0.1)
    if feed_first:
        fs.feed(False, 0.3)
    fs.position("x_mm", 16.0, 0.3)
    fs.position("z_mm", -2.5, 0.3)
    if not feed_first:
        fs.feed(False, 0.3)
    assert fs.left
    fs.position("x_mm", 16.0, 0.4)
    assert fs.left and not fs.standing


def test_the_axes_moving_as_the_feed_goes_on_again_are_no_retract():
    """The dwell's end: the poll that finds the axes moving again has the feed on; its position
    samples may come before the feed's, and are not taken for the tool leaving."""
    fs = FeedStop(["x_mm", "z_mm"])
    for i in range(3):
        fs.feed(True, i * 0.1)
        fs.position("x_mm", 14.0, i * 0.1)
        fs.position("z_mm", -1.0 * i, i * 0.1)
    for t in (0.3, 0.4):
        fs.position("x_mm", 14.0, t)
        fs.position("z_mm", -2.2, t)
        fs.feed(False, t)
    fs.position("x_mm", 14.0, 0.5)
    fs.position("z_mm", -2.9, 0.5)                   # moving: the feed is on again ...
    assert fs.standing and not fs.left
    fs.feed(True, 0.5)                               # ... as its sample of the same poll says
    assert not fs.left and not fs.standing
    fs.position("x_mm", 14.0, 0.6)
    fs.position("z_mm", -3.9, 0.6)
    fs.feed(False, 0.65)                             # a later poll with the feed off: had it stayed
    fs.position("x_mm", 14.0, 0.7)                   # off at 0.5, the move would be the tool leaving
    assert fs.standing


def test_a_feed_stop_on_an_axis_never_read_under_feed_is_no_dwell():
    """No reading under feed, no path to judge the stop by: not taken for a dwell (the cut ends
    as without the axes)."""
    fs = FeedStop(["x_mm", "z_mm"])
    fs.feed(True, 0.0)
    fs.position("x_mm", 14.0, 0.0)
    fs.feed(False, 0.1)
    fs.position("x_mm", 14.0, 0.1)
    fs.position("z_mm", -3.0, 0.1)
    assert fs.left and not fs.standing


@pytest.mark.parametrize("axes_first", [True, False])
def test_the_feed_back_on_with_the_tool_elsewhere_is_the_next_pass(axes_first):
    """A groove's dwell, then retract, shift and the next plunge within one poll: the feed is
    on again with the axes mm away; it was taken for the same pass (the cure held into the
    next).  Back where it stood, or on the feed's way on from there, it is the same pass."""
    for back_at, away in ((11.6, False), (10.7, False), (15.5, True)):
        fs = FeedStop(["x_mm", "z_mm"])
        for i in range(3):                             # plunging X at 1 mm a poll, Z standing
            fs.feed(True, i * 0.1)
            fs.position("x_mm", 14.0 - i, i * 0.1)
            fs.position("z_mm", -10.0, i * 0.1)
        for t in (0.3, 0.4):
            fs.feed(False, t)
            fs.position("x_mm", 11.6, t)
            fs.position("z_mm", -10.0, t)
        assert fs.standing
        z = -13.0 if away else -10.0
        if axes_first:
            fs.position("x_mm", back_at, 0.5)
            fs.position("z_mm", z, 0.5)
        fs.feed(True, 0.5)
        assert fs.resuming is not axes_first
        if not axes_first:
            fs.position("x_mm", back_at, 0.5)
            fs.position("z_mm", z, 0.5)
        assert not fs.resuming and fs.away is away, (back_at, away)


def test_a_dwell_then_the_next_plunge_within_a_poll_are_two_cuts():
    import structlog

    from lathed.analyzer import AnalyzerContext
    from lathed.bus import Bus, Sample
    from lathed.config import Section
    from lathed_plugins.chatter import ChatterAnalyzer
    for axes_first in (True, False):
        conf = {"input": "accel", "machine": "lathe", "cut_from": ["feed"], "dwell_axes": ["x_mm", "z_mm"]}
        an = ChatterAnalyzer("chatter", Section("t.toml", "analyzer.chatter", conf))
        bus, out = Bus(), []
        publish = bus.publish
        bus.publish = lambda m: (out.append((m.quantity, m.value, round(m.t, 2)))
                                 if isinstance(m, Sample) else None, publish(m))[1]
        an.ctx = AnalyzerContext(bus, structlog.get_logger("test"), lambda *a, **k: None,
                                 None, None, None, lambda n: None, ".")
        t = 0.0

        def poll(feed, x, z):
            nonlocal t
            samples = [("x_mm", x), ("z_mm", z)]
            samples = samples + [("cutting_feed", feed)] if axes_first else [("cutting_feed", feed)] + samples
            for q, v in samples:
                an._on_machine(Sample("lathe", q, v, "", t))
            t = round(t + 0.1, 3)
        for i in range(6):
            poll(1, 15 - i, -10.0)                   # plunge 1
        for _ in range(3):
            poll(0, 10.0, -10.0)                     # G04 at the bottom
        for i in range(6):
            poll(1, 15.5 - i, -13.0)                 # retract, shift, approach between two polls: plunge 2
        cuts = [(v, ts) for q, v, ts in out if q == "cutting"]
        assert cuts == [(1.0, 0.0), (0.0, 0.6), (1.0, 0.9)], (axes_first, out)


def test_a_dwell_is_timed_on_the_clock_that_began_it():
    """The accelerometer's clock 3 s off the host's: a dwell the feed began (host time) was
    ended at once by the first vibration block's time stamp (dwell_max 2 s)."""
    import structlog

    from lathed.analyzer import AnalyzerContext
    from lathed.bus import Block, Bus, Sample
    from lathed.config import Section
    from lathed_plugins.chatter import ChatterAnalyzer
    conf = {"input": "accel", "machine": "lathe", "cut_from": ["feed"], "dwell_axes": ["x_mm", "z_mm"]}
    an = ChatterAnalyzer("chatter", Section("t.toml", "analyzer.chatter", conf))
    bus, out = Bus(), []
    publish = bus.publish
    bus.publish = lambda m: (out.append((m.quantity, m.value)) if isinstance(m, Sample) else None, publish(m))[1]
    an.ctx = AnalyzerContext(bus, structlog.get_logger("test"), lambda *a, **k: None,
                             None, None, None, lambda n: None, ".")
    rng = np.random.default_rng(0)
    for k in range(20):
        t = k * 0.1
        an._on_machine(Sample("lathe", "x_mm", 14.0, "", t))
        an._on_machine(Sample("lathe", "z_mm", -min(t, 1.0) * 5, "", t))
        an._on_machine(Sample("lathe", "cutting_feed", 1.0 if t < 1.0 else 0.0, "", t))
        an._on_block(Block("accel", "acceleration", RATE, t + 3.0, k * FRAME, rng.normal(0, 1, FRAME), 2000.0))
    assert ("dwell", 1.0) in out and ("cutting", 0.0) not in out, out
    for k in range(20, 35):
        an._on_machine(Sample("lathe", "cutting_feed", 0.0, "", k * 0.1))
    assert out[-2:] == [("dwell", 0.0), ("cutting", 0.0)]      # dwell_max on the host's clock


def _dwell_run(program: list[str], parts: int, dwell_axes: bool, dwell_max: str = "2s", seed: int = 0,
               stall: tuple[float, float] | None = None, monkeypatch=None):
    """The simulated lathe's program (no daemon: its vibration in 20 ms frames, its registers
    polled every 100 ms as the Modbus driver does) into the chatter analyzer with the shipped
    cut_from; returns the published (quantity, value, sample time, sim time), the lathe, the analyzer.
    ``stall``: (from, seconds) of sim time with no poll (a loaded host), received on the sim's clock."""
    import structlog

    from lathed.analyzer import AnalyzerContext
    from lathed.bus import Block, Bus, Sample
    from lathed.config import Section
    from lathed.sim.program import parse_cut
    from lathed_plugins import chatter
    from lathed_plugins.chatter import ChatterAnalyzer
    conf = {"input": "accel", "machine": "lathe", "cut_from": ["feed", "load", "vibration"]}
    if dwell_axes:
        conf.update(dwell_axes=["x_mm", "y_mm"], dwell_max=dwell_max)
    an = ChatterAnalyzer("chatter", Section("t.toml", "analyzer.chatter", conf))
    lathe = SimLathe(program=tuple(parse_cut(c) for c in program), load_s=0.5, retract_s=0.2, seed=seed)
    out = []
    bus = Bus()
    publish = bus.publish

    def seen(m):
        if isinstance(m, Sample) and m.quantity in ("cutting", "chatter_alarm"):
            out.append((m.quantity, m.value, m.t, lathe.t))
        return publish(m)
    bus.publish = seen
    an.ctx = AnalyzerContext(bus, structlog.get_logger("test"), lambda kind, payload=None: None,
                             None, None, None, lambda name: None, ".")
    if monkeypatch is not None:
        monkeypatch.setattr(chatter.time, "monotonic", lambda: lathe.t)
    poll, k = 0.037, 0
    while len(lathe.parts) <= parts or lathe.phase_t < 0.4:      # the last end seen, the next pass not begun
        x = lathe.step(FRAME)
        while lathe.t >= poll:
            if stall is None or not stall[0] <= poll < stall[0] + stall[1]:
                for q, v in lathe.registers().items():
                    an._on_machine(Sample("lathe", q, float(v), "", poll))
            poll += 0.1
        an._on_block(Block("accel", "acceleration", RATE, lathe.t - FRAME / RATE, k * FRAME, x.astype(float),
                           lathe.block_rpm))
        k += 1
    return out, lathe, an


def _cuts(out) -> list[tuple[float, float, float]]:
    """(start, end, the sim time the end was published) of each cut."""
    states = [(v, t, at) for q, v, t, at in out if q == "cutting"]
    return [(a[1], b[1], b[2]) for a, b in zip(states[::2], states[1::2])]


@pytest.mark.parametrize("program, seed", [
    (["2000,1.0,0.3,30,dwell=1", "1500,1.0,0.3,20"], 0),
    (["2000,1.0,0.3,30,dwell=1", "1500,1.0,0.3,20"], 1),
    (["2000,1.0,0.3,30,dwell=1", "1500,1.0,0.3,20"], 2),
    # a finishing pass (the feed alone sees its chip) and a roughing one, each with a dwell
    (["3000,0.3,0.1,8,dwell=0.3", "1200,1.0,0.3,20,dwell=1"], 0)])
def test_a_dwell_is_not_the_end_of_the_cut(program, seed):
    """A dwell halfway along a stable pass: the feed, the load and the vibration all say "no
    chip" there.  With the axes' registers the pass is one cut: its end is not published before
    the retract, the re-entry raises no alarm, and the passes' real ends are seen as soon as
    without them (the next pass's feed comes on 0.7 s after the retract, well inside dwell_max).
    Without them the dwell ends the cut: two cuts for the one pass."""
    out, lathe, an = _dwell_run(program, 2, dwell_axes=True, seed=seed)
    cuts = _cuts(out)
    assert len(cuts) == 2 and an.dwells == sum("dwell=" in c for c in program), cuts
    assert not any(v for q, v, *_ in out if q == "chatter_alarm")
    for (start, end, told), p in zip(cuts, lathe.parts):
        assert start <= p.cut_start_s + 0.05 and p.cut_end_s < end
        assert told - p.cut_end_s < 0.35, (told, p.cut_end_s)      # the retract: at once, as without a hold
    before, lathe, _ = _dwell_run(program, 1, dwell_axes=False, seed=seed)
    assert [c[1] < lathe.parts[0].dwell_end_s for c in _cuts(before)] == [True, False]


@pytest.mark.parametrize("before, seconds", [(0.3, 0.5), (0.1, 0.8)])
def test_a_stalled_poll_at_a_dwell_holds_the_cut(monkeypatch, before, seconds):
    """No poll from just before a dwell's stop into it (a loaded host): the feed's last reading
    went stale in air, which ended the cut, so the pass made two cuts (the cure released under
    the chip; seen live on a loaded fresh clone). The stop is held until the feed is read."""
    program = ["2000,1.0,0.3,30,dwell=1", "1500,1.0,0.3,20"]
    _, lathe, _ = _dwell_run(program, 1, dwell_axes=True)
    p = lathe.parts[0]
    out, lathe, an = _dwell_run(program, 1, dwell_axes=True, stall=(p.dwell_start_s - before, seconds),
                                monkeypatch=monkeypatch)
    cuts = _cuts(out)
    assert len(cuts) == 1 and an.dwells == 1, cuts
    assert cuts[0][0] <= p.cut_start_s + 0.05 and p.cut_end_s < cuts[0][1] < p.cut_end_s + 0.35, cuts


@pytest.mark.parametrize("seconds", [1.0, 1.4])
def test_a_stalled_poll_over_a_pass_end_and_the_next_entry_is_two_cuts_with_the_axes_read(monkeypatch, seconds):
    """The same stall over a pass's end, the retract and the next pass's entry, with dwell_axes
    (the shipped table): held as a possible dwell, then the feed and axes read again say the tool
    went elsewhere: the first cut ends where the vibration went to air, the next is its own."""
    program = ["2000,1.0,0.3,30", "2500,1.0,0.3,20"]
    _, lathe, _ = _dwell_run(program, 2, dwell_axes=True)
    p, q = lathe.parts[0], lathe.parts[1]
    out, lathe, an = _dwell_run(program, 2, dwell_axes=True, stall=(p.cut_end_s - 0.1, seconds),
                                monkeypatch=monkeypatch)
    cuts = _cuts(out)
    assert len(cuts) == 2, cuts
    assert p.cut_end_s < cuts[0][1] < p.cut_end_s + 0.35 and q.cut_start_s <= cuts[1][0] < q.cut_start_s + seconds
    assert not any(v for k, v, *_ in out if k == "chatter_alarm")


def test_a_dwell_longer_than_dwell_max_ends_the_cut_then():
    """A feed stop that lasts (a feed hold left on, a 3 s dwell) holds the cut dwell_max, then
    ends it, dated when the chip was last seen; the pass's rest is a cut of its own."""
    out, lathe, an = _dwell_run(["2000,1.0,0.3,30,dwell=3"], 1, dwell_axes=True, dwell_max="1s")
    p = lathe.parts[0]
    cuts = _cuts(out)
    assert len(cuts) == 2 and an.dwells == 1, cuts
    (start, end, told), (start2, end2, _) = cuts
    assert p.dwell_start_s < end < p.dwell_start_s + 0.3            # the chip's end
    assert told - end == pytest.approx(1.0, abs=0.12)               # held dwell_max
    assert p.dwell_end_s - FRAME / RATE <= start2 < p.dwell_end_s + 0.2 and end2 > p.cut_end_s


@pytest.mark.parametrize("conf, error", [
    ({"dwell_max": "2s"}, 'dwell_max: a dwell is told by the axes standing: needs dwell_axes'),
    ({"dwell_axes": ["x_mm"], "cut_from": ["load", "vibration"]},
     'dwell_axes: a dwell is told from the cutting-feed signal: needs "feed" in cut_from'),
    ({"dwell_axes": ["x_mm"], "cut_from": ["feed"], "dwell_max": "0s"}, "dwell_max: '0s' is out of range")])
def test_the_dwell_keys_are_checked(conf, error):
    from lathed.config import ConfigError, Section
    from lathed_plugins.chatter import ChatterAnalyzer
    with pytest.raises(ConfigError, match=re.escape(f"t.toml: [analyzer.chatter] {error}")):
        ChatterAnalyzer("chatter", Section("t.toml", "analyzer.chatter",
                                           {"input": "accel", "machine": "lathe", **conf}))


def test_the_cut_state_is_one_pure_core_of_every_source():
    """lathed.analysis.cut.state.CutState, without the analyzer: the feed starts a cut in air,
    the vibration's step is the chip's contact (the detector then takes the samples from it),
    a feed stop with the axes standing holds the cut (its blocks are not the cut's), the feed
    back where it stopped is the same cut, joined as an impulse, and the retract ends it dated
    when the chip was last seen."""
    from lathed.analysis.cut.state import CutState
    cut = CutState(["feed", "vibration"], ["x_mm"], dwell_max=2.0)
    rng = np.random.default_rng(4)

    def block(level, t0):
        return cut.block(rng.normal(0, level, FRAME), RATE, t0)
    for k in range(40):                                   # the spindle in air: the floor learned
        assert block(1.0, k * FRAME / RATE).data is None
    assert cut.machine("x_mm", 15.5, 1.0, 2000.0) == []
    assert [e.kind for e in cut.machine("cutting_feed", 1.0, 1.0, 2000.0)] == ["start"]
    assert cut.cutting and cut.cut_by == "feed" and cut.chip_by is None
    air = block(1.0, 1.0)
    assert air.events == [] and air.data is not None      # the approach: the cut's, in air
    chip = cut.block(np.r_[rng.normal(0, 1.0, FRAME // 2), rng.normal(0, 8.0, FRAME // 2)], RATE, 1.02)
    assert [e.kind for e in chip.events] == ["contact"] and cut.chip_by == "vibration"
    assert chip.data is not None and len(chip.data) < FRAME      # from the chip on, not the air before
    cut.machine("x_mm", 15.0, 1.1, 2000.0)
    cut.machine("x_mm", 14.9, 1.2, 2000.0)
    assert cut.machine("cutting_feed", 0.0, 1.3, 2000.0) == []   # G04: the feed stops, the axis stands
    cut.machine("x_mm", 14.88, 1.35, 2000.0)
    held = []
    for k in range(12):                                   # ... and the chip thins to nothing
        b = block(1.0, 1.3 + k * FRAME / RATE)
        held += b.events
    assert [e.kind for e in held] == ["dwell"] and cut.held is not None and cut.dwells == 1
    assert b.data is None                                  # the dwell's blocks are not the cut's
    assert [e.kind for e in cut.machine("cutting_feed", 1.0, 1.6, 2000.0)] == ["dwell_over"]
    joined = block(8.0, 1.6)
    assert joined.data is not None and joined.impulse_at == 0 and cut.cutting
    cut.machine("x_mm", 14.7, 1.7, 2000.0)
    for k in range(12):                                   # the pass's end: the chip gone ...
        block(1.0, 1.7 + k * FRAME / RATE)
    assert [e.kind for e in cut.machine("cutting_feed", 0.0, 2.0, 2000.0)] == ["dwell"]
    assert cut.machine("x_mm", 20.0, 2.1, 2000.0) == []     # ... and the retract, the feed still
    (end,) = cut.machine("cutting_feed", 0.0, 2.2, 2000.0)   # off in the next poll: dated at the chip
    assert (end.kind, end.t, end.source, end.held) == ("end", 2.0, "axes", True) and not cut.cutting
    with pytest.raises(ValueError, match="needs \"feed\" in cut_from"):
        CutState(["load"], ["x_mm"])


def _two_passes(gap_s=0.33, stall=None, on_change=False, approach_s=0.0):
    """Two 1 s passes at 2500 r/min ``gap_s`` apart as a machine and its accelerometer send
    them: the feed read every 0.1 s (``stall``: no poll within it; ``on_change``: a driver that
    publishes only changes), the accelerometer in 20 ms blocks, each received when it happens.
    The feed goes on ``approach_s`` before each pass's chip. Yields (now, quantity, value) for
    the machine's samples and (now, None, (block, t0)) for the accelerometer's."""
    air0 = 0.3
    rec = simulate_cut([S(air0, 2500, 0.0), S(1.0, 2500, 1.0), S(gap_s, 2500, 0.0), S(1.0, 2500, 1.0),
                        S(0.3, 2500, 0.0)], modes=LATHE_MODES, kf_n_per_m2=LATHE_KF, seed=5)
    passes = [(air0 - approach_s, air0 + 1.0), (air0 + 1.0 + gap_s - approach_s, air0 + 2.0 + gap_s)]
    polls, last = iter(np.arange(0.0, len(rec.signal) / RATE, 0.1)), None
    poll = next(polls)
    for i in range(0, len(rec.signal) - FRAME + 1, FRAME):
        now = (i + FRAME) / RATE
        while poll is not None and poll <= now:
            if stall is None or not stall[0] < poll < stall[1]:
                on = any(a <= poll < b for a, b in passes)
                if not on_change or on != last:
                    yield poll, "cutting_feed", 1.0 if on else 0.0
                    last = on
                if not on_change:
                    yield poll, "spindle_rpm", 2500.0
            poll = next(polls, None)
        yield now, None, (rec.signal[i:i + FRAME], i / RATE)


def _passes(**kw):
    """_two_passes through CutState(["feed", "vibration"]): its events."""
    from lathed.analysis.cut.state import CutState
    cs, ev = CutState(["feed", "vibration"]), []
    for now, q, v in _two_passes(**kw):
        ev += cs.machine(q, v, now, 2500.0, now) if q else cs.block(v[0], RATE, v[1], now=now).events
    return ev


def test_a_stalled_feed_poll_does_not_hold_one_cut_across_two_passes():
    # no poll from 1.2 s to 2.0 s (a loaded host): the feed's last "on" held one cut over both
    # passes, and the detector met the second pass's entry mid-cut
    for stall in (None, (1.2, 2.0)):
        ev = _passes(stall=stall)
        starts = [e.t for e in ev if e.kind == "start"]
        ends = [e.t for e in ev if e.kind == "end"]
        assert len(starts) == 2 and len(ends) == 2, (stall, ev)
        # the first pass ends when the vibration's ring has decayed (or the feed's off is read)
        assert 1.3 <= ends[0] < 1.6 and 1.6 <= starts[1] < 1.66, (stall, ev)


def test_a_feed_on_in_air_holds_the_cut_while_it_is_read_and_from_a_driver_of_changes():
    # an approach at feed in air, 0.5 s: the feed read every poll, or published once by a driver
    # that sends only changes (its silence is no age), is one cut with the chip's contact in it
    for on_change in (False, True):
        ev = _passes(approach_s=0.5, gap_s=1.0, on_change=on_change)
        kinds = [e.kind for e in ev]
        assert kinds == ["start", "contact", "end", "start", "contact", "end"], (on_change, ev)


def test_the_chatter_analyzer_judges_its_sources_ages_on_the_hosts_clock(monkeypatch):
    # the plugin gives the cut state each sample's time of receipt: a stalled poll makes two cuts
    import structlog

    from lathed.analyzer import AnalyzerContext
    from lathed.bus import Block, Bus, Sample
    from lathed.config import Section
    from lathed_plugins import chatter
    conf = {"input": "accel", "machine": "lathe", "cut_from": ["feed", "vibration"]}
    an = chatter.ChatterAnalyzer("chatter", Section("t.toml", "analyzer.chatter", conf))
    bus, out = Bus(), []
    publish = bus.publish
    bus.publish = lambda m: (out.append((m.quantity, m.value)) if isinstance(m, Sample) else None, publish(m))[1]
    an.ctx = AnalyzerContext(bus, structlog.get_logger("test"), lambda *a, **k: None,
                             None, None, None, lambda n: None, ".")
    clock = [0.0]
    monkeypatch.setattr(chatter.time, "monotonic", lambda: clock[0])
    for now, q, v in _two_passes(stall=(1.2, 2.0)):
        clock[0] = 1000.0 + now            # the host's clock: not the samples' time stamps
        if q:
            an._on_machine(Sample("lathe", q, v, "", now))
        else:
            an._on_block(Block("accel", "acceleration", RATE, v[1], round(v[1] * RATE), v[0], 2500.0))
    assert [v for q, v in out if q == "cutting"] == [1.0, 0.0, 1.0, 0.0], out
