"""The alternating loop, the LLE estimator, the estimation volume and the loop's constraints, on small scans."""

import numpy as np
import pytest

from robot_ct_ros.ct.calibration import calibrate
from robot_ct_ros.ct.calibration.constraints import focus_conjugate_modes, hold_magnification, view_angles
from robot_ct_ros.ct.calibration.kernels import detector_homographies, warp_projections
from robot_ct_ros.ct.calibration.lle.estimator import LLEConfig, estimate_views
from robot_ct_ros.ct.calibration.volume import reconstruct_for_estimation
from robot_ct_ros.ct.geometry import VolumeGrid
from robot_ct_ros.ct.metrics import fit_object_scale, ncc, reprojection_error, roi_points
from robot_ct_ros.ct.projector import forward_project
from robot_ct_ros.ct.reconstruction import fdk
from robot_ct_ros.ct.simulation import mouse_phantom, robot_coordination, voxelize
from robot_ct_ros.ct.trajectory import circular_scan


def _small_scan(n_views=30, n_det=48, body_width_mm=9.0, length_mm=10.0, seed=1, error_model=None):
    """A small circular scan of a mouse phantom with ~0.3 mm / 0.3 deg robot errors per view
    (or ``error_model``'s). Projections come from a 2x finer voxelisation than the reconstruction
    grid."""
    nominal = circular_scan(n_views, 60.0, 150.0, n_det, n_det, 32.0 / n_det, 32.0 / n_det)
    grid = VolumeGrid.centered((32, 32, 32), 12.0 / 32)
    phantom = mouse_phantom(body_width_mm=body_width_mm, length_mm=length_mm)
    lo, hi = phantom.bounds_mm()
    size = np.minimum(hi - lo, 40.0)
    fine = VolumeGrid.centered(tuple(np.ceil(size[::-1] / 0.1875).astype(int)), 0.1875, 0.5 * (lo + hi))
    errors = (error_model or robot_coordination(0.3, 0.3, seed=seed)).sample(n_views)
    true = nominal.perturbed(errors)
    measured = forward_project(voxelize(phantom, fine), fine, true)
    return nominal, true, grid, measured


def test_fast_schedule_reduces_the_geometry_error():
    """The large-scan schedule (4x then 2x binned, no fine SIRT, source held on the finer level)."""
    nominal, true, grid, measured = _small_scan(n_det=64)
    pts = roi_points(grid)
    before = reprojection_error(nominal, true, pts)["mean_px"]
    said = []
    result = calibrate(measured, nominal, grid, method="ncc-lle", iterations=2, schedule="fast", projections="auto",
                       progress=said.append)
    assert "not truncated, FDK" in said[0]  # the object fits in the field of view
    after = reprojection_error(result.geom, true, pts)["mean_px"]
    assert before > 1.0
    assert after < 0.6 * before, (before, after)
    assert result.volume.shape == grid.shape_zyx  # the final volume is full size
    with pytest.raises(ValueError, match="schedule"):
        calibrate(measured, nominal, grid, schedule="fastest")
    with pytest.raises(ValueError, match="padding"):
        calibrate(measured, nominal, grid, padding=0.9)


@pytest.mark.parametrize("method", ["ncc-lle-exact", "ncc-lle", "l2-lle"])
def test_calibrate_reduces_the_geometry_error(method):
    nominal, true, grid, measured = _small_scan()
    pts = roi_points(grid)
    before = reprojection_error(nominal, true, pts)["mean_px"]
    result = calibrate(measured, nominal, grid, method=method, iterations=2)
    after = reprojection_error(result.geom, true, pts)["mean_px"]
    assert before > 1.0
    assert after < 0.6 * before, (method, before, after)
    assert len(result.history) == 2 and result.volume.shape == grid.shape_zyx
    assert all(0.0 < h.independent_fraction <= 1.0 for h in result.history)  # the default prior is on


def test_coarse_warm_up_passes_converge_the_first_iteration_and_stop_when_the_views_settle():
    """Re-reconstructing the coarse volume between coarse passes of the first iteration starts
    the finer level from a better volume; the passes stop once they move the views less than
    ``coarse_tol_px``."""
    nominal, true, grid, measured = _small_scan()
    pts = roi_points(grid)
    errors, said = {}, {}
    for passes in (1, 3):
        said[passes] = []
        result = calibrate(measured, nominal, grid, method="ncc-lle-exact", iterations=1, coarse_passes=passes,
                           progress=said[passes].append)
        errors[passes] = reprojection_error(result.geom, true, pts)["mean_px"]
    assert errors[3] < 0.85 * errors[1], errors
    moved = [float(line.split("moved ")[1].split()[0]) for line in said[3] if "coarse estimate" in line]
    assert len(moved) >= 2 and moved[1] < moved[0]
    assert len(moved) == 3 or moved[-1] < 0.1  # stopped early only because the views settled
    single = [line for line in said[1] if "coarse estimate" in line]
    assert len(single) == 1
    with pytest.raises(ValueError, match="coarse_passes"):
        calibrate(measured, nominal, grid, coarse_passes=0)


def test_undo_inconsistent_restores_the_geometry_and_compares_with_the_one_entering_the_iteration():
    """Started at the true geometry with a deliberately poor estimator (2 neighbours of 8 samples
    in a wide box), the iteration lowers the FDK's data consistency and is undone. The check
    compares with the geometry that entered the iteration, also after coarse warm-up passes."""
    nominal, true, grid, measured = _small_scan()
    poor = LLEConfig(weighting="l2", n_samples=8, n_neighbours=2, half_width=(2.0,) * 6 + (0.04,) * 3, levels=1,
                     safeguard=False, reg=1e-9)
    before = {}
    for passes in (1, 3):
        said = []
        result = calibrate(measured, true, grid, method="l2-lle", iterations=2, configs=(poor, poor), coarse_passes=passes,
                           coarse_tol_px=0.0, undo_inconsistent=True, progress=said.append)
        undone = [line for line in said if "data consistency fell" in line]
        assert len(undone) == 1 and len(result.history) == 0
        assert np.array_equal(result.params, np.zeros_like(result.params))  # back at the entering geometry
        told = [n for n in result.notes if n.startswith("undo_inconsistent: iteration 1 ")]
        assert len(told) == 1 and "no correction was made" in told[0]  # the result says so, not only the log
        assert sum("coarse estimate" in line for line in said) == passes
        before[passes] = undone[0].split("fell (")[1].split(" ->")[0]
    assert before[1] == before[3]


