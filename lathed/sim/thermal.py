"""Thermal behaviour of the simulated spindle: lumped heat capacities, the
growth of the spindle nose, and DS18B20-like readings of the four sensors.

Used twice: by the live simulated lathe (``SpindleThermal.step`` every 0.1 s
of sim time) and to generate runs for tests and benchmarks
(``generate_run``), so the analysis is always tested against the same physics
the daemon compensates.

Nodes (°C): front bearing, rear bearing, motor, spindle body, shaft; each
sensor is a node of its own that follows its body with a short lag, because
a DS18B20 glued to a housing reads the housing late. The room is an input
(set point plus a slow daily swing and drift). Heat from speed: bearing
friction ~ n^1.3, motor losses ~ a·n + b·n² (iron and copper).

With no effect switched on, the nose growth is a *static linear* function of
the body temperatures, which the sensors follow within ~20 s: the paper's
regression (eq. 14) is then the right model. Each effect adds what such a
regression lacks:

- ``lag``:        a heavy shaft warmed through the front bearing grows the
                  nose; it lags the front-bearing sensor by ~30 min.
- ``rate``:       while the front bearing heats, the radial gradient across
                  its housing adds growth in proportion to dT/dt (the
                  gradient builds up over ~2 min, the wall's diffusion time).
- ``speed``:      centrifugal (and gyroscopic) shortening ~ n², instantaneous.
- ``nonlinear``:  growth rises with the square of the front bearing's rise
                  (preload grows with temperature).
- ``hysteresis``: the bearing seat slips: the growth lags its temperature by a
                  dead band (play operator), different heating vs cooling.
- ``drift``:      a slow creep of the bed after a cold start, µm per hour,
                  seen by no sensor.
"""
from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
from scipy.linalg import expm

EFFECTS = ("lag", "rate", "speed", "nonlinear", "hysteresis", "drift")

SENSOR_KEYS = ("front_bearing", "rear_bearing", "motor", "room")
CSV_COLUMNS = ("time_s", "spindle_rpm", "t_front_bearing_c", "t_rear_bearing_c",
               "t_motor_c", "t_room_c", "displacement_um")

# State vector order.
FB, RB, MOT, BODY, SHAFT, S_FB, S_RB, S_MOT, GRAD = range(9)
_N = 9


@dataclass(frozen=True)
class ThermalParams:
    """Lumped parameters; C in J/K, G in W/K, heat in W at 4000 r/min."""
    c_fb: float = 6000.0
    c_rb: float = 9000.0
    c_mot: float = 15000.0
    c_body: float = 15.0            # small: the body follows its neighbours within seconds
    c_shaft: float = 6000.0
    g_fb_room: float = 3.0
    g_rb_room: float = 3.0
    g_mot_room: float = 6.0
    g_body_room: float = 0.5
    g_shaft_room: float = 0.5
    g_fb_body: float = 2.0
    g_rb_body: float = 1.5
    g_mot_body: float = 1.0
    g_fb_shaft: float = 3.0
    tau_sensor_s: float = 5.0
    q_fb_w: float = 60.0            # bearing friction at 4000 r/min
    q_rb_w: float = 30.0
    q_mot_lin_w: float = 20.0       # iron losses ~ n
    q_mot_sq_w: float = 60.0        # copper losses ~ n² (torque rises with speed)
    bearing_exponent: float = 1.3
    # Growth of the nose, µm per °C rise of each body (base, static-linear).
    k_fb: float = -2.0
    k_rb: float = 1.5
    k_mot: float = 0.5
    k_body: float = 8.0
    k_room: float = -1.0
    # Effects.
    k_lag_um_per_c: float = 6.0          # shaft
    k_rate_um_per_c_min: float = 30.0    # front bearing dT/dt ...
    tau_gradient_s: float = 240.0        # ... as the housing's radial gradient builds up
    k_speed_um_per_krpm2: float = -0.6
    k_nonlinear_um_per_c2: float = 0.3   # front bearing rise squared
    k_hyst_um_per_c: float = 4.0
    hyst_width_c: float = 1.0
    drift_um_per_h: float = 3.0
    # Room.
    room_daily_amp_c: float = 1.0
    room_drift_c_per_h: float = 0.05
    # DS18B20.
    quantum_c: float = 0.0625
    sensor_noise_c: float = 0.02


