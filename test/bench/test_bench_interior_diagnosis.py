"""bench/bench_interior_diagnosis.py: its tables on a small interior neck."""

from __future__ import annotations

import numpy as np

from robot_ct_ros.ct import calibration
from robot_ct_ros.ct.calibration.exterior import exterior_support
from robot_ct_ros.ct.projector import forward_project


def test_the_scout_exterior_explains_what_the_interior_scan_sees_outside_its_roi(load_bench):
    """A small interior neck scan (axis +y): the exterior FDK'd from the simulated scout is non-negative,
    empty where the ROI part lives, and its projection through the interior scan's true geometry
    follows the interior data, which the object outside the field of view dominates. A scout about the
    wrong axis or in the wrong place would not."""
    bench = load_bench("bench_interior_diagnosis")
    sc = bench.make_scan(0.1, views=24, det=(16, 40), axis="y", seed=0, nxy=24, say=lambda m: None)
    st = bench.Study(sc, calibration.CalibrationSettings().with_prior(0.1, 0.1))
    vol, ext, pixel_mm = bench.scout_exterior(st, 1.0, views=90)
    assert pixel_mm < 1.0
    assert vol.min() >= 0.0 and vol.max() > 0.01
    assert np.all(vol[exterior_support(ext, st.grid_f) == 0] == 0.0)
    proj = forward_project(vol, ext, sc.true)
    data = np.where(sc.mask, sc.li, np.nan)
    ok = np.isfinite(data)
    assert np.corrcoef(proj[ok], data[ok])[0, 1] > 0.95  # 0.99 here; about the z axis instead: 0.53
    # the exterior carries most of each ray's attenuation: the ROI holds a sixth of the body's width
    assert 0.8 < np.median(proj[ok] / np.maximum(data[ok], 1e-6)) < 1.2


def test_the_shift_combinations_are_what_the_roi_centre_s_projection_sees(load_bench):
    """Table 12's combinations: small random source and detector shifts move the ROI centre's
    projection by d + (M - 1) s along u and v (detector mm, sign aside), whatever the split between d
    and s, in a world whose rotation axis is +y."""
    bench = load_bench("bench_interior_diagnosis")
    sc = bench.make_scan(0.1, views=24, det=(16, 40), axis="y", seed=0, nxy=24, say=lambda m: None)
    st = bench.Study(sc, calibration.CalibrationSettings().with_prior(0.1, 0.1))
    combos = list(bench.shift_combinations(st).values())
    rng = np.random.default_rng(3)
    params = np.zeros((st.n, 9))
    params[:, [0, 1, 3, 4]] = rng.normal(0.0, 0.1, (st.n, 4))
    centre = np.asarray(sc.grid.center_mm)[None]
    nom = sc.nominal
    moved = (nom.perturbed(params).project_points(centre) - nom.project_points(centre))[:, 0]  # (views, (col, row)) px
    pitch = np.array([nom.col_pitch_mm, nom.row_pitch_mm])
    for axis in (0, 1):
        np.testing.assert_allclose(np.abs(moved[:, axis] * pitch[axis]), np.abs(combos[axis](params)), rtol=0.02,
                                   atol=2e-3)
    # a split that keeps the combination leaves the centre's projection where it was
    m1 = float(np.mean(nom.magnification())) - 1.0
    split = np.zeros((st.n, 9))
    split[:, 0], split[:, 3] = 0.1, -m1 * 0.1
    assert np.abs(nom.perturbed(split).project_points(centre) - nom.project_points(centre)).max() < 0.05


def test_views_held_out_are_predicted_worse_than_views_in_at_each_band(load_bench):
    """Table 14 on a small interior neck (axis +y): a band's level is the data binned so, with its grid and
    geometry binned alike, and a volume from the true geometry explains the views whose data built it
    better than the views it did not see. A table that scored the held-out views against a volume
    containing them would find no gap."""
    bench = load_bench("bench_interior_diagnosis")
    sc = bench.make_scan(0.1, views=24, det=(16, 40), axis="y", seed=0, nxy=24, say=lambda m: None)
    st = bench.Study(sc, calibration.CalibrationSettings().with_prior(0.1, 0.1))
    li, nom, grid, mask, cfg = st.level(4)
    assert li.shape == (24, 4, 10) and mask.shape == li.shape
    assert (nom.n_rows, nom.n_cols) == (4, 10) and nom.col_pitch_mm == 4 * sc.nominal.col_pitch_mm
    assert grid == st.grid_f.binned(4) and cfg.levels == 1
    (row,) = bench.table_bands(st, lambda m: None, bands=(2,), folds=4)
    assert row["binning"] == 2 and row["views"] == 24
    assert -1.0 <= row["projection NCC, own views held out"] < row["projection NCC, own views in"] <= 1.0
    for key in ("estimate, true geometry, own views in (px)", "estimate, true geometry, own views held out (px)",
                "estimate, nominal geometry, own views in (px)"):
        assert np.isfinite(row[key]) and row[key] >= 0.0


