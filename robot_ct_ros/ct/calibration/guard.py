"""Never worse than the robots: a correction the robots' accuracy cannot explain is not applied.

The estimator follows its data term; where truncation biases that term, the estimate follows the
bias, and any consistency measure computed from the same data tends to approve it (a joint
reconstruction fits each view in its own geometry). What the data term cannot fake is the size of
the correction: the robots' stated per-view accuracy (the settings' prior) says how far a view can
be from its nominal geometry. The guard compares how far the correction moves each view's ROI
points with how far errors of that accuracy move them:

* R = (mean displacement of the ROI points' projections by the correction) / (the same mean for
  random errors of the stated accuracy). R well above 1 means the loop moved the views much
  further than the robots can err: the whole scan keeps its nominal geometry. Where the data
  term is known to be biased (a strongly truncated scan whose exterior was not modelled) the
  caller passes a stricter ``scan_max_ratio``.
* Otherwise a view moved further than ``max_ratio`` times the ``view_quantile`` of the random
  displacements keeps its nominal geometry alone: the same tolerance for an understated accuracy
  as the scan's (without it, robots that err 1.4 times more than stated lose their largest,
  correct corrections).

It needs the robots' accuracy stated to within ``max_ratio``. Evidence: docs/calibration.md,
"Never worse than the robots".
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robot_ct_ros.ct.geometry import ConeGeometry

__all__ = ["GuardResult", "plausibility_guard"]


@dataclass(frozen=True)
class GuardResult:
    """``params`` after the guard, the ratio R, the views kept at nominal, and the scan-level verdict."""

    params: np.ndarray
    ratio: float
    reverted_views: tuple
    scan_reverted: bool

    def note(self, max_ratio: float) -> str:
        """The verdict in words; ``max_ratio``: the scan-level limit that was applied."""
        if self.scan_reverted:
            return (f"guard: the correction moved the views {self.ratio:.2f} times as far as the robots' stated accuracy "
                    f"explains (limit {max_ratio:g}); the data do not support it and the nominal geometry is kept")
        kept = f"; {len(self.reverted_views)} view(s) moved beyond that accuracy keep their nominal geometry: " \
               f"{list(self.reverted_views)[:20]}{' ...' if len(self.reverted_views) > 20 else ''}" \
            if self.reverted_views else ""
        return f"guard: the correction is {self.ratio:.2f} times the robots' stated accuracy (limit {max_ratio:g}){kept}"


def _displacement_px(nominal: ConeGeometry, params: np.ndarray, points: np.ndarray, reference: np.ndarray):
    return np.linalg.norm(nominal.perturbed(params).project_points(points) - reference, axis=-1).mean(axis=1)


def plausibility_guard(nominal: ConeGeometry, params: np.ndarray, points_mm, stated_sigma, *, max_ratio: float = 1.5,
                       view_quantile: float = 0.999, draws: int = 20, seed: int = 0,
                       scan_max_ratio: float | None = None) -> GuardResult:
    """The correction ``params`` (n, 9) relative to ``nominal``, checked against the robots' accuracy.

    Parameters
    ----------
    points_mm : (m, 3) array
        ROI points (e.g. :func:`robot_ct_ros.ct.metrics.roi_points`).
    stated_sigma : sequence of 9 floats
        The robots' per-view error, mm x6 and rad x3 (the prior's standard deviations).
    max_ratio : float
        Above this R the scan keeps its nominal geometry (unless ``scan_max_ratio`` is given); the
        single views' tolerance.
    scan_max_ratio : float, optional
        The scan-level limit on R instead of ``max_ratio``.
    view_quantile : float
        A view displaced beyond ``max_ratio`` times this quantile of the random displacements keeps
        its nominal geometry.
    draws : int
        Random scans drawn to estimate the displacements errors of the stated accuracy cause.
    """
    params = np.asarray(params, np.float64).reshape(nominal.n_views, 9)
    sigma = np.asarray(stated_sigma, np.float64)
    if sigma.shape != (9,) or not np.all(sigma > 0):
        raise ValueError("the guard needs the robots' accuracy as 9 positive standard deviations")
    points = np.atleast_2d(np.asarray(points_mm, np.float64))
    reference = nominal.project_points(points)
    rng = np.random.default_rng(seed)
    drawn = np.concatenate([_displacement_px(nominal, rng.standard_normal(params.shape) * sigma, points, reference)
                            for _ in range(int(draws))])
    moved = _displacement_px(nominal, params, points, reference)
    ratio = float(moved.mean() / max(drawn.mean(), 1e-300))
    if ratio > (max_ratio if scan_max_ratio is None else scan_max_ratio):
        return GuardResult(np.zeros_like(params), ratio, tuple(range(nominal.n_views)), True)
    beyond = np.flatnonzero(moved > max_ratio * np.quantile(drawn, view_quantile))
    out = params.copy()
    out[beyond] = 0.0
    return GuardResult(out, ratio, tuple(int(v) for v in beyond), False)
