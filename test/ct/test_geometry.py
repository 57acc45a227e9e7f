"""Tests of robot_ct_ros.ct.geometry (conventions, 9-DOF parameters, serialisation, validation)."""

import json

import numpy as np
import pytest

from robot_ct_ros.ct.geometry import PARAM_NAMES, ConeGeometry, VolumeGrid, bin_projections


def _geom(n=12, n_rows=20, n_cols=27, row_pitch=0.3, col_pitch=0.25, seed=0, perturb=True):
    """A circular orbit about z (source on +x at angle 0) with a random 9-DOF perturbation."""
    th = np.linspace(0, 2 * np.pi, n, endpoint=False)
    w = np.stack([np.cos(th), np.sin(th), 0 * th], axis=1)
    v = np.tile([0.0, 0.0, 1.0], (n, 1))
    u = np.cross(v, w)
    g = ConeGeometry(100.0 * w, -200.0 * w, u, v, n_rows, n_cols, row_pitch, col_pitch)
    if not perturb:
        return g
    rng = np.random.default_rng(seed)
    p = np.concatenate([rng.normal(0, 0.5, (n, 6)), rng.normal(0, 0.01, (n, 3))], axis=1)
    return g.perturbed(p)


def _random_params(n, seed):
    rng = np.random.default_rng(seed)
    return np.concatenate([rng.normal(0, 1.0, (n, 6)), rng.normal(0, 0.05, (n, 3))], axis=1)


# ------------------------------------------------------------------ VolumeGrid
def test_volume_grid_centered_axes_bounds():
    g = VolumeGrid.centered((4, 6, 8), (0.5, 1.0, 2.0), center_mm=(1.0, 2.0, 3.0))
    assert g.shape_xyz == (8, 6, 4)
    np.testing.assert_allclose(g.center_mm, (1.0, 2.0, 3.0))
    np.testing.assert_allclose(g.extent_mm, (4.0, 6.0, 8.0))
    lo, hi = g.bounds_mm()
    np.testing.assert_allclose(lo, (-1.0, -1.0, -1.0))
    np.testing.assert_allclose(hi, (3.0, 5.0, 7.0))
    x, y, z = g.axes_mm()
    assert (len(x), len(y), len(z)) == (8, 6, 4)
    np.testing.assert_allclose(x[0], g.origin_mm[0])
    np.testing.assert_allclose(np.mean(x), 1.0)
    np.testing.assert_allclose(np.diff(z), 2.0)
    b = g.binned(2)
    assert b.shape_zyx == (2, 3, 4) and b.voxel_size_mm == (1.0, 2.0, 4.0)
    np.testing.assert_allclose(b.center_mm, g.center_mm)
    assert VolumeGrid.from_dict(json.loads(json.dumps(g.to_dict()))) == g


@pytest.mark.parametrize("kw", [dict(shape_zyx=(0, 2, 2), voxel_size_mm=(1, 1, 1)),
                                dict(shape_zyx=(2, 2), voxel_size_mm=(1, 1, 1)),
                                dict(shape_zyx=(2, 2, 2), voxel_size_mm=(1, 0, 1)),
                                dict(shape_zyx=(2, 2, 2), voxel_size_mm=(1, 1))])
def test_volume_grid_validation(kw):
    with pytest.raises(ValueError):
        VolumeGrid(**kw)


# ---------------------------------------------------------------- ConeGeometry
def test_basic_quantities():
    g = _geom(perturb=False)
    assert g.n_views == len(g) == 12 and g.det_shape == (20, 27)
    np.testing.assert_allclose(g.sdd_mm, 300.0)
    np.testing.assert_allclose(g.sod_mm(), 100.0)
    np.testing.assert_allclose(g.magnification(), 3.0)
    np.testing.assert_allclose(g.magnification((0, 0, 5.0)), 3.0)  # along the axis: same depth
    np.testing.assert_allclose(np.cross(g.u, g.v), g.w)
    B = g.local_frames()
    np.testing.assert_allclose(np.einsum("vji,vjk->vik", B, B), np.tile(np.eye(3), (12, 1, 1)), atol=1e-12)
    # geometry arrays are read-only, so a geometry cannot be changed behind its back
    with pytest.raises(ValueError):
        g.source_mm[0, 0] = 1.0


