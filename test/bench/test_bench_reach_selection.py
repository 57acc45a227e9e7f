"""bench/bench_reach_selection.py: the two consistency figures it scores each reach by."""

from __future__ import annotations

import pytest


def test_the_fit_prefers_a_wider_model_and_held_out_views_a_narrower_one(load_bench):
    """A tiny wide mouse (30 views, a 16 x 24 detector): widening the exterior model from a third of the way to
    the far side to twice the far side raises how well it reproduces the views it was built from and lowers how
    well it predicts the views it did not see: the two figures pull the reach opposite ways."""
    bench = load_bench("bench_reach_selection")
    calib = load_bench("bench_calibration")
    sc = calib.make_scenario("a", 30, (16, 24), 16, 4, 0, lambda m: None, phantom_scale=3.0)
    far = float(sc.exterior_half_width_mm)
    (held_short, fit_short), (held_wide, fit_wide) = (bench.scores(sc, 1, far * f) for f in (1 / 3, 2))
    assert all(-1.0 <= x <= 1.0 for x in (held_short, fit_short, held_wide, fit_wide))
    assert fit_wide > fit_short
    assert held_wide < held_short


@pytest.mark.parametrize("argv", [["--cases", "leg"], ["--neck-reaches", "16,abc"], ["--mouse-also", "-3"]])
def test_a_bad_case_or_reach_is_a_usage_error_before_any_work(load_bench, argv, tmp_path):
    with pytest.raises(SystemExit) as stop:
        load_bench("bench_reach_selection").main([*argv, "--out", str(tmp_path / "out")])
    assert stop.value.code == 2
    assert not (tmp_path / "out").exists()
