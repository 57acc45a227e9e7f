"""Benchmark: where the interior scan's remaining error comes from (the exterior model's alternation).

The scan is bench_interior.py's (a 41 mm neck through a 6.5 mm field of view, RTK's exact line
integrals, photon counting, rotation axis +y), at one robot error. The estimator is
ncc-lle-exact with the exterior model's settings (no ROI support mask), the prior at the
robots' accuracy; "coarse" is one pass on 2 x 2 binned data against a volume reconstructed from
them, "fine" then one full-size pass against a full-size volume, as the loop's first
iteration does. Each volume is the exterior model (calibration.exterior.reconstruct_with_exterior:
the ROI grid and a 0.5 mm exterior grid 30 mm wide, joint non-negative OS-SIRT) reconstructed
from the measured data with a geometry chosen here, so the tables separate what the data term
can do from what the reconstruction feeds it:

1. the same estimator against volumes reconstructed with the true, a half-corrected and the
   nominal geometry, and how well each volume explains the data (projection RMSE and NCC);
2. ROI and exterior parts swapped between the true- and nominal-geometry volumes;
3. held-out volumes (views estimated against a volume their own data did not build, in k folds);
4. the exterior grid's voxel and SIRT passes;
5. the whole loop (calibration.calibrate, exterior on) over more outer iterations;
6. candidates against the volume's pull: total variation lowered in the exterior, the ROI or both
   (an edge-keeping object prior), the pixels the exterior's edges dominate left out, the update
   extrapolated;
7. held-out volumes as in 3, but reconstructed with the true geometry: what the other views'
   data, placed exactly, tell about a view;
8. the same scan with 360 and 720 views;
9. the same scan with smooth robot errors of the same size (harmonics 1-3 of the orbit): the loop
   with independent per-view estimates and with the drift model;
10. the loop of table 5 under the fast schedule (4 x 4, then 2 x 2 binned data);
11. data from outside the field of view: the exterior taken from a wide, low-magnification scout
    scan of the whole neck (simulated as the interior scan, with its own robot errors) and held
    fixed, the ROI reconstructed from the interior data that remain;
12. how much of each view's error the estimate recovers in the combinations the ROI sees (the
    projection shifts d + (M - 1) s and the in-plane rotation): slope on the truth, correlation, noise;
13. that absorption undone with a response measured by moving the geometry by known amounts;
14. what the other views' data tell about a view, band by band: volumes from the true geometry without
    the view's fold, on data binned 2, 4 and 8 times, how well they predict the views they did not see and
    where the estimate ends against them; at 180, 360 and 720 views;
15. tables 3 and 7 with each fold's own term (the full volume's reprojection less the held-out
    one's) taken out of the fold's data too, so that the data and the held-out volume hold the same;
16. the ROI grid's voxel (fewer voxels to follow each view's error, less resolution to place it);
17. table 15's leave-out iterated from the nominal geometry, beside the plain alternation;
18. a smooth background (polynomial across the detector) that each view's NCC ignores: the metric high-passed;
19. where in the image each view's placement lies: the detector shift at which the NCC peaks (searched
    exhaustively, no estimator), of the images as they are, normalised locally (windowed NCC, the issue's
    candidate), low-passed or with the residuals weighted robustly, against volumes from the true and the
    nominal geometry, with each view's own data in and held out;
20. table 19's held-out row (the true geometry, the images as they are) over the exterior grid's voxel and
    SIRT passes: whether a finer or a more converged exterior lets the other views place a view better.

``--tables 6`` computes only table 6 and keeps the others from the json already in ``--out``.

Writes ``interior_diagnosis.md`` and ``.json`` into ``--out``.

    .venv/bin/python bench/bench_interior_diagnosis.py --out docs/results     # about 160 min on 2 cores
    .venv/bin/python bench/bench_interior_diagnosis.py --tables 11 --out docs/results   # one table (11: 8 min, 14: 16 min)
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from dataclasses import replace

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from bench_interior import make_scan  # noqa: E402
from scipy import ndimage  # noqa: E402
from robot_ct_ros.ct import calibration  # noqa: E402
from robot_ct_ros.ct import simulation as sim  # noqa: E402
from robot_ct_ros.ct.calibration.exterior import exterior_grid, exterior_support, reconstruct_with_exterior  # noqa: E402
from robot_ct_ros.ct.calibration.lle.estimator import default_lle_configs, estimate_views  # noqa: E402
from robot_ct_ros.ct.calibration.masks import bin_masked  # noqa: E402
from robot_ct_ros.ct.calibration.model import VolumeParts, project  # noqa: E402
from robot_ct_ros.ct.calibration.volume import estimation_grid, projection_consistency  # noqa: E402
from robot_ct_ros.ct.iterative import sirt  # noqa: E402
from robot_ct_ros.ct.metrics import reprojection_error, roi_points  # noqa: E402
from robot_ct_ros.ct.projector import forward_project  # noqa: E402
from robot_ct_ros.ct.reconstruction import fdk  # noqa: E402
from robot_ct_ros.ct.rtk_bridge import rtk_ellipsoid_projections  # noqa: E402
from robot_ct_ros.ct.trajectory import SeedSystem, circular_scan  # noqa: E402
from robot_ct_ros.jobs.figures import markdown_table  # noqa: E402

HALF_WIDTH_MM = 30.0
"""The exterior grid's reach from the ROI centre, as in bench_interior's exterior variant (the 41 mm body)."""


def table(rows: list) -> str:
    """The rows (dicts with the same keys) as a Markdown table (figures.markdown_table, a column per key)."""
    return markdown_table(rows, [(k, k, "{:.5g}" if isinstance(v, float) else "{}") for k, v in rows[0].items()])


class Study:
    """The scan, the estimator's two levels and the exterior model's reconstruction, at chosen geometries."""

    def __init__(self, sc, settings: calibration.CalibrationSettings):
        self.sc, self.settings = sc, settings
        self.exterior_iterations = settings.plan(exterior=True)["exterior_iterations"]  # the exterior model's passes
        self.n = sc.nominal.n_views
        self.points = roi_points(sc.grid)
        coarse, fine = default_lle_configs("ncc-exact", prior_sigma=settings.prior_sigma)
        self.coarse, self.fine = (replace(c, roi_support_fraction=None) for c in (coarse, fine))
        self.grid_f = estimation_grid(sc.grid, settings.padding)
        self.grid_c = self.grid_f.binned(2)
        self.li_c, self.mask_c = bin_masked(sc.li, sc.mask, 2)
        self.nom_c = sc.nominal.binned(2)
        self.true_p = sc.true.params_relative_to(sc.nominal)
        self._bands = {}
        self._more_views = {}

    def with_views(self, n: int, args) -> "Study":
        """This study, or the same scan with ``n`` views (``args``: the scan arguments; same photons per view),
        made once and kept for the tables that use it."""
        if n == self.n:
            return self
        if n not in self._more_views:
            det = tuple(int(x) for x in args.det.lower().split("x"))
            self._more_views[n] = Study(make_scan(args.sigma, views=n, det=det, axis="y", seed=args.seed,
                                                  nxy=args.nxy, say=lambda m: None), self.settings)
        return self._more_views[n]

    def error_px(self, params) -> float:
        return reprojection_error(self.sc.nominal.perturbed(params), self.sc.true, self.points)["mean_px"]

    def level(self, level):
        """(line integrals, nominal geometry, grid, valid mask, LLE configuration) of ``level``: "coarse"
        (2 x 2 binned data, the loop's coarse configuration), "fine" (full size, the fine one), or a binning
        factor (the data binned so, the coarse configuration with one LLE level: that band alone)."""
        if level == "coarse":
            return self.li_c, self.nom_c, self.grid_c, self.mask_c, self.coarse
        if level == "fine":
            return self.sc.li, self.sc.nominal, self.grid_f, self.sc.mask, self.fine
        if level not in self._bands:
            li, mask = bin_masked(self.sc.li, self.sc.mask, level)
            self._bands[level] = (li, self.sc.nominal.binned(level), self.grid_f.binned(level), mask,
                                  replace(self.coarse, levels=1))
        return self._bands[level]

    def volume(self, level, params, views=None, *, voxel_mm=None, iterations=None,
               after_pass=None, grid=None) -> VolumeParts:
        """The exterior model reconstructed from the level's data (``views`` of them) with the geometry ``params``;
        ``grid`` replaces the level's ROI grid."""
        s = self.settings
        li, nom, grid_l, mask, _ = self.level(level)
        grid = grid_l if grid is None else grid
        geom = nom.perturbed(params)
        if views is not None:
            li, geom, mask = li[views], geom.subset(views), mask[views]
        return reconstruct_with_exterior(li, geom, grid, mask, voxel_mm=voxel_mm or s.exterior_voxel_mm,
                                         half_width_mm=HALF_WIDTH_MM, iterations=iterations or self.exterior_iterations,
                                         subsets=s.exterior_subsets, after_pass=after_pass)

    def estimate(self, level, params, volume, views=None, *, mask=None, cfg=None, measured=None, grid=None):
        """One estimation pass of ``views`` (default all) from ``params`` against ``volume``; ``mask``
        (the level's shape) replaces the level's valid-pixel mask, ``cfg`` the level's LLE configuration,
        ``measured`` (``views``' data at the level) the level's data of those views, ``grid`` the level's ROI
        grid (the one ``volume`` was built on)."""
        views = np.arange(self.n) if views is None else views
        li, nom, grid_l, mask_l, cfg_l = self.level(level)
        grid = grid_l if grid is None else grid
        mask = mask_l if mask is None else mask
        cfg = cfg_l if cfg is None else cfg
        out = np.array(params, float)
        data = li[views] if measured is None else np.asarray(measured, np.float32)
        out[views], _ = estimate_views(data, nom.subset(views), out[views], volume, grid, cfg, mask[views],
                                       view_ids=views)
        return out


def table_reconstruction_geometry(st: Study, say) -> list:
    """1: the estimator against volumes reconstructed with the true, a half-corrected and the nominal geometry."""
    rows = []
    for name, frac in (("true", 1.0), ("half-corrected", 0.5), ("nominal", 0.0)):
        t0 = time.perf_counter()
        p_rec = frac * st.true_p
        p = st.estimate("coarse", np.zeros((st.n, 9)), st.volume("coarse", p_rec))
        e_coarse = st.error_px(p)
        vol_f = st.volume("fine", p_rec)
        p = st.estimate("fine", p, vol_f)
        rmse, ncc = projection_consistency(vol_f, st.grid_f, st.sc.nominal.perturbed(p_rec), st.sc.li, st.sc.mask)
        rows.append({"volume reconstructed with": f"the {name} geometry", "its error (px)": round(st.error_px(p_rec), 3),
                     "projection RMSE": round(float(rmse), 5), "projection NCC": round(float(ncc), 5),
                     "estimate, coarse (px)": round(e_coarse, 3), "estimate, fine (px)": round(st.error_px(p), 3),
                     "wall time (s)": round(time.perf_counter() - t0, 1)})
        say(f"  1. {rows[-1]}")
    return rows


def table_parts(st: Study, say) -> list:
    """2: the ROI and the exterior part each from the true- or the nominal-geometry volume (coarse level)."""
    built = {k: st.volume("coarse", p) for k, p in (("true", st.true_p), ("nominal", np.zeros((st.n, 9))))}
    rows = []
    for roi in ("true", "nominal"):
        for ext in ("true", "nominal"):
            vol = VolumeParts((built[roi].parts[0], built[ext].parts[1]))
            p = st.estimate("coarse", np.zeros((st.n, 9)), vol)
            rows.append({"ROI part from": f"the {roi} geometry", "exterior part from": f"the {ext} geometry",
                         "estimate, coarse (px)": round(st.error_px(p), 3)})
            say(f"  2. {rows[-1]}")
    return rows


def table_held_out(st: Study, say, folds=(1, 4, 12), geometry: str = "nominal") -> list:
    """3 (7 with ``geometry`` "true"): each view estimated against a volume reconstructed with that
    geometry without its fold (coarse level)."""
    rows = []
    p_rec = st.true_p if geometry == "true" else np.zeros((st.n, 9))
    for k in folds:
        t0 = time.perf_counter()
        p = np.zeros((st.n, 9))
        for f in range(k):
            test = np.arange(f, st.n, k)
            train = np.setdiff1d(np.arange(st.n), test) if k > 1 else None
            p = st.estimate("coarse", p, st.volume("coarse", p_rec, train), test)
        rows.append({"volume of each view": "all views (its own included)" if k == 1 else
                     f"the other views ({k} interleaved folds, 1/{k} left out)",
                     "estimate, coarse (px)": round(st.error_px(p), 3),
                     "wall time (s)": round(time.perf_counter() - t0, 1)})
        say(f"  {7 if geometry == 'true' else 3}. {rows[-1]}")
    return rows


def table_left_out(st: Study, say, folds: int = 12, geometries=("true", "nominal")) -> list:
    """15: tables 3 and 7 with each fold's own term taken out of its data too. A held-out volume lacks what the
    fold's own data put into the full one; the view's data keep it, and the registration follows that mismatch. The
    own term is the full volume's reprojection minus the held-out volume's, both through the geometry they were
    built with (the part of the views' data their own fold explained); the views' data less it are registered
    against the held-out volume (coarse level)."""
    li, nom, grid, _, _ = st.level("coarse")
    zero = np.zeros((st.n, 9))
    rows = []
    for name in geometries:
        t0 = time.perf_counter()
        p_rec = st.true_p if name == "true" else zero
        geom = nom.perturbed(p_rec)
        full = st.volume("coarse", p_rec)
        p_all = st.estimate("coarse", zero, full)
        p_held, p_left = zero.copy(), zero.copy()
        for f in range(folds):
            test = np.arange(f, st.n, folds)
            held = st.volume("coarse", p_rec, np.setdiff1d(np.arange(st.n), test))
            p_held = st.estimate("coarse", p_held, held, test)
            own = project(full, grid, geom.subset(test)) - project(held, grid, geom.subset(test))
            p_left = st.estimate("coarse", p_left, held, test, measured=li[test] - own)
        rows.append({"volumes reconstructed with": f"the {name} geometry",
                     "all views, own data in (px)": round(st.error_px(p_all), 3),
                     f"held out ({folds} folds), data as measured (px)": round(st.error_px(p_held), 3),
                     "held out, own term taken out of the data too (px)": round(st.error_px(p_left), 3),
                     "wall time (s)": round(time.perf_counter() - t0, 1)})
        say(f"  15. {rows[-1]}")
    return rows


def table_roi_voxel(st: Study, say, binnings=(1, 2, 3)) -> list:
    """16: the ROI grid's voxel. A coarser ROI has fewer voxels with which to follow each view's error, and
    resolves less of what places the views (coarse level, one pass from the nominal geometry, against volumes
    from the nominal and from the true geometry)."""
    zero = np.zeros((st.n, 9))
    grid_c = st.level("coarse")[2]
    rows = []
    for b in binnings:
        grid = grid_c.binned(b) if b > 1 else grid_c
        t0 = time.perf_counter()
        est = {name: st.error_px(st.estimate("coarse", zero, st.volume("coarse", p_rec, grid=grid), grid=grid))
               for name, p_rec in (("nominal", zero), ("true", st.true_p))}
        rows.append({"ROI voxel (mm)": round(float(grid.voxel_size_mm[0]), 4), "ROI grid (z, y, x)": str(grid.shape_zyx),
                     "estimate, volume from the nominal geometry (px)": round(est["nominal"], 3),
                     "estimate, volume from the true geometry (px)": round(est["true"], 3),
                     "wall time (s)": round(time.perf_counter() - t0, 1)})
        say(f"  16. {rows[-1]}")
    return rows


def table_left_out_iterated(st: Study, say, rounds: int = 4, folds: int = 12) -> list:
    """17: table 15's leave-out (each fold registered against a volume its own views did not build, with the fold's
    own term taken out of its data) iterated from the nominal geometry, each round's volumes built with the
    previous round's estimate, beside the plain alternation (every view's data in) from the same start; with the
    u shift's slope on the truth (table 12) after each round (coarse level)."""
    li, nom, grid, _, _ = st.level("coarse")
    p_left, p_plain = np.zeros((st.n, 9)), np.zeros((st.n, 9))
    rows = []
    t0 = time.perf_counter()
    for r in range(1, rounds + 1):
        geom = nom.perturbed(p_left)
        full = st.volume("coarse", p_left)
        p_next = p_left.copy()
        for f in range(folds):
            test = np.arange(f, st.n, folds)
            held = st.volume("coarse", p_left, np.setdiff1d(np.arange(st.n), test))
            own = project(full, grid, geom.subset(test)) - project(held, grid, geom.subset(test))
            p_next = st.estimate("coarse", p_next, held, test, measured=li[test] - own)
        p_left = p_next
        p_plain = st.estimate("coarse", p_plain, st.volume("coarse", p_plain))
        rows.append({"round": r, "left out, own term out (px)": round(st.error_px(p_left), 3),
                     "left out: u-shift slope": u_shift_slope(st, p_left),
                     "every view in (px)": round(st.error_px(p_plain), 3),
                     "every view in: u-shift slope": u_shift_slope(st, p_plain),
                     "elapsed (s)": round(time.perf_counter() - t0, 1)})
        say(f"  17. {rows[-1]}")
    return rows


def table_background(st: Study, say, orders=((0, 0), (1, 1), (2, 2), (4, 4))) -> list:
    """18: the smooth background each view's NCC ignores (``LLEConfig.background``: polynomial orders along columns
    and rows; (0, 0), the default, ignores offset and gain only), a high-pass of the metric that drops what varies
    slowly across the detector, the exterior's share among it (coarse level, one pass from the nominal geometry,
    against the volumes from the nominal and from the true geometry), with the u shift's slope on the truth."""
    zero = np.zeros((st.n, 9))
    vols = {"nominal": st.volume("coarse", zero), "true": st.volume("coarse", st.true_p)}
    rows = []
    for order in orders:
        t0 = time.perf_counter()
        row = {"background ignored (orders along u, v)": str(tuple(order))}
        for name, vol in vols.items():
            p = st.estimate("coarse", zero, vol, cfg=replace(st.coarse, background=tuple(order)))
            row[f"estimate, volume from the {name} geometry (px)"] = round(st.error_px(p), 3)
            row[f"u-shift slope, {name}"] = u_shift_slope(st, p)
        row["wall time (s)"] = round(time.perf_counter() - t0, 1)
        rows.append(row)
        say(f"  18. {rows[-1]}")
    return rows


FILTERS = (("as they are", None, 0.0), ("normalised locally (windowed NCC)", "local", 1.5),
           ("normalised locally (windowed NCC)", "local", 6.0), ("low-passed", "low", 1.0), ("low-passed", "low", 4.0),
           ("as they are, residuals weighted robustly (Tukey)", "robust", 4.685))
"""Table 19's image filters: (name, kind, parameter): the Gaussian sigma in pixels of the level's data, or for
"robust" the Tukey biweight's cut in robust standard deviations of the residual (:func:`shift_optimum`)."""

ROBUST_ROUNDS = 3
"""Reweighting rounds of table 19's robust metric."""


def filtered(image, mask, kind, sigma_px: float) -> np.ndarray:
    """``image`` (rows, cols) as table 19's metric sees it, over the valid pixels ``mask`` (normalised
    convolution, so dead pixels and chip gaps do not leak in): as it is (``kind`` None), low-passed by a
    Gaussian of ``sigma_px`` ("low"), or normalised locally ("local"): less its local mean, divided by its
    local standard deviation, both Gaussian-weighted over ``sigma_px`` (so that every edge counts alike, however
    strong, and the smooth background drops out)."""
    image = np.asarray(image, np.float64)
    if kind is None:
        return image.copy()
    m = np.asarray(mask, np.float64)
    weight = ndimage.gaussian_filter(m, sigma_px) + 1e-12
    mean = ndimage.gaussian_filter(image * m, sigma_px) / weight
    if kind == "low":
        return mean
    if kind != "local":
        raise ValueError(f"unknown filter {kind!r}")
    dev = (image - mean) * m
    var = ndimage.gaussian_filter(dev * dev, sigma_px) / weight
    return dev / np.sqrt(var + 1e-2 * np.median(var[m > 0]))  # the floor keeps flat regions from blowing up


def shift_optimum(measured, model, mask, kind=None, sigma_px: float = 0.0, reach_px: float = 4.0,
                  border_px: int = 6) -> np.ndarray:
    """Per view, the shift (cols, rows) in pixels that carries ``model`` (n, rows, cols) onto ``measured`` best:
    the maximum of their NCC after :func:`filtered`, over the valid pixels of ``mask`` at least ``border_px``
    from the edge, searched exhaustively on a 0.5 px grid within ``reach_px``, then on a 0.1 px grid around
    its best (linear interpolation). No estimator, no prior: where the metric itself places each view.

    ``kind`` "robust": the images as they are, then :data:`ROBUST_ROUNDS` rounds that weight each pixel by
    Tukey's biweight of its residual at the best shift so far (the data less the shifted model's least-squares
    gain and offset; cut at ``sigma_px`` robust standard deviations, 1.4826 x the median absolute residual) and
    search again, within 1 px of that best, on 0.25 and 0.1 px grids: a metric that ignores the pixels the model
    fails to predict (structure in the data that the volume does not hold), whatever their cause."""
    def ncc(a, b, m, w=None):
        if w is None:
            a, b = a[m] - a[m].mean(), b[m] - b[m].mean()
            return float(a @ b) / max(float(np.sqrt((a @ a) * (b @ b))), 1e-300)
        a, b, w = a[m], b[m], w[m]
        a, b = a - (w @ a) / w.sum(), b - (w @ b) / w.sum()
        return float((w * a) @ b) / max(float(np.sqrt(((w * a) @ a) * ((w * b) @ b))), 1e-300)

    robust = kind == "robust"
    if robust:
        kind, cut = None, sigma_px

    out = np.zeros((len(measured), 2))
    for i, (data, ref, valid) in enumerate(zip(measured, model, mask)):
        valid = np.asarray(valid, bool)
        inner = valid.copy()
        b = min(border_px, valid.shape[0] // 4, valid.shape[1] // 4)  # a small test detector keeps its middle half
        if b > 0:
            inner[:b], inner[-b:], inner[:, :b], inner[:, -b:] = False, False, False, False
        target = filtered(data, valid, kind, sigma_px)

        def moved(d):
            return filtered(ndimage.shift(ref, (d[1], d[0]), order=1, mode="nearest"), valid, kind, sigma_px)

        def search(best, steps, weight=None):
            for step, reach in steps:
                grid = np.arange(-reach, reach + step / 2, step)
                cands = [best + (du, dv) for du in grid for dv in grid]
                best = cands[int(np.argmax([ncc(target, moved(d), inner, weight) for d in cands]))]
            return best

        best = search(np.zeros(2), ((0.5, reach_px), (0.1, 0.5)))
        for _ in range(ROBUST_ROUNDS if robust else 0):
            model_px = moved(best)[inner]
            fit = np.stack([model_px, np.ones_like(model_px)], 1)
            residual = target[inner] - fit @ np.linalg.lstsq(fit, target[inner], rcond=None)[0]
            scaled = residual / (cut * 1.4826 * np.median(np.abs(residual)) + 1e-300)
            weight = np.zeros_like(target)
            weight[inner] = np.where(np.abs(scaled) < 1.0, (1.0 - scaled ** 2) ** 2, 0.0)
            best = search(best, ((0.25, 1.0), (0.1, 0.3)), weight)
        out[i] = best
    return out


def table_metric_optimum(st: Study, say, folds: int = 12, filters=FILTERS) -> list:
    """19: where in the image each view's placement lies. Per view, the detector shift at which the NCC of the data
    and the volume's reprojection (through the nominal geometry) peaks (:func:`shift_optimum`, exhaustive), of the
    images as they are, normalised locally, low-passed or robustly weighted (:data:`FILTERS`), against the
    volumes from the true and from the nominal geometry, with every view's data in and with each view's fold held
    out (``folds`` interleaved): slope on the truth's projection shift (table 12's combinations), scatter about slope x truth,
    and the RMS distance from the truth, px of the full-size detector (coarse level)."""
    _, nom, grid, _, _ = st.level("coarse")
    rows = []
    for name, p_rec in (("true", st.true_p), ("nominal", np.zeros((st.n, 9)))):
        for held_out in (False, True):
            t0 = time.perf_counter()
            model = (held_out_model(st, p_rec, folds)[0] if held_out
                     else project(st.volume("coarse", p_rec), grid, nom))
            built_s = time.perf_counter() - t0
            for label, kind, sigma in filters:
                t0 = time.perf_counter()
                row = {"volume from": f"the {name} geometry",
                       "each view's data": f"held out ({folds} folds)" if held_out else "in",
                       "images": (label if kind is None else f"{label}, cut {sigma:g}" if kind == "robust"
                                  else f"{label}, sigma {sigma:g} px"),
                       **shift_rows(st, measured_shifts(st, model, kind, sigma)),
                       "search (s)": round(time.perf_counter() - t0, 1)}
                rows.append(row)
                say(f"  19. {rows[-1]} (volumes built in {built_s:.1f} s)")
    return rows


def held_out_model(st: Study, p_rec, folds: int, **volume_args):
    """Each view's reprojection, through the nominal geometry, of the coarse volume built with ``p_rec`` from the
    views outside its fold (``folds`` interleaved), and the held-out views' projection NCC with the volume (each
    against its fold's volume through ``p_rec``, the mean over the views); ``volume_args`` go to
    :meth:`Study.volume`."""
    li, nom, grid, mask, _ = st.level("coarse")
    model, ncc = np.empty_like(li), 0.0
    for f in range(folds):
        test = np.arange(f, st.n, folds)
        vol = st.volume("coarse", p_rec, np.setdiff1d(np.arange(st.n), test), **volume_args)
        model[test] = project(vol, grid, nom.subset(test))
        ncc += projection_consistency(vol, grid, nom.perturbed(p_rec).subset(test), li[test], mask[test])[1] * len(test)
    return model, float(ncc / st.n)


def shift_rows(st: Study, shifts) -> dict:
    """Table 19's columns for the measured projection shifts ``shifts`` (:func:`measured_shifts`): per axis the
    slope on the truth's (table 12's combinations), the scatter about slope x truth and the RMS from the truth, px
    of the full-size detector; and how many views' peaks lie at the search's edge (beyond it the search cannot
    see, so those views' scatter is if anything understated)."""
    est_px, at_edge = shifts
    full_pitch = float(np.mean(st.sc.nominal.col_pitch_mm))
    combos = list(shift_combinations(st).values())
    row = {}
    for k, axis in enumerate("uv"):
        truth = combos[k](st.true_p) / full_pitch
        slope = float(np.polyfit(truth, est_px[:, k], 1)[0])
        row[f"{axis}: slope"] = round(slope, 3)
        row[f"{axis}: scatter (px)"] = round(float(np.std(est_px[:, k] - slope * truth)), 3)
        row[f"{axis}: from the truth (px)"] = round(float(np.sqrt(np.mean((est_px[:, k] - truth) ** 2))), 3)
    row["views at the search's edge"] = int(at_edge)
    return row


def measured_shifts(st: Study, model, kind=None, sigma_px: float = 0.0, reach_px: float = 4.0):
    """The coarse data's projection shift (views, (u, v)) relative to ``model``, px of the full-size detector
    (minus the shift that carries the model onto the data, :func:`shift_optimum` within ``reach_px`` of the
    coarse data), and the number of views whose peak lies at the search's edge along either axis."""
    li, nom, _, mask, _ = st.level("coarse")
    bin_px = float(np.mean(nom.col_pitch_mm)) / float(np.mean(st.sc.nominal.col_pitch_mm))
    found = shift_optimum(li, model, mask, kind, sigma_px, reach_px=reach_px)
    at_edge = int(np.sum(np.any(np.abs(found) >= reach_px + 0.4, axis=1)))  # the fine step reaches 0.5 px past it
    return -found * bin_px, at_edge


def table_held_out_exterior(st: Study, say, folds: int = 12,
                            settings=((1.0, 15), (0.5, 5), (0.5, 15), (0.5, 40), (0.5, 80), (0.25, 15))) -> list:
    """20: table 19's held-out row (volumes from the true geometry without the view's fold, images as they are)
    over the exterior grid's voxel and SIRT passes (``settings``: (voxel mm, passes)), with the held-out views'
    projection NCC: how well the other views, placed exactly, predict a view as the exterior is resolved or
    converged further."""
    rows = []
    for voxel_mm, passes in settings:
        t0 = time.perf_counter()
        model, ncc = held_out_model(st, st.true_p, folds, voxel_mm=voxel_mm, iterations=passes)
        rows.append({"exterior voxel (mm)": voxel_mm, "SIRT passes": passes, "held-out projection NCC": round(ncc, 5),
                     **shift_rows(st, measured_shifts(st, model)), "wall time (s)": round(time.perf_counter() - t0, 1)})
        say(f"  20. {rows[-1]}")
    return rows


def table_exterior_settings(st: Study, say) -> list:
    """4: the exterior grid's voxel and its SIRT passes (volume with the nominal geometry, coarse level)."""
    s = st.settings
    rows = []
    for voxel, its in ((1.0, None), (0.5, None), (0.25, None), (None, 4), (None, 40)):
        vol = st.volume("coarse", np.zeros((st.n, 9)), voxel_mm=voxel, iterations=its)
        p = st.estimate("coarse", np.zeros((st.n, 9)), vol)
        rows.append({"exterior voxel (mm)": voxel or s.exterior_voxel_mm, "SIRT passes": its or st.exterior_iterations,
                     "estimate, coarse (px)": round(st.error_px(p), 3)})
        say(f"  4. {rows[-1]}")
    return rows


def tv_step(weight: float, steps: int = 20, parts=(1,)):
    """An ``after_pass`` (calibration.exterior.joint_sirt) that lowers the isotropic total variation of
    the model's ``parts`` (0: the ROI, 1: the exterior) by ``steps`` normalised gradient steps each,
    each step ``weight`` times as long as the pass changed that part (the ASD-POCS rule), keeping it
    non-negative and within its support."""

    def grad(x):
        g = [np.diff(x, axis=a, append=np.take(x, [-1], axis=a)) for a in range(3)]
        norm = np.sqrt(sum(c * c for c in g) + np.float32(1e-12))
        g = [c / norm for c in g]
        div = sum(c - np.roll(c, 1, axis=a) for a, c in enumerate(g))
        for a, c in enumerate(g):  # the first slice has no backward neighbour
            idx = [slice(None)] * 3
            idx[a] = 0
            div[tuple(idx)] += np.roll(c, 1, axis=a)[tuple(idx)]
        return -div

    def lower(x, before):
        support = (x > 0) | (before > 0)
        length = float(np.linalg.norm(x - before))
        for _ in range(steps):
            g = grad(x) * support
            n = float(np.linalg.norm(g))
            if n == 0.0:
                break
            x -= np.float32(weight * length / n) * g
            np.maximum(x, 0.0, out=x)

    def after_pass(xs, before):
        for part in parts:
            lower(xs[part], before[part])

    return after_pass


def table_candidates(st: Study, say) -> list:
    """6: ways to keep the data term from following the volume's geometry, against the volumes from the
    true and from the nominal geometry (coarse level): total variation lowered in the exterior, the ROI or
    both, pixels the exterior's edges dominate left out, and the update extrapolated (the estimate moves a
    fraction of the way)."""
    zero = np.zeros((st.n, 9))
    geoms = {"true": st.true_p, "nominal": zero}
    plain = {k: st.volume("coarse", p) for k, p in geoms.items()}
    rows = []

    def row(name, errors):
        rows.append({"candidate": name} | {f"volume from the {k} geometry (px)": (None if e is None else round(e, 3))
                                           for k, e in errors.items()})
        say(f"  6. {rows[-1]}")

    row("as the loop does (baseline)", {k: st.error_px(st.estimate("coarse", zero, v)) for k, v in plain.items()})
    # the exterior alone (an object prior that should not follow each view), then the ROI, where the
    # phantom's edges are sharp and piecewise constant, and both: total variation as the edge-keeping prior
    for parts, name in (((1,), "exterior"), ((0,), "ROI"), ((0, 1), "ROI and exterior")):
        for w in (0.1, 0.2, 0.5):
            row(f"{name} with total variation lowered after each SIRT pass (weight {w:g}, 20 steps)",
                {k: st.error_px(st.estimate("coarse", zero, st.volume("coarse", p, after_pass=tv_step(w, parts=parts))))
                 for k, p in geoms.items()})
    from robot_ct_ros.ct.projector import forward_project

    base = np.ones(st.li_c.shape, bool) if st.mask_c is None else np.asarray(st.mask_c, bool)
    for q in (0.2, 0.4):
        errs = {}
        for k, v in plain.items():
            (ev, eg) = v.parts[1]
            pe = forward_project(ev, eg, st.nom_c.perturbed(geoms[k]))
            edge = np.hypot(*np.gradient(pe, axis=(1, 2)))
            keep = base & (edge < np.quantile(edge, 1 - q, axis=(1, 2), keepdims=True))
            errs[k] = st.error_px(st.estimate("coarse", zero, v, mask=keep))
        row(f"the {q:.0%} of pixels with the exterior's strongest edges left out", errs)
    p = st.estimate("coarse", zero, plain["nominal"])
    for beta in (1.5, 2.0, 3.0):
        row(f"the update from the nominal geometry extrapolated {beta:g} times", {"true": None,
                                                                                  "nominal": st.error_px(beta * p)})
    return rows


def table_views(st: Study, args, say, more=(360, 720)) -> list:
    """8: the same scan with more views (same photons per view), the estimator against volumes from the
    true and from the nominal geometry (coarse level)."""
    rows = []
    for n in (st.n,) + tuple(more):
        t0 = time.perf_counter()
        s = st.with_views(n, args)
        zero = np.zeros((s.n, 9))
        row = {"views": n, "nominal error (px)": round(s.error_px(zero), 3)}
        for name, p in (("true", s.true_p), ("nominal", zero)):
            row[f"estimate against the {name}-geometry volume (px)"] = round(
                s.error_px(s.estimate("coarse", zero, s.volume("coarse", p))), 3)
        row["wall time (s)"] = round(time.perf_counter() - t0, 1)
        rows.append(row)
        say(f"  8. {rows[-1]}")
    return rows


def smooth_errors(sigma: float, views: int, seed: int, harmonics: int = 3) -> np.ndarray:
    """(views, 9) robot errors that vary smoothly over the orbit: harmonics 1..``harmonics`` of the view
    angle with random coefficients, each parameter scaled to ``sigma`` mm / deg RMS (as the independent ones)."""
    rng = np.random.default_rng(seed)
    t = 2 * np.pi * np.arange(views) / views
    out = sum(np.cos(k * t)[:, None] * rng.standard_normal(9) + np.sin(k * t)[:, None] * rng.standard_normal(9)
              for k in range(1, harmonics + 1))
    out = out - out.mean(axis=0)
    return out / out.std(axis=0) * np.array([sigma] * 6 + [np.deg2rad(sigma)] * 3)


def table_smooth(st: Study, args, say, drift_order: int = 8) -> list:
    """9: the same scan with smooth robot errors of the same size, the loop (exterior on, 2 iterations)
    with independent per-view estimates and with the drift model (a polynomial in time per parameter)."""
    det = tuple(int(x) for x in args.det.lower().split("x"))
    sc = make_scan(args.sigma, views=st.n, det=det, axis="y", seed=args.seed, nxy=args.nxy, say=lambda m: None,
                   errors=smooth_errors(args.sigma, st.n, args.seed))
    s = Study(sc, st.settings)
    rows = [{"estimate": "none (the nominal geometry)", "reproj. error mean (px)": round(s.error_px(np.zeros((s.n, 9))), 3),
             "wall time (s)": 0.0}]
    base = st.settings.replace(exterior="on", exterior_half_width_mm=HALF_WIDTH_MM)
    for name, settings in (("independent per view", base),
                           (f"drift model (degree {drift_order})", base.replace(drift_order=drift_order))):
        t0 = time.perf_counter()
        r = calibration.calibrate(sc.li, sc.nominal, sc.grid, settings, valid_mask=sc.mask)
        rows.append({"estimate": name, "reproj. error mean (px)": round(s.error_px(r.params), 3),
                     "wall time (s)": round(time.perf_counter() - t0, 1)})
        say(f"  9. {rows[-1]}")
    return rows


def table_loop(st: Study, iterations: int, say, schedule: str = "accurate", label: str = "5") -> list:
    """5 (and 10 with the fast schedule): calibration.calibrate with the exterior model, the error after
    each outer iteration."""
    rows = []
    t0 = time.perf_counter()

    def record(rec, params):
        rows.append({"outer iteration": rec.iteration, "reproj. error mean (px)": round(st.error_px(params), 3),
                     "model NCC": round(rec.projection_ncc, 5), "views moved (px)": round(rec.update_px, 3),
                     "elapsed (s)": round(time.perf_counter() - t0, 1)})
        say(f"  {label}. {rows[-1]}")

    calibration.calibrate(st.sc.li, st.sc.nominal, st.sc.grid, st.settings.replace(
        exterior="on", exterior_half_width_mm=HALF_WIDTH_MM, iterations=iterations, stop_update_px=0.0,
        guard=False, schedule=schedule), valid_mask=st.sc.mask, on_iteration=record)
    return rows


def scout_exterior(st: Study, voxel_mm: float, *, magnification: float = 1.25, views: int = 360,
                   photons_behind_body: float = 4000.0):
    """The exterior part from a scout scan: the whole neck at ``magnification`` on the seed system's 70 x 30 mm
    detector, offset so that the field of view (about 104 mm across) holds the neck, raw pixels binned
    to about 0.7 ``voxel_mm`` at the rotation centre, ``views`` over the orbit with robot errors of the
    interior scan's size (drawn separately), photon noise at ``photons_behind_body`` per 110 um pixel
    behind the scout's thickest ray (more per larger pixel), RTK's exact line integrals. FDK with the scout's nominal
    geometry onto the exterior grid (``voxel_mm``, reaching HALF_WIDTH_MM), outside the ROI, non-negative.
    Returns (volume, grid, scout pixel mm)."""
    sc, system = st.sc, SeedSystem()
    sod = system.sdd_mm / magnification
    binning = max(1, round(0.7 * voxel_mm * magnification / system.raw_pixel_mm))
    pitch = binning * system.raw_pixel_mm
    cols, rows = int(system.detector_width_mm / pitch), int(system.detector_height_mm / pitch)
    offset = 0.5 * cols * pitch - 5.0  # the rotation centre projects 5 mm inside one edge
    nominal = circular_scan(views, sod, system.sdd_mm, rows, cols, pitch, pitch, det_offset_u_mm=offset,
                            axis=sc.axis)
    errors = sim.robot_coordination(sc.sigma, sc.sigma, seed=sc.seed + 7).sample(views)
    li = rtk_ellipsoid_projections(sc.phantom.primitives, nominal.perturbed(errors))
    i0 = photons_behind_body * (binning / 2) ** 2 * np.exp(float(li.max()))
    counts = np.maximum(np.random.default_rng(sc.seed + 8).poisson(i0 * np.exp(-li)), 1)
    ext = exterior_grid(st.grid_f, sc.nominal, voxel_mm, HALF_WIDTH_MM)
    vol = np.maximum(fdk(-np.log(counts / i0).astype(np.float32), nominal, ext), 0.0) * exterior_support(ext, st.grid_f)
    return vol, ext, pitch / magnification


def table_scout(st: Study, args, say, voxels=(0.5, 0.25), coarse_passes: int = 3) -> list:
    """11: the exterior from a scout scan (:func:`scout_exterior`) held fixed; the ROI part reconstructed
    (SIRT from zero, as the exterior model's passes) from the data minus the scout's projection, with
    the current geometry; ``coarse_passes`` coarse alternations, then one fine pass, from the nominal
    and from the true geometry; the model NCC of the coarse ROI + scout at either geometry."""
    rows = []
    for voxel in voxels:
        t0 = time.perf_counter()
        x_ext, ext, px = scout_exterior(st, voxel)
        row = {"scout voxel (mm)": voxel, "scout pixel at the centre (mm)": round(px, 3)}

        def model(level, params):
            li, nom, grid, mask = ((st.li_c, st.nom_c, st.grid_c, st.mask_c) if level == "coarse"
                                   else (st.sc.li, st.sc.nominal, st.grid_f, st.sc.mask))
            geom = nom.perturbed(params)
            roi = sirt(li - forward_project(x_ext, ext, geom), geom, grid, st.exterior_iterations,
                       valid_mask=mask)
            return VolumeParts(((roi, grid), (x_ext, ext)))

        for name, start in (("nominal", np.zeros((st.n, 9))), ("true", st.true_p)):
            row[f"model NCC, {name} geometry"] = round(float(projection_consistency(
                model("coarse", start), st.grid_c, st.nom_c.perturbed(start), st.li_c, st.mask_c)[1]), 5)
        for name, start in (("nominal", np.zeros((st.n, 9))), ("true", st.true_p)):
            p = start
            for _ in range(coarse_passes):
                p = st.estimate("coarse", p, model("coarse", p))
            row[f"from the {name} geometry, coarse (px)"] = round(st.error_px(p), 3)
            row[f"from the {name} geometry, fine (px)"] = round(st.error_px(st.estimate("fine", p, model("fine", p))), 3)
        row["wall time (s)"] = round(time.perf_counter() - t0, 1)
        rows.append(row)
        say(f"  11. {rows[-1]}")
    return rows


def shift_combinations(st: Study) -> dict:
    """Name -> function of (views, 9) parameters giving what the ROI's projection sees of them, per view
    (detector mm): the ROI centre's projection shift along u and v from a detector shift d and a source
    shift s, d + (M - 1) s, and the in-plane rotation times the detector's half-width. A ROI a few mm
    across cannot separate d from s; it sees these (the rest moves its points by a fraction of a pixel)."""
    m1 = float(np.mean(st.sc.nominal.magnification())) - 1.0
    half_mm = 0.5 * st.sc.nominal.n_cols * float(np.mean(st.sc.nominal.col_pitch_mm))
    return {f"u shift (d_u + {m1:.2f} s_u)": lambda p: p[:, 3] + m1 * p[:, 0],
            f"v shift (d_v + {m1:.2f} s_v)": lambda p: p[:, 4] + m1 * p[:, 1],
            "in-plane rotation x detector half-width": lambda p: p[:, 8] * half_mm}


def u_shift_slope(st: Study, params) -> float:
    """The slope of the estimate ``params``' projection shift along u on the truth's (table 12's first
    combination; 1: the estimate recovers all of each view's shift), rounded to 3 places (tables 17 and 18)."""
    u_shift = next(iter(shift_combinations(st).values()))
    return round(float(np.polyfit(u_shift(st.true_p), u_shift(params), 1)[0]), 3)


def table_absorption(st: Study, say) -> list:
    """12: how much of each view's error the estimate recovers, per combination the ROI sees
    (:func:`shift_combinations`), against the volumes from the true and from the nominal geometry
    (coarse level, one pass from the nominal geometry): the slope of the estimate on the truth (1:
    all of it; what the volume absorbed is 1 - slope), their correlation, and the estimate's scatter
    about slope x truth (the noise, px of the detector). The last rows repeat the nominal-geometry
    volume's without the robots' prior: whether the prior, which pulls towards the nominal geometry,
    is what holds the estimate back."""
    zero = np.zeros((st.n, 9))
    pitch = float(np.mean(st.sc.nominal.col_pitch_mm))
    rows = []
    no_prior = replace(default_lle_configs("ncc-exact", prior_sigma=None)[0], roi_support_fraction=None)
    vols = {"true": st.volume("coarse", st.true_p), "nominal": st.volume("coarse", zero)}
    for name, cfg, prior in (("true", None, "the robots'"), ("nominal", None, "the robots'"),
                             ("nominal", no_prior, "none")):
        est = st.estimate("coarse", zero, vols[name], cfg=cfg)
        for combo, f in shift_combinations(st).items():
            truth, got = f(st.true_p), f(est)
            slope, icpt = np.polyfit(truth, got, 1)
            rows.append({"volume from": f"the {name} geometry", "prior": prior, "combination": combo,
                         "truth RMS (px)": round(float(truth.std() / pitch), 3),
                         "slope on the truth": round(float(slope), 3),
                         "correlation": round(float(np.corrcoef(truth, got)[0, 1]), 3),
                         "noise (px)": round(float((got - slope * truth - icpt).std() / pitch), 3),
                         "error (px)": round(float((got - truth).std() / pitch), 3)})
            say(f"  12. {rows[-1]}")
    return rows


def table_response(st: Study, say, probes: int = 3, caps=(0.5, 0.7, 0.9)) -> list:
    """13: the absorption undone with a measured response. Volumes are reconstructed (coarse) with the
    nominal geometry moved by ``probes`` known random errors of the robots' size, and each view
    estimated from there; the change of the estimates regressed on the known moves gives the 9 x 9
    response A (estimate change = A x move, over all views). If the estimate followed e = g* + A (g - g*),
    the truth would be g* = (I - A)^-1 (e - A g); A's eigenvalues are capped, since near 1 the inverse
    only amplifies the noise."""
    zero = np.zeros((st.n, 9))
    t0 = time.perf_counter()
    e0 = st.estimate("coarse", zero, st.volume("coarse", zero))
    moves, changes = [], []
    for k in range(probes):
        d = sim.robot_coordination(st.sc.sigma, st.sc.sigma, seed=st.sc.seed + 1000 + k).sample(st.n)
        moves.append(d)
        changes.append(st.estimate("coarse", d, st.volume("coarse", d)) - e0)
    X, Y = np.concatenate(moves), np.concatenate(changes)
    scale = X.std(axis=0)
    Xs = X / scale
    B = np.linalg.solve(Xs.T @ Xs + 1e-3 * len(Xs) * np.eye(9), Xs.T @ Y)
    A = (B / scale[:, None]).T
    w, V = np.linalg.eig(A)
    eig = ", ".join(f"{x:.2f}" for x in np.sort(w.real)[::-1])
    rows = [{"estimate": "one pass against the nominal-geometry volume", "A's eigenvalues": eig,
             "reproj. error mean (px)": round(st.error_px(e0), 3), "wall time (s)": round(time.perf_counter() - t0, 1)}]
    for cap in caps:
        Ac = np.real(V @ np.diag(np.minimum(w.real, cap)) @ np.linalg.inv(V))
        g = e0 @ np.linalg.inv(np.eye(9) - Ac).T  # g = 0 (nominal): g* = (I - A)^-1 e
        rows.append({"estimate": f"undone with A, eigenvalues capped at {cap:g}", "A's eigenvalues": eig,
                     "reproj. error mean (px)": round(st.error_px(g), 3), "wall time (s)": 0.0})
    for r in rows:
        say(f"  13. {r}")
    return rows


def table_bands(st: Study, say, bands=(2, 4, 8), folds: int = 12, more_views=(), args=None) -> list:
    """14: what the other views' data tell about a view, band by band. At each binning (one LLE level on
    data binned so: the coarser, the lower the band), volumes reconstructed with the *true* geometry
    without each view's interleaved fold (as table 7): how well they predict the views they did not see
    (projection NCC at the true geometry, against the volume from every view, which includes the view's
    own data), and where each view's estimate from the nominal geometry ends against them; for
    comparison, the estimate against the volumes from every view with the true and the nominal geometry.
    ``more_views``: the same for the scan with that many views (same photons per view, as table 8; needs
    ``args``), where the views lie closer together and a left-out view's neighbours nearer."""
    rows = []
    for n in (st.n,) + tuple(more_views):
        rows += _bands(st.with_views(n, args), say, bands, folds)
    return rows


def _bands(st: Study, say, bands, folds: int) -> list:
    """Table 14's rows for one scan (its Study), one per binning in ``bands``."""
    zero = np.zeros((st.n, 9))
    rows = []
    for b in bands:
        t0 = time.perf_counter()
        li, nom, grid, mask, _ = st.level(b)
        true_geom = nom.perturbed(st.true_p)
        own = st.volume(b, st.true_p)
        ncc_own = projection_consistency(own, grid, true_geom, li, mask)[1]
        p, ncc_held = zero.copy(), []
        for f in range(folds):
            test = np.arange(f, st.n, folds)
            vol = st.volume(b, st.true_p, np.setdiff1d(np.arange(st.n), test))
            ncc_held.append(projection_consistency(vol, grid, true_geom.subset(test), li[test], mask[test])[1]
                            * len(test))
            p = st.estimate(b, p, vol, test)
        rows.append({"views": st.n, "binning": b, "pixel (mm)": round(float(nom.col_pitch_mm), 3),
                     "projection NCC, own views in": round(float(ncc_own), 5),
                     "projection NCC, own views held out": round(float(sum(ncc_held) / st.n), 5),
                     "estimate, true geometry, own views in (px)": round(st.error_px(st.estimate(b, zero, own)), 3),
                     "estimate, true geometry, own views held out (px)": round(st.error_px(p), 3),
                     "estimate, nominal geometry, own views in (px)": round(
                         st.error_px(st.estimate(b, zero, st.volume(b, zero))), 3),
                     "wall time (s)": round(time.perf_counter() - t0, 1)})
        say(f"  14. {rows[-1]}")
    return rows


TABLES = {
    "1": ("The estimator against volumes reconstructed with a chosen geometry",
          lambda st, args, say: table_reconstruction_geometry(st, say)),
    "2": ("Which part of the nominal-geometry volume misleads it", lambda st, args, say: table_parts(st, say)),
    "3": ("Held-out volumes", lambda st, args, say: table_held_out(st, say)),
    "4": ("The exterior grid's voxel and SIRT passes", lambda st, args, say: table_exterior_settings(st, say)),
    "5": ("The loop over more outer iterations", lambda st, args, say: table_loop(st, args.loop_iterations, say)),
    "6": ("Candidates against the volume's pull (coarse)", lambda st, args, say: table_candidates(st, say)),
    "7": ("Held-out volumes reconstructed with the true geometry",
          lambda st, args, say: table_held_out(st, say, folds=(4, 12), geometry="true")),
    "8": ("More views (same photons per view)", table_views),
    "9": ("Smooth robot errors of the same size: the loop with and without the drift model", table_smooth),
    "10": ("The loop over more outer iterations, fast schedule (4 x 4 binned, then 2 x 2 binned; table 5 is "
           "the default, accurate: 2 x 2 binned, then full size)",
           lambda st, args, say: table_loop(st, args.loop_iterations, say, schedule="fast", label="10")),
    "11": ("The exterior from a wide scout scan, held fixed (3 coarse alternations, then one fine pass)", table_scout),
    "12": ("How much of each view's error the estimate recovers, per combination the ROI sees (coarse, one pass)",
           lambda st, args, say: table_absorption(st, say)),
    "13": ("The absorption undone with a measured response (coarse)", lambda st, args, say: table_response(st, say)),
    "14": ("What the other views tell about a view, band by band (12 interleaved folds held out, one LLE level "
           "on the binned data; 360 and 720 views with the same photons per view)",
           lambda st, args, say: table_bands(st, say, more_views=(360, 720), args=args)),
    "15": ("Held-out volumes with the views' own term taken out of their data too (12 interleaved folds, coarse)",
           lambda st, args, say: table_left_out(st, say)),
    "16": ("The ROI grid's voxel (coarse, one pass)", lambda st, args, say: table_roi_voxel(st, say)),
    "17": ("Table 15's leave-out iterated, beside the plain alternation (coarse)",
           lambda st, args, say: table_left_out_iterated(st, say)),
    "18": ("A smooth background ignored by the metric (coarse, one pass)",
           lambda st, args, say: table_background(st, say)),
    "19": ("Where each view's placement lies in the image: the NCC's own optimum over detector shifts (coarse data, "
           "exhaustive search, no estimator; px of the full-size detector)",
           lambda st, args, say: table_metric_optimum(st, say)),
    "20": ("What the other views tell about a view, by the exterior's voxel and SIRT passes (table 19's held-out "
           "row: the true geometry, 12 folds, the images as they are)",
           lambda st, args, say: table_held_out_exterior(st, say)),
}
"""Number -> (title, builder(study, args, say) -> rows)."""


def scan_args(args) -> dict:
    """The arguments that fix the scan and the study (tables from runs that share them can be merged)."""
    return {k: getattr(args, k) for k in ("sigma", "views", "det", "nxy", "seed")}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sigma", type=float, default=0.1, help="robot errors, mm and deg")
    ap.add_argument("--views", type=int, default=180)
    ap.add_argument("--det", default="96x160", help="ROWSxCOLS binned pixels (110 um)")
    ap.add_argument("--nxy", type=int, default=96)
    ap.add_argument("--loop-iterations", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tables", default=",".join(TABLES), help="tables to compute; the others are kept from the "
                    "interior_diagnosis.json already in --out (same scan arguments)")
    ap.add_argument("--out", default="out/bench_interior_diagnosis")
    args = ap.parse_args(argv)
    rows_, cols_ = (int(x) for x in args.det.lower().split("x"))
    os.makedirs(args.out, exist_ok=True)
    t_all = time.perf_counter()

    def say(msg):
        print(msg, flush=True)

    sc = make_scan(args.sigma, views=args.views, det=(rows_, cols_), axis="y", seed=args.seed, nxy=args.nxy, say=say)
    # the tables were measured under accurate, the default before the exterior schedule (its 15 SIRT passes of the
    # exterior model: Study.exterior_iterations); the loops of tables 5 and 10 name their own schedule
    settings = calibration.CalibrationSettings(schedule="accurate").with_prior(args.sigma, args.sigma)
    st = Study(sc, settings)
    wanted = [k.strip() for k in args.tables.split(",") if k.strip()]
    unknown = set(wanted) - set(TABLES)
    if unknown:
        ap.error(f"unknown tables {sorted(unknown)}; choose from {', '.join(TABLES)}")
    kept, kept_wall, later = {}, 0.0, set()
    previous = os.path.join(args.out, "interior_diagnosis.json")
    if set(wanted) != set(TABLES):
        if not os.path.exists(previous):
            ap.error(f"--tables {args.tables} keeps the other tables from {previous}, which does not exist")
        with open(previous) as f:
            old = json.load(f)
        if "argv_scan" not in old:  # written before the field existed: its arguments say the same
            old["argv_scan"] = scan_args(ap.parse_args(old.get("argv", [])))
        if old.get("argv_scan") != scan_args(args):
            ap.error(f"{previous} was made with other scan arguments ({old.get('argv_scan')}); run every table")
        kept, kept_wall = old["tables"], float(old.get("wall_s", 0.0))
        # tables an earlier --tables run computed after the rest (a json from before this field: the
        # tables it computed, when that was not all of them)
        now = set(old.get("tables_computed_now", old["tables"]))
        later = set(old.get("tables_later", now if now != set(old["tables"]) else ()))
    computed = {k: TABLES[k][1](st, args, say) for k in TABLES if k in wanted}
    tables = {k: (TABLES[k][0], computed[k] if k in computed else kept[k]) for k in TABLES if k in computed or k in kept}
    wall = time.perf_counter() - t_all + (kept_wall if kept else 0.0)
    report = {"bench": "bench/bench_interior_diagnosis.py", "argv": sys.argv[1:] if argv is None else list(argv),
              "argv_scan": scan_args(args), "tables_computed_now": sorted(computed),
              "tables_later": sorted(later | set(computed), key=int) if kept else [],
              "machine": f"{platform.machine()}, {os.cpu_count()} cores", "settings": settings.to_dict(),
              "nominal_error_px": st.error_px(np.zeros((st.n, 9))), "tables": {k: r for k, (_, r) in tables.items()},
              "wall_s": wall}
    lines = ["# Interior scan: where the remaining error comes from (bench/bench_interior_diagnosis.py)", "",
             f"The interior neck of bench_interior.py ({args.views} views, {rows_} x {cols_} detector of 110 um, "
             f"axis +y) with robot errors of {args.sigma:g} mm / {args.sigma:g} deg: the nominal geometry lies "
             f"{report['nominal_error_px']:.3f} px from the truth (gauge-aligned mean over ROI points). Estimator: "
             f"ncc-lle-exact, prior at the robots' accuracy, no ROI support mask; 'coarse' is one pass on 2 x 2 "
             f"binned data, 'fine' one full-size pass after it. Volumes: the exterior model (ROI grid and "
             f"{settings.exterior_voxel_mm:g} mm exterior grid reaching {HALF_WIDTH_MM:g} mm, joint non-negative "
             f"OS-SIRT, {st.exterior_iterations} passes of {settings.exterior_subsets} subsets) reconstructed "
             f"from the measured data with the geometry named in each row. Projection RMSE and NCC: that volume "
             f"reprojected with the same geometry against the data (how well it explains them).", ""]
    for k, (title, rows) in tables.items():
        lines += [f"## {k}. {title}", "", table(rows), ""]
    if kept:
        done = report["tables_later"]
        lines += [f"{'Tables' if len(done) > 1 else 'Table'} {', '.join(done)} {'were' if len(done) > 1 else 'was'} "
                  f"computed in later runs (--tables) than the others, with the same scan arguments.", ""]
    lines += [f"Total {wall / 60:.1f} min on this machine ({report['machine']}), shared with other jobs.", ""]
    with open(os.path.join(args.out, "interior_diagnosis.json"), "w") as f:
        json.dump(report, f, indent=2, default=str)
    with open(os.path.join(args.out, "interior_diagnosis.md"), "w") as f:
        f.write("\n".join(lines))
    say(f"wrote {args.out}/interior_diagnosis.md ({wall / 60:.1f} min)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
