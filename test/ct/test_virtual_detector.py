"""Tests of robot_ct_ros.ct.virtual_detector: FDK on a detector rolled in its own plane.

The data are exact analytic line integrals of ellipsoids on each detector; the reference is FDK
of the same phantom on the upright detector (rows along the source motion), so the comparison
measures what the roll costs (the bilinear resampling onto the virtual detector), not FDK's own
error. Before the virtual detector, FDK filtered along the rolled rows: a few per cent off at
10 degrees, tens of per cent at 30, and all zeros at 90 (a portrait detector).
"""

import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from robot_ct_ros.ct.geometry import VolumeGrid
from robot_ct_ros.ct.reconstruction import fdk, fdk_backproject, fdk_filter_projections
from robot_ct_ros.ct.simulation import ellipsoid, ellipsoid_line_integrals
from robot_ct_ros.ct.trajectory import circular_scan
from robot_ct_ros.ct.virtual_detector import align_rows_to_motion, row_roll_deg

N_VOX, VOX_MM = 32, 0.3


def phantom(center=(0.0, 0.0, 0.0)):
    """Inside the field of view and inside the detector's top and bottom rows in every view."""
    c = np.asarray(center, dtype=float)
    return [ellipsoid(c, (5.0, 4.5, 4.5), 0.02, mode="add"),
            ellipsoid(c + [1.5, 1.0, 1.0], (1.2, 0.8, 1.0), 0.03, rotvec=(0.3, 0.2, 0.1), mode="add"),
            ellipsoid(c + [-2.0, -1.0, -1.0], (0.8, 1.5, 0.7), 0.04, mode="add")]


def scan(axis=(0.0, 0.0, 1.0), n_views=72, n=48):
    return circular_scan(n_views, 100.0, 200.0, n, n, 0.5, 0.5, axis=axis)


def rolled(geom, deg):
    """The detector turned by ``deg`` in its own plane about its centre (same w, same pixels)."""
    a = np.radians(deg)
    return geom.replace(u=np.cos(a) * geom.u + np.sin(a) * geom.v, v=-np.sin(a) * geom.u + np.cos(a) * geom.v)


def field_of_view():
    """Voxel mask (grid's own z, y, x) well inside the cone in every view."""
    z, y, x = np.meshgrid(*[np.arange(N_VOX) - 0.5 * (N_VOX - 1)] * 3, indexing="ij")
    return (x ** 2 + y ** 2 < 13.0 ** 2) & (np.abs(z) < 13.0)


def rel_rms(vol, ref):
    m = field_of_view()
    return float(np.sqrt(np.mean((vol[m] - ref[m]) ** 2)) / np.sqrt(np.mean(ref[m] ** 2)))


@pytest.fixture(scope="module")
def upright():
    g = scan()
    grid = VolumeGrid.centered((N_VOX,) * 3, VOX_MM)
    return g, grid, fdk(ellipsoid_line_integrals(phantom(), g), g, grid)


@pytest.mark.parametrize("deg, tol", [(10.0, 0.03), (30.0, 0.03), (-45.0, 0.03), (90.0, 1e-3)])
def test_rolled_detector_matches_upright(upright, deg, tol):
    g0, grid, ref = upright
    g = rolled(g0, deg)
    np.testing.assert_allclose(row_roll_deg(g), abs(deg) if abs(deg) <= 90 else 180 - abs(deg), atol=1e-6)
    vol = fdk(ellipsoid_line_integrals(phantom(), g), g, grid)
    assert rel_rms(vol, ref) < tol
    c = N_VOX // 2
    assert abs(vol[c, c, c] - ref[c, c, c]) < 0.01 * ref[c, c, c]


def test_portrait_detector_is_the_landscape_one_transposed():
    """Columns along the scan axis, the data transposed: the same rays, so the same volume (the
    virtual detector is then the landscape one, pixel for pixel). Old code: all zeros."""
    g0 = circular_scan(48, 100.0, 200.0, 32, 64, 0.5, 0.5)
    grid = VolumeGrid.centered((N_VOX,) * 3, VOX_MM)
    li = ellipsoid_line_integrals(phantom(), g0)
    mask = np.ones(g0.det_shape, bool)
    mask[10, 20] = False  # a dead pixel: it stays one dead pixel
    ref = fdk(li, g0, grid, valid_mask=mask)
    gp = g0.replace(u=g0.v, v=-g0.u, n_rows=g0.n_cols, n_cols=g0.n_rows)
    lp = np.ascontiguousarray(li[:, :, ::-1].transpose(0, 2, 1))
    mp = np.ascontiguousarray(mask[:, ::-1].T)
    # the other quarter turn too: (u, v) = (-v0, u0)
    gq = g0.replace(u=-g0.v, v=g0.u, n_rows=g0.n_cols, n_cols=g0.n_rows)
    lq = np.ascontiguousarray(li[:, ::-1, :].transpose(0, 2, 1))
    np.testing.assert_allclose(ellipsoid_line_integrals(phantom(), gq), lq, atol=1e-5)
    assert np.abs(fdk(lq, gq, grid, valid_mask=np.ascontiguousarray(mask[::-1, :].T)) - ref).max() \
        < 1e-4 * np.abs(ref).max()
    np.testing.assert_allclose(ellipsoid_line_integrals(phantom(), gp), lp, atol=1e-5)
    vd = align_rows_to_motion(lp, gp, grid.center_mm, valid_mask=mp)
    assert vd is not None and vd.geom.det_shape == g0.det_shape
    np.testing.assert_array_equal(vd.valid_mask, np.broadcast_to(mask, vd.valid_mask.shape))
    vol = fdk(lp, gp, grid, valid_mask=mp)
    assert np.abs(vol - ref).max() < 1e-4 * np.abs(ref).max()


