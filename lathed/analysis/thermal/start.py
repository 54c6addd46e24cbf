"""Runs from several days: which start cold, which continue an earlier run, which start warm.

Rises are taken from a run's first rows, which is right for a run from a cold start. A run is
cold when the machine's own sensors agree with each other as they did at the first run's cold
start, whatever the room air reads (a shop warms up in the morning faster than a machine's iron),
as long as it is within ROOM_SLACK_C of that air.
See docs/thermal.md, "Several runs".
"""
from __future__ import annotations

import statistics
from typing import Mapping, Sequence

import numpy as np

from lathed.analysis.thermal.data import ThermalData, ThermalRuns, room_column, start_temp

# A machine sensor standing further above the others than at the cold start, by more than this
# share of its rise in that run: the run did not start cold.
WARM_START_SHARE = 0.25
WARM_START_MIN_C = 0.25     # 4 DS18B20 steps: below it a start is cold whatever the run's rise
# How far a shop's air may lead or lag the machine's iron at a cold start (it warms up in the
# morning faster than the iron): a machine further above the room than this is warm even when
# its sensors agree with each other.
ROOM_SLACK_C = 2.0


def _is_room(column: str) -> bool:
    return "room" in column or "ambient" in column


def warm_sensors(cold: ThermalData, run: ThermalData) -> list[str]:
    """Why ``run`` does not start cold, judged against ``cold`` (a run from a cold start): one
    line per machine sensor that starts warm, none when it starts cold.

    Each sensor's start is compared with its start in ``cold``. The machine is cold when its own
    sensors agree with each other as they did then (each within its share of the run's rise of
    their common shift, the median), whatever the room's air reads, as long as the machine is not
    further above the room than a shop's air lags its iron (``ROOM_SLACK_C``): the only check a
    machine whose sensors all heat alike leaves."""
    sensors = [s for s in run.sensors if s in cold.temps_c and not _is_room(s)]
    if not sensors:
        return []

    def start(d: ThermalData, k: str) -> float:
        return start_temp(d.time_s, d.temps_c[k])
    d = {s: start(run, s) - start(cold, s) for s in sensors}
    span = {s: float(np.ptp(cold.rise(s))) for s in sensors}
    shift = statistics.median(d.values())
    room = room_column([k for k in run.sensors if k in cold.temps_c])
    room_shift = None if room is None else start(run, room) - start(cold, room)
    out = []
    for s in sensors:
        allowed = max(WARM_START_SHARE * span[s], WARM_START_MIN_C)
        if len(sensors) > 1 and d[s] - shift > allowed:
            out.append(f"{s} starts at {start(run, s):.2f} °C, {d[s] - shift:.2f} °C further above the machine's "
                       f"other sensors than at the cold start (it rose {span[s]:.2f} °C in that run)")
        elif room_shift is not None and d[s] - room_shift > allowed + ROOM_SLACK_C:
            out.append(f"{s} starts at {start(run, s):.2f} °C, {d[s] - room_shift:.2f} °C further above the room "
                       f"than at the cold start (it rose {span[s]:.2f} °C in that run; a cold machine is within "
                       f"{ROOM_SLACK_C:g} °C of the room's air)")
    return out


def cold_again(cold_c: Mapping[str, float], now_c: Mapping[str, float], rpm_then: float | None = None,
               rpm_now: float | None = None) -> bool:
    """Live, from one reading of each sensor (keys as the daemon keeps them, ``motor`` or
    ``t_motor_c``): is the machine cold again since the cold start that read ``cold_c``, and
    has it moved from it (another day)? Its own sensors agree with each other within
    ``WARM_START_MIN_C`` of their common shift (no run's rise is at hand to scale it by), and it
    is within ``ROOM_SLACK_C`` of the room's shift.

    Only a standing spindle is judged (``rpm_now``, and ``rpm_then`` at the cold start; None:
    not known): a turning one heats its bearings, and a machine that has run for hours at one
    speed warms all over, its sensors then as far apart as at a cold start taken on a turning
    spindle, all of them shifted alike."""
    if (rpm_now or 0.0) > 0 or (rpm_then or 0.0) > 0:
        return False
    keys = [k for k in now_c if k in cold_c]
    machine = [k for k in keys if not _is_room(k)]
    if len(machine) < 2:
        return False            # one sensor has nothing to agree with: keep the cold start in use
    d = {k: float(now_c[k]) - float(cold_c[k]) for k in keys}
    shift = statistics.median(d[k] for k in machine)
    if any(d[k] - shift > WARM_START_MIN_C for k in machine):
        return False
    room = next((k for k in keys if _is_room(k)), None)
    if room is not None and any(d[k] - d[room] > WARM_START_MIN_C + ROOM_SLACK_C for k in machine):
        return False
    return max(abs(d[k]) for k in machine) >= WARM_START_MIN_C


