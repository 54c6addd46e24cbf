"""What the programs the suite starts hundreds of times import at start: a library that only a
configured feature uses is imported with that feature (bench/bench_startup.py has the CPU figures)."""
from __future__ import annotations

import json
import subprocess
import sys

HEAVY = ("aiohttp", "can", "cantools", "scipy.signal")


def _imported(code: str, watch: tuple[str, ...] = HEAVY) -> list[str]:
    code += f"\nimport sys, json\nprint(json.dumps([m for m in {watch!r} if m in sys.modules]))"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.splitlines()[-1])


def test_the_daemon_loading_every_plugin_imports_no_driver_library():
    # the daemon loads every installed plugin at start; the MTConnect and CAN drivers' libraries
    # come with the first machine of their type
    assert _imported("from lathed.plugins import load_all\nassert not [p for p in load_all([]).plugins "
                     "if p.error]") == []


def test_the_simulator_imports_no_mtconnect_agent_without_its_port():
    # pymodbus's server package still brings aiohttp (its HTTP simulator's); the agent's own is
    # not imported without --mtconnect-port
    assert _imported("import lathed.sim.__main__", HEAVY + ("lathed.sim.mtconnect_agent",)) == ["aiohttp"]


def test_lathectl_imports_no_pluggy_or_numpy_for_a_status():
    code = ("import sys\nsys.argv = ['lathectl', '--socket', '/nonexistent/lathed.sock', 'status']\n"
            "from lathed.cli.main import main\ntry:\n    main()\nexcept SystemExit:\n    pass")
    assert _imported(code, HEAVY + ("pluggy", "numpy")) == []