def test_loop_stops_when_an_iteration_hardly_moves_the_views():
    """``update_px`` is the gauge-aligned displacement of the ROI points' projections between the
    geometries before and after the iteration; below ``stop_update_px`` the loop ends early."""
    nominal, true, grid, measured = _small_scan()
    pts = roi_points(grid)
    seen, said = [], []
    result = calibrate(measured, nominal, grid, method="ncc-lle-exact", iterations=3, stop_update_px=0.0,
                       on_iteration=lambda rec, params: seen.append(params))
    assert len(result.history) == 3
    before = [np.zeros_like(seen[0])] + seen[:-1]
    for rec, p0, p1 in zip(result.history, before, seen):
        expected = reprojection_error(nominal.perturbed(p1), nominal.perturbed(p0), pts)["mean_px"]
        assert rec.update_px == pytest.approx(expected, rel=1e-9)
    assert result.history[0].update_px > 0.5  # the first iteration undoes most of the ~1 px error
    # a threshold above the first update: one iteration, and it says why
    first = result.history[0].update_px
    stopped = calibrate(measured, nominal, grid, method="ncc-lle-exact", iterations=3, stop_update_px=2 * first,
                        progress=said.append)
    assert len(stopped.history) == 1
    # nothing found at once is not convergence (an outside check read "converged" on a correction of 0.01 px)
    assert not any(line.startswith("converged") for line in said)
    assert any("stopping after the first of 3 iterations" in line for line in said)
    # a threshold the user set high stops a real correction: the note says so, not that nothing was found (it did)
    assert any("less than stop_update_px" in n and "no further iteration ran" in n for n in stopped.notes), \
        stopped.notes
    assert not any("next to nothing" in n for n in stopped.notes), stopped.notes
    # a threshold between the first and the second update: two iterations, converged
    said.clear()
    second = result.history[1].update_px
    assert second < first
    stopped = calibrate(measured, nominal, grid, method="ncc-lle-exact", iterations=3,
                        stop_update_px=0.5 * (first + second), progress=said.append)
    assert len(stopped.history) == 2 and any(line.startswith("converged") for line in said)
    assert not any("next to nothing" in n for n in stopped.notes)
    with pytest.raises(ValueError, match="stop_update_px"):
        calibrate(measured, nominal, grid, stop_update_px=-1.0)


def test_stop_ncc_gain_undoes_an_iteration_that_hardly_raises_the_model_ncc():
    """With ``stop_ncc_gain`` an iteration after the first whose estimation model explains the data
    by less than that much better than the previous one's (projection NCC) is undone and ends the loop;
    the first iteration has nothing to compare with and always counts. Off (0) by default."""
    nominal, true, grid, measured = _small_scan()
    seen = []
    free = calibrate(measured, nominal, grid, method="ncc-lle-exact", iterations=3, stop_update_px=0.0,
                     on_iteration=lambda rec, params: seen.append(params))
    assert len(free.history) == 3 and not any("stop_ncc_gain" in n for n in free.notes)
    gains = np.diff([rec.projection_ncc for rec in free.history])
    said = []
    # a threshold above iteration 2's gain: iteration 2 is undone, iteration 1's geometry stays
    stopped = calibrate(measured, nominal, grid, method="ncc-lle-exact", iterations=3, stop_update_px=0.0,
                        stop_ncc_gain=max(gains[0], 0.0) + 1e-3, progress=said.append)
    assert len(stopped.history) == 1
    np.testing.assert_allclose(stopped.params, seen[0], atol=1e-12)
    assert any("undone, stopping" in line for line in said)
    told = [n for n in stopped.notes if n.startswith("stop_ncc_gain: iteration 2 ")]
    assert len(told) == 1 and "the geometry of iteration 1 stays" in told[0]
    # a threshold below every gain leaves the loop as it was
    if gains.min() > 0:
        kept = calibrate(measured, nominal, grid, method="ncc-lle-exact", iterations=3, stop_update_px=0.0,
                         stop_ncc_gain=0.5 * gains.min())
        np.testing.assert_allclose(kept.params, free.params, atol=1e-12)
    with pytest.raises(ValueError, match="stop_ncc_gain"):
        calibrate(measured, nominal, grid, stop_ncc_gain=-1.0)


def test_the_stop_ncc_gain_note_says_lowered_for_a_fall():
    """An undone iteration whose NCC fell was 'raised ... by -5.87e-04 only'."""
    from robot_ct_ros.ct.calibration.loop import _ncc_gain_note

    fell = _ncc_gain_note(8, 0.91234, 0.91234 - 5.87e-4, 1e-4)
    assert fell.startswith("stop_ncc_gain: iteration 8 lowered the estimation model's projection NCC by 5.87e-04 "
                           "(0.91234 -> 0.91175; stop_ncc_gain asks a rise of 0.0001 at least) and was undone"), fell
    assert "raised" not in fell and "-5.87" not in fell and fell.endswith("the geometry of iteration 7 stays")
    rose = _ncc_gain_note(2, 0.9, 0.90005, 1e-4)
    assert "raised the estimation model's projection NCC by 5.00e-05 only (0.90000 -> 0.90005" in rose
    assert "unchanged" in _ncc_gain_note(2, 0.9, 0.9, 1e-4)


def test_fit_drift_keeps_polynomials_and_outvotes_single_views():
    from robot_ct_ros.ct.calibration import fit_drift

    t = np.linspace(-1.0, 1.0, 40)[:, None]
    smooth = np.hstack([0.1 + 0.2 * t - 0.3 * t ** 3] * 9)  # a cubic drift of every parameter
    np.testing.assert_allclose(fit_drift(smooth, 3), smooth, atol=1e-12)
    assert np.abs(fit_drift(smooth, 1) - smooth).max() > 0.01  # a line cannot follow it
    noisy = smooth + np.random.default_rng(0).normal(0.0, 0.05, smooth.shape)
    assert np.abs(fit_drift(noisy, 3) - smooth).mean() < 0.5 * np.abs(noisy - smooth).mean()
    # with a pause in the scan the drift is a polynomial in time, not in the view index
    times = np.r_[np.arange(20), 60 + np.arange(20)].astype(float)
    tn = 2 * times / times.max() - 1
    paused = np.hstack([0.1 + 0.2 * tn[:, None] ** 2] * 9)
    np.testing.assert_allclose(fit_drift(paused, 2, times), paused, atol=1e-12)
    assert np.abs(fit_drift(paused, 2) - paused).max() > 0.01
    with pytest.raises(ValueError, match="drift times"):
        fit_drift(paused, 2, np.zeros(40))
    with pytest.raises(ValueError, match=">= 0"):
        fit_drift(smooth, -1)
    with pytest.raises(ValueError, match="more than"):
        fit_drift(smooth[:3], 3)


