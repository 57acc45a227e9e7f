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


def test_the_axial_test_follows_the_scan_axis_not_the_grid_z():
    """A cube left world-aligned around a scan about +y (RTK's axis): the pixel mask's axial test stretched the
    grid along its own z, across the scan axis, so most views kept no pixels ("saw too little of the grid") and
    the correction ended 7 times worse than on a grid turned with the scan. The test now sweeps the grid along the
    scan axis: the same correction whichever way the cube is turned."""
    from robot_ct_ros.ct.calibration.masks import ray_chords_mm, roi_support_mask

    nominal, true, _, measured = _scan()
    cube = VolumeGrid.centered((28, 28, 28), 12.0 / 28)
    about_y = Rotation.from_rotvec([-np.pi / 2, 0.0, 0.0]).as_matrix()  # the scan's z axis to +y
    assert np.allclose(about_y @ [0.0, 0.0, 1.0], [0.0, 1.0, 0.0])
    t = np.array([3.0, -2.0, 5.0])
    world_cube = VolumeGrid.centered(cube.shape_zyx, cube.voxel_size_mm, center_mm=t)  # world axes: z across the scan
    turned_cube = cube.moved(about_y, t)
    zeros = np.zeros((nominal.n_views, 9))
    kept_world = roi_support_mask(nominal.moved(about_y, t), zeros, world_cube, 0.2)
    kept_turned = roi_support_mask(nominal.moved(about_y, t), zeros, turned_cube, 0.2)
    # the world cube is the turned one (a quarter turn maps a cube onto itself): the same swept body
    moved = nominal.moved(about_y, t)
    np.testing.assert_allclose(ray_chords_mm(moved, world_cube, 3.0, axis=[0.0, 1.0, 0.0]),
                               ray_chords_mm(moved, turned_cube, 3.0), atol=1e-4)
    assert kept_world.sum() > 0.9 * kept_turned.sum()  # the exact test alone: no margin at the end faces
    pts = roi_points(cube)
    before = reprojection_error(nominal, true, pts)["mean_px"]
    here = calibrate(measured, nominal.moved(about_y, t), world_cube, method="ncc-lle-exact", iterations=1)
    after = reprojection_error(here.geom, true.moved(about_y, t), pts @ about_y.T + t)["mean_px"]
    assert after < 0.5 * before, (before, after)
    assert not any("saw too little" in n for n in here.notes), here.notes


def test_ray_chords_in_a_grid_swept_along_an_oblique_axis():
    """The zonotope (box swept along a direction) chords against points sampled along each ray."""
    from robot_ct_ros.ct.calibration.masks import ray_chords_mm

    nominal, _, _, _ = _scan(n_views=3, n_det=12)
    grid = VolumeGrid.centered((6, 10, 8), (0.9, 0.7, 1.1), center_mm=(1.0, -2.0, 0.5))
    axis = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])
    chords = ray_chords_mm(nominal, grid, z_stretch=3.0, axis=axis)
    # brute force: a point is in the swept body when some shift along the axis puts it in the box
    half = 0.5 * np.asarray(grid.shape_xyz) * np.asarray(grid.voxel_size_mm)
    a = grid.direction_matrix.T @ axis
    reach = 2.0 * np.abs(a * half).sum()  # (3 - 1) / 2 times the box's length along the axis, each way
    shifts = np.linspace(-reach, reach, 801)
    r0 = 0.5 * (nominal.n_rows - 1) * nominal.row_pitch_mm
    c0 = 0.5 * (nominal.n_cols - 1) * nominal.col_pitch_mm
    t = np.linspace(0.0, 1.0, 4001)
    for v in range(nominal.n_views):
        for row, col in ((0, 0), (5, 7), (11, 3), (6, 6)):
            pix = (nominal.detector_mm[v] + (col * nominal.col_pitch_mm - c0) * nominal.u[v]
                   + (row * nominal.row_pitch_mm - r0) * nominal.v[v])
            p = nominal.source_mm[v] + t[:, None] * (pix - nominal.source_mm[v])
            local = (p - np.asarray(grid.center_mm)) @ grid.direction_matrix  # grid frame, mm about its centre
            inside = np.zeros(len(t), bool)
            for s in shifts:
                inside |= np.all(np.abs(local - s * a) <= half, axis=1)
            expect = inside.mean() * np.linalg.norm(pix - nominal.source_mm[v])
            assert chords[v, row, col] == pytest.approx(expect, abs=0.05 + 0.02 * expect)


