"""Cuts from a lathe whose true dynamics differ from the model it was given:
the test and benchmark data of the stability refit.

Labels come from the true model's lobes (lathed.analysis.stability.model
.limit_depth), not from running lathed.analysis.regen.simulate_cut on every
cut: a cut there takes about a second to simulate, a refit needs hundreds.
The true lobes are what the regenerative simulator converges to (tests/test_regen
checks the simulator against them), and the noise model stands for what a
single real cut adds:

* the limit a cut meets is the true limit times exp(N(0, ``boundary_sigma``))
  (tool wear, hardness and runout from cut to cut), so cuts within a few
  per cent of the limit go either way;
* the measured chatter frequency is the true one times (1 + N(0, ``freq_sigma``))
  (the frequency resolution of the detector's spectrum);
* cuts are made in random order over speed and depth (log-uniform), so the
  earlier (training) and later (held-out) cuts cover the same ground.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from lathed.analysis.cuts import Cuts
from lathed.analysis.modal import Mode
from lathed.analysis.regen import DEFAULT_KF, DEFAULT_MODES
from lathed.analysis.stability.model import StabilityModel

GIVEN = StabilityModel(DEFAULT_MODES, DEFAULT_KF)


def _dominant(m: StabilityModel) -> int:
    """The mode with the largest oriented compliance (u/k zeta)."""
    return int(np.argmax([md.u / (md.k_n_per_m * md.zeta) for md in m.modes]))


def true_dynamics(effect: str, given: StabilityModel = GIVEN) -> StabilityModel:
    """The lathe's true dynamics for one undeclared effect (``none``: as given)."""
    i = _dominant(given)
    modes = list(given.modes)
    if effect == "none":
        return given
    if effect == "natural_frequency":      # another tool holder: the dominant mode 12 % higher
        modes[i] = replace(modes[i], fn_hz=modes[i].fn_hz * 1.12)
        return replace(given, modes=tuple(modes))
    if effect == "second_mode":            # a mode the tap test missed, between the two
        b_min = 2 * modes[i].k_n_per_m * modes[i].zeta / (modes[i].u * given.kf)
        z = 0.03
        k = 0.8 * b_min * given.kf / (2 * z * (1 + z))
        return replace(given, modes=tuple(modes) + (Mode(950.0, z, k, 0.0),))
    if effect == "process_damping":        # added damping ratio 0.04 at 500 r/min
        return replace(given, process_damping=20.0)
    if effect == "cutting_coefficient":    # a harder material: Kf 45 % higher
        return replace(given, kf=given.kf * 1.45)
    raise ValueError(f"unknown undeclared effect {effect!r}")


UNDECLARED = ("natural_frequency", "second_mode", "process_damping", "cutting_coefficient")


def generate_cuts(true: StabilityModel, n: int, *, given: StabilityModel = GIVEN, seed: int = 0,
                  rpm_range: tuple[float, float] = (300.0, 6000.0),
                  depth_factor: tuple[float, float] = (0.5, 2.5),
                  boundary_sigma: float = 0.05, freq_sigma: float = 0.005,
                  material: str = "C45") -> Cuts:
    """``n`` cuts labelled by ``true``; depths span ``depth_factor`` times the
    given model's critical depth (what a user would try around it)."""
    rng = np.random.default_rng(seed)
    b_min = float(given.limit(np.geomspace(*rpm_range, 2000))[0].min())
    rpm = np.exp(rng.uniform(*np.log(rpm_range), n))
    depth = b_min * np.exp(rng.uniform(*np.log(depth_factor), n))
    b_true, f_true = true.limit(rpm)
    chatter = depth >= b_true * np.exp(boundary_sigma * rng.standard_normal(n))
    f = np.where(chatter & np.isfinite(f_true), f_true * (1 + freq_sigma * rng.standard_normal(n)), np.nan)
    return Cuts.from_arrays(np.round(rpm, 1), np.round(depth * 1e3, 4), chatter, np.round(f, 1),
                            machine="sim-lathe", tool="CNMG120408", material=material)


