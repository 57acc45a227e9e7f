"""Quality measures: gauge removal, reprojection error, similarity, cap thickness."""

import numpy as np
import pytest

from robot_ct_ros.ct.geometry import VolumeGrid
from robot_ct_ros.ct.metrics import (cap_thickness_mm, edge_sharpness, fit_gauge, ncc, projection_rmse, psnr,
                                     remove_gauge, reprojection_error, rigidly_moved, roi_points, ssim)
from robot_ct_ros.ct.simulation import carotid_plaque_phantom, voxelize
from robot_ct_ros.ct.trajectory import circular_scan


@pytest.fixture
def scan():
    return circular_scan(24, 128.0, 342.4, 60, 80, 0.11, 0.11)


def test_gauge_removal_recovers_a_known_global_motion(scan):
    pts = roi_points(VolumeGrid.centered((20, 20, 20), 0.2))
    rotvec, t = np.array([0.01, -0.02, 0.015]), np.array([0.4, -0.3, 0.25])
    moved = rigidly_moved(scan, rotvec, t, pts.mean(axis=0))
    assert reprojection_error(moved, scan, pts, align_gauge=False)["mean_px"] > 2.0
    err = reprojection_error(moved, scan, pts)
    assert err["max_px"] < 1e-6
    # the fitted motion undoes the applied one
    back_rot, back_t, c = fit_gauge(moved, scan, pts)
    np.testing.assert_allclose(remove_gauge(moved, scan, pts).source_mm, scan.source_mm, atol=1e-6)
    np.testing.assert_allclose(back_rot, -rotvec, atol=1e-3)


def test_reprojection_error_of_a_detector_shift_is_the_shift_in_pixels(scan):
    pts = roi_points(VolumeGrid.centered((20, 20, 20), 0.2))
    shift_px = 1.5
    params = np.zeros((scan.n_views, 9))
    params[:, 3] = shift_px * scan.col_pitch_mm
    err = reprojection_error(scan.perturbed(params), scan, pts, align_gauge=False)
    assert err["mean_px"] == pytest.approx(shift_px, rel=1e-9)
    assert err["mean_u_px"] == pytest.approx(shift_px, rel=1e-9)
    # a shift across the rows (what a one-row fan beam cannot see) counts in the distance, not along the rows
    params[:, 3], params[:, 4] = 0.0, shift_px * scan.row_pitch_mm
    across = reprojection_error(scan.perturbed(params), scan, pts, align_gauge=False)
    assert across["mean_px"] == pytest.approx(shift_px, rel=1e-9) and across["mean_u_px"] < 1e-9
    # random per-view errors are not a gauge: aligning cannot remove them
    rng = np.random.default_rng(0)
    noisy = scan.perturbed(np.concatenate([rng.normal(0, 0.3, (24, 6)), rng.normal(0, 0.005, (24, 3))], 1))
    assert reprojection_error(noisy, scan, pts)["mean_px"] > 1.0


def test_similarity_measures():
    rng = np.random.default_rng(1)
    x = ndimage_blobs(rng)
    assert ssim(x, x) == pytest.approx(1.0)
    noisy = x + rng.normal(0, 0.05, x.shape)
    noisier = x + rng.normal(0, 0.2, x.shape)
    assert 1.0 > ssim(noisy, x) > ssim(noisier, x)
    assert psnr(noisy, x) > psnr(noisier, x)
    assert ncc((3.0 * x + 2.0).reshape(1, -1), x.reshape(1, -1))[0] == pytest.approx(1.0)
    assert projection_rmse(x + 0.5, x) == pytest.approx(0.5)
    from scipy.ndimage import gaussian_filter
    assert edge_sharpness(gaussian_filter(x, 1.5)) < edge_sharpness(x)


def ndimage_blobs(rng):
    z, y, x = np.mgrid[:24, :24, :24]
    vol = np.zeros((24, 24, 24))
    for _ in range(5):
        c = rng.uniform(5, 19, 3)
        vol[(z - c[0]) ** 2 + (y - c[1]) ** 2 + (x - c[2]) ** 2 < rng.uniform(4, 16)] += 1.0
    return vol


