"""bench/bench_exterior_reach.py: calibration settings given on its command line reach every reach's run and the
report; the bench keeps the prior, the exterior and its reach to itself."""

from __future__ import annotations

import json

import pytest


def test_a_setting_given_to_the_reach_bench_reaches_the_report(load_bench, tmp_path):
    """A tiny interior neck (12 views, a 16 x 40 detector) with the exterior on 1 mm voxels at one reach: the
    report names the changed setting and the run modelled the object outside the ROI."""
    bench = load_bench("bench_exterior_reach")
    out = tmp_path / "reach"
    assert bench.main(["--reaches", "30", "--views", "12", "--det", "16x40", "--nxy", "16", "--iterations", "1",
                       "--exterior-voxel-mm", "1", "--out", str(out)]) == 0
    report = json.loads((out / "exterior_reach.json").read_text())
    assert report["settings_changed"] == {"exterior_voxel_mm": 1.0}
    assert "`exterior_voxel_mm` 1.0" in (out / "exterior_reach.md").read_text()
    (row,) = report["rows"]
    assert row["half_width_mm"] == 30.0
    assert any("the object outside the ROI was modelled" in n for n in row["notes"])
    for owned in (["--prior-sigma", "1,1"], ["--exterior", "off"], ["--exterior-half-width-mm", "5"]):
        with pytest.raises(SystemExit):
            bench.main([*owned, "--out", str(out)])
