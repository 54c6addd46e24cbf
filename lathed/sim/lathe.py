"""Physics of the simulated lathe: spindle, part program, axes, heat, cut.

A simulator of physics, not of a particular controller: the spindle follows
its commanded speed within an acceleration limit; the program turns parts
one after another (load, cut along the part, retract); the cut's vibration
comes from the regenerative chip-thickness model (lathed.analysis.regen), so
a depth above the stability limit really chatters; the spindle warms with
speed (lathed.sim.thermal). No asyncio here: the peers in this package serve
this state over Modbus, serial and TCP.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lathed.analysis.modal import Mode
from lathed.analysis.regen import RegenerativeTurning
from lathed.sim.thermal import SpindleThermal

# The simulated lathe's structure: a compliant workpiece mode at 190 Hz
# (a 30 mm bar on an 80 mm overhang) and a stiffer tool-post mode. Its lobes
# are distinct at the paper's speeds: the limiting depth is ~2.4 mm at 1500,
# 2000 and 2500 r/min (the paper's 3 mm cut chatters, 1 mm does not) and
# above 5 mm near 2300 r/min, so a spindle speed choice can save the cut.
LATHE_MODES = (Mode(190.0, 0.03, 7.5e7, 0.0), Mode(620.0, 0.035, 4.0e8, 30.0))
LATHE_KF = 2.0e9    # N/m² along the chip-thickness direction (medium carbon steel)
LATHE_KT = 1.5e9    # N/m² tangential: sets the spindle torque a cut needs


@dataclass(frozen=True)
class Cut:
    """One part of the program: a turning pass along the bar."""
    rpm: float
    depth_mm: float
    feed_mm_rev: float = 0.3
    length_mm: float = 40.0
    diameter_mm: float = 30.0


# The paper's three speeds; every third part is cut 3 mm deep (the paper's
# depth, above the stability limit of DEFAULT_MODES), the others 1 mm.
DEFAULT_PROGRAM = (
    Cut(1500, 1.0), Cut(2000, 1.0), Cut(2500, 3.0),
    Cut(2000, 1.0), Cut(1500, 3.0), Cut(2500, 1.0),
)

LOAD_S = 1.5       # bar loaded, spindle brought to the part's speed
RETRACT_S = 1.0    # tool retracted, part measured (probe cycle), unloaded


class SimLathe:
    def __init__(self, program: tuple[Cut, ...] = DEFAULT_PROGRAM, rate_hz: int = 51200,
                 time_scale: float = 1.0, accel_rpm_s: float = 3000.0, max_rpm: float = 6000.0,
                 depth_override_mm: float | None = None, seed: int = 0, room_c: float = 20.0):
        self.program = program
        self.rate_hz = rate_hz
        self.time_scale = time_scale          # thermal clock speed-up
        self.accel_rpm_s = accel_rpm_s
        self.max_rpm = max_rpm
        self.depth_override_mm = depth_override_mm
        self.cutter = RegenerativeTurning(LATHE_MODES, LATHE_KF, rate_hz=float(rate_hz), seed=seed)
        self.thermal = SpindleThermal(room_c=room_c, seed=seed)
        self._rng = np.random.default_rng(seed + 1)
        self.t = 0.0
        self.part_index = 0
        self.phase = "load"
        self.phase_t = 0.0
        self.y_mm = 0.0
        self.rpm = 0.0
        self.rpm_override: float | None = None   # written over Modbus; holds for the current part
        self.offset_x_um = 0.0
        self.part_count = 0
        self.cycle_start = 0.0
        self.cycle_time_s = 0.0
        self.probe_displacement_um = 0.0
        self.probe_seq = 0
        self.program_number = 1000

    # -- program ------------------------------------------------------------
    @property
    def part(self) -> Cut:
        return self.program[self.part_index % len(self.program)]

    @property
    def depth_mm(self) -> float:
        return self.part.depth_mm if self.depth_override_mm is None else self.depth_override_mm

    @property
    def rpm_cmd(self) -> float:
        return self.part.rpm if self.rpm_override is None else self.rpm_override

    def write(self, name: str, value: float) -> None:
        """A register written by a client (the daemon)."""
        if name == "spindle_rpm_cmd":
            if not (math.isfinite(value) and 0 <= value <= self.max_rpm):
                raise ValueError(f"spindle speed {value} r/min beyond the drive's 0..{self.max_rpm:g}")
            self.rpm_override = value
        elif name == "offset_x_um":
            if not math.isfinite(value):
                raise ValueError("offset is not a number")
            self.offset_x_um = value
        else:
            raise KeyError(name)

    def _advance_program(self, dt: float) -> None:
        self.phase_t += dt
        if self.phase == "load" and self.phase_t >= LOAD_S and abs(self.rpm - self.rpm_cmd) < 1.0:
            self.phase, self.phase_t, self.y_mm = "cut", 0.0, 0.0
        elif self.phase == "cut":
            self.y_mm += self.part.feed_mm_rev * self.rpm / 60.0 * dt
            if self.y_mm >= self.part.length_mm:
                self.phase, self.phase_t = "retract", 0.0
                # probe cycle: the spindle's thermal growth as a touch probe sees it
                self.probe_displacement_um = self.thermal.displacement_um + self._rng.normal(0, 0.3)
                self.probe_seq = (self.probe_seq + 1) % 65536
        elif self.phase == "retract" and self.phase_t >= RETRACT_S:
            self.part_count += 1
            self.cycle_time_s = self.t - self.cycle_start
            self.cycle_start = self.t
            self.part_index += 1
            self.rpm_override = None
            self.phase, self.phase_t, self.y_mm = "load", 0.0, 0.0

    # -- physics --------------------------------------------------------------
    def step(self, n: int) -> np.ndarray:
        """Advance n samples; returns the accelerometer signal (m/s²)."""
        dt = n / self.rate_hz
        self.t += dt
        target = self.rpm_cmd
        step = self.accel_rpm_s * dt
        self.rpm = target if abs(target - self.rpm) <= step else self.rpm + math.copysign(step, target - self.rpm)
        self._advance_program(dt)
        depth = self.depth_mm if self.phase == "cut" else 0.0
        block = self.cutter.run(n, max(self.rpm, 60.0), depth, self.part.feed_mm_rev)
        self.thermal.step(dt * self.time_scale, self.rpm)
        return np.asarray(block.accel, dtype=np.float32)

    def registers(self) -> dict[str, float]:
        radius = self.part.diameter_mm / 2
        cutting = self.phase == "cut"
        return {
            "spindle_rpm_cmd": self.rpm_cmd,
            "spindle_rpm": self.rpm,
            "spindle_override_pct": 100.0 * self.rpm_cmd / self.part.rpm,
            "x_mm": (radius - self.depth_mm if cutting else radius + 5.0) + self.offset_x_um / 1000.0,
            "y_mm": self.y_mm,
            "b_deg": 0.0,
            "part_count": self.part_count,
            "cycle_time_s": self.cycle_time_s,
            "program_state": 1,
            "program_number": self.program_number,
            "offset_x_um": self.offset_x_um,
            "depth_of_cut_mm": self.depth_mm if cutting else 0.0,
            "feed_mm_rev": self.part.feed_mm_rev,
            "alarm_code": 0,
            "tool_number": 1,
            "probe_displacement_um": self.probe_displacement_um,
            "probe_seq": self.probe_seq,
        }
