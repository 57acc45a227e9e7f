"""Tests of robot_ct_ros.ct.trajectory (circular and robotic ROI scans)."""


import numpy as np
import pytest

from robot_ct_ros.ct.trajectory import (SeedSystem, circular_scan, detector_edge_for_fov_mm, fov_radius_mm,
                                        robotic_roi_scan, roi_scan_offset_mm)


def test_circular_scan_conventions():
    g = circular_scan(8, 100.0, 300.0, 20, 30, 0.4, 0.5)
    assert g.n_views == 8 and g.det_shape == (20, 30)
    np.testing.assert_allclose(g.sdd_mm, 300.0)
    np.testing.assert_allclose(g.magnification(), 3.0)
    # source on +x at angle 0, u = +y, v = +z, w = u x v pointing from detector to source
    np.testing.assert_allclose(g.source_mm[0], [100.0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(g.detector_mm[0], [-200.0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(g.u[0], [0, 1.0, 0], atol=1e-12)
    np.testing.assert_allclose(g.v, np.tile([0, 0, 1.0], (8, 1)), atol=1e-12)
    assert np.all(np.einsum("ij,ij->i", g.source_mm - g.detector_mm, g.w) > 0)
    # counter-clockwise about +z: view 2 (90 degrees) has its source on +y
    np.testing.assert_allclose(g.source_mm[2], [0, 100.0, 0], atol=1e-12)
    # equally spaced angles, full circle without repeating the first view
    ang = np.unwrap(np.arctan2(g.source_mm[:, 1], g.source_mm[:, 0]))
    np.testing.assert_allclose(np.diff(ang), 2 * np.pi / 8)


def test_circular_scan_axis_center_offset_and_arc():
    c = np.array([3.0, -1.0, 2.0])
    g = circular_scan(6, 80.0, 200.0, 10, 21, 1.0, 1.0, arc_rad=np.pi, start_rad=0.3, det_offset_u_mm=4.0,
                      center_mm=c, axis=(0, 1, 0))
    np.testing.assert_allclose(g.v, np.tile([0, 1.0, 0], (6, 1)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(g.source_mm - c, axis=1), 80.0)
    np.testing.assert_allclose(g.magnification(c), 200.0 / 80.0)
    # the centre projects onto column (n-1)/2 - offset/pitch, row (n-1)/2, in every view
    cr = g.project_points(c)[:, 0]
    np.testing.assert_allclose(cr[:, 0], 10.0 - 4.0, atol=1e-9)
    np.testing.assert_allclose(cr[:, 1], 4.5, atol=1e-9)
    # sources stay in the plane through c perpendicular to the axis, spanning [0.3, 0.3 + pi]
    np.testing.assert_allclose(g.source_mm[:, 1], c[1], atol=1e-12)
    with pytest.raises(ValueError):
        circular_scan(4, 300.0, 200.0, 4, 4, 1.0, 1.0)
    with pytest.raises(ValueError):
        circular_scan(4, 100.0, 200.0, 4, 4, 1.0, 1.0, axis=(0, 0, 0))


def test_seed_system_figures():
    s = SeedSystem()
    assert s.sod_mm == pytest.approx(342.4 / 2.67)
    assert 128.0 < s.sod_mm < 128.5
    assert s.n_cols_raw * s.raw_pixel_mm <= 70.0 < (s.n_cols_raw + 1) * s.raw_pixel_mm
    assert s.n_rows_raw * s.raw_pixel_mm <= 30.0 < (s.n_rows_raw + 1) * s.raw_pixel_mm


def test_robotic_roi_scan_full_detector():
    s = SeedSystem()
    roi = np.array([5.0, -10.0, 20.0])
    g = robotic_roi_scan(s, roi_center_mm=roi, fov_diameter_mm=50.0)
    assert g.n_views == 360
    assert g.col_pitch_mm == pytest.approx(0.110) and g.row_pitch_mm == pytest.approx(0.110)
    assert g.det_shape == (s.n_rows_raw // 2, s.n_cols_raw // 2)
    np.testing.assert_allclose(g.sdd_mm, 342.4)
    np.testing.assert_allclose(g.magnification(roi), 2.67)
    # the source faces the ROI centre: the central ray (source -> ROI) is the detector normal
    to_roi = roi - g.source_mm
    to_roi /= np.linalg.norm(to_roi, axis=1, keepdims=True)
    np.testing.assert_allclose(to_roi, -g.w, atol=1e-12)
    # 50 mm needs an offset detector, within the half width
    half = 0.5 * g.n_cols * g.col_pitch_mm
    offset = roi_scan_offset_mm(50.0, half, s.sod_mm, s.sdd_mm)
    assert 0 < offset <= half
    col = g.project_points(roi)[:, 0, 0]
    np.testing.assert_allclose(col, (g.n_cols - 1) / 2 - offset / g.col_pitch_mm, atol=1e-9)
    # the 50 mm FOV is exact: every line through points at radius 25 mm is measured, not so at 25.5 mm
    # (the paraxial rule (h + o) / M would leave the rim at 24.5 mm uncovered)
    phi = np.linspace(0, 2 * np.pi, 90, endpoint=False)
    ring = lambda rad: roi + np.stack([rad * np.cos(phi), rad * np.sin(phi), np.zeros_like(phi)], axis=1)
    c0 = (g.n_cols - 1) / 2 - offset / g.col_pitch_mm
    assert _line_measured(g, ring(24.99), c0).all()
    assert not _line_measured(g, ring(25.5), c0).all()
    # a 60 mm FOV cannot be reached with this detector
    with pytest.raises(ValueError):
        robotic_roi_scan(s, fov_diameter_mm=60.0)


def test_fov_relation_inverse_and_paraxial_limit():
    sod, sdd = 128.0, 342.0
    for r in (0.1, 5.0, 25.0):
        assert fov_radius_mm(detector_edge_for_fov_mm(r, sod, sdd), sod, sdd) == pytest.approx(r, rel=1e-12)
    assert fov_radius_mm(0.01, sod, sdd) == pytest.approx(0.01 * sod / sdd, rel=1e-6)


def _line_measured(g, pts, c0):
    """(n_views, n_points) bool: the ray through each point is measured in this view or its conjugate.

    Along the central ray's column c0 the detector extent is [-0.5 - c0, n_cols - 0.5 - c0] pixels; the
    conjugate view sees the same line at the mirrored coordinate.
    """
    t = g.project_points(pts)[..., 0] - c0
    lo, hi = -0.5 - c0, g.n_cols - 0.5 - c0
    on = (t >= lo) & (t <= hi)
    on_conj = (-t >= lo) & (-t <= hi)
    return on | on_conj


@pytest.mark.parametrize("fov_mm", [3.0, 6.0, 7.5])
def test_robotic_roi_scan_fov_coverage(fov_mm):
    """Reduced detector: points at the stated FOV radius are measured on every line, just outside they are not."""
    s = SeedSystem()
    roi = np.array([2.0, 3.0, -1.0])
    g = robotic_roi_scan(s, roi_center_mm=roi, fov_diameter_mm=fov_mm, n_views=120, n_rows=16, n_cols=96)
    half = 0.5 * g.n_cols * g.col_pitch_mm
    offset = roi_scan_offset_mm(fov_mm, half, s.sod_mm, s.sdd_mm)
    centred_fov = 2 * fov_radius_mm(half, s.sod_mm, s.sdd_mm)
    assert (offset > 0) == (fov_mm > centred_fov)
    # the stated FOV radius: the smallest one reached by the detector edge (exact when offset > 0)
    r = fov_radius_mm(half + offset, s.sod_mm, s.sdd_mm)
    assert r >= 0.5 * fov_mm - 1e-9
    c0 = (g.n_cols - 1) / 2 - offset / g.col_pitch_mm
    phi = np.linspace(0, 2 * np.pi, 90, endpoint=False)
    ring = lambda rad, z: roi + np.stack([rad * np.cos(phi), rad * np.sin(phi), np.full_like(phi, z)], axis=1)
    for z in (0.0, 0.3):  # off the central plane too: the transaxial coordinate ignores z
        assert _line_measured(g, ring(0.999 * r, z), c0).all()
        assert not _line_measured(g, ring(1.02 * r, z), c0).all()
    # every point inside the FOV is seen directly in at least (about) half the views
    seen = g.project_points(ring(0.999 * r, 0.0))[..., 0]
    direct = ((seen >= -0.5) & (seen <= g.n_cols - 0.5)).mean(axis=0)
    assert direct.min() >= 0.45


def test_circular_scan_about_y_is_a_plain_rtk_circular_orbit():
    """About world y the scan is RTK's standard orbit: positive SID/SDD, no tilts, gantry = theta + 90 deg."""
    pytest.importorskip("itk")
    from robot_ct_ros.ct.rtk_bridge import to_rtk_parameters

    g = circular_scan(12, 100.0, 300.0, 8, 10, 1.0, 1.0, start_rad=0.2, det_offset_u_mm=3.0, axis=(0, 1, 0))
    p = to_rtk_parameters(g)
    np.testing.assert_allclose(p[:, 0], 100.0, atol=1e-9)
    np.testing.assert_allclose(p[:, 1], 300.0, atol=1e-9)
    theta = np.degrees(0.2 + 2 * np.pi * np.arange(12) / 12)
    d = (p[:, 2] - (theta + 90.0) + 180.0) % 360.0 - 180.0
    np.testing.assert_allclose(d, 0.0, atol=1e-9)
    np.testing.assert_allclose(p[:, 3], 3.0, atol=1e-9)  # offset detector = RTK projection offset x
    np.testing.assert_allclose(p[:, [4, 7, 8]], 0.0, atol=1e-9)
    tilt = (p[:, [5, 6]] + 180.0) % 360.0 - 180.0
    np.testing.assert_allclose(tilt, 0.0, atol=1e-9)


def test_a_partial_arc_spans_the_whole_arc_and_a_full_circle_does_not_repeat_its_first_view():
    """A partial arc of A over n views ended at A (n-1)/n, as a full circle does: --arc-deg 190 with 12 views covered
    174.2 deg, at most half a turn, so no Parker weights. It now runs from the start to start + A; a full circle
    keeps its n equal steps of 360/n."""
    from robot_ct_ros.ct.scan_weights import scan_arc

    for arc_deg, start_deg in ((190.0, 0.0), (200.0, 30.0), (90.0, -10.0)):
        g = circular_scan(12, 100.0, 200.0, 4, 8, 1.0, 1.0, arc_rad=np.radians(arc_deg),
                          start_rad=np.radians(start_deg))
        ang = np.degrees(np.unwrap(np.arctan2(g.source_mm[:, 1], g.source_mm[:, 0])))
        np.testing.assert_allclose(ang, start_deg + arc_deg * np.arange(12) / 11, atol=1e-9)
        assert np.degrees(scan_arc(g)[0]) == pytest.approx(arc_deg, abs=1e-6)
    full = circular_scan(12, 100.0, 200.0, 4, 8, 1.0, 1.0)
    ang = np.degrees(np.unwrap(np.arctan2(full.source_mm[:, 1], full.source_mm[:, 0])))
    np.testing.assert_allclose(ang, 30.0 * np.arange(12), atol=1e-9)
    # a full circle turned the other way (a protocol's arc_deg -360) too; the first version repeated its first view
    back = circular_scan(12, 100.0, 200.0, 4, 8, 1.0, 1.0, arc_rad=-2 * np.pi)
    ang = np.degrees(np.unwrap(np.arctan2(back.source_mm[:, 1], back.source_mm[:, 0])))
    np.testing.assert_allclose(ang, -30.0 * np.arange(12), atol=1e-9)
