"""Streaming estimation: each view estimated as it arrives, against a running FDK volume.

FDK is a sum over views of filtered back-projections, so a volume can grow view by view. A
:class:`StreamingEstimator` waits for the first ``warmup_views`` views, back-projects them with
their nominal geometry into a first volume, estimates them against it and rebuilds the sum with
their estimates; from then on every new view (or batch of views) is estimated against the
running volume (the method's coarse level: its binning, search box and sampling), scored by
the projection NCC of the volume's reprojection at the estimate against the view, and
back-projected with the estimate into the sum. Each view is filtered alone, weighted by
``2 pi / n_views`` (the whole scan's angular step) about the scan's axis and centre, so adding a
view never changes another's contribution. Axis and centre are the warm-up views' (as
:func:`~robot_ct_ros.ct.reconstruction.fdk` takes them from the whole scan: any world frame, a grid
anywhere), unless given; the running volume's grid is the ROI grid with its z along that axis,
widened across it.

Nothing here is the whole-scan calibration (:func:`~robot_ct_ros.ct.calibration.calibrate`):
the live estimates depend on which views were in the volume when a view arrived; the final
correction runs on the whole scan afterwards, independently of this state. Pure numpy/numba,
no ROS, no processes (the jobs-level driver robot_ct_ros.jobs.streaming owns those).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robot_ct_ros.ct.calibration.masks import as_view_mask, bin_masked, usable_data
from robot_ct_ros.ct.calibration.model import project
from robot_ct_ros.ct.calibration.registry import get_method
from robot_ct_ros.ct.calibration.settings import CalibrationSettings
from robot_ct_ros.ct.calibration.volume import axis_last, estimation_grid
from robot_ct_ros.ct.geometry import ConeGeometry, VolumeGrid
from robot_ct_ros.ct.metrics import ncc

__all__ = ["StreamingEstimator", "StreamStep", "DEFAULT_WARMUP_VIEWS"]

DEFAULT_WARMUP_VIEWS = 8
"""Views back-projected with their nominal geometry into the first volume before any is estimated."""


@dataclass(frozen=True)
class StreamStep:
    """What one :meth:`StreamingEstimator.add_views` call estimated.

    ``view_ids`` the views' indices in the scan (arrival order); ``params`` (k, 9) their
    parameters relative to their nominal geometry (geometry.py order, mm and rad); ``geom`` their
    corrected geometry (full-size detector); ``ncc`` (k,) the projection NCC of the running
    volume's reprojection at the estimate against each view, before it was added (nan for the
    warm-up views, estimated against a volume they are part of); ``mean_ncc`` the running mean of
    the finite ones over the scan so far.
    """

    view_ids: np.ndarray
    params: np.ndarray
    geom: ConeGeometry
    ncc: np.ndarray
    mean_ncc: float


class StreamingEstimator:
    """Per-view estimation against a running FDK volume (see the module docstring).

    Parameters
    ----------
    settings : CalibrationSettings
        Method (its estimator and coarse configuration), schedule (the coarse binning), prior, seed
        and padding. ``"none"``: every view keeps its nominal geometry (the volume still grows).
    grid : VolumeGrid
        The ROI grid; the running volume lies on it widened ``settings.padding`` times across and
        binned as the coarse level.
    n_views : int
        The scan's number of views (its angular step weights each view); at least 1.
    warmup_views : int
        Views collected before the first volume and the first estimates.
    fdk_kwargs : dict, optional
        Options of the filtering (window, cutoff, truncation, ...).
    axis, center_mm : array (3,), optional
        The scan's rotation axis (unit) and a point on it (mm), where the caller knows them. By
        default both come from the warm-up views' nominal geometry
        (:func:`~robot_ct_ros.ct.scan_weights.estimate_scan_axis`,
        :func:`~robot_ct_ros.ct.reconstruction.scan_centre`); with fewer than 3 warm-up views, which
        tell no axis, the grid's z and its centre.
    """

    def __init__(self, settings: CalibrationSettings, grid: VolumeGrid, n_views: int, *,
                 warmup_views: int = DEFAULT_WARMUP_VIEWS, fdk_kwargs: dict | None = None, axis=None,
                 center_mm=None):
        self.settings = settings
        self.method = get_method(settings.method)
        self.binning = max(1, int(settings.plan()["coarse_binning"]))
        self.roi_grid = grid
        self.grid = self._estimation_grid(grid)  # until the warm-up tells the axis: the grid's own z
        self.n_views = max(1, int(n_views))
        self.warmup_views = max(1, int(warmup_views))
        self.fdk_kwargs = dict(fdk_kwargs or {})
        # the scan's axis and centre: given, or fixed by the warm-up views (_fix_frame)
        self.axis = None if axis is None else np.asarray(axis, np.float64) / np.linalg.norm(axis)
        self.center_mm = None if center_mm is None else np.asarray(center_mm, np.float64).reshape(3)
        self.config = None if self.method.estimate is None else self.method.configs(settings)[0]
        self._sum = np.zeros(self.grid.shape_zyx, np.float32)
        self._added = 0                     # views in the running sum
        self._pending: list = []            # warm-up views: (view_id, li, mask, nominal) at the coarse level
        self._ncc: list = []
        self.n_estimated = 0

    def _estimation_grid(self, grid: VolumeGrid) -> VolumeGrid:
        est = estimation_grid(grid, self.settings.padding)
        return est.binned(self.binning) if self.binning > 1 else est

    def _fix_frame(self, warmup: ConeGeometry) -> None:
        """The scan's axis and centre (given, or the warm-up views'), and the running volume's grid: the ROI
        grid's axes renamed so that z runs along the axis (:func:`axis_last`), widened across it."""
        from robot_ct_ros.ct.reconstruction import scan_centre
        from robot_ct_ros.ct.scan_weights import estimate_scan_axis

        grid_z = np.asarray(self.roi_grid.direction_matrix, np.float64)[:, 2]
        if self.axis is None:
            self.axis = estimate_scan_axis(warmup) if warmup.n_views >= 3 else grid_z
        if self.center_mm is None:
            self.center_mm = (scan_centre(warmup, self.axis, fallback_mm=self.roi_grid.center_mm)
                              if warmup.n_views >= 3 else np.asarray(self.roi_grid.center_mm, np.float64))
        self.grid = self._estimation_grid(axis_last(self.roi_grid, warmup, self.axis))
        self._sum = np.zeros(self.grid.shape_zyx, np.float32)

    @property
    def started(self) -> bool:
        """Whether the first volume exists (the warm-up views arrived)."""
        return self._added > 0

    @property
    def volume(self) -> np.ndarray:
        """The running volume on :attr:`grid`, scaled to the whole scan (sum x n_views / views added)."""
        if self._added == 0:
            return self._sum.copy()
        return self._sum * np.float32(self.n_views / self._added)

    @property
    def mean_ncc(self) -> float:
        v = [x for x in self._ncc if np.isfinite(x)]
        return float(np.mean(v)) if v else float("nan")

    def _level(self, li, mask, nominal: ConeGeometry):
        li, mask = usable_data(li, mask)
        if self.binning <= 1:
            return li, mask, nominal
        li_b, mask_b = bin_masked(li, mask, self.binning)
        return li_b, mask_b, nominal.binned(self.binning)

    def _backproject(self, li, mask, geom: ConeGeometry) -> np.ndarray:
        """The FDK contributions of these views (each filtered alone, weighted 1 / n_views), summed. Each view is
        weighted as in a full circle: Parker's short-scan weights need the whole arc, which a stream has not seen."""
        from robot_ct_ros.ct.reconstruction import fdk_backproject
        from robot_ct_ros.ct.reconstruction import fdk_filter_motion_rows  # rows along the motion, as fdk

        out = np.zeros(self.grid.shape_zyx, np.float32)
        for i in range(geom.n_views):
            q, q_geom = fdk_filter_motion_rows(li[i:i + 1], geom.subset(np.array([i])),
                                               center_mm=self.center_mm, axis=self.axis,
                                               valid_mask=mask[i:i + 1], **self.fdk_kwargs)
            out += fdk_backproject(q, q_geom, self.grid) * np.float32(1.0 / self.n_views)
        return out

    def _estimate(self, li, mask, nominal: ConeGeometry, view_ids) -> np.ndarray:
        zeros = np.zeros((nominal.n_views, 9))
        if self.config is None:
            return zeros
        params, _ = self.method.estimate(li, nominal, zeros, self.volume, self.grid, self.config, mask,
                                         view_ids=np.asarray(view_ids, np.int64))
        return params

    def _score(self, li, mask, geom: ConeGeometry) -> np.ndarray:
        """Projection NCC per view of the running volume at ``geom`` against the data."""
        pred = project(self.volume, self.grid, geom)
        mk = as_view_mask(mask, li.shape)
        k = len(li)
        return np.asarray(ncc(pred.reshape(k, -1), li.reshape(k, -1), mk.reshape(k, -1)), np.float64).reshape(k)

    def add_views(self, line_integrals, valid_mask, nominal: ConeGeometry, view_ids) -> StreamStep | None:
        """Estimate these views (full-size data ``(k, rows, cols)``, their nominal geometry and scan
        indices) and add them to the volume; None while the warm-up views are still being collected.
        The call that completes the warm-up returns the warm-up views and, when more views came with
        it, those estimated against the first volume, in one step."""
        view_ids = np.asarray(view_ids, np.int64).reshape(-1)
        li, mask, nom = self._level(np.asarray(line_integrals, np.float32), valid_mask, nominal)
        parts = [(view_ids, li, mask, nom, nominal)]
        if not self.started:
            self._pending.append(parts[0])
            if sum(len(p[0]) for p in self._pending) < self.warmup_views:
                return None
            joined = [np.concatenate([p[j] for p in self._pending]) for j in range(3)]
            joined += [ConeGeometry.concatenate([p[j] for p in self._pending]) for j in (3, 4)]
            self._pending = []
            k = self.warmup_views
            first, rest = np.arange(k), np.arange(k, len(joined[0]))
            parts = [tuple(x[first] if j < 3 else x.subset(first) for j, x in enumerate(joined))]
            if rest.size:
                parts.append(tuple(x[rest] if j < 3 else x.subset(rest) for j, x in enumerate(joined)))
        ids, params, geoms, scores = [], [], [], []
        for ids_p, li_p, mask_p, nom_p, full_p in parts:
            if not self.started:  # the first volume: nominal geometry, then rebuilt with the estimates
                self._fix_frame(nom_p)
                self._sum += self._backproject(li_p, mask_p, nom_p)
                self._added = len(ids_p)
                p = self._estimate(li_p, mask_p, nom_p, ids_p)
                self._sum = self._backproject(li_p, mask_p, nom_p.perturbed(p))
                sc = np.full(len(ids_p), np.nan)
            else:
                p = self._estimate(li_p, mask_p, nom_p, ids_p)
                sc = self._score(li_p, mask_p, nom_p.perturbed(p))
                self._sum += self._backproject(li_p, mask_p, nom_p.perturbed(p))
                self._added += len(ids_p)
            ids.append(ids_p)
            params.append(p)
            geoms.append(full_p.perturbed(p))
            scores.append(sc)
        scores = np.concatenate(scores)
        self._ncc.extend(scores.tolist())
        self.n_estimated += sum(len(x) for x in ids)
        return StreamStep(np.concatenate(ids), np.concatenate(params), ConeGeometry.concatenate(geoms), scores,
                          self.mean_ncc)
