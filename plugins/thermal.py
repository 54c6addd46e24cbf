"""Thermal compensation: predict the spindle's growth from live temperatures and
write it to the CNC as an X offset (numeric core: lathed.analysis.thermal).

    [analyzer.thermal]
    plugin = "thermal"
    input = "temps"            # the temperature sensor instance (t_<place> samples)
    machine = "lathe"          # spindle speed, probe results, and where the offset goes
    model = ""                 # a model TOML; default: the newest saved fit, else the paper's eq. 14
    tolerance_um = 2.0         # act when the offset lags the prediction by more than this
    rate_um_s = 2.0            # phase the offset in at most this fast
    step = "1s"                # how often the prediction is evaluated
    sign = -1.0                # -1 or 1: offset = sign * growth since the tool was touched off
    stale_after = "20s"        # a temperature older than this holds the offset (asks nothing)
    growth_rate_max_um_s = 1.0 # predicted growth moving faster is a sensor fault: the offset holds

The growth is compensated since the tool was touched off. The touch-off (the
temperatures, time and speed of that moment, the prediction then, and the
offset then in force) is stored as a ``thermal_touchoff`` record. On the
very first start the spindle is assumed cold and touched off at the first
full set of readings: those temperatures are the model's cold reference
(rises are taken from them, as in the fit) and that time starts its drift
clock. ``lathectl thermal touchoff`` says the operator touched off again,
perhaps warm: the cold reference stays (a rise squared or a bearing's
hysteresis depends on it), the prediction of that moment becomes the zero
and the offset in force the new base. A restarted daemon goes on from the
stored touch-off instead of taking a warm spindle for a cold one.
Nothing is written until the machine has reported the offset it holds
(``offset_x_um``), so phasing always starts from the real value. Each probe result the
machine reports (``probe_seq`` changing) is stored as a
``thermal_measurement`` with the temperatures of the moment; ``lathectl
thermal refit`` runs the residual loop on them, keeps the new model only if
it is better on the newest, held-out part of the data, saves it as a new
version (TOML) and records before/after.
"""
from __future__ import annotations

import asyncio
import functools
import math
import pickle
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from lathed import hookimpl
from lathed.analysis.compensation_hold import CompensationHold
from lathed.analysis.thermal import ThermalData, ThermalRuns, eq14_model, load_model, refit, save_model
from lathed.analysis.thermal.loop import min_rows
from lathed.analysis.thermal.start import cold_again
from lathed.analyzer import Analyzer
from lathed.args import Args
from lathed.caller import require_operator
from lathed.bus import Sample
from lathed.command import Command
from lathed.config import Section
from lathed.control import RequestError, offload
from lathed.worker import in_process


# refit() analyses all but the newest 20 %, and analyze() needs min_rows() of those.
REFIT_HOLDOUT = 0.2
MIN_REFIT_ROWS = math.ceil(min_rows() / (1 - REFIT_HOLDOUT))