def _system(p: ThermalParams) -> tuple[np.ndarray, np.ndarray]:
    """x' = A x + B u with u = (Q_fb, Q_rb, Q_mot, T_room)."""
    A = np.zeros((_N, _N))
    B = np.zeros((_N, 4))
    caps = {FB: p.c_fb, RB: p.c_rb, MOT: p.c_mot, BODY: p.c_body, SHAFT: p.c_shaft}
    links = [(FB, BODY, p.g_fb_body), (RB, BODY, p.g_rb_body), (MOT, BODY, p.g_mot_body),
             (FB, SHAFT, p.g_fb_shaft)]
    for i, j, g in links:
        A[i, i] -= g / caps[i]
        A[i, j] += g / caps[i]
        A[j, j] -= g / caps[j]
        A[j, i] += g / caps[j]
    for i, g in ((FB, p.g_fb_room), (RB, p.g_rb_room), (MOT, p.g_mot_room),
                 (BODY, p.g_body_room), (SHAFT, p.g_shaft_room)):
        A[i, i] -= g / caps[i]
        B[i, 3] += g / caps[i]
    B[FB, 0] = 1.0 / p.c_fb
    B[RB, 1] = 1.0 / p.c_rb
    B[MOT, 2] = 1.0 / p.c_mot
    for s, body in ((S_FB, FB), (S_RB, RB), (S_MOT, MOT)):
        A[s, s] = -1.0 / p.tau_sensor_s
        A[s, body] = 1.0 / p.tau_sensor_s
    # Radial gradient across the front housing (°C/s): follows the bearing's
    # heating rate with the wall's own diffusion time.
    A[GRAD] = A[FB] / p.tau_gradient_s
    A[GRAD, GRAD] = -1.0 / p.tau_gradient_s
    B[GRAD] = B[FB] / p.tau_gradient_s
    return A, B


