"""Regenerative turning simulator: the time-delay chip model behind chatter.

Chip thickness along the surface normal (y positive = tool pushed away from
the part, so a larger y thins the chip):

    h(t) = h0 + s(theta - 2*pi) - y(t) + rho(theta)

``s`` is the surface the previous pass left, looked up one revolution back
*in spindle angle* (the delay follows speed changes exactly; at constant speed
it is T = 60/n).  In the cut s(t) = y(t); out of the cut (h <= 0, or over the
flat of an interrupted surface) no material is removed and s(t) = s(t-T) + h0.
``h0`` is what the tool advanced over the last revolution: where the feed
stops with the tool in the work (a dwell, G04) the caller passes that (0 once
the tool has stood a revolution), so the chip is only the last revolution's
surface against the tool's present place, and it thins to nothing within a
few revolutions as the structure's deflection relaxes (sparkout), the tool
rubbing or out of contact.  Only a depth of 0 is the tool clear of the part.
The force Kf*b*h (plus a small random cutting-process part that makes a stable
cut sound like one) is zero out of the cut, which bounds chatter.
Optionally (``flank``, off by default) the worn flank land ploughs the wavy
surface (lathed.analysis.process_damping): a damping force that grows with
the chatter amplitude, so a cut just above the limit saturates at a small
amplitude (mild chatter) instead of growing until the tool leaves the cut.
Each ``Mode`` takes the force projected by its directional factor ``u``
(lathed.analysis.modal) and the accelerometer reads the summed modal
acceleration along the normal, plus sensor noise.

A real stable cut is not stationary (``wander``, a ``Wander``; on by default
in ``simulate_cut``, off in ``RegenerativeTurning`` unless given): the bar's
hardness and the stock's depth vary along the cut and the chip's formation
changes, so the level of a stable cut's vibration drifts over tens of
revolutions without repeating.  See ``Wander`` for the physics and sizes.

Runout (``runout_um``) is modelled as spindle error motion the cut cannot
remove: rho(theta) = r*(cos theta + 0.3 cos(2 theta + 0.7)), a synchronous
chip-load modulation every revolution.  A flat (``flat_fraction``) takes the
tool out of the cut over that fraction of every revolution; re-entry is a
force step, so the structure rings once per revolution.

Speed: each regime (in or out of the cut) is linear, so its zero-order-hold
discretisation is diagonalised and evaluated in closed form over chunks shorter
than a revolution (``lathed.analysis.regime``); the flank's force enters through its
describing function at the recent amplitude.  No asyncio here.  docs/simulator.md.
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from lathed.analysis.lobes import StabilityLobes
from lathed.analysis.modal import Mode
from lathed.analysis.process_damping import FlankWear
from lathed.analysis.regime import Regime

# Default lathe structure: a compliant tool-post/spindle mode at 620 Hz at
# 30 deg to the surface normal, plus a stiffer one at 1450 Hz.  With
# DEFAULT_KF (medium carbon steel, specific cutting pressure ~2 GPa) the
# limiting depth is ~1.5-1.9 mm between 1500 and 2500 r/min, so the paper's
# 3 mm cut chatters and a 1 mm cut does not (tests/test_regen.py checks it).
DEFAULT_MODES: tuple[Mode, ...] = (
    Mode(620.0, 0.035, 3.0e7, 30.0),
    Mode(1450.0, 0.05, 9.0e7, 60.0),
)
DEFAULT_KF = 2.0e9          # N/m^2
DEFAULT_RATE_HZ = 51200.0   # the paper's DAQ rate
DEFAULT_NOISE_RMS = 0.2    # m/s^2, accelerometer + DAQ noise floor
DEFAULT_PROCESS_NOISE = 0.03  # relative random part of the cutting force
# Chatter is "visible" when the surface the cut leaves differs from the one
# a revolution earlier by this rms over a revolution and keeps doing so
# (see simulate_cut).  2 um is about twice the random pass-to-pass waviness
# of a stable cut near the limit in this model, and the order of the Ra
# difference chatter makes in the paper (3.6 vs 4.5 um).
VISIBLE_WAVINESS_M = 2.0e-6

_HIST = 1 << 19             # samples of surface history kept (>= 10 s at 51.2 kS/s)
DEFAULT_DIAMETER_MM = 30.0  # workpiece diameter: sets the cutting speed the flank land sees
# The flank force's amplitude is the peak normal velocity, sqrt(2) x its rms
# over about this long (several chatter periods; chatter grows over tens of
# revolutions, so the describing function's lag is negligible).
_VEL_TAU_S = 0.01


@dataclass(frozen=True)
class Wander:
    """Slow, non-repeating variation of a real stable cut (physics, not fitted to any recording).

    Three independent stationary Gauss-Markov (Ornstein-Uhlenbeck) processes,
    advanced with the material the tool has cut, so they follow the part, not
    the clock (a slow spindle wanders slowly):

    - ``kf_rel``: relative standard deviation of the cutting coefficient Kf
      along the cutting path, correlation length ``kf_path_m`` (m of helical
      path).  Bar stock of one grade varies by about +-10 HB around 200 HB
      within a bar and its segregation bands (e.g. 1045 cold drawn:
      170-210 HB across a lot); specific cutting pressure rises roughly as
      HB^0.5-0.8, so a 1-sigma of about 2 %.
    - ``depth_rel``: relative standard deviation of the actual depth of cut
      along the axis, correlation length ``depth_axial_mm`` (mm of tool
      travel): bar straightness (0.5-1 mm/m for cold-drawn bar) and the
      part's deflection changing with the tool's axial position move the
      depth by some um over a few mm of travel; 1 % of a 1 mm cut is 10 um.
      Once-per-revolution ovality and runout repeat every revolution
      (``runout_um``) and are not part of this.
    - ``noise_log``: standard deviation of the log of the random cutting
      force's intensity (the broadband part from chip segmentation, shear
      localisation, built-up-edge growth and shedding, chip curl contact),
      correlation length ``noise_path_m`` (m of cutting path).  The chip's
      form and the edge's contact state persist over many chip curls and
      then change; a 1-sigma of 20 % of the fluctuating force, whose rms is
      itself a few % of the static force (``process_noise``; Fodor, Sykora,
      Bachrathy 2020, doi:10.1007/s00170-020-05877-8, measured 4-9 % of the
      mean force in orthogonal cutting, the share varying with speed, chip
      thickness and rake: a factor of two between conditions, so +-20 %
      within one cut as the local conditions move is an assumption of the
      same order, the least constrained of the three, and the one that
      moves a detector's index most).

    Kf and depth enter the chip force only as their product Kf*b, so they
    move the cut's distance to the stability limit (near the limit, the
    regenerative amplification of the noise); the labels of ``simulate_cut``
    use that effective depth.  Tool wear over a 3 s cut (about 0.3 % of a
    15 min tool life) and the tool's warm-up (the force falls by a few %
    over the first seconds: a fall, never a rise) are left out.
    """
    kf_rel: float = 0.02
    kf_path_m: float = 1.0
    depth_rel: float = 0.01
    depth_axial_mm: float = 5.0
    noise_log: float = 0.2
    noise_path_m: float = 2.0

    def __post_init__(self) -> None:
        for k in ("kf_rel", "depth_rel", "noise_log"):
            if not 0.0 <= getattr(self, k) <= 0.5:
                raise ValueError(f"wander {k} must be in [0, 0.5], got {getattr(self, k)}")
        for k in ("kf_path_m", "depth_axial_mm", "noise_path_m"):
            if not getattr(self, k) > 0:
                raise ValueError(f"wander {k} must be > 0, got {getattr(self, k)}")


DEFAULT_WANDER = Wander()


@dataclass
class SimBlock:
    accel: np.ndarray       # m/s^2 along the normal, with sensor noise
    y_m: np.ndarray         # tool-workpiece displacement along the normal (m)
    in_cut: np.ndarray      # bool: tool removing material at that sample
    h_m: np.ndarray         # geometric chip thickness (m), <= 0 out of the cut
    theta_rad: np.ndarray   # cumulative spindle angle at each sample


class RegenerativeTurning:
    """Streaming regenerative turning model; all state is kept between ``run`` calls."""

    def __init__(self, modes=DEFAULT_MODES, kf_n_per_m2: float = DEFAULT_KF,
                 rate_hz: float = DEFAULT_RATE_HZ, noise_rms: float = DEFAULT_NOISE_RMS,
                 runout_um: float = 0.0, flat_fraction: float = 0.0, seed: int = 0,
                 process_noise: float = DEFAULT_PROCESS_NOISE, flank: FlankWear | None = None,
                 diameter_mm: float = DEFAULT_DIAMETER_MM, wander: Wander | None = None) -> None:
        if not modes:
            raise ValueError("the simulator needs at least one structural mode")
        if not kf_n_per_m2 > 0:
            raise ValueError(f"cutting coefficient Kf must be > 0 N/m^2, got {kf_n_per_m2}")
        if not rate_hz > 0:
            raise ValueError(f"sample rate must be > 0 Hz, got {rate_hz}")
        if not 0.0 <= flat_fraction < 1.0:
            raise ValueError(f"flat fraction must be in [0, 1), got {flat_fraction}")
        if noise_rms < 0 or runout_um < 0 or process_noise < 0:
            raise ValueError("noise, runout and process noise must be >= 0")
        if not diameter_mm > 0:
            raise ValueError(f"workpiece diameter must be > 0 mm, got {diameter_mm}")
        self.modes = tuple(modes)
        self.kf = float(kf_n_per_m2)
        self.rate = float(rate_hz)
        self.dt = 1.0 / self.rate
        self.noise_rms = float(noise_rms)
        self.runout_m = runout_um * 1e-6
        self.flat_fraction = float(flat_fraction)
        self.process_noise = float(process_noise)
        self.flank = flank
        self.diameter_mm = float(diameter_mm)
        self.rng = np.random.default_rng(seed)
        # the wander has its own stream, so the cut's noise draws are the same with or without it
        self.wander = wander
        self._wrng = np.random.default_rng([seed, 1])
        self._u = self._wrng.standard_normal(3)   # kf, depth, noise intensity: a random spot of the bar
        self.g_scale = 1.0                        # Kf*b over its nominal value (last block)

        m = len(self.modes)
        a = np.zeros((2 * m, 2 * m))
        b = np.zeros(2 * m)
        self._c = np.zeros(2 * m)          # displacement along the normal
        self._cv = np.zeros(2 * m)         # velocity along the normal
        for i, md in enumerate(self.modes):
            a[2 * i, 2 * i + 1] = 1.0
            a[2 * i + 1, 2 * i] = -md.wn ** 2
            a[2 * i + 1, 2 * i + 1] = -2 * md.zeta * md.wn
            b[2 * i + 1] = md.u / md.mass_kg
            self._c[2 * i] = 1.0
            self._cv[2 * i + 1] = 1.0
        self._a0 = a
        self._b = b
        # acceleration along the normal = acc_row . x + acc_gain * F
        self._acc_row = np.zeros(2 * m)
        for i, md in enumerate(self.modes):
            self._acc_row[2 * i] = -md.wn ** 2
            self._acc_row[2 * i + 1] = -2 * md.zeta * md.wn
        self._acc_gain = float(b.sum())
        self._free = Regime(a, b, 0.0, self.dt)
        # the regimes met lately: the wander moves the depth about a few dozen quantised levels
        self._cut_cache: OrderedDict[tuple[float, float], Regime] = OrderedDict()
        # flank damping is quantised to 0.25 % of the weakest mode's own
        # damping (far below what moves a limit) so regimes can be cached
        self._c_step = 0.0025 * min(2 * md.zeta * md.wn * md.mass_kg for md in self.modes)
        self._vel_ms = 0.0                  # mean square normal velocity, recent (m^2/s^2)

        self.x = np.zeros(2 * m)
        self.theta = 0.0
        self._th = np.empty(_HIST)
        self._s = np.empty(_HIST)
        self._n = 0                         # valid history samples
        self._was_cutting = False

    # -- history of the machined surface -----------------------------------------
    def _push(self, th: np.ndarray, s: np.ndarray) -> None:
        k = len(th)
        if self._n + k > _HIST:
            keep = _HIST // 2
            self._th[:keep] = self._th[self._n - keep:self._n]
            self._s[:keep] = self._s[self._n - keep:self._n]
            self._n = keep
        self._th[self._n:self._n + k] = th
        self._s[self._n:self._n + k] = s
        self._n += k

    def _surface_back(self, th: np.ndarray) -> np.ndarray:
        """Surface left one revolution earlier at these angles (0: fresh material)."""
        if self._n == 0:
            return np.zeros_like(th)
        q = th - 2 * np.pi
        lo = int(np.searchsorted(self._th[:self._n], q[0])) - 1
        lo = max(lo, 0)
        return np.interp(q, self._th[lo:self._n], self._s[lo:self._n], left=0.0)

    def _cut_regime(self, b_m: float, c_n_s_m: float = 0.0) -> Regime:
        """In-cut regime at depth b_m with extra (flank) damping c along the normal."""
        key = (b_m, c_n_s_m)
        reg = self._cut_cache.get(key)
        if reg is not None:
            self._cut_cache.move_to_end(key)
        else:
            g = self.kf * b_m
            a = self._a0 - g * np.outer(self._b, self._c) - c_n_s_m * np.outer(self._b, self._cv)
            reg = Regime(a, self._b, g, self.dt)
            if len(self._cut_cache) > 64:
                self._cut_cache.popitem(last=False)
            self._cut_cache[key] = reg
        return reg

    def _flank_terms(self, b_m: float, rpm: float, diameter_mm: float) -> tuple[float, float]:
        """Flank land's equivalent damping (quantised) and mean force at the recent amplitude."""
        v = np.pi * diameter_mm * 1e-3 * rpm / 60.0
        c, f_dc = self.flank.equivalent(b_m, v, float(np.sqrt(2.0 * self._vel_ms)))
        return round(c / self._c_step) * self._c_step, f_dc

    def _track_velocity(self, xs: np.ndarray) -> None:
        k = xs.shape[1]
        if k:
            vel = self._cv @ xs
            w = np.exp(-k * self.dt / _VEL_TAU_S)
            self._vel_ms = w * self._vel_ms + (1.0 - w) * float(vel @ vel) / k

    # -- public ------------------------------------------------------------------
    def reset(self) -> None:
        self.x[:] = 0.0
        self.theta = 0.0
        self._n = 0
        self._vel_ms = 0.0

    def run(self, n_samples: int, rpm: float, depth_mm: float, feed_mm_rev: float,
            diameter_mm: float | None = None) -> SimBlock:
        """Advance ``n_samples`` at a constant speed, depth and feed (``diameter_mm``:
        the part's, for the cutting speed the flank land sees; default the constructor's).
        A feed of 0 with a depth is a dwell: the tool stands in the work."""
        if not rpm > 0:
            raise ValueError(f"spindle speed must be > 0 r/min, got {rpm}")
        if depth_mm < 0 or feed_mm_rev < 0:
            raise ValueError("depth of cut and feed must be >= 0 mm")
        n = int(n_samples)
        b_m = depth_mm * 1e-3
        h0 = feed_mm_rev * 1e-3
        dth = 2 * np.pi * rpm / 60.0 * self.dt
        spr = 2 * np.pi / dth               # samples per revolution
        theta = self.theta + dth * np.arange(1, n + 1)   # angle at each output sample
        y = np.empty(n)
        acc = np.empty(n)
        h = np.empty(n)
        inc = np.zeros(n, dtype=bool)

        if b_m == 0.0:
            # Tool clear of the part: free vibration; the next pass meets fresh material.
            z = self._free_run(n)
            xs = (self._free.v @ z).real
            y[:] = self._c @ xs[:, 1:]
            acc[:] = self._acc_row @ xs[:, 1:]
            self.x = xs[:, -1]
            if self.flank is not None:
                self._track_velocity(xs[:, 1:])
            h[:] = 0.0
            self._push(theta, np.zeros(n))
        else:
            dia = self.diameter_mm if diameter_mm is None else float(diameter_mm)
            if not dia > 0:
                raise ValueError(f"workpiece diameter must be > 0 mm, got {dia}")
            noise = self.process_noise
            if self.wander is not None:
                g_scale, noise_scale = self._advance_wander(n * dth / (2 * np.pi), feed_mm_rev, dia)
                # quantised to 0.1 % so the regimes stay cached (far below what moves a limit)
                b_m = b_m * round(g_scale, 3)
                noise *= noise_scale
            self._run_cut(theta, n, b_m, h0, spr, y, acc, h, inc, rpm, dia, noise)

        self.theta = float(theta[-1]) if n else self.theta
        if self.noise_rms:
            acc += self.rng.normal(0.0, self.noise_rms, n)
        return SimBlock(acc, y, inc, h, theta)

    def _advance_wander(self, revs: float, feed_mm_rev: float, dia: float) -> tuple[float, float]:
        """Advance the wander over ``revs`` revolutions of cutting; (Kf*b scale, noise scale)."""
        w = self.wander
        path_m = revs * np.pi * dia * 1e-3
        corr = np.exp(-np.array([path_m / w.kf_path_m, revs * feed_mm_rev / w.depth_axial_mm,
                                 path_m / w.noise_path_m]))
        self._u = corr * self._u + np.sqrt(1.0 - corr * corr) * self._wrng.standard_normal(3)
        uk, ud, un = self._u
        self.g_scale = max(0.5, 1.0 + w.kf_rel * uk) * max(0.5, 1.0 + w.depth_rel * ud)
        return self.g_scale, float(np.exp(w.noise_log * un - 0.5 * w.noise_log ** 2))

    def _free_run(self, n: int) -> np.ndarray:
        return self._free.response(self._free.vinv @ self.x, None, n)

    def _run_cut(self, theta, n, b_m, h0, spr, y, acc, h, inc, rpm, dia, noise) -> None:
        cut = self._cut_regime(b_m)
        free = self._free
        g = self.kf * b_m
        max_chunk = max(1, min(4096, int(spr) - 1, cut.safe_len))
        chunk = max_chunk
        flat_edge = 2 * np.pi * self.flat_fraction
        pos = 0
        while pos < n:
            m = min(chunk, n - pos)
            th = theta[pos:pos + m]
            s_back = self._surface_back(th)
            geo = h0 + s_back
            if self.runout_m:
                geo = geo + self.runout_m * (np.cos(th) + 0.3 * np.cos(2 * th + 0.7))
            flat = (np.mod(th, 2 * np.pi) < flat_edge) if flat_edge else None
            y0 = float(self._c @ self.x)
            cutting = geo[0] - y0 > 0 and not (flat is not None and flat[0])
            reg = cut if cutting else free
            c_fl = f_dc = 0.0
            if cutting and self.flank is not None:
                c_fl, f_dc = self._flank_terms(b_m, rpm, dia)
                reg = self._cut_regime(b_m, c_fl)
            z0 = reg.vinv @ self.x
            if cutting:
                # force g*(w - y) - c_fl*y': the flank's mean force enters as chip
                w = geo + f_dc / g
                if noise:
                    w = w + h0 * noise * self.rng.standard_normal(m)
                z = reg.response(z0, w, m)
            else:
                z = reg.response(z0, None, m)
            xs = (reg.v @ z).real
            ys = self._c @ xs[:, :m]
            hs = geo - ys
            now = hs > 0
            if flat is not None:
                now &= ~flat
            # first sample whose regime differs from the one simulated
            bad = np.flatnonzero(now != cutting)
            # sample 0 always matches (same state, same test), so j >= 1
            j = int(bad[0]) if bad.size else m
            sl = slice(pos, pos + j)
            y[sl] = ys[:j]
            h[sl] = hs[:j]
            inc[sl] = cutting
            force = g * (w[:j] - ys[:j]) if cutting else 0.0
            if c_fl:
                force = force - c_fl * (self._cv @ xs[:, :j])
            acc[sl] = self._acc_row @ xs[:, :j] + self._acc_gain * force
            if self.flank is not None:
                self._track_velocity(xs[:, :j])
            if cutting:
                surf = ys[:j]
            else:
                surf = s_back[:j] + h0
                if flat is not None:
                    # over the flat there is no material; keep the neighbours' level
                    surf = np.where(flat[:j], ys[:j], surf)
            self._push(th[:j], surf)
            self.x = xs[:, j]
            pos += j
            # long chunks while the regime holds, short ones while it switches
            chunk = max_chunk if j == m else max(32, min(max_chunk, 4 * j))


