"""The alternating loop: reconstruct, estimate every view, fix the gauge, repeat (docs/calibration.md §1).

:func:`calibrate` is the one entry point: data, nominal geometry, ROI grid and a
:class:`~robot_ct_ros.ct.calibration.settings.CalibrationSettings`. The method comes from the
registry (:mod:`robot_ct_ros.ct.calibration.registry`). Why each step is there, and the
measurements behind the defaults: docs/calibration.md.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from robot_ct_ros.ct.calibration.constraints import fit_drift, focus_conjugate_modes, hold_magnification, moved_px
from robot_ct_ros.ct.calibration.distributed import InProcess, executor_for
from robot_ct_ros.ct.calibration.ensemble import average_estimates, member_seeds
from robot_ct_ros.ct.calibration.exterior import choose_reach, reconstruct_with_exterior
from robot_ct_ros.ct.calibration.guard import plausibility_guard
from robot_ct_ros.ct.calibration.kernels import blas_single_threaded
from robot_ct_ros.ct.calibration.masks import bin_masked, usable_data
from robot_ct_ros.ct.calibration.registry import get_method
from robot_ct_ros.ct.calibration.result import CalibrationResult, IterationRecord
from robot_ct_ros.ct.calibration.settings import REACH_SETTING, CalibrationSettings
from robot_ct_ros.ct.calibration.volume import (EXTERIOR_ABOVE, TRUNCATED_ABOVE, EstimationVolume, axis_last,
                                                estimation_grid,
                                                projection_consistency, reconstruct_for_estimation,
                                                truncation_level)
from robot_ct_ros.ct.field_of_view import field_of_view_extent, field_of_view_mask
from robot_ct_ros.ct.geometry import PARAM_NAMES, ConeGeometry, VolumeGrid, observable_params
from robot_ct_ros.ct.metrics import remove_gauge, roi_points

__all__ = ["calibrate", "settings_with"]


def _guess_reach(li, mask, nominal, grid, settings, notes: list, say, memo: dict | None = None):
    """The exterior model's reach where none is stated: :func:`choose_reach` on the exterior schedule's
    coarse level, with the nominal geometry. Returns (settings with the reach, whether the exterior is
    modelled, whether the scan is strongly truncated and unmodelled). Where no reach can be scored (too
    few views, no room between the ROI and the sources), auto keeps the ROI model and on reaches up to
    the sources, and ``notes`` says why. ``memo`` (a dict shared by an ensemble's members, whose guess
    does not depend on their sampling seeds) keeps the first member's choice for the others."""
    if memo is not None and "choice" in memo:
        choice = memo["choice"]
    else:
        plan = settings.resolved(True).plan()
        binning = int(plan["coarse_binning"])
        li_c, mask_c, nom_c, grid_c = _level(li, mask, nominal, estimation_grid(grid, settings.padding), binning)
        say("the object's reach is not stated: guessing it (held-out prediction of candidate reaches, coarse level)")
        try:
            choice = choose_reach(li_c, nom_c, grid_c, mask_c, voxel_mm=settings.exterior_voxel_mm,
                                  iterations=int(plan["exterior_iterations"]), subsets=settings.exterior_subsets)
        except ValueError as e:
            choice = e
        if memo is not None:
            memo["choice"] = choice
    if isinstance(choice, ValueError):
        e = choice
        on = settings.exterior == "on"
        notes.append(f"the object's reach was not stated and could not be guessed ({e}): " + (
            "the exterior model reached up to the sources" if on else
            "the object outside the ROI of this strongly truncated scan was not modelled; state its reach "
            f"({REACH_SETTING})"))
        return settings, on, not on
    notes.append(choice.note())
    say(choice.note())
    return settings.replace(exterior_half_width_mm=choice.reach_mm), True, False


def _level(li, mask, nominal, grid, factor):
    """Data, mask, nominal geometry and grid binned ``factor`` times (the inputs themselves at 1)."""
    if factor <= 1:
        return li, mask, nominal, grid
    li_b, mask_b = bin_masked(li, mask, factor)
    return li_b, mask_b, nominal.binned(factor), grid.binned(factor)


def settings_with(settings: CalibrationSettings | None, changes: dict) -> CalibrationSettings:
    """``settings`` (default: ``CalibrationSettings()``) with field ``changes`` applied."""
    base = CalibrationSettings() if settings is None else settings
    return base.replace(**changes) if changes else base


