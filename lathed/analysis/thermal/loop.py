"""The thermal residual loop: select the sensors, then add the effects the linear model lacks,
every choice judged forward in time; hand on the loop's model or a plain baseline, whichever
predicts later rows better. See docs/thermal.md."""
from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from lathed.analysis.forward import CONFIRM_SHARE, N_FOLDS, Scored, beats, first_row, forward_folds, improvement_z, rmse
from lathed.analysis.thermal.baselines import baseline_stages, fit_stage, judged
from lathed.analysis.thermal.candidates import Candidate, SpeedStepCandidate, builtin_candidates
from lathed.analysis.thermal.data import ROOM_REF_MIN_DT_S, ThermalData, ThermalRuns
from lathed.analysis.thermal.fit import cached_forward, design
from lathed.analysis.thermal.model import ThermalModel, eq14_model
from lathed.analysis.thermal.report import Analysis, EffectFound, Stage
from lathed.analysis.thermal.residual import residual_structure
from lathed.analysis.thermal.selection import select_sensors, usable_sensors
from lathed.analysis.thermal.terms import PeriodicTerm, Term

Rows = ThermalData | ThermalRuns

# Rows the forward folds need per fold (they cover the later half of the rows before the newest).
MIN_ROWS_PER_FOLD = 10


def min_rows(n_folds: int = N_FOLDS) -> int:
    """The fewest training rows ``analyze`` takes."""
    return math.ceil(MIN_ROWS_PER_FOLD * n_folds / (1 - CONFIRM_SHARE))

# Time constants a lag term may have: the run holds at least this many of them. A lag that never
# settles within the run is a smooth ramp there, fitted to whatever drifts slowly in this run.
_SETTLE_TAUS = 4.0
# Kinds of effect (effect and sensor) whose best proposal is re-tuned jointly with those in.
_JOINT_KINDS = 6


def _duplicate(term: Term, others: Sequence[Term]) -> bool:
    """Would ``term`` repeat one of ``others``? The same effect on the same sensor does, unless
    both are lags a factor 2 or more apart (a housing and the shaft behind it)."""
    for o in others:
        if o.effect != term.effect or o.sensor != term.sensor:
            continue
        a, b = o.params.get("tau_s"), term.params.get("tau_s")
        if a and b and max(a, b) / min(a, b) >= 2.0 and o.params.get("form") == term.params.get("form"):
            continue
        return True
    return False


def describe(term: Term) -> str:
    where = f" of {term.sensor}" if term.sensor else ""
    p = ", ".join(f"{k} {v}" for k, v in term.params.items())
    return f"{term.effect}{where}" + (f" ({p})" if p else "")


def _kind(term: Term) -> str:
    return f"{term.effect}/{term.sensor}"


