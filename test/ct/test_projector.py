"""Tests of the Joseph forward projector and its adjoint (robot_ct_ros.ct.projector)."""

from __future__ import annotations

import numpy as np
import pytest

from robot_ct_ros.ct import projector
from robot_ct_ros.ct.geometry import ConeGeometry, VolumeGrid
from robot_ct_ros.ct.projector import back_project, forward_project


def circular_geometry(n_views, sod_mm=100.0, sdd_mm=200.0, n_rows=32, n_cols=40, pitch_mm=0.5,
                      center_mm=(0.0, 0.0, 0.0), arc_rad=2 * np.pi, start_rad=0.0):
    """Circular orbit about the world z axis around ``center_mm`` (u tangential, v = +z)."""
    a = start_rad + np.linspace(0.0, arc_rad, n_views, endpoint=False)
    c, s, zero = np.cos(a), np.sin(a), np.zeros(n_views)
    center = np.asarray(center_mm, dtype=np.float64)
    src = center + np.stack([sod_mm * c, sod_mm * s, zero], axis=1)
    det = center - (sdd_mm - sod_mm) * np.stack([c, s, zero], axis=1)
    u = np.stack([-s, c, zero], axis=1)
    v = np.tile([0.0, 0.0, 1.0], (n_views, 1))
    return ConeGeometry(src, det, u, v, n_rows, n_cols, pitch_mm, pitch_mm)


def perturb(geom, rng, scale_mm=2.0, scale_rad=0.05):
    p = rng.normal(size=(geom.n_views, 9)) * np.array([scale_mm] * 6 + [scale_rad] * 3)
    return geom.perturbed(p)


def all_axes_geometry(rng, n_rows=24, n_cols=28):
    """Perturbed views whose central rays run along x, y and z (every dominant axis)."""
    g = perturb(circular_geometry(8, n_rows=n_rows, n_cols=n_cols, start_rad=0.3), rng)
    # a view looking down the z axis: source above, detector below
    top = ConeGeometry(source_mm=[[1.0, -2.0, 100.0]], detector_mm=[[0.5, 1.0, -100.0]],
                       u=[[1.0, 0.0, 0.0]], v=[[0.0, 1.0, 0.0]], n_rows=n_rows, n_cols=n_cols,
                       row_pitch_mm=0.5, col_pitch_mm=0.5)
    return ConeGeometry.concatenate([g, perturb(top, rng)])


def smooth_phantom(grid, rng, n_ellipsoids=5):
    """A few Gaussian-blurred ellipsoids, exactly zero in the outer two voxel layers."""
    from scipy.ndimage import gaussian_filter

    nz, ny, nx = grid.shape_zyx
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    n = np.array([nx, ny, nz], dtype=np.float64)
    vol = np.zeros(grid.shape_zyx, dtype=np.float64)
    for _ in range(n_ellipsoids):
        c = rng.uniform(0.3, 0.7, 3) * n
        r = rng.uniform(0.08, 0.2, 3) * n
        inside = ((i - c[0]) / r[0]) ** 2 + ((j - c[1]) / r[1]) ** 2 + ((k - c[2]) / r[2]) ** 2 <= 1.0
        vol += inside * rng.uniform(0.5, 1.0)
    vol = gaussian_filter(vol, 1.5)
    vol[:2], vol[-2:], vol[:, :2], vol[:, -2:], vol[:, :, :2], vol[:, :, -2:] = 0, 0, 0, 0, 0, 0
    return vol.astype(np.float32)


def rel_adjoint_error(x, y, grid, geom):
    ax = forward_project(x, grid, geom)
    aty = back_project(y, geom, grid)
    lhs = float(np.dot(ax.ravel().astype(np.float64), y.ravel().astype(np.float64)))
    rhs = float(np.dot(x.ravel().astype(np.float64), aty.ravel().astype(np.float64)))
    return abs(lhs - rhs) / max(abs(lhs), abs(rhs)), lhs


def test_adjoint_perturbed_geometry_offcentre_anisotropic_grid():
    rng = np.random.default_rng(0)
    geom = all_axes_geometry(rng)
    # off-centre, anisotropic ROI grid that the rays enter and leave through every face
    grid = VolumeGrid((18, 22, 26), (0.45, 0.35, 0.55), origin_mm=(-4.0, -5.5, -3.0))
    x = rng.random(grid.shape_zyx, dtype=np.float32)
    y = rng.random((geom.n_views,) + geom.det_shape, dtype=np.float32)
    err, lhs = rel_adjoint_error(x, y, grid, geom)
    assert lhs > 0  # the rays do hit the volume
    assert err < 1e-4


