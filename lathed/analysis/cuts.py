"""Cut records: the evidence the stability model is checked against.

One cut (entry to exit) is one row of a CSV file:

    machine,tool,material,rpm,depth_mm,feed_mm_rev,outcome,chatter_frequency_hz
    lathe1,CNMG120408,C45,1850,1.2,0.25,stable,
    lathe1,CNMG120408,C45,2100,2.4,0.25,chatter,668.5

``outcome`` is ``stable`` or ``chatter``; ``chatter_frequency_hz`` is
optional (column or cell may be left out) and only allowed on a chatter cut.
The order of the rows is the order the cuts were made: the refit fits on the
earlier ones and judges on the later ones.  Columns not named here are
ignored (listed in the report).

The reader is strict: a cut that cannot be read is not silently dropped, since
one wrong label moves the fitted lobes.  Every bad row yields one line naming
file, line and column; :class:`CutsCsvError` carries them all.
"""
from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import numpy as np

EX_DATAERR = 65
EX_NOINPUT = 66

REQUIRED = ("machine", "tool", "material", "rpm", "depth_mm", "feed_mm_rev", "outcome")
OPTIONAL = ("chatter_frequency_hz",)
OUTCOMES = ("stable", "chatter")

# Physical ranges: beyond them the column is in other units or corrupt.
RPM_MAX = 100_000.0        # lathed.cli.SPINDLE_RPM_MAX: beyond any spindle
DEPTH_MM_MAX = 50.0        # radial depth of a turning cut
FEED_MM_REV_MAX = 10.0
CHATTER_HZ_MAX = 50_000.0  # above any structural mode of a machine tool
# At most this many bad-row lines are kept (the count says how many in all).
MAX_ERRORS = 20


class CutsCsvError(Exception):
    """Bad cut records: one line per problem, and the exit code for the CLI."""

    def __init__(self, lines: list[str], exit_code: int = EX_DATAERR, total: int | None = None):
        self.lines = list(lines)
        self.total = len(lines) if total is None else total
        self.exit_code = exit_code
        super().__init__("\n".join(self.lines))


@dataclass
class Cuts:
    """Cuts of one file as columns, in the order they were made."""
    machine: list[str]
    tool: list[str]
    material: list[str]
    rpm: np.ndarray
    depth_mm: np.ndarray
    feed_mm_rev: np.ndarray
    chatter: np.ndarray                 # bool: the cut chattered
    chatter_frequency_hz: np.ndarray    # nan where not measured
    line: np.ndarray                    # line in the file (1 = header)
    source: str = ""
    ignored_columns: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.rpm)

    def take(self, idx) -> Cuts:
        idx = np.asarray(idx)
        if idx.dtype == bool:
            idx = np.flatnonzero(idx)
        pick = lambda xs: [xs[i] for i in idx]  # noqa: E731
        return Cuts(pick(self.machine), pick(self.tool), pick(self.material), self.rpm[idx],
                    self.depth_mm[idx], self.feed_mm_rev[idx], self.chatter[idx],
                    self.chatter_frequency_hz[idx], self.line[idx], self.source, self.ignored_columns)

    def setups(self) -> list[tuple[str, str, str]]:
        """Distinct (machine, tool, material) in order of first appearance."""
        return list(dict.fromkeys(zip(self.machine, self.tool, self.material)))

    @classmethod
    def from_arrays(cls, rpm, depth_mm, chatter, chatter_frequency_hz=None, *, machine="lathe",
                    tool="tool", material="material", feed_mm_rev=0.25, source="") -> Cuts:
        rpm = np.asarray(rpm, float)
        n = len(rpm)
        f = np.full(n, np.nan) if chatter_frequency_hz is None else np.asarray(chatter_frequency_hz, float)
        return cls([machine] * n, [tool] * n, [material] * n, rpm, np.asarray(depth_mm, float),
                   np.broadcast_to(np.asarray(feed_mm_rev, float), (n,)).copy(),
                   np.asarray(chatter, bool), f, np.arange(2, n + 2), source)


def _number(cell: str, col: str, lo: float, hi: float, where: str, unit: str) -> tuple[float | None, str | None]:
    if cell == "":
        return None, f"{col} is empty ({where}, column {col})"
    try:
        v = float(cell)
    except ValueError:
        return None, f"{col} = {cell!r} is not a number ({where}, column {col})"
    if not math.isfinite(v):
        return None, f"{col} = {cell} is not a finite number ({where}, column {col})"
    if not lo < v <= hi:
        return None, f"{col} = {cell} is outside the physical range {lo:g} < {col} <= {hi:g} {unit} ({where}, column {col})"
    return v, None


