"""Physics of the simulated lathe: spindle, part program, axes, heat, cut.

A simulator of physics, not of a particular controller: the spindle follows
its commanded speed within an acceleration limit; the program turns parts
one after another (load, approach at feed, cut along the part, a dwell where
the program has one, retract); the cut's vibration
comes from the regenerative chip-thickness model (lathed.analysis.regen), so
a depth above the stability limit really chatters (with a worn tool,
``flank``, chatter just above it stays mild); the spindle warms with
speed (lathed.sim.thermal). It also watches its own cut for the instant
chatter becomes visible on the surface (``VisibleChatter``, regen's rule
applied live), so the closed loop's reaction can be timed against the truth.
No asyncio here: the peers in this package serve this state over Modbus,
serial and TCP.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field, fields

import numpy as np

from lathed.analysis.lobes import StabilityLobes
from lathed.analysis.modal import Mode
from lathed.analysis.process_damping import FlankWear
from lathed.analysis.regen import VISIBLE_WAVINESS_M, RegenerativeTurning, SimBlock
from lathed.sim.program import Cut
from lathed.sim.thermal import SpindleThermal

# The simulated lathe's structure: a compliant workpiece mode at 190 Hz
# (a 30 mm bar on an 80 mm overhang) and a stiffer tool-post mode. Its lobes
# are distinct at the paper's speeds: the limiting depth is ~2.4 mm at 1500,
# 2000 and 2500 r/min (the paper's 3 mm cut chatters, 1 mm does not) and
# above 5 mm near 2300 r/min, so a spindle speed choice can save the cut.
LATHE_MODES = (Mode(190.0, 0.03, 7.5e7, 0.0), Mode(620.0, 0.035, 4.0e8, 30.0))
LATHE_KF = 2.0e9    # N/m² along the chip-thickness direction (medium carbon steel)
LATHE_KT = 1.5e9    # N/m² tangential: sets the spindle torque a cut needs
LATHE_PEAK_TORQUE_NM = 35.8   # the spindle drive's rating: 100 % load
IDLE_LOAD_PCT = 2.0           # bearings and seals at speed, no chip


# The turret: tool 1 is the turning tool the tap test measured (LATHE_MODES, or the true
# modes a test gives); tool 2 a slender boring bar, its own mode far softer than the
# tool post's (a limit of 0.6 mm against tool 1's 2.4): the same workpiece, another tool.
BORING_BAR = Mode(350.0, 0.02, 3.0e7, 0.0)


def tool_modes(modes: tuple[Mode, ...], tool: int) -> tuple[Mode, ...]:
    """The structure a turret position cuts with: tool 2 swaps the tool mode for the bar's."""
    return modes if tool == 1 else (modes[0], BORING_BAR)


# The paper's three speeds; every third part is cut 3 mm deep (the paper's
# depth, above the stability limit of DEFAULT_MODES), the others 1 mm.  Then a
# face at constant surface speed (G96, 190 m/min: 2016 -> 2880 r/min as the
# tool moves in from 30 to 21 mm at 0.1 mm/rev, 0.7-1 % a revolution), 1.5 mm
# deep: stable.
DEFAULT_PROGRAM = (
    Cut(1500, 1.0), Cut(2000, 1.0), Cut(2500, 3.0),
    Cut(2000, 1.0), Cut(1500, 3.0), Cut(2500, 1.0),
    Cut(3500, 1.5, 0.1, 4.5, css_m_min=190.0),
)