def test_adjoint_partial_volumes_match_single_volume(monkeypatch):
    # the race-free back-projector must not depend on how the rays are split into chunks
    rng = np.random.default_rng(1)
    geom = perturb(circular_geometry(6, n_rows=16, n_cols=20), rng)
    grid = VolumeGrid.centered((16, 18, 20), (0.5, 0.5, 0.4), center_mm=(1.0, -1.0, 0.5))
    y = rng.random((geom.n_views,) + geom.det_shape, dtype=np.float32)
    ref = back_project(y, geom, grid)
    for n in (1, 3):
        monkeypatch.setattr(projector, "_n_partials", lambda n_vox, n_lines, n=n: n)
        np.testing.assert_allclose(back_project(y, geom, grid), ref, rtol=1e-5, atol=1e-5 * ref.max())
    assert ref.max() > 0


def test_uniform_cube_chords_along_each_axis():
    # anisotropic voxels; central rays along x, y and z cross the whole box edge to edge
    grid = VolumeGrid.centered((10, 12, 14), (0.3, 0.4, 0.5), center_mm=(2.0, -1.0, 3.0))
    ones = np.ones(grid.shape_zyx, dtype=np.float32)
    c = grid.center_mm
    views = []
    for axis, (uu, vv) in enumerate([((0, 1, 0), (0, 0, 1)), ((1, 0, 0), (0, 0, 1)), ((1, 0, 0), (0, 1, 0))]):
        e = np.zeros(3)
        e[axis] = 1.0
        views.append(ConeGeometry(source_mm=[c - 80 * e], detector_mm=[c + 80 * e], u=[uu], v=[vv],
                                  n_rows=9, n_cols=9, row_pitch_mm=0.05, col_pitch_mm=0.05))
    geom = ConeGeometry.concatenate(views)
    p = forward_project(ones, grid, geom)
    extent = grid.extent_mm
    for axis in range(3):
        # the central pixel's ray is exactly on the axis: chord = box extent (within a voxel)
        assert abs(p[axis, 4, 4] - extent[axis]) < 0.5 * grid.voxel_size_mm[axis]
    # a ray that misses the box, and a box behind the source, give exactly 0
    far = ConeGeometry(source_mm=[c + (0, 0, 30.0)], detector_mm=[c + (80.0, 0, 30.0)], u=[(0, 1, 0)],
                       v=[(0, 0, 1)], n_rows=3, n_cols=3, row_pitch_mm=0.1, col_pitch_mm=0.1)
    behind = ConeGeometry(source_mm=[c + (20.0, 0, 0)], detector_mm=[c + (100.0, 0, 0)], u=[(0, 1, 0)],
                          v=[(0, 0, 1)], n_rows=3, n_cols=3, row_pitch_mm=0.1, col_pitch_mm=0.1)
    assert np.all(forward_project(ones, grid, far) == 0)
    assert np.all(forward_project(ones, grid, behind) == 0)