@pytest.mark.parametrize("thickness_mm", [0.06, 0.12])
def test_cap_thickness_of_the_voxelised_phantom(thickness_mm):
    ph = carotid_plaque_phantom(cap_thickness_mm=thickness_mm)
    cap = ph.cap
    centre = cap.lumen_point_mm + 0.5 * thickness_mm * np.asarray(cap.direction)
    grid = VolumeGrid.centered((12, 200, 200), (0.01, 0.01, 0.1), centre)
    vol = voxelize(ph, grid, supersample=3)
    assert cap_thickness_mm(vol, grid, cap) == pytest.approx(thickness_mm, abs=0.01)


def test_gauge_aligned_error_reports_the_motion_and_ignores_it(scan):
    from robot_ct_ros.ct.metrics import gauge_aligned_reprojection_error
    pts = roi_points(VolumeGrid.centered((20, 20, 20), 0.2), per_axis=4)
    rotvec, t = np.array([-0.02, 0.01, 0.03]), np.array([-0.2, 0.5, 0.1])
    moved = rigidly_moved(scan, rotvec, t, pts.mean(axis=0))
    res = gauge_aligned_reprojection_error(moved, scan, pts)
    assert res["mean_px"] < 1e-6 and res["p95_px"] < 1e-6
    # moving back by the fitted motion restores the geometry: the fit is the inverse motion
    g = res["gauge"]
    back = rigidly_moved(moved, g["rotvec_rad"], g["translation_mm"], g["center_mm"])
    assert back.allclose(scan, atol=1e-6)
    assert gauge_aligned_reprojection_error(moved, scan, pts, remove=False)["gauge"] is None


def test_ncc_is_blind_to_gain_and_offset_per_view_and_rmse_per_view():
    from robot_ct_ros.ct.metrics import mean_ncc
    rng = np.random.default_rng(5)
    a = rng.normal(size=(4, 10, 12))
    gain, off = rng.uniform(0.5, 3, 4), rng.normal(0, 5, 4)
    b = a * gain[:, None, None] + off[:, None, None]
    np.testing.assert_allclose(ncc(b, a), 1.0, atol=1e-12)
    mask = np.ones((10, 12), bool)
    mask[:, :3] = False
    c = b.copy()
    c[:, :, :3] = 1e6  # garbage outside the mask
    np.testing.assert_allclose(ncc(c, a, mask), 1.0, atol=1e-12)
    assert mean_ncc(a + rng.normal(0, 1, a.shape), a) < 0.9
    r = projection_rmse(a + np.arange(4)[:, None, None], a, per_view=True)
    np.testing.assert_allclose(r, np.arange(4), atol=1e-12)


def test_uniform_window_ssim_and_edge_rise_distance():
    from scipy.ndimage import gaussian_filter
    from robot_ct_ros.ct.metrics import edge_rise_distance_mm
    rng = np.random.default_rng(2)
    x = ndimage_blobs(rng)
    assert ssim(x, x, window="uniform") == pytest.approx(1.0)
    assert ssim(x + rng.normal(0, 0.05, x.shape), x, window="uniform") > ssim(
        x + rng.normal(0, 0.3, x.shape), x, window="uniform")
    # a step edge at x = 0 blurred by a Gaussian of sigma: 10-90 % width = 2.563 sigma
    grid = VolumeGrid.centered((4, 4, 200), 0.01)
    step = np.broadcast_to((grid.axes_mm()[0] > 0).astype(np.float32), grid.shape_zyx)
    for sigma_mm in (0.05, 0.1):
        blurred = gaussian_filter(step, (0, 0, sigma_mm / 0.01))
        w = edge_rise_distance_mm(3.0 * blurred + 7.0, grid, (-0.8, 0, 0), (0.8, 0, 0))
        assert w == pytest.approx(2.563 * sigma_mm, rel=0.03)


def test_cap_thickness_accepts_the_phantom_and_blur_widens_it():
    from scipy.ndimage import gaussian_filter
    ph = carotid_plaque_phantom(cap_thickness_mm=0.1)
    cap = ph.cap
    centre = cap.lumen_point_mm + 0.05 * np.asarray(cap.direction)
    grid = VolumeGrid.centered((12, 200, 200), (0.01, 0.01, 0.1), centre)
    vol = voxelize(ph, grid, supersample=3)
    sharp = cap_thickness_mm(vol, grid, ph)
    assert sharp == pytest.approx(0.1, abs=0.01)
    assert cap_thickness_mm(gaussian_filter(vol, (0, 6, 6)), grid, ph) > sharp + 0.02