def test_drift_model_beats_per_view_estimates_on_a_drifting_truncated_scan():
    """A linear detector drift (0.9 mm and 0.3 deg over the scan) on a truncated scan: part of it
    lies in modes that conjugate views cannot tell apart, which the per-view estimate leaves
    in place; fitted as a polynomial in acquisition order, the seen part carries the rest."""
    from robot_ct_ros.ct.calibration import fit_drift
    from robot_ct_ros.ct.simulation import detector_drift

    n_views = 30
    nominal, true, grid, measured = _small_scan(  # a body wider than the field of view
        n_views, body_width_mm=20.0, error_model=detector_drift(0.9 / n_views, 0.3 / n_views, kind="linear", seed=1))
    pts = roi_points(grid)
    errors = {}
    for order in (None, 3):
        result = calibrate(measured, nominal, grid, method="ncc-lle-exact", iterations=2, drift_order=order)
        errors[order] = reprojection_error(result.geom, true, pts)["mean_px"]
        if order is not None:
            # polynomials in time, in the nominal gauge (the two alternate to 10 nm)
            np.testing.assert_allclose(fit_drift(result.params, order), result.params, atol=1e-5)
            assert any(n.startswith("drift model: each parameter a polynomial of degree 3") and "hardly" not in n
                       for n in result.notes), result.notes  # the result says which model made it
        else:
            assert not any(n.startswith("drift model") for n in result.notes)
    assert reprojection_error(nominal, true, pts)["mean_px"] > 0.5
    assert errors[3] < 0.85 * errors[None], errors
    with pytest.raises(ValueError, match="more than"):
        calibrate(measured, nominal, grid, drift_order=n_views)


def test_ncc_ignores_an_intensity_offset_that_misleads_l2():
    """Truncation and flat-field drift add a smooth offset to every interior projection."""
    nominal, true, grid, measured = _small_scan(body_width_mm=14.0, length_mm=30.0)
    offset = measured + 0.15 + 0.1 * np.linspace(-1, 1, measured.shape[2])[None, None, :] ** 2
    volume = fdk(measured, true, grid)  # the estimator alone: reconstruction with the true geometry
    pts = roi_points(grid)
    errs = {}
    for weighting in ("l2", "ncc-exact"):
        cfg = LLEConfig(weighting=weighting, background=(2, 2), levels=3)
        params, _ = estimate_views(offset, nominal, np.zeros((nominal.n_views, 9)), volume, grid, cfg)
        errs[weighting] = reprojection_error(nominal.perturbed(params), true, pts)["mean_px"]
    assert errs["ncc-exact"] < 0.7 * errs["l2"], errs


def test_homography_warp_equals_a_true_reprojection_after_a_detector_move():
    nominal, true, grid, _ = _small_scan(n_views=3)
    volume = voxelize(mouse_phantom(body_width_mm=9.0, length_mm=10.0), grid)
    params = np.zeros((3, 9))
    params[:, 3:6] = [0.4, -0.3, 1.0]
    params[:, 6:9] = np.deg2rad([0.5, -0.4, 0.8])
    moved = nominal.perturbed(params)
    virtual = nominal.with_detector(nominal.n_rows + 16, nominal.n_cols + 16)
    warped, valid = warp_projections(forward_project(volume, grid, virtual),
                                     detector_homographies(virtual, moved), np.arange(3),
                                     moved.n_rows, moved.n_cols)
    direct = forward_project(volume, grid, moved)
    assert valid.all()
    rel = np.linalg.norm(warped - direct) / np.linalg.norm(direct)
    assert rel < 0.03, rel  # bilinear resampling of a 0.67 mm-pixel image
    unmoved = forward_project(volume, grid, nominal)
    assert np.linalg.norm(unmoved - direct) / np.linalg.norm(direct) > 3 * rel


def test_shift_search_captures_a_large_detector_shift_that_the_local_search_misses():
    nominal, true, grid, _ = _small_scan(n_views=8)
    volume = voxelize(mouse_phantom(body_width_mm=9.0, length_mm=10.0), grid)
    offset = np.zeros((8, 9))
    offset[:, 3] = np.where(np.arange(8) % 2, 1.0, -1.0) * 5 * nominal.col_pitch_mm  # +-5 px along u
    offset[:, 4] = 3 * nominal.row_pitch_mm                                        # 3 px along v
    measured = forward_project(volume, grid, nominal.perturbed(offset))
    pts = roi_points(grid)
    local = LLEConfig(levels=2, half_width=(0.05,) * 6 + (0.001,) * 3)  # a box far smaller than the shift
    errs = {}
    for reach in (0, 6):
        params, _ = estimate_views(measured, nominal, np.zeros((8, 9)), volume, grid,
                                   LLEConfig(**{**local.__dict__, "shift_search_px": reach}))
        errs[reach] = reprojection_error(nominal.perturbed(params), nominal.perturbed(offset), pts,
                                         align_gauge=False)["mean_px"]
    assert errs[0] > 3.0 and errs[6] < 0.5, errs


@pytest.mark.parametrize("weighting,source_positions", [("l2", "star"), ("l2", "fixed"), ("ncc", "fixed")])
def test_nan_and_inf_pixels_change_nothing_but_their_own_exclusion(weighting, source_positions):
    """Dead pixels reported as NaN or inf are excluded like masked ones: the estimate equals the
    one with those pixels zeroed and marked invalid (the scoring kernel reads every pixel and
    weights it 0 or 1, so a NaN must never reach it)."""
    nominal, true, grid, measured = _small_scan(n_views=6)
    volume = voxelize(mouse_phantom(body_width_mm=9.0, length_mm=10.0), grid)
    rng = np.random.default_rng(3)
    bad = rng.random(measured.shape) < 0.05
    broken = measured.copy()
    broken[bad] = np.where(rng.random(bad.sum()) < 0.5, np.nan, np.inf)
    config = LLEConfig(weighting=weighting, levels=2, n_samples=48, source_positions=source_positions,
                       shift_search_px=2, prior_sigma=(0.3,) * 6 + (0.005,) * 3)
    got, _ = estimate_views(broken, nominal, np.zeros((6, 9)), volume, grid, config)
    want, _ = estimate_views(np.where(bad, 0.0, measured), nominal, np.zeros((6, 9)), volume, grid, config,
                             valid_mask=~bad)
    assert np.isfinite(got).all()
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    assert np.abs(want).max() > 0.01  # the views did move


def test_hold_magnification_restores_the_nominal_object_scale():
    nominal, _, grid, _ = _small_scan(n_views=12)
    pts = roi_points(grid)
    params = np.zeros((12, 9))
    params[:, 5] = 2.0  # every detector 2 mm off along its normal: a common magnification change
    params[:, 3] = 0.1 * np.arange(12) / 12  # and something else that must survive
    assert abs(fit_object_scale(nominal.perturbed(params), nominal, pts) - 1.0) > 5e-3
    held = hold_magnification(nominal, params, pts)
    assert abs(fit_object_scale(nominal.perturbed(held), nominal, pts) - 1.0) < 1e-5
    np.testing.assert_allclose(held[:, 5], 0.0, atol=2e-3)
    np.testing.assert_array_equal(held[:, [0, 1, 2, 3, 4, 6, 7, 8]], params[:, [0, 1, 2, 3, 4, 6, 7, 8]])


def test_view_angles_follow_the_scan():
    nominal = circular_scan(36, 60.0, 150.0, 16, 16, 1.0, 1.0)
    t = view_angles(nominal, (0.0, 0.0, 0.0))
    np.testing.assert_allclose(np.diff(t), 2 * np.pi / 36, atol=1e-9)
    assert t[0] == 0.0


