"""bench/bench_realdata_halves.py: the centre shift, the halves' comparison and the harmonics it reports."""

from __future__ import annotations

import numpy as np
import pytest

from robot_ct_ros.ct.trajectory import circular_scan


def test_the_centre_shift_is_where_the_rotation_centre_projects(load_bench):
    """c = d_u + k s_u in pixels is the move of the rotation centre's projection (less its mean), up to
    the sign of the detector's u axis: checked by projecting the centre through the perturbed geometry.
    A wrong k (or its sign) would decorrelate them, since s_u and d_u move it by similar amounts."""
    bench = load_bench("bench_realdata_halves")
    geom = circular_scan(36, 400.0, 550.0, 1, 200, 0.2, 0.2)
    rng = np.random.default_rng(2)
    params = np.zeros((36, 9))
    params[:, 0] = rng.normal(0.0, 0.5, 36)   # s_u, mm
    params[:, 3] = rng.normal(0.0, 0.2, 36)   # d_u, mm
    c = bench.centre_shift_px(params, geom)
    centre = np.zeros((1, 3))
    shift = geom.perturbed(params).project_points(centre)[:, 0, 0] - geom.project_points(centre)[:, 0, 0]
    shift -= shift.mean()
    assert abs(np.corrcoef(c, shift)[0, 1]) > 0.999
    assert np.sqrt(np.mean(c ** 2)) == pytest.approx(np.sqrt(np.mean(shift ** 2)), rel=0.01)


def test_the_halves_agree_on_a_shared_pull_and_not_on_noise(load_bench):
    bench = load_bench("bench_realdata_halves")
    theta = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    pull = 0.1 * np.cos(3 * theta) + 0.05 * np.sin(5 * theta)
    rng = np.random.default_rng(0)
    shared = bench.compare_halves(pull + rng.normal(0, 0.01, 360), pull + rng.normal(0, 0.01, 360))
    assert shared["corr"] > 0.95 and abs(shared["corr_quarter"]) < 0.3 and shared["lag1"] > 0.9
    assert shared["rms_even_px"] == pytest.approx(np.sqrt(np.mean(pull ** 2)), rel=0.05)
    noise = bench.compare_halves(rng.normal(0, 0.1, 360), rng.normal(0, 0.1, 360))
    assert abs(noise["corr"]) < 0.2 and abs(noise["lag1"]) < 0.2


def test_harmonic_amplitudes_recover_a_known_mix(load_bench):
    bench = load_bench("bench_realdata_halves")
    theta = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    amps = bench.harmonic_amplitudes(0.07 * np.cos(4 * theta + 0.3) + 0.02 * np.sin(8 * theta))
    assert len(amps) == bench.HARMONICS
    assert amps[3] == pytest.approx(0.07) and amps[7] == pytest.approx(0.02)
    assert max(a for h, a in enumerate(amps, 1) if h not in (4, 8)) < 1e-9


def test_injected_errors_are_scored_against_the_documented_geometry_and_the_methods_own_start(load_bench):
    """recover_injected on a small one-row scan whose documented geometry is exact: the default method
    reuses the documented-start estimate it is given (here the documented geometry itself, so both
    scores agree exactly), another method is calibrated from the documented start itself; both undo
    most of the injected pixel."""
    from types import SimpleNamespace

    from robot_ct_ros.ct.geometry import VolumeGrid
    from robot_ct_ros.ct.metrics import roi_points
    from robot_ct_ros.ct.projector import forward_project
    from robot_ct_ros.ct.simulation import Phantom, elliptic_cylinder, voxelize

    bench = load_bench("bench_realdata_halves")
    geom = circular_scan(60, 60.0, 150.0, 1, 64, 0.4, 0.4)
    phantom = Phantom("disc", (elliptic_cylinder((0, 0, 0), (4.5, 3.8), 30.0, 0.02),
                               elliptic_cylinder((1.5, 0.8, 0), (1.0, 1.4), 30.0, 0.05),
                               elliptic_cylinder((-1.8, -0.6, 0), (0.8, 0.8), 30.0, 0.035)))
    fine = VolumeGrid.centered((40, 100, 100), 0.1)
    li = forward_project(voxelize(phantom, fine), fine, geom)
    grid = VolumeGrid.centered((1, 48, 48), (0.22, 0.22, 0.16))
    settings = bench.calibration.CalibrationSettings().replace(iterations=2)
    rows = bench.recover_injected(li, geom, grid, None, settings, SimpleNamespace(geom=geom), 0.4 * 60 / 90,
                                  roi_points(grid), ["ncc-lle-exact", "gdc"], "disc", lambda m: None)
    assert [r["method"] for r in rows] == ["ncc-lle-exact", "gdc"]
    exact, gdc = rows
    assert exact["from_documented_px"] == 0.0 and exact["vs_own_px"] == exact["vs_documented_px"]
    assert gdc["from_documented_px"] > 0.0 and gdc["vs_own_px"] != gdc["vs_documented_px"]
    for r in rows:
        assert r["nominal_px"] > 0.8
        assert r["vs_documented_px"] < 0.25 * r["nominal_px"], r  # about 0.06 of 1 px here
