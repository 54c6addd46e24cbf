"""What a turret's second tool does to the stability loop, and what ``tool_number`` buys.

    .venv/bin/python bench/turret.py [--seeds 5]

Tool 1 is the tap-tested turning tool (the refit tests' GIVEN model).  Tool 2 is a slender
boring bar in the same turret: the same workpiece mode, its own tool mode at 350 Hz
(zeta 0.02, k 3e7 N/m), so its limit is 0.6 mm where tool 1's is 2.4.  Labels come from
each tool's true lobes (lathed.analysis.stability.cases, as the refit benchmark's).

1. The refit: 300 of tool 1's cuts (its mode shifted: the refit's ``natural_frequency``
   case, an effect the model lacks), alone (what the refit reads with ``tool_number``
   set) or shuffled with 100 of tool 2's (what it read before); the model it adopts is
   scored on 400 new cuts of tool 1.
2. The speed picked on tool 2's chatter: the lobes of tool 1's model (what suppression
   used before) against the model-free frequency rule (what it uses now for another
   tool), at 1000-4000 r/min and 1-1.5 x tool 2's limit; cured when tool 2's true limit
   at the new speed is above the depth.  Prints Markdown tables.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from lathed.analysis.cuts import Cuts  # noqa: E402
from lathed.analysis.speed_selection import Cut, FrequencySelection, LobeSelection, SpindleLimits, reach  # noqa: E402
from lathed.analysis.stability.cases import GIVEN, generate_cuts, true_dynamics  # noqa: E402
from lathed.analysis.stability import StabilityModel, refit  # noqa: E402
from lathed.sim.lathe import BORING_BAR  # noqa: E402

BAR = StabilityModel((GIVEN.modes[0], BORING_BAR), GIVEN.kf)     # the simulated turret's tool 2


def shuffled(a: Cuts, b: Cuts, seed: int) -> Cuts:
    order = np.random.default_rng(seed).permutation(len(a) + len(b))
    cols = [np.r_[getattr(a, k), getattr(b, k)][order] for k in ("rpm", "depth_mm", "chatter", "chatter_frequency_hz")]
    return Cuts.from_arrays(*cols, machine="sim-lathe", tool="CNMG120408", material="C45")


def refit_rows(seeds: int) -> list[str]:
    rows = []
    true1 = true_dynamics("natural_frequency")
    for seed in range(seeds):
        tool1 = generate_cuts(true1, 300, seed=seed)
        test = generate_cuts(true1, 400, seed=200 + seed)

        def score(cuts: Cuts) -> str:
            r = refit(GIVEN, cuts)
            m = r.model if r.effects else GIVEN
            acc = float(np.mean(m.predict_chatter(test)[0] == test.chatter))
            return f"{', '.join(e['effect'] for e in r.to_json()['effects']) or 'nothing adopted'} | {acc:.3f}"
        base = float(np.mean(GIVEN.predict_chatter(test)[0] == test.chatter))
        rows.append(f"| {seed} | {base:.3f} | {score(tool1)} | "
                    f"{score(shuffled(tool1, generate_cuts(BAR, 100, seed=100 + seed), seed))} |")
    return rows


def speed_rows() -> list[str]:
    limits = SpindleLimits(accel_rpm_per_s=3000.0)
    b_min = float(BAR.limit(np.linspace(800.0, 4000.0, 3201))[0].min())
    picked = {"lobes": [0, 0], "frequency": [0, 0]}
    chattering = 0
    for rpm in range(1000, 4001, 100):
        b_here = float(BAR.limit(np.array([float(rpm)]))[0][0])
        for depth in np.round(np.array([1.0, 1.15, 1.3, 1.5]) * b_min, 6):
            if b_here > depth:
                continue                       # stable already
            chattering += 1
            f = float(BAR.limit(np.array([float(rpm)]))[1][0])
            cut = Cut(depth, 0.3e-3, 0.03, 1.5e9)
            within = reach(limits, rpm, 1.3)
            for name, strategy in (("lobes", LobeSelection(GIVEN, cut, within)),
                                   ("frequency", FrequencySelection(within, cut))):
                d = strategy.select(float(rpm), f)
                if d is None:
                    continue
                picked[name][0] += 1
                picked[name][1] += bool(BAR.limit(np.array([d.rpm_after]))[0][0] > depth)
    return [f"| tool 1's lobes (before) | {chattering} | {picked['lobes'][0]} | {picked['lobes'][1]} |",
            f"| the frequency rule (model-free, now) | {chattering} | {picked['frequency'][0]} | "
            f"{picked['frequency'][1]} |"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5, help="draws of the refit case (default 5)")
    a = ap.parse_args(argv)
    if a.seeds < 1:
        print("turret.py: --seeds must be at least 1", file=sys.stderr)
        return 2
    print("The refit of tool 1's model (its mode shifted), scored on 400 new cuts of tool 1\n")
    print("| seed | configured model | tool 1's cuts only: adopted | accuracy | with tool 2's mixed in: adopted "
          "| accuracy |")
    print("|---|---|---|---|---|---|")
    print("\n".join(refit_rows(a.seeds)))
    print("\nThe first speed picked on tool 2's chatter (1-1.5 x its limit, 1000-4000 r/min, within 1.3 x)\n")
    print("| speed from | chattering cuts | a speed picked | cured there |")
    print("|---|---|---|---|")
    print("\n".join(speed_rows()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
