"""Starting the simulated lathe from the daemon's [simulator] table.

The simulator runs as its own process, so the daemon reaches it only
through its drivers and real protocols, as it would a machine.
"""
from __future__ import annotations

import asyncio
import json
import sys
from pathlib import Path

import structlog

from lathed.config import Section
from lathed.extras import missing
from lathed.sim.program import MAX_DEPTH_MM
from lathed.sim.serial_peer import link_dir_problem

log = structlog.get_logger("lathed.sim")


class SimulatorSettings:
    def __init__(self, sec: Section, runtime_dir: Path):
        self.spawn = sec.getbool("spawn", True)
        self.host = sec.getstr("host", "127.0.0.1")
        self.modbus_port = sec.getint("modbus_port", 15020, minval=1, maxval=65535)
        self.vibration_port = sec.getint("vibration_port", 15021, minval=1, maxval=65535)
        # the tty links live in a directory of ours (see link_dir_problem), by default in the runtime dir
        self.serial_link = sec.getstr("serial_link", str(runtime_dir / "sim" / "ttyARDUINO"))
        self.control = sec.getstr("control", str(runtime_dir / "sim.sock"))
        self.time_scale = sec.getfloat("time_scale", 1.0, minval=0.01, maxval=10_000.0)
        # the simulated DAQ's sample rate (real ones offer 12.8 to 51.2 kS/s); the daemon takes it
        # from each frame
        self.rate_hz = sec.getint("rate_hz", 51200, minval=2000, maxval=204800)
        self.depth_mm = sec.getfloat("depth_mm", -1.0, minval=0.0, maxval=MAX_DEPTH_MM)
        self.seed = sec.getint("seed", 0, minval=0)
        # the tool's worn flank ploughing the wavy surface (process damping: mild
        # chatter just above the limit, lathed.analysis.process_damping); 0: a sharp tool
        self.flank_wear_mm = sec.getfloat("flank_wear_mm", 0.0, minval=0.0, maxval=1.0)
        if 0.0 < self.flank_wear_mm < 0.01:
            raise sec.error("flank_wear_mm", f"{self.flank_wear_mm} is out of range; allowed: 0 (a sharp "
                                             "tool) or a wear land in [0.01, 1] mm")
        self.flank_clearance_deg = sec.getfloat("flank_clearance_deg", 0.2, minval=0.0, maxval=10.0)
        self.flank_indentation = sec.getfloat("flank_indentation_n_m3", 4.0e13, minval=1e11, maxval=1e16)
        # the lathe's neighbours; each off unless configured
        self.mill_port = sec.getint("mill_port", 0, minval=0, maxval=65535)
        # the lathe as an MTConnect agent too (read-only, beside its Modbus server; 0: none)
        self.mtconnect_port = sec.getint("mtconnect_port", 0, minval=0, maxval=65535)
        # the lathe's control as an OPC UA server too (security on; 0: none), its certificates and
        # password made by the simulator in opcua_pki (a directory of the runtime dir's, like its ttys)
        self.opcua_port = sec.getint("opcua_port", 0, minval=0, maxval=65535)
        self.opcua_pki = sec.getstr("opcua_pki", str(runtime_dir / "sim" / "pki"))
        if self.opcua_port and (why := missing("asyncua")):
            raise sec.error("opcua_port", f"the simulated control's OPC UA server cannot run: {why}")
        # asyncua builds its server's address space before the simulator is READY: seconds, tens on a
        # loaded host
        self.ready_timeout = 60.0 if self.opcua_port else 20.0
        self.grinder_link = sec.getstr("grinder_link", "")
        self.robot_link = sec.getstr("robot_link", "")
        # the lathe's true dynamics and program, when they are to differ from the built-in ones
        # (the daemon's own model stays what its analyzers are configured with)
        self.modes = sec.getlist("modes", [])
        self.kf = sec.getfloat("kf", 0.0, minval=0.0)
        self.program = sec.getlist("program", [])
        self.load_s = sec.getfloat("load_s", -1.0, minval=0.0, maxval=60.0)
        self.retract_s = sec.getfloat("retract_s", -1.0, minval=0.0, maxval=60.0)
        from lathed.analysis.modal import parse_mode
        from lathed.sim.program import parse_cut
        for key, parse in (("modes", parse_mode), ("program", parse_cut)):
            for text in getattr(self, key):
                try:
                    parse(str(text))
                except ValueError as e:
                    raise sec.error(key, str(e)) from None
        sec.check_unused()
        for key in ("serial_link", "grinder_link", "robot_link", "opcua_pki"):
            link = getattr(self, key)
            problem = link and link_dir_problem(Path(link).parent, create=False)
            if problem:
                what = "certificates" if key == "opcua_pki" else "tty link"
                raise sec.error(key, f"unsafe place for the simulator's {what}: {problem}")

    def link_problems(self) -> list[str]:
        """Make the links' directories (0700) and check them again, now."""
        return [p for link in (self.serial_link, self.grinder_link, self.robot_link,
                               self.opcua_pki if self.opcua_port else "")
                if link and (p := link_dir_problem(Path(link).parent, create=True))]

    def argv(self) -> list[str]:
        a = [sys.executable, "-m", "lathed.sim", "--host", self.host, "--modbus-port", str(self.modbus_port),
             "--vibration-port", str(self.vibration_port), "--serial-link", self.serial_link,
             "--control", self.control, "--time-scale", str(self.time_scale), "--rate", str(self.rate_hz), "--seed", str(self.seed),
             "--exit-with-parent"]
        if self.mill_port:
            a += ["--mill-port", str(self.mill_port)]
        if self.mtconnect_port:
            a += ["--mtconnect-port", str(self.mtconnect_port)]
        if self.opcua_port:
            a += ["--opcua-port", str(self.opcua_port), "--opcua-pki", self.opcua_pki]
        if self.grinder_link:
            a += ["--grinder-link", self.grinder_link]
        if self.robot_link:
            a += ["--robot-link", self.robot_link]
        if self.depth_mm >= 0:
            a += ["--depth-mm", str(self.depth_mm)]
        for m in self.modes:
            a += ["--mode", str(m)]
        for c in self.program:
            a += ["--cut", str(c)]
        if self.kf > 0:
            a += ["--kf", str(self.kf)]
        if self.load_s >= 0:
            a += ["--load-s", str(self.load_s)]
        if self.retract_s >= 0:
            a += ["--retract-s", str(self.retract_s)]
        if self.flank_wear_mm:
            a += ["--flank-wear-mm", str(self.flank_wear_mm), "--flank-clearance-deg",
                  str(self.flank_clearance_deg), "--flank-indentation", str(self.flank_indentation)]
        return a


