"""No frame is special: a scan moved rigidly as a whole calibrates to the same correction, moved."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from robot_ct_ros.ct.calibration import calibrate
from robot_ct_ros.ct.geometry import VolumeGrid, axis_frame
from robot_ct_ros.ct.metrics import reprojection_error, roi_points
from robot_ct_ros.ct.projector import forward_project
from robot_ct_ros.ct.reconstruction import fdk
from robot_ct_ros.ct.simulation import mouse_phantom, robot_coordination, voxelize
from robot_ct_ros.ct.trajectory import circular_scan


def _scan(n_views=24, n_det=40):
    nominal = circular_scan(n_views, 60.0, 150.0, n_det, n_det, 32.0 / n_det, 32.0 / n_det)
    grid = VolumeGrid.centered((24, 28, 28), 12.0 / 28)
    phantom = mouse_phantom(body_width_mm=9.0, length_mm=10.0)
    fine = VolumeGrid.centered((64, 64, 64), 0.2)
    true = nominal.perturbed(robot_coordination(0.3, 0.3, seed=4).sample(n_views))
    return nominal, true, grid, forward_project(voxelize(phantom, fine), fine, true)


def _motions(seed):
    rng = np.random.default_rng(seed)
    return Rotation.random(random_state=rng).as_matrix(), rng.uniform(-50.0, 50.0, 3)


@pytest.mark.parametrize("method", ["ncc-lle-exact", "gdc-log"])
def test_a_rigidly_moved_scan_calibrates_to_the_moved_correction(method):
    nominal, true, grid, measured = _scan()
    R, t = _motions(7)
    # the projections of a moved scan are the same arrays: object and scanner move together
    here = calibrate(measured, nominal, grid, method=method, iterations=1)
    there = calibrate(measured, nominal.moved(R, t), grid.moved(R, t), method=method, iterations=1)
    pts = roi_points(grid)
    before = reprojection_error(nominal, true, pts)["mean_px"]
    after = reprojection_error(here.geom, true, pts)["mean_px"]
    assert after < 0.7 * before, (before, after)  # the calibration did something worth comparing
    moved_pts = pts @ R.T + t
    apart = reprojection_error(there.geom, here.geom.moved(R, t), moved_pts, align_gauge=False)["mean_px"]
    assert apart < 0.05 * before, (apart, before)  # sampling scatter at most: here float rounding
    np.testing.assert_allclose(there.params, here.params, atol=1e-3)  # local detector frames: invariant
    # the volume on the moved grid is the same, up to what a Gauss-Newton step accepted in one frame and
    # rejected in the other (float rounding) changes: the RMS difference, relative to the volume's
    rms = np.sqrt(np.mean((there.volume - here.volume) ** 2)) / np.sqrt(np.mean(here.volume ** 2))
    assert rms < 1e-3, rms


def test_oriented_grids_project_and_reconstruct_like_the_world_axes():
    """A grid whose axes are rotated sees the same object: its projections and FDK equal those of
    the axis-aligned grid after the same rotation of the scan."""
    nominal, _, grid, measured = _scan(n_views=36)
    R, t = _motions(3)
    vol = fdk(measured, nominal, grid)
    np.testing.assert_allclose(fdk(measured, nominal.moved(R, t), grid.moved(R, t)), vol, atol=1e-4 * vol.max())
    p = forward_project(vol, grid, nominal)
    np.testing.assert_allclose(forward_project(vol, grid.moved(R, t), nominal.moved(R, t)), p,
                               atol=1e-4 * p.max())


def test_axis_frame_puts_the_grid_z_on_the_scan_axis():
    np.testing.assert_array_equal(axis_frame([0, 0, 1]), np.eye(3))
    np.testing.assert_array_equal(axis_frame([0, 0, -1]), np.eye(3))  # either sense of the same axis
    D = axis_frame([0.0, 1.0, 0.0])
    np.testing.assert_allclose(D[:, 2], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(D.T @ D, np.eye(3), atol=1e-12)
    a = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    np.testing.assert_allclose(axis_frame(a)[:, 2], a, atol=1e-12)
    assert np.linalg.det(axis_frame(a)) == pytest.approx(1.0)


@pytest.mark.parametrize("method", ["ncc-lle-exact", "ncc-lle", "l2-lle", "gdc", "gdc-log"])
def test_views_that_see_little_of_the_grid_do_not_stop_the_calibration(method):
    """Two views whose detector sits 40 mm to the side: their rays miss the ROI grid. They keep
    their geometry (up to the global gauge and magnification fix) and the report says so."""
    nominal, true, grid, measured = _scan(n_views=16)
    off = np.zeros((16, 9))
    off[[3, 11], 3] = 40.0
    away = nominal.perturbed(off)
    result = calibrate(measured, away, grid, method=method, iterations=1)
    assert np.isfinite(result.params).all() and np.isfinite(result.volume).all()
    assert any("[3, 11]" in note for note in result.notes), result.notes
    pts = roi_points(grid)
    others = np.setdiff1d(np.arange(16), [3, 11])
    before = reprojection_error(nominal.subset(others), true.subset(others), pts)["mean_px"]
    after = reprojection_error(result.geom.subset(others), true.subset(others), pts)["mean_px"]
    assert after < before, (before, after)