def test_a_held_out_volume_registers_the_view_once_its_own_term_leaves_its_data(load_bench):
    """Table 15 on a small interior neck (axis +y, 4 folds): against volumes from the true geometry without the
    view's fold, the view's data as measured mislead the estimate; with the fold's own term (the full model's
    reprojection less the held-out model's) taken out of them it ends far closer to the truth. Both start at the
    nominal geometry, so neither is right by staying put."""
    bench = load_bench("bench_interior_diagnosis")
    sc = bench.make_scan(0.1, views=24, det=(16, 40), axis="y", seed=0, nxy=24, say=lambda m: None)
    st = bench.Study(sc, calibration.CalibrationSettings().with_prior(0.1, 0.1))
    nominal_px = st.error_px(np.zeros((st.n, 9)))
    (true_row,) = bench.table_left_out(st, lambda m: None, folds=4, geometries=("true",))
    held = true_row["held out (4 folds), data as measured (px)"]
    left = true_row["held out, own term taken out of the data too (px)"]
    assert true_row["volumes reconstructed with"] == "the true geometry"
    assert left < 0.8 * held and left < 0.8 * nominal_px  # 1.237 against 2.553 and 2.165 here


def test_the_total_variation_step_smooths_only_the_parts_it_is_given(load_bench):
    """Table 6's total-variation candidate: after a pass, the named parts' total variation falls, stays
    non-negative and zero outside what the pass touched; a part not named is left as it was."""
    bench = load_bench("bench_interior_diagnosis")
    rng = np.random.default_rng(0)

    def tv(x):
        return float(sum(np.abs(np.diff(x, axis=a)).sum() for a in range(3)))

    before = [np.zeros((8, 8, 8), np.float32), np.zeros((6, 6, 6), np.float32)]
    xs = [b.copy() for b in before]
    xs[0][2:6, 2:6, 2:6] = 1.0 + 0.3 * rng.random((4, 4, 4), dtype=np.float32)  # a noisy block: the pass's change
    xs[1][1:5, 1:5, 1:5] = 1.0 + 0.3 * rng.random((4, 4, 4), dtype=np.float32)
    roi, ext = xs[0].copy(), xs[1].copy()
    bench.tv_step(0.1, parts=(0,))(xs, before)
    assert tv(xs[0]) < tv(roi)
    assert xs[0].min() >= 0.0 and np.all(xs[0][roi == 0] == 0.0)  # support: where the pass put object
    np.testing.assert_array_equal(xs[1], ext)
    bench.tv_step(0.1)(xs, before)  # the default: the exterior alone
    assert tv(xs[1]) < tv(ext)


def test_the_roi_voxel_table_builds_and_registers_on_the_grid_it_names(load_bench):
    """Table 16 on a small interior neck (axis +y): each row's volume is built and registered on the ROI grid
    binned as it says (voxel twice the coarse level's at binning 2), and the volume from the true geometry places
    the views closer to the truth than the nominal geometry does. A table that built the binned volume but
    registered on the coarse grid would fail inside the estimator (shapes differ)."""
    bench = load_bench("bench_interior_diagnosis")
    sc = bench.make_scan(0.1, views=24, det=(16, 40), axis="y", seed=0, nxy=24, say=lambda m: None)
    st = bench.Study(sc, calibration.CalibrationSettings().with_prior(0.1, 0.1))
    nominal_px = st.error_px(np.zeros((st.n, 9)))
    rows = bench.table_roi_voxel(st, lambda m: None, binnings=(1, 2))
    coarse = st.level("coarse")[2]
    assert [r["ROI voxel (mm)"] for r in rows] == [round(coarse.voxel_size_mm[0], 4),
                                                  round(coarse.binned(2).voxel_size_mm[0], 4)]
    assert rows[1]["ROI grid (z, y, x)"] == str(coarse.binned(2).shape_zyx)
    for r in rows:
        assert r["estimate, volume from the true geometry (px)"] < nominal_px


