import numpy as np
import pytest

from lathed.analysis.cuts import Cuts, CutsCsvError, load_cuts_csv, write_cuts_csv

HEADER = "machine,tool,material,rpm,depth_mm,feed_mm_rev,outcome,chatter_frequency_hz\n"


def _write(tmp_path, body, header=HEADER):
    p = tmp_path / "cuts.csv"
    p.write_text(header + body)
    return p


def test_reads_cuts_in_order(tmp_path):
    p = _write(tmp_path, "l1,T1,C45,1850,1.2,0.25,stable,\n\nl1,T1,C45,2100,2.4,0.2,Chatter,668.5\n")
    c = load_cuts_csv(p)
    assert len(c) == 2
    assert list(c.rpm) == [1850, 2100] and list(c.chatter) == [False, True]
    assert np.isnan(c.chatter_frequency_hz[0]) and c.chatter_frequency_hz[1] == 668.5
    assert list(c.line) == [2, 4]
    assert c.setups() == [("l1", "T1", "C45")]


def test_frequency_column_is_optional(tmp_path):
    p = _write(tmp_path, "l1,T1,C45,1850,1.2,0.25,chatter\n", HEADER.replace(",chatter_frequency_hz", ""))
    assert np.isnan(load_cuts_csv(p).chatter_frequency_hz[0])


@pytest.mark.parametrize("row,column,needle", [
    ("l1,T1,C45,fast,1.2,0.25,stable,", "rpm", "not a number"),
    ("l1,T1,C45,1850,-1,0.25,stable,", "depth_mm", "outside the physical range"),
    ("l1,T1,C45,1850,1.2,,stable,", "feed_mm_rev", "is empty"),
    ("l1,T1,C45,1850,1.2,0.25,wobbly,", "outcome", "stable or chatter"),
    ("l1,T1,C45,1850,1.2,0.25,stable,600", "chatter_frequency_hz", "on a stable cut"),
    ("l1,T1,C45,1850,1.2,0.25,chatter,nan", "chatter_frequency_hz", "not a finite number"),
    (",T1,C45,1850,1.2,0.25,chatter,", "machine", "is empty"),
    ("l1,T1,C45,1850,1200,0.25,stable,", "depth_mm", "outside the physical range"),
])
def test_bad_row_is_one_line_naming_file_line_column(tmp_path, row, column, needle):
    p = _write(tmp_path, "l1,T1,C45,1850,1.2,0.25,stable,\n" + row + "\n")
    with pytest.raises(CutsCsvError) as e:
        load_cuts_csv(p)
    assert len(e.value.lines) == 1
    line = e.value.lines[0]
    assert "\n" not in line
    assert f"{p}:3" in line and f"column {column}" in line and needle in line


def test_every_bad_row_is_listed(tmp_path):
    p = _write(tmp_path, "l1,T1,C45,x,1.2,0.25,stable,\nl1,T1,C45,1850,1.2,0.25,stable,\n"
                         "l1,T1,C45,1850,1.2,0.25,maybe,\n")
    with pytest.raises(CutsCsvError) as e:
        load_cuts_csv(p)
    assert [ln.split(",")[0].split("(")[-1] for ln in e.value.lines] == [f"{p}:2", f"{p}:4"]


def test_missing_column_and_empty_file(tmp_path):
    p = _write(tmp_path, "l1,T1,C45,1850,1.2,stable\n", "machine,tool,material,rpm,depth_mm,outcome\n")
    with pytest.raises(CutsCsvError, match=r":1: missing required column 'feed_mm_rev'"):
        load_cuts_csv(p)
    p.write_text("")
    with pytest.raises(CutsCsvError, match="empty file"):
        load_cuts_csv(p)
    with pytest.raises(CutsCsvError) as e:
        load_cuts_csv(tmp_path / "nope.csv")
    assert e.value.exit_code == 66


def test_write_then_read_round_trips(tmp_path):
    c = Cuts.from_arrays([500.0, 2500.0], [0.5, 3.0], [False, True], [np.nan, 640.0])
    write_cuts_csv(c, tmp_path / "c.csv")
    r = load_cuts_csv(tmp_path / "c.csv")
    assert list(r.rpm) == [500, 2500] and list(r.chatter) == [False, True]
    assert r.chatter_frequency_hz[1] == 640.0