class ThermalAnalyzer(Analyzer):
    def __init__(self, name: str, section: Section):
        super().__init__(name, section)
        self.input = section.getstr("input")
        self.machine = section.getstr("machine")
        self.model_path = section.getstr("model", "")
        self.tolerance = section.getfloat("tolerance_um", 2.0, above=0, maxval=1000)
        self.rate = section.getfloat("rate_um_s", 2.0, above=0, maxval=1000)
        self.step = section.getduration("step", 1.0, minval=0.05, maxval=600)
        self.sign = section.getfloat("sign", -1.0, minval=-1.0, maxval=1.0)
        if self.sign not in (-1.0, 1.0):
            # the offset's direction against the growth; 0.3 would compensate 30 % without a word
            raise section.error("sign", f"expected -1 or 1 (the offset's direction against the growth), "
                                        f"got {self.sign:g}")
        # what the compensation must not act on: stale readings, a growth no spindle makes (docs/safety.md)
        self.hold = CompensationHold(section.getduration("stale_after", 20.0, minval=0.1, maxval=3600),
                                     section.getfloat("growth_rate_max_um_s", 1.0, above=0, maxval=10_000),
                                     self.step, self.tolerance)
        self.held: str | None = None
        self._held_kind: str | None = None
        self._read_at: dict[str, float] = {}     # place -> time of its last reading
        if self.model_path:
            p = Path(self.model_path)
            if not p.is_absolute():
                p = Path(section.file).parent / p
            try:
                self.model = load_model(p)
            except (OSError, ValueError, KeyError) as e:
                raise section.error("model", f"cannot load thermal model {p}: {e}") from None
            self.model_name = p.name
        else:
            self.model, self.model_name = eq14_model(), "eq14"
        self.temps: dict[str, float] = {}
        self.rpm: float | None = None
        self.prediction: float | None = None
        self.pred0: float | None = None
        self.touchoff: dict | None = None
        self.applied: float | None = None      # the offset the machine reports holding
        self.target: float = 0.0
        self.writes = 0
        self.refused: str | None = None
        self.last_refit: dict | None = None
        self._refitting = False     # one refit at a time: each reads every probe row and writes thermal-vN
        self._probe_seq: float | None = None
        self._probe_value: float | None = None
        self._phasing = False
        self._predictor = None
        self._restored = False      # a stored touch-off taken up at start: is the machine cold again?
        self._read: dict = {"temps_c": None, "rpm": None}     # the readings the prediction is from

    def inputs(self) -> list[str]:
        return [self.input, self.machine]

    def machines(self) -> list[str]:
        return [self.machine]

    def offset_pace(self) -> tuple[float, float]:
        """The most the offset moves: per write (rate x step) and per second."""
        return self.rate * self.step, self.rate

    def refers(self) -> dict[str, tuple[str, str, str | None]]:
        # the offset is not needed: on a read-only machine (MTConnect) the analyzer predicts only
        return {"input": (self.input, "sensor", "temperature")}

    @property
    def models_dir(self) -> Path:
        return self.ctx.store.path.parent / "thermal-models"

    def _candidates(self) -> list:
        try:
            return self.ctx.plugins.thermal_candidates() if self.ctx.plugins else []
        except Exception as e:   # a broken plugin candidate must not stop compensation
            self.ctx.log.error("thermal_candidates_failed", error=str(e))
            return []

    def _load_newest(self) -> None:
        if self.model_path or not self.models_dir.is_dir():
            return
        versions = sorted(self.models_dir.glob("thermal-v*.toml"), key=lambda p: int(p.stem.split("-v")[1]))
        for i, path in enumerate(reversed(versions)):
            try:
                self.model = load_model(path, self._candidates())
            except (OSError, ValueError, KeyError, TypeError) as e:
                # a damaged file (a disk fault, a hand edit): the previous version, said loudly
                older = versions[-2 - i].name if i + 1 < len(versions) else "eq14"
                self.ctx.log.error("thermal_model_unreadable", file=path.name, error=str(e), using=older)
                self.ctx.record("thermal_model_unreadable", {"file": path.name, "error": str(e),
                                                             "using": older})
                continue
            self.model_name = path.name
            return

    async def run(self) -> None:
        self.ctx.register_control("thermal", self._control)
        self._load_newest()
        self._restore_touchoff()
        sub = self.ctx.bus.subscribe(self.input, self.machine, maxsize=4096, name=self.name)
        ticker = asyncio.create_task(self._tick())
        try:
            while True:
                s = await sub.get()
                if not isinstance(s, Sample):
                    continue
                if s.source == self.input and s.quantity.startswith("t_"):
                    self.temps[s.quantity[2:]] = s.value
                    self._read_at[s.quantity[2:]] = s.t
                elif s.source == self.machine:
                    if s.quantity == "spindle_rpm":
                        self.rpm = s.value
                    elif s.quantity == "offset_x_um":
                        self.applied = s.value
                    elif s.quantity == "probe_seq":
                        if self._probe_seq is not None and s.value != self._probe_seq:
                            self._measured()
                        self._probe_seq = s.value
                    elif s.quantity == "probe_displacement_um":
                        self._probe_value = s.value
        finally:
            ticker.cancel()
            self.ctx.bus.unsubscribe(sub)

    def _measured(self) -> None:
        value = self._probe_value
        if value is None or not self.temps:
            return
        m = {"machine": self.machine, "t": time.time(), "displacement_um": value, "rpm": self.rpm,
             "temps_c": dict(self.temps)}
        if self.touchoff is not None:   # the reference the live prediction takes its rises from
            m["cold_c"], m["cold_t"] = self.touchoff["cold_c"], self.touchoff["cold_t"]
        self.ctx.record("thermal_measurement", m)

    # -- touch-off ----------------------------------------------------------------
    def _restore_touchoff(self) -> None:
        rows = self.ctx.store.events(limit=1, kind="thermal_touchoff", source=self.name)
        if rows:
            t = rows[0]["payload"]
            if t.get("machine") == self.machine:
                self.touchoff = t
                self._restored = True
                self._rebuild()

    def _touch_off(self, reason: str, base_um: float, by: str | None = None) -> None:
        now = time.time()
        prev = self.touchoff
        to = {"machine": self.machine, "t": now, "temps_c": dict(self.temps), "rpm": self.rpm,
              "base_um": base_um, "reason": reason, "by": by,
              # the model's cold reference: kept from the first start
              "cold_c": dict(prev["cold_c"]) if prev else dict(self.temps),
              "cold_t": prev["cold_t"] if prev else now,
              "cold_rpm": self._cold_rpm() if prev else self.rpm,
              "model": self.model_name, "pred0_um": None}
        if prev is not None and self._predictor is not None:
            # the live prediction, with the state of lagging and hysteretic terms
            to["pred0_um"] = self._predictor.update(self.temps, self.rpm, now)
        self.touchoff = to
        self.hold.reset()       # the operator's touch-off takes the growth of now as it is
        self.ctx.record("thermal_touchoff", to)
        if to["pred0_um"] is not None:
            self.pred0 = to["pred0_um"]     # same model and predictor: only the zero moves
            # the status says so at once, not the last step's target until the next step
            self.prediction, self.target = self.pred0, base_um
        else:
            self._rebuild()

    def _take_up(self) -> None:
        """At the first full set of readings: touch off on a first start; after a restart, a
        machine that is cold again starts a new run."""
        if self.touchoff is None:
            self._touch_off("first start: spindle assumed cold, tool touched off", 0.0)
        elif self._restored:
            self._restored = False
            # the rpm of the stored cold start: the first touch-off's (a cold start takes its own)
            if cold_again(self.touchoff["cold_c"], self.temps, self._cold_rpm(), self.rpm):
                self._cold_start()

    def _cold_rpm(self) -> float | None:
        """The spindle speed when the stored cold start was taken (None: not known)."""
        to = self.touchoff
        return to.get("cold_rpm", to.get("rpm") if to.get("cold_t") == to.get("t") else None)

    def _cold_start(self) -> None:
        """Started on a machine that is cold again (another day): rises and the drift clock from
        now, a run of its own for the refit. The offset goes on from what it would be on the
        cold machine under the stored touch-off: the growth since then is the model's cold
        prediction less the prediction at the touch-off."""
        now, prev = time.time(), self.touchoff
        p_cold = self.model.predictor(self.temps, now).update(self.temps, self.rpm, now)
        base = prev["base_um"] + self.sign * (p_cold - (self.pred0 if self.pred0 is not None else p_cold))
        to = {"machine": self.machine, "t": now, "temps_c": dict(self.temps), "rpm": self.rpm, "base_um": base,
              "reason": "cold start: the machine's sensors agree with each other again, a new run",
              "by": None, "cold_c": dict(self.temps), "cold_t": now, "cold_rpm": self.rpm, "model": self.model_name,
              "pred0_um": p_cold}
        self.touchoff = to
        self.ctx.record("thermal_touchoff", to)
        self._rebuild()

    def _rebuild(self) -> None:
        """Predictor and zero for the current model from the stored touch-off:
        the growth is the model's prediction now less its prediction at the
        touch-off (rises from the cold reference in both)."""
        to = self.touchoff
        cold, cold_t = to["cold_c"], to["cold_t"]
        lacking = [p for p in self._sensor_places() if p not in cold or p not in to["temps_c"]]
        if lacking:
            self._predictor = self.pred0 = None
            self.refused = (f"the touch-off of {time.strftime('%F %T', time.localtime(to['t']))} has no reading "
                            f"of {', '.join(lacking)}, which model {self.model_name} needs: touch the tool off "
                            f"again and run `lathectl thermal touchoff`")
            return
        self._predictor = self.model.predictor(cold, cold_t)
        if to.get("pred0_um") is not None and to.get("model") == self.model_name:
            self.pred0 = to["pred0_um"]
        else:   # another model since (or the cold start itself): its prediction, settled at the touch-off
            self.pred0 = self.model.predictor(cold, cold_t).update(to["temps_c"], to["rpm"] or 0.0, to["t"])
        self.prediction = None      # until the next step: the last one was another model's
        self.hold.reset()

    async def _tick(self) -> None:
        while True:
            await asyncio.sleep(self.step)
            if not all(k in self.temps for k in self._sensor_places()):
                continue
            stale = self.hold.stale(self._read_at, self._sensor_places(), time.time())
            if stale is not None:       # nothing predicted from them, nothing asked
                self._hold(stale, "stale")
                continue
            self._take_up()
            if self._predictor is None or self.applied is None:
                continue
            try:
                pred = self._predictor.update(self.temps, self.rpm, time.time())
            except ValueError as e:
                self.ctx.log.warning("thermal_prediction_failed", error=str(e))
                continue
            self.prediction, self._read = pred, {"temps_c": dict(self.temps), "rpm": self.rpm}
            self.ctx.bus.publish(Sample(self.name, "predicted_growth_um", pred - self.pred0, "µm", time.time()))
            self._hold(self.hold.judge(pred - self.pred0, time.time()), "growth")
            if self.held is not None:
                continue
            self.target = self.touchoff["base_um"] + self.sign * (pred - self.pred0)
            gap = self.target - self.applied
            # hysteresis: start phasing in past the tolerance, stop once caught up
            if abs(gap) > self.tolerance:
                self._phasing = True
            if not self._phasing or abs(gap) < 0.1:
                self._phasing = False
                continue
            held = self.ctx.interlock(self.machine, "offset_x_um")
            if held is not None:         # a thread being cut: phased in after it, not asked in vain
                self.refused = held
                continue
            # phase in: never more than rate * step per write
            move = math.copysign(min(abs(gap), self.rate * self.step), gap)
            value = round(self.applied + move, 2)
            r = await self.ctx.command(Command(self.machine, "offset_x_um", value, self.name,
                                               reason="thermal compensation"))
            if r["sent"]:
                self.applied, self.writes, self.refused = value, self.writes + 1, None
                self.ctx.bus.publish(Sample(self.name, "compensation_um", value, "µm", time.time()))
                self.ctx.record("compensation", {"machine": self.machine, "predicted_um": pred - self.pred0,
                                                 "offset_um": value, "target_um": self.target,
                                                 "model": self.model_name})
            else:
                self.refused = r["reason"]

    def _hold(self, why: str | None, kind: str = "") -> None:
        """Hold the offset (``why``; ``kind``: stale or growth) or act again (None); each change
        recorded once, not each step."""
        said = self._held_kind
        self.held, self._held_kind = why, (kind if why is not None else None)
        if self._held_kind == said:
            return
        payload = {"machine": self.machine, "offset_um": self.applied}
        if why is not None:
            self.ctx.log.warning("thermal_held", why=why, **payload)
            self.ctx.record("thermal_held", {**payload, "why": why})
        else:
            self.ctx.log.info("thermal_resumed", **payload)
            self.ctx.record("thermal_resumed", {**payload, "held": said})

    def _sensor_places(self) -> list[str]:
        return [s[2:-2] if s.startswith("t_") and s.endswith("_c") else s for s in self.model.sensors]

    # -- refit -----------------------------------------------------------------------
    def _measurements(self) -> ThermalData | ThermalRuns:
        pts = [r["payload"] for r in self.ctx.store.events(limit=None, kind="thermal_measurement",
                                                           source=self.name)]
        if len(pts) < MIN_REFIT_ROWS:
            raise RequestError(f"only {len(pts)} probe measurements stored; a refit needs at least {MIN_REFIT_ROWS}")
        places = sorted(set.intersection(*(set(p["temps_c"]) for p in pts)))
        # Rows since one cold start form a run: rises and drift hours from that start's
        # temperatures and time, as the live prediction takes them; lag and hysteresis
        # start afresh in each. Rows stored without it (before touch-offs were stored)
        # are one run from their own start.
        groups: dict[object, list[dict]] = {}
        for p in pts:
            cold = p.get("cold_c")
            key = p["cold_t"] if cold is not None and all(k in cold for k in places) else None
            groups.setdefault(key, []).append(p)
        runs = [self._run(g, places, cold_t) for cold_t, g in groups.items()]
        runs.sort(key=lambda r: r[0])
        return runs[0][1] if len(runs) == 1 else ThermalRuns([r for _, r in runs])

    @staticmethod
    def _run(g: list[dict], places: list[str], cold_t: float | None) -> tuple[float, ThermalData]:
        t = np.array([p["t"] for p in g])
        temps = {f"t_{k}_c": np.array([p["temps_c"][k] for p in g]) for k in places}
        disp = np.array([p["displacement_um"] for p in g])
        rpm = np.array([p["rpm"] or 0.0 for p in g])
        if cold_t is None:
            return float(t[0]), ThermalData(t - t[0], temps, disp, rpm)
        cold = g[0]["cold_c"]
        return float(t[0]), ThermalData(t - cold_t, temps, disp, rpm,
                                        reference_c={f"t_{k}_c": float(cold[k]) for k in places}, t0_s=0.0)

    async def _refit(self) -> tuple[dict, object]:
        data = await offload(self._measurements)
        # The daemon applies each model as growth since touch-off; judge the printed eq. 14 the
        # same way, without the intercept it carries from the paper's machine (-222 µm), or any
        # refit would look "better".
        current = replace(self.model, intercept_um=0.0) if self.model.source == "eq14" else self.model
        job = functools.partial(refit, data, current=current, holdout_fraction=REFIT_HOLDOUT,
                                extra_candidates=self._candidates())
        try:
            # a process: a minute of numpy in small steps on a thread holds the GIL from the loop
            res = await in_process(job, "lathed-thermal-refit")
        except ValueError as e:     # data the residual loop cannot use: say so, keep the model
            raise RequestError(f"refit failed on {len(data)} probe measurements: {e}") from None
        except (pickle.PicklingError, AttributeError, TypeError) as e:
            if "pickle" not in str(e):
                raise
            raise RequestError(f"refit: a thermal candidate plugin cannot be sent to the refit process ({e}): "
                               f"define its Candidate and Term classes at module level") from None
        ls = res.least_squares_rmse_um
        out = {"before_rmse_um": round(res.before_rmse_um, 3), "after_rmse_um": round(res.after_rmse_um, 3),
               "least_squares_rmse_um": None if ls is None else round(ls, 3),
               "baselines_rmse_um": {k: round(v, 3) for k, v in res.baselines_rmse_um.items()},
               "handed_on": res.label, "why": res.why,
               "better": res.better, "rows": len(data), "model_before": self.model_name,
               "effects": [{"effect": e.term.effect, "sensor": e.term.sensor} for e in res.analysis.effects],
               # what each kept sensor carries: a user with many sensors sees which matter
               "sensors": [k.to_json() for k in res.analysis.sensors],
               "residual": res.analysis.residual.note}
        out["model_after"] = (await offload(self._save, res, len(data))) if res.better else self.model_name
        return out, res

    def _save(self, res, rows: int) -> str:
        """A new version of the model in the state directory; its file name."""
        self.models_dir.mkdir(parents=True, exist_ok=True)
        n = 1 + max((int(p.stem.split("-v")[1]) for p in self.models_dir.glob("thermal-v*.toml")), default=0)
        path = self.models_dir / f"thermal-v{n}.toml"
        save_model(res.model, path, meta={"created": time.time(), "rows": rows, "before_rmse_um": res.before_rmse_um,
                                          "after_rmse_um": res.after_rmse_um})
        return path.name

    async def _control(self, args: dict) -> dict:
        a = Args("thermal", args)
        action = a.getstr("action", "status", choices=("status", "refit", "touchoff"))
        by = a.getstr("by", None)     # who touched off, for the record (the operator view sends its user)
        a.check_unused()
        if action == "status":
            return self.status()
        require_operator(f"thermal {action}")
        if action == "touchoff":
            missing = [p for p in self._sensor_places() if p not in self.temps]
            if missing:
                raise RequestError(f"no reading yet from {', '.join(missing)}: cannot take the touch-off temperatures")
            stale = self.hold.stale(self._read_at, self._sensor_places(), time.time())
            if stale is not None:
                raise RequestError(f"cannot take the touch-off temperatures: {stale.split(':')[0]}")
            if self.applied is None:
                raise RequestError(f"{self.machine} has not reported its offset_x_um yet: cannot take the touch-off")
            self._touch_off("operator touched the tool off", self.applied, by)
            return self.status()
        if self._refitting:
            raise RequestError("thermal: a refit is already running; wait for its result")
        self._refitting = True
        try:
            out, res = await self._refit()
        finally:
            self._refitting = False
        if res.better:
            # the new model's growth since the same touch-off; any step is phased in
            self.model, self.model_name = res.model, out["model_after"]
            if self.touchoff is not None:
                self._rebuild()
        out["by"] = by
        self.last_refit = out
        self.ctx.record("thermal_refit", out)
        return out

    def status(self) -> dict:
        growth = None if self.prediction is None or self.pred0 is None else round(self.prediction - self.pred0, 2)
        to = self.touchoff
        since = "no touch-off yet" if to is None else \
            f"since touch-off {time.strftime('%F %T', time.localtime(to['t']))}"
        offset = f"offset {self.applied:g} µm" if self.applied is not None else \
            f"waiting for {self.machine}'s offset_x_um"
        return {"model": self.model_name, "predicted_growth_um": growth, "target_offset_um": round(self.target, 2),
                "applied_offset_um": self.applied, "writes": self.writes, "refused": self.refused, "held": self.held,
                "touchoff": None if to is None else {k: to[k] for k in ("t", "base_um", "reason")},
                "last_refit": self.last_refit, "refitting": self._refitting, **self._read,
                "summary": f"model {self.model_name}, growth {growth} µm {since}, {offset}"}


@hookimpl
def lathed_analyzer_types():
    return {"thermal": ThermalAnalyzer}
