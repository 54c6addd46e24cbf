"""A recording made by ``lathectl record`` run through a detector as the live analyzer ran
it: the detector only in the cuts the daemon saw, learning afresh at each cut's start, fed
in the sensor's own blocks at the speed the machine (or the keyphasor) gave at each block.
Windows come back dated in seconds from the recording's first sample.
"""
from __future__ import annotations

import numpy as np


def speed_at(track: list[list[float]], t: float) -> float | None:
    """The last speed given at or before ``t`` (the first one before any)."""
    if not track:
        return None
    times = [row[0] for row in track]
    i = int(np.searchsorted(times, t, side="right")) - 1
    return float(track[max(i, 0)][1])


def replay(det, x: np.ndarray, rate_hz: float, side: dict, rpm: float | None = None, block: int = 1024):
    """Windows of ``det`` over ``x`` cut by cut (``side``: the sidecar). ``rpm``: one speed for
    all, instead of the recorded track. Returns (windows, cuts [(start_s, end_s)])."""
    track = side.get("speed_keyphasor") or side.get("speed") or []
    cuts = side.get("cuts") or []
    if not cuts and not side.get("cut_from"):
        cuts = [[0.0, None]]             # recorded without a cut state: the whole recording is one cut
    out, spans = [], []
    for start, end in cuts:
        i0 = max(0, int(round(start * rate_hz)))
        i1 = len(x) if end is None else min(len(x), int(round(end * rate_hz)))
        if i1 - i0 < block:
            continue
        det.reset()
        spans.append((i0 / rate_hz, i1 / rate_hz))
        for i in range(i0, i1, block):
            r = rpm if rpm is not None else speed_at(track, i / rate_hz)
            if not r or r <= 0:
                continue
            for w in det.process(x[i:min(i + block, i1)], r):
                w.t_s += i0 / rate_hz
                out.append(w)
    return out, spans


def live_spans(alarms: list[list[float]]) -> list[tuple[float, float | None]]:
    """The live analyzer's alarms, [seconds, 1/0] as recorded, as (raised, cleared) spans."""
    spans, t0 = [], None
    for t, v in alarms:
        if v and t0 is None:
            t0 = t
        elif not v and t0 is not None:
            spans.append((t0, t))
            t0 = None
    if t0 is not None:
        spans.append((t0, None))
    return spans
