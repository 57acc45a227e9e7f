"""A simulated scan: the phantom voxelised finely in the ROI and coarsely elsewhere, projected, counted."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from robot_ct_ros.ct.geometry import ConeGeometry, VolumeGrid, bin_projections
from robot_ct_ros.ct.simulation.detector import (DetectorModel, counts_to_line_integrals, simulate_counts,
                                                 simulate_flat)
from robot_ct_ros.ct.simulation.phantoms import Phantom, _rng, voxelize

__all__ = ["raw_geometry", "irradiated_bounds_mm", "scan_volumes", "SimulatedScan", "project_parts", "simulate_scan"]

# ----------------------------------------------------------------------------- scan simulation
def raw_geometry(geom: ConeGeometry, binning: int) -> ConeGeometry:
    """The unbinned detector whose ``binning`` x ``binning`` binning is ``geom`` (same centre)."""
    if binning == 1:
        return geom
    return geom.with_detector(geom.n_rows * binning, geom.n_cols * binning,
                              geom.row_pitch_mm / binning, geom.col_pitch_mm / binning)


def irradiated_bounds_mm(geom: ConeGeometry) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box holding every ray of the scan (hull of sources and detector corners)."""
    hu = 0.5 * geom.n_cols * geom.col_pitch_mm
    hv = 0.5 * geom.n_rows * geom.row_pitch_mm
    pts = [geom.source_mm]
    for a in (-1, 1):
        for b in (-1, 1):
            pts.append(geom.detector_mm + a * hu * geom.u + b * hv * geom.v)
    pts = np.concatenate(pts)
    return pts.min(axis=0), pts.max(axis=0)


def _box_ramp(grid: VolumeGrid, lo, hi, blend_mm) -> np.ndarray:
    """Separable weight at the voxel centres of ``grid``: 1 deeper than ``blend_mm`` inside the
    box [lo, hi], falling linearly to 0 at its faces, 0 outside. float32 (nz, ny, nx)."""
    ramps = []
    for a, ax in enumerate(grid.axes_mm()):
        dist = np.minimum(ax - lo[a], hi[a] - ax)
        ramps.append(np.clip(dist / blend_mm[a], 0.0, 1.0).astype(np.float32))
    return ramps[2][:, None, None] * ramps[1][None, :, None] * ramps[0][None, None, :]


