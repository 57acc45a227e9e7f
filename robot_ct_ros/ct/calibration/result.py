"""What a calibration returns: the corrected geometry, its volume and the iterations' record."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robot_ct_ros.ct.geometry import ConeGeometry

__all__ = ["CalibrationResult", "IterationRecord"]


@dataclass(frozen=True)
class IterationRecord:
    """What one outer iteration did.

    ``projection_rmse`` and ``projection_ncc``: consistency of the finer level's volume with the
    data after the iteration; ``update_rms_mm`` / ``update_rms_deg``: RMS change of the
    translations and rotations; ``independent_fraction`` (LLE with a prior): the median fraction
    of each view's pixels whose residual counts as independent at the last level (near 1 where
    the volume explains the data up to noise, near 0 where the estimate leans on the prior;
    :func:`~robot_ct_ros.ct.calibration.lle.weights.effective_pixel_fraction`); ``update_px``:
    how far the iteration moved the views, as the mean gauge-aligned displacement of the ROI
    points' projections (full-size detector pixels), on which the loop stops."""

    iteration: int
    projection_rmse: float
    projection_ncc: float
    update_rms_mm: float
    update_rms_deg: float
    wall_s: float
    independent_fraction: float = float("nan")
    update_px: float = float("nan")


@dataclass(frozen=True, eq=False)
class CalibrationResult:
    """A calibrated scan: ``params`` (n, 9) relative to the nominal geometry, ``geom`` =
    nominal.perturbed(params), ``volume`` the FDK with ``geom`` on the ROI grid, ``history`` one
    :class:`IterationRecord` per outer iteration (an ensemble's: its first member's), ``members``
    the runs averaged and ``spread_px`` their mean gauge-aligned distance to the mean (NaN for
    one run), ``settings`` the :class:`~robot_ct_ros.ct.calibration.settings.CalibrationSettings`
    the run used (with the stated accuracy, which a method without a prior does not estimate with and
    the guard reads all the same), ``notes`` what the loop decided on
    its own (e.g. views it kept at nominal), ``params_unguarded`` the loop's estimate before the guard
    kept views at nominal (None when it kept none)."""

    method: str
    params: np.ndarray
    geom: ConeGeometry
    volume: np.ndarray
    history: tuple
    wall_s: float
    members: int = 1
    spread_px: float = float("nan")
    settings: object = None
    notes: tuple = ()
    params_unguarded: np.ndarray | None = None
