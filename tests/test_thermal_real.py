"""The thermal loop on a real spindle (../shared/data/real/spindle-thermal, CAIVIAC FL_THERMAL, MIT):
fitted on the first 70 % by time, judged on the last 30 %, beside the plain baselines fitted on
the same rows. Nothing is tuned to these files; they check the result."""
import json
from pathlib import Path

import pytest

from lathed.analysis.thermal import analyze, join_runs, reference_test, split_run
from lathed.analysis.thermal.csvfile import load_thermal_csv

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "spindle-thermal"
pytestmark = pytest.mark.skipif(not REAL.is_dir(), reason="shared real data not present")


@pytest.mark.slow
@pytest.mark.parametrize("channel", ["ch1", "ch2"])
def test_the_model_handed_on_is_no_worse_than_the_best_baseline_on_later_rows(channel):
    d, rep = load_thermal_csv(REAL / f"spindle_{channel}.csv")
    assert rep.used == 11115 and len(d.sensors) == 16
    tr, te = split_run(d, 0.7)
    a = analyze(tr, te)
    labels = [b.model.source for b in a.baselines]
    assert labels == ["least_squares", "least_squares_speed", "ridge_lags"]
    best = min(b.test_rmse_um for b in a.baselines)
    assert a.final.test_rmse_um <= best * 1.0001, [(c.label, c.later) for c in a.comparison]
    # the report carries every baseline beside the selected model, on the same rows
    js = a.to_json()
    shown = [m for m in js["comparison"]["models"] if m["baseline"]]
    assert [m["rmse_um"] for m in shown] == [round(b.test_rmse_um, 4) for b in a.baselines]
    assert json.dumps(js)


@pytest.mark.parametrize("channel", ["ch1", "ch2"])
def test_logged_without_the_speed_once_a_minute_the_model_handed_on_is_still_no_worse(channel, tmp_path):
    """The same run as a spindle that logs no speed, once a minute, would give it (the shape of
    a real spindle the issue names that is not shared): a CSV without spindle_rpm, every 4th row."""
    src = (REAL / f"spindle_{channel}.csv").read_text().splitlines()
    head = src[0].split(",")
    keep = [i for i, h in enumerate(head) if h != "spindle_rpm"]
    rows = [",".join(r.split(",")[i] for i in keep) for r in src[1::4]]
    path = tmp_path / f"{channel}_no_speed.csv"
    path.write_text("\n".join([",".join(head[i] for i in keep), *rows]) + "\n")
    d, rep = load_thermal_csv(path)
    assert d.rpm is None and rep.used == len(rows) and len(d.sensors) == 16
    tr, te = split_run(d, 0.7)
    a = analyze(tr, te)
    assert [b.model.source for b in a.baselines] == ["least_squares", "ridge_lags"]
    best = min(b.test_rmse_um for b in a.baselines)
    assert a.final.test_rmse_um <= best * 1.0001, [(c.label, c.later) for c in a.comparison]


def _part(d, lo_h, hi_h):
    """Hours lo_h..hi_h of the run as a run of its own, its clock restarted."""
    keep = (d.time_s >= lo_h * 3600) & (d.time_s < hi_h * 3600)
    from lathed.analysis.thermal import ThermalData
    return ThermalData(d.time_s[keep] - d.time_s[keep][0], {k: v[keep] for k, v in d.temps_c.items()},
                       d.displacement_um[keep], d.rpm[keep])


def test_a_real_run_taken_up_mid_warm_up_is_told_warm_and_the_start_again_is_cold():
    d, _ = load_thermal_csv(REAL / "spindle_ch1.csv")
    first = _part(d, 0, 12)
    # two hours into the 5000 r/min block the spindle's own sensors stand apart: warm
    with pytest.raises(ValueError, match="does not start cold: .*t_s5_c starts at .* further above the machine's other"):
        reference_test(first, _part(d, 26, 32))
    # the same run read again from its start is cold, whichever day it is on
    rows, notes = join_runs([("a.csv", first), ("b.csv", _part(d, 0, 12))])
    assert len(rows.runs) == 2 and notes == []