# -- labelled recordings ---------------------------------------------------------
@dataclass(frozen=True)
class Segment:
    """A stretch of a simulated cut: speed (r/min), depth (mm), duration (s).
    The speed and the depth ramp linearly from the previous segment's over
    ``ramp_s`` (a speed change; a taper or growing stock: a depth that rises
    through the stability limit without the kick of a step).  ``flat_deg``: the
    part has no material over that angle of every revolution along this stretch
    (a flat or a keyway: an interrupted cut, no chip there).  ``modes``: the
    structure cutting (another tool after a tool change; None: the cut's own);
    a change of tool is a fresh surface for the new tool, the spindle's angle
    goes on."""
    duration_s: float
    rpm: float
    depth_mm: float
    ramp_s: float = 0.0
    flat_deg: float = 0.0
    modes: tuple | None = None


@dataclass
class Recording:
    name: str
    signal: np.ndarray          # accelerometer, m/s^2
    rate_hz: float
    rpm: np.ndarray             # spindle speed at each sample
    depth_mm: np.ndarray        # depth of cut at each sample
    y_m: np.ndarray
    in_cut: np.ndarray
    label: str                  # "chatter" or "stable"
    unstable_at_s: float | None  # first instant depth > stability limit at the speed
    visible_at_s: float | None   # first instant chatter is visible (see VISIBLE_WAVINESS_M)
    meta: dict = field(default_factory=dict)

    @property
    def duration_s(self) -> float:
        return len(self.signal) / self.rate_hz