def calibrate(line_integrals: np.ndarray, nominal: ConeGeometry, grid: VolumeGrid,
              settings: CalibrationSettings | None = None, *, valid_mask=None, drift_times=None,
              gauge_points_mm=None, configs: tuple | None = None, focus_modes: dict | None = None,
              fdk_kwargs: dict | None = None, progress=None, on_iteration=None, final_volume: bool = True,
              **changes) -> CalibrationResult:
    """Correct the per-view geometry of a scan by alternating reconstruction and per-view estimation.

    Parameters
    ----------
    line_integrals : (n, rows, cols) array
        The measured projections as line integrals on ``nominal``'s detector grid.
    nominal : ConeGeometry
        The nominal (robot-reported) geometry of the n views. A one-row detector is a fan beam:
        only the parameters it sees are estimated (:func:`_calibrate_once`).
    grid : VolumeGrid
        The ROI grid the result is reconstructed on.
    settings : CalibrationSettings, optional
        Method, iterations, schedule, prior, ...; ``changes`` (field names) override fields of it.
    valid_mask : (rows, cols) or (n, rows, cols) bool, optional
        Usable pixels (dead pixels and chip gaps False); non-finite data are masked too.
    drift_times : (n,) array, optional
        Acquisition times of the views for ``settings.drift_order`` (default: the view index).
    gauge_points_mm : (m, 3) array, optional
        Points the gauge (global rigid motion) and the magnification are fixed on (default: points
        filling ``grid``).
    configs : (coarse, fine), optional
        Expert override of the method's per-level settings (e.g. an ``LLEConfig`` pair).
    focus_modes : dict, optional
        Conjugate modes set by image sharpness after each iteration
        (:func:`~robot_ct_ros.ct.calibration.constraints.focus_conjugate_modes`); off by default.
    fdk_kwargs : dict, optional
        Options of every FDK (window, cutoff, ...).
    progress : callable, optional
        ``progress(message)``, one line per step.
    on_iteration : callable, optional
        ``on_iteration(record, params)`` after each outer iteration.
    final_volume : bool
        Reconstruct the full-size FDK on ``grid`` with the final geometry (the result's ``volume``);
        False leaves ``volume`` None, for a caller that reconstructs the full-size volume itself
        (bench/bench_fullsize.py: in its own stage, and written slab by slab).

    Returns
    -------
    CalibrationResult
        With ``settings.ensemble`` > 1 and a sampling method, the mean of that many runs with the
        seeds :func:`~robot_ct_ros.ct.calibration.ensemble.member_seeds` and their spread.

    Raises
    ------
    ValueError
        Frame and geometry counts or detector shapes disagree, a setting is invalid, or (with a method that
        estimates) the grid misses the scan's field of view: no voxel of it has complete data, while the scan has
        such voxels elsewhere (:func:`~robot_ct_ros.ct.field_of_view.field_of_view_mask`).
    """
    settings = settings_with(settings, changes)
    method = get_method(settings.method)
    say = progress or (lambda message: None)
    accuracy = settings.prior_sigma  # the robots' stated accuracy: the guard's reference, prior or not
    # once per calibration, before any executor or ensemble member starts
    if method.estimate is not None and not field_of_view_mask(nominal, grid).any():
        # the grid misses a field of view the scan has elsewhere
        raise ValueError(f"{field_of_view_extent(nominal).misses_note(grid)}; the calibration has no object to "
                         "register the views against there and stops")
    if not method.uses_prior and accuracy is not None and method.estimate is not None:
        # the settings keep the stated accuracy (the guard reads it), so that the result's settings repeat the run
        say(f"{method.name} has no prior: the robots' error (prior_sigma) serves the guard only")
    with executor_for(settings) as executor:  # in-process, or Dask tasks (settings.scheduler)
        if settings.scheduler:
            say(f"estimation and FDK run on {executor.description}")
        kw = dict(valid_mask=valid_mask, drift_times=drift_times, gauge_points_mm=gauge_points_mm, configs=configs,
                  focus_modes=focus_modes, fdk_kwargs=fdk_kwargs, progress=progress, on_iteration=on_iteration,
                  accuracy=accuracy, executor=executor, final_volume=final_volume)
        if settings.ensemble <= 1 or not method.samples or configs is not None:
            result = _calibrate_once(line_integrals, nominal, grid, settings, **kw)
        else:
            runs = []
            # the reach guess (nominal geometry, no sampling) is the same for every member; only the mean's volume
            kw |= dict(reach_memo={}, final_volume=False)
            for k, seed in enumerate(member_seeds(settings.seed, settings.ensemble)):
                say(f"ensemble member {k + 1}/{settings.ensemble} (sampling seed {seed})")
                runs.append(_calibrate_once(line_integrals, nominal, grid, settings.replace(seed=seed), **kw))
            result = average_estimates(runs, line_integrals, nominal, grid, valid_mask=valid_mask,
                                       points_mm=gauge_points_mm, fdk_kwargs=fdk_kwargs, fdk=executor.fdk,
                                       final_volume=final_volume)
            say(f"ensemble of {settings.ensemble}: the members lie {result.spread_px:.3f} px from their mean")
    unused = _unused_settings(method, settings)
    return replace(result, notes=result.notes + (unused,)) if unused else result