@pytest.mark.parametrize("deg", [0.0, 2.0, 180.0])
def test_upright_scan_is_untouched(upright, deg):
    """Rows along the motion (or within the 3 degree tolerance, or turned half a turn, which
    the filter's sign handles): no virtual detector, and fdk is bit for bit the filter and
    back-projection of the data as they are."""
    g0, grid, _ = upright
    g = rolled(g0, deg)
    li = ellipsoid_line_integrals(phantom(), g)
    assert align_rows_to_motion(li, g, grid.center_mm) is None
    q, q_geom = fdk_filter_projections(li, g, center_mm=grid.center_mm)
    np.testing.assert_array_equal(fdk(li, g, grid), fdk_backproject(q, q_geom, grid))


@pytest.mark.parametrize("deg", [30.0, 90.0])
def test_rotated_world_axis_along_y(deg):
    """Scan about +y on a grid whose z follows the axis: nothing may assume a world axis."""
    R = Rotation.from_rotvec([-np.pi / 2, 0.0, 0.0]).as_matrix()  # grid z -> world +y
    g0 = scan(axis=(0.0, 1.0, 0.0))
    grid = VolumeGrid.centered((N_VOX,) * 3, VOX_MM, direction=R)
    ph = [ellipsoid((0.0, 0.0, 0.0), (5.0, 4.5, 4.5), 0.02, mode="add"),
          ellipsoid((1.5, 1.0, 1.0), (1.2, 1.0, 0.8), 0.03, rotvec=(0.3, 0.2, 0.1), mode="add"),
          ellipsoid((-2.0, -1.0, -1.0), (0.8, 0.7, 1.5), 0.04, mode="add")]
    ref = fdk(ellipsoid_line_integrals(ph, g0), g0, grid)
    g = rolled(g0, deg)
    vol = fdk(ellipsoid_line_integrals(ph, g), g, grid)
    assert rel_rms(vol, ref) < 0.03


def test_virtual_frame_and_bad_pixels(upright):
    """u' along the projected motion, w unchanged, (u', v', w) right-handed; bad pixels stay bad
    on the virtual detector and FDK still matches the upright scan."""
    g0, grid, ref = upright
    g = rolled(g0, 30.0)
    li = ellipsoid_line_integrals(phantom(), g)
    mask = np.ones(g.det_shape, bool)
    mask[20, 10:30] = False
    mask[5:40, 33] = False
    li[:, ~mask] = np.nan
    vd = align_rows_to_motion(li, g, grid.center_mm, valid_mask=mask)
    np.testing.assert_allclose(vd.geom.w, g.w, atol=1e-12)
    np.testing.assert_allclose(np.cross(vd.geom.u, vd.geom.v), g.w, atol=1e-12)
    np.testing.assert_allclose(vd.geom.u, g0.u, atol=1e-9)  # the upright rows, for a circle
    assert np.isfinite(vd.projections).all()
    assert not vd.valid_mask.all() and vd.valid_mask.mean() > 0.5
    vol = fdk(li, g, grid, valid_mask=mask)
    assert np.isfinite(vol).all()
    assert rel_rms(vol, ref) < 0.04


def test_a_rolled_displaced_detector_says_fdk_is_approximate():
    """Its redundancy weights are taken on the virtual detector (not exact): FDK says so, and is
    still far closer to the upright scan than filtering along the rolled rows."""
    g0 = circular_scan(72, 100.0, 200.0, 48, 40, 0.5, 0.5, det_offset_u_mm=5.0)
    grid = VolumeGrid.centered((N_VOX,) * 3, VOX_MM)
    ref = fdk(ellipsoid_line_integrals(phantom(), g0), g0, grid)
    g = rolled(g0, 30.0)
    with pytest.warns(RuntimeWarning, match="displaced detector turned in its plane"):
        vol = fdk(ellipsoid_line_integrals(phantom(), g), g, grid)
    assert rel_rms(vol, ref) < 0.15
    g = g0.replace(u=g0.v, v=-g0.u, n_rows=g0.n_cols, n_cols=g0.n_rows)  # portrait: the same detector
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        vol = fdk(ellipsoid_line_integrals(phantom(), g), g, grid)
    assert rel_rms(vol, ref) < 0.01


def test_a_detector_too_short_for_its_roll_is_filtered_as_it_is_and_says_so():
    """From an outside check: a two-row detector rolled 3.1 degrees lost half the slice's density on the virtual
    detector (its rows end at the real detector's top and bottom edges), against a few per cent filtered along the
    rolled rows. Such a detector is filtered as it is, with a warning; a tall one is still resampled."""
    g = rolled(circular_scan(90, 100.0, 200.0, 2, 96, 0.8, 0.8), 3.1)
    li = ellipsoid_line_integrals([ellipsoid(np.zeros(3), (9.0, 9.0, 30.0), 0.02, mode="add")], g)
    grid = VolumeGrid.centered((1, 40, 40), 0.6)
    with pytest.warns(RuntimeWarning, match="too short"):
        assert align_rows_to_motion(li, g) is None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        vol = fdk(li, g, grid)
        as_it_is = fdk_backproject(*fdk_filter_projections(li, g), grid)
    np.testing.assert_array_equal(vol, as_it_is)
    inside = np.hypot(*np.meshgrid(np.arange(40) - 19.5, np.arange(40) - 19.5)) < 10
    assert abs(vol[0][inside].mean() / 0.02 - 1.0) < 0.05  # the density kept (the virtual detector: about half)
    tall = rolled(scan(), 10.0)
    assert align_rows_to_motion(ellipsoid_line_integrals(phantom(), tall), tall) is not None