def test_validation_errors():
    g = _geom(n=3, perturb=False)
    kw = dict(source_mm=g.source_mm, detector_mm=g.detector_mm, u=g.u, v=g.v, n_rows=4, n_cols=4,
              row_pitch_mm=1.0, col_pitch_mm=1.0)
    ConeGeometry(**kw)  # the baseline is valid
    bad_nan = np.array(g.source_mm)
    bad_nan[1, 2] = np.nan
    bad_inf = np.array(g.detector_mm)
    bad_inf[0, 0] = np.inf
    cases = [
        dict(source_mm=bad_nan), dict(detector_mm=bad_inf),
        dict(u=2 * np.asarray(g.u)),  # not unit
        dict(v=np.asarray(g.v) * 1.001),
        dict(v=np.asarray(g.u)),  # not orthogonal (and u x v = 0)
        dict(detector_mm=g.detector_mm[:2]),  # mismatched view counts
        dict(u=g.u[:2]),
        dict(source_mm=np.zeros((3, 2))),  # not 3-vectors
        dict(n_rows=0), dict(n_cols=-1), dict(row_pitch_mm=0.0), dict(col_pitch_mm=-0.1),
    ]
    for change in cases:
        with pytest.raises(ValueError):
            ConeGeometry(**{**kw, **change})


def test_single_vectors_broadcast_to_all_views():
    g = ConeGeometry(np.array([[100.0, 0, 0], [0, 100.0, 0]]), [0.0, 0, 0], [0, 0, 1.0], [0, 1.0, 0], 4, 4, 1, 1)
    assert g.detector_mm.shape == (2, 3) and g.u.shape == (2, 3)


def test_perturbed_and_params_relative_to_round_trip():
    nominal = _geom(perturb=False)
    p = _random_params(nominal.n_views, 1)
    g = nominal.perturbed(p)
    assert not g.allclose(nominal, atol=1e-3)
    np.testing.assert_allclose(g.params_relative_to(nominal), p, atol=1e-10)
    np.testing.assert_allclose(nominal.params_relative_to(nominal), 0.0, atol=1e-12)
    # also relative to an already perturbed nominal geometry
    base = _geom(seed=5)
    np.testing.assert_allclose(base.perturbed(p).params_relative_to(base), p, atol=1e-10)
    # a single 9-vector applies to every view
    one = p[0]
    np.testing.assert_allclose(nominal.perturbed(one).params_relative_to(nominal), np.tile(one, (12, 1)), atol=1e-10)
    with pytest.raises(ValueError):
        nominal.perturbed(np.zeros((3, 9)))
    with pytest.raises(ValueError):
        g.params_relative_to(nominal.subset(slice(0, 3)))


def test_parameters_act_in_local_detector_frame():
    assert PARAM_NAMES == ("s_u", "s_v", "s_w", "d_u", "d_v", "d_w", "r_u", "r_v", "r_w")
    g = _geom(perturb=False)
    # source shift along w changes magnification; detector shift along u moves the image by whole pixels
    p = np.zeros(9)
    p[2] = 10.0
    np.testing.assert_allclose(g.perturbed(p).source_mm - g.source_mm, 10.0 * g.w, atol=1e-12)
    np.testing.assert_allclose(g.perturbed(p).magnification(), 310.0 / 110.0)
    p = np.zeros(9)
    p[3] = 2 * g.col_pitch_mm
    shift = g.perturbed(p).project_points([[1.0, 2.0, 3.0]]) - g.project_points([[1.0, 2.0, 3.0]])
    np.testing.assert_allclose(shift[..., 0], -2.0, atol=1e-9)  # detector moves +u -> image moves -2 columns
    np.testing.assert_allclose(shift[..., 1], 0.0, atol=1e-9)
    # r_w is an in-plane rotation about the detector centre: w fixed, u turned towards v
    p = np.zeros(9)
    p[8] = 0.1
    gr = g.perturbed(p)
    np.testing.assert_allclose(gr.w, g.w, atol=1e-12)
    np.testing.assert_allclose(gr.detector_mm, g.detector_mm, atol=1e-12)
    np.testing.assert_allclose(np.einsum("ij,ij->i", gr.u, g.v), np.sin(0.1), atol=1e-12)