def _in_nominal_gauge(params, nominal: ConeGeometry, points, held) -> np.ndarray:
    """``params`` aligned to the nominal geometry (:func:`remove_gauge`) with its magnification held
    (:func:`hold_magnification`), and the parameters a fan beam cannot see (``held``) at 0."""
    params = remove_gauge(nominal.perturbed(params), nominal, points).params_relative_to(nominal)
    params = hold_magnification(nominal, params, points)
    params[:, held] = 0.0  # a fan beam: the gauge fit must not move what the data cannot see
    return params


def _unused_settings(method, settings) -> str:
    """The note for settings that ``method`` or the other settings leave unused (given, yet the result would be the
    same without them); empty when there are none."""
    if method.estimate is None:
        given = [f"{name} {value}" for name, value, off in (("ensemble", settings.ensemble, 1),
                                                              ("drift_order", settings.drift_order, None))
                 if value != off]
        return (f"no correction ({method.name}): {', '.join(given)} did not apply" if given else "")
    notes = []
    defaults = CalibrationSettings()

    def changed(names):
        return [f"{n} {getattr(settings, n)}" for n in names if getattr(settings, n) != getattr(defaults, n)]

    if settings.ensemble > 1 and not method.samples:
        notes.append(f"ensemble {settings.ensemble} did not apply: {method.name} draws no samples, so its runs would "
                     "be identical (one run)")
    if not method.samples and (given := changed(["seed"])):
        notes.append(f"{given[0]} did not apply: {method.name} draws no samples (it is deterministic)")
    if not method.uses_prior and settings.prior_sigma is not None and (
            given := changed(["prior_translation_mm", "prior_rotation_deg", "prior_source_mm", "prior_detector_mm"])):
        notes.append(f"{', '.join(given)} did not apply to the estimate: {method.name} has no prior (the robots' "
                     "stated accuracy served the guard only)")
    if settings.projections == "complete" and (given := changed(["sirt_iterations"])):
        notes.append(f"{given[0]} did not apply: projections complete (the volumes are FDK's)")

    if given := changed([n for n in ("lle_neighbours", "lle_ridge") if n not in method.lle_settings]):
        notes.append(f"{', '.join(given)} did not apply: {method.name} " + (
            f"reads only {', '.join(method.lle_settings)} of the embedding's settings" if method.lle_settings
            else "embeds no samples"))
    if settings.prior_sigma is None and (given := changed(["prior_source_mm", "prior_detector_mm"])):
        notes.append(f"{', '.join(given)} did not apply: the prior is off (prior_translation_mm or "
                     "prior_rotation_deg 0)")
    # (not exterior_iterations: a schedule field, which a result's settings record resolved)
    # a floor is looser when lower, a ratio limit when higher
    looser = [f"{name} {getattr(settings, name)} (looser than {general} {getattr(settings, general)})"
              for name, general, sign in (("guard_min_ncc_unmodelled", "guard_min_ncc", 1),
                                          ("guard_min_ncc_exterior", "guard_min_ncc", 1),
                                          ("guard_max_ratio_unmodelled", "guard_max_ratio", -1))
              if sign * (getattr(settings, general) - getattr(settings, name)) > 0]
    if settings.guard and looser:
        notes.append(f"{', '.join(looser)} did not apply: the guard takes the stricter of the two")
    if settings.exterior == "off" and (given := changed(["exterior_voxel_mm", "exterior_half_width_mm",
                                                          "exterior_subsets", "exterior_reach_guess"])):
        notes.append(f"{', '.join(given)} did not apply: exterior is off")
    return "; ".join(notes)


def _ncc_gain_note(iteration: int, before: float, after: float, threshold: float) -> str:
    """The note on an iteration that ``stop_ncc_gain`` undid: the estimation model's projection NCC went from
    ``before`` to ``after``, which rose by less than ``threshold`` or fell."""
    gain = after - before
    change = (f"raised the estimation model's projection NCC by {gain:.2e} only" if gain > 0 else
              "left the estimation model's projection NCC unchanged" if gain == 0 else
              f"lowered the estimation model's projection NCC by {-gain:.2e}")
    return (f"stop_ncc_gain: iteration {iteration} {change} ({before:.5f} -> {after:.5f}; stop_ncc_gain asks a rise "
            f"of {threshold:g} at least) and was undone; the geometry of iteration {iteration - 1} stays")