def load_cuts_csv(path: str | Path) -> Cuts:
    """Read a cut-record CSV; raise CutsCsvError listing every bad row."""
    path = Path(path)
    try:
        f = open(path, newline="", encoding="utf-8-sig")
    except OSError as e:
        raise CutsCsvError([f"cannot read {path}: {e.strerror or e}"], EX_NOINPUT) from None
    with f:
        try:
            rows = list(csv.reader(f))
        except (csv.Error, UnicodeDecodeError) as e:
            raise CutsCsvError([f"{path} is not a readable CSV file: {e}"]) from None
    if not rows or not any(c.strip() for c in rows[0]):
        raise CutsCsvError([f"{path}:1: empty file: expected the header {','.join(REQUIRED + OPTIONAL)}"])
    header = [c.strip() for c in rows[0]]
    dupes = sorted({c for c in header if c and header.count(c) > 1})
    if dupes:
        raise CutsCsvError([f"{path}:1: column {dupes[0]!r} appears twice in the header"])
    missing = [c for c in REQUIRED if c not in header]
    if missing:
        raise CutsCsvError([f"{path}:1: missing required column {missing[0]!r}; found {', '.join(header)}"])
    idx = {c: header.index(c) for c in REQUIRED + OPTIONAL if c in header}
    ignored = [c for c in header if c not in idx]
    errors: list[str] = []
    total_bad = 0
    vals: dict[str, list] = {c: [] for c in REQUIRED + OPTIONAL}
    lines: list[int] = []
    for lineno, row in enumerate(rows[1:], start=2):
        if not any(c.strip() for c in row):
            continue           # a blank line is not a cut
        where = f"{path}:{lineno}"
        cell = {c: (row[i].strip() if i < len(row) else "") for c, i in idx.items()}
        err = None
        if len(row) > len(header) and any(c.strip() for c in row[len(header):]):
            err = f"{len(row)} fields for {len(header)} columns ({where}, after column {header[-1]})"
        for c in ("machine", "tool", "material"):
            if err is None and cell[c] == "":
                err = f"{c} is empty ({where}, column {c})"
        rpm = depth = feed = freq = None
        if err is None:
            rpm, err = _number(cell["rpm"], "rpm", 0.0, RPM_MAX, where, "r/min")
        if err is None:
            depth, err = _number(cell["depth_mm"], "depth_mm", 0.0, DEPTH_MM_MAX, where, "mm")
        if err is None:
            feed, err = _number(cell["feed_mm_rev"], "feed_mm_rev", 0.0, FEED_MM_REV_MAX, where, "mm/rev")
        outcome = cell["outcome"].lower()
        if err is None and outcome not in OUTCOMES:
            err = f"outcome = {cell['outcome']!r} must be stable or chatter ({where}, column outcome)"
        fcell = cell.get("chatter_frequency_hz", "")
        if err is None and fcell != "":
            if outcome == "stable":
                err = (f"chatter_frequency_hz = {fcell} on a stable cut: a frequency is measured only "
                       f"when the cut chatters ({where}, column chatter_frequency_hz)")
            else:
                freq, err = _number(fcell, "chatter_frequency_hz", 0.0, CHATTER_HZ_MAX, where, "Hz")
        if err is not None:
            total_bad += 1
            if len(errors) < MAX_ERRORS:
                errors.append(err)
            continue
        for c in ("machine", "tool", "material"):
            vals[c].append(cell[c])
        vals["rpm"].append(rpm)
        vals["depth_mm"].append(depth)
        vals["feed_mm_rev"].append(feed)
        vals["outcome"].append(outcome == "chatter")
        vals["chatter_frequency_hz"].append(math.nan if freq is None else freq)
        lines.append(lineno)
    if total_bad:
        if total_bad > len(errors):
            errors.append(f"{path}: {total_bad - len(errors)} more bad row(s) not listed; {total_bad} in all")
        raise CutsCsvError(errors, total=total_bad)
    if not lines:
        raise CutsCsvError([f"{path}: no cut in the file, only the header"])
    return Cuts(vals["machine"], vals["tool"], vals["material"], np.array(vals["rpm"]),
                np.array(vals["depth_mm"]), np.array(vals["feed_mm_rev"]), np.array(vals["outcome"], bool),
                np.array(vals["chatter_frequency_hz"]), np.array(lines), str(path), ignored)


def write_cuts_csv(cuts: Cuts, path: str | Path | TextIO) -> None:
    """Write cuts in the format load_cuts_csv reads (to a path or an open text file)."""
    if not isinstance(path, (str, Path)):
        _write_rows(cuts, path)
        return
    with open(path, "w", newline="", encoding="utf-8") as f:
        _write_rows(cuts, f)


def _write_rows(cuts: Cuts, f: TextIO) -> None:
    w = csv.writer(f)
    w.writerow(REQUIRED + OPTIONAL)
    for i in range(len(cuts)):
        fz = cuts.chatter_frequency_hz[i]
        w.writerow([cuts.machine[i], cuts.tool[i], cuts.material[i], f"{cuts.rpm[i]:.6g}",
                    f"{cuts.depth_mm[i]:.6g}", f"{cuts.feed_mm_rev[i]:.6g}",
                    "chatter" if cuts.chatter[i] else "stable",
                    "" if not math.isfinite(fz) else f"{fz:.6g}"])
