"""Simulation: phantoms, photon-counting detector model, geometric error models, scans."""

import numpy as np
import pytest

from robot_ct_ros.ct.geometry import VolumeGrid
from robot_ct_ros.ct.simulation import (DetectorModel, GeometryErrorModel, Phantom, battery_phantom, box, spiral,
                                        carotid_plaque_phantom, counts_to_line_integrals, detector_drift,
                                        ellipsoid, elliptic_cylinder, mouse_phantom, robot_coordination,
                                        simulate_counts, simulate_scan, voxelize)
from robot_ct_ros.ct.trajectory import circular_scan


@pytest.mark.parametrize("prim", [
    ellipsoid((0.3, -0.2, 0.1), (2.0, 1.5, 1.0), 1.0, rotvec=(0.3, 0.2, 0.1)),
    elliptic_cylinder((0.0, 0.0, 0.0), (2.0, 1.2), 1.5, 1.0),
])
def test_voxelised_primitive_keeps_its_analytic_volume(prim):
    grid = VolumeGrid.centered((40, 56, 56), 0.1)
    vol = voxelize(Phantom("one", (prim,)), grid, supersample=3)
    measured = vol.sum() * np.prod(grid.voxel_size_mm)
    assert measured == pytest.approx(prim.analytic_volume_mm3(), rel=0.01)


def test_phantoms_voxelise_to_plausible_attenuation():
    for ph in (mouse_phantom(), battery_phantom(), carotid_plaque_phantom()):
        lo, hi = ph.bounds_mm()
        grid = VolumeGrid.centered((8, 48, 48), (hi - lo)[:2].max() / 48, 0.5 * (lo + hi))
        vol = voxelize(ph, grid)
        assert vol.dtype == np.float32 and np.isfinite(vol).all()
        assert 0.0 <= vol.min() and 0.015 < np.median(vol[vol > 0]) < 0.2


def test_counts_follow_poisson_statistics_and_invert_noiselessly():
    model = DetectorModel(photons_per_pixel=4000.0, dead_pixel_fraction=0.0, hot_pixel_fraction=0.0,
                          flat_field_sigma=0.0, chip_gap_px=0, flat_frames=1000)
    p = np.full((200, 16, 16), 1.2, np.float32)
    counts, flat, valid = simulate_counts(p, model, rng=np.random.default_rng(0))
    expected = 4000.0 * np.exp(-1.2)
    assert counts.mean() == pytest.approx(expected, rel=0.01)
    assert counts.var() == pytest.approx(expected, rel=0.05)

    clean = DetectorModel(poisson=False, dead_pixel_fraction=0.0, hot_pixel_fraction=0.0, chip_gap_px=0,
                          flat_field_sigma=0.0)
    li_true = np.random.default_rng(1).uniform(0, 3, (3, 32, 32)).astype(np.float32)
    c, f, v = simulate_counts(li_true, clean)
    li, mask = counts_to_line_integrals(c, f, v)
    binned = li_true.reshape(3, 16, 2, 16, 2)
    # binned counts average exp(-p), so compare with -log(mean(exp(-p)))
    expect = -np.log(np.exp(-binned.astype(np.float64)).mean(axis=(2, 4)))
    np.testing.assert_allclose(li, expect, atol=1e-4)
    assert mask.all()


def test_defects_are_masked_and_nothing_non_finite_escapes():
    model = DetectorModel(dead_pixel_fraction=0.02, hot_pixel_fraction=0.01, chip_size_px=24, chip_gap_px=2,
                          min_valid_fraction=1.0)
    p = np.random.default_rng(2).uniform(0, 8, (2, 52, 52)).astype(np.float32)
    p[0, :4, :4] = 40.0  # photon starvation: zero counts
    counts, flat, valid = simulate_counts(p, model, rng=np.random.default_rng(3))
    li, mask = counts_to_line_integrals(counts, flat, valid)
    assert np.isfinite(li).all()
    gap = model.gap_mask((52, 52)).reshape(26, 2, 26, 2).all(axis=(1, 3))
    assert not mask[gap].any()  # bins made only of gap pixels are invalid
    np.testing.assert_array_equal(np.broadcast_to(mask, li.shape)[0], model.valid_mask((52, 52)))  # and bins spoilt by dead/hot pixels
    assert model.valid_mask((52, 52)).sum() < (~gap).sum()
    assert np.all(li[:, ~mask] == 0)