class VisibleChatter:
    """regen.simulate_cut's "chatter is visible" rule, evaluated live block by block.

    Same quantities as regen.wav_rev/simulate_cut: d = y(theta) - y(theta - 2 pi)
    less its centred moving mean over rate/200 samples, zero out of the cut;
    rms per revolution counted from the cut's start (revolution length fixed
    by the speed there); visible from the start of the first revolution with
    rms >= VISIBLE_WAVINESS_M that does not shrink by more than 10 % over the
    next two.  The stream since start-up is the "recording".  The centred mean
    looks ahead half a window, so the verdict comes half a window plus three
    revolutions after the instant it reports.  O(block) work per block.
    """

    def __init__(self, rate_hz: float):
        self.rate = float(rate_hz)
        k = max(1, int(rate_hz / 200))
        self.k = k
        self.ahead = (k - 1) // 2           # np.convolve(mode="same") centring
        self.behind = k - 1 - self.ahead
        self.n = 0                          # samples fed
        self._th = np.empty(0)              # last ~revolution, for y(theta - 2 pi)
        self._y = np.empty(0)
        # d not yet mean-removed, from absolute index _dbase; zeros before the
        # stream like np.convolve's padding
        self._d = np.zeros(self.behind)
        self._inc = np.zeros(self.behind, dtype=bool)
        self._dbase = -self.behind
        self._p = 0                         # first sample not yet final
        self.i0: int | None = None          # tracked cut: first sample, end, revolution
        self.end: int | None = None
        self.rev = 0
        self.revs: list[float] = []         # rms per completed revolution (m)
        self._sum = 0.0
        self.visible_at: int | None = None  # sample index

    def start(self, i0: int, rpm: float) -> None:
        self.i0, self.end = i0, None
        self.rev = max(1, int(self.rate * 60.0 / rpm))
        self.revs, self._sum, self.visible_at = [], 0.0, None

    def stop(self, end: int) -> None:
        if self.i0 is not None and self.end is None:
            self.end = end

    def feed(self, b: SimBlock) -> None:
        th, y = b.theta_rad, b.y_m
        hth = np.concatenate((self._th, th))
        hy = np.concatenate((self._y, y))
        d = y - np.interp(th - 2 * np.pi, hth, hy, left=np.nan)
        d[~np.isfinite(d)] = 0.0
        keep = int(np.searchsorted(hth, hth[-1] - 2.05 * np.pi))
        self._th, self._y = hth[keep:], hy[keep:]
        self.n += len(y)
        self._d = np.concatenate((self._d, d))
        self._inc = np.concatenate((self._inc, b.in_cut))
        lo, hi = self._p, self.n - self.ahead    # final now: [lo, hi)
        if hi <= lo:
            return
        c = np.concatenate(([0.0], np.cumsum(self._d)))
        idx = np.arange(lo, hi) - self._dbase
        mean = (c[idx + self.ahead + 1] - c[idx - self.behind]) / self.k
        wav = np.where(self._inc[idx], self._d[idx] - mean, 0.0)
        self._track(lo, wav)
        self._p = hi
        cut = hi - self.behind - self._dbase
        self._d, self._inc, self._dbase = self._d[cut:], self._inc[cut:], hi - self.behind

    def _track(self, lo: int, wav: np.ndarray) -> None:
        if self.i0 is None or self.visible_at is not None:
            return
        hi = lo + len(wav)
        pos = max(lo, self.i0 + len(self.revs) * self.rev)
        stop = hi if self.end is None else min(hi, self.end)
        while pos < stop:
            rev_end = self.i0 + (len(self.revs) + 1) * self.rev
            e = min(stop, rev_end)
            seg = wav[pos - lo:e - lo]
            self._sum += float(seg @ seg)
            pos = e
            if e == rev_end:
                self.revs.append(math.sqrt(self._sum / self.rev))
                self._sum = 0.0
                r = self.revs
                if len(r) >= 3 and r[-3] >= VISIBLE_WAVINESS_M and r[-2] >= 0.9 * r[-3] \
                        and r[-1] >= 0.9 * r[-2]:
                    self.visible_at = self.i0 + (len(r) - 3) * self.rev
                    return
        if self.end is not None and hi >= self.end:
            self.i0 = None      # cut over: a revolution it did not finish does not count


@dataclass
class PartRecord:
    """One part as the machine saw it: for timing the closed loop against the truth.
    Times are sim seconds (sample index / rate); the simulator process adds
    the wall-clock times of its vibration stream (``*_wall``)."""
    part: int
    rpm: float                    # programmed (a G96 pass: its speed at entry)
    depth_mm: float
    css_m_min: float = 0.0        # a G96 pass's surface speed (no visible-chatter instant is timed)
    thread: bool = False          # a threading pass (the control's threading signal on)
    b_lim_mm: float | None = None     # limiting depth at the speed the cut started at
    cut_start_s: float | None = None
    cut_end_s: float | None = None
    dwell_start_s: float | None = None    # the pass's dwell (G04): the feed stood from ... to
    dwell_end_s: float | None = None
    visible_at_s: float | None = None
    waviness_um: list[float] = field(default_factory=list)   # first revolutions' rms
    speed_writes: list[dict] = field(default_factory=list)   # {"sim_t", "rpm"[, "wall_t"]}
    cut_start_wall: float | None = None
    visible_wall: float | None = None

    def as_dict(self) -> dict:
        return {k: v for k, v in self.__dict__.items()}