def test_the_iterated_leave_out_starts_as_table_15_and_rebuilds_its_volumes_each_round(load_bench):
    """Table 17 on a small interior neck (axis +y, 4 folds, 2 rounds): its first round is table 15's nominal-geometry
    row (the leave-out with the own term out, and every view in), and the second round registers against volumes
    rebuilt with the first round's estimates, so it ends elsewhere."""
    bench = load_bench("bench_interior_diagnosis")
    sc = bench.make_scan(0.1, views=24, det=(16, 40), axis="y", seed=0, nxy=24, say=lambda m: None)
    st = bench.Study(sc, calibration.CalibrationSettings().with_prior(0.1, 0.1))
    rows = bench.table_left_out_iterated(st, lambda m: None, rounds=2, folds=4)
    (once,) = bench.table_left_out(st, lambda m: None, folds=4, geometries=("nominal",))
    assert [r["round"] for r in rows] == [1, 2]
    assert rows[0]["left out, own term out (px)"] == once["held out, own term taken out of the data too (px)"]
    assert rows[0]["every view in (px)"] == once["all views, own data in (px)"]
    for key in ("left out, own term out (px)", "every view in (px)"):
        assert rows[1][key] != rows[0][key] and np.isfinite(rows[1][key])


def test_the_background_table_passes_each_order_to_the_metric(load_bench):
    """Table 18 on a small interior neck (axis +y): the (0, 0) row is the default coarse pass (the loop's metric), and
    a quadratic background changes the estimate, so each row's order reaches the estimator."""
    bench = load_bench("bench_interior_diagnosis")
    sc = bench.make_scan(0.1, views=24, det=(16, 40), axis="y", seed=0, nxy=24, say=lambda m: None)
    st = bench.Study(sc, calibration.CalibrationSettings().with_prior(0.1, 0.1))
    assert tuple(st.coarse.background) == (0, 0)
    rows = bench.table_background(st, lambda m: None, orders=((0, 0), (2, 2)))
    zero = np.zeros((st.n, 9))
    default = round(st.error_px(st.estimate("coarse", zero, st.volume("coarse", zero))), 3)
    assert [r["background ignored (orders along u, v)"] for r in rows] == ["(0, 0)", "(2, 2)"]
    assert rows[0]["estimate, volume from the nominal geometry (px)"] == default
    assert rows[1]["estimate, volume from the nominal geometry (px)"] != default


def test_the_shift_optimum_finds_a_known_shift_through_every_filter(load_bench):
    """Table 19's exhaustive search: an image of blobs shifted by a known fraction of a pixel along both axes, with
    a gain and an offset on the data and a few dead pixels masked, is found within a tenth of a pixel whether
    the images are taken as they are, normalised locally or low-passed; a search that mixed up the axes or the
    sign would report the shift elsewhere."""
    bench = load_bench("bench_interior_diagnosis")
    from scipy import ndimage

    rng = np.random.default_rng(1)
    rows, cols = 40, 64
    model = ndimage.gaussian_filter(rng.normal(size=(rows, cols)), 2.0)
    shift_cols, shift_rows = 1.3, -0.7
    data = ndimage.shift(model, (shift_rows, shift_cols), order=3, mode="nearest")
    data = 3.0 * data + 0.5  # a gain and an offset, which no NCC minds
    mask = np.ones((rows, cols), bool)
    mask[rng.integers(0, rows, 20), rng.integers(0, cols, 20)] = False
    data[~mask] = 50.0
    for _, kind, sigma in bench.FILTERS:
        found = bench.shift_optimum(data[None], model[None], mask[None], kind, sigma)[0]
        np.testing.assert_allclose(found, (shift_cols, shift_rows), atol=0.1 if kind != "low" else 0.15,
                                   err_msg=f"{kind} {sigma}")