def test_estimation_volume_is_consistent_with_truncated_data():
    """SIRT after FDK reprojects closer to truncated data than FDK alone; masked pixels are ignored."""
    nominal, true, grid, measured = _small_scan(body_width_mm=14.0, length_mm=30.0)
    mask = np.ones(measured.shape[1:], bool)
    mask[:, 7] = False
    bad = measured.copy()
    bad[:, :, 7] = 1e3
    from robot_ct_ros.ct.calibration.volume import projection_consistency
    ncc_fdk = reconstruct_for_estimation(bad, true, grid, mask, 0).fdk_ncc
    vol, ncc_fdk_again, _ = reconstruct_for_estimation(bad, true, grid, mask, 10)
    assert ncc_fdk_again == ncc_fdk
    assert projection_consistency(vol, grid, true, measured, mask)[1] > ncc_fdk + 0.01
    clean = reconstruct_for_estimation(measured, true, grid, mask, 10).volume
    np.testing.assert_allclose(vol, clean, atol=1e-5 * np.abs(clean).max())  # the 1e3 column did not leak in


def test_coarse_sirt_correction_makes_the_fine_fdk_consistent():
    """FDK plus the 2x binned level's SIRT correction reprojects closer to truncated data than FDK
    at the coarse level's resolution (the low frequencies, where truncation leaves FDK wrong)."""
    from robot_ct_ros.ct.calibration.masks import bin_masked
    from robot_ct_ros.ct.geometry import bin_projections

    nominal, true, grid, measured = _small_scan(body_width_mm=14.0, length_mm=30.0)
    mask = np.ones(measured.shape, bool)
    li_c, mask_c = bin_masked(measured, mask, 2)
    coarse = reconstruct_for_estimation(li_c, true.binned(2), grid.binned(2), mask_c, 10)
    fine_fdk = reconstruct_for_estimation(measured, true, grid, mask, 0)
    fine = reconstruct_for_estimation(measured, true, grid, mask, 0,
                                      correction=(coarse.volume - coarse.fdk, grid.binned(2)))
    np.testing.assert_array_equal(fine.fdk, fine_fdk.fdk)

    def binned_ncc(vol):
        p = bin_projections(forward_project(vol, grid, true), 2, mean=True)
        return ncc(p.reshape(len(p), -1), li_c.reshape(len(p), -1)).mean()

    assert binned_ncc(fine.volume) > binned_ncc(fine.fdk) + 0.01


def test_focus_finds_an_odd_detector_shift_mode():
    """A cos(3t) detector shift (odd under the half turn, which conjugate views see only weakly) is found by
    sharpness."""
    nominal = circular_scan(60, 60.0, 150.0, 48, 48, 32.0 / 48, 32.0 / 48)
    grid = VolumeGrid.centered((16, 32, 32), 12.0 / 32)
    phantom = mouse_phantom(body_width_mm=9.0, length_mm=10.0)
    measured = forward_project(voxelize(phantom, grid), grid, nominal)
    t = view_angles(nominal, grid.center_mm)
    start = np.zeros((60, 9))
    start[:, 3] = 1.0 * nominal.col_pitch_mm * np.cos(3 * t)
    params, info = focus_conjugate_modes(measured, nominal, start, grid, None, modes={"shift": (3,)})
    residual = np.abs(params[:, 3]).max() / nominal.col_pitch_mm
    assert residual < 0.3, (residual, info)
    assert info["entropy_after"] < info["entropy_before"]


def test_truncation_level_tells_interior_scans_apart():
    """About zero when the object fits in the field of view, clearly above the threshold for
    an object wider than it; dead edge pixels are ignored."""
    from robot_ct_ros.ct.calibration.volume import TRUNCATED_ABOVE, truncation_level

    _, _, _, inside = _small_scan(n_views=8, body_width_mm=9.0, length_mm=30.0)
    _, _, _, wider = _small_scan(n_views=8, body_width_mm=40.0, length_mm=30.0)
    assert truncation_level(inside) < 0.1 * TRUNCATED_ABOVE
    assert truncation_level(wider) > 5 * TRUNCATED_ABOVE
    hot = inside.copy()
    hot[:, :, 0] = 1e3  # a dead, saturated edge column, masked out
    mask = np.ones(inside.shape[1:], bool)
    mask[:, 0] = False
    assert truncation_level(hot, mask) < 0.1 * TRUNCATED_ABOVE
    assert truncation_level(hot) > TRUNCATED_ABOVE
    below = inside.copy()
    below[:, :, :2] = below[:, :, -2:] = -1e-3 * float(inside.max())  # noise about an empty edge: no object there
    assert truncation_level(below) == 0.0  # was -0.001, printed "truncation level -0.000"


@pytest.mark.parametrize("body_width_mm", [9.0, 40.0])
def test_truncation_level_reads_the_edges_across_the_axis_of_a_portrait_detector(body_width_mm):
    """The same rays on a detector turned a quarter (rows along the axis): its first and last rows are the edges an
    interior scan truncates. Its columns' ends, where a long object leaves the cone, read 0.49 for a mouse that fits."""
    from robot_ct_ros.ct.calibration.volume import TRUNCATED_ABOVE, truncation_level

    nominal, _, _, li = _small_scan(n_views=8, body_width_mm=body_width_mm, length_mm=30.0)
    portrait = nominal.replace(u=nominal.v, v=-nominal.u, n_rows=nominal.n_cols, n_cols=nominal.n_rows)
    lp = np.ascontiguousarray(li[:, :, ::-1].transpose(0, 2, 1))
    assert truncation_level(lp, geom=portrait) == pytest.approx(truncation_level(li, geom=nominal), rel=1e-6)
    assert truncation_level(li, geom=nominal) == truncation_level(li)
    assert (truncation_level(lp, geom=portrait) > 5 * TRUNCATED_ABOVE) == (body_width_mm > 20)


def test_prior_keeps_views_whose_data_the_volume_cannot_explain_near_nominal():
    """Registered against a volume of another object, views follow spurious optima by the data
    alone; the posterior keeps them near the nominal geometry, and still moves views whose data
    the volume explains."""
    nominal, true, grid, measured = _small_scan(n_views=8)
    other = voxelize(mouse_phantom(body_width_mm=9.0, length_mm=10.0, seed=5), grid)[::-1].copy()
    sigma = (0.3,) * 6 + (np.deg2rad(0.3),) * 3
    moved = {}
    for prior in (None, sigma):
        cfg = LLEConfig(levels=3, shift_search_px=4, prior_sigma=prior)
        params, _ = estimate_views(measured, nominal, np.zeros((8, 9)), other, grid, cfg)
        moved[prior is not None] = float(np.sqrt((params[:, 3:5] ** 2).mean()))
    assert moved[True] < 0.5 * moved[False], moved
    # consistent data: the prior does not stop the estimate
    volume = voxelize(mouse_phantom(body_width_mm=9.0, length_mm=10.0), grid)
    offset = np.zeros((8, 9))
    offset[:, 3] = 1.0  # 1.5 px, over 3 prior sigmas
    target = nominal.perturbed(offset)
    exact = forward_project(volume, grid, target)
    params, _ = estimate_views(exact, nominal, np.zeros((8, 9)), volume, grid, LLEConfig(levels=3, prior_sigma=sigma))
    pts = roi_points(grid)
    before = reprojection_error(nominal, target, pts, align_gauge=False)["mean_px"]
    after = reprojection_error(nominal.perturbed(params), target, pts, align_gauge=False)["mean_px"]
    assert before > 1.2 and after < 0.2 * before, (before, after)
    with pytest.raises(ValueError, match="prior_sigma"):
        LLEConfig(prior_sigma=(0.3,) * 8)


