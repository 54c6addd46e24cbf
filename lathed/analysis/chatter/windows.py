"""What a chatter detector reports per window, its common parameters, and the judged index
(docs/chatter.md)."""
from __future__ import annotations

import math
from dataclasses import dataclass

@dataclass
class Window:
    t_s: float                          # end of the window, seconds since reset
    index: float                        # raw / baseline (nan while nothing learned yet)
    threshold: float                    # index level that counts as chatter
    alarm: bool                         # alarm state after this window (hysteresis applied)
    chatter_frequency_hz: float | None = None   # only while alarm
    learning: bool = False              # window used to learn the baseline
    raised_by: str | None = None        # on the window that raises the alarm: "threshold" or
                                        # "sustained rise" (the CUSUM: index held above cusum_ratio)
    judged: bool = True                 # False: the index was not judged (learning, a speed change,
                                        # the tool entering or leaving the work, waiting for the load)
    shape: float = math.nan             # the spectral shape index (chatter.shape): 1 for a change of level;
                                        # nan where the shape gate did not need it (it is made only then)


# name -> (default, min, max, meaning)
BASE_PARAMS: dict[str, tuple[float, float, float, str]] = {
    "window_revs": (1.0, 0.25, 16.0, "window length in spindle revolutions"),
    "hop_revs": (0.5, 0.1, 4.0, "hop between windows in revolutions"),
    "min_window_s": (0.02, 0.002, 1.0, "window never shorter than this (high speeds)"),
    "min_hop_s": (0.01, 0.001, 1.0, "hop never shorter than this (bounds the cost)"),
    "learn_windows": (4, 2, 1000, "windows at the start of a cut used to learn the baseline"),
    "learn_quantile": (0.25, 0.0, 1.0, "quantile of the learning windows taken as baseline "
                       "(low: ignores the cut-entry transient and chatter already growing)"),
    "threshold": (2.0, 1.05, 1000.0, "index above which a window counts as chatter"),
    "on_windows": (2, 1, 50, "consecutive windows above threshold to raise the alarm"),
    "off_windows": (4, 1, 1000, "consecutive windows below off_ratio*threshold to clear it"),
    "off_ratio": (0.7, 0.1, 1.0, "hysteresis: clear level as a fraction of threshold"),
    "settle_revs": (2.0, 0.0, 50.0, "no new alarm this many revolutions after a speed change"),
    "ramp_per_rev": (0.01, 0.0, 1.0, "a speed change counts (settle_revs) when the speed moved by more than this "
                     "share over the last revolution: a drive's ramp (2-8 % a revolution), not a slow drift "
                     "such as constant surface speed (G96), under which chatter is still judged"),
    "cusum_ratio": (0.0, 0.0, 100.0, "0: off; else a cumulative sum of log(index / cusum_ratio) "
                    "also raises the alarm past on_windows x log(threshold / cusum_ratio): a "
                    "sustained rise below the threshold adds up (1 < cusum_ratio < threshold)"),
    "follow_quantile": (0.0, 0.0, 0.99, "0: off; else, with cusum_ratio set, the baseline rises to this "
                        "quantile of the cut's last 256 windows below the allowance, once there are "
                        "2 x learn_windows of them: the sustained-rise test learns how far the stable "
                        "cut wanders (never below the learned baseline)"),
    "load_scaled": (0.0, 0.0, 1.0, "1: the index is divided by the cutting load's ratio to its value "
                    "when the baseline was set (set_load: the spindle load above its no-chip load), so "
                    "a deeper stable pass in the same cut (a shoulder) is not chatter; an upward level "
                    "step then waits for the next load reading (0: off)"),
    "growth_ratio": (0.0, 0.0, 100.0, "0: off; else on_windows windows in a row whose raw measure is this many "
                     "times the lowest of the growth_revs revolutions before raise the alarm (raised_by "
                     "'growth'): chatter growing, whatever the baseline; a window whose second half is "
                     "quieter than its first (the ring of the tool's release) does not count"),
    "growth_revs": (4.0, 1.0, 64.0, "revolutions the growth test looks back over (counted once a cut, a "
                    "speed change or a level step has that many behind it)"),
    "shape_min": (0.0, 0.0, 1000.0, "0: off; else the threshold and the sustained rise raise the alarm only "
                  "on a window whose spectral shape index (power new in shape over the baseline's, scaled) "
                  "is at least this: a change of level alone (a deeper pass, the cut's wander, a gain) "
                  "is not chatter"),
    "rise_ratio": (0.0, 0.0, 100.0, "0: off; else a window whose level is this many times the level a revolution "
                   "earlier, from a cut at its steady level, is a deeper pass (a shoulder): the span whose "
                   "revolution difference sees the step is judged only for growth beyond rise_growth x its "
                   "lowest window, and a level that settles there is the deeper pass's own baseline (off "
                   "with a reference baseline)"),
    "rise_growth": (3.0, 1.5, 100.0, "within a deeper pass's span (rise_ratio), growth over this many times its "
                    "lowest window raises the alarm (growth, off with growth_ratio 0): a stable cut's echo "
                    "is smaller every revolution, so two revolutions on it stays under 3 x the first"),
    "jump_ratio": (3.0, 1.5, 1000.0, "a window whose level (median |x|) is above jump_ratio x, or below "
                   "1/jump_ratio x, the level one revolution earlier does not count towards "
                   "the alarm (the tool entering or leaving the work, not chatter)"),
    "fmin_hz": (50.0, 0.0, 20000.0, "lower edge of the chatter band"),
    "fmax_hz": (5000.0, 10.0, 25600.0, "upper edge of the chatter band"),
}


class JudgedIndex:
    """The index of the windows a detector judged (``Window.judged``), one window late: the
    window where the tool leaves the work is judged before the next one shows the level step,
    so a judged window followed by one not judged is dropped.  What a part's record keeps."""

    def __init__(self) -> None:
        self._held: tuple[float, float] | None = None

    def reset(self) -> None:
        self._held = None

    def push(self, w: Window, t: float) -> tuple[float, float] | None:
        """This window; returns the (index, t) of the one before it if that one stands."""
        judged = getattr(w, "judged", True) and not math.isnan(w.index)   # a plugin's may lack it
        out = self._held if judged else None
        self._held = (w.index, t) if judged else None
        return out
