"""bench/bench_fullsize.py: the field of view, the start at the true geometry and the calibration settings given on
its command line reach the run and its report, and bench_guard reads its verdict."""

from __future__ import annotations

import json

import pytest


def _run(bench, out, *extra):
    assert bench.main(["--views", "12", "--scale", "0.125", "--iterations", "1", "--no-rtk", "--out", str(out),
                       "--volume-out", str(out), *extra]) == 0
    return json.loads((out / "fullsize.json").read_text())


def test_the_seed_systems_scan_takes_its_field_of_view_and_the_calibration_settings(load_bench, tmp_path):
    """A tiny cut-down scan (12 views of 79 x 34 pixels): the default is the offset detector for 50 mm; ``--fov 0``
    the centred detector's own field of view; a calibration setting reaches the run, its notes and the report."""
    bench = load_bench("bench_fullsize")
    offset = _run(bench, tmp_path / "offset")
    assert offset["geometry"]["fov_mm"] == 50.0 and offset["geometry"]["detector_offset_mm"] > 30.0
    assert offset["calibration"]["settings_changed"] == {}
    centred = _run(bench, tmp_path / "centred", "--fov", "0", "--exterior", "on", "--exterior-half-width-mm", "30",
                   "--exterior-voxel-mm", "2")
    g = centred["geometry"]
    assert g["detector_offset_mm"] == 0.0 and 20.0 < g["fov_mm"] < 30.0
    c = centred["calibration"]
    assert c["settings_changed"] == {"exterior": "on", "exterior_half_width_mm": 30.0, "exterior_voxel_mm": 2.0}
    assert c["settings"]["prior_translation_mm"] == 0.3  # the prior is --sigma
    assert any("the object outside the ROI was modelled" in n for n in c["notes"])
    assert 0.0 < c["model_ncc"] <= 1.0
    md = (tmp_path / "centred" / "fullsize.md").read_text()
    assert "centred detector" in md and "`exterior` on" in md
    for wrong in (["--prior-sigma", "1,1"], ["--fov", "-1"], ["--fov", "nan"], ["--fov", "200"], ["--scale", "0.3"]):
        with pytest.raises(SystemExit):
            bench.main([*wrong, "--out", str(tmp_path / "x")])


def test_a_start_at_the_true_geometry_is_measured_and_left_out_of_the_guards_count(load_bench, tmp_path):
    """``--from-true`` starts the loop at the truth (error 0 before it); bench_guard counts the run from the nominal
    geometry and leaves the one from the truth out."""
    bench = load_bench("bench_fullsize")
    results = tmp_path / "results"
    _run(bench, results / "nominal_start", "--sigma", "0.2")
    truth = _run(bench, results / "true_start", "--sigma", "0.2", "--from-true")
    assert truth["calibration"]["from_true"] and truth["calibration"]["error_before_px"] == 0.0
    assert truth["calibration"]["error_after_px"] >= 0.0
    assert "started at the true geometry" in (results / "true_start" / "fullsize.md").read_text()
    guard = load_bench("bench_guard")
    records, read = guard.collect(str(results))
    assert read == ["nominal_start/fullsize.json", "true_start/fullsize.json"]
    (r,) = records
    assert r["source"] == "nominal_start/fullsize.json" and r["scan"].startswith("seed system, 60 mm neck, 50 mm")
    assert r["nominal_px"] > 0 and r["outcome"] != "unknown (no error before the guard)"