def test_seed_reproduces_an_lle_estimate_and_another_seed_samples_anew():
    nominal, _, grid, measured = _small_scan(n_views=12)
    runs = {(method, seed): calibrate(measured, nominal, grid, method=method, iterations=1, seed=seed).params
            for method in ("ncc-lle-exact", "gdc") for seed in (0, 7)}
    np.testing.assert_array_equal(runs["ncc-lle-exact", 0], calibrate(measured, nominal, grid, iterations=1).params)
    assert np.abs(runs["ncc-lle-exact", 7] - runs["ncc-lle-exact", 0]).max() > 1e-4
    np.testing.assert_array_equal(runs["gdc", 7], runs["gdc", 0])  # the baselines draw no samples


def test_an_ensemble_is_the_mean_of_its_members_and_says_how_far_they_spread():
    from robot_ct_ros.ct.calibration import ENSEMBLE_SEED_STEP, average_estimates

    nominal, true, grid, measured = _small_scan(n_views=12)
    members = [calibrate(measured, nominal, grid, iterations=1, seed=3 + k * ENSEMBLE_SEED_STEP) for k in range(2)]
    said = []
    both = calibrate(measured, nominal, grid, ensemble=2, seed=3, iterations=1, progress=said.append)
    np.testing.assert_allclose(both.params, 0.5 * (members[0].params + members[1].params), atol=1e-12)
    assert both.members == 2
    assert [h.projection_rmse for h in both.history] == [h.projection_rmse for h in members[0].history]
    np.testing.assert_allclose(both.volume, fdk(measured, both.geom, grid), rtol=1e-5, atol=1e-6)
    # the spread: each member's distance from the mean, here half the distance between the two
    pts = roi_points(grid)
    apart = reprojection_error(members[0].geom, members[1].geom, pts)["mean_px"]
    assert 0.0 < both.spread_px and both.spread_px == pytest.approx(0.5 * apart, rel=0.05)
    assert any("ensemble of 2" in line for line in said)
    # what the members said reaches the ensemble's result: a note both made as it is, one only one made marked so
    for k, member in enumerate(members, start=1):
        for note in member.notes:
            assert note in both.notes or f"run {k}: {note}" in both.notes
    assert any(n.startswith("ensemble of 2: ") for n in both.notes)
    assert calibrate(measured, nominal, grid, ensemble=1, seed=3, iterations=1).spread_px != 0.0  # nan: one run
    with pytest.raises(ValueError, match="ensemble"):
        calibrate(measured, nominal, grid, ensemble=0)
    with pytest.raises(ValueError, match="no estimates"):
        average_estimates([], measured, nominal, grid)


def test_an_ensemble_keeps_its_runs_notes_and_their_estimates_before_the_guard():
    """A run whose guard kept the nominal geometry says so in the ensemble's notes, and the ensemble's
    estimate before the guard is the mean of the runs' estimates before theirs."""
    from dataclasses import replace

    from robot_ct_ros.ct.calibration import average_estimates
    from robot_ct_ros.ct.calibration.ensemble import member_notes

    nominal, _, grid, measured = _small_scan(n_views=12)
    run = calibrate(measured, nominal, grid, iterations=1, seed=3)
    refused = replace(run, params=np.zeros_like(run.params), params_unguarded=run.params + 0.01,
                      notes=("strongly truncated", "guard: the nominal geometry is kept"))
    kept = replace(run, notes=("strongly truncated", "guard: the correction is 0.5 times the robots' accuracy"),
                   params_unguarded=None)
    both = average_estimates([refused, kept], measured, nominal, grid)
    np.testing.assert_allclose(both.params, 0.5 * run.params, atol=1e-12)
    np.testing.assert_allclose(both.params_unguarded, run.params + 0.005, atol=1e-12)
    assert both.notes[:3] == ("strongly truncated", "run 1: guard: the nominal geometry is kept",
                              "run 2: guard: the correction is 0.5 times the robots' accuracy")
    assert both.notes[3].startswith("ensemble of 2: ")
    assert average_estimates([kept, kept], measured, nominal, grid).params_unguarded is None
    assert member_notes([kept]) == kept.notes
    assert member_notes([refused, refused, kept])[1] == "runs 1, 2: guard: the nominal geometry is kept"


def test_without_prior_the_loop_reports_no_independent_fraction():
    nominal, _, grid, measured = _small_scan(n_views=12)
    result = calibrate(measured, nominal, grid, method="ncc-lle-exact", iterations=1,
                       prior_translation_mm=0.0, prior_rotation_deg=0.0)
    assert np.isnan(result.history[0].independent_fraction)


def test_averaged_sample_sets_scatter_less_between_seeds_than_one_set():
    """``draws`` sets of samples per level, embedded one by one and averaged: the estimate's
    sampling noise (how far two seeds' estimates of the same views lie apart) shrinks, which is
    what the sets are for, and the views stay as close to the truth (each set embeds its own
    view's samples). Without the safeguard, which may replace the average by the best single
    sample."""
    nominal, true, grid, measured = _small_scan(n_views=8)
    volume = voxelize(mouse_phantom(body_width_mm=9.0, length_mm=10.0), grid)
    pts = roi_points(grid)
    base = LLEConfig(levels=2, n_samples=48, half_width=(0.3,) * 6 + (0.005,) * 3, safeguard=False)

    def scatter_and_error(draws):
        est = [nominal.perturbed(estimate_views(measured, nominal, np.zeros((8, 9)), volume, grid,
                                                LLEConfig(**{**base.__dict__, "draws": draws, "seed": s}))[0])
               for s in range(4)]
        apart = np.mean([reprojection_error(a, b, pts, align_gauge=False)["mean_px"]
                         for i, a in enumerate(est) for b in est[i + 1:]])
        return apart, np.mean([reprojection_error(e, true, pts)["mean_px"] for e in est])

    (one, one_error), (four, four_error) = scatter_and_error(1), scatter_and_error(4)
    assert four < 0.75 * one, (one, four)
    before = reprojection_error(nominal, true, pts)["mean_px"]
    assert four_error < 1.1 * one_error < 0.3 * before, (before, one_error, four_error)
    with pytest.raises(ValueError, match="draws"):
        LLEConfig(draws=0)


