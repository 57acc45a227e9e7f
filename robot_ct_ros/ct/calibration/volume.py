"""The estimation volume: what the views are registered against, and how truncated the scan is."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from robot_ct_ros.ct.calibration.masks import as_view_mask
from robot_ct_ros.ct.calibration.model import project
from robot_ct_ros.ct.geometry import ConeGeometry, VolumeGrid
from robot_ct_ros.ct.metrics import ncc

__all__ = ["EstimationVolume", "reconstruct_for_estimation", "projection_consistency", "estimation_grid", "axis_last",
           "truncation_level", "TRUNCATED_ABOVE", "EXTERIOR_ABOVE"]


def projection_consistency(volume, grid, geom, measured, mask) -> tuple[float, float]:
    """Masked RMSE and mean NCC between the reprojection of ``volume`` and ``measured``."""
    pred = project(volume, grid, geom)
    mk = as_view_mask(mask, measured.shape) & np.isfinite(measured)
    diff = np.where(mk, pred - measured, 0.0)
    rmse = float(np.sqrt((diff.astype(np.float64) ** 2).sum() / max(mk.sum(), 1)))
    return rmse, float(ncc(pred.reshape(len(pred), -1), measured.reshape(len(pred), -1),
                           mk.reshape(len(pred), -1)).mean())


class EstimationVolume(NamedTuple):
    volume: np.ndarray    # the volume to register the views against
    fdk_ncc: float        # masked NCC of the FDK's reprojection to the data
    fdk: np.ndarray       # the FDK it started from (zero outside ``fdk_shape_yx``)


def reconstruct_for_estimation(line_integrals, geom, grid, mask, sirt_iterations: int, fdk_kwargs=None,
                               fdk_shape_yx=None, correction=None, measure_fdk: bool = True,
                               fdk=None, support=None) -> EstimationVolume:
    """The volume the views are registered against: FDK, then ``sirt_iterations`` of masked SIRT.

    FDK of a truncated scan does not reproject to its own data (the extrapolated rows leave
    low-frequency errors, and what lies outside the grid is missing), and no background
    model absorbs all of that. A few SIRT iterations started from FDK make the volume
    consistent with the measured rays (docs/calibration.md, "The estimation volume and
    truncation"). Where the object reaches far
    beyond the grid, SIRT piles the missing mass into the border voxels instead; the SIRT
    volume is kept only where it reprojects closer (masked NCC) to the data than the FDK.
    ``fdk_shape_yx`` keeps the FDK to that central part of the grid (zero around it): outside
    the field of view FDK has incomplete data and only SIRT may fill the padding
    (:func:`estimation_grid`). ``correction`` = (volume - fdk of a coarser reconstruction,
    its grid) replaces the SIRT iterations: the difference, resampled onto ``grid``, is added
    to this FDK (the coarse level's SIRT, for the low frequencies and the rim, at a fraction of
    the cost of fine SIRT; on the 360-view scan of :data:`SCHEDULES` it registered the views
    worse than the FDK alone). Returns an :class:`EstimationVolume`; its ``fdk_ncc`` measures how
    consistent the geometry is, which SIRT cannot inflate by fitting an underdetermined
    (few-view) problem. It costs a reprojection: without SIRT and with ``measure_fdk`` False it
    is skipped (NaN). ``fdk`` is the FDK to run (default :func:`~robot_ct_ros.ct.reconstruction.fdk`;
    the loop passes its executor's, :mod:`robot_ct_ros.ct.calibration.distributed`). ``support``
    (bool, ``grid.shape_zyx``; :func:`~robot_ct_ros.ct.field_of_view.field_of_view_mask`) keeps
    the FDK to the voxels it reconstructs from complete data; SIRT may fill the rest.
    """
    from robot_ct_ros.ct.iterative import sirt
    from robot_ct_ros.ct.reconstruction import fdk as fdk_in_process, resample

    fdk = fdk or fdk_in_process
    vol = fdk(line_integrals, geom, grid, valid_mask=mask, **(fdk_kwargs or {}))
    if fdk_shape_yx is not None:
        _, ny, nx = grid.shape_zyx
        y0, x0 = (ny - fdk_shape_yx[0]) // 2, (nx - fdk_shape_yx[1]) // 2
        inner = np.zeros_like(vol)
        inner[:, y0:y0 + fdk_shape_yx[0], x0:x0 + fdk_shape_yx[1]] = vol[:, y0:y0 + fdk_shape_yx[0], x0:x0 + fdk_shape_yx[1]]
        vol = inner
    if support is not None:
        vol = np.where(support, vol, np.float32(0.0))
    if correction is not None:
        delta, delta_grid = correction
        return EstimationVolume(vol + resample(delta, delta_grid, grid), float("nan"), vol)
    if sirt_iterations <= 0 and not measure_fdk:
        return EstimationVolume(vol, float("nan"), vol)
    corr_fdk = projection_consistency(vol, grid, geom, line_integrals, mask)[1]
    out = vol
    if sirt_iterations > 0:
        refined = sirt(line_integrals, geom, grid, sirt_iterations, x0=vol, valid_mask=mask)
        if projection_consistency(refined, grid, geom, line_integrals, mask)[1] > corr_fdk:
            out = refined
    return EstimationVolume(out, corr_fdk, vol)


TRUNCATED_ABOVE = 0.01
""":func:`truncation_level` above which :func:`calibrate` treats a scan as truncated."""

EXTERIOR_ABOVE = 0.3
""":func:`truncation_level` above which ``exterior="auto"`` models the object outside the ROI
(docs/calibration.md, "The exterior model")."""


def truncation_level(line_integrals: np.ndarray, valid_mask=None, edge_px: int = 2, geom=None) -> float:
    """How much object the left and right detector edges see: the median over views of the mean
    line integral in the ``edge_px`` outermost columns on each side (valid pixels only),
    relative to the 99.9th percentile of all data. About 0 when the object fits in the field of
    view (noise averages out; never below 0), a few per cent and more for an interior scan. The edges are those
    across the scan axis: with ``geom`` given and its detector's rows along the axis (a portrait
    detector, :func:`~robot_ct_ros.ct.scan_weights.rows_run_across_axis`), the outermost rows."""
    from robot_ct_ros.ct.scan_weights import rows_run_across_axis

    li = np.asarray(line_integrals, dtype=np.float32)
    mask = as_view_mask(valid_mask, li.shape) & np.isfinite(li)
    if geom is not None and not rows_run_across_axis(geom):
        li, mask = np.swapaxes(li, -1, -2), np.swapaxes(mask, -1, -2)
    n_cols = li.shape[-1]
    edge_px = max(1, min(edge_px, n_cols // 2))  # a narrow detector: its edges are its own columns
    cols = np.unique(np.r_[0:edge_px, n_cols - edge_px:n_cols])
    edge, m = li[..., cols], mask[..., cols]
    per_view = (np.where(m, edge, 0.0).sum(axis=(1, 2)) / np.maximum(m.sum(axis=(1, 2)), 1))
    peak = float(np.percentile(li[mask], 99.9)) if mask.any() else 0.0
    # noise about a zero edge can make the median slightly negative: no object there reads as 0, not -0.000
    return max(0.0, float(np.median(per_view) / peak)) if peak > 0 else 0.0


def estimation_grid(grid: VolumeGrid, padding: float) -> VolumeGrid:
    """``grid`` widened ``padding`` times across (x and y, same voxels and centre): room for
    the part of the object outside the ROI that the truncated rays still cross."""
    nz, ny, nx = grid.shape_zyx
    return grid.resized((nz, int(round(ny * padding)), int(round(nx * padding))))


def axis_last(grid: VolumeGrid, geom: ConeGeometry, axis=None) -> VolumeGrid:
    """The same box and voxels as ``grid``, its axes named so that z is the one along the scan axis
    (:func:`~robot_ct_ros.ct.scan_weights.estimate_scan_axis`, within
    :data:`~robot_ct_ros.ct.calibration.masks.AXIS_ALIGNED_DEG`): a cyclic renaming, so the voxel centres are the
    very same points. The estimation widens a grid across its x and y (:func:`estimation_grid`) and keeps the FDK
    to its central x-y part: a world-aligned grid around a scan about +y (RTK's axis) was widened along the axis and
    not across it. ``grid`` itself where its z already is along the axis, or none of its axes is. ``axis``: the
    scan's unit axis where the caller knows it (default: estimated from ``geom``)."""
    from robot_ct_ros.ct.calibration.masks import AXIS_ALIGNED_DEG
    from robot_ct_ros.ct.scan_weights import estimate_scan_axis

    D = grid.direction_matrix
    n = estimate_scan_axis(geom) if axis is None else np.asarray(axis, np.float64) / np.linalg.norm(axis)
    along = np.abs(n @ D) >= np.cos(np.deg2rad(AXIS_ALIGNED_DEG))
    if along[2] or not along.any():
        return grid
    k = int(np.flatnonzero(along)[0])
    order = [(k + 1) % 3, (k + 2) % 3, k]  # cyclic: keeps the frame right-handed
    n_xyz, vs = np.asarray(grid.shape_xyz), np.asarray(grid.voxel_size_mm)
    return VolumeGrid.centered(tuple(int(n) for n in n_xyz[order][::-1]), tuple(vs[order]), grid.center_mm,
                               D[:, order])
