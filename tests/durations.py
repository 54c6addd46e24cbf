"""Writes tests/durations.json, the seconds each test file takes, from the log of a full run
with `--durations=0` (setup, call and teardown summed per file). conftest.py orders the files
by it for `make test`, the longest first; the figures decide nothing else.

    .venv/bin/python -m pytest -n 4 --dist loadfile --durations=0 > run.log
    .venv/bin/python tests/durations.py run.log
"""
from __future__ import annotations

import json
import re
import sys
from pathlib import Path

LINE = re.compile(r"^([\d.]+)s (?:setup|call|teardown)\s+(tests/[^:]+\.py)::")


def per_file(log: str) -> dict[str, float]:
    seconds: dict[str, float] = {}
    for line in log.splitlines():
        m = LINE.match(line)
        if m:
            seconds[m[2]] = seconds.get(m[2], 0.0) + float(m[1])
    return {f: round(s, 1) for f, s in sorted(seconds.items(), key=lambda kv: -kv[1])}


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: tests/durations.py RUN.LOG (a pytest log with --durations=0)", file=sys.stderr)
        return 2
    seconds = per_file(Path(argv[0]).read_text(errors="replace"))
    if not seconds:
        print(f"tests/durations.py: {argv[0]}: no durations (was the run made with --durations=0?)",
              file=sys.stderr)
        return 65
    out = Path(__file__).with_name("durations.json")
    out.write_text(json.dumps(seconds, indent=0) + "\n")
    print(f"{out}: {len(seconds)} files, {sum(seconds.values()):.0f} s in all")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
