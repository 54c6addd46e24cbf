"""lathed.memtrim gives a freed heap back to the system (make bench-hostile's RSS bar)."""
import subprocess
import sys

import pytest

from lathed import memtrim

PROBE = r"""
import sys
from lathed import memtrim

def rss_mb():
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS"):
            return int(line.split()[1]) / 1024

held = [bytes(4000) for _ in range(40_000)]       # 160 MB of malloc'd blocks on the heap
keep = bytes(4000)                                # a block above them: the heap's top stays in use
del held
before = rss_mb()
if sys.argv[1] == "trim":
    memtrim.trim()
print(before, rss_mb())
"""


@pytest.mark.skipif(not memtrim.available(), reason="this C library has no malloc_trim")
def test_trim_returns_freed_heap_pages():
    out = {}
    for mode in ("none", "trim"):
        r = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, check=True)
        out[mode] = [float(x) for x in r.stdout.split()]
    before, after = out["none"]
    assert after > before - 20, out          # freed but kept: what the daemon's RSS did after a flood
    before, after = out["trim"]
    assert after < before - 100, out         # trimmed: given back