class ResidualLoop:
    """Effects added to the selected sensors one at a time while one lowers the forward error by
    ``min_gain`` (relative) with a Diebold-Mariano z of ``min_z``; each time one enters, the
    parameters of those in are re-chosen with it and any it made redundant leaves."""

    def __init__(self, train: Rows, test: Rows | None, folds, cands: Sequence[Candidate], *,
                 max_effects: int, min_gain: float, min_z: float, max_sensors: int):
        self.train, self.test, self.folds = train, test, folds
        self.cands, self.makers = list(cands), {c.name: c for c in cands}
        self.max_effects, self.min_gain, self.min_z, self.max_sensors = max_effects, min_gain, min_z, max_sensors
        # few sensors are taken as read until an effect is in (see select_sensors)
        self.sensor_terms, self.notes, self.kept = select_sensors(train, folds, max_sensors, prune=False,
                                                                  filters=False)
        # Candidates see every usable sensor, kept or not: a sensor whose linear share adds
        # nothing may still carry an effect (a lag of the front bearing).
        self.view = train.select(usable_sensors(train, folds)[0])
        self.effects: list[Term] = []
        self._usable: dict[str, bool] = {}
        self.dropped: set[tuple[str, Any]] = set()
        self.gains: dict[str, tuple[float, float]] = {}
        self.max_tau_s = float(np.max(train.time_s - train.t0_s)) / _SETTLE_TAUS
        # the rows forward errors are for (residual structure is read on them)
        self.tail = train.slice(first_row(folds), len(train))
        self.e_cur = self.score([])[1]

    def usable(self, term: Term) -> bool:
        key = repr(term)
        if key not in self._usable:
            self._usable[key] = self._can_use(term)
        return self._usable[key]

    def _can_use(self, term: Term) -> bool:
        if term.params.get("tau_s", 0.0) > self.max_tau_s:
            return False
        try:
            F = design(self.train, [term])
            if self.test is not None:
                design(self.test, [term])
        except (ValueError, KeyError):
            return False       # could not be evaluated (on the test run: a sensor or the speed missing)
        return bool(np.all(np.isfinite(F)) and np.any(np.ptp(F, axis=0) > 0))

    def score(self, terms: Sequence[Term]) -> tuple[float, np.ndarray]:
        e = cached_forward(self.train, [*self.sensor_terms, *terms], self.folds)
        return rmse(e), e

    def alternatives(self, t: Term) -> list[Term]:
        """The same effect on the same sensor at its other parameters."""
        cand = self.makers.get(t.effect)
        if cand is None:
            return []
        out = [a for a in cand.propose(self.view) if a.effect == t.effect and a.sensor == t.sensor]
        return out + list(cand.refine(t))

    def tune(self, terms: list[Term], order: Sequence[int]) -> tuple[float, list[Term], np.ndarray]:
        """Re-choose each listed term's parameter with all the others fitted beside it."""
        r, e = self.score(terms)
        for i in order:
            for alt in self.alternatives(terms[i]):
                others = terms[:i] + terms[i + 1:]
                if repr(alt) == repr(terms[i]) or _duplicate(alt, others) or not self.usable(alt):
                    continue
                trial = [*terms[:i], alt, *terms[i + 1:]]
                r2, e2 = self.score(trial)
                if r2 < r:
                    r, e, terms = r2, e2, trial
        return r, terms, e

    def ranked(self, proposals: Sequence[Term], others: list[Term]) -> list[Term]:
        """Each kind's best proposal beside ``others``, best kinds first."""
        per_kind: dict[str, tuple[float, Term]] = {}
        for term in proposals:
            if _duplicate(term, others) or (term.effect, term.sensor) in self.dropped or not self.usable(term):
                continue
            r, _ = self.score([*others, term])
            if _kind(term) not in per_kind or r < per_kind[_kind(term)][0]:
                per_kind[_kind(term)] = (r, term)
        return [t for _, t in sorted(per_kind.values(), key=lambda v: v[0])]

    def step(self, proposals: Sequence[Term]) -> tuple[float, list[Term], np.ndarray] | None:
        """The best set of effects with one more: each proposal scored beside those in; for the
        best few kinds every parameter re-chosen jointly; then each term swapped for the best
        kinds ranked beside the others (a stand-in that half-explains two effects ranks the true
        ones low beside itself); last, a term the newcomer made redundant leaves."""
        top = self.ranked(proposals, self.effects)[:_JOINT_KINDS]
        if not top:
            return None
        n_in = len(self.effects)
        best = min((self.tune([*self.effects, t], [n_in, *range(n_in), n_in] if n_in else [n_in]) for t in top),
                   key=lambda f: f[0])
        r, terms, e = best
        for _ in range(2 * len(terms)):
            swapped = False
            for i in range(len(terms)):
                others = terms[:i] + terms[i + 1:]
                for term in self.ranked(proposals, others)[:_JOINT_KINDS // 2]:
                    if _kind(term) == _kind(terms[i]):
                        continue
                    found = self.tune([*terms[:i], term, *terms[i + 1:]], [i, *range(len(terms)), i])
                    if found[0] < r:
                        (r, terms, e), swapped = found, True
            if not swapped:
                break
        for i in range(len(terms) - 2, -1, -1):
            trial = terms[:i] + terms[i + 1:]
            r2, e2 = self.score(trial)
            if r2 < r:
                r, terms, e = r2, trial, e2
        return r, terms, e

    def admit(self, found) -> bool:
        r, terms, e = found
        gain, z = 1.0 - r / rmse(self.e_cur), improvement_z(self.e_cur, e)
        if gain < self.min_gain or z < self.min_z:
            return False
        self.effects[:] = terms
        self.gains[repr(terms[-1])] = (gain, z)
        self.e_cur = e
        return True

    def _sensors_again(self, prune: bool) -> None:
        terms, snotes, kept = select_sensors(self.train, self.folds, self.max_sensors, start=self.sensor_terms,
                                             fixed=self.effects, prune=prune)
        changed = [repr(t) for t in terms] != [repr(t) for t in self.sensor_terms]
        self.sensor_terms, self.kept = terms, kept
        self.notes[:] = [n for n in self.notes if not n.startswith("sensor selection kept")] + \
            [n for n in snotes if n.startswith("sensor selection kept")]
        if changed:
            self.e_cur = self.score(self.effects)[1]

    def settle(self) -> None:
        """After an effect entered: sensors whose share the missing effect hid come in, and
        effects the newcomer made redundant go."""
        newcomer = self.effects[-1]
        self._sensors_again(prune=False)
        for t in list(self.effects[:-1]):
            rest = [o for o in self.effects if o is not t]
            r, e = self.score(rest)
            if 1.0 - rmse(self.e_cur) / r < self.min_gain / 2:
                self.effects[:] = rest
                self.e_cur = e
                self.dropped.add((t.effect, t.sensor))
                self.notes.append(f"{describe(t)} dropped: once {describe(newcomer)} entered it added under "
                                  f"{100 * self.min_gain / 2:g} % forward in time")

    def structure(self) -> None:
        """Structure no library term explains, turned into a term where it has a form one can
        fit: steps at the logged speed changes, a spectral line."""
        for _ in range(3):
            if len(self.effects) >= self.max_effects + 2:
                break
            res = residual_structure(self.tail.time_s, self.e_cur, self.tail)
            if not res.structured:
                break
            if not any(t.effect == "speed_step" for t in self.effects):
                found = self.step(SpeedStepCandidate().structure(self.view))
                if found is not None and self.admit(found):
                    self.settle()
                    continue
            if res.period_s is None:
                break
            f0, df = 1.0 / res.period_s, 1.0 / float(np.ptp(self.tail.time_s))
            found = self.step([PeriodicTerm(1.0 / f) for f in f0 + df * np.linspace(-0.5, 0.5, 11) if f > 0])
            if found is None or not self.admit(found):
                self.notes.append(f"a periodicity of {res.period_s / 60:.1f} min is left in the residual, but a "
                                  f"periodic term at it does not lower the forward error enough to keep")
                break
            self.settle()

    def run(self) -> None:
        while len(self.effects) < self.max_effects:
            found = self.step([t for c in self.cands for t in c.propose(self.view)])
            if found is None or not self.admit(found):
                break
            self.settle()
        self.structure()
        res = residual_structure(self.tail.time_s, self.e_cur, self.tail)
        if res.structured:
            self.notes.append("not modelled: " + res.note)
        self._sensors_again(prune=True)     # let go of sensors that add nothing with the effects in
        # In the order of what they carry: chosen jointly, the order they entered in says little.
        if len(self.effects) > 1:
            without = {repr(t): self.score([o for o in self.effects if o is not t])[0] for t in self.effects}
            self.effects.sort(key=lambda t: -without[repr(t)])


def analyze(train: Rows, test: Rows | None = None, *,
            candidates: Sequence[Candidate] | None = None, extra_candidates: Sequence[Candidate] = (),
            max_effects: int = 4, n_folds: int = N_FOLDS, min_gain: float = 0.05, min_z: float = 2.0,
            max_sensors: int = 8, current: ThermalModel | None = None) -> Analysis:
    """Select the sensors and run the residual loop on the earlier training rows (every choice
    judged on forward folds of them), fit the plain baselines beside it on the same rows, and judge
    them all on the newest training rows (``CONFIRM_SHARE``, rows no choice was made on): the
    selected model is handed on only if it beats the best baseline there (``beats``), else that
    baseline is; either refitted on every training row. ``test`` (later rows, or another
    run) is only reported on, beside the paper's eq. 14 and ``current``."""
    if train.displacement_um is None:
        raise ValueError("training data has no displacement_um to fit")
    n = len(train)
    cut = int(round(n * (1 - CONFIRM_SHARE)))
    if cut < MIN_ROWS_PER_FOLD * n_folds:
        raise ValueError(f"{n} rows are too few for {n_folds} forward folds on the first "
                         f"{100 * (1 - CONFIRM_SHARE):g} % (need at least {min_rows(n_folds)})")
    folds = forward_folds(cut, n_folds)
    cands = list(builtin_candidates() if candidates is None else candidates) + list(extra_candidates)
    loop = ResidualLoop(train.slice(0, cut), test, folds, cands, max_effects=max_effects, min_gain=min_gain,
                        min_z=min_z, max_sensors=max_sensors)
    notes = loop.notes
    if train.rises_from is not None:
        notes.insert(0, f"rows are over {ROOM_REF_MIN_DT_S:g} s apart: every rise is taken from the room's "
                        f"temperature at the start ({train.rises_from}, a line through its first hour), not "
                        f"from each sensor's first reading (a run that starts at speed has warmed by then)")
    start = fit_stage(train, loop.sensor_terms, test, cut, f"linear on {len(loop.sensor_terms)} selected sensor(s)",
                      notes)
    loop.run()
    sensor_terms = loop.sensor_terms
    # chosen on the earlier rows, fitted on them all
    loop.effects = [loop.makers[t.effect].for_rows(t, train) if t.effect in loop.makers else t for t in loop.effects]
    found: list[EffectFound] = []
    stage = fit_stage(train, sensor_terms, test, cut, "", notes)
    for k, t in enumerate(loop.effects):
        stage = fit_stage(train, [*sensor_terms, *loop.effects[:k + 1]], test, cut, "", notes)
        g, z = loop.gains.get(repr(t), (0.0, 0.0))
        found.append(EffectFound(t, stage, g, z))
    stage.label = (f"selected: {len(sensor_terms)} sensor(s) and {len(loop.effects)} effect(s), "
                   f"{len(stage.model.names)} term(s)")
    baselines = baseline_stages(train, test, cut, folds)
    final = hand_on(stage, baselines, min_gain, n_folds, notes)
    newest = train.slice(cut, n)
    if test is not None:
        res = residual_structure(test.time_s, test.displacement_um - final.model.predict(test), test)
        judged_on = f"the test rows ({len(test)})"
    else:
        # what the model handed on leaves over the whole run
        res = residual_structure(train.time_s, train.displacement_um - final.model.predict(train), train)
        judged_on = f"the newest {n - cut} training rows, fitted on the {cut} before them"
    forward_on = f"the newest {n - cut} of {n} training rows, fitted on the {cut} before them"
    comparison = _comparison(newest, test, current, [start, stage, *baselines], final)
    return Analysis(start, found, stage, final, baselines, res, notes, comparison, loop.kept, judged_on,
                    forward_on)


def baseline_handed_on(baselines: Sequence[Stage]) -> Stage:
    """The baseline ``hand_on`` hands on when the selected model loses: the least error over the
    later half of the training rows."""
    return min(baselines, key=lambda s: s.rolling_rmse_um)


def hand_on(stage: Stage, baselines: Sequence[Stage], min_gain: float, n_folds: int, notes: list[str]) -> Stage:
    """The model ``analyze`` hands on: ``stage`` (the selected model) or a baseline.

    The baseline is the one with the least error over the later half of the training rows. The
    selected model came out of a search over thousands of variants and will fit some folds by
    chance, so it is judged only on the newest rows, which no choice saw: it replaces the
    baselines only when it beats the best of them there by as much as an effect must, and
    consistently so across them, as a sensor must to enter."""
    best = baseline_handed_on(baselines)
    rival = min(baselines, key=lambda s: s.forward_rmse_um)
    verdict = beats(rival.forward_errors, stage.forward_errors, min_gain, n_folds)
    if verdict.better:
        return stage
    notes.append(f"{best.label} is the model, the baseline with the least error over the later half "
                 f"of the training rows ({best.rolling_rmse_um:.2f} µm): on the newest training rows the "
                 f"selected model ({stage.forward_rmse_um:.2f} µm) does not beat {rival.label} "
                 f"({rival.forward_rmse_um:.2f} µm) by {100 * min_gain:g} % consistently ({verdict.why()})")
    return best


def _comparison(newest: Rows, test: Rows | None, current: ThermalModel | None, stages: Sequence[Stage],
                final: Stage) -> list[Scored]:
    """Every model on the same rows: fitted ones with their forward and later errors; fixed ones
    (the paper's, the model in use) predicted on the newest training rows and the later rows."""
    later_rows = test if test is not None else newest
    eq14 = eq14_model()
    eq14.intercept_um = 0.0
    out = []
    for label, model in (("paper eq. 14 (intercept dropped: growth from the cold start)", eq14),
                         *((("current model", current),) if current is not None else ())):
        miss = [s for s in model.sensors if s not in later_rows.temps_c]
        out.append(Scored(label, None if miss else judged(model, newest), None if miss else judged(model, later_rows),
                          note=f"needs {', '.join(miss)}" if miss else ""))
    for s in stages:
        sc = s.scored()
        if s is final:
            sc.note = "handed on"
        out.append(sc)
    return out