def simulate_labels(true: StabilityModel, cuts: Cuts, *, revolutions: float = 15.0, min_s: float = 0.3,
                    rate_hz: float = 20_000.0, seed: int = 0) -> Cuts:
    """The same cuts labelled by running each through the regenerative
    simulator (lathed.analysis.regen.simulate_cut) with the true dynamics:
    chatter when the surface waviness it leaves grows visible within
    ``revolutions`` (at least ``min_s``), the chatter frequency the spectral
    peak of the tool vibration over the cut's second half.  Counted in
    revolutions, not seconds: chatter grows per pass, so a fixed short time
    would call slow cuts stable and fake process damping.  About 0.1 s a cut
    over 300-6000 r/min; the simulator has no process damping, so that effect
    cannot be labelled this way."""
    from lathed.analysis.regen import Segment, simulate_cut
    if true.process_damping:
        raise ValueError("the regenerative simulator has no process damping: label those cuts from the lobes")
    chatter = np.zeros(len(cuts), bool)
    freq = np.full(len(cuts), np.nan)
    for i in range(len(cuts)):
        duration_s = max(min_s, revolutions * 60.0 / float(cuts.rpm[i]))
        rec = simulate_cut([Segment(duration_s, float(cuts.rpm[i]), float(cuts.depth_mm[i]))],
                           modes=true.modes, kf_n_per_m2=true.kf, rate_hz=rate_hz,
                           feed_mm_rev=float(cuts.feed_mm_rev[i]), seed=seed + i,
                           # the label of the cut as programmed: no drift of Kf*b across the limit
                           wander=None)
        if rec.label != "chatter":
            continue
        chatter[i] = True
        y = rec.y_m[len(rec.y_m) // 2:]
        spec = np.abs(np.fft.rfft((y - y.mean()) * np.hanning(len(y))))
        f = np.fft.rfftfreq(len(y), 1.0 / rate_hz)
        band = f >= 0.3 * min(m.fn_hz for m in true.modes)
        freq[i] = round(float(f[band][np.argmax(spec[band])]), 1)
    return Cuts(cuts.machine, cuts.tool, cuts.material, cuts.rpm, cuts.depth_mm, cuts.feed_mm_rev, chatter, freq,
                cuts.line, cuts.source, cuts.ignored_columns)


def random_machine(seed: int) -> tuple[StabilityModel, dict]:
    """A lathe none of the above: one or two modes (the first 120-900 Hz, damping 1.5-6 %, at
    0-45 deg; the second 2-4x higher and stiffer), Kf 1.5-3 GN/m^2, process damping on one in
    three, and its own noise (the limit's scatter 3-8 %, chatter frequencies 0.3-1 %).  For
    judging the model learned from cuts on machines it was not developed on.  Returns the
    model and generate_cuts' keyword arguments for it (depths around its own critical depth)."""
    rng = np.random.default_rng(seed)
    kf = float(rng.uniform(1.5e9, 3e9))
    fn = float(np.exp(rng.uniform(np.log(120), np.log(900))))
    z = float(rng.uniform(0.015, 0.06))
    b_min = float(np.exp(rng.uniform(np.log(0.5e-3), np.log(3e-3))))
    th = float(rng.uniform(0, 45))
    u = np.cos(np.radians(th)) ** 2
    modes = [Mode(fn, z, b_min * u * kf / (2 * z * (1 + z)) / u ** 2, th)]
    if rng.random() < 0.5:
        z2 = float(rng.uniform(0.02, 0.06))
        k2 = modes[0].k_n_per_m * float(rng.uniform(1.5, 4.0))
        modes.append(Mode(fn * float(rng.uniform(2.0, 4.0)), z2, k2, float(rng.uniform(0, 60))))
    pd = float(z * 500 * rng.uniform(0.5, 2.0)) if rng.random() < 1 / 3 else 0.0
    true = StabilityModel(tuple(modes), kf, pd)
    return true, {"given": true, "boundary_sigma": float(rng.uniform(0.03, 0.08)),
                  "freq_sigma": float(rng.uniform(0.003, 0.01))}