def test_error_models_are_seeded_and_respect_their_sigma():
    a = robot_coordination(0.3, 0.3, seed=7).sample(4000)
    b = robot_coordination(0.3, 0.3, seed=7).sample(4000)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, robot_coordination(0.3, 0.3, seed=8).sample(4000))
    np.testing.assert_allclose(a[:, :6].std(axis=0), 0.3, rtol=0.06)
    np.testing.assert_allclose(a[:, 6:].std(axis=0), np.deg2rad(0.3), rtol=0.06)
    drift = detector_drift(mm_per_view=0.002).sample(100)
    assert np.abs(drift[-1, 3:6]).max() > np.abs(drift[1, 3:6]).max()  # creeps
    static = GeometryErrorModel(static_offset=(0, 0, 0, 1.0, 0, 0, 0, 0, 0)).sample(5)
    np.testing.assert_array_equal(static[:, 3], 1.0)


def test_simulated_scan_matches_shapes_and_sees_the_object():
    geom = circular_scan(6, 60.0, 150.0, 16, 24, 0.8, 0.8)
    ph = mouse_phantom(body_width_mm=10.0, length_mm=12.0)
    scan = simulate_scan(ph, geom, DetectorModel(chip_size_px=64), voxel_size_mm=0.3,
                         rng=np.random.default_rng(0))
    assert scan.line_integrals.shape == (6, 16, 24)
    assert np.isfinite(scan.line_integrals).all()
    centre = scan.line_integrals[:, 6:10, 10:14]
    assert centre.mean() > 0.1  # ~10 mm of tissue
    assert np.abs(scan.line_integrals - scan.ideal_line_integrals)[:, scan.valid_mask].mean() < 0.05


@pytest.mark.parametrize("prim", [
    elliptic_cylinder((0.1, 0.0, 0.0), (2.0, 1.6), 1.0, 1.0, inner_semi_axes_mm=(1.0, 0.7), half_angle_rad=2.2,
                      rotvec=(0.2, 0.0, 0.4)),
    box((0.2, -0.1, 0.0), (1.5, 0.9, 0.8), 1.0, rotvec=(0.3, -0.2, 0.5)),
    spiral((0.0, 0.0, 0.0), 0.5, 0.3, 4, 0.03, 1.0, 1.0),  # foil thinner than a voxel: anti-aliased
])
def test_voxelised_annulus_box_and_spiral_keep_their_volume(prim):
    grid = VolumeGrid.centered((28, 56, 56), 0.1)
    vol = voxelize(Phantom("one", (prim,)), grid, supersample=2)
    measured = vol.sum() * np.prod(grid.voxel_size_mm)
    assert measured == pytest.approx(prim.analytic_volume_mm3(), rel=0.02)


@pytest.mark.parametrize("thickness_mm", [0.05, 0.065, 0.2])
def test_plaque_cap_is_as_thick_as_asked(thickness_mm):
    ph = carotid_plaque_phantom(cap_thickness_mm=thickness_mm, seed=3)
    cap = ph.cap
    d = np.asarray(cap.direction)
    s = np.arange(-0.3, thickness_mm + 0.3, 0.0005)
    for z in (-0.5 * cap.half_length_mm, 0.0, 0.5 * cap.half_length_mm):
        pts = cap.lumen_point_mm + s[:, None] * d + z * np.asarray(cap.axis)
        vals = ph.evaluate(pts)
        inside = s[np.isclose(vals, ph.info["cap_mu"])]
        assert inside.max() - inside.min() == pytest.approx(thickness_mm, abs=0.002)
        # lumen before, lipid core after
        assert vals[0] == pytest.approx(ph.info["lumen_mu"]) and vals[-1] < ph.info["lumen_mu"]
    np.testing.assert_allclose(np.linalg.norm(cap.core_point_mm - cap.lumen_point_mm), thickness_mm)


