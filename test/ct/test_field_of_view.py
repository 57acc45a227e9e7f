"""The field of view: the voxels whose measured rays cover every direction (ct/field_of_view.py)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from robot_ct_ros.ct.field_of_view import field_of_view_mask
from robot_ct_ros.ct.geometry import VolumeGrid
from robot_ct_ros.ct.trajectory import circular_scan, fov_radius_mm


def _radius_mm(grid):
    """Distance of each voxel centre from the z axis, shaped like the grid."""
    nz, ny, nx = grid.shape_zyx
    idx = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"), -1).reshape(-1, 3)
    p = grid.index_to_world(idx)
    return np.hypot(p[:, 0], p[:, 1]).reshape(nx, ny, nz).transpose(2, 1, 0)


@pytest.mark.parametrize("offset_mm", [0.0, -4.0])
def test_field_of_view_mask_is_the_circle_the_rays_cover(offset_mm):
    """Centred detector: the circle every view sees; offset: the wider one the conjugate views fill in.
    Only voxels within a small band about that circle may differ (direction bins of a few degrees)."""
    n_cols, pitch = 100 if offset_mm == 0 else 60, 0.2
    geom = circular_scan(120, 100.0, 160.0, 1, n_cols, pitch, pitch, det_offset_u_mm=offset_mm)
    grid = VolumeGrid.centered((1, 90, 90), 0.2)
    edge = 0.5 * n_cols * pitch + abs(offset_mm)
    r_fov = fov_radius_mm(edge, 100.0, 160.0)
    radius = _radius_mm(grid)
    assert radius.max() > r_fov + 2.0 and radius.min() < 1.0  # the grid's corners lie outside
    mask = field_of_view_mask(geom, grid)
    wrong = mask != (radius <= r_fov)
    assert np.abs(radius[wrong] - r_fov).max() < 0.03 * r_fov
    assert wrong.mean() < 0.02


def test_field_of_view_mask_turns_with_the_scan_and_is_all_true_without_complete_data():
    geom = circular_scan(90, 100.0, 160.0, 4, 80, 0.2, 0.2)
    grid = VolumeGrid.centered((6, 80, 80), 0.2)
    mask = field_of_view_mask(geom, grid)
    assert 0.3 < mask.mean() < 0.9
    R = Rotation.from_rotvec([0.4, -1.1, 0.7]).as_matrix()
    np.testing.assert_array_equal(field_of_view_mask(geom.moved(R, (5.0, -3.0, 20.0)), grid.moved(R, (5.0, -3.0, 20.0))),
                                  mask)
    # evaluated on blocks (a cost bound): the blocks' answers, close to the voxels' own
    coarse = field_of_view_mask(geom, grid, max_evaluations=90 * 6 * 80 * 80 / 8)
    assert (coarse != mask).mean() < 0.05
    # a quarter turn: no voxel's rays cover every direction, FDK is approximate everywhere, nothing is cut
    short = circular_scan(30, 100.0, 160.0, 4, 80, 0.2, 0.2, arc_rad=np.pi / 2)
    assert field_of_view_mask(short, grid).all()


def test_field_of_view_mask_of_a_portrait_detector_is_the_landscape_one():
    """The same rays on a detector turned a quarter in its plane (columns along the axis): its rows are the extent
    across the axis. Testing its columns took the cone's top and bottom for the field of view (100 % against 33 %)."""
    landscape = circular_scan(96, 60.0, 150.0, 16, 32, 1.0, 1.0)
    portrait = landscape.replace(u=landscape.v, v=-landscape.u, n_rows=landscape.n_cols, n_cols=landscape.n_rows)
    grid = VolumeGrid.centered((8, 40, 40), 0.5)
    mask = field_of_view_mask(landscape, grid)
    assert 0.2 < mask.mean() < 0.5
    np.testing.assert_array_equal(field_of_view_mask(portrait, grid), mask)