def test_usable_data_and_binning_make_no_full_size_copy_and_change_nothing():
    """Clean float32 data are used as they are (no copy); data with invalid pixels are zeroed there;
    binning in chunks of views equals binning the stack at once."""
    from robot_ct_ros.ct.calibration import masks
    from robot_ct_ros.ct.calibration.masks import bin_masked, usable_data
    from robot_ct_ros.ct.geometry import bin_projections

    rng = np.random.default_rng(0)
    li = rng.random((37, 12, 18), dtype=np.float32)
    valid = rng.random((12, 18)) > 0.1
    li[:, ~valid] = 0.0
    same, mask = usable_data(li, valid)
    assert same is li and mask.shape == li.shape and not mask[:, ~valid].any()
    dirty = li.copy()
    dirty[:, ~valid] = 5.0
    dirty[3, 4, 5] = np.nan
    clean, mask2 = usable_data(dirty, valid)
    assert clean is not dirty and clean.dtype == np.float32
    np.testing.assert_array_equal(clean, np.where(mask2, dirty, 0.0))
    assert not mask2[3, 4, 5] and clean[3, 4, 5] == 0.0
    for factor in (2, 3):
        m = mask2.astype(np.float32)
        total = bin_projections(np.where(m > 0, clean, 0.0).astype(np.float32), factor)
        count = bin_projections(m, factor)
        binned, ok = bin_masked(clean, mask2, factor)
        assert masks.BIN_CHUNK_VIEWS < len(clean)  # several chunks
        np.testing.assert_array_equal(binned, (total / np.maximum(count, 1.0)).astype(np.float32))
        np.testing.assert_array_equal(ok, count > 0)


def test_calibrate_without_the_final_volume_returns_the_same_geometry():
    nominal, true, grid, measured = _small_scan(n_views=12, n_det=32)
    kw = dict(method="ncc-lle", iterations=1, schedule="fast", projections="complete")
    with_volume = calibrate(measured, nominal, grid, **kw)
    without = calibrate(measured, nominal, grid, final_volume=False, **kw)
    assert with_volume.volume.shape == grid.shape_zyx and without.volume is None
    np.testing.assert_array_equal(without.params, with_volume.params)
    assert calibrate(measured, nominal, grid, method="none", final_volume=False).volume is None


def test_an_ensemble_honours_final_volume_reconstructs_on_the_executor_and_names_unused_settings(monkeypatch):
    """An ensemble reconstructed its mean geometry in this process whatever the executor (scheduler), also with
    final_volume False, and dropped the notes on settings that did not apply, which a single run adds."""
    from robot_ct_ros.ct import reconstruction
    from robot_ct_ros.ct.calibration import loop
    from robot_ct_ros.ct.calibration.distributed import InProcess

    nominal, _, grid, measured = _small_scan(n_views=12, n_det=32)
    real, on_executor, elsewhere = reconstruction.fdk, [], []

    class Counted(InProcess):
        def fdk(self, line_integrals, geom, grid_, **kwargs):
            on_executor.append(grid_.shape_zyx)
            return real(line_integrals, geom, grid_, **kwargs)

    monkeypatch.setattr(loop, "executor_for", lambda settings: Counted())
    monkeypatch.setattr(reconstruction, "fdk",
                        lambda li, geom, grid_, **kw: elsewhere.append(1) or real(li, geom, grid_, **kw))
    kw = dict(method="ncc-lle", iterations=1, schedule="fast", projections="complete", exterior="off",
              exterior_voxel_mm=0.25, ensemble=2)
    both = calibrate(measured, nominal, grid, **kw)
    assert on_executor.count(grid.shape_zyx) == 1 and not elsewhere  # the mean's volume alone, on the executor
    np.testing.assert_allclose(both.volume, real(measured, both.geom, grid), rtol=1e-5, atol=1e-6)
    on_executor.clear()
    without = calibrate(measured, nominal, grid, final_volume=False, **kw)
    assert without.volume is None and grid.shape_zyx not in on_executor and not elsewhere
    np.testing.assert_array_equal(without.params, both.params)
    for result in (both, without):
        unused = [n for n in result.notes if "exterior_voxel_mm 0.25 did not apply: exterior is off" in n]
        assert len(unused) == 1, result.notes


def test_the_lle_settings_a_method_ignores_come_from_the_registry_not_from_its_name_or_prior():
    """Whether lle_ridge applied was decided by the name "ncc-lle", whether the method embeds samples at all by
    its prior: an embedding without a prior, or another closed form, got the wrong "did not apply" note."""
    from dataclasses import replace

    from robot_ct_ros.ct.calibration import CalibrationSettings
    from robot_ct_ros.ct.calibration.loop import _unused_settings
    from robot_ct_ros.ct.calibration.registry import get_method

    given = CalibrationSettings(lle_neighbours=8, lle_ridge=1e-3)
    assert {n: get_method(n).lle_settings for n in ("ncc-lle-exact", "l2-lle", "ncc-lle", "gdc", "none")} == {
        "ncc-lle-exact": ("lle_neighbours", "lle_ridge"), "l2-lle": ("lle_neighbours", "lle_ridge"),
        "ncc-lle": ("lle_neighbours",), "gdc": (), "none": ()}
    no_prior = replace(get_method("l2-lle"), name="l2-lle-data", uses_prior=False)
    assert "lle_" not in _unused_settings(no_prior, given)
    closed = replace(get_method("ncc-lle-exact"), name="closed", lle_settings=("lle_neighbours",))
    assert "lle_ridge 0.001 did not apply: closed" in _unused_settings(closed, given)
    assert "lle_neighbours 8" not in _unused_settings(closed, given)
    assert "lle_neighbours 8, lle_ridge 0.001 did not apply: gdc embeds no samples" in _unused_settings(
        get_method("gdc"), given)


def test_calibrate_leaves_the_callers_data_as_they_were():
    """usable_data hands clean data through uncopied: no step of the loop may write into them."""
    nominal, true, grid, measured = _small_scan(n_views=12, n_det=32)
    measured = np.ascontiguousarray(measured, dtype=np.float32)
    before = measured.copy()
    for kw in (dict(method="ncc-lle-exact", projections="truncated"), dict(method="gdc", projections="complete"),
               dict(method="ncc-lle-exact", exterior="on", exterior_voxel_mm=2.0)):
        calibrate(measured, nominal, grid, iterations=1, schedule="fast", **kw)
        np.testing.assert_array_equal(measured, before)