def iron_referenced(first: ThermalData, run: ThermalData) -> ThermalData:
    """``run``, a cold start on another day, with its machine sensors' rises taken from where the
    iron stood at ``first``'s cold start, shifted as the machine's own sensors shifted (their
    median), when both take their rises from the room (rows over ``ROOM_REF_MIN_DT_S`` apart):
    the room's air of a morning may stand 1-1.5 °C off the iron, and from it every rise of the
    run would be off by as much (2.0 µm/°C on three sensors: 5.6 µm on a simulated day)."""
    if run.rises_from is None or first.rises_from is None:
        return run
    machine = [k for k in run.sensors if k in first.temps_c and not _is_room(k)]
    if not machine:
        return run
    shift = statistics.median(start_temp(run.time_s, run.temps_c[k]) - start_temp(first.time_s, first.temps_c[k])
                              for k in machine)
    ref = dict(run.reference_c) | {k: first.reference_c[k] + shift for k in machine}
    return ThermalData(run.time_s, run.temps_c, run.displacement_um, run.rpm, ref, run.t0_s, run.rises_from)


def continues(before: ThermalData, run: ThermalData) -> bool:
    """Does ``run`` go on from ``before`` (its clock starts after ``before`` ends)?"""
    return bool(run.time_s[0] > before.time_s[-1])


def continued(before: ThermalData, run: ThermalData) -> ThermalData:
    """``run`` with its rises and drift clock taken from ``before``'s cold start."""
    ref = {k: before.reference_c[k] for k in run.temps_c if k in before.reference_c}
    ref |= {k: v for k, v in run.reference_c.items() if k not in before.reference_c}
    return ThermalData(run.time_s, run.temps_c, run.displacement_um, run.rpm, ref, before.t0_s, before.rises_from)


def reference_test(train: ThermalData | ThermalRuns, test: ThermalData) -> tuple[ThermalData, str | None]:
    """Make a test run's rises comparable with the fit's: a run on the (last) training run's
    clock continues it; any other must start cold. Returns the test run and a line saying what
    was done (None when it starts cold); ValueError when it starts warm."""
    runs = train.runs if isinstance(train, ThermalRuns) else [train]
    if continues(runs[-1], test):
        return continued(runs[-1], test), (
            f"the test run continues the training run's clock (starts at {test.time_s[0]:g} s, the training "
            f"run ends at {runs[-1].time_s[-1]:g} s): its rises are taken from the training run's cold start, "
            f"not from its own first rows")
    warm = warm_sensors(runs[0], test)
    if warm:
        raise ValueError(f"the test run does not start cold: {'; '.join(warm)}; rises from its first rows "
                         f"would miss the warm-up. Give a run from a cold start, one continuing the training "
                         f"run's time_s, or use --split")
    return iron_referenced(runs[0], test), None


def _joined(a: ThermalData, b: ThermalData) -> ThermalData:
    """``b`` appended to ``a`` as one run (terms with memory carry on)."""
    cat = np.concatenate
    return ThermalData(cat([a.time_s, b.time_s]), {k: cat([a.temps_c[k], b.temps_c[k]]) for k in a.temps_c},
                       None if a.displacement_um is None or b.displacement_um is None
                       else cat([a.displacement_um, b.displacement_um]),
                       None if a.rpm is None or b.rpm is None else cat([a.rpm, b.rpm]),
                       a.reference_c, a.t0_s, a.rises_from)


def join_runs(runs: Sequence[tuple[str, ThermalData]]) -> tuple[ThermalData | ThermalRuns, list[str]]:
    """Several runs (name, rows) in time order as training rows: each from its own cold start, or
    continuing the run before it when its clock goes on from it. A run that starts warm is
    refused (ValueError naming it). Returns the rows and a line for each continuation."""
    if not runs:
        raise ValueError("no run given")
    cols = set(runs[0][1].temps_c)
    out: list[ThermalData] = [runs[0][1]]
    notes = []
    for name, r in runs[1:]:
        if set(r.temps_c) != cols:
            raise ValueError(f"{name} has temperature columns {', '.join(sorted(r.temps_c))}, the first run "
                             f"{', '.join(sorted(cols))}: every run needs the same ({name}, line 1)")
        if continues(out[-1], r):
            out[-1] = _joined(out[-1], continued(out[-1], r))
            notes.append(f"{name} continues the run before it (its time_s goes on): one run from that cold start")
            continue
        warm = warm_sensors(out[0], r)
        if warm:
            raise ValueError(f"{name} does not start cold: {'; '.join(warm)}; rises from its first rows would "
                             f"miss the warm-up. Give runs from a cold start, or continue a run's time_s ({name})")
        out.append(iron_referenced(out[0], r))
    return (out[0] if len(out) == 1 else ThermalRuns(out)), notes