def test_ball_chord_lengths():
    # oblique rays through a voxelised ball: line integral ~ analytic chord 2 sqrt(R^2 - d^2)
    grid = VolumeGrid.centered((64, 64, 64), 0.25, center_mm=(3.0, -2.0, 1.0))
    radius = 6.0
    z, y, x = np.meshgrid(*[a for a in grid.axes_mm()[::-1]], indexing="ij")
    c = grid.center_mm
    ball = (((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2) <= radius ** 2).astype(np.float32)
    rng = np.random.default_rng(2)
    geom = perturb(circular_geometry(5, n_rows=15, n_cols=15, pitch_mm=1.0, center_mm=c, start_rad=0.4),
                   rng, scale_mm=0.5, scale_rad=0.02)
    p = forward_project(ball, grid, geom)
    for view in range(geom.n_views):
        pix = geom.pixel_centers_mm(view).reshape(-1, 3)
        d = pix - geom.source_mm[view]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        w = c - geom.source_mm[view]
        dist2 = np.sum(w * w) - (d @ w) ** 2
        chord = 2 * np.sqrt(np.clip(radius ** 2 - dist2, 0, None))
        err = p[view].ravel() - chord
        vox = grid.voxel_size_mm[0]
        # central pixel (7, 7) of 15 x 15, its ray passes near the centre: within a voxel
        assert abs(err[7 * 15 + 7]) < vox
        # staircase of the binary ball: within 1.5 voxel everywhere, no bias on average
        assert np.abs(err).max() < 1.5 * vox
        assert abs(err[chord > 0].mean()) < 0.1 * vox
        assert chord.max() > radius  # the detector does see the ball


def test_batches_out_and_virtual_detector():
    rng = np.random.default_rng(3)
    grid = VolumeGrid.centered((20, 24, 22), (0.4, 0.4, 0.5), center_mm=(-1.0, 2.0, 0.0))
    vol = rng.random(grid.shape_zyx, dtype=np.float32)
    geom = perturb(circular_geometry(4, n_rows=20, n_cols=24, pitch_mm=0.4), rng)
    full = forward_project(vol, grid, geom)
    # one view at a time == one batched call
    for view in range(geom.n_views):
        np.testing.assert_array_equal(forward_project(vol, grid, geom.subset([view]))[0], full[view])
    # out= is overwritten and returned
    out = np.full(full.shape, np.nan, dtype=np.float32)
    assert forward_project(vol, grid, geom, out=out) is out
    np.testing.assert_array_equal(out, full)
    # an enlarged virtual detector (6 extra pixels on each side) contains the physical one
    big = forward_project(vol, grid, geom.with_detector(32, 36))
    np.testing.assert_allclose(big[:, 6:26, 6:30], full, rtol=1e-5, atol=1e-5 * full.max())
    assert full.max() > 0
    with pytest.raises(ValueError):
        forward_project(vol[:-1], grid, geom)


def test_translation_invariance_of_roi_grid():
    # moving volume and scanner together by a world offset changes nothing
    rng = np.random.default_rng(4)
    grid = VolumeGrid.centered((16, 20, 18), (0.5, 0.4, 0.45))
    vol = rng.random(grid.shape_zyx, dtype=np.float32)
    geom = perturb(circular_geometry(5, n_rows=16, n_cols=16), rng)
    shift = np.array([37.3, -12.1, 55.0])
    grid2 = VolumeGrid(grid.shape_zyx, grid.voxel_size_mm, tuple(np.asarray(grid.origin_mm) + shift))
    geom2 = geom.replace(source_mm=geom.source_mm + shift, detector_mm=geom.detector_mm + shift)
    a = forward_project(vol, grid, geom)
    b = forward_project(vol, grid2, geom2)
    np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-4 * a.max())
    assert a.max() > 0


def rtk_case():
    rng = np.random.default_rng(5)
    # perturbed, non-circular: irregular angles, per-view 9-DOF errors, off-centre ROI grid
    angles = np.sort(rng.uniform(0, 2 * np.pi, 30))
    base = ConeGeometry.concatenate([circular_geometry(1, n_rows=64, n_cols=64, pitch_mm=0.8,
                                                       start_rad=a, center_mm=(1.0, -2.0, 0.5))
                                     for a in angles])
    geom = perturb(base, rng, scale_mm=3.0, scale_rad=0.05)
    grid = VolumeGrid((48, 48, 48), (0.5, 0.45, 0.55), origin_mm=(-10.0, -12.0, -11.0))
    return geom, grid, smooth_phantom(grid, rng)


def test_matches_rtk_joseph():
    pytest.importorskip("itk")
    from robot_ct_ros.ct.rtk_bridge import rtk_forward_project

    geom, grid, vol = rtk_case()
    ours = forward_project(vol, grid, geom)
    ref = rtk_forward_project(vol, grid, geom)
    rel_rmse = np.sqrt(np.mean((ours - ref) ** 2) / np.mean(ref ** 2))
    assert ref.max() > 1.0
    # Joseph vs Joseph with matching conventions: float32 rounding only (measured ~2e-7)
    assert rel_rmse < 1e-5


