"""What the views are registered against: one volume on one grid, or several parts on their own grids.

A strongly truncated scan needs the object outside the ROI in its model: the exterior model
(:mod:`robot_ct_ros.ct.calibration.exterior`) is the ROI grid plus a coarse grid around it, and
a view's model projection is the sum of the parts' projections. Every estimator projects through
:func:`project`, so it does not care which it has.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robot_ct_ros.ct.geometry import ConeGeometry, VolumeGrid

__all__ = ["VolumeParts", "project", "as_model"]


@dataclass(frozen=True, eq=False)
class VolumeParts:
    """Volumes on their own grids whose line integrals add up: ``parts`` = ((volume, grid), ...)."""

    parts: tuple

    def __post_init__(self):
        parts = tuple((np.ascontiguousarray(v, dtype=np.float32), g) for v, g in self.parts)
        for v, g in parts:
            if v.shape != g.shape_zyx:
                raise ValueError(f"a part's volume {v.shape} does not match its grid {g.shape_zyx}")
        object.__setattr__(self, "parts", parts)


def as_model(volume):
    """A volume ready for :func:`project`: float32 C-contiguous, or the :class:`VolumeParts` as given."""
    return volume if isinstance(volume, VolumeParts) else np.ascontiguousarray(volume, dtype=np.float32)


def project(volume, grid: VolumeGrid, geom: ConeGeometry) -> np.ndarray:
    """Line integrals (n, rows, cols) of ``volume`` on ``grid`` for ``geom``; for a
    :class:`VolumeParts` the sum over its parts (``grid`` is then not used)."""
    from robot_ct_ros.ct.projector import forward_project

    if not isinstance(volume, VolumeParts):
        return forward_project(as_model(volume), grid, geom)
    out = None
    for v, g in volume.parts:
        p = forward_project(v, g, geom)
        out = p if out is None else np.add(out, p, out=out)
    return out