def test_views_skipped_on_one_level_only_are_not_said_to_have_kept_their_geometry():
    """A two-row detector rolled 10 degrees on a three-slice grid: the coarse level (its rows binned to one) keeps no
    pixel of any view, the fine level estimates them all. The note said every view "kept its geometry", yet the
    result moved them; it now says on which level they were skipped and that the other estimated them."""
    from robot_ct_ros.ct.simulation import ellipsoid_line_integrals
    from robot_ct_ros.ct.simulation.phantoms import ellipsoid

    g0 = circular_scan(48, 100.0, 200.0, 2, 48, 0.5, 0.5)
    rot = Rotation.from_rotvec(np.deg2rad(10.0) * g0.w)
    geom = g0.replace(u=rot.apply(np.array(g0.u)), v=rot.apply(np.array(g0.v)))
    grid = VolumeGrid.centered((3, 24, 24), (0.4, 0.4, 0.25))
    li = ellipsoid_line_integrals([ellipsoid((0, 0, 0), (3.5, 3.0, 3.2), 0.02, mode="add"),
                                   ellipsoid((1.2, -0.8, 0.5), (1.0, 0.6, 0.9), 0.03, mode="add")], geom)
    result = calibrate(li, geom, grid, method="ncc-lle-exact", iterations=1)
    assert not any("kept their geometry" in n for n in result.notes), result.notes
    assert any("on the coarse level to be estimated there and were estimated on the fine level only" in n
               for n in result.notes), result.notes


def test_the_estimation_widens_a_grid_across_the_scan_axis_whichever_axis_of_the_grid_runs_along_it():
    """The estimation grid is the ROI widened across its x and y (padding); a world-aligned grid around a scan about
    +y was widened along the axis and not across it. axis_last renames the grid's axes (the same voxel centres) so
    that its z runs along the scan axis."""
    from robot_ct_ros.ct.calibration.volume import axis_last, estimation_grid

    nominal, _, _, _ = _scan(n_views=12, n_det=8)
    about_y = Rotation.from_rotvec([-np.pi / 2, 0.0, 0.0]).as_matrix()
    geom = nominal.moved(about_y, np.zeros(3))
    box = VolumeGrid.centered((6, 10, 14), (0.3, 0.4, 0.5), center_mm=(1.0, 2.0, -3.0))  # world axes: y along the scan
    renamed = axis_last(box, geom)
    assert abs(renamed.direction_matrix[:, 2] @ [0.0, 1.0, 0.0]) == pytest.approx(1.0)
    assert np.linalg.det(renamed.direction_matrix) == pytest.approx(1.0)
    def centres(g):  # every voxel centre, in world mm, as a sorted set
        idx = np.stack(np.meshgrid(*[np.arange(n) for n in g.shape_xyz], indexing="ij"), -1).reshape(-1, 3)
        pts = np.round(g.index_to_world(idx), 9)
        return pts[np.lexsort(pts.T)]

    np.testing.assert_allclose(centres(renamed), centres(box), atol=1e-9)
    wide = estimation_grid(renamed, 1.5)
    assert wide.shape_zyx[0] == box.shape_xyz[1]  # along the axis: as it was
    assert axis_last(renamed, geom) is renamed and axis_last(box, nominal) is box  # z along the axis already


def test_the_skipped_view_notes_name_only_what_happened_over_the_whole_run():
    """The notes merged every pass: a view one level skipped in one iteration and estimated in the next was said to be
    estimated on the other level only (on a one-level schedule, on a level that never ran), and a view the coarse
    level took once got two contradicting notes."""
    from robot_ct_ros.ct.calibration.loop import _skipped_view_notes

    none = {"coarse": set(), "fine": set()}
    # one level (no coarse passes): fine skipped view 3 in iteration 1 and estimated it in iteration 2
    assert _skipped_view_notes({"coarse": set(), "fine": {3}}, {"coarse": set(), "fine": set(range(8))}, 8) == []
    # the coarse level took view 3 in one pass and skipped it in another; the fine level never took it
    notes = _skipped_view_notes({"coarse": {3}, "fine": {3}}, {"coarse": set(range(8)), "fine": set(range(8)) - {3}}, 8)
    assert notes == ["1 view(s) saw too little of the grid on the fine level to be estimated there and were "
                     "estimated on the coarse level only: [3]"]
    # skipped everywhere: kept its geometry, and nothing else is said of it
    notes = _skipped_view_notes({"coarse": {5}, "fine": {5}}, {k: set(range(8)) - {5} for k in none}, 8)
    assert len(notes) == 1 and "kept their geometry" in notes[0] and "[5]" in notes[0]