def wav_rev(y_m: np.ndarray, theta: np.ndarray, in_cut: np.ndarray,
            rate_hz: float = DEFAULT_RATE_HZ) -> np.ndarray:
    """Pass-to-pass surface difference y(theta) - y(theta - 2 pi) at each in-cut
    sample (0 elsewhere), less a moving mean over 1/200 s so the static
    deflection step of a depth change (form, not waviness) does not count."""
    d = y_m - np.interp(theta - 2 * np.pi, theta, y_m, left=np.nan)
    d = np.where(np.isfinite(d), d, 0.0)
    k = max(1, int(rate_hz / 200))
    d = d - np.convolve(d, np.ones(k) / k, mode="same")
    return np.where(in_cut, d, 0.0)


def surface_waviness(y_m: np.ndarray, theta: np.ndarray, in_cut: np.ndarray,
                     rate_hz: float = DEFAULT_RATE_HZ) -> np.ndarray:
    """Per-sample rms over the last revolution of y(theta) - y(theta - 2 pi) over
    in-cut samples: the pass-to-pass surface difference chatter leaves.  A
    moving mean over 1/200 s is removed first, so the static deflection step
    at cut entry (form, not waviness) does not count."""
    d = wav_rev(y_m, theta, in_cut, rate_hz)
    spr = 2 * np.pi / np.maximum(np.gradient(theta), 1e-12)
    win = int(max(1, np.median(spr)))
    c = np.cumsum(np.r_[0.0, d * d])
    cnt = np.cumsum(np.r_[0, in_cut.astype(np.int64)])
    idx = np.arange(1, len(d) + 1)
    lo = np.maximum(idx - win, 0)
    return np.sqrt((c[idx] - c[lo]) / np.maximum(cnt[idx] - cnt[lo], 1))