def test_projection_matrices_match_pixel_centers():
    g = _geom(seed=2)
    P = g.projection_matrices()
    assert P.shape == (g.n_views, 3, 4)
    rows, cols = np.mgrid[0:g.n_rows, 0:g.n_cols]
    for i in range(g.n_views):
        pix = g.pixel_centers_mm(i)
        # any point on the ray source -> pixel centre projects onto that pixel
        for t in (0.3, 0.7, 1.0):
            pts = g.source_mm[i] + t * (pix - g.source_mm[i])
            hom = np.concatenate([pts, np.ones(pts.shape[:2] + (1,))], axis=2)
            q = hom @ P[i].T
            np.testing.assert_allclose(q[..., 0] / q[..., 2], cols, atol=1e-9)
            np.testing.assert_allclose(q[..., 1] / q[..., 2], rows, atol=1e-9)
            # lambda = (X - s).w, with the sign of (d - s).w between source and detector
            np.testing.assert_allclose(q[..., 2], (pts - g.source_mm[i]) @ g.w[i], rtol=1e-12, atol=1e-9)
    # pixel (0, 0) is the centre of the first pixel: half a pitch in from the grid corner
    c00 = g.pixel_centers_mm(0)[0, 0]
    expect = g.detector_mm[0] - 0.5 * (g.n_cols - 1) * g.col_pitch_mm * g.u[0] - 0.5 * (g.n_rows - 1) * g.row_pitch_mm * g.v[0]
    np.testing.assert_allclose(c00, expect, atol=1e-12)
    # project_points agrees with the matrices
    pt = np.array([[1.0, -2.0, 3.0]])
    cr = g.project_points(pt)
    q = P @ np.array([1.0, -2.0, 3.0, 1.0])
    np.testing.assert_allclose(cr[:, 0], q[:, :2] / q[:, 2:], atol=1e-12)


@pytest.mark.parametrize("shape,factor", [((20, 27), 2), ((21, 26), 3), ((8, 8), 1)])
def test_binned_geometry_aligns_with_bin_projections(shape, factor):
    g = _geom(n=3, n_rows=shape[0], n_cols=shape[1], seed=3)
    gb = g.binned(factor)
    nr, nc = shape[0] // factor, shape[1] // factor
    assert gb.det_shape == (nr, nc)
    assert gb.row_pitch_mm == pytest.approx(g.row_pitch_mm * factor)
    for i in range(g.n_views):
        raw = g.pixel_centers_mm(i)  # (rows, cols, 3)
        # binning the raw pixel centres (mean) gives the binned pixel centres
        mean_centres = np.stack([bin_projections(raw[..., k], factor, mean=True) for k in range(3)], axis=-1)
        np.testing.assert_allclose(gb.pixel_centers_mm(i), mean_centres, atol=1e-9)
    # a projection of raw counts: sums of blocks, trailing pixels dropped
    proj = np.arange(3 * shape[0] * shape[1], dtype=np.float64).reshape(3, *shape)
    b = bin_projections(proj, factor)
    assert b.shape == (3, nr, nc)
    assert b[1, 0, 0] == proj[1, :factor, :factor].sum()
    np.testing.assert_allclose(bin_projections(proj, factor, mean=True), b / factor ** 2)


def test_json_and_dict_round_trip():
    g = _geom(seed=4)
    g2 = ConeGeometry.from_json(g.to_json())
    assert g2 == g and g2.det_shape == g.det_shape and g2.row_pitch_mm == g.row_pitch_mm
    d = g.to_dict()
    assert d["units"] == "mm" and len(d["source_mm"]) == g.n_views
    d["format"] = "something/else"
    with pytest.raises(ValueError):
        ConeGeometry.from_dict(d)
    assert ConeGeometry.from_json(g.replace(n_rows=7).to_json()) != g


def test_astra_round_trip():
    g = _geom(seed=6)
    vec = g.to_astra_vec()
    assert vec.shape == (g.n_views, 12)
    np.testing.assert_allclose(np.linalg.norm(vec[:, 6:9], axis=1), g.col_pitch_mm)
    np.testing.assert_allclose(np.linalg.norm(vec[:, 9:12], axis=1), g.row_pitch_mm)
    back = ConeGeometry.from_astra_vec(vec, g.n_rows, g.n_cols)
    assert back.allclose(g, atol=1e-12)
    vec[1, 6:9] *= 1.01
    with pytest.raises(ValueError):
        ConeGeometry.from_astra_vec(vec, g.n_rows, g.n_cols)


def test_subset_concatenate_replace_with_detector():
    g = _geom(seed=7)
    a, b = g.subset(slice(0, 5)), g.subset(np.arange(5, 12))
    assert a.n_views == 5 and ConeGeometry.concatenate([a, b]) == g
    one = g.subset(3)
    assert one.n_views == 1 and np.array_equal(one.source_mm[0], g.source_mm[3])
    mask = np.zeros(12, bool)
    mask[[1, 4]] = True
    assert g.subset(mask).n_views == 2
    with pytest.raises(ValueError):
        ConeGeometry.concatenate([a, b.with_detector(4, 4)])
    big = g.with_detector(40, 50)
    assert big.det_shape == (40, 50) and big.col_pitch_mm == g.col_pitch_mm
    np.testing.assert_array_equal(big.detector_mm, g.detector_mm)
    assert g.replace(col_pitch_mm=1.0).col_pitch_mm == 1.0 and g.col_pitch_mm == 0.25