def test_exterior_auto_models_a_strongly_truncated_scan_only_when_the_objects_reach_is_stated_or_guessed():
    """An exterior reaching far past the object costs more than it gains (docs/results/exterior_reach.md):
    ``auto`` models the object outside the ROI only on a strongly truncated scan and only with its
    reach stated or guessed, and says so either way; without the guess (exterior_reach_guess off) ``on``
    says that it reached the sources. A scan too short to guess on (8 views) keeps the ROI model and
    says why."""
    _, _, _, inside = _small_scan(n_views=8, body_width_mm=9.0, length_mm=30.0)
    nominal, _, grid, wider = _small_scan(n_views=8, body_width_mm=40.0, length_mm=30.0)
    kw = dict(method="ncc-lle-exact", iterations=1, schedule="fast", exterior_voxel_mm=2.0, final_volume=False)
    modelled = "the object outside the ROI was modelled (exterior model)"
    stated = calibrate(wider, nominal, grid, exterior="auto", exterior_half_width_mm=20.0, **kw).notes
    assert modelled in stated and not any("not stated" in n or "not modelled" in n for n in stated)
    unstated = calibrate(wider, nominal, grid, exterior_reach_guess=False, **kw).notes  # auto is the default
    assert modelled not in unstated
    assert any("strongly truncated" in n and "exterior_half_width_mm" in n and "on ROS exterior_half_width_m," in n
               for n in unstated)
    too_few = calibrate(wider, nominal, grid, **kw).notes  # the guess needs 20 views
    assert modelled not in too_few
    assert any("could not be guessed" in n and "20 views" in n and "not modelled" in n for n in too_few), too_few
    small = calibrate(inside, nominal, grid, exterior_half_width_mm=20.0, **kw).notes
    assert modelled not in small and not any("strongly truncated" in n for n in small)
    to_sources = calibrate(wider, nominal, grid, exterior="on", exterior_reach_guess=False, **kw).notes
    assert modelled in to_sources and any("up to the sources" in n for n in to_sources)


def test_an_unstated_reach_is_guessed_by_held_out_prediction_and_the_result_says_which():
    """auto (and on) without exterior_half_width_mm: the exterior model reaches the candidate that best
    predicted the views its model was not built from; the result's settings hold that reach, its notes
    the candidates' scores. The guess runs on the schedule's coarse level with the nominal geometry, so
    choose_reach there gives the same reach."""
    from robot_ct_ros.ct.calibration.exterior import choose_reach
    from robot_ct_ros.ct.calibration.masks import bin_masked
    from robot_ct_ros.ct.calibration.volume import estimation_grid

    nominal, _, grid, wider = _small_scan(n_views=20, n_det=32, body_width_mm=40.0, length_mm=30.0)
    kw = dict(method="ncc-lle-exact", iterations=1, exterior_voxel_mm=2.0, final_volume=False)
    said = []
    guessed = calibrate(wider, nominal, grid, progress=said.append, **kw)
    reach = guessed.settings.exterior_half_width_mm
    assert "the object outside the ROI was modelled (exterior model)" in guessed.notes
    assert guessed.settings.schedule == "exterior" and reach > 0
    note = [n for n in guessed.notes if "was not stated" in n]
    assert len(note) == 1 and f"reaches {reach:.1f} mm" in note[0] and "held-out NCC" in note[0], guessed.notes
    li, mask = bin_masked(wider, np.ones(wider.shape, bool), 4)
    direct = choose_reach(li, nominal.binned(4), estimation_grid(grid, guessed.settings.padding).binned(4), mask,
                          voxel_mm=2.0, iterations=30, subsets=guessed.settings.exterior_subsets)
    assert direct.reach_mm == reach
    on = calibrate(wider, nominal, grid, exterior="on", **kw)
    assert on.settings.exterior_half_width_mm == reach and not any("up to the sources" in n for n in on.notes)
    kept = calibrate(wider, nominal, grid, exterior_reach_guess=False, **kw)
    assert kept.settings.exterior_half_width_mm == 0 and kept.settings.schedule == "accurate"


