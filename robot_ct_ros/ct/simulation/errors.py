"""Per-view geometric errors: robot coordination, slow drift, static offsets (9-DOF, geometry.py order)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d

from robot_ct_ros.ct.simulation.phantoms import _rng

__all__ = ["GeometryErrorModel", "SumOfErrorModels", "robot_coordination", "detector_drift", "static_misalignment"]

# ----------------------------------------------------------------------------- geometric errors
@dataclass(frozen=True)
class GeometryErrorModel:
    """Per-view 9-DOF geometric errors (geometry.py order and units: mm x6, rad x3).

    ``sample(n)`` = ``static_offset`` + drift + white noise, where the white noise is
    independent per view with ``per_view_sigma`` (robot coordination), and the drift is
    ``drift_per_view * view_index`` (``drift_kind="linear"``, creep starting at 0) or a
    random walk with step sigma ``drift_per_view`` smoothed by a Gaussian of
    ``drift_smooth_views`` views (``"random_walk"``). Reproducible from ``seed``.
    """

    per_view_sigma: tuple = (0.0,) * 9
    drift_per_view: tuple = (0.0,) * 9
    static_offset: tuple = (0.0,) * 9
    drift_kind: str = "linear"
    drift_smooth_views: float = 10.0
    seed: int = 0

    def __post_init__(self):
        for name in ("per_view_sigma", "drift_per_view", "static_offset"):
            v = tuple(float(x) for x in np.broadcast_to(np.asarray(getattr(self, name), float), (9,)))
            object.__setattr__(self, name, v)
        if self.drift_kind not in ("linear", "random_walk"):
            raise ValueError("drift_kind must be 'linear' or 'random_walk'")
        if min(self.per_view_sigma) < 0:
            raise ValueError("per_view_sigma must be non-negative")

    def sample(self, n_views: int, rng=None) -> np.ndarray:
        """(n_views, 9) float64 parameters for ``ConeGeometry.perturbed``."""
        rng = _rng(self.seed if rng is None else rng)
        sigma = np.asarray(self.per_view_sigma)
        drift = np.asarray(self.drift_per_view)
        out = np.broadcast_to(np.asarray(self.static_offset), (n_views, 9)).copy()
        out += rng.standard_normal((n_views, 9)) * sigma
        if np.any(drift != 0):
            if self.drift_kind == "linear":
                out += np.arange(n_views)[:, None] * drift
            else:
                walk = np.cumsum(rng.standard_normal((n_views, 9)) * drift, axis=0)
                if self.drift_smooth_views > 0 and n_views > 1:
                    walk = gaussian_filter1d(walk, self.drift_smooth_views, axis=0, mode="nearest")
                out += walk - walk[:1]
        return out

    def __add__(self, other: "GeometryErrorModel") -> "SumOfErrorModels":
        return SumOfErrorModels((self, other))


@dataclass(frozen=True)
class SumOfErrorModels:
    """Several error models added (e.g. robot coordination + detector drift + static offset)."""

    models: tuple

    def sample(self, n_views: int, rng=None) -> np.ndarray:
        rng = None if rng is None else _rng(rng)
        return sum(m.sample(n_views, rng) for m in self.models)

    def __add__(self, other) -> "SumOfErrorModels":
        return SumOfErrorModels(self.models + (other.models if isinstance(other, SumOfErrorModels) else (other,)))


def robot_coordination(sigma_mm: float = 0.3, sigma_deg: float = 0.3, seed: int = 0) -> GeometryErrorModel:
    """Independent per-view errors of both arms: source and detector shifts (sigma_mm each
    axis) and detector rotations (sigma_deg each axis)."""
    return GeometryErrorModel(per_view_sigma=(sigma_mm,) * 6 + (np.deg2rad(sigma_deg),) * 3, seed=seed)


def detector_drift(mm_per_view: float = 0.002, deg_per_view: float = 0.0005, kind: str = "linear",
                   smooth_views: float = 10.0, seed: int = 0) -> GeometryErrorModel:
    """Slow detector creep: all detector shifts and rotations drift by the given amount per view
    (linear), or as a smoothed random walk with that step sigma."""
    drift = (0.0,) * 3 + (mm_per_view,) * 3 + (np.deg2rad(deg_per_view),) * 3
    return GeometryErrorModel(drift_per_view=drift, drift_kind=kind, drift_smooth_views=smooth_views, seed=seed)


def static_misalignment(offset) -> GeometryErrorModel:
    """A constant 9-DOF offset on every view."""
    return GeometryErrorModel(static_offset=tuple(offset))
