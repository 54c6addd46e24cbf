"""Physics of the lathe's neighbours on the simulated line: a mill, a grinder
and a robot arm that loads parts. Kinematics only, enough to give every
value a driver reads a plausible, changing source; no asyncio here (the
peers in this package serve these states over Modbus TCP, Modbus RTU and CAN).
"""
from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class CycleProgram:
    """A machining cycle: load, cut at ``rpm`` along ``travel_mm``, unload."""
    program_number: int
    rpm: float
    cycle_s: float
    travel_mm: tuple[float, float, float]   # x, y, z amplitude of the tool path
    load_s: float = 2.0


MILL_PROGRAM = CycleProgram(2100, rpm=8000.0, cycle_s=12.0, travel_mm=(120.0, 80.0, 15.0))
GRINDER_PROGRAM = CycleProgram(3100, rpm=1800.0, cycle_s=18.0, travel_mm=(0.3, 150.0, 0.0))


class SimCycleMachine:
    """A mill or grinder running one program over and over."""

    def __init__(self, program: CycleProgram, accel_rpm_s: float = 4000.0, max_rpm: float = 12000.0):
        self.program = program
        self.accel_rpm_s = accel_rpm_s
        self.max_rpm = max_rpm
        self.t = 0.0
        self.phase_t = 0.0
        self.rpm = 0.0
        self.rpm_override: float | None = None
        self.part_count = 0
        self.cycle_time_s = 0.0
        self.alarm_code = 0
        self.xyz = (0.0, 0.0, 0.0)

    @property
    def rpm_cmd(self) -> float:
        p = self.program
        if self.alarm_code or self.phase_t < p.load_s:
            return 0.0
        return p.rpm if self.rpm_override is None else self.rpm_override

    def write(self, name: str, value: float) -> None:
        if name != "spindle_rpm_cmd":
            raise KeyError(name)
        if not (math.isfinite(value) and 0 <= value <= self.max_rpm):
            raise ValueError(f"spindle speed {value} r/min beyond the drive's 0..{self.max_rpm:g}")
        self.rpm_override = value

    def step(self, dt: float) -> None:
        p = self.program
        self.t += dt
        if self.alarm_code:
            self.rpm = max(0.0, self.rpm - self.accel_rpm_s * dt)
            return
        self.phase_t += dt
        target = self.rpm_cmd
        step = self.accel_rpm_s * dt
        self.rpm = target if abs(target - self.rpm) <= step else self.rpm + math.copysign(step, target - self.rpm)
        s = max(0.0, self.phase_t - p.load_s) / (p.cycle_s - p.load_s)
        w = 2 * math.pi * s
        ax, ay, az = p.travel_mm
        self.xyz = (ax * math.sin(w), ay * s, -az * (1 - math.cos(w)) / 2)
        if self.phase_t >= p.cycle_s:
            self.part_count += 1
            self.cycle_time_s = self.phase_t
            self.phase_t = 0.0
            self.rpm_override = None

    def registers(self) -> dict[str, float]:
        x, y, z = self.xyz
        return {"spindle_rpm_cmd": self.rpm_cmd, "spindle_rpm": self.rpm, "x_mm": x, "y_mm": y, "z_mm": z,
                "part_count": self.part_count, "cycle_time_s": self.cycle_time_s,
                "program_state": 2 if self.alarm_code else (1 if self.rpm > 0.5 else 0),
                "program_number": self.program.program_number, "alarm_code": self.alarm_code}


# Joint poses (deg) of the pick-and-place cycle: above the conveyor, down to
# pick, above the lathe's chuck, down to place.
POSES = ((0, -30, 60, 0, 60, 0), (0, -10, 75, 0, 25, 0), (90, -30, 60, 0, 60, 90), (90, -10, 75, 0, 25, 90))
LINK_MM = (400.0, 350.0)    # upper arm, forearm


class SimRobotArm:
    """A six-axis arm moving parts from the conveyor to the lathe."""

    MOVE_S = 1.5
    GRIP_S = 0.5

    def __init__(self):
        self.t = 0.0
        self.segment = 0          # moving from POSES[segment] to POSES[segment + 1]
        self.seg_t = 0.0
        self.cycle_count = 0
        self.gripper = 0          # 0 open, 1 closed, 2 moving
        self.alarm_code = 0
        self.program = 7
        self.joints = POSES[0]

    def step(self, dt: float) -> None:
        self.t += dt
        if self.alarm_code:
            return
        self.seg_t += dt
        total = self.MOVE_S + self.GRIP_S
        if self.seg_t >= total:
            self.seg_t -= total
            self.segment = (self.segment + 1) % len(POSES)
            if self.segment == 0:
                self.cycle_count = (self.cycle_count + 1) % 65536
        a, b = POSES[self.segment], POSES[(self.segment + 1) % len(POSES)]
        s = min(1.0, self.seg_t / self.MOVE_S)
        s = s * s * (3 - 2 * s)    # smooth start and stop
        self.joints = tuple(x + (y - x) * s for x, y in zip(a, b))
        gripping = self.seg_t > self.MOVE_S
        closed_after = self.segment in (1, 2)  # closed from the pick until the place
        self.gripper = 2 if gripping else (1 if closed_after else 0)

    @property
    def state(self) -> int:
        return 2 if self.alarm_code else 1

    def tool_mm(self) -> tuple[float, float, float]:
        """Tool centre point from joints 1-3 (a planar two-link arm on a turntable)."""
        j1, j2, j3 = (math.radians(j) for j in self.joints[:3])
        l1, l2 = LINK_MM
        r = l1 * math.cos(j2) + l2 * math.cos(j2 + j3)
        z = 300.0 + l1 * math.sin(-j2) - l2 * math.sin(j2 + j3)
        return r * math.cos(j1), r * math.sin(j1), z
