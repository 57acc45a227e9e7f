"""Ensembles: several calibrations of one scan with different sampling seeds, averaged."""

from __future__ import annotations

import time

import numpy as np

from robot_ct_ros.ct.calibration.constraints import moved_px
from robot_ct_ros.ct.calibration.masks import usable_data
from robot_ct_ros.ct.calibration.result import CalibrationResult
from robot_ct_ros.ct.geometry import ConeGeometry, VolumeGrid
from robot_ct_ros.ct.metrics import roi_points

__all__ = ["average_estimates", "ENSEMBLE_SEED_STEP", "member_notes", "member_seeds"]


ENSEMBLE_SEED_STEP = 1000
"""Sampling seeds of an ensemble's members: seed, seed + 1000, seed + 2000, ... (each run's
levels use its seed and seed + 1)."""


def member_seeds(seed: int, members: int) -> list[int]:
    """The sampling seeds of an ensemble of ``members`` runs started at ``seed``."""
    return [int(seed) + k * ENSEMBLE_SEED_STEP for k in range(int(members))]


def average_estimates(results, line_integrals, nominal: ConeGeometry, grid: VolumeGrid, *, valid_mask=None,
                      points_mm=None, fdk_kwargs: dict | None = None, fdk=None,
                      final_volume: bool = True) -> CalibrationResult:
    """One estimate from several :class:`CalibrationResult` of the same scan (runs of
    :func:`~robot_ct_ros.ct.calibration.loop.calibrate` with different sampling seeds): the
    mean of their parameters, reconstructed (FDK: ``fdk``, default
    :func:`~robot_ct_ros.ct.reconstruction.fdk`, e.g. an executor's; none with ``final_volume``
    False, the result's ``volume`` None).

    Each run's parameters are already in the nominal geometry's gauge (:func:`calibrate` removes
    the global rigid motion and holds the magnification), so they average directly. What the
    runs disagree on is the LLE's sampling noise, which the mean reduces; what they share, the
    bias of the data and of the volume, it keeps. ``spread_px`` of the result is the mean
    gauge-aligned displacement of the ROI points (``points_mm``, default those of ``grid``)
    between each run and the mean: the sampling's share of the error, a measure of the
    estimate's precision that needs no ground truth.

    The result keeps what the runs said (:func:`member_notes`: the truncation, the exterior
    model, each run's guard verdict) and, where the guard changed any run, ``params_unguarded``:
    the mean of the runs' estimates before their guards.
    """
    if fdk is None:
        from robot_ct_ros.ct.reconstruction import fdk

    results = list(results)
    if not results:
        raise ValueError("no estimates to average")
    if any(r.params.shape != (nominal.n_views, 9) for r in results):
        raise ValueError(f"every estimate needs ({nominal.n_views}, 9) parameters")
    t0 = time.perf_counter()
    params = np.mean([r.params for r in results], axis=0)
    points = roi_points(grid) if points_mm is None else np.asarray(points_mm, float)
    spread = (float(np.mean([moved_px(nominal, r.params, params, points) for r in results]))
              if len(results) > 1 else float("nan"))
    geom = nominal.perturbed(params)
    volume = None
    if final_volume:
        li, mask = usable_data(line_integrals, valid_mask)  # as calibrate's final FDK
        volume = fdk(li, geom, grid, valid_mask=mask, **(fdk_kwargs or {}))
    wall = sum(r.wall_s for r in results) + time.perf_counter() - t0
    first = results[0]
    settings = first.settings.replace(ensemble=len(results)) if first.settings is not None else None
    unguarded = None
    if any(r.params_unguarded is not None for r in results):
        unguarded = np.mean([r.params if r.params_unguarded is None else r.params_unguarded for r in results], axis=0)
    notes = member_notes(results)
    if len(results) > 1:
        notes += (f"ensemble of {len(results)}: the mean of the runs' geometries; they lie {spread:.3f} px from it",)
    return CalibrationResult(first.method, params, geom, volume, first.history, wall,
                             members=sum(r.members for r in results), spread_px=spread, settings=settings,
                             notes=notes, params_unguarded=unguarded)


def member_notes(results) -> tuple:
    """The notes of several runs as one list, in the order they first appear: a note every run made
    once; one that only some runs made (a guard's verdict with its own figures), prefixed with the runs
    (counted from 1) that made it."""
    results = list(results)
    order, made_by = [], {}
    for k, r in enumerate(results, start=1):
        for note in r.notes:
            if note not in made_by:
                order.append(note)
                made_by[note] = []
            made_by[note].append(k)
    if len(results) == 1:
        return tuple(order)
    every = list(range(1, len(results) + 1))
    return tuple(note if made_by[note] == every
                 else f"run{'s' if len(made_by[note]) > 1 else ''} {', '.join(map(str, made_by[note]))}: {note}"
                 for note in order)
