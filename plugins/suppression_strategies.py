"""Suppression's strategies: one class per value of ``strategy``, each reading its own keys
(docs/chatter.md, docs/configuration.md). The analyzer in suppression.py picks one and
composes it with what every strategy shares: the guard, remembered cures, modes, records."""
from __future__ import annotations

import asyncio
import time
from dataclasses import replace
from typing import Awaitable, Callable

import numpy as np

from lathed.analysis.lobes import StabilityLobes
from lathed.analysis.speed_selection import (WHEN_NO_STABLE_SPEED, Advice, Cut, Decision, FrequencySelection,
                                             LobeSelection, RatedSpeed, SpindleLimits, SuppressionPolicy,
                                             VariationSelection, lobe_policy, model_free_policy, reach)
from lathed.analysis.speed_variation import KINDS, SpeedVariation
from lathed.config import Section

SSV_STEP_S = 0.05     # speed commands while modulating


class Strategy:
    """What the analyzer asks of a strategy. ``keys``: the keys it reads beside the shared ones;
    a key of another strategy in the table is refused (``check_keys``)."""
    name = ""
    keys: tuple[str, ...] = ()
    predicts = False          # may act at cut entry on the lobes' prediction (``avoid``)
    learns = False            # without ``modes``, learns a model from the cut records
    when_no_stable_speed: str | None = None

    def __init__(self, section: Section):
        self.limits = spindle_limits(section)
        self.settle_revs = section.getfloat("settle_revs", 20.0, minval=0, maxval=1000)
        self.max_speed_ratio = section.getfloat("max_speed_ratio", 1.3, minval=1.0, maxval=10.0)
        self.avoid = section.getbool("avoid", False)
        if self.avoid and not self.predicts:
            raise section.error("avoid", 'predicting chatter at cut entry needs strategy = "lobes" (and its modes)')

    def policy(self, cut: Cut, rpm: float | None, lobes: StabilityLobes | None, grid,
               depth_known: bool) -> SuppressionPolicy:
        """A new cut's policy. ``rpm``: the programmed speed; ``lobes``: the model for this cut's
        tool, or None; ``depth_known``: the depth is measured or programmed."""
        raise NotImplementedError

    def depth_changed(self, policy: SuppressionPolicy, cut: Cut, modelled: bool) -> None:
        """The depth became known, or changed, within a cut: the policy goes on (bans, budget,
        the lobes it began with) with that depth."""
        policy.strategy = replace(policy.strategy, cut=cut)
        if policy.fallback is not None:
            policy.fallback = replace(policy.fallback, cut=cut)

    def predicted(self, policy: SuppressionPolicy, grid, rpm: float, depth_mm: float) -> Decision | Advice | None:
        """At cut entry (with ``avoid``): a move when the model calls the programmed speed unstable."""
        return None

    def modulate(self, d: Decision, send: Callable[[float, str], Awaitable[bool]]) -> None:
        """A decision that modulates the speed was sent: keep modulating (variation only)."""

    def stop(self) -> None:
        """The cut ended or suppression was switched off: stop whatever runs."""

    def _within(self, rpm: float | None) -> SpindleLimits:
        return reach(self.limits, rpm, self.max_speed_ratio)


def spindle_limits(section: Section) -> SpindleLimits:
    """The spindle's envelope, which every strategy selects within."""
    max_rpm = section.getfloat("max_rpm", 6000.0, above=0)
    lim = SpindleLimits(
        max_rpm=max_rpm,
        min_rpm=section.getfloat("min_rpm", 100.0, minval=0),
        peak_torque_nm=section.getfloat("peak_torque_nm", 35.8, above=0),
        # the default at most the top speed: a slow spindle's max_rpm alone is not an error
        base_rpm=section.getfloat("base_rpm", min(1500.0, max_rpm), above=0),
        accel_rpm_per_s=section.getfloat("accel_rpm_s", 3000.0, above=0))
    if lim.min_rpm >= lim.max_rpm:      # no speed would be within reach: every alarm exhausted
        raise section.error("min_rpm", f"{lim.min_rpm:g} r/min is not below max_rpm {lim.max_rpm:g} r/min")
    if lim.base_rpm > lim.max_rpm:
        # the torque is flat up to base_rpm: above max_rpm it only inflates the power, which no
        # speed in reach uses, so the number would be taken and mean nothing (or be a swap)
        raise section.error("base_rpm", f"{lim.base_rpm:g} r/min is above max_rpm {lim.max_rpm:g} r/min; "
                                        "a spindle with its peak torque over its whole range (constant "
                                        "torque) has base_rpm = max_rpm")
    return lim


def predicted_unstable(grid, rpm: float, depth_mm: float) -> tuple[bool, float]:
    """The lobes' verdict on a cut: (unstable, worst b_lim in mm within +-3 % of ``rpm``)."""
    n, _, worst = grid
    w = float(np.interp(rpm, n, worst))
    return w < LobeSelection.margin * depth_mm / 1000, w * 1000


def _rated_rpm(section: Section) -> float:
    return section.getfloat("rated_rpm", 750.0, above=0)


