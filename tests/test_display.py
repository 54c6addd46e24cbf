"""What a screen gets of a 51.2 kS/s channel (lathed.display): small, and true to the signal."""
from __future__ import annotations

import json

import numpy as np

from lathed.display import COLUMNS, SPECTRUM_BINS, Ring, envelope, packed, rounded, spectrum, unpacked

RATE = 51200.0


def test_envelope_keeps_every_extreme():
    x = np.random.default_rng(1).normal(size=8192)
    x[5000] = 9.0                      # one sample spike: a plot of every 20th sample would miss it
    env = {k: unpacked(v) for k, v in envelope(x, RATE).items()}
    assert len(env["env_max"]) == COLUMNS
    assert max(env["env_max"]) == 9.0 and min(env["env_min"]) == np.float32(x.min())


def test_spectrum_finds_a_chatter_tone_at_its_frequency_and_amplitude():
    t = np.arange(8192) / RATE
    x = 0.01 * np.random.default_rng(2).normal(size=t.size) + 2.0 * np.sin(2 * np.pi * 620.0 * t)
    sp = {k: unpacked(v) for k, v in spectrum(x, RATE).items()}
    assert len(sp["spec_f"]) <= SPECTRUM_BINS and max(sp["spec_f"]) <= 5000
    peak = int(np.argmax(sp["spec_a"]))
    assert abs(sp["spec_f"][peak] - 620.0) < 15      # a bin is 12.5 Hz wide
    assert 1.6 < sp["spec_a"][peak] < 2.1           # Hann scalloping at most -1.4 dB


def test_ring_view_is_small_json_and_follows_a_rate_change():
    r = Ring()
    r.add(np.ones(10_000), RATE, 100.0)
    v = r.view()
    assert v["t_end"] == 100.0 + 10_000 / RATE and len(json.dumps(v)) < 20_000
    r.add(np.ones(100), 1000.0, 200.0)       # another stream rate: the old samples are not mixed in
    assert r.filled == 100


def test_ring_keeps_the_last_window_in_order_across_wraps():
    # blocks of every size, smaller and larger than the ring: the view is that of the last samples
    rng = np.random.default_rng(3)
    r, seen = Ring(size=1000), np.zeros(0)
    for i, n in enumerate([1, 999, 7, 1500, 333, 333, 333, 64, 2000, 5]):
        block = rng.normal(size=n)
        r.add(block, RATE, float(i))
        seen = np.concatenate((seen, block))[-1000:]
        if len(seen) >= 64:
            assert r.view() == {"t_end": i + n / RATE, "rate_hz": RATE, **envelope(seen, RATE), **spectrum(seen, RATE)}


def test_rounded_is_json_safe():
    assert rounded(np.array([0.0123456, 1.23456, np.nan, np.inf])) == [0.012, 1.235, None, None]
    assert json.dumps(rounded(np.zeros(2))) == "[0.0, 0.0]"


def test_packed_arrays_are_float32_exact_and_smaller_than_json():
    a = np.random.default_rng(4).normal(size=400) * 1e3
    a[7] = np.nan                                  # a gap stays a gap
    p = packed(a)
    back = unpacked(json.loads(json.dumps(p)))
    assert np.array_equal(back[np.isfinite(a)], a[np.isfinite(a)].astype(np.float32)) and np.isnan(back[7])
    assert len(json.dumps(p)) < len(json.dumps(rounded(a)))
    assert unpacked([1.0, 2.0]).tolist() == [1.0, 2.0] and unpacked(packed(np.empty(0))).size == 0


def test_ring_holds_no_more_blocks_than_its_window_needs():
    r = Ring(size=1000)
    for i in range(500):
        r.add(np.full(300, float(i)), RATE, float(i))
    assert len(r._blocks) == 4 and r.filled == 1000       # 1000 samples span 4 blocks of 300
    assert (r.window() == np.repeat([496.0, 497, 498, 499], [100, 300, 300, 300])).all()
