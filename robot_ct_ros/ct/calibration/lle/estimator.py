"""The LLE estimator: one pass over all views, coarse to fine (docs/calibration.md §2)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from robot_ct_ros.ct.calibration.kernels import blas_single_threaded, warp_projections
from robot_ct_ros.ct.calibration.lle.sampling import (best_fit_fraction, ranking, score_samples, score_warped,
                                                      source_offsets, virtual_margin_px)
from robot_ct_ros.ct.calibration.lle.weights import WEIGHTINGS, background_basis, lle_weights, view_distances
from robot_ct_ros.ct.calibration.model import as_model, project
from robot_ct_ros.ct.calibration.masks import estimator_inputs, summarise_views, usable_views, view_chunks
from robot_ct_ros.ct.geometry import ConeGeometry, VolumeGrid, observable_params

__all__ = ["LLEConfig", "estimate_views", "default_lle_configs", "narrowed", "DEFAULT_BACKGROUND", "DRAWS",
           "COARSE_SAMPLES", "EMBEDDING_SETTINGS", "MAX_NARROWING"]


@dataclass(frozen=True)
class LLEConfig:
    """Settings of one LLE estimation pass (all views at once, coarse to fine).

    Each level samples ``n_samples`` geometries per view in a box of ``half_width`` (9
    values: mm x6, rad x3, geometry.py parameter order) around the current estimate; the
    box shrinks by ``shrink`` per level. Source shifts are drawn from a small set of
    positions (``source_positions``: ``"star"`` = centre and ±half width along each axis,
    7 ray-casts per view; ``"grid"`` = 3 x 3 x 3; ``"fixed"`` = the current source only, one
    ray-cast per view: a detector-only refinement); detector shifts and rotations are drawn
    uniformly and rendered by homography from the ray-cast of their source position.
    ``safeguard`` keeps the best sample when the embedding scores worse than it.
    ``background`` = (order along columns, order along rows) of the smooth per-view
    background that the NCC weightings ignore (:func:`background_basis`); (0, 0) is the
    published NCC (offset and gain only). A higher order also absorbs the bowl that the
    truncated object outside the ROI adds to every interior projection.
    ``shift_search_px`` > 0 first searches the detector translation exhaustively over that
    many pixels each way (:func:`_shift_search`). ``prior_sigma`` (9 values, mm x6, rad x3;
    None = off) is the standard deviation of the nominal geometry's error (the robots'
    coordination error): samples are then ranked, and the ``l2`` and ``ncc-exact`` weights
    solved, by posterior instead of data alone (:func:`posterior_cost`), so the parameters
    the data hardly see stay near their nominal values. ``draws`` independent sets of
    ``n_samples`` samples are drawn per level, all scored against the same ray-casts; each set
    is embedded in its own ``n_neighbours`` nearest samples and the sets' estimates are averaged
    (fewer sampling errors for the cost of scoring, :data:`DRAWS`); the safeguard compares the
    average with the best sample of all sets.
    """

    weighting: str = "ncc-exact"
    background: tuple = (0, 0)
    n_samples: int = 192
    n_neighbours: int = 16
    source_positions: str = "star"
    half_width: tuple = (0.6, 0.6, 0.6, 0.6, 0.6, 0.6, 0.0105, 0.0105, 0.0105)
    levels: int = 3
    shrink: float = 0.5
    reg: float = 1e-3
    roi_support_fraction: float | None = 0.3
    safeguard: bool = True
    virtual_oversample: int = 1
    shift_search_px: float = 0.0
    chunk_views: int = 8
    seed: int = 0
    prior_sigma: tuple | None = None
    draws: int = 1

    def __post_init__(self):
        if self.weighting not in WEIGHTINGS:
            raise ValueError(f"weighting must be one of {WEIGHTINGS}")
        if len(self.half_width) != 9:
            raise ValueError("half_width needs 9 values (mm x6, rad x3)")
        if self.n_neighbours < 2 or self.n_neighbours > self.n_samples:
            raise ValueError("need 2 <= n_neighbours <= n_samples")
        if not (isinstance(self.draws, (int, np.integer)) and self.draws >= 1):
            raise ValueError("draws must be a whole number >= 1")
        if self.prior_sigma is not None and (len(self.prior_sigma) != 9 or not all(x > 0 for x in self.prior_sigma)):
            raise ValueError("prior_sigma needs 9 positive values (mm x6, rad x3)")

    @property
    def prior_inv_var(self):
        """Inverse prior variances (9,), or None without a prior."""
        return None if self.prior_sigma is None else 1.0 / np.asarray(self.prior_sigma, np.float64) ** 2


def _shift_search(measured, nominal, params, vol, grid, config, mask_all):
    """Exhaustive search of the detector translation (d_u, d_v) within ``config.shift_search_px``.

    Whole-pixel steps, then half-pixel steps around the best; a view moves only where a shift
    scores better (with ``config.prior_sigma``: by posterior) than its current pose. Captures
    large in-plane errors, and the aliased optimum one period away on periodic anatomy (ribs,
    electrode layers), before the local LLE sampling, whose random samples rarely land in the
    right period.
    """
    R = int(np.ceil(config.shift_search_px))
    pitch = np.array([nominal.col_pitch_mm, nominal.row_pitch_mm])
    along_v = bool(observable_params(nominal)[4])  # a fan beam searches d_u alone
    out = params.copy()
    for step, reach in ((1.0, R), (0.5, 1)):
        k = np.arange(-reach, reach + 1) * step
        du, dv = (a.ravel() for a in np.meshgrid(k, k if along_v else np.zeros(1), indexing="ij"))
        offsets = np.stack([du, dv], axis=1) * pitch  # mm, includes (0, 0)
        S = offsets.shape[0]
        margin = (int(np.ceil(reach * step)) + 2, int(np.ceil(reach * step)) + 2)
        for idx in view_chunks(usable_views(mask_all), config.chunk_views):
            c = idx.size
            sample_params = np.repeat(out[idx][:, None, :], S, axis=1)
            sample_params[:, :, 3:5] += offsets
            image_index = np.repeat(np.arange(c), S)
            mask_c = np.ascontiguousarray(mask_all[idx])
            dist, images, H, n_valid, _ = score_samples(vol, grid, nominal.subset(idx), out[idx], sample_params,
                                                         image_index, measured[idx], mask_c, config, margin)
            centre = S // 2  # the zero offset
            fraction = best_fit_fraction(images, H, image_index, S, dist, measured[idx], mask_c, config)
            dist = ranking(dist, sample_params, n_valid, config, fraction)
            best = np.argmin(dist, axis=1)
            better = dist[np.arange(c), best] < dist[:, centre]
            out[idx[better]] = sample_params[np.flatnonzero(better), best[better]]
    return out


def _view_draws(seed: int, level: int, view_ids, n_src: int, D: int, S: int):
    """The random part of each view's samples: source position indices (c, D, S), sample 0 of
    each set the current one, and uniform detector offsets in [-1, 1] (c, D, S, 6), from one
    generator per view seeded by (seed, level, view id), so any split of the views draws the same."""
    c = len(view_ids)
    a = np.empty((c, D, S), np.int64)
    u = np.empty((c, D, S, 6))
    for k, v in enumerate(view_ids):
        rng = np.random.default_rng((int(seed), int(level), int(v)))
        a[k] = rng.integers(0, n_src, size=(D, S))
        u[k] = rng.uniform(-1.0, 1.0, size=(D, S, 6))
    a[:, :, 0] = 0
    return a, u


@blas_single_threaded
def estimate_views(measured: np.ndarray, nominal: ConeGeometry, params0: np.ndarray, volume: np.ndarray,
                   grid: VolumeGrid, config: LLEConfig = LLEConfig(), valid_mask=None,
                   progress=None, *, support_mask=None, view_ids=None) -> tuple[np.ndarray, dict]:
    """One LLE pass: new 9-DOF parameters (n, 9) of every view, relative to ``nominal``.

    ``measured`` (n, rows, cols) line integrals on ``nominal``'s detector grid; ``params0``
    the current estimate; ``volume`` on ``grid`` the current reconstruction; ``valid_mask``
    (rows, cols) or (n, rows, cols) marks usable pixels (dead pixels and chip gaps False).
    Returns the parameters and a dict with, per level, the mean distance of the best sample
    (``best_distance``), of the chosen estimate (``chosen_distance``, with the safeguard) and,
    with a prior, the median over views of :func:`effective_pixel_fraction`
    (``independent_fraction``).

    A one-row (fan-beam) ``nominal`` estimates only the parameters a fan beam sees
    (:func:`~robot_ct_ros.ct.geometry.observable_params`: in-plane source position, detector
    shift and distance, rotation within the fan plane); the other four keep ``params0``'s values.

    Every view draws its samples from its own generator, seeded by (``config.seed``, level, view
    id), and nothing couples the views, so a block of views estimated alone (``view_ids``: the
    block's indices in the whole scan, default 0..n-1; ``support_mask``: the whole scan's ROI
    support for the block's views, see :func:`~robot_ct_ros.ct.calibration.masks.estimator_inputs`)
    gets what the whole scan gets for those views (:mod:`robot_ct_ros.ct.calibration.distributed`).
    ``info["per_view"]`` holds the per-view values the summaries are taken over
    (:func:`~robot_ct_ros.ct.calibration.masks.summarise_views`).
    """
    n = nominal.n_views
    measured, params, _, mask_all = estimator_inputs(measured, nominal, params0, valid_mask, grid,
                                                     config.roi_support_fraction, support_mask)
    view_ids = np.arange(n) if view_ids is None else np.asarray(view_ids, np.int64)
    vol = as_model(volume)
    metric = "l2" if config.weighting == "l2" else "ncc"
    measured = np.where(mask_all, measured, np.float32(0.0))  # dead pixels may be nan or inf: see score_warped
    if config.shift_search_px > 0:
        params = _shift_search(measured, nominal, params, vol, grid, config, mask_all)
    h0 = np.asarray(config.half_width, dtype=np.float64) * observable_params(nominal)  # held parameters: no width
    views = usable_views(mask_all)  # the others keep their geometry (they lean on the prior)
    per_view = {"best_distance": ("mean", float("nan"), []), "chosen_distance": ("mean", None, []),
                "independent_fraction": ("median", None, [])}
    info = {"skipped_views": [int(v) for v in view_ids[np.setdiff1d(np.arange(n), views)]], "per_view": per_view}
    for level in range(config.levels):
        h = h0 * config.shrink ** level
        src_offsets = source_offsets(config.source_positions, h)
        n_src = src_offsets.shape[0]
        best_d, chosen_d, fractions = [], [], []
        for idx in view_chunks(views, config.chunk_views):
            c = idx.size
            nom_c, g = nominal.subset(idx), params[idx]
            margin = virtual_margin_px(nom_c, h)  # the chunk's own: nothing couples the chunks
            # one ray-cast per source position; samples: a source position each, detector pose
            # uniform in the box; sample 0 = the current estimate
            src_params = np.repeat(g, n_src, axis=0)
            src_params[:, 0:3] += np.tile(src_offsets, (c, 1))
            # config.draws independent sets of S samples, scored together: set d is samples
            # d * S ... d * S + S - 1, each with the current estimate first
            S, D = config.n_samples, config.draws
            a, u = _view_draws(config.seed, level, view_ids[idx], n_src, D, S)
            delta = np.zeros((c, D, S, 9))
            delta[..., 0:3] = src_offsets[a]
            delta[..., 3:9] = u * h[3:9]
            delta[:, :, 0, 3:9] = 0.0
            sample_params = (g[:, None, None, :] + delta).reshape(c, D * S, 9)
            image_index = (np.arange(c)[:, None] * n_src + a.reshape(c, D * S)).reshape(-1)
            mask_c = np.ascontiguousarray(mask_all[idx])
            data_dist, images, H, n_valid, virtual = score_samples(
                vol, grid, nom_c, src_params, sample_params, image_index, measured[idx], mask_c, config, margin)
            fraction = best_fit_fraction(images, H, image_index, D * S, data_dist, measured[idx], mask_c, config)
            dist = ranking(data_dist, sample_params, n_valid, config, fraction)
            if fraction is not None:
                fractions.append(fraction)
            # one embedding per set, in that set's K nearest samples; the sets' estimates averaged
            K = config.n_neighbours
            near = (np.argpartition(dist.reshape(c, D, S), K - 1, axis=2)[:, :, :K]
                    + (np.arange(D) * S)[None, :, None]).reshape(c, D * K)
            flat_sel = (np.arange(c)[:, None] * (D * S) + near).reshape(-1)
            neigh, on_virtual = warp_projections(images, H[flat_sel], image_index[flat_sel], nominal.n_rows,
                                                 nominal.n_cols)
            m = (mask_all[idx][:, None] & on_virtual.reshape(c, D, K, *nominal.det_shape).all(axis=2)).reshape(
                c * D, *nominal.det_shape)
            g_near = np.take_along_axis(sample_params, near[:, :, None], axis=1).reshape(c * D, K, 9)
            w = lle_weights(np.repeat(measured[idx].reshape(c, -1), D, axis=0), neigh.reshape(c * D, K, -1),
                            config.weighting, mask=m.reshape(c * D, -1), reg=config.reg,
                            basis=None if metric == "l2" else background_basis(m, *config.background).reshape(
                                c * D, -1, m[0].size),
                            prior=None if fraction is None else (
                                g_near, config.prior_inv_var / np.repeat(fraction, D)[:, None]))
            g_new = np.einsum("ck,ckj->cj", w, g_near).reshape(c, D, 9)
            # an embedding may extrapolate; never beyond the sampled box (stability under model error)
            g_new = np.clip(g_new, (g - h)[:, None], (g + h)[:, None]).mean(axis=1)
            rows = np.arange(c)
            best = np.argmin(dist, axis=1)  # by posterior with a prior
            d_best = data_dist[rows, best]
            if config.safeguard:
                if n_src == 1:  # the samples' common source: the ray-cast renders g_new by homography too
                    d_new = score_warped(images, virtual, nom_c, g_new[:, None, :], np.arange(c), measured[idx],
                                          mask_c, config)[0][:, 0]
                else:
                    p_new = project(vol, grid, nom_c.perturbed(g_new))
                    d_new = view_distances(p_new, measured[idx], mask_c, metric, config.background)
                if config.prior_sigma is None:
                    worse = ~(d_new <= d_best)
                else:  # compare posteriors, on the same data reference
                    both = ranking(np.stack([d_best, d_new], axis=1),
                                    np.stack([sample_params[rows, best], g_new], axis=1),
                                    np.stack([n_valid[rows, best], mask_c.reshape(c, -1).sum(axis=1)], axis=1),
                                    config, fraction, np.min(data_dist, axis=1))
                    worse = ~(both[:, 1] <= both[:, 0])
                g_new[worse] = sample_params[rows, best][worse]
                d_new = np.where(worse, d_best, d_new)
                chosen_d.append(d_new)
            params[idx] = g_new
            best_d.append(d_best)
        for key, values in (("best_distance", best_d), ("chosen_distance", chosen_d),
                            ("independent_fraction", fractions)):
            per_view[key][2].append(np.concatenate(values) if values else np.zeros(0))
        info.update(summarise_views(per_view))
        if progress is not None:
            progress(level, config.levels, info)
    return params, info


DEFAULT_BACKGROUND = (0, 0)
"""Smooth background ignored by the NCC weightings by default: (0, 0) = offset and gain only,
the metric as published. A quadratic one, (2, 2), also absorbs the bowl a truncated object adds;
against the SIRT-consistent estimation volumes the published one did better on the mouse scan and
worse on the battery scan (docs/calibration.md, "Three weightings")."""


EMBEDDING_SETTINGS = {"l2": {"n_neighbours": 24, "reg": 1e-5}, "ncc-exact": {"n_neighbours": 24, "reg": 1e-5}}
"""Neighbours and Gram regularisation per weighting where they differ from :class:`LLEConfig`'s
(16, 1e-3). The solved weightings embed in more neighbours with a weaker ridge: the ridge pulls
the weights towards the neighbours' centroid, i.e. the weakly seen parameters (scale,
perspective) towards the current estimate, and with the robots' accuracy as prior the ridge
need not hold them any more. The published ``ncc`` closed form has no ridge and keeps 16
(docs/calibration.md, "Three weightings"; the measurements are listed there as open)."""


COARSE_SAMPLES = 96


DRAWS = 2
"""Samples per view and level of the coarse pass (:class:`LLEConfig` default 192), and the
independent sample sets per level whose embeddings are averaged (:attr:`LLEConfig.draws`) on
both levels. Each set is one draw of the random sampling; its embedding carries that draw's
noise, which more samples in one set do not average out (they only tighten the K nearest
ones), while a second set is scored against the same ray-casts, so it costs only its
homography scoring and weights (docs/calibration.md, "Sample sets")."""


def default_lle_configs(weighting: str, seed: int = 0, background=DEFAULT_BACKGROUND,
                        prior_sigma=None, n_neighbours: int | None = None,
                        reg: float | None = None) -> tuple[LLEConfig, LLEConfig]:
    """Coarse (binned, wide box) and fine (full size, narrow box) LLE settings. ``n_neighbours``
    and ``reg`` replace the weighting's own (:data:`EMBEDDING_SETTINGS`) where given."""
    prior = None if prior_sigma is None else tuple(float(x) for x in prior_sigma)
    embedding = dict(EMBEDDING_SETTINGS.get(weighting, {}))
    if n_neighbours is not None:
        embedding["n_neighbours"] = int(n_neighbours)
    if reg is not None:
        embedding["reg"] = float(reg)
    coarse = LLEConfig(weighting=weighting, levels=3, seed=seed, background=tuple(background), shift_search_px=4,
                       prior_sigma=prior, n_samples=COARSE_SAMPLES, draws=DRAWS, **embedding)
    fine = LLEConfig(weighting=weighting, levels=2, seed=seed + 1, background=tuple(background),
                     half_width=tuple(np.asarray(coarse.half_width) * 0.25), prior_sigma=prior, draws=DRAWS,
                     **embedding)
    return coarse, fine


MAX_NARROWING = 2
"""Outer iterations after which the LLE search box stops shrinking: halving it without end leaves
the box smaller than the estimator's own scatter (docs/calibration.md, "Stopping and narrowing")."""


def narrowed(config: LLEConfig, iteration: int) -> LLEConfig:
    """The search box of outer iteration ``iteration`` (0-based): halved each time up to
    :data:`MAX_NARROWING` times, so later iterations refine around the estimate instead of
    re-exploring the whole range."""
    return replace(config, half_width=tuple(np.asarray(config.half_width) * 0.5 ** min(iteration, MAX_NARROWING)),
                   seed=config.seed + 7919 * iteration)