def test_an_ensemble_guesses_the_reach_once_for_all_its_members(monkeypatch):
    """The guess uses the nominal geometry and no sampling: an ensemble's members share the first one's
    choice (choose_reach runs once), model the same reach, and the ensemble's notes carry the guess's note
    as a note every member made."""
    from robot_ct_ros.ct.calibration import loop

    nominal, _, grid, wider = _small_scan(n_views=20, n_det=32, body_width_mm=40.0, length_mm=30.0)
    calls = []
    real = loop.choose_reach

    def counted(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(loop, "choose_reach", counted)
    both = calibrate(wider, nominal, grid, method="ncc-lle-exact", iterations=1, exterior_voxel_mm=2.0,
                     final_volume=False, ensemble=2)
    assert len(calls) == 1
    assert both.settings.exterior_half_width_mm > 0
    guess = [n for n in both.notes if "was not stated" in n]
    assert len(guess) == 1 and not guess[0].startswith("run"), both.notes
    single = calibrate(wider, nominal, grid, method="ncc-lle-exact", iterations=1, exterior_voxel_mm=2.0,
                       final_volume=False)
    assert len(calls) == 2 and single.settings.exterior_half_width_mm == both.settings.exterior_half_width_mm


def test_the_default_schedule_is_exterior_with_the_exterior_model_and_accurate_without_and_the_result_says_which():
    """schedule auto: the loop decides the model first, then runs that model's schedule, and its result records
    the schedule and the values it filled in (iterations, stop_ncc_gain, exterior passes); values given win."""
    nominal, _, grid, wider = _small_scan(n_views=8, body_width_mm=40.0, length_mm=30.0)
    kw = dict(method="ncc-lle-exact", exterior_voxel_mm=2.0, final_volume=False)
    said = []
    modelled = calibrate(wider, nominal, grid, exterior_half_width_mm=20.0, iterations=2, progress=said.append, **kw)
    used = modelled.settings
    assert (used.schedule, used.iterations, used.stop_ncc_gain, used.exterior_iterations) == ("exterior", 2, 1e-4, 30)
    assert any(m.startswith("schedule exterior: 2 iteration(s) at most") for m in said), said
    assert 1 <= len(modelled.history) <= 2
    roi = calibrate(wider, nominal, grid, iterations=1, exterior_reach_guess=False, **kw).settings  # the ROI model
    assert (roi.schedule, roi.iterations, roi.stop_ncc_gain, roi.exterior_iterations) == ("accurate", 1, 0.0, 15)
    named = calibrate(wider, nominal, grid, exterior_half_width_mm=20.0, iterations=1, schedule="fast", **kw).settings
    assert (named.schedule, named.stop_ncc_gain, named.exterior_iterations) == ("fast", 0.0, 15)


def test_the_guard_is_stricter_on_a_strongly_truncated_scan_whose_exterior_was_not_modelled():
    """There the ROI model's data term is biased: the scan-level limit on R is guard_max_ratio_unmodelled
    (1), whether exterior is auto without a stated or guessed reach or off; a modelled or untruncated scan keeps
    guard_max_ratio (1.5). The limit decides: just below the correction's own R, the scan keeps its
    nominal geometry."""
    import re

    _, _, _, inside = _small_scan(n_views=8, body_width_mm=9.0, length_mm=30.0)
    nominal, _, grid, wider = _small_scan(n_views=8, body_width_mm=40.0, length_mm=30.0)
    # the model-NCC floors 0: the ROI model's poor fit of the wide body must not decide first
    kw = dict(method="ncc-lle-exact", iterations=1, schedule="fast", exterior_voxel_mm=2.0, final_volume=False,
              guard_min_ncc=0.0, guard_min_ncc_unmodelled=0.0, exterior_reach_guess=False)

    def limit(notes):
        found = [re.search(r"times the robots' stated accuracy \(limit ([\d.]+)\)", n) for n in notes]
        return [(float(m.group(1)), float(re.search(r"([\d.]+) times", m.string).group(1))) for m in found if m][0]

    unmodelled = calibrate(wider, nominal, grid, **kw)
    assert limit(unmodelled.notes)[0] == 1.0
    off = calibrate(wider, nominal, grid, exterior="off", **kw)
    assert limit(off.notes)[0] == 1.0 and any("exterior off" in n for n in off.notes), off.notes
    assert limit(calibrate(wider, nominal, grid, exterior_half_width_mm=20.0, **kw).notes)[0] == 1.5
    assert limit(calibrate(inside, nominal, grid, **kw).notes)[0] == 1.5
    ratio = limit(unmodelled.notes)[1]
    assert ratio > 0.05 and np.abs(unmodelled.params).max() > 0
    refused = calibrate(wider, nominal, grid, guard_max_ratio_unmodelled=0.9 * ratio, **kw)
    np.testing.assert_array_equal(refused.params, 0.0)
    assert any("nominal geometry is kept" in n for n in refused.notes), refused.notes


def test_a_strongly_truncated_scan_whose_exterior_was_not_modelled_needs_a_model_that_explains_more():
    """guard_min_ncc_unmodelled is the model-NCC floor there (the stricter of it and guard_min_ncc); a scan
    whose exterior was modelled keeps guard_min_ncc. Each floor decides at the correction's own NCC."""
    nominal, _, grid, wider = _small_scan(n_views=8, body_width_mm=40.0, length_mm=30.0)
    kw = dict(method="ncc-lle-exact", iterations=1, schedule="fast", exterior_voxel_mm=2.0, final_volume=False,
              guard_min_ncc=0.0, guard_max_ratio=100.0, guard_max_ratio_unmodelled=100.0, exterior_reach_guess=False,
              guard_min_ncc_exterior=0.0)
    free = calibrate(wider, nominal, grid, guard_min_ncc_unmodelled=0.0, **kw)
    ncc = free.history[-1].projection_ncc
    assert 0.0 < ncc < 1.0 and np.abs(free.params).max() > 0
    refused = calibrate(wider, nominal, grid, guard_min_ncc_unmodelled=min(1.0, ncc + 0.01), **kw)
    np.testing.assert_array_equal(refused.params, 0.0)
    assert any("explains the data poorly" in n and f"< {min(1.0, ncc + 0.01):g}" in n for n in refused.notes), \
        refused.notes
    kept = calibrate(wider, nominal, grid, guard_min_ncc_unmodelled=max(0.0, ncc - 0.01), **kw)
    np.testing.assert_array_equal(kept.params, free.params)
    # the exterior modelled (its reach stated): the unmodelled floor does not apply
    modelled = calibrate(wider, nominal, grid, exterior_half_width_mm=20.0, guard_min_ncc_unmodelled=1.0, **kw)
    assert not any("explains the data poorly" in n for n in modelled.notes), modelled.notes


def test_a_scan_whose_exterior_was_modelled_needs_a_model_that_explains_it_well():
    """guard_min_ncc_exterior is the model-NCC floor where the exterior was modelled (the stricter of it and
    guard_min_ncc), decided at the correction's own NCC; the note says to state a guessed reach. Without
    the exterior model the floor does not apply."""
    nominal, _, grid, wider = _small_scan(n_views=8, body_width_mm=40.0, length_mm=30.0)
    kw = dict(method="ncc-lle-exact", iterations=1, schedule="fast", exterior_voxel_mm=2.0, final_volume=False,
              guard_min_ncc=0.0, guard_min_ncc_unmodelled=0.0, guard_max_ratio=100.0,
              guard_max_ratio_unmodelled=100.0, exterior_reach_guess=False, exterior_half_width_mm=20.0)
    free = calibrate(wider, nominal, grid, guard_min_ncc_exterior=0.0, **kw)
    assert "the object outside the ROI was modelled (exterior model)" in free.notes
    ncc = free.history[-1].projection_ncc
    assert 0.0 < ncc < 1.0 and np.abs(free.params).max() > 0
    refused = calibrate(wider, nominal, grid, guard_min_ncc_exterior=min(1.0, ncc + 0.01), **kw)
    np.testing.assert_array_equal(refused.params, 0.0)
    np.testing.assert_array_equal(refused.params_unguarded, free.params)
    note = next(n for n in refused.notes if "explains the data poorly" in n)
    assert f"< {min(1.0, ncc + 0.01):g}" in note and "exterior_half_width_mm" in note, note
    kept = calibrate(wider, nominal, grid, guard_min_ncc_exterior=max(0.0, ncc - 0.01), **kw)
    np.testing.assert_array_equal(kept.params, free.params)
    # the stricter floor decides: guard_min_ncc above the exterior's refuses too
    stricter = calibrate(wider, nominal, grid, **(kw | dict(guard_min_ncc=min(1.0, ncc + 0.01))),
                         guard_min_ncc_exterior=0.0)
    np.testing.assert_array_equal(stricter.params, 0.0)
    # the ROI model (exterior off): the exterior floor does not apply
    roi = calibrate(wider, nominal, grid, exterior="off", guard_min_ncc_exterior=1.0, **kw)
    assert not any("explains the data poorly" in n for n in roi.notes), roi.notes


def test_a_drift_fitted_estimate_stays_in_the_nominal_gauge():
    """The drift fit ran after the gauge fix and put part of a gauge motion back: a linear drift's estimate sat
    0.09 mm rigidly off the nominal frame that calibration.md §5 and the ensemble's mean rely on."""
    from robot_ct_ros.ct.metrics import remove_gauge

    n = 24
    t = np.linspace(-1.0, 1.0, n)[:, None]
    drift = np.hstack([0.3 * t, np.zeros((n, 2)), 0.5 * t, np.zeros((n, 1)), 0.2 * t, np.zeros((n, 3))])
    model = type("Drift", (), {"sample": staticmethod(lambda k: drift)})()
    nominal, true, grid, measured = _small_scan(n_views=n, n_det=32, error_model=model)
    result = calibrate(measured, nominal, grid, iterations=1, drift_order=1, exterior="off", schedule="fast")
    pts = roi_points(grid)
    aligned = remove_gauge(result.geom, nominal, pts).params_relative_to(nominal)
    assert np.abs(aligned - result.params)[:, :6].max() < 2e-3, np.abs(aligned - result.params).max(axis=0)