class SpindleThermal:
    """The spindle's temperatures and nose growth, advanced in exact steps
    (piecewise-constant speed), so any step length is stable and a step is two
    8x8 matrix-vector products."""

    def __init__(self, room_c: float = 20.0, seed: int = 0, effects: Iterable[str] = (),
                 params: ThermalParams | None = None, room_phase_h: float | None = None):
        self.effects = frozenset(effects)
        unknown = self.effects - set(EFFECTS)
        if unknown:
            raise ValueError(f"unknown thermal effect(s) {sorted(unknown)}; known: {', '.join(EFFECTS)}")
        self.p = params or ThermalParams()
        self.room_c = float(room_c)
        self._rng = np.random.default_rng(seed)
        # Where in the day the run starts; a different seed is a different day.
        self.room_phase_h = float(self._rng.uniform(0, 24) if room_phase_h is None else room_phase_h)
        self._A, self._B = _system(self.p)
        self._steps: dict[float, tuple[np.ndarray, np.ndarray]] = {}
        self.t_s = 0.0
        self.rpm = 0.0
        t0 = self.room_temp(0.0)
        self.x = np.full(_N, t0)
        self.x[GRAD] = 0.0
        self.x0 = self.x.copy()
        self.room0 = t0
        self._play = t0           # hysteresis state on the front bearing

    # -- physics ---------------------------------------------------------
    def room_temp(self, t_s: float) -> float:
        p = self.p
        h = t_s / 3600.0
        return (self.room_c + p.room_daily_amp_c * math.sin(2 * math.pi * (h + self.room_phase_h) / 24.0)
                + p.room_drift_c_per_h * h)

    def heat_w(self, rpm: float) -> tuple[float, float, float]:
        p = self.p
        r = max(float(rpm), 0.0) / 4000.0
        bearing = r ** p.bearing_exponent
        return p.q_fb_w * bearing, p.q_rb_w * bearing, p.q_mot_lin_w * r + p.q_mot_sq_w * r * r

    def _step_matrices(self, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        key = round(dt_s, 9)
        m = self._steps.get(key)
        if m is None:
            phi = expm(self._A * dt_s)
            gamma = np.linalg.solve(self._A, (phi - np.eye(_N)) @ self._B)
            m = self._steps[key] = (phi, gamma)
        return m

    def step(self, dt_s: float, rpm: float) -> None:
        """Advance ``dt_s`` seconds at constant spindle speed ``rpm``."""
        if not dt_s > 0:
            raise ValueError(f"thermal step must be > 0 s, got {dt_s}")
        phi, gamma = self._step_matrices(dt_s)
        # Room held at its mid-step value: its swing is hours long.
        u = np.array([*self.heat_w(rpm), self.room_temp(self.t_s + dt_s / 2)])
        self.x = phi @ self.x + gamma @ u
        self.t_s += dt_s
        self.rpm = float(rpm)
        w = self.p.hyst_width_c
        self._play = min(max(self._play, self.x[FB] - w), self.x[FB] + w)

    # -- outputs ---------------------------------------------------------
    @property
    def displacement_um(self) -> float:
        """True growth of the spindle nose (µm) since the cold start."""
        return float(self._growths(self.x[None, :], np.array([self.t_s]), np.array([self.rpm]),
                                   np.array([self._play]))[0])

    def true_temperatures(self) -> dict[str, float]:
        names = ("front_bearing", "rear_bearing", "motor", "spindle_body", "shaft")
        out = {n: float(self.x[i]) for n, i in zip(names, (FB, RB, MOT, BODY, SHAFT))}
        out["room"] = self.room_temp(self.t_s)
        return out

    def readings(self) -> dict[str, float]:
        """What the four DS18B20s report now (°C, 1/16 °C steps, small noise)."""
        raw = np.array([self.x[S_FB], self.x[S_RB], self.x[S_MOT], self.room_temp(self.t_s)])
        return dict(zip(SENSOR_KEYS, (float(v) for v in self._read(raw))))

    def _read(self, raw: np.ndarray) -> np.ndarray:
        """DS18B20 readings of true temperatures ``raw`` (the four sensors' last axis): the
        noise drawn from this spindle's stream in order, row after row, as one reading at a time."""
        p = self.p
        noisy = raw + self._rng.normal(0.0, p.sensor_noise_c, raw.shape)
        return np.round(noisy / p.quantum_c) * p.quantum_c

    def _growths(self, x: np.ndarray, t_s: np.ndarray, rpm: np.ndarray, play: np.ndarray) -> np.ndarray:
        """``displacement_um`` at each row of states ``x`` (times, speeds, play-operator states):
        the same operations in the same order, element by element (Python's ``**`` where it
        used it: it is not always x*x to the last bit)."""
        p = self.p
        rise = x - self.x0
        room_rise = np.array([self.room_temp(t) for t in t_s.tolist()]) - self.room0
        d = (p.k_fb * rise[:, FB] + p.k_rb * rise[:, RB] + p.k_mot * rise[:, MOT]
             + p.k_body * rise[:, BODY] + p.k_room * room_rise)
        e = self.effects
        if "lag" in e:
            d += p.k_lag_um_per_c * rise[:, SHAFT]
        if "rate" in e:
            d += p.k_rate_um_per_c_min * x[:, GRAD] * 60.0
        if "speed" in e:
            d += p.k_speed_um_per_krpm2 * np.array([(r / 1000.0) ** 2 for r in rpm.tolist()])
        if "nonlinear" in e:
            d += p.k_nonlinear_um_per_c2 * np.array([r ** 2 for r in rise[:, FB].tolist()])
        if "hysteresis" in e:
            d += p.k_hyst_um_per_c * (play - x[:, FB])
        if "drift" in e:
            d += p.drift_um_per_h * t_s / 3600.0
        return d


# -- runs for tests and benchmarks ---------------------------------------

def random_schedule(seed: int, total_s: float = 18000.0, seg_s: tuple[float, float] = (600.0, 2400.0),
                    rpms: Sequence[float] = (0, 1000, 1500, 2000, 2500, 3000, 3500, 4000)
                    ) -> list[tuple[float, float]]:
    """Piecewise-constant speed schedule ``[(duration_s, rpm), ...]``."""
    rng = np.random.default_rng(seed)
    out: list[tuple[float, float]] = []
    t = 0.0
    last = None
    while t < total_s:
        d = float(min(rng.uniform(*seg_s), total_s - t))
        r = float(rng.choice([x for x in rpms if x != last]))
        out.append((d, r))
        last = r
        t += d
    return out


@dataclass
class Run:
    """A generated run: one array per CSV column."""
    columns: dict[str, np.ndarray] = field(default_factory=dict)
    effects: frozenset[str] = frozenset()
    noise_um: float = 0.0

    def __len__(self) -> int:
        return len(self.columns["time_s"])

    def write_csv(self, path: str | Path) -> None:
        temps = [c for c in self.columns if c.startswith("t_")]   # the four, and any added (many_sensors)
        header = ["time_s", "spindle_rpm", *temps, "displacement_um"]
        with open(path, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(header)
            cols = [self.columns[c] for c in header]
            for row in zip(*cols):
                w.writerow([f"{row[0]:.1f}", f"{row[1]:.0f}", *(f"{v:.4f}" for v in row[2:-1]),
                            f"{row[-1]:.3f}"])


def generate_run(schedule: Sequence[tuple[float, float]], effects: Iterable[str] = (), seed: int = 0,
                 dt_s: float = 6.0, room_c: float = 20.0, noise_um: float = 0.5,
                 params: ThermalParams | None = None) -> Run:
    """Simulate ``schedule`` from a cold start and sample every ``dt_s``:
    sensor readings, speed, and the displacement a probe measures (true growth
    plus ``noise_um`` of probe repeatability)."""
    sim = SpindleThermal(room_c=room_c, seed=seed, effects=effects, params=params)
    rng = np.random.default_rng(seed + 7919)
    rpm_at = np.concatenate([np.full(max(int(round(d / dt_s)), 0), r) for d, r in schedule])
    n = len(rpm_at)
    # the states stepped one by one; the readings and the growth from them in one go
    xs, ts, plays = np.empty((n, _N)), np.empty(n), np.empty(n)
    for k in range(n):
        sim.step(dt_s, rpm_at[k])
        xs[k], ts[k], plays[k] = sim.x, sim.t_s, sim._play
    room = np.array([sim.room_temp(t) for t in ts.tolist()])
    read = sim._read(np.column_stack([xs[:, S_FB], xs[:, S_RB], xs[:, S_MOT], room]))
    cols = {"time_s": ts, "spindle_rpm": rpm_at.astype(float),
            **{f"t_{key}_c": np.ascontiguousarray(read[:, i]) for i, key in enumerate(SENSOR_KEYS)},
            "displacement_um": sim._growths(xs, ts, rpm_at, plays)}
    cols = {c: cols[c] for c in CSV_COLUMNS}
    cols["displacement_um"] += rng.normal(0.0, noise_um, n)
    return Run(columns=cols, effects=frozenset(effects), noise_um=noise_um)


# -- harder runs: many sensors, effects outside the library -----------------

def add_periodic(run: Run, period_s: float = 1200.0, amp_um: float = 3.0, phase: float = 0.7) -> Run:
    """A cycle in the growth no sensor sees (a coolant pump, a door), on the
    run's clock: an effect outside the candidate library."""
    t = run.columns["time_s"]
    run.columns["displacement_um"] = run.columns["displacement_um"] + amp_um * np.sin(
        2 * math.pi * t / period_s + phase)
    return run


def add_speed_steps(run: Run, threshold_rpm: float = 2750.0, step_um: float = 4.0) -> Run:
    """Growth that steps when the speed crosses ``threshold_rpm`` and holds
    while it holds (a preload switch): steps at the logged speed changes,
    with no temperature change, by no smooth function of speed."""
    run.columns["displacement_um"] = run.columns["displacement_um"] + step_um * (
        run.columns["spindle_rpm"] >= threshold_rpm)
    return run


TRUE_SENSORS = tuple(f"t_{k}_c" for k in SENSOR_KEYS)


def many_sensors(run: Run, seed: int, n_sensors: int = 16, osc_period_s: float = 270.0,
                 osc_amp_c: float = 0.4, rig_seed: int = 4242) -> Run:
    """The run's four sensors plus ``n_sensors - 4`` that carry no growth of
    their own, as on a spindle fitted with many: some read the heated parts
    late and scaled (a housing further out), some follow the room, some
    wander; several oscillate on their own at a few minutes' period. The
    motor's sensor oscillates too (coolant past it): in its reading only,
    not in the growth. The growth stays the four sensors' bodies'.

    The sensors are the rig's (``rig_seed``): where each sits (its lag, its
    scale, its own oscillation) is the same on every run, as on a real
    spindle from one shift to the next; the readings' noise, a wandering
    sensor's walk and an oscillation's phase are the run's (``seed``)."""
    rng = np.random.default_rng(seed + 4242)
    rig = np.random.default_rng(rig_seed)
    c = run.columns
    t = c["time_s"]
    p = ThermalParams()
    n = len(t)

    def reading(x: np.ndarray) -> np.ndarray:
        return np.round((x + rng.normal(0.0, p.sensor_noise_c, n)) / p.quantum_c) * p.quantum_c

    # parts further out follow the heated bodies, not the coolant at the motor's sensor
    heated = [c[k] for k in TRUE_SENSORS[:3]]
    c["t_motor_c"] = reading(c["t_motor_c"] + osc_amp_c * np.sin(2 * math.pi * t / osc_period_s))
    room = c["t_room_c"]
    cold = float(room[0])     # a cold machine is at the room's temperature
    dt = float(np.median(np.diff(t)))
    for i in range(n_sensors - len(TRUE_SENSORS)):
        kind = i % 3
        if kind == 0:      # a heated part further out: one heated part's rise, late and scaled
            src = heated[(i // 3) % 3]      # front bearing, rear bearing, motor in turn
            a = 1.0 - math.exp(-dt / rig.uniform(300.0, 3000.0))
            x = np.empty(n)
            acc = cold                      # from the cold start, not from the heated part's first row
            for k, v in enumerate(src.tolist()):
                acc += a * (v - acc)
                x[k] = acc
            x = cold + rig.uniform(0.3, 1.2) * (x - cold)
        elif kind == 1:    # near the room
            x = room + rig.normal(0.0, 0.05) + 0.3 * np.sin(2 * math.pi * t / rig.uniform(3600, 7200))
        else:              # wanders (a sensor on a cabinet)
            x = room[0] + np.cumsum(rng.normal(0.0, 0.01, n))
        if i % 2 == 0:     # its own oscillation
            x = x + rig.uniform(0.1, 0.5) * np.sin(2 * math.pi * t / rig.uniform(180.0, 600.0) + rng.uniform(0, 6))
        c[f"t_extra{i + 1:02d}_c"] = reading(x)
    return run