def test_cap_thickness_is_nan_without_a_ridge():
    """A plain edge from lumen to core (no cap, or one blurred into the edge) is not a cap."""
    ph = carotid_plaque_phantom(cap_thickness_mm=0.06)
    cap = ph.cap
    grid = VolumeGrid.centered((40, 64, 64), 0.115, cap.lumen_point_mm + 0.03 * np.asarray(cap.direction))
    z, y, x = np.meshgrid(*[np.arange(n) for n in grid.shape_zyx], indexing="ij")
    pts = np.stack([x, y, z], axis=-1) * 0.115 + np.asarray(grid.origin_mm)
    depth = (pts - cap.lumen_point_mm) @ np.asarray(cap.direction)
    assert np.isnan(cap_thickness_mm((depth > 0.02).astype(np.float32), grid, cap))
    assert np.isnan(cap_thickness_mm(depth.astype(np.float32), grid, cap))  # a ramp has no ridge either


def _fine_cap_volume(thickness_mm=0.06):
    ph = carotid_plaque_phantom(cap_thickness_mm=thickness_mm)
    cap = ph.cap
    centre = cap.lumen_point_mm + 0.5 * thickness_mm * np.asarray(cap.direction)
    grid = VolumeGrid.centered((40, 200, 20), (0.02, 0.01, 0.05), centre)  # 10 um along the cap
    return cap, grid, voxelize(ph, grid, supersample=3)


def test_cap_thickness_needs_a_ridge_above_the_noise():
    """Independent noise per slice: a faint cap under strong noise is NaN by the noise test
    (while its highest bump would read as some width without it); under weak noise it measures."""
    from scipy.ndimage import gaussian_filter
    cap, grid, vol = _fine_cap_volume()
    rng = np.random.default_rng(0)
    noise = gaussian_filter(rng.normal(size=vol.shape), (0, 1, 1)).astype(np.float32)
    noise /= noise.std()
    contrast = 0.008  # cap against the core
    assert cap_thickness_mm(vol + 0.1 * contrast * noise, grid, cap) == pytest.approx(0.06, abs=0.01)
    loud = vol + 10 * contrast * noise
    assert np.isnan(cap_thickness_mm(loud, grid, cap))
    assert np.isfinite(cap_thickness_mm(loud, grid, cap, min_snr=0.0))


def test_cap_thickness_looks_for_the_ridge_at_the_cap_only():
    """A ridge 0.2 mm (20 voxels) off the cap is no cap (search_voxels=2), unless the search reaches it."""
    cap, grid, vol = _fine_cap_volume()
    d_axis = 1  # cap.direction is -y: along the grid's y axis
    assert np.asarray(cap.direction)[1] == pytest.approx(-1.0)
    moved = np.roll(vol, -20, axis=d_axis)  # 0.2 mm along -y: deeper than the cap, into the core
    assert np.isnan(cap_thickness_mm(moved, grid, cap))
    assert cap_thickness_mm(moved, grid, cap, search_voxels=26) == pytest.approx(0.06, abs=0.01)


def test_cap_thickness_drops_lines_outside_the_grid_and_needs_one():
    cap, grid, vol = _fine_cap_volume()
    # the grid spans ±1 mm along the vessel, the lines ±1.8 mm: the outer ones are dropped
    assert cap_thickness_mm(vol, grid, cap) == pytest.approx(0.06, abs=0.01)
    away = VolumeGrid(grid.shape_zyx, grid.voxel_size_mm, np.asarray(grid.origin_mm) + [0.0, 0.0, 10.0])
    with pytest.raises(ValueError, match="inside the grid"):
        cap_thickness_mm(vol, away, cap)


def test_ssim_and_psnr_on_constant_and_mismatched_images():
    """ssim(c, c) of a constant image was NaN and psnr of a constant reference -inf (its range, the default
    data_range, is 0); psnr broadcast images of different shapes."""
    import pytest

    from robot_ct_ros.ct.metrics import psnr, ssim

    c = np.ones((6, 6, 6))
    assert ssim(c, c) == 1.0 and psnr(c, c) == float("inf")
    for f in (lambda: psnr(c + 0.1, c), lambda: ssim(2 * c, c)):
        with pytest.raises(ValueError, match="data_range"):
            f()
    assert ssim(2 * c, c, data_range=1.0) < 1.0 and np.isfinite(psnr(c + 0.1, c, data_range=1.0))
    with pytest.raises(ValueError, match="shapes differ"):
        psnr(c[0], c)
