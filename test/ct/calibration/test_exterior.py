"""The exterior model: the object outside the ROI, reconstructed with it."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from robot_ct_ros.ct.calibration.exterior import exterior_grid, exterior_support, joint_sirt
from robot_ct_ros.ct.calibration.volume import projection_consistency
from robot_ct_ros.ct.calibration.model import VolumeParts, project
from robot_ct_ros.ct.geometry import VolumeGrid
from robot_ct_ros.ct.projector import forward_project
from robot_ct_ros.ct.iterative import sirt
from robot_ct_ros.ct.simulation import mouse_phantom, voxelize
from robot_ct_ros.ct.trajectory import circular_scan


def test_the_exterior_grid_covers_the_rays_around_the_roi_in_any_frame():
    geom = circular_scan(24, 60.0, 150.0, 16, 32, 0.8, 0.8)
    roi = VolumeGrid.centered((8, 20, 20), 0.3)
    ext = exterior_grid(roi, geom, 1.0, half_width_mm=25.0)
    assert np.allclose(ext.direction_matrix, np.eye(3))
    assert ext.extent_mm[0] >= 50.0 and ext.extent_mm[1] >= 50.0  # +-25 mm across
    lo, hi = ext.bounds_mm()
    assert lo[2] < -4.0 and hi[2] > 4.0  # the cone's height at its widest, not the ROI's 2.4 mm
    up_to_sources = exterior_grid(roi, geom, 1.0)
    assert up_to_sources.extent_mm[0] >= 2 * 60.0 - 2.0
    sup = exterior_support(ext, roi)
    assert sup.shape == ext.shape_zyx and sup.min() == 0.0 and sup.max() == 1.0
    centre = ext.world_to_index(roi.center_mm).round().astype(int)
    assert sup[centre[2], centre[1], centre[0]] == 0.0  # the ROI is the ROI grid's
    R = Rotation.from_rotvec([0.3, -1.0, 0.4]).as_matrix()
    moved = exterior_grid(roi.moved(R), geom.moved(R), 1.0, half_width_mm=25.0)
    assert moved.shape_zyx == ext.shape_zyx and np.allclose(moved.direction_matrix, R)
    np.testing.assert_allclose(moved.center_mm, R @ ext.center_mm, atol=1e-9)
    # the same voxels are free, but for a few on the box's faces that rounding puts on the other side
    assert np.mean(exterior_support(moved, roi.moved(R)) != sup) < 1e-3


def test_the_roi_and_its_exterior_reproduce_a_truncated_scan_that_the_roi_alone_cannot():
    geom = circular_scan(36, 60.0, 150.0, 16, 24, 0.8, 0.8)
    fine = VolumeGrid.centered((40, 120, 120), 0.25)
    data = forward_project(voxelize(mouse_phantom(body_width_mm=24.0, length_mm=20.0), fine), fine, geom)
    roi = VolumeGrid.centered((12, 24, 24), 0.3)  # 7 mm of a 24 mm body
    ext = exterior_grid(roi, geom, 1.0, half_width_mm=16.0)
    x_roi, x_ext = joint_sirt(data, geom, [(None, roi, None), (None, ext, exterior_support(ext, roi))], 10, subsets=6)
    assert x_ext.min() >= 0.0 and x_roi.min() >= 0.0
    joint = projection_consistency(VolumeParts(((x_roi, roi), (x_ext, ext))), roi, geom, data, None)
    alone = projection_consistency(sirt(data, geom, roi, 60), roi, geom, data, None)
    assert joint[1] > 0.98 and joint[1] > alone[1] + 0.5, (joint, alone)
    np.testing.assert_allclose(project(VolumeParts(((x_roi, roi), (x_ext, ext))), roi, geom),
                               forward_project(x_roi, roi, geom) + forward_project(x_ext, ext, geom), rtol=1e-5)


def test_after_pass_runs_between_passes_on_the_parts_in_place():
    """The hook sees every pass: the parts as they are (changed in place) and copies from before it."""
    geom = circular_scan(12, 60.0, 150.0, 6, 10, 0.8, 0.8)
    roi = VolumeGrid.centered((6, 10, 10), 0.4)
    data = forward_project(np.full(roi.shape_zyx, 0.02, np.float32), roi, geom)
    seen = []

    def hook(xs, before):
        seen.append((len(xs), float(np.abs(xs[0] - before[0]).max())))
        xs[0][...] = 0.0  # in place: the next pass starts from zero again

    x_hooked, = joint_sirt(data, geom, [(None, roi, None)], 3, subsets=2, after_pass=hook)
    x_plain, = joint_sirt(data, geom, [(None, roi, None)], 1, subsets=2)
    assert len(seen) == 3 and all(n == 1 and moved > 0 for n, moved in seen)
    np.testing.assert_array_equal(x_hooked, 0.0)
    assert x_plain.max() > 0


def test_choose_reach_scores_each_candidate_on_held_out_views_and_picks_the_best_in_any_frame():
    """The candidates are REACH_FACTORS times the grid's half-width across its axis, short of the sources;
    the pick is the best held-out NCC; a rotated world gives the same reach and scores. On a 40 mm body
    through a 9 mm grid the pick lies short of the body's far side (20 mm), as on the scans measured."""
    from robot_ct_ros.ct.calibration.exterior import REACH_FACTORS, choose_reach

    geom = circular_scan(20, 60.0, 150.0, 16, 24, 0.8, 0.8)
    fine = VolumeGrid.centered((40, 170, 170), 0.25)
    data = forward_project(voxelize(mouse_phantom(body_width_mm=40.0, length_mm=20.0), fine), fine, geom)
    roi = VolumeGrid.centered((12, 30, 30), 0.3)  # 9 mm across: half-width 4.5 mm
    kw = dict(voxel_mm=2.0, iterations=10, subsets=5)
    choice = choose_reach(data, geom, roi, None, **kw)
    reaches = [r for r, _ in choice.scores]
    np.testing.assert_allclose(reaches, [4.5 * f for f in REACH_FACTORS if 4.5 * f < 60.0])
    assert choice.reach_mm == max(choice.scores, key=lambda rs: rs[1])[0]
    assert len({round(s, 4) for _, s in choice.scores}) > 1  # the candidates differ
    assert choice.reach_mm < 20.0, choice.scores
    assert f"{choice.reach_mm:.1f} mm" in choice.note()
    R = Rotation.from_rotvec([0.3, -1.0, 0.4]).as_matrix()
    moved = choose_reach(data, geom.moved(R), roi.moved(R), None, **kw)
    assert moved.reach_mm == choice.reach_mm
    np.testing.assert_allclose([s for _, s in moved.scores], [s for _, s in choice.scores], atol=2e-3)
    with pytest.raises(ValueError, match="20 views"):
        choose_reach(data[:12], geom.subset(np.arange(12)), roi, None, **kw)