@pytest.mark.parametrize("factor", [2, 4])
def test_binning_never_reduces_a_dimension_to_zero(factor):
    """A one-row (fan-beam) detector stays one row at every binning level; its columns are binned,
    and the binned geometry still lies over the pixels bin_projections sums. A grid one voxel thick
    keeps its voxel."""
    g = _geom(n=3, n_rows=1, n_cols=27, seed=5)
    gb = g.binned(factor)
    assert gb.det_shape == (1, 27 // factor)
    assert gb.row_pitch_mm == g.row_pitch_mm and gb.col_pitch_mm == pytest.approx(g.col_pitch_mm * factor)
    for i in range(g.n_views):
        mean_centres = np.stack([bin_projections(g.pixel_centers_mm(i)[..., k], factor, mean=True)
                                 for k in range(3)], axis=-1)
        np.testing.assert_allclose(gb.pixel_centers_mm(i), mean_centres, atol=1e-9)
    proj = np.arange(3 * 27, dtype=np.float64).reshape(3, 1, 27)
    assert bin_projections(proj, factor).shape == (3, 1, 27 // factor)
    # a few rows: binned only when there are at least `factor` of them
    assert _geom(n=3, n_rows=factor - 1, n_cols=27).binned(factor).n_rows == factor - 1
    assert _geom(n=3, n_rows=2 * factor + 1, n_cols=27).binned(factor).n_rows == 2
    grid = VolumeGrid.centered((1, 8, 12), (0.5, 0.5, 0.2))
    gb = grid.binned(factor)
    assert gb.shape_zyx == (1, 8 // factor, 12 // factor)
    assert gb.voxel_size_mm == (0.5 * factor, 0.5 * factor, 0.2)
    np.testing.assert_allclose(gb.center_mm, grid.center_mm)


def test_sizes_that_are_not_finite_or_not_whole_are_refused():
    """A NaN pitch, voxel size or origin passed the "<= 0" checks and made the projector return zeros; a
    fractional detector or grid size was truncated without a word."""
    from robot_ct_ros.ct.trajectory import circular_scan

    for make in (lambda: VolumeGrid.centered((4, 4, 4), np.nan), lambda: VolumeGrid.centered((4, 4, 4), np.inf),
                 lambda: VolumeGrid((4, 4, 4), (1.0, 1.0, 1.0), (np.nan, 0.0, 0.0)),
                 lambda: VolumeGrid((4, 4, 4.9), (1.0, 1.0, 1.0)),
                 lambda: circular_scan(4, 60.0, 150.0, 8, 8, np.nan, 1.0),
                 lambda: circular_scan(4, 60.0, 150.0, 8, 8, 1.0, np.inf),
                 lambda: circular_scan(4, 60.0, 150.0, 2.7, 8, 1.0, 1.0)):
        with pytest.raises(ValueError):
            make()
    assert VolumeGrid((4.0, 4, 4), (1, 1, 1)).shape_zyx == (4, 4, 4)  # a whole float is a size


def test_the_centre_of_the_views_is_where_their_central_rays_meet_and_none_for_one_view():
    """views_center_mm: a circular scan about a point off the origin is centred there, a detector tilted out of
    its plane so far that it does not hold its principal point still points at the centre (the ray through its
    centre), and one view fixes no centre (the reader's magnification check is then skipped)."""
    from scipy.spatial.transform import Rotation

    from robot_ct_ros.ct.geometry import views_center_mm
    from robot_ct_ros.ct.trajectory import circular_scan

    g = circular_scan(12, 200.0, 400.0, 16, 32, 0.8, 0.8)
    centre = np.array([3.0, -2.0, 1.0])
    moved = g.replace(source_mm=g.source_mm + centre, detector_mm=g.detector_mm + centre)
    np.testing.assert_allclose(views_center_mm(moved), centre, atol=1e-9)
    tilt = Rotation.from_rotvec(np.deg2rad(25.0) * np.array(g.v))  # about each detector's v, through its centre
    tilted = moved.replace(u=tilt.apply(np.array(g.u)), v=np.array(g.v))
    np.testing.assert_allclose(views_center_mm(tilted), centre, atol=1e-9)
    assert views_center_mm(moved.subset([0]), determined_only=True) is None
