"""lathed-sim: the simulated lathe (and its line) as a separate process with real peers.

It serves the machine over the same protocols a real one uses: the CNC on
Modbus TCP, the Arduino's DS18B20 line on a pseudo-terminal, the
accelerometer DAQ as a framed TCP stream. Optionally its neighbours: a mill
on Modbus TCP (``--mill-port``), a grinder on Modbus RTU over a null-modem
pseudo-terminal pair (``--grinder-link``), a robot arm on CAN through a
serial-line CAN adapter (slcan) on a pseudo-terminal (``--robot-link``).
The lathe's control can be an OPC UA server as well (``--opcua-port``, security on, its
certificates in ``--opcua-pki``: lathed.sim.opcua_peer, lathed.sim.pki).
A JSON-lines control socket lets an operator or a test change the cut,
take a peer down or raise an alarm:

    {"cmd": "status"}      (with "parts": the last parts' cut start, the instant
                            chatter became visible and the speed writes received,
                            in the wall time of the vibration stream's t0 stamps)
    {"cmd": "set", "args": {"depth_mm": 3.0}}        (null: back to the program)
    {"cmd": "set", "args": {"rpm": 425}}             (every part's programmed speed; null: the program's)
    {"cmd": "outage", "args": {"peer": "modbus", "seconds": 10}}
        peer: modbus | vibration | serial | opcua (the lathe's), mill, grinder
        (server gone, RS-485 line cut), robot (the arm powered off: CAN silent)
    {"cmd": "alarm", "args": {"machine": "mill", "code": 42}}   (0 clears)

Prints one line ``READY {...endpoints...}`` on stdout when all peers listen.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import signal
import sys
import time
from collections import deque
from pathlib import Path

from lathed.analysis.process_damping import FlankWear
from lathed.extras import missing
from lathed.sim.can_peer import CanPeer
from lathed.analysis.modal import parse_mode
from lathed.sim.lathe import LATHE_KF, LATHE_MODES, LOAD_S, RETRACT_S, SimLathe
from lathed.sim.program import FORM as CUT_FORM, MAX_DEPTH_MM, MAX_OUTAGE_S, parse_cut
from lathed.sim.line import GRINDER_PROGRAM, MILL_PROGRAM, SimCycleMachine, SimRobotArm
from lathed.sim.modbus_peer import ModbusPeer
from lathed.sim.registers import (CELL_IDENTITY, CELL_MAP, HEARTBEAT_TIMEOUT_S, LATHE_IDENTITY, LATHE_MAP,
                                  N_CELL_REGISTERS, N_REGISTERS, SERIALS)
from lathed.sim.serial_peer import NullModem, SerialPeer
from lathed.sim.vibration_peer import VibrationPeer

BLOCK = 1024              # samples per vibration frame: 20 ms at 51.2 kS/s
READING_PERIOD_S = 6.0    # the Arduino reads its DS18B20s every 6 s (sim time)
LINE_PERIOD_S = 0.1       # the neighbours' physics step, and the robot's CAN frame period (10 Hz)


class Simulator:
    def __init__(self, args: argparse.Namespace):
        self.args = args
        self.lathe = SimLathe(rate_hz=args.rate, time_scale=args.time_scale, seed=args.seed,
                              depth_override_mm=args.depth_mm, flank=args.flank, **args.lathe)
        self.modbus = ModbusPeer(args.host, args.modbus_port, LATHE_MAP, N_REGISTERS, self._lathe_write,
                                 identity=_identity(LATHE_IDENTITY, args.lathe_serial))
        self.vibration = VibrationPeer(args.host, args.vibration_port, args.rate)
        self.agent = None
        if args.mtconnect_port:  # aiohttp (half a CPU-second of import) only where the agent is served
            from lathed.sim.mtconnect_agent import MTConnectAgent
            self.agent = MTConnectAgent(args.host, args.mtconnect_port, serial_number=args.lathe_serial)
        self.opcua = None
        if args.opcua_port:      # asyncua (the opcua extra) only where the control serves OPC UA
            from lathed.sim.opcua_peer import OpcUaPeer
            from lathed.sim.pki import ensure_pki
            self.opcua = OpcUaPeer(args.host, args.opcua_port, ensure_pki(Path(args.opcua_pki)), self._lathe_write,
                                   serial_number=args.lathe_serial)
        self.serial = SerialPeer(Path(args.serial_link))
        self.mill = self.grinder = self.robot = None
        self.mill_peer = self.grinder_peer = self.robot_peer = None
        if args.mill_port:
            self.mill = SimCycleMachine(MILL_PROGRAM)
            self.mill_peer = ModbusPeer(args.host, args.mill_port, CELL_MAP, N_CELL_REGISTERS, self.mill.write,
                                        identity=_identity(CELL_IDENTITY, SERIALS["mill"]))
        if args.grinder_link:
            self.grinder = SimCycleMachine(GRINDER_PROGRAM)
            self.grinder_peer = ModbusPeer(args.host, 0, CELL_MAP, N_CELL_REGISTERS, self.grinder.write,
                                           null_modem=NullModem(Path(args.grinder_link)),
                                           identity=_identity(CELL_IDENTITY, SERIALS["grinder"]))
        if args.robot_link:
            self.robot = SimRobotArm()
            self.robot_peer = CanPeer(Path(args.robot_link))
        self.robot_silent = False
        self.produced = 0
        self.overruns = 0
        self._beat_wall: float | None = None    # wall time the heartbeat count last changed
        self._beat: float | None = None
        self.watchdog_resets: list[dict] = []   # the PMC took a held override back
        self.booted = time.monotonic()
        # (sim time, wall time) of recent vibration blocks' first samples: sim
        # instants become comparable with the stream's t0 stamps, overruns too
        self._clock: deque[tuple[float, float]] = deque(maxlen=512)
        self._outages: set[asyncio.Task] = set()
        self._stop = asyncio.Event()
        self.control: asyncio.Server | None = None

    async def _start_peers(self) -> str:
        """Every peer listening; the Arduino's tty name."""
        tty = self.serial.open()
        await self.modbus.start()
        await self.vibration.start()
        if self.agent is not None:
            self.agent.update(self.lathe.registers())
            await self.agent.start()
        if self.opcua is not None:
            # before READY and the physics: asyncua builds its address space for seconds (tens on a
            # loaded host), holding the interpreter; the machine's other servers would not answer
            await self._start_opcua()
        for peer in (self.mill_peer, self.grinder_peer):
            if peer is not None:
                await peer.start()
        if self.robot_peer is not None:
            self.robot_peer.open()
        if self.args.control:
            Path(self.args.control).parent.mkdir(parents=True, exist_ok=True)
            if os.path.exists(self.args.control):
                os.unlink(self.args.control)
            self.control = await asyncio.start_unix_server(self._control_client, path=self.args.control)
        self.modbus.block.update(self.lathe.registers())
        self._update_line(0.0)
        return tty

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, self._stop.set)
        try:
            tty = await self._start_peers()
        except Exception as e:      # a port taken, a link not made: the daemon says why and stops
            text = " ".join(str(e).split()) or type(e).__name__
            print(f"FAILED {text}", flush=True)
            raise SystemExit(1) from None
        ready = {"modbus": [self.args.host, self.args.modbus_port],
                 "vibration": [self.args.host, self.args.vibration_port],
                 "serial": self.args.serial_link, "tty": tty, "control": self.args.control}
        if self.agent is not None:
            ready["mtconnect"] = [self.args.host, self.args.mtconnect_port]
        if self.opcua is not None:
            ready["opcua"] = self.opcua.url
            ready["opcua_pki"] = str(self.opcua.pki.root)
        if self.mill_peer:
            ready["mill"] = [self.args.host, self.args.mill_port]
        if self.grinder_peer:
            ready["grinder"] = self.args.grinder_link
        if self.robot_peer:
            ready["robot"] = self.args.robot_link
        try:
            print("READY " + json.dumps(ready), flush=True)
        except BrokenPipeError:
            # the daemon that started us stopped before reading this line: nothing to
            # simulate for, and no traceback in its log (stdout to /dev/null, so the
            # interpreter's own flush at exit does not fail again)
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            self._stop.set()
        parent = os.getppid()
        tasks = [asyncio.create_task(self._vibration_loop()), asyncio.create_task(self._serial_loop())]
        if self.mill or self.grinder or self.robot:
            tasks.append(asyncio.create_task(self._line_loop()))
        while not self._stop.is_set():
            try:
                await asyncio.wait_for(self._stop.wait(), 1.0)
            except asyncio.TimeoutError:
                pass
            if self.args.exit_with_parent and os.getppid() != parent:
                break   # the daemon that spawned us is gone
        for t in tasks + list(self._outages):
            t.cancel()
        await self.modbus.stop()
        await self.vibration.stop()
        if self.agent is not None:
            await self.agent.stop()
        if self.opcua is not None:
            await self.opcua.stop()
        self.serial.close()
        for peer in (self.mill_peer, self.grinder_peer):
            if peer is not None:
                await peer.stop()
        if self.robot_peer is not None:
            self.robot_peer.close()
        if self.control is not None:
            self.control.close()

    async def _vibration_loop(self) -> None:
        start = time.time()
        rate = self.args.rate
        while True:
            due = int((time.time() - start) * rate)
            if due - self.produced > rate:        # more than 1 s behind: skip, and count it
                self.overruns += 1
                self.produced = due - BLOCK
            while self.produced + BLOCK <= due:
                t0 = start + self.produced / rate
                self._clock.append((self.lathe.n_samples / self.lathe.rate_hz, t0))
                data = self.lathe.step(BLOCK)
                self._stamp(self.lathe.record)
                # the speed the block was cut at (read before the step, it lagged a ramp step)
                self.vibration.send(t0, self.lathe.block_rpm, data)
                self.produced += BLOCK
            self._pmc_watchdog()
            if self.modbus.up or self.agent is not None or self.opcua is not None:
                regs = self.lathe.registers()
                if self.modbus.up:
                    self.modbus.block.update(regs)
                if self.agent is not None and self.agent.up:
                    self.agent.update(regs)
                if self.opcua is not None and self.opcua.up:
                    await self.opcua.update(regs, self.lathe.phase)
            await asyncio.sleep(max(0.0, start + (self.produced + BLOCK) / rate - time.time()))

    async def _start_opcua(self) -> None:
        try:
            await self.opcua.start()
        except OSError as e:   # the port taken: no READY, the daemon says why
            raise SystemExit(f"lathed-sim: cannot serve OPC UA at {self.opcua.url}: {e.strerror or e}") from None
        await self.opcua.update(self.lathe.registers(), self.lathe.phase)

    def _wall(self, sim_t: float) -> float | None:
        for s0, w0 in reversed(self._clock):
            if s0 <= sim_t:
                return w0 + (sim_t - s0)
        return None

    def _stamp(self, rec) -> None:
        # the cut starts on a block boundary and chatter is known visible at most
        # a few revolutions late, so both are still in the clock's window
        if rec.cut_start_s is not None and rec.cut_start_wall is None:
            rec.cut_start_wall = self._wall(rec.cut_start_s)
        if rec.visible_at_s is not None and rec.visible_wall is None:
            rec.visible_wall = self._wall(rec.visible_at_s)

    def _pmc_watchdog(self) -> None:
        """The PMC's side of the heartbeat (wall time, as a ladder's timer): an override held
        while the count stopped is the client's, and the client is gone. Not in a thread: its
        passes run at one speed, the reset waits for its end (the threading bit off)."""
        now = time.time()
        if (self._beat_wall is not None and now - self._beat_wall > HEARTBEAT_TIMEOUT_S
                and self.lathe.override_pct != 100.0 and not self.lathe.part.thread):
            self.watchdog_resets.append({"wall_t": now, "override_pct": self.lathe.override_pct,
                                         "silent_s": round(now - self._beat_wall, 3)})
            self.lathe.override_pct = 100.0

    def _lathe_write(self, name: str, value: float) -> None:
        # the instant the machine got the command, not when the daemon sent it
        t = time.time()
        if name == "heartbeat":
            if value != self._beat:
                self._beat, self._beat_wall = value, t
            return
        self.lathe.write(name, value)
        if name in ("spindle_rpm_cmd", "spindle_override_pct"):
            self.lathe.record.speed_writes[-1]["wall_t"] = t

    async def _serial_loop(self) -> None:
        period = READING_PERIOD_S / self.args.time_scale
        while True:
            r = self.lathe.thermal.readings()
            uptime_ms = int((time.monotonic() - self.booted) * 1000)
            self.serial.send(uptime_ms, {k: r[k] for k in ("front_bearing", "rear_bearing", "motor", "room")})
            await asyncio.sleep(period)

    def _update_line(self, dt: float) -> None:
        for m, peer in ((self.mill, self.mill_peer), (self.grinder, self.grinder_peer)):
            if m is not None:
                if dt:
                    m.step(dt)
                if peer.up:
                    peer.block.update(m.registers())
        if self.robot is not None:
            if dt:
                self.robot.step(dt)
            if not self.robot_silent:
                self.robot_peer.send_arm(self.robot)

    async def _line_loop(self) -> None:
        last = time.monotonic()
        while True:
            await asyncio.sleep(LINE_PERIOD_S)
            now = time.monotonic()
            self._update_line(now - last)
            last = now

    # -- control ----------------------------------------------------------------
    async def _control_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while line := await reader.readline():
                try:
                    req = json.loads(line)
                    result = await self._command(req["cmd"], req.get("args") or {})
                    reply = {"ok": True, "result": result}
                except Exception as e:   # a bad control request never stops the simulator
                    reply = {"ok": False, "error": f"{type(e).__name__}: {e}"}
                writer.write(json.dumps(reply).encode() + b"\n")
                await writer.drain()
        except ConnectionError:
            pass
        finally:
            writer.close()

    async def _command(self, cmd: str, args: dict) -> object:
        if cmd == "status":
            return {"t": self.lathe.t, "phase": self.lathe.phase, "part": self.lathe.part_index,
                    "registers": self.lathe.registers(), "temperatures": self.lathe.thermal.readings(),
                    "displacement_um": self.lathe.thermal.displacement_um, "overruns": self.overruns,
                    "watchdog_resets": self.watchdog_resets[-16:],
                    "visible_at": self.lathe.record.visible_wall,
                    "parts": [r.as_dict() for r in list(self.lathe.parts)[-max(1, int(args.get("parts", 16))):]],
                    "peers": {"modbus": self.modbus.up, "vibration": self.vibration.server is not None,
                              **({"opcua": self.opcua.up} if self.opcua else {}),
                              "serial": self.serial.master is not None,
                              **({"mill": self.mill_peer.up} if self.mill_peer else {}),
                              **({"grinder": self.grinder_peer.up} if self.grinder_peer else {}),
                              **({"robot": not self.robot_silent} if self.robot_peer else {})},
                    "line": {n: {"part_count": m.part_count, "alarm_code": m.alarm_code}
                             for n, m in (("mill", self.mill), ("grinder", self.grinder)) if m}
                            | ({"robot": {"cycle_count": self.robot.cycle_count,
                                          "alarm_code": self.robot.alarm_code}} if self.robot else {})}
        if cmd == "set":
            if "depth_mm" in args:
                d = args["depth_mm"]
                if d is not None and not (isinstance(d, (int, float)) and 0 <= d <= MAX_DEPTH_MM):
                    raise ValueError(f"depth_mm must be null or in [0, {MAX_DEPTH_MM:g}]")
                self.lathe.depth_override_mm = d
            if "rpm" in args:
                r = args["rpm"]
                if r is not None and (isinstance(r, bool) or not isinstance(r, (int, float))
                                      or not 60 <= r <= self.lathe.max_rpm):
                    raise ValueError(f"rpm must be null or in [60, {self.lathe.max_rpm:g}]")
                self.lathe.rpm_program_override = None if r is None else float(r)
                return {"depth_mm": self.lathe.depth_mm, "rpm": self.lathe.rpm_program_override}
            return {"depth_mm": self.lathe.depth_mm}
        if cmd == "outage":
            peer, seconds = args.get("peer"), args.get("seconds", 10)
            # float() took "-5", nan and 1e12: a peer down for ever, or back before it went
            if isinstance(seconds, bool) or not isinstance(seconds, (int, float)) \
                    or not 0 < seconds <= MAX_OUTAGE_S:
                raise ValueError(f"seconds must be a number in (0, {MAX_OUTAGE_S:g}], got {seconds!r}")
            seconds = float(seconds)
            fns = {"modbus": self.modbus.outage, "vibration": self._vibration_outage,
                   "serial": self._serial_outage}
            if self.opcua:
                fns["opcua"] = self.opcua.outage
            if self.mill_peer:
                fns["mill"] = self.mill_peer.outage
            if self.grinder_peer:
                fns["grinder"] = self.grinder_peer.outage
            if self.robot_peer:
                fns["robot"] = self._robot_outage
            fn = fns.get(peer)
            if fn is None:
                raise ValueError(f"peer must be one of {', '.join(fns)}")
            task = asyncio.create_task(fn(seconds))
            self._outages.add(task)
            task.add_done_callback(self._outages.discard)
            return {"peer": peer, "seconds": seconds}
        if cmd == "alarm":
            m = {"mill": self.mill, "grinder": self.grinder, "robot": self.robot}.get(args.get("machine"))
            code = args.get("code", 0)
            if m is None:
                raise ValueError("machine must be a running neighbour: mill, grinder or robot")
            if not (isinstance(code, int) and 0 <= code <= 65535):
                raise ValueError("code must be an integer in [0, 65535] (0 clears)")
            m.alarm_code = code
            return {"machine": args["machine"], "code": code}
        raise ValueError(f"unknown command {cmd!r}")

    async def _vibration_outage(self, seconds: float) -> None:
        await self.vibration.stop()
        await asyncio.sleep(seconds)
        await self.vibration.start()

    async def _robot_outage(self, seconds: float) -> None:
        self.robot_silent = True         # the arm powered off; the adapter stays plugged in
        await asyncio.sleep(seconds)
        self.robot_silent = False

    async def _serial_outage(self, seconds: float) -> None:
        self.serial.close()              # the USB cable pulled: the tty vanishes
        self.serial.link.unlink(missing_ok=True)
        await asyncio.sleep(seconds)
        self.serial.open()


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="lathed-sim", description="Simulated lathe with real protocol peers.")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--modbus-port", type=int, default=15020)
    p.add_argument("--vibration-port", type=int, default=15021)
    p.add_argument("--serial-link", default="/tmp/lathed-sim/ttyARDUINO",
                   help="path of the symlink to the simulated Arduino's tty")
    p.add_argument("--control", help="path of the simulator's control socket")
    p.add_argument("--rate", type=int, default=51200, help="accelerometer sample rate, Hz")
    p.add_argument("--time-scale", type=float, default=1.0, help="speed-up of the thermal clock")
    p.add_argument("--depth-mm", type=float, default=None, help="override every part's depth of cut")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--flank-wear-mm", type=float, default=0.0,
                   help="the tool's flank wear land VB, mm: process damping (0: a sharp tool, none)")
    p.add_argument("--flank-clearance-deg", type=float, default=FlankWear.clearance_deg,
                   help="the wear land's clearance to the cut surface, deg")
    p.add_argument("--flank-indentation", type=float, default=FlankWear.k_sp_n_per_m3,
                   help="indentation coefficient under the land, N/m^3")
    p.add_argument("--exit-with-parent", action="store_true")
    p.add_argument("--lathe-serial", default=SERIALS["lathe"],
                   help="the serial number the lathe's control serves (its identity registers)")
    p.add_argument("--mill-port", type=int, default=0, help="serve the mill on this Modbus TCP port (0: no mill)")
    p.add_argument("--mtconnect-port", type=int, default=0,
                   help="serve the lathe as an MTConnect agent on this HTTP port too (0: none)")
    p.add_argument("--opcua-port", type=int, default=0,
                   help="serve the lathe's control as an OPC UA server on this port too (0: none)")
    p.add_argument("--opcua-pki", default="/tmp/lathed-sim/pki",
                   help="the simulated plant's OPC UA certificates and password: made there if missing")
    p.add_argument("--grinder-link", default="",
                   help="serve the grinder on Modbus RTU; path of the symlink to its tty (empty: no grinder)")
    p.add_argument("--robot-link", default="",
                   help="serve the robot arm on slcan; path of the symlink to its tty (empty: no robot)")
    p.add_argument("--mode", action="append", default=[], metavar="FN,ZETA,K[,THETA_DEG]",
                   help="the lathe's true structural modes (repeat; default: the default configuration's model)")
    p.add_argument("--kf", type=float, default=LATHE_KF, help="the true cutting coefficient, N/m^2")
    p.add_argument("--cut", action="append", default=[], metavar=CUT_FORM,
                   help="the cut program, one part per --cut, repeated in turn; css=M_MIN: a facing pass at "
                        "that constant surface speed (G96), RPM its clamp; tool=2: cut with the turret's "
                        "boring bar; dwell=S: the feed stops S seconds halfway along the pass (G04) "
                        "(default: the paper's six parts and a G96 face)")
    p.add_argument("--load-s", type=float, default=LOAD_S, help="seconds to load a part")
    p.add_argument("--retract-s", type=float, default=RETRACT_S, help="seconds to retract and unload")
    args = p.parse_args(argv)
    if args.opcua_port and (why := missing("asyncua")):
        p.error(f"--opcua-port: the simulated control's OPC UA server cannot run: {why}")
    if not (math.isfinite(args.time_scale) and args.time_scale > 0):
        p.error("--time-scale must be > 0")
    try:
        lathe = {"modes": tuple(parse_mode(m) for m in args.mode) or LATHE_MODES, "kf": args.kf,
                 "load_s": args.load_s, "retract_s": args.retract_s}
        if args.cut:
            lathe["program"] = tuple(parse_cut(c) for c in args.cut)
    except ValueError as e:
        p.error(str(e))
    if not (math.isfinite(args.kf) and args.kf > 0):
        p.error("--kf must be > 0 N/m^2")
    if not (0 <= args.load_s <= 60 and 0 <= args.retract_s <= 60):
        p.error("--load-s and --retract-s must be within 0..60 s")
    args.lathe = lathe
    args.flank = None
    if args.flank_wear_mm:
        try:
            args.flank = FlankWear(args.flank_wear_mm, args.flank_clearance_deg, args.flank_indentation)
        except ValueError as e:
            p.error(str(e))
    return args


def _identity(where: dict[str, tuple[int, int]], serial: str) -> dict:
    return {"serial_number": (where["serial_number"], serial)}


def main(argv: list[str] | None = None) -> int:
    asyncio.run(Simulator(parse_args(argv)).run())
    return 0


if __name__ == "__main__":
    sys.exit(main())