def test_the_metric_optimum_table_measures_each_volume_and_filter(load_bench):
    """Table 19 on a small interior neck (axis +y, 4 folds, two filters): a row per volume (true, nominal),
    own data in or held out, and filter; the volume from the true geometry with every view in places the views'
    projection shift along u at about its true value (slope near 1), so the sign and the units agree with the
    truth's."""
    bench = load_bench("bench_interior_diagnosis")
    sc = bench.make_scan(0.1, views=24, det=(16, 40), axis="y", seed=0, nxy=24, say=lambda m: None)
    st = bench.Study(sc, calibration.CalibrationSettings().with_prior(0.1, 0.1))
    rows = bench.table_metric_optimum(st, lambda m: None, folds=4, filters=bench.FILTERS[:2])
    assert [(r["volume from"], r["each view's data"]) for r in rows[::2]] == [
        ("the true geometry", "in"), ("the true geometry", "held out (4 folds)"),
        ("the nominal geometry", "in"), ("the nominal geometry", "held out (4 folds)")]
    assert rows[0]["images"] == "as they are" and "windowed" in rows[1]["images"]
    assert 0.7 < rows[0]["u: slope"] < 1.3
    for r in rows:
        assert all(np.isfinite(v) for k, v in r.items() if k.startswith(("u:", "v:")))
        assert 0 <= r["views at the search's edge"] <= st.n
    # the small neck's held-out volumes predict its views so badly that many peaks run to the search's edge
    assert rows[2]["views at the search's edge"] > rows[0]["views at the search's edge"]


def test_a_peak_beyond_the_search_is_counted_at_its_edge(load_bench):
    """Table 19's edge count: data shifted by 3 px against their model, searched within 1 px, peak at the search's
    edge (1.5 px with the fine step) and are counted there; searched within 4 px they are found and not counted."""
    bench = load_bench("bench_interior_diagnosis")
    from scipy import ndimage
    from types import SimpleNamespace

    rng = np.random.default_rng(2)
    model = np.stack([ndimage.gaussian_filter(rng.normal(size=(32, 48)), 2.0) for _ in range(3)])
    data = np.stack([ndimage.shift(m, (0.0, 3.0), order=3, mode="nearest") for m in model])
    geom = SimpleNamespace(col_pitch_mm=np.float64(0.11))
    st = SimpleNamespace(level=lambda name: (data, geom, None, np.ones(data.shape, bool), None),
                         sc=SimpleNamespace(nominal=geom))
    near, at_edge = bench.measured_shifts(st, model, reach_px=1.0)
    assert at_edge == 3 and np.allclose(near[:, 0], -1.5)
    found, at_edge = bench.measured_shifts(st, model, reach_px=4.0)
    assert at_edge == 0 and np.allclose(found[:, 0], -3.0, atol=0.1)


def test_the_held_out_exterior_table_builds_each_fold_without_its_views(load_bench):
    """Table 20 on a small interior neck (axis +y, 4 folds): the held-out model predicts its views worse than the
    volume their own data built (a model that let a fold's views in would not), and each row's voxel and passes
    reach the volume, so the rows differ."""
    bench = load_bench("bench_interior_diagnosis")
    from robot_ct_ros.ct.calibration.volume import projection_consistency

    sc = bench.make_scan(0.1, views=24, det=(16, 40), axis="y", seed=0, nxy=24, say=lambda m: None)
    st = bench.Study(sc, calibration.CalibrationSettings().with_prior(0.1, 0.1))
    li, nom, grid, mask, _ = st.level("coarse")
    true_geom = nom.perturbed(st.true_p)
    own_ncc = projection_consistency(st.volume("coarse", st.true_p, iterations=10), grid, true_geom, li, mask)[1]
    model, held_ncc = bench.held_out_model(st, st.true_p, 4, iterations=10)
    assert model.shape == li.shape and np.isfinite(model).all()
    assert held_ncc < own_ncc - 0.1
    rows = bench.table_held_out_exterior(st, lambda m: None, folds=4, settings=((0.5, 2), (0.5, 10), (1.0, 10)))
    assert [(r["exterior voxel (mm)"], r["SIRT passes"]) for r in rows] == [(0.5, 2), (0.5, 10), (1.0, 10)]
    assert len({r["held-out projection NCC"] for r in rows}) == 3
    assert rows[1]["held-out projection NCC"] == round(held_ncc, 5)