class FrequencyStrategy(Strategy):
    """Revolution frequency at the chatter frequency / N; the rated speed as its fallback."""
    name = "frequency"
    keys = ("rated_rpm",)

    def __init__(self, section: Section):
        super().__init__(section)
        self.rated_rpm = _rated_rpm(section)

    def policy(self, cut, rpm, lobes, grid, depth_known):
        within = self._within(rpm)
        return SuppressionPolicy(FrequencySelection(within, cut), within,
                                 fallback=RatedSpeed(self.rated_rpm, lobes, cut, limits=within),
                                 settle_revs=self.settle_revs)


class RatedStrategy(Strategy):
    """The paper's rule: drop to ``rated_rpm``."""
    name = "rated"
    keys = ("rated_rpm",)

    def __init__(self, section: Section):
        super().__init__(section)
        self.rated_rpm = _rated_rpm(section)

    def policy(self, cut, rpm, lobes, grid, depth_known):
        within = self._within(rpm)
        return SuppressionPolicy(RatedSpeed(self.rated_rpm, lobes, cut, limits=within), within,
                                 settle_revs=self.settle_revs)


class LobesStrategy(Strategy):
    """The highest speed the lobes call stable within reach; model-free while the cut has no model."""
    name = "lobes"
    keys = ("rated_rpm", "when_no_stable_speed")
    predicts = True
    learns = True

    def __init__(self, section: Section):
        super().__init__(section)
        self.rated_rpm = _rated_rpm(section)
        self.when_no_stable_speed = section.getstr("when_no_stable_speed", "hold", choices=WHEN_NO_STABLE_SPEED)

    def policy(self, cut, rpm, lobes, grid, depth_known):
        if lobes is None:      # another turret tool; no model learned yet
            return model_free_policy(cut, self.limits, rpm, self.max_speed_ratio, self.rated_rpm, self.settle_revs)
        # with no depth known the lobes cannot say that every speed chatters: no hold
        hold = self.when_no_stable_speed if depth_known else "move"
        return lobe_policy(lobes, cut, self.limits, rpm, self.max_speed_ratio, self.rated_rpm, grid=grid,
                           settle_revs=self.settle_revs, when_no_stable_speed=hold)

    def depth_changed(self, policy, cut, modelled):
        super().depth_changed(policy, cut, modelled)
        if modelled:
            policy.when_no_stable_speed = self.when_no_stable_speed

    def predicted(self, policy, grid, rpm, depth_mm):
        unstable, b_mm = predicted_unstable(grid, rpm, depth_mm)
        if not unstable:
            return None
        d = policy.observe(time.monotonic(), rpm, True)
        if d is None or isinstance(d, Advice):
            return d
        return replace(d, reason=f"predicted at cut entry: {depth_mm:g} mm deep, the lobes allow {b_mm:.2f} mm "
                                 f"at {rpm:.0f} r/min; {d.reason}")


class VariationStrategy(Strategy):
    """Keep the speed and modulate it (spindle speed variation)."""
    name = "variation"
    keys = ("ssv", "ssv_amplitude", "ssv_period")

    def __init__(self, section: Section):
        super().__init__(section)
        try:
            self.variation = SpeedVariation(section.getstr("ssv", "sine", choices=KINDS),
                                            section.getfloat("ssv_amplitude", 0.1, above=0, maxval=0.5),
                                            section.getduration("ssv_period", 0.5, minval=0.05, maxval=60),
                                            self.limits.accel_rpm_per_s)
        except ValueError as e:
            raise section.error("ssv", str(e)) from None
        if self.variation.amplitude_ratio > self.max_speed_ratio - 1:
            # its swing would pass the speed cap at every alarm: refused there, so refuse it here
            raise section.error("ssv_amplitude", f"{self.variation.amplitude_ratio:g} swings the speed above "
                                f"max_speed_ratio = {self.max_speed_ratio:g} x the programmed speed")
        self._task: asyncio.Task | None = None

    def policy(self, cut, rpm, lobes, grid, depth_known):
        within = self._within(rpm)
        return SuppressionPolicy(VariationSelection(self.variation), within, settle_revs=self.settle_revs)

    def depth_changed(self, policy, cut, modelled):
        pass        # the modulation does not depend on the depth

    def modulate(self, d, send):
        self.stop()
        self._task = asyncio.create_task(self._run(d.rpm_before, d.variation, send))

    def stop(self):
        if self._task is not None:
            self._task.cancel()
            self._task = None

    async def _run(self, n0: float, var: SpeedVariation, send) -> None:
        t0 = time.monotonic()       # its first speed was sent with the decision, just now
        while True:
            await asyncio.sleep(SSV_STEP_S)
            if not await send(float(np.asarray(var.profile(time.monotonic() - t0, n0))), var.kind):
                return


STRATEGIES: dict[str, type[Strategy]] = {c.name: c for c in (LobesStrategy, FrequencyStrategy, RatedStrategy,
                                                              VariationStrategy)}


def check_keys(section: Section, chosen: type[Strategy]) -> None:
    """A key only another strategy reads is an error, not silently ignored."""
    for cls in STRATEGIES.values():
        for key in cls.keys:
            if key in section and key not in chosen.keys:
                owners = [c.name for c in STRATEGIES.values() if key in c.keys]
                raise section.error(key, f"read only with strategy = {' | '.join(owners)}; this table's strategy "
                                         f"is {chosen.name!r}")