def test_back_projection_matches_rtk_joseph_inside():
    # RTK's Joseph back-projector clips rays to the box of voxel centres, ours to the voxel
    # faces (see the module docstring): they agree away from the outer two voxel layers
    itk = pytest.importorskip("itk")
    from itk import RTK as rtk

    from robot_ct_ros.ct import rtk_bridge

    geom, grid, vol = rtk_case()
    proj = forward_project(vol, grid, geom)
    ours = back_project(proj, geom, grid)
    img = itk.Image[itk.F, 3]
    bp = rtk.JosephBackProjectionImageFilter[img, img].New()
    bp.SetInput(0, rtk_bridge.volume_to_itk(np.zeros(grid.shape_zyx, np.float32), grid))
    bp.SetInput(1, rtk_bridge.projections_to_itk(proj, geom))
    bp.SetGeometry(rtk_bridge.to_rtk_geometry(geom))
    bp.Update()
    ref = rtk_bridge.itk_to_volume(bp.GetOutput())[0]
    inner = (slice(2, -2),) * 3
    rel_rmse = np.sqrt(np.mean((ours[inner] - ref[inner]) ** 2) / np.mean(ref[inner] ** 2))
    assert np.mean(ref[inner] > 0) > 0.5  # most inner voxels are seen
    assert rel_rmse < 1e-5  # measured ~4e-7


def test_back_project_refuses_values_that_are_not_finite():
    """With fast-math a NaN pixel was taken for 0 without a word (the adjoint of forward_project spreads it)."""
    import pytest

    from robot_ct_ros.ct.geometry import VolumeGrid
    from robot_ct_ros.ct.projector import back_project
    from robot_ct_ros.ct.trajectory import circular_scan

    geom = circular_scan(4, 60.0, 150.0, 6, 8, 1.0, 1.0)
    grid = VolumeGrid.centered((4, 4, 4), 1.0)
    proj = np.ones((4, 6, 8), np.float32)
    assert np.isfinite(back_project(proj, geom, grid)).all()
    proj[1, 2, 3] = np.nan
    with pytest.raises(ValueError, match="1 NaN or infinite"):
        back_project(proj, geom, grid)


def test_forward_project_refuses_a_volume_that_is_not_finite():
    """One NaN voxel made every ray through it NaN without a word."""
    import pytest

    from robot_ct_ros.ct.geometry import VolumeGrid
    from robot_ct_ros.ct.projector import forward_project
    from robot_ct_ros.ct.trajectory import circular_scan

    geom = circular_scan(4, 60.0, 150.0, 6, 8, 1.0, 1.0)
    grid = VolumeGrid.centered((4, 4, 4), 1.0)
    vol = np.ones(grid.shape_zyx, np.float32)
    assert np.isfinite(forward_project(vol, grid, geom)).all()
    vol[1, 2, 3] = np.nan
    with pytest.raises(ValueError, match="1 NaN or infinite"):
        forward_project(vol, grid, geom)
    with pytest.raises(ValueError, match="NaN or infinite"):
        forward_project(np.full(grid.shape_zyx, 1e300), grid, geom)  # infinite as float32


def test_uniform_volume_chord_through_a_side_face_is_short_by_an_eighth_voxel_over_cos():
    """The documented shortfall (module docstring): a ray stepping along x that leaves through the +y face
    loses 1/8 voxel (y) / |cos(ray, y)| to the interpolation with the zero outside; the x faces are exact."""
    grid = VolumeGrid.centered((10, 10, 40), (1.0, 0.8, 1.0))
    ones = np.ones(grid.shape_zyx, np.float32)
    lo, hi = grid.bounds_mm()
    for slope in (0.05, 0.1, 0.2, 0.3):  # enters through the x = lo face
        d = np.array([1.0, slope, 0.0]) / np.hypot(1.0, slope)
        src = np.array([0.0, hi[1], 0.0]) - 200.0 * d  # leaves through y = hi[1] at x = 0
        u = np.cross([0.0, 0.0, 1.0], d)
        geom = ConeGeometry([src], [src + 400.0 * d], [u / np.linalg.norm(u)], [(0.0, 0.0, 1.0)], 1, 1, 0.01, 0.01)
        with np.errstate(divide="ignore"):
            t = np.stack([(lo - src) / d, (hi - src) / d])
        exact = np.nanmin(t.max(axis=0)) - np.nanmax(t.min(axis=0))
        short = exact - float(forward_project(ones, grid, geom)[0, 0, 0])
        assert short == pytest.approx(0.125 * 0.8 / d[1], rel=0.1), slope  # the slices sample the fade
