"""Fan-beam (one-row) and few-row detectors, end to end: projector, FDK, support mask, every estimator.

The phantom is 2D-ish (cylinders far longer than the slab any of these detectors sees), so a one-row
scan is a complete fan-beam scan of its slice. The errors are in the fan plane: detector shift
along the row (about 1 pixel), source position in the plane.
"""

import numpy as np
import pytest

from robot_ct_ros.ct.calibration import calibrate
from robot_ct_ros.ct.calibration.masks import roi_support_mask
from robot_ct_ros.ct.geometry import FAN_BEAM_PARAMS, PARAM_NAMES, VolumeGrid, observable_params
from robot_ct_ros.ct.metrics import ncc, reprojection_error, roi_points
from robot_ct_ros.ct.projector import forward_project
from robot_ct_ros.ct.reconstruction import fdk
from robot_ct_ros.ct.simulation import Phantom, box, elliptic_cylinder, voxelize
from robot_ct_ros.ct.trajectory import circular_scan

METHODS = ["ncc-lle-exact", "ncc-lle", "l2-lle", "gdc", "gdc-log"]
N_VIEWS, N_COLS, PITCH_MM = 60, 64, 0.4
HELD = [PARAM_NAMES.index(p) for p in PARAM_NAMES if p not in FAN_BEAM_PARAMS]


def _phantom():
    h = 30.0
    return Phantom("slab2d", (
        elliptic_cylinder((0, 0, 0), (4.5, 3.8), h, 0.02),
        elliptic_cylinder((1.5, 0.8, 0), (1.0, 1.4), h, 0.05),
        elliptic_cylinder((-1.8, -0.6, 0), (0.8, 0.8), h, 0.035),
        box((0.2, -2.0, 0), (1.2, 0.4, h), 0.045),
        elliptic_cylinder((-0.5, 2.0, 0), (0.4, 0.4), h, 0.06)))


def _in_plane_errors(seed=0):
    rng = np.random.default_rng(seed)
    err = np.zeros((N_VIEWS, 9))
    err[:, 3] = rng.normal(0.0, PITCH_MM, N_VIEWS)  # d_u: about 1 pixel
    err[:, 0] = rng.normal(0.0, 0.3, N_VIEWS)       # s_u
    err[:, 2] = rng.normal(0.0, 0.3, N_VIEWS)       # s_w
    return err


def _scan(n_rows):
    """Nominal and true geometry, the slab grid the cone sees at the centre, and the projections of a
    finer voxelisation along the true geometry."""
    nominal = circular_scan(N_VIEWS, 60.0, 150.0, n_rows, N_COLS, PITCH_MM, PITCH_MM)
    true = nominal.perturbed(_in_plane_errors())
    fine = VolumeGrid.centered((40, 100, 100), 0.1)
    measured = forward_project(voxelize(_phantom(), fine), fine, true)
    grid = VolumeGrid.centered((n_rows, 48, 48), (0.22, 0.22, PITCH_MM / 2.5))
    return nominal, true, grid, measured


@pytest.fixture(scope="module")
def fan():
    return _scan(1)


@pytest.fixture(scope="module")
def thin():
    return _scan(8)


def test_observable_parameters_of_a_fan_beam():
    nominal = circular_scan(4, 60.0, 150.0, 1, 8, 1.0, 1.0)
    free = observable_params(nominal)
    assert [PARAM_NAMES[k] for k in np.flatnonzero(free)] == ["s_u", "s_w", "d_u", "d_w", "r_v"]
    assert observable_params(nominal.with_detector(2, 8)).all()


def test_one_row_scan_reconstructs_and_reprojects_its_slice(fan):
    """The projector and FDK on a one-row detector and a grid one slice thick: the FDK with the true
    geometry is close to the phantom's slice and reprojects to the data."""
    _, true, grid, measured = fan
    assert measured.shape == (N_VIEWS, 1, N_COLS)
    vol = fdk(measured, true, grid)
    ref = voxelize(_phantom(), grid)
    inner = (slice(None), slice(4, -4), slice(4, -4))
    rel = np.sqrt(np.mean((vol - ref)[inner] ** 2) / np.mean(ref[inner] ** 2))
    assert rel < 0.15, rel
    assert ncc(forward_project(vol, grid, true), measured).min() > 0.99


def test_one_row_scan_calibrates_the_in_plane_parameters_and_holds_the_others(fan):
    nominal, true, grid, measured = fan
    pts = roi_points(grid)
    before = reprojection_error(nominal, true, pts)["mean_px"]
    result = calibrate(measured, nominal, grid, method="ncc-lle-exact", iterations=2)
    after = reprojection_error(result.geom, true, pts)["mean_px"]
    assert before > 0.8
    assert after < 0.3 * before, (before, after)
    assert np.all(result.params[:, HELD] == 0.0)  # what a fan beam cannot see stays nominal
    assert result.volume.shape == grid.shape_zyx and np.isfinite(result.volume).all()
    # and the result says so (neither the command line nor report.json did): what was estimated, what stays, why
    fan_notes = [n for n in result.notes if n.startswith("one-row detector (fan beam)")]
    assert len(fan_notes) == 1, result.notes
    assert "(s_u, s_w, d_u, d_w, r_v" in fan_notes[0] and "s_v, d_v, r_u, r_w stay nominal" in fan_notes[0]
    assert "docs/calibration.md §5b" in fan_notes[0]


