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


def test_the_simulator_imports_no_aiohttp_without_its_mtconnect_agent():
    assert _imported("import lathed.sim.__main__") == []


def test_the_simulator_serves_modbus_with_pymodbus_own_server_classes_either_way():
    code = ("{first}\nfrom lathed.sim import modbus_peer as m\nimport pymodbus.server.server as s\n"
            "assert (m.ModbusTcpServer, m.ModbusSerialServer) == (s.ModbusTcpServer, s.ModbusSerialServer)\n"
            "from pymodbus.server import ModbusSimulatorServer\n")
    assert _imported(code.format(first="")) == []
    assert _imported(code.format(first="import aiohttp")) == ["aiohttp"]
    # the MTConnect agent's aiohttp after pymodbus's servers: a whole aiohttp, not the blocked one
    assert _imported(code.format(first="") + "from lathed.sim.mtconnect_agent import MTConnectAgent\n"
                     "import aiohttp.web\n") == ["aiohttp"]


def test_lathectl_imports_no_pluggy_or_numpy_for_a_status():
    code = ("import sys\nsys.argv = ['lathectl', '--socket', '/nonexistent/lathed.sock', 'status']\n"
            "from lathed.cli.main import main\ntry:\n    main()\nexcept SystemExit:\n    pass")
    assert _imported(code, HEAVY + ("pluggy", "numpy")) == []


def test_with_another_thread_running_pymodbus_is_imported_as_it_comes():
    # no module blocked where another thread could be importing it meanwhile (a pytest worker)
    code = ("import threading\nstop = threading.Event()\nt = threading.Thread(target=stop.wait)\nt.start()\n"
            "from lathed.sim import modbus_peer\nstop.set()\nt.join()")
    assert _imported(code) == ["aiohttp"]
