"""bench/bench_interior.py: calibration settings given on its command line reach every method and its report."""

from __future__ import annotations

import json

import pytest


def test_a_setting_given_to_the_bench_reaches_the_calibration_and_the_report(load_bench, tmp_path):
    """A tiny interior neck with the exterior on 1 mm voxels: the report names the changed setting, the
    json holds it in the settings every method ran with, and the '+ exterior' row modelled the object
    outside the ROI (its notes say so). The prior stays the bench's own (each scan's robot error)."""
    bench = load_bench("bench_interior")
    out = tmp_path / "interior"
    assert bench.main(["--sigmas", "0.1", "--methods", "none,ncc-lle-exact + exterior", "--views", "12",
                       "--det", "16x40", "--nxy", "16", "--iterations", "1", "--exterior-voxel-mm", "1",
                       "--out", str(out)]) == 0
    report = json.loads((out / "interior.json").read_text())
    assert report["settings_changed"] == {"exterior_voxel_mm": 1.0}
    assert report["settings"]["exterior_voxel_mm"] == 1.0
    assert "`exterior_voxel_mm` 1.0" in (out / "interior.md").read_text()
    notes = report["scans"][0]["notes"]["ncc-lle-exact + exterior"]
    assert any("the object outside the ROI was modelled" in n for n in notes)
    # the loop's error after each outer iteration: one iteration, the final row's error unless the guard reverted it
    per_iteration = report["scans"][0]["error_per_iteration_px"]
    assert list(per_iteration) == ["ncc-lle-exact + exterior"] and len(per_iteration["ncc-lle-exact + exterior"]) == 1
    row = next(r for r in report["scans"][0]["rows"] if r["method"] == "ncc-lle-exact + exterior")
    if not any("nominal geometry is kept" in n for n in notes):
        assert per_iteration["ncc-lle-exact + exterior"][0] == pytest.approx(row["reproj_mean_px"], abs=1e-3)
    assert "error after each outer iteration" in (out / "interior.md").read_text()
    with pytest.raises(SystemExit):
        bench.main(["--prior-sigma", "1,1", "--out", str(out)])


def test_the_perfect_volume_table_takes_the_volumes_asked_for(load_bench, tmp_path):
    """``--oracle-voxels`` chooses the perfect volumes (the ROI alone, exterior voxel sizes): one row per volume, in
    that order, each with the error from the nominal and from the true geometry; a bad list is refused."""
    bench = load_bench("bench_interior")
    out = tmp_path / "oracle"
    assert bench.main(["--sigmas", "0.1", "--methods", "none", "--views", "12", "--det", "16x40", "--nxy", "16",
                       "--oracle", "--oracle-voxels", "roi,1", "--out", str(out)]) == 0
    rows = json.loads((out / "interior.json").read_text())["scans"][0]["oracle"]
    assert [r["model"] for r in rows] == ["ROI only", "ROI + exterior on 1 mm voxels"]
    assert all(r["from_nominal_px"] >= 0 and r["from_true_px"] >= 0 for r in rows)
    assert "| ROI + exterior on 1 mm voxels |" in (out / "interior.md").read_text()
    with pytest.raises(SystemExit):
        bench.main(["--oracle-voxels", "roi,fine", "--out", str(out)])
