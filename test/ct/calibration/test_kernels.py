"""Detector homographies, warps and the fused warp-and-score kernel."""

import numpy as np
import pytest

from robot_ct_ros.ct.calibration.kernels import detector_homographies, warp_projections
from robot_ct_ros.ct.geometry import ConeGeometry


def _view(source, det_center, u, v, n_rows, n_cols, pitch):
    return ConeGeometry(source_mm=[source], detector_mm=[det_center], u=[u], v=[v], n_rows=n_rows,
                        n_cols=n_cols, row_pitch_mm=pitch, col_pitch_mm=pitch)


def _ray_image(geom: ConeGeometry) -> np.ndarray:
    """A smooth 'projection' that depends only on each pixel's ray: a function of where the ray
    crosses the plane x = 0 (the object's mid-plane). Any two detectors that see the same ray
    must show the same value there."""
    s = geom.source_mm[0]
    X = geom.pixel_centers_mm(0)
    t = -s[0] / (X[..., 0] - s[0])
    y = s[1] + t * (X[..., 1] - s[1])
    z = s[2] + t * (X[..., 2] - s[2])
    return (np.sin(0.4 * y) * np.cos(0.3 * z) + 0.02 * y * z).astype(np.float32)


def test_homography_warp_equals_direct_image_of_moved_detector():
    source = np.array([120.0, 0.0, 0.0])
    virtual = _view(source, [-200.0, 0.0, 0.0], [0, 1, 0], [0, 0, 1], 240, 320, 0.1)
    # the moved detector: shifted, tilted and skewed, with another pixel grid
    params = np.array([[0, 0, 0, 0.8, -0.5, 1.5, np.deg2rad(2.0), np.deg2rad(-1.5), np.deg2rad(3.0)]])
    nominal = _view(source, [-200.0, 0.0, 0.0], [0, 1, 0], [0, 0, 1], 150, 200, 0.11)
    moved = nominal.perturbed(params)
    H = detector_homographies(virtual, moved)
    warped, valid = warp_projections(_ray_image(virtual)[None], H, [0], moved.n_rows, moved.n_cols)
    direct = _ray_image(moved)
    assert valid.all()
    err = np.abs(warped[0] - direct)
    assert err.max() < 2e-3 * np.abs(direct).max()
    # and an unrelated detector pose does not match: the test can fail
    other = nominal.perturbed(params * 0.0 + np.array([0, 0, 0, 2.0, 0, 0, 0, 0, 0]))
    assert np.abs(warped[0] - _ray_image(other)).max() > 1e-2


def test_homography_requires_same_source_and_reports_off_detector_pixels():
    source = np.array([120.0, 0.0, 0.0])
    virtual = _view(source, [-200.0, 0.0, 0.0], [0, 1, 0], [0, 0, 1], 20, 20, 0.1)
    big = _view(source, [-200.0, 0.0, 0.0], [0, 1, 0], [0, 0, 1], 40, 40, 0.1)
    _, valid = warp_projections(np.ones((1, 20, 20), np.float32), detector_homographies(virtual, big), [0], 40, 40)
    assert valid.any() and not valid.all()
    with pytest.raises(ValueError):
        detector_homographies(virtual, big.replace(source_mm=[[121.0, 0.0, 0.0]]))


@pytest.mark.parametrize("background", [(0, 0), (2, 1)])
def test_fused_warp_and_score_sums_equal_those_of_the_stored_warps(background):
    """The scoring kernel (branch-free, never stores a warped image) accumulates the same sums
    as the warped images themselves, over the mask and only where the ray hits the virtual
    detector (some of these detectors hang over its edge)."""
    from robot_ct_ros.ct.calibration.kernels import N_SUMS, _warp_score_kernel
    from robot_ct_ros.ct.calibration.lle.weights import background_basis, project_out

    rng = np.random.default_rng(11)
    source = np.array([120.0, 0.0, 0.0])
    virtual = _view(source, [-200.0, 0.0, 0.0], [0, 1, 0], [0, 0, 1], 30, 40, 0.1)
    nominal = _view(source, [-200.0, 0.0, 0.0], [0, 1, 0], [0, 0, 1], 24, 36, 0.11)
    n_targets, S = 2, 5
    params = np.zeros((n_targets * S, 9))
    params[:, 3:6] = rng.uniform(-0.6, 0.6, size=(n_targets * S, 3))
    params[:, 6:9] = np.deg2rad(rng.uniform(-2.0, 2.0, size=(n_targets * S, 3)))
    moved = nominal.subset(np.zeros(n_targets * S, int)).perturbed(params)
    H = np.ascontiguousarray(detector_homographies(virtual.subset(np.zeros(n_targets * S, int)), moved))
    images = np.stack([_ray_image(virtual), rng.random((30, 40)).astype(np.float32)])
    image_index = rng.integers(0, 2, size=n_targets * S)
    target_index = np.repeat(np.arange(n_targets), S)
    measured = rng.random((n_targets, 24, 36)).astype(np.float32)
    mask = rng.random((n_targets, 24, 36)) > 0.2
    basis = background_basis(mask, *background)
    residual = project_out(measured, basis, mask)
    sums = np.empty((n_targets * S, N_SUMS + basis.shape[1]))
    _warp_score_kernel(images, H, image_index, target_index, measured, residual.astype(np.float32),
                       basis.astype(np.float32), mask.astype(np.float32), sums)

    warped, on = warp_projections(images, H, image_index, 24, 36)
    assert (~on).any() and on.any()
    use = (mask[target_index] & on).astype(np.float64)
    p = warped.astype(np.float64) * use
    b = measured[target_index].astype(np.float64)
    expected = np.stack([use.sum((1, 2)), p.sum((1, 2)), (p * p).sum((1, 2)), (p * b).sum((1, 2)),
                         (b * use).sum((1, 2)), (b * b * use).sum((1, 2)), (p * residual[target_index]).sum((1, 2))]
                        + [(p * basis[target_index, k]).sum((1, 2)) for k in range(basis.shape[1])], axis=1)
    np.testing.assert_allclose(sums, expected, rtol=1e-5, atol=1e-6 * np.abs(expected).max())
