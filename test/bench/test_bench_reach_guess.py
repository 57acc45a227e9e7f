"""bench/bench_reach_guess.py: its scans and its usage."""

from __future__ import annotations

import pytest


@pytest.mark.parametrize("argv", [["--cases", "leg"], ["--cases", ","], ["--seed", "one"]])
def test_a_bad_case_or_seed_is_a_usage_error_before_any_work(load_bench, argv, tmp_path):
    with pytest.raises(SystemExit) as stop:
        load_bench("bench_reach_guess").main([*argv, "--out", str(tmp_path / "out")])
    assert stop.value.code == 2
    assert not (tmp_path / "out").exists()


def test_each_scan_states_the_reach_its_own_bench_states(load_bench):
    """The mice's and (b)'s far side from their scenario, the neck's bench_interior.REACH_MM; the mice and (b)
    run 3 iterations as their benches do, the neck the defaults with the prior at its robots' accuracy."""
    bench = load_bench("bench_reach_guess")
    sc, stated, settings = bench.scan("mouse3", 0, lambda m: None)
    assert stated == pytest.approx(float(sc.exterior_half_width_mm)) and stated > 10.0
    assert settings.iterations == 3 and settings.method == "ncc-lle-exact" and settings.exterior_half_width_mm == 0
    assert settings.exterior_reach_guess