def simulate_cut(segments, name: str = "cut", modes=DEFAULT_MODES, kf_n_per_m2: float = DEFAULT_KF,
                 rate_hz: float = DEFAULT_RATE_HZ, feed_mm_rev: float = 0.25,
                 runout_um: float = 0.0, flat_fraction: float = 0.0,
                 noise_rms: float = DEFAULT_NOISE_RMS, process_noise: float = DEFAULT_PROCESS_NOISE,
                 seed: int = 0, block: int = 512, flank: FlankWear | None = None,
                 diameter_mm: float = DEFAULT_DIAMETER_MM,
                 wander: Wander | None = DEFAULT_WANDER) -> Recording:
    """Simulate a cut made of ``Segment``s and label it.

    ``wander``: a real stable cut's slow variation (``Wander``; None: the
    stationary cut of earlier versions).  ``unstable_at_s``: first instant the
    (effective depth, speed) pair lies above the stability lobe limit (the
    effective depth: the programmed one times the wander's Kf*b scale).  ``visible_at_s``: chatter is *visible* from the
    start of the first revolution (counted from the unstable instant) whose
    rms pass-to-pass surface difference (``wav_rev``) is at least
    VISIBLE_WAVINESS_M and does not shrink (by more than 10 %) over the next
    two revolutions.  Label "chatter" iff that happens.  The lobes do not
    include the flank's damping (``flank``): it adds none to vibrations below
    its clearance (with a clearance of 0 it damps every vibration and raises
    the limit itself, so ``unstable_at_s`` is then early).
    """
    segs = [s if isinstance(s, Segment) else Segment(*s) for s in segments]
    sims: dict[tuple, RegenerativeTurning] = {}
    sim = None
    acc, ys, inc, th, rpms, deps, effs, lims = [], [], [], [], [], [], [], []
    prev_rpm, prev_depth = segs[0].rpm, segs[0].depth_mm
    for seg in segs:
        tool = tuple(modes if seg.modes is None else seg.modes)
        if tool not in sims:
            # each tool its own structure and noise stream; the first keeps the cut's seed
            sims[tool] = RegenerativeTurning(tool, kf_n_per_m2, rate_hz, noise_rms, runout_um, flat_fraction,
                                             seed + 7919 * len(sims), process_noise, flank, diameter_mm,
                                             wander)
        if sims[tool] is not sim:
            if sim is not None:
                sims[tool].reset()          # the tool change: at rest, fresh material
                sims[tool].theta = sim.theta
            sim = sims[tool]
        sim.flat_fraction = seg.flat_deg / 360.0 if seg.flat_deg else flat_fraction
        n_seg = int(round(seg.duration_s * rate_hz))
        done = 0
        while done < n_seg:
            k = min(block, n_seg - done)
            t_in = done / rate_hz
            if seg.ramp_s > 0 and t_in < seg.ramp_s:
                frac = (t_in + 0.5 * k / rate_hz) / seg.ramp_s
                rpm = prev_rpm + (seg.rpm - prev_rpm) * frac
                depth = prev_depth + (seg.depth_mm - prev_depth) * frac
            else:
                rpm, depth = seg.rpm, seg.depth_mm
            out = sim.run(k, rpm, depth, feed_mm_rev)
            acc.append(out.accel); ys.append(out.y_m); inc.append(out.in_cut)
            th.append(out.theta_rad)
            rpms.append(np.full(k, rpm)); deps.append(np.full(k, depth))
            effs.append(depth * sim.g_scale)
            lims.append((tool, rpm))
            done += k
        prev_rpm, prev_depth = seg.rpm, seg.depth_mm
    signal = np.concatenate(acc)
    y = np.concatenate(ys)
    in_cut = np.concatenate(inc)
    theta = np.concatenate(th)
    rpm_arr = np.concatenate(rpms)
    dep = np.concatenate(deps)

    # unstable where the effective depth exceeds the limit at the block's speed (and tool)
    b_lim = {}
    for tool in sims:
        speeds = np.unique([r for t, r in lims if t == tool])
        b_lim.update({(tool, r): b for r, b in zip(speeds, StabilityLobes(tool, kf_n_per_m2).b_lim_at(speeds)[0])})
    unstable = np.array(effs) * 1e-3 > np.array([b_lim[k] for k in lims])
    starts = np.cumsum([0] + [len(a) for a in acc[:-1]])
    unstable_at = float(starts[np.flatnonzero(unstable)[0]] / rate_hz) if unstable.any() else None
    visible_at = None
    if unstable_at is not None:
        i0 = int(unstable_at * rate_hz)
        # visible: per-revolution waviness (revolutions counted from the
        # unstable instant) >= the level and not shrinking over the next two
        # revolutions; the decaying mark of a depth step or entry is not chatter
        rev = int(rate_hz * 60.0 / float(rpm_arr[i0]))
        nrev = (len(y) - i0) // rev
        if nrev >= 3:
            seg = wav_rev(y, theta, in_cut, rate_hz)[i0:i0 + nrev * rev].reshape(nrev, rev)
            r = np.sqrt(np.mean(seg * seg, axis=1))
            for k in range(nrev - 2):
                if r[k] >= VISIBLE_WAVINESS_M and r[k + 1] >= 0.9 * r[k] and r[k + 2] >= 0.9 * r[k + 1]:
                    visible_at = (i0 + k * rev) / rate_hz
                    break
    return Recording(name, signal, rate_hz, rpm_arr, dep, y, in_cut,
                     "chatter" if visible_at is not None else "stable",
                     unstable_at, visible_at,
                     {"feed_mm_rev": feed_mm_rev, "runout_um": runout_um,
                      "flat_fraction": flat_fraction, "seed": seed, "flank": flank,
                      "diameter_mm": diameter_mm, "wander": wander})