def fan_beam_note(nominal: ConeGeometry) -> str:
    """The note for a one-row detector (a fan beam, docs/calibration.md §5b): which parameters the calibration
    estimates, which stay nominal and why; empty for a detector of two or more rows."""
    held = ~observable_params(nominal)
    if not held.any():
        return ""
    free = [n for n, h in zip(PARAM_NAMES, held) if not h]
    kept = [n for n, h in zip(PARAM_NAMES, held) if h]
    return (f"one-row detector (fan beam): only the {len(free)} parameters that move its rays within the fan plane "
            f"were estimated ({', '.join(free)}: the source's in-plane position, the detector's shift along the row "
            f"and distance, its rotation within the plane); {', '.join(kept)} stay nominal: s_v, d_v and r_w move the "
            "rays off the one slice the row sees, which a one-row scan cannot tell from the object changing along the "
            "axis, and r_u turns the detector about its own row, moving none of its pixels (docs/calibration.md §5b)")


def _skipped_view_notes(skipped: dict, estimated: dict, n_views: int) -> list:
    """The notes on views that saw too little of the grid, from the views each level's estimates skipped and
    estimated over the whole run (``{"coarse": set, "fine": set}`` each): those no estimate took kept their
    geometry; those one level never took and the other did were estimated on that other level only (a binned
    level may keep no pixel of a thin detector's rays). A view a level skipped once and took in another
    iteration is no news."""
    def listed(views):
        return f"{views[:20]}{' ...' if len(views) > 20 else ''}"

    notes = []
    never = sorted(set(range(n_views)) - estimated["coarse"] - estimated["fine"])
    if never:
        notes.append(f"{len(never)} view(s) saw too little of the grid to be estimated and kept their geometry, "
                     "moved only with the whole scan by the gauge fix (its common rigid motion and magnification): "
                     + listed(never))
    for level, other in (("coarse", "fine"), ("fine", "coarse")):
        partly = sorted((skipped[level] - estimated[level]) & estimated[other])
        if partly:
            notes.append(f"{len(partly)} view(s) saw too little of the grid on the {level} level to be estimated "
                         f"there and were estimated on the {other} level only: " + listed(partly))
    return notes


