"""GDC and GDC-LoG baselines: the estimator alone (volume reconstructed with the true geometry)."""

import numpy as np
import pytest

from robot_ct_ros.ct.calibration.gdc import GDCConfig, default_gdc_configs, estimate_views_gdc
from robot_ct_ros.ct.calibration import calibrate
from robot_ct_ros.ct.geometry import VolumeGrid
from robot_ct_ros.ct.metrics import reprojection_error, roi_points
from robot_ct_ros.ct.projector import forward_project
from robot_ct_ros.ct.reconstruction import fdk
from robot_ct_ros.ct.simulation import robot_coordination
from robot_ct_ros.ct.trajectory import circular_scan

N_VIEWS, DET = 30, 56


def _blobs(grid, seed=0, n=25):
    rng = np.random.default_rng(seed)
    vol = np.zeros(grid.shape_zyx, np.float32)
    z, y, x = np.meshgrid(*[np.arange(s) for s in grid.shape_zyx], indexing="ij")
    for _ in range(n):
        c = rng.uniform(8, 40, 3)
        r = rng.uniform(1.5, 5, 3)
        vol[((z - c[0]) / r[0]) ** 2 + ((y - c[1]) / r[1]) ** 2 + ((x - c[2]) / r[2]) ** 2 < 1] += rng.uniform(0.01, 0.03)
    return vol


@pytest.fixture(scope="module")
def problem():
    nominal = circular_scan(N_VIEWS, 128.0, 342.4, DET, DET, 0.44, 0.44)
    grid = VolumeGrid.centered((48, 48, 48), DET * 0.44 / 2.67 / 48 * 0.9)
    vol = _blobs(grid)
    true = nominal.perturbed(robot_coordination(0.3, 0.3, seed=1).sample(N_VIEWS))
    meas = forward_project(vol, grid, true)
    rec = fdk(meas, true, grid)  # the TRUE geometry: tests the per-view estimator alone
    return nominal, true, grid, meas, rec, roi_points(grid)


def _error(nominal, true, params, pts):
    return reprojection_error(nominal.perturbed(params), true, pts)["mean_px"]


@pytest.mark.parametrize("sigma", [None, 1.5], ids=["gdc", "gdc-log"])
def test_gdc_reduces_gauge_aligned_reprojection_error(problem, sigma):
    nominal, true, grid, meas, rec, pts = problem
    before = _error(nominal, true, np.zeros((N_VIEWS, 9)), pts)
    calls = []
    params, info = estimate_views_gdc(meas, nominal, np.zeros((N_VIEWS, 9)), rec, grid,
                                      GDCConfig(log_sigma_px=sigma, iterations=5),
                                      progress=lambda *a: calls.append(a))
    after = _error(nominal, true, params, pts)
    assert before > 1.0
    assert after < 0.15 * before, (before, after)
    assert params.shape == (N_VIEWS, 9) and len(calls) == 5
    assert info["cost"][-1] < 0.2 * info["cost"][0]
    assert all(np.diff(info["cost"]) <= 0)  # a step is only kept when it lowers the cost


def test_log_is_blind_to_a_constant_offset_and_l2_is_not(problem):
    nominal, true, grid, meas, rec, pts = problem
    offset = np.float32(0.3 * meas.max())
    zero = np.zeros((N_VIEWS, 9))
    out = {}
    for name, sigma in (("gdc", None), ("gdc-log", 1.5)):
        cfg = GDCConfig(log_sigma_px=sigma, iterations=4)
        p0, _ = estimate_views_gdc(meas, nominal, zero, rec, grid, cfg)
        p1, _ = estimate_views_gdc(meas + offset, nominal, zero, rec, grid, cfg)
        out[name] = (_error(nominal, true, p0, pts), _error(nominal, true, p1, pts), np.abs(p1 - p0).max())
    e0, e1, dp_l2 = out["gdc"]
    assert e1 > 1.2 * e0 and dp_l2 > 0.1, out       # the offset pulls the L2 estimate away
    e0, e1, dp_log = out["gdc-log"]
    assert abs(e1 - e0) < 0.01 and e1 < 0.2, out    # LoG(constant) = 0: nothing changes
    assert dp_log < 1e-3 and dp_l2 > 100 * dp_log, out


def test_signature_and_validation(problem):
    nominal, true, grid, meas, rec, pts = problem
    with pytest.raises(ValueError):
        estimate_views_gdc(meas[:, :-1], nominal, np.zeros((N_VIEWS, 9)), rec, grid)
    with pytest.raises(ValueError):
        GDCConfig(log_sigma_px=-1.0)
    with pytest.raises(ValueError):
        default_gdc_configs("gdc-l1")
    # zero iterations leave the start untouched
    p0 = np.full((N_VIEWS, 9), 0.01)
    p, info = estimate_views_gdc(meas, nominal, p0, rec, grid, GDCConfig(iterations=0))
    np.testing.assert_array_equal(p, p0)


def test_calibrate_gdc_alternating_loop_improves_geometry(problem):
    nominal, true, grid, meas, rec, pts = problem
    res = calibrate(meas, nominal, grid, method="gdc-log", iterations=1,
                        configs=(GDCConfig(log_sigma_px=1.0, iterations=3, fd_step=(0.1,) * 6 + (0.004,) * 3),
                                 GDCConfig(log_sigma_px=1.5, iterations=2)))
    assert res.method == "gdc-log" and len(res.history) == 1 and res.volume.shape == grid.shape_zyx
    assert _error(nominal, true, res.params, pts) < 0.5 * _error(nominal, true, np.zeros((N_VIEWS, 9)), pts)