class SimulatorFailed(Exception):
    """The configured simulator did not start; the message says why, in one line."""

    def __init__(self, why: str, process: asyncio.subprocess.Process | None = None):
        super().__init__(why)
        self.process = process


async def spawn(s: SimulatorSettings, timeout: float | None = None) -> asyncio.subprocess.Process | None:
    """The simulator started and listening; None when the config says it runs elsewhere
    (``spawn = false``). Raises SimulatorFailed with its reason: the daemon must not go on to
    command whatever else answers at its addresses."""
    if not s.spawn:
        return None
    problems = s.link_problems()
    if problems:
        raise SimulatorFailed(f"not started: unsafe place for its tty links: {'; '.join(problems)}")
    # its own session: a Ctrl-C on the terminal reaches lathed only, which stops its
    # drivers before the simulator (--exit-with-parent covers lathed dying)
    proc = await asyncio.create_subprocess_exec(*s.argv(), stdout=asyncio.subprocess.PIPE, start_new_session=True)
    try:
        line = await asyncio.wait_for(proc.stdout.readline(), timeout or s.ready_timeout)
    except asyncio.TimeoutError:
        line = b""
    if not line.startswith(b"READY "):
        text = line.decode(errors="replace").strip()
        if text.startswith("FAILED "):
            why = text[7:]
        elif text:
            why = f"said {text[:200]!r} instead of READY"
        else:
            try:
                await asyncio.wait_for(proc.wait(), 1.0)
            except asyncio.TimeoutError:
                pass
            why = (f"exited with code {proc.returncode} before it was ready" if proc.returncode is not None
                   else f"not ready within {timeout or s.ready_timeout:g} s")
        await stop(proc)
        raise SimulatorFailed(f"the simulator did not start: {why}", proc)
    log.info("simulator_ready", pid=proc.pid, **json.loads(line[6:]))
    asyncio.create_task(_drain(proc))
    return proc


async def _drain(proc: asyncio.subprocess.Process) -> None:
    while await proc.stdout.readline():
        pass


async def stop(proc: asyncio.subprocess.Process) -> None:
    if proc.returncode is not None:
        return
    proc.terminate()
    try:
        await asyncio.wait_for(proc.wait(), 5.0)
    except asyncio.TimeoutError:
        proc.kill()
        await proc.wait()
