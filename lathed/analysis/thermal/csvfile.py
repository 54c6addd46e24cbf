"""Reading thermal runs from CSV, rejecting bad rows by reason.

Columns: ``time_s``, optional ``spindle_rpm``, temperature columns
``t_<place>_c`` (°C) and ``displacement_um``. A row is rejected, and counted
under its reason, when a DS18B20 glitch shows (85.0 °C is the power-on value
read before the first conversion; −127 °C means the sensor is disconnected),
a cell is empty or not a number (or NaN), or its time stamp repeats or runs
backwards. A file that cannot be read, lacks a required column, has a value
outside what its quantity can physically be (lathed.plausible's bounds of its
unit: °C, r/min, µm; time_s within ±1e10 s) or has no usable row raises :class:`ThermalCsvError` with one line naming file and line.
"""
from __future__ import annotations

import csv
import math
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lathed.analysis.thermal.data import ThermalData
from lathed.plausible import UNIT_DEFAULTS

EX_DATAERR = 65
EX_NOINPUT = 66

DS18B20_POWER_ON_C = 85.0
DS18B20_DISCONNECTED_C = -127.0

# Reasons, in the order they are checked.
REASONS = ("sensor_disconnected_-127", "sensor_power_on_85", "empty_cell", "not_a_number",
           "nan", "duplicate_time", "backwards_time")


class ThermalCsvError(Exception):
    """One line for the operator, and the exit code that goes with it."""

    def __init__(self, message: str, exit_code: int = EX_DATAERR):
        super().__init__(message)
        self.exit_code = exit_code


@dataclass
class LoadReport:
    used: int = 0
    rejected: Counter = field(default_factory=Counter)
    first_line: dict[str, int] = field(default_factory=dict)   # first line per reason
    ignored_columns: list[str] = field(default_factory=list)

    def reject(self, reason: str, line: int) -> None:
        self.rejected[reason] += 1
        self.first_line.setdefault(reason, line)

    def to_json(self) -> dict:
        return {"used": self.used, "rejected": {r: self.rejected[r] for r in REASONS if self.rejected[r]},
                "rejected_total": sum(self.rejected.values()),
                **({"ignored_columns": self.ignored_columns} if self.ignored_columns else {})}


def _is_temp(name: str) -> bool:
    return name.startswith("t_") and name.endswith("_c") and len(name) > 4


TIME_S_MAX = 1e10    # s: covers Unix time stamps; beyond it the column is not seconds


def _plausible(col: str, temps: list[str]) -> tuple[float, float]:
    if col in temps:
        b = UNIT_DEFAULTS["°C"]
    elif col == "spindle_rpm":
        b = UNIT_DEFAULTS["r/min"]
    elif col == "displacement_um":
        b = UNIT_DEFAULTS["µm"]
    else:
        return -TIME_S_MAX, TIME_S_MAX
    return b.lo, b.hi


def load_thermal_csv(path: str | Path, need_displacement: bool = True) -> tuple[ThermalData, LoadReport]:
    path = Path(path)
    try:
        f = open(path, newline="", encoding="utf-8-sig")
    except OSError as e:
        raise ThermalCsvError(f"cannot read {path}: {e.strerror or e}", EX_NOINPUT) from None
    with f:
        try:
            rows = list(csv.reader(f))
        except (csv.Error, UnicodeDecodeError) as e:
            raise ThermalCsvError(f"{path} is not a readable CSV file: {e}") from None
    if not rows or not any(c.strip() for c in rows[0]):
        raise ThermalCsvError(f"{path} is empty: expected a header line with time_s, t_<place>_c "
                              f"and displacement_um ({path}, line 1)")
    header = [c.strip() for c in rows[0]]
    dupes = sorted({c for c in header if header.count(c) > 1})
    if dupes:
        raise ThermalCsvError(f"column {dupes[0]!r} appears twice in the header ({path}, line 1)")
    required = ["time_s"] + (["displacement_um"] if need_displacement else [])
    for col in required:
        if col not in header:
            raise ThermalCsvError(f"missing required column {col!r}; found {', '.join(header)} "
                                  f"({path}, line 1)")
    temps = [c for c in header if _is_temp(c)]
    if not temps:
        raise ThermalCsvError(f"no temperature column: expected columns named t_<place>_c, "
                              f"e.g. t_front_bearing_c ({path}, line 1)")
    known = set(required) | set(temps) | {"spindle_rpm", "displacement_um"}
    report = LoadReport(ignored_columns=[c for c in header if c not in known])
    cols = [c for c in header if c in known]
    idx = {c: header.index(c) for c in cols}
    out: dict[str, list[float]] = {c: [] for c in cols}
    # per column once, not per cell: (index, is a temperature, plausible range)
    spec = [(c, idx[c], c in temps, *_plausible(c, temps)) for c in cols]
    last_t = -math.inf
    for lineno, row in enumerate(rows[1:], start=2):
        if not any(c.strip() for c in row):
            continue      # a blank line is not a row
        vals: dict[str, float] = {}
        reason = None
        for c, i, is_temp, lo, hi in spec:
            cell = row[i].strip() if i < len(row) else ""
            if cell == "":
                reason = reason or "empty_cell"
                continue
            try:
                v = float(cell)
            except ValueError:
                reason = reason or "not_a_number"
                continue
            if not math.isfinite(v):
                reason = reason or "nan"
                continue
            if not lo <= v <= hi and not (is_temp and v == DS18B20_DISCONNECTED_C):
                # wrong units or a corrupt file, not a glitch of one row: refuse it whole
                raise ThermalCsvError(f"{c} = {cell} is outside the physically plausible {lo:g}..{hi:g} "
                                      f"({path}, line {lineno}, column {c})")
            if is_temp and v == DS18B20_DISCONNECTED_C:
                reason = "sensor_disconnected_-127"
            elif is_temp and v == DS18B20_POWER_ON_C and reason != "sensor_disconnected_-127":
                reason = "sensor_power_on_85"
            vals[c] = v
        if reason is None:
            t = vals["time_s"]
            if t == last_t:
                reason = "duplicate_time"
            elif t < last_t:
                reason = "backwards_time"
        if reason is not None:
            report.reject(reason, lineno)
            continue
        last_t = vals["time_s"]
        for c in cols:
            out[c].append(vals[c])
    report.used = len(out["time_s"])
    if report.used == 0:
        why = ", ".join(f"{n} {r} (first at line {report.first_line[r]})"
                        for r, n in report.rejected.most_common()) or "no data rows"
        raise ThermalCsvError(f"no usable row in {path}: {why} ({path})")
    data = ThermalData(
        time_s=np.array(out["time_s"]),
        temps_c={c: np.array(out[c]) for c in temps},
        displacement_um=np.array(out["displacement_um"]) if "displacement_um" in out else None,
        rpm=np.array(out["spindle_rpm"]) if "spindle_rpm" in out else None,
    )
    return data, report
