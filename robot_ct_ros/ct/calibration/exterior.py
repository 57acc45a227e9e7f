"""The exterior model: the object outside the ROI, reconstructed with it, for strongly truncated scans.

In an interior scan every ray crosses far more object outside the ROI than inside it. A model
of the ROI alone cannot reproduce the projections (the outside's edges, bones, air, dominate
them), and every estimator then registers the views to what is missing. The exterior model adds
a coarse grid around the ROI, over the region the rays cross, and reconstructs both together by
non-negative ordered-subsets SIRT from zero, so that the sum of the two parts' projections
reproduces the measured rays. Evidence and limits: docs/calibration.md, "The exterior model".

Grids are built in the ROI grid's own frame (any world frame; its z axis is the scan axis).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robot_ct_ros.ct.calibration.masks import as_view_mask
from robot_ct_ros.ct.calibration.model import VolumeParts
from robot_ct_ros.ct.calibration.settings import REACH_SETTING
from robot_ct_ros.ct.geometry import ConeGeometry, VolumeGrid

__all__ = ["REACH_FACTORS", "ReachChoice", "choose_reach", "exterior_grid", "exterior_support", "held_out_ncc",
           "joint_sirt", "reconstruct_with_exterior"]


def exterior_grid(roi: VolumeGrid, geom: ConeGeometry, voxel_mm: float, half_width_mm: float = 0.0) -> VolumeGrid:
    """A grid of ``voxel_mm`` voxels around ``roi`` (same direction) for what the rays cross outside it.

    Across the scan axis it reaches ``half_width_mm`` from the ROI centre (0: up to the sources,
    the largest region an object can fill), clipped to the box the rays span; along the axis, the
    rays' whole extent, so no ray leaves it through its top or bottom inside the object.
    """
    from robot_ct_ros.ct.simulation.scan import irradiated_bounds_mm

    if not voxel_mm > 0:
        raise ValueError("the exterior grid's voxel must be positive")
    local_roi, R = roi.in_own_frame()
    g = geom.moved(R)
    lo, hi = irradiated_bounds_mm(g)
    c = np.asarray(local_roi.center_mm, np.float64)
    half = (float(np.max(np.linalg.norm((g.source_mm - c)[:, :2], axis=1))) if not half_width_mm > 0
            else float(half_width_mm))
    lo[:2] = np.maximum(lo[:2], c[:2] - half)
    hi[:2] = np.minimum(hi[:2], c[:2] + half)
    k_lo = np.floor((lo - c) / voxel_mm).astype(int)
    k_hi = np.ceil((hi - c) / voxel_mm).astype(int)
    n = k_hi - k_lo + 1
    local = VolumeGrid(tuple(int(x) for x in n[::-1]), (float(voxel_mm),) * 3, tuple(c + k_lo * voxel_mm))
    return local.moved(R.T)


def exterior_support(ext: VolumeGrid, roi: VolumeGrid, overlap_voxels: float = 1.0) -> np.ndarray:
    """float32 0/1 mask of the exterior grid's voxels that may hold object: those whose centre lies
    outside the ROI box shrunk by ``overlap_voxels`` exterior voxels (the two grids overlap in
    that band, so no ray passes between them). Both grids must share their direction."""
    if not np.allclose(ext.direction_matrix, roi.direction_matrix, atol=1e-9):
        raise ValueError("the exterior and ROI grids must have the same direction")
    local_roi, _ = roi.in_own_frame()
    lo, hi = local_roi.bounds_mm()
    m = overlap_voxels * np.asarray(ext.voxel_size_mm)
    lo, hi = lo + m, hi - m
    x, y, z = ext.axes_mm()  # the grids' shared own frame
    inside = ((z[:, None, None] > lo[2]) & (z[:, None, None] < hi[2]) & (y[None, :, None] > lo[1])
              & (y[None, :, None] < hi[1]) & (x[None, None, :] > lo[0]) & (x[None, None, :] < hi[0]))
    return (~inside).astype(np.float32)


def joint_sirt(line_integrals, geom: ConeGeometry, parts, iterations: int, valid_mask=None, *, subsets: int = 1,
               nonneg: bool = True, relaxation: float = 1.0, after_pass=None) -> list:
    """SIRT on several grids at once: the data are fitted by the sum of the parts' projections.

    Parameters
    ----------
    parts : sequence of (x0 or None, grid, support or None)
        Start volume (None: zeros), grid, and a 0/1 mask of the voxels that may change.
    iterations : int
        Passes over all views.
    subsets : int
        Ordered subsets of interleaved views, each updated in turn (1: plain SIRT).
    after_pass : callable, optional
        ``after_pass(volumes, before)`` after each pass, with the parts' volumes (changed in
        place) and copies of them from before the pass: a regularisation step between passes
        (bench/bench_interior_diagnosis.py tries a total-variation one on the exterior).

    Returns
    -------
    list of float32 volumes, one per part. Row sums are those of all parts together, column sums
    per part and subset.
    """
    from robot_ct_ros.ct.projector import back_project, forward_project

    b = np.asarray(line_integrals, np.float32)
    mask = as_view_mask(valid_mask, b.shape) & np.isfinite(b)
    b = np.where(mask, b, 0.0).astype(np.float32)
    xs, grids, sups = [], [], []
    row = None
    for x0, g, sup in parts:
        s = np.ones(g.shape_zyx, np.float32) if sup is None else np.asarray(sup, np.float32)
        xs.append(np.zeros(g.shape_zyx, np.float32) if x0 is None else np.array(x0, np.float32) * s)
        grids.append(g)
        sups.append(s)
        p = forward_project(s, g, geom)
        row = p if row is None else row + p
    eps = np.float32(1e-6)
    R = np.where(mask & (row > eps * row.max()), 1.0 / np.maximum(row, eps), 0.0).astype(np.float32)
    subsets = max(1, min(int(subsets), geom.n_views))
    views = [np.arange(k, geom.n_views, subsets) for k in range(subsets)]  # interleaved: each spans the orbit
    sub = [(geom.subset(v), b[v], R[v], mask[v]) for v in views]
    inv_cols = []
    for g_s, _, _, m_s in sub:
        per_part = []
        for g, s in zip(grids, sups):
            col = back_project(m_s.astype(np.float32), g_s, g) * s
            per_part.append(np.where(col > eps * col.max(), 1.0 / np.maximum(col, eps), 0.0).astype(np.float32) * s)
        inv_cols.append(per_part)
    for _ in range(int(iterations)):
        before = [x.copy() for x in xs] if after_pass is not None else None
        for (g_s, b_s, R_s, _), C_s in zip(sub, inv_cols):
            pred = None
            for x, g in zip(xs, grids):
                p = forward_project(x, g, g_s)
                pred = p if pred is None else pred + p
            res = (b_s - pred) * R_s
            for x, g, C in zip(xs, grids, C_s):
                x += np.float32(relaxation) * C * back_project(res, g_s, g)
                if nonneg:
                    np.maximum(x, 0.0, out=x)
        if after_pass is not None:
            after_pass(xs, before)
    return xs


def reconstruct_with_exterior(line_integrals, geom: ConeGeometry, grid: VolumeGrid, mask, *, voxel_mm: float,
                              half_width_mm: float, iterations: int, subsets: int, after_pass=None) -> VolumeParts:
    """The estimation volume of a strongly truncated scan: ``grid`` and an exterior grid around it
    (:func:`exterior_grid`, :func:`exterior_support`) reconstructed together from zero
    (:func:`joint_sirt`). Starting from zero matters: an FDK start brings the truncation's bias
    into the ROI, and it leaves slowly. ``after_pass``: see :func:`joint_sirt` (parts: ROI, exterior)."""
    ext = exterior_grid(grid, geom, voxel_mm, half_width_mm)
    roi_vol, ext_vol = joint_sirt(line_integrals, geom, [(None, grid, None), (None, ext, exterior_support(ext, grid))],
                                  iterations, mask, subsets=subsets, after_pass=after_pass)
    return VolumeParts(((roi_vol, grid), (ext_vol, ext)))


REACH_FACTORS = (1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0)
"""The reaches :func:`choose_reach` scores, as multiples of its grid's half-width across the axis (the loop
passes the estimation grid, the ROI grid widened by ``padding``)."""


@dataclass(frozen=True)
class ReachChoice:
    """The reach :func:`choose_reach` picked (mm from the ROI centre across the axis) and each candidate's
    held-out NCC, ``((reach_mm, ncc), ...)``."""

    reach_mm: float
    scores: tuple

    def note(self) -> str:
        table = ", ".join(f"{r:.1f} mm {s:.4f}" for r, s in self.scores)
        return (f"the object's reach was not stated: the exterior model reaches {self.reach_mm:.1f} mm, the reach "
                f"whose model, built from 9 in 10 views, best predicted the views it did not see (held-out NCC: "
                f"{table}); where the object's far side is known, state it ({REACH_SETTING})")


def choose_reach(line_integrals, geom: ConeGeometry, grid: VolumeGrid, mask, *, voxel_mm: float, iterations: int,
                 subsets: int, factors=REACH_FACTORS, folds: int = 10, held_out=(0, 5)) -> ReachChoice:
    """The exterior model's reach for a scan that does not state it: the candidate whose model best
    predicts views it was not built from.

    For each reach (``factors`` times the half-width of ``grid`` across its z axis, the scan axis;
    those that reach the sources left out), the ROI and exterior model is reconstructed with ``geom``
    from all views but one interleaved fold in ``folds`` (views f, f + folds, ...; f in
    ``held_out`` in turn), and scored by the mean projection NCC of its reprojection into the
    held-out views. The fit to the views a model was built from rises with the reach and tells
    nothing; held-out prediction peaks short of the far side of the wide objects measured. The
    reach it picks corrected every strongly truncated scan measured, less than the far side stated
    on the interior neck and more on the sweep's wider mice and the full neck (docs/calibration.md,
    "The exterior model"). Raises ValueError with fewer than ``2 * folds`` views or no candidate.
    """
    li = np.asarray(line_integrals, np.float32)
    mk = as_view_mask(mask, li.shape)
    local, R = grid.in_own_frame()
    lo, hi = local.bounds_mm()
    half_roi = float(np.max(hi[:2] - lo[:2])) / 2.0
    g_local = geom.moved(R)
    to_source = float(np.min(np.linalg.norm((g_local.source_mm - np.asarray(local.center_mm))[:, :2], axis=1)))
    reaches = [f * half_roi for f in factors if f * half_roi < to_source]
    if not reaches:
        raise ValueError("no candidate reach lies between the ROI and the sources")
    if geom.n_views < 2 * folds:
        raise ValueError(f"choosing the reach needs at least {2 * folds} views, got {geom.n_views}")
    scores = [(float(reach), held_out_ncc(li, geom, grid, mk, reach, voxel_mm=voxel_mm, iterations=iterations,
                                          subsets=subsets, folds=folds, held_out=held_out)[0]) for reach in reaches]
    best = max(scores, key=lambda rs: rs[1])[0]
    return ReachChoice(best, tuple(scores))


def held_out_ncc(line_integrals, geom: ConeGeometry, grid: VolumeGrid, mask, reach_mm: float, *, voxel_mm: float,
                 iterations: int, subsets: int, folds: int = 10, held_out=(0, 5), with_fit: bool = False):
    """(held-out NCC, fit NCC or None) of the ROI and exterior model reaching ``reach_mm`` (0: up to the
    sources), reconstructed with ``geom`` from all views but the interleaved fold f (views f, f + folds,
    ...), f in ``held_out`` in turn: the mean projection NCC of its reprojection into the held-out views,
    and with ``with_fit`` the same in every ``folds``-th view it was built from."""
    from robot_ct_ros.ct.calibration.volume import projection_consistency

    li = np.asarray(line_integrals, np.float32)
    mk = as_view_mask(mask, li.shape)
    n = geom.n_views
    held, fit = [], []
    for f in held_out:
        test = np.arange(f, n, folds)
        train = np.setdiff1d(np.arange(n), test)
        parts = reconstruct_with_exterior(li[train], geom.subset(train), grid, mk[train], voxel_mm=voxel_mm,
                                          half_width_mm=reach_mm, iterations=iterations, subsets=subsets)
        held.append(projection_consistency(parts, grid, geom.subset(test), li[test], mk[test])[1])
        if with_fit:
            seen = train[::folds]
            fit.append(projection_consistency(parts, grid, geom.subset(seen), li[seen], mk[seen])[1])
    return float(np.mean(held)), (float(np.mean(fit)) if with_fit else None)