def test_cone_reach_counts_the_slices_the_cones_reach_and_suggests_a_shape_that_fits():
    """A 4-row detector, a grid 64 slices tall: the rays reach the middle 4 (the FDK puts 0 in the others), which
    field_of_view_mask, across the axis only, does not see; a grid those slices tall gets no note, nor one with none
    reached (FDK warns of that)."""
    from robot_ct_ros.ct.field_of_view import cone_reach

    geom = circular_scan(24, 60.0, 150.0, 4, 64, 0.5, 0.5)  # 4 rows of 0.5 mm: 0.8 mm tall at the centre (M 2.5)
    tall = VolumeGrid.centered((64, 48, 48), 0.2)
    assert field_of_view_mask(geom, tall).all()  # the cone's top and bottom are not its business
    reach = cone_reach(geom, tall)
    assert reach.axis == 2 and reach.mostly_outside()
    np.testing.assert_array_equal(np.flatnonzero(reach.slices), [30, 31, 32, 33])
    assert reach.outside_fraction == pytest.approx(60 / 64)
    note = reach.note()
    assert "the rays reach 4 of its 64 slices along z" in note and "slices 30-33" in note, note
    assert note.endswith("--shape 48,48,4"), note
    # the same answer where the budget samples the voxels across the axis
    coarse = cone_reach(geom, tall, max_evaluations=24 * 64 * 30)
    np.testing.assert_array_equal(coarse.slices, reach.slices)
    assert cone_reach(geom, tall.resized((4, 48, 48))).note() == ""
    assert cone_reach(geom, VolumeGrid.centered((8, 48, 48), 0.2, center_mm=(0, 0, 40))).note() == ""
    # a grid along y on a scan about y (the grid's z runs across the axis)
    tilted = VolumeGrid.centered((48, 64, 48), 0.2)
    rot = Rotation.from_euler("x", 90, degrees=True).as_matrix()
    about_y = geom.replace(source_mm=geom.source_mm @ rot.T, detector_mm=geom.detector_mm @ rot.T,
                           u=geom.u @ rot.T, v=geom.v @ rot.T)
    assert cone_reach(about_y, tilted).axis == 1 and cone_reach(about_y, tilted).n_reached == 4


def test_a_grid_wholly_outside_the_field_of_view_is_all_outside_and_the_field_of_view_is_located():
    """An outside tester's 20 mm ROI centred 40 mm off the axis of a scan whose field of view is 12.8 mm in radius
    read outside_field_of_view_fraction 0.0: "no voxel covered" was taken for a scan without complete data, and every
    voxel counted. A grid beyond the detector plane (300 mm off the axis of a 200 mm orbit) also counted as seen."""
    from robot_ct_ros.ct.field_of_view import cone_reach, field_of_view_extent

    geom = circular_scan(60, 200.0, 400.0, 16, 64, 0.8, 0.8)  # 6.4 mm tall at the axis: the grids fit the cones
    r_fov = fov_radius_mm(0.5 * 64 * 0.8, 200.0, 400.0)
    extent = field_of_view_extent(geom)
    assert extent.radius_mm == pytest.approx(r_fov, rel=0.05)
    assert np.allclose(extent.center_mm, 0.0, atol=1e-6) and abs(extent.axis[2]) == pytest.approx(1.0)
    off = VolumeGrid.centered((4, 20, 20), 1.0, center_mm=(40.0, 0.0, 0.0))
    assert not field_of_view_mask(geom, off).any()
    note = extent.misses_note(off)
    assert "the grid misses the field of view" in note and f"within {extent.radius_mm:.1f} mm" in note, note
    assert "[0.0, 0.0, 0.0] mm" in note and "40.0 mm from that axis" in note, note
    assert cone_reach(geom, off).outside_fraction == 0.0  # some view sees every voxel, from too few directions
    beyond = VolumeGrid.centered((4, 20, 20), 1.0, center_mm=(300.0, 0.0, 0.0))
    assert not field_of_view_mask(geom, beyond).any()
    assert cone_reach(geom, beyond).outside_fraction == 1.0  # behind every source or beyond every detector
    # a grid across the edge keeps its inside part; a limited-angle scan still has no field of view anywhere
    edge = field_of_view_mask(geom, VolumeGrid.centered((1, 20, 20), 1.0, center_mm=(12.0, 0.0, 0.0)))
    assert 0.05 < edge.mean() < 0.6
    short = circular_scan(30, 200.0, 400.0, 4, 64, 0.8, 0.8, arc_rad=np.pi / 2)
    assert field_of_view_extent(short) is None and field_of_view_mask(short, off).all()