def scan_volumes(phantom: Phantom, geom: ConeGeometry, voxel_size_mm, roi_grid: VolumeGrid | None = None,
                 outer_voxel_size_mm=None, roi_margin_mm: float = 0.5, supersample: int = 2,
                 max_voxels: int = 400 ** 3, blend_voxels: int = 2):
    """The voxelised parts ``[(volume, grid), ...]`` whose projections sum to the scan.

    Without ``roi_grid``/``outer_voxel_size_mm``: one grid of ``voxel_size_mm`` over the
    irradiated part of the phantom. With both: a coarse grid (``outer_voxel_size_mm``, rounded
    to a multiple of ``voxel_size_mm``) over the irradiated phantom and a fine grid
    (``voxel_size_mm``) over the box around ``roi_grid`` (+ ``roi_margin_mm``, snapped to
    coarse voxels, + ``blend_voxels`` coarse voxels), combined by a partition of unity: the
    fine part is weighted by ``w`` (1 inside the ROI + margin, falling linearly to 0 over the
    blend band), the coarse part by ``1 - w``. A hard cut would leave line artefacts where
    rays graze the box faces (the two grids' interpolation kernels do not add up to one
    there); the blend, with its kinks on voxel centres of both grids, removes them.
    The coarse part only feeds the truncated rays; the ROI is fine.
    """
    vs = np.broadcast_to(np.asarray(voxel_size_mm, float), (3,)).copy()
    plo, phi = phantom.bounds_mm()
    ilo, ihi = irradiated_bounds_mm(geom)
    lo, hi = np.maximum(plo, ilo), np.minimum(phi, ihi)
    if np.any(hi <= lo):
        raise ValueError("the phantom is not irradiated by this geometry")
    if roi_grid is None or outer_voxel_size_mm is None:
        n = np.maximum(1, np.ceil((hi - lo) / vs).astype(int))
        if np.prod(n) > max_voxels:
            raise ValueError(f"fine grid {tuple(int(x) for x in n)} exceeds max_voxels; pass roi_grid and outer_voxel_size_mm")
        g = VolumeGrid.centered(tuple(n[::-1]), vs, 0.5 * (lo + hi))
        return [(voxelize(phantom, g, supersample), g)]
    # both lattices share the node c0 and the coarse pitch is a multiple of the fine one, so
    # every coarse voxel centre is a fine voxel centre and the ramp kinks sit on both lattices:
    # linear interpolation (the projector's) of the two weighted parts then sums exactly.
    fac = np.maximum(1, np.round(np.broadcast_to(np.asarray(outer_voxel_size_mm, float), (3,)) / vs)).astype(int)
    ovs = fac * vs
    c0 = roi_grid.center_mm
    rlo, rhi = roi_grid.bounds_mm()
    in_lo = c0 + np.floor((rlo - roi_margin_mm - c0) / ovs) * ovs
    in_hi = c0 + np.ceil((rhi + roi_margin_mm - c0) / ovs) * ovs
    nb = max(1, int(blend_voxels))
    out_lo, out_hi = in_lo - nb * ovs, in_hi + nb * ovs
    k_lo = np.floor((lo - c0) / ovs - 0.5).astype(int)
    k_hi = np.ceil((hi - c0) / ovs + 0.5).astype(int)
    nc = k_hi - k_lo + 1
    if np.prod(nc) > max_voxels:
        raise ValueError(f"coarse grid {tuple(int(x) for x in nc)} exceeds max_voxels; raise outer_voxel_size_mm")
    cg = VolumeGrid(tuple(nc[::-1]), tuple(ovs), tuple(c0 + k_lo * ovs))
    nf = np.round((out_hi - out_lo) / vs).astype(int) + 1
    if np.prod(nf) > max_voxels:
        raise ValueError(f"fine ROI grid {tuple(int(x) for x in nf)} exceeds max_voxels")
    fg = VolumeGrid(tuple(nf[::-1]), tuple(vs), tuple(out_lo))
    blend = nb * ovs
    coarse = voxelize(phantom, cg, supersample)
    coarse *= 1.0 - _box_ramp(cg, out_lo, out_hi, blend)
    fine = voxelize(phantom, fg, supersample) * _box_ramp(fg, out_lo, out_hi, blend)
    return [(coarse, cg), (fine, fg)]


@dataclass(frozen=True, eq=False)
class SimulatedScan:
    """Result of :func:`simulate_scan` (arrays per the geometry.py conventions).

    ``line_integrals`` float32 (n_views, rows, cols) on the readout detector ``geom``, 0 where
    ``valid_mask`` (bool (rows, cols)) is False; ``ideal_line_integrals`` the noiseless,
    defect-free line integrals (mean over the raw pixels of each bin); ``counts`` and
    ``flat`` the binned detector output (None without a detector model). ``ideal_line_integrals``
    and ``counts`` are None when :func:`simulate_scan` ran with ``keep_intermediates=False``.
    """

    line_integrals: np.ndarray
    valid_mask: np.ndarray
    geom: ConeGeometry
    ideal_line_integrals: np.ndarray | None
    counts: np.ndarray | None = None
    flat: np.ndarray | None = None
    info: dict = field(default_factory=dict)


def project_parts(parts, geom: ConeGeometry) -> np.ndarray:
    """Line integrals of the voxelised parts ``[(volume, grid), ...]`` (:func:`scan_volumes`), summed."""
    from robot_ct_ros.ct.projector import forward_project

    li = None
    for vol, grid in parts:
        p = forward_project(vol, grid, geom)
        li = p if li is None else li + p
    return li


