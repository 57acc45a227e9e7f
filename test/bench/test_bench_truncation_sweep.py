"""bench/bench_truncation_sweep.py: calibration settings given on its command line reach every row and the
report, and --keep refuses to mix cells run with other settings."""

from __future__ import annotations

import json

import pytest


def test_a_setting_given_to_the_sweep_reaches_the_rows_and_the_report(load_bench, tmp_path):
    """A tiny sweep (one width, 8 views, a 16 x 24 detector): the report and the json name the changed setting,
    the row with the reach stated modelled the object outside the ROI (its notes say so), and --keep with
    other settings stops instead of mixing the two runs' cells in one table."""
    bench = load_bench("bench_truncation_sweep")
    out = tmp_path / "sweep"
    tiny = ["--scales", "2", "--views", "8", "--det", "16x24", "--vol", "16", "--iterations", "1"]
    assert bench.main([*tiny, "--methods", "none,ncc-lle-exact (reach stated)", "--exterior-iterations", "2",
                       "--out", str(out)]) == 0
    report = json.loads((out / "sweep.json").read_text())
    assert report["settings_changed"] == {"exterior_iterations": 2}
    assert (report["det"], report["vol"]) == ([16, 24], 16)
    assert "`exterior_iterations` 2" in (out / "sweep.md").read_text()
    row = report["scales"]["2.0"]
    assert set(row["errors_px"]) == {"none", "ncc-lle-exact (reach stated)"}
    assert any("the object outside the ROI was modelled" in n for n in row["notes"]["ncc-lle-exact (reach stated)"])
    with pytest.raises(SystemExit, match="calibration settings"):
        bench.main([*tiny, "--methods", "none", "--keep", "--out", str(out)])
    with pytest.raises(SystemExit):  # the bench sets the reach itself
        bench.main([*tiny, "--exterior-half-width-mm", "5", "--out", str(out)])
