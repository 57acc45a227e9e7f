"""Streaming estimation: a running FDK volume grown view by view, each view estimated as it arrives."""

import numpy as np
import pytest

from robot_ct_ros.ct.calibration.lle.estimator import estimate_views
from robot_ct_ros.ct.calibration.masks import bin_masked
from robot_ct_ros.ct.calibration.settings import CalibrationSettings
from robot_ct_ros.ct.calibration.streaming import StreamingEstimator
from robot_ct_ros.ct.geometry import VolumeGrid
from robot_ct_ros.ct.projector import forward_project
from robot_ct_ros.ct.reconstruction import fdk, resample
from robot_ct_ros.ct.simulation import robot_coordination
from robot_ct_ros.ct.trajectory import circular_scan


def _scan(n_views=12, n_det=24):
    nominal = circular_scan(n_views, 60.0, 150.0, n_det, n_det, 32.0 / n_det, 32.0 / n_det)
    grid = VolumeGrid.centered((16, 16, 16), 12.0 / 16)
    z, y, x = np.meshgrid(*(np.arange(16) - 7.5,) * 3, indexing="ij")
    phantom = np.zeros(grid.shape_zyx, np.float32)
    for (cz, cy, cx), r, mu in (((0, 0, 0), 6.0, 0.02), ((2, -1, 3), 2.0, 0.03)):
        phantom[(z - cz) ** 2 + (y - cy) ** 2 + (x - cx) ** 2 < r * r] += mu
    true = nominal.perturbed(robot_coordination(0.2, 0.2, seed=3).sample(n_views))
    return nominal, grid, forward_project(phantom, grid, true), np.ones((n_views, n_det, n_det), bool)


def test_the_running_volume_is_the_fdk_of_the_views_so_far_and_warmup_waits():
    """method none: no estimate, the volume grows; after every view it is the FDK of the whole scan."""
    nominal, grid, li, mask = _scan()
    settings = CalibrationSettings(method="none", padding=1.0, coarse_binning=1, fine_binning=1)
    est = StreamingEstimator(settings, grid, nominal.n_views, warmup_views=3)
    steps = [est.add_views(li[i:i + 1], mask[i:i + 1], nominal.subset(np.array([i])), [i]) for i in range(2)]
    assert steps == [None, None] and not est.started
    first = est.add_views(li[2:5], mask[2:5], nominal.subset(np.arange(2, 5)), [2, 3, 4])
    # the warm-up views at once, and the views that came with the last of them against the first volume
    assert list(first.view_ids) == [0, 1, 2, 3, 4]
    assert np.isnan(first.ncc[:3]).all() and np.isfinite(first.ncc[3:]).all()
    assert first.geom.allclose(nominal.subset(np.arange(5)))
    for i in range(5, nominal.n_views):
        step = est.add_views(li[i:i + 1], mask[i:i + 1], nominal.subset(np.array([i])), [i])
        assert list(step.view_ids) == [i] and np.isfinite(step.ncc).all() and step.params.shape == (1, 9)
    assert est.n_estimated == nominal.n_views and np.isfinite(est.mean_ncc)
    ref = fdk(li, nominal, grid, valid_mask=mask)
    np.testing.assert_allclose(est.volume, ref, atol=2e-3 * float(np.abs(ref).max()))


def test_a_view_streamed_is_estimated_as_the_estimator_estimates_it_alone_against_that_volume():
    nominal, grid, li, mask = _scan()
    settings = CalibrationSettings(method="ncc-lle-exact")
    est = StreamingEstimator(settings, grid, nominal.n_views, warmup_views=4)
    est.add_views(li[:4], mask[:4], nominal.subset(np.arange(4)), np.arange(4))
    volume = est.volume
    step = est.add_views(li[4:6], mask[4:6], nominal.subset(np.arange(4, 6)), [4, 5])
    b = est.binning
    li_b, mask_b = bin_masked(li[5:6], mask[5:6], b)
    alone, _ = estimate_views(li_b, nominal.subset(np.array([5])).binned(b), np.zeros((1, 9)), volume, est.grid,
                              est.config, mask_b, view_ids=[5])
    np.testing.assert_allclose(step.params[1], alone[0], atol=1e-9)
    assert step.geom.allclose(nominal.subset(np.arange(4, 6)).perturbed(step.params))


def test_a_portrait_detector_streams_the_same_volume():
    """Columns along the scan axis (the same rays, the data transposed): each view is filtered with
    its rows along the source motion, as fdk does, not across it (which gave an empty volume)."""
    nominal, grid, li, mask = _scan()
    portrait = nominal.replace(u=nominal.v, v=-nominal.u, n_rows=nominal.n_cols, n_cols=nominal.n_rows)
    lp = np.ascontiguousarray(li[:, :, ::-1].transpose(0, 2, 1))
    settings = CalibrationSettings(method="none", padding=1.0, coarse_binning=1, fine_binning=1)
    est = StreamingEstimator(settings, grid, nominal.n_views, warmup_views=1)
    for i in range(nominal.n_views):
        est.add_views(lp[i:i + 1], mask[i:i + 1], portrait.subset(np.array([i])), [i])
    ref = fdk(li, nominal, grid, valid_mask=mask)
    np.testing.assert_allclose(est.volume, ref, atol=2e-3 * float(np.abs(ref).max()))


@pytest.mark.parametrize("axis, centre_mm", [((0.0, 1.0, 0.0), (0.0, 0.0, 0.0)),   # RTK's axis
                                             ((0.0, 0.0, 1.0), (3.0, 0.0, 0.0)),   # the grid off the scan centre
                                             ((0.6, 0.0, 0.8), (1.0, -2.0, 0.5))])
def test_the_running_volume_is_the_fdk_in_any_frame_with_the_grid_anywhere(axis, centre_mm):
    """The views are weighted about the scan's own axis and centre (from the warm-up views), as fdk takes them
    from the whole scan; the grid's z and centre gave a volume 48 % and 88 % off."""
    n_views, n_det = 24, 24
    nominal = circular_scan(n_views, 60.0, 150.0, n_det, n_det, 32.0 / n_det, 32.0 / n_det, axis=axis,
                            center_mm=centre_mm)
    grid = VolumeGrid.centered((16, 16, 16), 12.0 / 16)
    z, y, x = np.meshgrid(*(np.arange(16) - 7.5,) * 3, indexing="ij")
    phantom = np.zeros(grid.shape_zyx, np.float32)
    for (cz, cy, cx), r, mu in (((0, 0, 0), 6.0, 0.02), ((2, -1, 3), 2.0, 0.03)):
        phantom[(z - cz) ** 2 + (y - cy) ** 2 + (x - cx) ** 2 < r * r] += mu
    li = forward_project(phantom, grid, nominal)
    mask = np.ones(li.shape, bool)
    settings = CalibrationSettings(method="none", padding=1.0, coarse_binning=1, fine_binning=1)
    est = StreamingEstimator(settings, grid, n_views, warmup_views=4)
    for i in range(n_views):
        est.add_views(li[i:i + 1], mask[i:i + 1], nominal.subset(np.array([i])), [i])
    np.testing.assert_allclose(est.axis, np.asarray(axis) / np.linalg.norm(axis), atol=1e-6)
    np.testing.assert_allclose(est.center_mm, centre_mm, atol=1e-6)
    ref = fdk(li, nominal, grid, valid_mask=mask)
    np.testing.assert_allclose(resample(est.volume, est.grid, grid), ref, atol=2e-3 * float(np.abs(ref).max()))
