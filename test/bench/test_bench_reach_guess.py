"""bench/bench_reach_guess.py: its scans and its usage."""

from __future__ import annotations

import pytest


@pytest.mark.parametrize("argv", [["--cases", "leg"], ["--cases", ","], ["--seed", "one"]])
def test_a_bad_case_or_seed_is_a_usage_error_before_any_work(load_bench, argv, tmp_path):
    with pytest.raises(SystemExit) as stop:
        load_bench("bench_reach_guess").main([*argv, "--out", str(tmp_path / "out")])
    assert stop.value.code == 2
    assert not (tmp_path / "out").exists()


def test_case_groups_name_the_benches_scans_and_the_users_bags(load_bench, tmp_path, capsys):
    """--cases scans (the default) is the other benches' scans, bags the robot-ct simulate ones; a group and
    names mix, and only an unknown name is reported."""
    bench = load_bench("bench_reach_guess")
    assert set(bench.GROUPS["scans"]) | set(bench.GROUPS["bags"]) == set(bench.CASES)
    assert not set(bench.GROUPS["scans"]) & set(bench.BAG_SCANS) and set(bench.GROUPS["bags"]) == set(bench.BAG_SCANS)
    with pytest.raises(SystemExit):
        bench.main(["--cases", "bags,leg", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert "unknown leg (" in err and "bag48" not in err.split("(known")[0]


def test_each_scan_states_the_reach_its_own_bench_states(load_bench):
    """The mice's and (b)'s far side from their scenario, the neck's bench_interior.REACH_MM; the mice and (b)
    run 3 iterations as their benches do, the neck the defaults with the prior at its robots' accuracy."""
    bench = load_bench("bench_reach_guess")
    sc, stated, settings = bench.scan("mouse3", 0, lambda m: None)
    assert stated == pytest.approx(float(sc.exterior_half_width_mm)) and stated > 10.0
    assert settings.iterations == 3 and settings.method == "ncc-lle-exact" and settings.exterior_half_width_mm == 0
    assert settings.exterior_reach_guess


def test_a_calibrations_outcome_reads_the_error_before_the_guard_and_its_verdict(load_bench):
    """One outcome for both rows of a scan: the final error, the error the estimate had before the guard
    (the final one where the guard changed nothing), and whether the guard kept the nominal geometry."""
    from types import SimpleNamespace

    import numpy as np

    from robot_ct_ros.ct.trajectory import circular_scan

    bench = load_bench("bench_reach_guess")
    nominal = circular_scan(12, 60.0, 150.0, 8, 8, 1.0, 1.0)
    moved = np.zeros((12, 9))
    moved[:, 3] = 0.5  # the detector 0.5 mm along u: half a pixel
    sc = SimpleNamespace(nominal=nominal, true=nominal.perturbed(moved))
    pts = np.zeros((1, 3))
    refused = SimpleNamespace(geom=nominal, params_unguarded=np.zeros((12, 9)), history=(1, 2),
                              notes=("guard: ...; the data do not support it and the nominal geometry is kept",))
    out = bench.outcome(refused, sc, pts)
    assert out["kept_nominal"] and out["iterations"] == 2
    assert out["error_px"] == pytest.approx(out["unguarded_px"]) and out["error_px"] > 0.1
    applied = SimpleNamespace(geom=sc.true, params_unguarded=None, history=(1,),
                              notes=("guard: the correction is 0.50 times the robots' stated accuracy (limit 1.5)",))
    out = bench.outcome(applied, sc, pts)
    assert not out["kept_nominal"] and out["error_px"] == out["unguarded_px"] == pytest.approx(0.0, abs=1e-9)


def test_a_bag_case_is_the_users_simulated_carotid_scan_read_back_with_the_neck_s_far_side(load_bench):
    """bag48: a robot-ct simulate carotid bag of 90 views of 48 x 64, read back with its true geometry, the
    default grid and settings; the stated reach is the 13 cm neck's far side from the ROI centre (83 mm)."""
    import numpy as np

    bench = load_bench("bench_reach_guess")
    sc, stated, settings = bench.scan("bag48", 0, lambda m: None)
    assert sc.li.shape == (90, 48, 64) and sc.mask.shape == sc.li.shape
    assert sc.true is not None and np.abs(sc.true.params_relative_to(sc.nominal)).max() > 0
    assert stated == pytest.approx(83.0, abs=0.5)
    assert settings == bench.DEFAULTS and settings.exterior_half_width_mm == 0 and settings.exterior_reach_guess
