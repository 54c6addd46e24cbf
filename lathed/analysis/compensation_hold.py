"""When thermal compensation must hold its offset instead of acting (docs/safety.md).

Two checks on what the compensation would act on, numeric only:

- its inputs are fresh: a temperature not read within ``stale_after`` (a sensor
  off its wire, the board's link down) says nothing of the spindle now;
- the predicted growth moved no faster than a spindle grows: a jump beyond
  ``tol + rate x step`` between two evaluations is a sensor fault (another board
  on the port, a level the entry check rebased to), not heat. The growth is then
  held at the last plausible value until the prediction comes back to it, or
  until the operator touches the tool off again (which takes the new level).

No credit for time without fresh inputs: after a gap the first prediction must
lie within one step's growth of the last one acted on, as the readings behind
it had no plausible history across the gap either.
"""
from __future__ import annotations


class CompensationHold:
    def __init__(self, stale_after_s: float, growth_rate_max_um_s: float, step_s: float, tol_um: float):
        self.stale_after_s = stale_after_s
        self.rate = growth_rate_max_um_s
        self.step_s = step_s
        self.tol = tol_um
        self._ref: tuple[float, float] | None = None    # (growth, t) last judged plausible

    def stale(self, read_at: dict[str, float], needed: list[str], now: float) -> str | None:
        """Why the inputs cannot be acted on (``read_at``: place -> time of its last reading), or None."""
        old = sorted((p, now - read_at[p]) for p in needed if p in read_at and now - read_at[p] > self.stale_after_s)
        if not old:
            return None
        ages = ", ".join(f"{p} {age:.0f} s" for p, age in old)
        return f"temperature readings are stale ({ages} old, more than {self.stale_after_s:g} s): holding the offset"

    def judge(self, growth_um: float, t: float) -> str | None:
        """None: ``growth_um`` at ``t`` is plausible (and becomes the reference); else why not."""
        if self._ref is None:
            self._ref = (growth_um, t)
            return None
        ref, ref_t = self._ref
        # one step's growth at most, whatever the time since: none is credited for a gap
        allowed = self.tol + self.rate * max(0.0, min(t - ref_t, self.step_s))
        if abs(growth_um - ref) <= allowed:
            self._ref = (growth_um, t)
            return None
        return (f"predicted growth moved {growth_um - ref:+.1f} µm (from {ref:.1f} to {growth_um:.1f} µm), more "
                f"than a spindle grows in {self.step_s:g} s ({allowed:.1f} µm at {self.rate:g} µm/s): a sensor "
                "fault, not heat; holding the offset until the prediction comes back or the tool is touched "
                "off again")

    def reset(self) -> None:
        """A new reference (a touch-off, another model): the next prediction is taken as it is."""
        self._ref = None