def test_only_a_one_row_detector_gets_the_fan_beam_note():
    from robot_ct_ros.ct.calibration.loop import fan_beam_note

    nominal = circular_scan(4, 60.0, 150.0, 1, 8, 1.0, 1.0)
    assert fan_beam_note(nominal).startswith("one-row detector (fan beam): only the 5 parameters")
    assert fan_beam_note(nominal.with_detector(2, 8)) == ""


@pytest.mark.parametrize("method", METHODS)
def test_every_method_runs_on_a_one_row_scan(fan, method):
    nominal, true, grid, measured = fan
    pts = roi_points(grid)
    result = calibrate(measured, nominal, grid, method=method, iterations=1)
    assert np.isfinite(result.params).all() and np.all(result.params[:, HELD] == 0.0)
    assert not any("saw too little" in note for note in result.notes), result.notes
    before = reprojection_error(nominal, true, pts)["mean_px"]
    after = reprojection_error(result.geom, true, pts)["mean_px"]
    assert after < 0.7 * before, (method, before, after)


def test_a_thin_detector_keeps_its_rows_in_the_support_mask(thin):
    """Eight rows, the grid the slab their cone sees: every ray stays inside it, and the mask keeps
    them (it once kept the middle half). Rays that do leave through the top or bottom, of a grid half
    as tall, are still dropped; a normal detector keeps its margin at the top and bottom rows."""
    nominal, _, grid, _ = thin
    zero = np.zeros((N_VIEWS, 9))
    kept = roi_support_mask(nominal, zero, grid, 0.3)
    assert kept.mean() > 0.9, kept.mean(axis=(0, 2))
    assert kept.any(axis=(0, 2)).all()  # every row
    half = roi_support_mask(nominal, zero, grid.resized((4, 48, 48)), 0.3)
    np.testing.assert_array_equal(half.any(axis=(0, 2)), [False, False, True, True, True, True, False, False])
    normal = circular_scan(30, 60.0, 150.0, 48, 48, 32.0 / 48, 32.0 / 48)
    mask = roi_support_mask(normal, np.zeros((30, 9)), VolumeGrid.centered((32, 32, 32), 12.0 / 32), 0.3)
    rows = mask.mean(axis=(0, 2))
    assert rows[:3].max() == 0 and rows[-3:].max() == 0 and rows[8:40].min() > 0.9, rows


@pytest.mark.parametrize("method", METHODS)
def test_every_method_runs_on_a_thin_detector(thin, method):
    nominal, true, grid, measured = thin
    pts = roi_points(grid)
    result = calibrate(measured, nominal, grid, method=method, iterations=1)
    assert np.isfinite(result.params).all() and np.isfinite(result.volume).all()
    assert not any("saw too little" in note for note in result.notes), result.notes
    before = reprojection_error(nominal, true, pts)["mean_px"]
    after = reprojection_error(result.geom, true, pts)["mean_px"]
    assert after < 0.7 * before, (method, before, after)


def test_the_field_of_view_support_keeps_fdk_streaks_in_the_corners_out_of_the_estimate(fan):
    """The square grid's corners lie outside the fan's field of view, where FDK's incomplete data
    leave streaks that are no object. Started at the true
    geometry, the estimate leaves it less when the estimation volume is zero there (fov_support,
    auto for a scan whose detector edges see air), on every sampling seed."""
    from robot_ct_ros.ct.field_of_view import field_of_view_mask

    _, true, grid, measured = fan
    assert not field_of_view_mask(true, grid).all()
    pts = roi_points(grid)
    for seed in (1, 2):
        moved = {fs: reprojection_error(calibrate(measured, true, grid, method="ncc-lle-exact", fov_support=fs,
                                                  seed=seed).geom, true, pts)["mean_px"] for fs in ("on", "off", "auto")}
        assert moved["on"] < 0.85 * moved["off"], moved
        assert moved["auto"] == moved["on"], moved


def test_a_one_row_scan_on_a_grid_whose_slices_all_miss_the_fan_plane(fan):
    """A one-row detector back-projects onto the voxels within half a pixel of its plane: a grid of an even number
    of thick slices centred on it has none. The calibration still corrects (its estimation volumes are its own),
    and FDK of that grid says that it put nothing there (it returned zeros silently)."""
    import warnings

    from robot_ct_ros.ct.reconstruction import FDKWarning

    nominal, true, grid, measured = fan
    thick = VolumeGrid.centered((8,) + grid.shape_zyx[1:], grid.voxel_size_mm[:2] + (0.4,))  # slices at +-0.2 mm...
    pts = roi_points(grid)
    before = reprojection_error(nominal, true, pts)["mean_px"]
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always", FDKWarning)
        result = calibrate(measured, nominal, thick, method="ncc-lle-exact", iterations=2)
    after = reprojection_error(result.geom, true, pts)["mean_px"]
    assert after < 0.3 * before, (before, after)
    assert result.volume.shape == thick.shape_zyx and not result.volume.any()
    assert any(issubclass(w.category, FDKWarning) and "put nothing into the grid" in str(w.message) for w in seen)