@blas_single_threaded
def _calibrate_once(line_integrals, nominal: ConeGeometry, grid: VolumeGrid, settings: CalibrationSettings, *,
                    valid_mask, drift_times, gauge_points_mm, configs, focus_modes, fdk_kwargs, progress,
                    on_iteration, accuracy, executor=None, final_volume=True,
                    reach_memo: dict | None = None) -> CalibrationResult:
    """One run of the loop (the body of :func:`calibrate`).

    Each outer iteration reconstructs with the current geometry (FDK, then SIRT on a truncated
    scan, on the ROI grid widened ``padding`` times across:
    :func:`~robot_ct_ros.ct.calibration.volume.reconstruct_for_estimation`) and re-estimates every
    view, first on coarsely binned projections, then on finer ones (the schedule). In the first
    iteration the coarse level alternates by itself up to ``coarse_passes`` times, until a pass
    moves the views less than ``coarse_tol_px``. The gauge (a global rigid motion) is then
    removed by aligning the estimate to the nominal geometry on the gauge points, the common
    magnification held at the nominal one, and optionally the drift model and the conjugate
    modes applied. The loop stops after ``iterations`` or after an iteration that moved the
    views less than ``stop_update_px``; with ``undo_inconsistent`` an iteration that lowers the
    data consistency is undone and ends it, and with ``stop_ncc_gain`` one (from the second on)
    that raises the estimation model's projection NCC by less than that. The returned volume is
    the full-size FDK with the final geometry (None with ``final_volume`` False).

    A one-row detector (fan beam) is calibrated as such: every level keeps one row
    (:meth:`~robot_ct_ros.ct.geometry.ConeGeometry.binned`), the grid may be one slice thick,
    and only the parameters a fan beam sees are estimated (in-plane source position, detector
    shift along the row, magnification, rotation within the fan plane:
    :data:`~robot_ct_ros.ct.geometry.FAN_BEAM_PARAMS`); the other four stay at their nominal
    values, which is also what the prior says of them.

    ``executor`` runs the per-view estimation and the FDKs: in-process by default, or as Dask tasks
    (:mod:`robot_ct_ros.ct.calibration.distributed`), with the same result.
    """
    executor = executor or InProcess()
    fdk = executor.fdk

    method = get_method(settings.method)
    drift_order, undo_inconsistent = settings.drift_order, settings.undo_inconsistent
    if drift_order is not None:
        fit_drift(np.zeros((nominal.n_views, 9)), drift_order, drift_times)  # validates order and times
    t_start = time.perf_counter()
    if nominal.n_views == 0:
        raise ValueError("calibration needs at least one view, got none")
    if nominal.n_cols < 2:  # a column alone shows no shift along the row: nothing to register
        raise ValueError(f"calibration needs a detector at least 2 columns wide, got {nominal.n_rows} x {nominal.n_cols}")
    shape, want = np.shape(line_integrals), (nominal.n_views,) + nominal.det_shape
    if shape != want:  # say which of the three differs
        if len(shape) != 3:
            raise ValueError(f"line integrals must have shape {want} (views, rows, columns), got {shape}")
        if shape[0] != want[0]:
            raise ValueError(f"{shape[0]} frames but {want[0]} views in the geometry")
        raise ValueError(f"the detector shapes differ: frames of {shape[1]} x {shape[2]} pixels, the geometry's "
                         f"detector {want[1]} x {want[2]} (rows x columns)")
    li, mask = usable_data(line_integrals, valid_mask)
    say = progress or (lambda message: None)
    if method.estimate is None:  # no correction: the nominal geometry
        volume = fdk(li, nominal, grid, valid_mask=mask, **(fdk_kwargs or {})) if final_volume else None
        return CalibrationResult(method.name, np.zeros((nominal.n_views, 9)), nominal, volume, (),
                                 time.perf_counter() - t_start, settings=settings.resolved())
    # the estimation's grid: the ROI grid, its axes renamed so that z runs along the scan axis (it is widened across
    # x and y); the final volume is reconstructed on the user's grid, and the gauge is fixed on its points
    est_grid = axis_last(grid, nominal)
    # how much object the detector's edges see: decides the volumes (projections auto) and the exterior model
    level = (truncation_level(li, mask, geom=nominal)
             if settings.projections == "auto" or settings.exterior != "on" else None)
    truncated = settings.projections == "truncated"
    if settings.projections == "auto":
        truncated = level > TRUNCATED_ABOVE
        say(f"truncation level {level:.4f}: {'truncated, FDK + SIRT' if truncated else 'not truncated, FDK'} volumes")
    sirt_iterations = settings.sirt_iterations if truncated else 0  # else every volume is an FDK
    fdk_kwargs = dict(fdk_kwargs or {})
    exterior = settings.exterior == "on"
    reach_stated = settings.exterior_half_width_mm > 0
    guess_reach = not reach_stated and settings.exterior_reach_guess  # chosen by held-out prediction, below
    exterior_notes = []
    if exterior and not reach_stated and not guess_reach:
        exterior_notes.append(f"the exterior model reached up to the sources: the object's reach "
                              f"({REACH_SETTING}) was not stated, and reaching past the object costs accuracy")
    unmodelled = False  # strongly truncated, the object outside the ROI not modelled: the guard is stricter
    if settings.exterior != "on":
        # auto models the object outside the ROI on a strongly truncated scan, with its reach stated or guessed: one
        # reaching far past the object does worse than none (docs/calibration.md, "The exterior model")
        strong = level > EXTERIOR_ABOVE
        exterior = settings.exterior == "auto" and strong and (reach_stated or guess_reach)
        unmodelled = strong and not exterior
        if unmodelled:
            exterior_notes.append(f"strongly truncated (truncation level {level:.3f} > {EXTERIOR_ABOVE:g}), " + (
                "and the object outside the ROI was not modelled (exterior off)" if settings.exterior == "off" else
                "yet the object outside the ROI was not modelled: state how far the object reaches from the ROI "
                f"centre ({REACH_SETTING}), or let it be guessed (exterior_reach_guess)"))
        if settings.exterior == "auto":
            say(f"truncation level {level:.3f}: {'the object outside the ROI is modelled' if exterior else 'ROI model'}")
    if exterior and guess_reach:
        settings, exterior, unmodelled = _guess_reach(li, mask, nominal, est_grid, settings, exterior_notes, say,
                                                      memo=reach_memo)
    reach_mm = settings.exterior_half_width_mm
    # the schedule (auto: exterior with the exterior model, else accurate) and the fields it sets; the result records them
    settings = settings.resolved(exterior)
    if exterior and settings.schedule == "exterior":
        say(f"schedule exterior: {settings.iterations} iteration(s) at most, stop_ncc_gain {settings.stop_ncc_gain:g}, "
            f"{settings.exterior_iterations} SIRT passes of the ROI and exterior model")
    plan = settings.plan()
    coarse_binning, fine_binning = int(plan["coarse_binning"]), int(plan["fine_binning"])
    fine_volume, coarse_passes = plan["fine_volume"], int(plan["coarse_passes"])
    n_iter, stop_update_px, coarse_tol_px = settings.iterations, settings.stop_update_px, settings.coarse_tol_px
    estimate, narrowed = method.estimate, method.narrow
    coarse_cfg, fine_cfg = configs if configs is not None else method.configs(settings)
    if exterior:  # every ray is modelled: no ROI support mask
        coarse_cfg, fine_cfg = (replace(c, roi_support_fraction=None) for c in (coarse_cfg, fine_cfg))

    def rebuild(li_l, geom_l, grid_l, mask_l, sirt_n, inner, support, correction=None, measure_fdk=True):
        """The volume a level registers against: the ROI with the exterior, or FDK (+ SIRT) of the ROI."""
        if exterior:
            parts = reconstruct_with_exterior(li_l, geom_l, grid_l, mask_l, voxel_mm=settings.exterior_voxel_mm,
                                              half_width_mm=reach_mm,
                                              iterations=settings.exterior_iterations,
                                              subsets=settings.exterior_subsets)
            return EstimationVolume(parts, float("nan"), None)
        return reconstruct_for_estimation(li_l, geom_l, grid_l, mask_l, sirt_n, fdk_kwargs, inner, correction=correction,
                                          measure_fdk=measure_fdk, fdk=fdk, support=support)

    points = roi_points(grid) if gauge_points_mm is None else np.asarray(gauge_points_mm, float)
    grid_e = estimation_grid(est_grid, settings.padding)
    has_coarse = coarse_binning > fine_binning
    li_f, mask_f, nom_f, grid_f = _level(li, mask, nominal, grid_e, fine_binning)
    inner_f = est_grid.binned(fine_binning).shape_zyx[1:]
    # FDK's field of view on each level, from the nominal geometry (the corrections move it by far less than a voxel):
    # auto where the detector's edges see air, so the object lies inside it (docs/calibration.md §6)
    fov = not exterior and (settings.fov_support == "on" or (settings.fov_support == "auto" and level is not None
                                                            and level <= TRUNCATED_ABOVE))
    fov_f = field_of_view_mask(nom_f, grid_f) if fov else None
    if fov:
        say(f"field of view: the estimation volumes' FDK is zero in the {1 - fov_f.mean():.0%} of the grid outside it")
    if has_coarse:
        li_c, mask_c, nom_c, grid_c = _level(li, mask, nominal, grid_e, coarse_binning)
        inner_c = est_grid.binned(coarse_binning).shape_zyx[1:]
        fov_c = field_of_view_mask(nom_c, grid_c) if fov else None
    else:  # one level: it also runs the data consistency check (undo_inconsistent)
        li_c, mask_c, nom_c, grid_c, inner_c, fov_c = li_f, mask_f, nom_f, grid_f, inner_f, fov_f
        if fine_volume == "fdk+coarse-sirt":  # no coarse level to take the correction from
            fine_volume = "sirt"
    params = np.zeros((nominal.n_views, 9))
    held = ~observable_params(nominal)
    history = []
    undone_note = None  # set when undo_inconsistent undoes an iteration: the result must say so
    still_note = None  # set when the first iteration already moves the views less than stop_update_px
    # per level: the views an estimate of that level skipped (they saw too little of the grid) and those it estimated
    skipped = {"coarse": set(), "fine": set()}
    estimated = {"coarse": set(), "fine": set()}
    all_views = set(range(nominal.n_views))
    # the coarse level's reconstruction with the geometry entering each iteration: its volume
    # for the coarse estimate, its FDK's NCC for undo_inconsistent, its SIRT correction for a
    # fine level without SIRT
    rec_c = rebuild(li_c, nom_c, grid_c, mask_c, sirt_iterations, inner_c, fov_c)
    # undo_inconsistent compares FDK volumes, which the exterior model does not build
    check_consistency = undo_inconsistent and not exterior
    for it in range(n_iter):
        t0 = time.perf_counter()
        start = params.copy()
        rec_in = rec_c  # the consistency of the geometry entering the iteration (undo_inconsistent)
        n_passes = (coarse_passes if it == 0 else 1) if has_coarse else 0
        for rep in range(n_passes):
            if rep:  # a warm-up pass: the coarse volume again, with the geometry of the last pass
                rec_c = rebuild(li_c, nom_c.perturbed(params), grid_c, mask_c, sirt_iterations, inner_c, fov_c)
            before = params
            cfg = narrowed(coarse_cfg, it)
            if rep:
                cfg = method.fresh_samples(cfg, rep)
            params, coarse_info = executor.estimate(estimate, li_c, nom_c, params, rec_c.volume, grid_c, cfg, mask_c)
            skipped["coarse"].update(coarse_info.get("skipped_views", ()))
            estimated["coarse"].update(all_views - set(coarse_info.get("skipped_views", ())))
            moved = moved_px(nom_c, params, before, points)
            say(f"iteration {it + 1}/{n_iter}: coarse estimate {rep + 1} done, views moved {moved:.3f} coarse px "
                f"({time.perf_counter() - t0:.1f} s)")
            if moved < coarse_tol_px:
                break
        correction = (rec_c.volume - rec_c.fdk, grid_c) if fine_volume == "fdk+coarse-sirt" and not exterior else None
        vol = rebuild(li_f, nom_f.perturbed(params), grid_f, mask_f, sirt_iterations if fine_volume == "sirt" else 0,
                      inner_f, fov_f, correction=correction, measure_fdk=False).volume
        params, fine_info = executor.estimate(estimate, li_f, nom_f, params, vol, grid_f, narrowed(fine_cfg, it), mask_f)
        skipped["fine"].update(fine_info.get("skipped_views", ()))
        estimated["fine"].update(all_views - set(fine_info.get("skipped_views", ())))
        params = _in_nominal_gauge(params, nominal, points, held)
        if drift_order is not None:
            # the polynomial fit puts part of a gauge motion back (a linear drift: 0.09 mm) and the gauge fix takes
            # the parameters off their polynomials a little: alternate until both hold
            for _ in range(100):  # alternating projections: a few rounds to 1e-9 mm, a slow (linear) case to 1e-6 mm
                fitted = fit_drift(params, drift_order, drift_times)
                params = _in_nominal_gauge(fitted, nominal, points, held)
                if np.abs(params - fitted).max() < 1e-9:
                    break
        if focus_modes:
            params, focus = focus_conjugate_modes(li, nominal, params, est_grid, mask, modes=focus_modes,
                                                  fdk_kwargs=fdk_kwargs)
            say(f"iteration {it + 1}/{n_iter}: sharpness focus of {len(focus['modes'])} conjugate modes, entropy "
                f"{focus['entropy_before']:.6f} -> {focus['entropy_after']:.6f}")
        moved = moved_px(nominal, params, start, points)
        last = it + 1 == n_iter or moved < stop_update_px
        rmse, corr = projection_consistency(vol, grid_f, nom_f.perturbed(params), li_f, mask_f)
        gain = corr - history[-1].projection_ncc if history else float("inf")
        if settings.stop_ncc_gain > 0 and gain < settings.stop_ncc_gain:
            # the model explains the data hardly better than before: the iteration moved the views along
            # geometries the data cannot tell apart (docs/calibration.md §7). Checked before the next coarse
            # volume is built, which an undone iteration would not use
            undone_note = _ncc_gain_note(it + 1, history[-1].projection_ncc, corr, settings.stop_ncc_gain)
            say(f"iteration {it + 1}/{n_iter}: the model's projection NCC changed by {gain:+.2e} "
                f"({history[-1].projection_ncc:.5f} -> {corr:.5f}), less than stop_ncc_gain "
                f"{settings.stop_ncc_gain:g}; undone, stopping")
            params = start
            break
        # the next iteration's coarse volume (and the consistency check): not after the last
        rec_next = (rebuild(li_c, nom_c.perturbed(params), grid_c, mask_c, sirt_iterations, inner_c, fov_c)
                    if check_consistency or not last else None)
        step = params - start
        fractions = fine_info.get("independent_fraction") or [float("nan")]
        rec = IterationRecord(it + 1, rmse, corr, float(np.sqrt((step[:, :6] ** 2).mean())),
                              float(np.rad2deg(np.sqrt((step[:, 6:] ** 2).mean()))), time.perf_counter() - t0,
                              fractions[-1], moved)
        if check_consistency and not rec_next.fdk_ncc > rec_in.fdk_ncc:
            say(f"iteration {it + 1}/{n_iter}: data consistency fell ({rec_in.fdk_ncc:.5f} -> {rec_next.fdk_ncc:.5f}); "
                f"undone, stopping")
            undone_note = (f"undo_inconsistent: iteration {it + 1} lowered the FDK's data consistency (reprojection "
                           f"NCC {rec_in.fdk_ncc:.5f} -> {rec_next.fdk_ncc:.5f}) and was undone; "
                           + (f"the geometry of iteration {it} stays" if it else "no correction was made"))
            params = start
            break
        rec_c = rec_next
        history.append(rec)
        if on_iteration is not None:
            on_iteration(rec, params.copy())
        say(f"iteration {rec.iteration}/{n_iter}: projection RMSE {rec.projection_rmse:.4g}, NCC "
            f"{rec.projection_ncc:.5f}, update {rec.update_rms_mm:.3f} mm / {rec.update_rms_deg:.3f} deg, "
            + ("" if np.isnan(rec.independent_fraction) else f"independent pixels {rec.independent_fraction:.3f}, ")
            + f"views moved {rec.update_px:.3f} px, {rec.wall_s:.1f} s")
        if last and it + 1 < n_iter:
            if rec.iteration == 1:  # nothing found is not convergence: say so, here and in the result
                still_note = (f"the first iteration moved the views by {rec.update_px:.3f} px, less than "
                              f"stop_update_px ({stop_update_px:g} px)" + (
                                  ": the data found next to nothing to correct, so the geometry stays close to where "
                                  "it started" if rec.update_px < CalibrationSettings().stop_update_px else
                                  ", so no further iteration ran"))
                say(f"stopping after the first of {n_iter} iterations: {still_note}")
            else:
                say(f"converged: the views moved less than {stop_update_px:g} px; stopping after {rec.iteration} "
                    f"of {n_iter} iterations")
            break
    notes = _skipped_view_notes(skipped, estimated, nominal.n_views)
    if held.any():  # a fan beam: what was estimated, what stays nominal
        notes.insert(0, fan_beam_note(nominal))
    if exterior:
        notes.append("the object outside the ROI was modelled (exterior model)")
    notes += exterior_notes
    if undone_note:
        notes.append(undone_note)
    if still_note:
        notes.append(still_note)
    if drift_order is not None:
        n_views = nominal.n_views
        notes.append(f"drift model: each parameter a polynomial of degree {drift_order} in time over the scan "
                     f"({drift_order + 1} coefficients for {n_views} views)"
                     + ("; so many that it is hardly a constraint (per-view estimates are as free)"
                        if drift_order + 1 > n_views // 2 else ""))
    unguarded = None
    explained = history[-1].projection_ncc if history else float("nan")
    # a strongly truncated scan needs a model that explains more, with the exterior modelled or not
    # (docs/calibration.md §11)
    # each the stricter of the general limit and the scan's own (a looser one is named in the notes)
    min_ncc = settings.guard_min_ncc
    if unmodelled:
        min_ncc = max(min_ncc, settings.guard_min_ncc_unmodelled)
    elif exterior:
        min_ncc = max(min_ncc, settings.guard_min_ncc_exterior)
    if settings.guard and explained < min_ncc:
        # the data term is dominated by what the model lacks (the object outside the ROI): its optimum is not the
        # geometry's, and no consistency figure can vouch for it
        unguarded, params = params, np.zeros_like(params)
        hint = ("the exterior model does not explain this scan well enough; where the object's reach was guessed, "
                f"state it: {REACH_SETTING}" if exterior else
                "for an interior scan of a wide object, state how far it reaches from the ROI centre: "
                f"{REACH_SETTING}")
        notes.append(f"guard: the estimation model explains the data poorly (projection NCC {explained:.3f} < "
                     f"{min_ncc:g}); the data do not support the correction and the nominal geometry is "
                     f"kept ({hint})")
    elif settings.guard and accuracy is not None:
        # where the ROI model's data term is biased (strong truncation, no exterior) the correction may not move the
        # views further than the robots' errors do: its helpful corrections there are partial (docs/calibration.md §11)
        scan_limit = min(settings.guard_max_ratio, settings.guard_max_ratio_unmodelled) if unmodelled \
            else settings.guard_max_ratio
        checked = plausibility_guard(nominal, params, points, accuracy, max_ratio=settings.guard_max_ratio,
                                     view_quantile=settings.guard_view_quantile, seed=settings.seed,
                                     scan_max_ratio=scan_limit)
        unguarded = params if checked.reverted_views else None
        params = checked.params
        notes.append(checked.note(scan_limit))
    elif settings.guard:
        notes.append("guard: no robot accuracy stated (prior 0), so only the model's explanation of the data is checked")
    for note in notes:
        say(note)
    geom = nominal.perturbed(params)
    volume = fdk(li, geom, grid, valid_mask=mask, **fdk_kwargs) if final_volume else None
    notes = tuple(notes)
    return CalibrationResult(method.name, params, geom, volume, tuple(history), time.perf_counter() - t_start,
                             settings=settings, notes=notes, params_unguarded=unguarded)