OVERRIDE_MIN_PCT, OVERRIDE_MAX_PCT = 50.0, 150.0   # the control's spindle override range
LOAD_S = 1.5       # bar loaded, spindle brought to the part's speed
RETRACT_S = 1.0    # tool retracted, part measured (probe cycle), unloaded
# A pass's G01 starts this far clear of the stock (the CAM's approach clearance): the control
# is in cutting feed that long before the chip, cutting air (the cutting_feed register says 1)
APPROACH_MM = 0.5
# Samples cut at one feed while the chip thins or grows after a dwell's stop or start (0.6 ms:
# short against the tool post's 1.6 ms period, so the chip's ramp does not ring it as steps)
RAMP_SAMPLES = 32


class SimLathe:
    def __init__(self, program: tuple[Cut, ...] = DEFAULT_PROGRAM, rate_hz: int = 51200,
                 time_scale: float = 1.0, accel_rpm_s: float = 3000.0, max_rpm: float = 6000.0,
                 depth_override_mm: float | None = None, seed: int = 0, room_c: float = 20.0,
                 modes: tuple[Mode, ...] = LATHE_MODES, kf: float = LATHE_KF,
                 load_s: float = LOAD_S, retract_s: float = RETRACT_S,
                 flank: FlankWear | None = None, approach_mm: float = APPROACH_MM):
        self.program = program
        self.rate_hz = rate_hz
        self.time_scale = time_scale          # thermal clock speed-up
        self.accel_rpm_s = accel_rpm_s
        self.max_rpm = max_rpm
        self.depth_override_mm = depth_override_mm
        self.rpm_program_override: float | None = None   # every part's programmed speed (None: the program's)
        # the true dynamics: by default the model the default configuration gives the daemon;
        # other modes or Kf make an effect the daemon's model lacks (issue 16's tests);
        # flank: the tool's worn land (process damping, issue 12), None for a sharp tool
        self._cutter_args = (modes, kf, float(rate_hz), seed, flank)
        self._cutters: dict[int, RegenerativeTurning] = {}
        self._tool_now: int | None = None
        self._lobes: dict[int, StabilityLobes] = {}
        self.load_s, self.retract_s = load_s, retract_s
        self.approach_mm = approach_mm
        self.approach_left_mm = 0.0
        self.dwell_left_s = 0.0                  # a dwell (G04) standing: its time left
        # spindle angles the feed stood between in this pass (the end inf while it stands):
        # the chip is what the tool advanced over the last revolution
        self._still: tuple[float, float] | None = None
        self._block_theta = (0.0, 0.0)          # the spindle angle over the step's samples
        self.thermal = SpindleThermal(room_c=room_c, seed=seed)
        self._rng = np.random.default_rng(seed + 1)
        self.t = 0.0
        self.part_index = 0
        self.phase = "load"
        self.phase_t = 0.0
        self.y_mm = 0.0
        self.rpm = 0.0
        self.block_rpm = 0.0                     # speed the last step's samples were cut at
        self.rpm_override: float | None = None   # written over Modbus; holds for the current part
        # the spindle override (Fanuc's SOV through the PMC, Siemens' DBB19): a percentage of
        # the programmed speed, G96 or not, that holds until written again, part after part
        self.override_pct = 100.0
        self.offset_x_um = 0.0
        self.part_count = 0
        self.cycle_start = 0.0
        self.cycle_time_s = 0.0
        self.probe_displacement_um = 0.0
        self.probe_seq = 0
        self.program_number = 1000
        self.load_pct = 0.0
        self.watch = VisibleChatter(rate_hz)
        self._tracked: PartRecord | None = None     # the part the watch follows
        self.n_samples = 0
        self.parts: deque[PartRecord] = deque(maxlen=64)
        self._new_part()

    def _new_part(self) -> None:
        self.parts.append(PartRecord(self.part_index, self.part.program_rpm(0.0), self.depth_mm,
                                     self.part.css_m_min, self.part.thread))

    @property
    def record(self) -> PartRecord:
        return self.parts[-1]

    @property
    def visible_at_s(self) -> float | None:
        """Sim time (sample index / rate) chatter became visible in the current part, or None."""
        return self.record.visible_at_s

    # -- program ------------------------------------------------------------
    @property
    def part(self) -> Cut:
        return self.program[self.part_index % len(self.program)]

    @property
    def depth_mm(self) -> float:
        return self.part.depth_mm if self.depth_override_mm is None else self.depth_override_mm

    @property
    def cut_depth_mm(self) -> float:
        """The chip's depth at the tool now: the pass's, a shoulder's beyond it, none over a groove
        (an override replaces the pass's depth, not the groove)."""
        depth = self.part.depth_at(self.y_mm)
        if self.depth_override_mm is not None and depth > 0.0:
            return self.depth_override_mm
        return depth

    @property
    def cutter(self) -> RegenerativeTurning:
        """The regenerative model of the tool cutting this part (one per turret position)."""
        tool = self.part.tool
        if tool not in self._cutters:
            modes, kf, rate, seed, flank = self._cutter_args
            self._cutters[tool] = RegenerativeTurning(tool_modes(modes, tool), kf, rate_hz=rate,
                                                      seed=seed + 1000 * (tool - 1), flank=flank)
        cutter = self._cutters[tool]
        if tool != self._tool_now:
            # a tool change (between parts): the spindle's angle goes on, the tool is at rest
            # and the next part is fresh material
            last = self._cutters.get(self._tool_now)
            cutter.reset()
            cutter.theta = last.theta if last is not None else 0.0
            self._tool_now = tool
        return cutter

    @property
    def lobes(self) -> StabilityLobes:
        tool = self.part.tool
        if tool not in self._lobes:
            self._lobes[tool] = StabilityLobes(tool_modes(self._cutter_args[0], tool), self._cutter_args[1])
        return self._lobes[tool]

    @property
    def program_rpm(self) -> float:
        """The speed the program asks for now (under G96 it follows the tool's diameter)."""
        if self.rpm_program_override is not None:
            return self.rpm_program_override
        return self.part.program_rpm(self.y_mm)

    @property
    def diameter_mm(self) -> float:
        """The diameter being cut (a facing pass moves in as it goes)."""
        return self.part.diameter_at(self.y_mm)

    @property
    def rpm_cmd(self) -> float:
        # a written speed is the pass's speed from then on, G96 or not: this control takes it
        # as an S word with G97 (the write ends constant surface speed for the part)
        base = self.program_rpm if self.rpm_override is None else self.rpm_override
        return min(base * self.override_pct / 100.0, self.max_rpm)    # the control clamps at its maximum

    def write(self, name: str, value: float) -> None:
        """A register written by a client (the daemon)."""
        if name == "spindle_rpm_cmd":
            if not (math.isfinite(value) and 0 <= value <= self.max_rpm):
                raise ValueError(f"spindle speed {value} r/min beyond the drive's 0..{self.max_rpm:g}")
            self.rpm_override = value
            self.record.speed_writes.append({"sim_t": self.t, "rpm": value})
        elif name == "spindle_override_pct":
            if not (math.isfinite(value) and OVERRIDE_MIN_PCT <= value <= OVERRIDE_MAX_PCT):
                raise ValueError(f"spindle override {value} % beyond the control's "
                                 f"{OVERRIDE_MIN_PCT:g}..{OVERRIDE_MAX_PCT:g} %")
            self.override_pct = value
            self.record.speed_writes.append({"sim_t": self.t, "rpm": self.rpm_cmd, "override_pct": value})
        elif name == "offset_x_um":
            if not math.isfinite(value):
                raise ValueError("offset is not a number")
            self.offset_x_um = value
        else:
            raise KeyError(name)

    def _advance_program(self, dt: float) -> None:
        self.phase_t += dt
        if self.phase == "load" and self.phase_t >= self.load_s and abs(self.rpm - self.rpm_cmd) < 1.0:
            self.phase, self.phase_t, self.y_mm = "approach", 0.0, 0.0
            self.approach_left_mm = self.approach_mm
        if self.phase == "approach":
            self.approach_left_mm -= self.part.feed_mm_rev * self.rpm / 60.0 * dt
            if self.approach_left_mm <= 0.0:
                self.phase, self.phase_t, self.approach_left_mm = "cut", 0.0, 0.0
        elif self.phase == "cut":
            if self.dwell_left_s > 0.0:
                # G04: the feed stands, the tool in the work, the spindle turning
                self.dwell_left_s -= dt
                if self.dwell_left_s <= 0.0:
                    self._still = (self._still[0], self._block_theta[1])   # on from the next step
                    self.record.dwell_end_s = (self.n_samples + round(dt * self.rate_hz)) / self.rate_hz
                return
            self.y_mm += self.part.feed_mm_rev * self.rpm / 60.0 * dt
            half = self.part.length_mm / 2
            if self.part.dwell_s and self._still is None and self.y_mm >= half:
                # the dwell at the pass's middle, from this step's end
                self.y_mm, self.dwell_left_s = half, self.part.dwell_s
                self._still = (self._block_theta[1], math.inf)
                self.record.dwell_start_s = (self.n_samples + round(dt * self.rate_hz)) / self.rate_hz
            if self.y_mm >= self.part.length_mm:
                self.phase, self.phase_t = "retract", 0.0
                # probe cycle: the spindle's thermal growth as a touch probe sees it
                self.probe_displacement_um = self.thermal.displacement_um + self._rng.normal(0, 0.3)
                self.probe_seq = (self.probe_seq + 1) % 65536
        elif self.phase == "retract" and self.phase_t >= self.retract_s:
            self.part_count += 1
            self.cycle_time_s = self.t - self.cycle_start
            self.cycle_start = self.t
            self.part_index += 1
            self.rpm_override = None
            self._still = None
            self.phase, self.phase_t, self.y_mm = "load", 0.0, 0.0
            self._new_part()

    # -- physics --------------------------------------------------------------
    def step(self, n: int) -> np.ndarray:
        """Advance n samples; returns the accelerometer signal (m/s²)."""
        dt = n / self.rate_hz
        self.t += dt
        target = self.rpm_cmd
        step = self.accel_rpm_s * dt
        self.rpm = target if abs(target - self.rpm) <= step else self.rpm + math.copysign(step, target - self.rpm)
        was = self.phase
        cutter = self.cutter
        self._block_theta = (cutter.theta, cutter.theta + 2 * math.pi * max(self.rpm, 60.0) / 60.0 * dt)
        self._advance_program(dt)
        depth = self.cut_depth_mm if self.phase == "cut" else 0.0
        # a flat or a keyway from its place along the pass: no material over part of every revolution
        cutter.flat_fraction = self.part.flat_at(self.y_mm) / 360.0 if self.phase == "cut" else 0.0
        # the speed these samples are cut at: a vibration frame carries this one, not the
        # speed before the step (one ramp step stale) nor the commanded one
        self.block_rpm = self.rpm
        block = self._cut(n, max(self.rpm, 60.0), depth)
        self._load(depth, block)
        self._watch(was, n, block, depth)
        self.thermal.step(dt * self.time_scale, self.rpm)
        return np.asarray(block.accel, dtype=np.float32)

    def _cut(self, n: int, rpm: float, depth: float) -> SimBlock:
        """The step's samples, cut.  The chip is what the tool advanced over the last revolution:
        where the feed stopped or went on within it (a dwell), the chip thins to nothing or grows
        back along that revolution, so the step is cut in pieces short against the structure's
        periods (RAMP_SAMPLES) and the force follows the chip smoothly, not in the step's stairs."""
        feed = self.part.feed_mm_rev
        th0, th1 = self._block_theta
        still = self._still
        if still is None or not any(th0 - 2 * math.pi < edge < th1 for edge in still):
            return self.cutter.run(n, rpm, depth, feed * self._moving_share(th0, th1), self.diameter_mm)
        dth = (th1 - th0) / n
        pieces = [self.cutter.run(min(RAMP_SAMPLES, n - i), rpm, depth,
                                  feed * self._moving_share(th0 + i * dth, th0 + min(i + RAMP_SAMPLES, n) * dth),
                                  self.diameter_mm) for i in range(0, n, RAMP_SAMPLES)]
        return SimBlock(*(np.concatenate([getattr(p, f.name) for p in pieces]) for f in fields(SimBlock)))

    def _moving_share(self, th0: float, th1: float) -> float:
        """The share of the last revolution (to the middle of th0..th1) the feed moved in."""
        if self._still is None:
            return 1.0
        stop, go = self._still
        mid = (th0 + th1) / 2
        stood = max(0.0, min(mid, go) - max(mid - 2 * math.pi, stop))
        return max(0.0, 1.0 - stood / (2 * math.pi))      # (the angles' rounding: never below 0)

    def _load(self, depth_mm: float, block: SimBlock) -> None:
        """Spindle load as a drive reports it: cutting torque (Kt b h r, the chip
        actually removed, so chatter's lost contact shows) over the rated torque."""
        torque = LATHE_KT * depth_mm * 1e-3 * float(np.mean(np.maximum(block.h_m, 0.0))) \
            * self.diameter_mm / 2e3
        idle = IDLE_LOAD_PCT if self.rpm > 0 else 0.0
        self.load_pct = idle + 100.0 * torque / LATHE_PEAK_TORQUE_NM

    def _watch(self, was: str, n: int, block: SimBlock, depth: float) -> None:
        i = self.n_samples                  # this block's first sample
        rec = self.record
        if self.phase == "cut" and was != "cut":
            rec.cut_start_s, rec.depth_mm = i / self.rate_hz, self.depth_mm
            rec.b_lim_mm = float(self.lobes.b_lim_at(max(self.rpm, 60.0))[0][0] * 1e3)
        if (self.phase == "cut" and self._tracked is not rec and depth > (rec.b_lim_mm or math.inf)
                and not self.part.css_m_min):
            # regen's rule counts from the instant the cut is above the limit (its entry, or a
            # shoulder's step into a deeper pass); its revolutions are that speed's, so a G96
            # pass (the speed drifting) is not timed
            self.watch.start(i, max(self.rpm, 60.0))
            self._tracked = rec
        elif was == "cut" and self.phase != "cut":
            # the part record moved on only after retract, so this is still its part
            rec.cut_end_s = i / self.rate_hz
            self.watch.stop(i)
        w = self.watch
        before = w.visible_at
        tracking = w.i0 is not None
        self.watch.feed(block)
        self.n_samples += n
        # the tracked part's record, not the current one: the watch finishes a part's last
        # revolutions after the program has moved on to the next part
        trec = self._tracked
        if tracking and w.visible_at is not None and before is None:
            trec.visible_at_s = w.visible_at / self.rate_hz
        if tracking and len(w.revs) != len(trec.waviness_um) and len(w.revs) <= 8:
            trec.waviness_um = [round(r * 1e6, 2) for r in w.revs]

    def registers(self) -> dict[str, float]:
        radius = self.diameter_mm / 2
        cutting = self.phase == "cut"
        feeding = cutting or self.phase == "approach"
        return {
            "spindle_rpm_cmd": self.rpm_cmd,
            "spindle_rpm": self.rpm,
            "spindle_override_pct": 100.0 * self.rpm_cmd / self.program_rpm,
            "spindle_load_pct": self.load_pct,
            # the tool tip's radius: the turned surface's, or (facing) where the tool is
            "x_mm": ((radius + self.approach_left_mm if self.part.css_m_min else radius - self.depth_mm)
                     if feeding else radius + 5.0) + self.offset_x_um / 1000.0,
            "y_mm": self.y_mm,
            "b_deg": 0.0,
            "part_count": self.part_count,
            "cycle_time_s": self.cycle_time_s,
            "program_state": 1,
            "program_number": self.program_number,
            "offset_x_um": self.offset_x_um,
            "depth_of_cut_mm": self.cut_depth_mm if cutting else 0.0,
            "feed_mm_rev": self.part.feed_mm_rev,
            # the control's cutting-feed signal (Fanuc CUT): off in a dwell (G04), the axes standing
            "cutting_feed": 1 if feeding and self.dwell_left_s <= 0.0 else 0,
            # G96 until a written S word ends it for the part (G97); an override does not
            "css_active": 1 if self.part.css_m_min and self.rpm_override is None else 0,
            # a threading part's whole cycle, its load to its retract (a PMC bit over G76)
            "threading": 1 if self.part.thread else 0,
            "alarm_code": 0,
            "tool_number": self.part.tool,
            "probe_displacement_um": self.probe_displacement_um,
            "probe_seq": self.probe_seq,
        }