def simulate_scan(phantom: Phantom, geom_true: ConeGeometry, detector: DetectorModel | None = None, *,
                  voxel_size_mm=0.02, roi_grid: VolumeGrid | None = None, outer_voxel_size_mm=None,
                  roi_margin_mm: float = 0.5, supersample: int = 2, pixel_supersample: int = 1, rng=None,
                  chunk_views: int = 16, parts=None, projector=None,
                  keep_intermediates: bool = True) -> SimulatedScan:
    """Simulate the measured projections of ``phantom`` along the true geometry.

    ``geom_true`` is the readout (binned) geometry. The phantom is voxelised at
    ``voxel_size_mm`` (choose finer than the reconstruction), see :func:`scan_volumes` for
    ``roi_grid``/``outer_voxel_size_mm`` (fine ROI + coarse rest; use it for large objects),
    or pass pre-voxelised ``parts``. With a ``detector`` the projection runs on the raw
    detector (``raw_geometry(geom_true, binning)``), then :func:`simulate_counts` and
    :func:`counts_to_line_integrals`; without one, on ``pixel_supersample``-times finer
    pixels averaged back, noise free. Processed in chunks of ``chunk_views`` views.

    ``projector(geom)``, when given, replaces the voxelised phantom: the line integrals of the
    views of ``geom`` (the raw detector's, a chunk at a time), e.g. RTK's exact ray-ellipsoid
    intersections (:func:`robot_ct_ros.ct.rtk_bridge.rtk_ellipsoid_projections`). With
    ``keep_intermediates`` False only the line integrals are kept (``ideal_line_integrals`` and
    ``counts`` are None), converted from counts chunk by chunk: one (n, rows, cols) float32
    stack in all instead of three and the conversion's temporaries (a full-size scan is 250 MB
    a stack); the line integrals and mask are identical.
    """
    sub = detector.binning if detector is not None else int(pixel_supersample)
    gproj = raw_geometry(geom_true, sub)
    if projector is None:
        if parts is None:
            parts = scan_volumes(phantom, gproj, voxel_size_mm, roi_grid, outer_voxel_size_mm, roi_margin_mm,
                                 supersample)

        def projector(g):
            return project_parts(parts, g)
    info = {"parts": [g.to_dict() for _, g in (parts or ())]}
    rng = _rng(rng)
    nv, nr, nc = geom_true.n_views, geom_true.n_rows, geom_true.n_cols
    lean = detector is not None and not keep_intermediates
    ideal = None if lean else np.empty((nv, nr, nc), np.float32)
    counts = np.empty((nv, nr, nc), np.float32) if detector is not None else None  # lean: the line integrals
    flat = valid = mask = None
    if detector is not None:
        flat, valid = simulate_flat((nr * sub, nc * sub), detector, rng)
    for v0 in range(0, nv, chunk_views):
        sel = slice(v0, min(nv, v0 + chunk_views))
        li = projector(gproj.subset(np.arange(sel.start, sel.stop)))
        if not lean:
            ideal[sel] = bin_projections(li, sub, mean=True)
        if detector is not None:
            c = simulate_counts(li, detector, rng, flat=flat)[0]
            if lean:  # elementwise, so chunk by chunk is the same as all at once
                counts[sel], mask = counts_to_line_integrals(c, flat, valid)
            else:
                counts[sel] = c
    if detector is None:
        return SimulatedScan(ideal, np.ones((nr, nc), bool), geom_true, ideal, info=info)
    info["detector"] = detector
    if lean:
        return SimulatedScan(counts, mask, geom_true, None, None, flat, info=info)
    li, mask = counts_to_line_integrals(counts, flat, valid)
    return SimulatedScan(li, mask, geom_true, ideal, counts, flat, info=info)