def test_random_walk_drift_is_smooth_and_reproducible():
    m = GeometryErrorModel(drift_per_view=(0.0,) * 3 + (0.01,) * 3 + (0.0,) * 3, drift_kind="random_walk",
                           drift_smooth_views=8.0, seed=4)
    a, b = m.sample(300), m.sample(300)
    np.testing.assert_array_equal(a, b)
    steps = np.diff(a[:, 3:6], axis=0)
    assert np.abs(a[:, 3:6]).max() > 0.02            # it wanders ...
    assert np.abs(steps).max() < 0.01                # ... in steps smaller than the raw walk's
    assert np.all(a[:, [0, 1, 2, 6, 7, 8]] == 0)
    both = (robot_coordination(0.1, 0.0, seed=1) + m).sample(300)
    np.testing.assert_allclose(both - a, robot_coordination(0.1, 0.0, seed=1).sample(300))


def test_fine_roi_plus_coarse_rest_projects_like_the_analytic_sphere():
    from robot_ct_ros.ct.simulation import ellipsoid as ell
    mu, R = 0.02, 4.0
    ph = Phantom("sphere", (ell((0.0, 0.0, 0.0), (R, R, R), mu),))
    geom = circular_scan(4, 60.0, 150.0, 24, 40, 0.5, 0.5)
    roi = VolumeGrid.centered((16, 16, 16), 0.15)  # interior ROI, much smaller than the sphere
    two = simulate_scan(ph, geom, None, voxel_size_mm=0.1, roi_grid=roi, outer_voxel_size_mm=0.3)
    assert len(two.info["parts"]) == 2
    # analytic chord length of every pixel ray through the sphere
    nv, nr, nc = two.line_integrals.shape
    expect = np.empty((nv, nr, nc))
    for v in range(nv):
        pix = geom.pixel_centers_mm(v)
        dirs = pix - geom.source_mm[v]
        dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
        b = np.einsum("rck,k->rc", dirs, geom.source_mm[v])
        disc = b * b - (geom.source_mm[v] @ geom.source_mm[v] - R * R)
        expect[v] = 2 * mu * np.sqrt(np.maximum(disc, 0))
    inner = expect > 0.5 * expect.max()  # away from the rim, where voxelisation blurs
    np.testing.assert_allclose(two.line_integrals[inner], expect[inner], atol=0.004)


def test_lean_simulation_and_a_projector_give_the_same_scan():
    """keep_intermediates=False converts counts chunk by chunk into one stack; projector= replaces the
    voxelised phantom: the line integrals and mask are those of the default path."""
    from robot_ct_ros.ct.simulation import project_parts, raw_geometry, scan_volumes

    geom = circular_scan(7, 60.0, 150.0, 16, 24, 0.8, 0.8)
    ph = mouse_phantom(body_width_mm=10.0, length_mm=12.0)
    det = DetectorModel(chip_size_px=64)
    full = simulate_scan(ph, geom, det, voxel_size_mm=0.3, rng=np.random.default_rng(0), chunk_views=3)
    parts = scan_volumes(ph, raw_geometry(geom, det.binning), 0.3)
    lean = simulate_scan(ph, geom, det, rng=np.random.default_rng(0), chunk_views=3, keep_intermediates=False,
                         projector=lambda g: project_parts(parts, g))
    np.testing.assert_array_equal(lean.line_integrals, full.line_integrals)
    np.testing.assert_array_equal(lean.valid_mask, full.valid_mask)
    assert lean.ideal_line_integrals is None and lean.counts is None
    np.testing.assert_array_equal(lean.flat, full.flat)
