"""bench/bench_offset_diagnosis.py: a view's own term is its exact share of the FDK, and taking it out of the
volume alone leaves a hole that taking it out of the view's data too closes."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from robot_ct_ros.ct import calibration
from robot_ct_ros.ct.projector import forward_project


def _level(bench, fov, views=24, folds=4):
    args = SimpleNamespace(views=views, scale=0.125, fov=fov, body=15.0, sigma=0.3, seed=0)
    nominal, true, li, mask, grid, geo = bench.make_scan(args, lambda m: None)
    settings = calibration.CalibrationSettings(method=bench.METHOD).with_prior(0.3, 0.3)
    return bench.Level(nominal, true, li, mask, grid, settings, folds), geo


def test_the_folds_own_terms_add_up_to_the_fdk_and_leave_the_data_consistent(load_bench):
    """A centred 24-view scan (axis +y): the folds' own terms sum to the whole FDK, and the true-geometry FDK without
    a fold's own terms, reprojected through the true geometry, plus those terms reprojected alike, is the FDK's
    reprojection: what the left-out view is compared with differs from the full model by its own term alone."""
    bench = load_bench("bench_offset_diagnosis")
    level, geo = _level(bench, 0.0)
    assert geo["detector_offset_mm"] == 0.0
    q = level.filtered(level.true_c)
    whole = level.backproject(q)
    parts = sum(level.backproject(q, views) for views in level.folds)
    assert np.abs(parts - whole).max() <= 1e-5 * np.abs(whole).max()
    views = level.folds[1]
    own = level.backproject(q, views)
    geom = level.true_c.subset(views)
    split = forward_project(whole - own, level.grid, geom) + forward_project(own, level.grid, geom)
    np.testing.assert_allclose(split, forward_project(whole, level.grid, geom), atol=1e-4 * float(np.abs(split).max()))
    assert np.abs(forward_project(own, level.grid, geom)).max() > 0.05 * np.abs(split).max()  # a sizeable term


def test_a_held_out_volume_misleads_the_view_unless_its_own_term_leaves_its_data_too(load_bench, tmp_path):
    """The bench on a small centred scan: registered against the true-geometry FDK without its own term, a view does
    worse than with the term also taken out of its data, and placing each view's own term with the true geometry
    in the nominal FDK helps more than the nominal FDK's first pass. The report names every row; bad options stop."""
    bench = load_bench("bench_offset_diagnosis")
    assert bench.main(["--scans", "24:0", "--scale", "0.125", "--passes", "2", "--folds", "4",
                       "--out", str(tmp_path)]) == 0
    out = json.loads((tmp_path / "offset_diagnosis.json").read_text())
    (scan,) = out["scans"]
    rows = scan["rows"]
    assert set(rows) == {key for key, _ in bench.ROWS}
    assert len(rows["loop"]) == 2 and len(rows["left_out_loop"]) == 2 and len(rows["true"]) == 1
    assert rows["true"][0] < scan["nominal_px"]
    assert rows["left_out"][0] < 0.8 * rows["held_out"][0]  # 0.306 against 0.762 here
    assert rows["own_placed"][0] < 0.8 * rows["loop"][0]  # 0.175 against 0.429 here
    md = (tmp_path / "offset_diagnosis.md").read_text()
    assert all(label in md for _, label in bench.ROWS)
    for wrong in (["--scans", "24"], ["--scans", "1:0"], ["--scans", "24:200"], ["--scale", "0.3"], ["--passes", "0"]):
        with pytest.raises(SystemExit):
            bench.main([*wrong, "--out", str(tmp_path / "x")])
