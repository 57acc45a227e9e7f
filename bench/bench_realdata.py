"""Benchmark on real measured data: the HTC2022 fan-beam scans, imported as scan bags.

Data: Helsinki Tomography Challenge 2022 (HTC2022) open tomographic dataset, phantoms 01a and
02a (``htc2022_0?a_full.mat``: 721 x 560 sinograms of line integrals; ``htc2022_0?a_recon_fbp.mat``:
the dataset's own 512 x 512 FBP), read from ``--data`` (default /work/shared/realdata/htc2022;
SOURCE.txt there says where they come from and how to cite them).

1. Geometry check. Each phantom is imported with the job behind ``robot-ct import htc2022``
   (robot_ct_ros.jobs.htc2022.import_htc2022, into a temporary folder) and reconstructed with
   the documented geometry (all 720 views) on the bag's default grid, which is the dataset's
   reconstruction grid (512 x 512 pixels of effectivePixelSizePost, one voxel thick). Reported:
   the Pearson correlation with the dataset's FBP for the FDK filter windows, with and without
   truncation handling, the image orientation that matches, and the intensity scale.
1b. Opposed rays. The documented geometry's centre of rotation checked from the data alone
   (robot_ct_ros.ct.opposed_rays, all 720 views): the detector shift at which every line's two
   measurements agree best.
2. Calibration. The documented geometry is taken as the true one; the data stay the measured
   sinogram (every ``--view-step``-th view). Per-view errors are injected into the geometry the
   calibration starts from (the "nominal"): the detector shift d_u with sigma one detector pixel
   and the source shift s_u with the sigma that moves the projection of the rotation centre by one
   pixel (independent, Gaussian, seeded); a second case adds a slow d_u drift (half a sine over the
   scan, ``--drift-px`` amplitude). Every method of the registry runs through calibration.calibrate
   with the default settings and the prior ``--prior-mm`` (source), ``--prior-detector-mm`` and
   ``--prior-deg`` (default: the injected sigmas and 0.01 deg), on the bag's default grid. Reported per method: the
   gauge-aligned reprojection error (mean, p95, px) against the documented geometry, SSIM and edge
   sharpness against the reconstruction with the documented geometry, model NCC, iterations, wall
   time and the guard's notes. Case ``documented`` injects nothing (each method started at the
   documented geometry); row ``oracle floor`` is the error left when each view's shift of the
   centre's projection is known exactly and the rotation about the centre that one row hardly
   sees is set by the prior (:func:`oracle_floor`). Cases ``twin`` and ``twin-documented`` repeat
   ``independent`` and ``documented`` on a synthetic twin of the data, which the documented geometry
   explains exactly (:func:`synthetic_twin`: our FDK resampled finer, RTK's projector, the measured
   noise level): what the measured data cost against it is what they hold beyond the documented
   geometry and the forward model.
3. Figures: per phantom and measured case the slice with the documented geometry, with the
   perturbed nominal, with ncc-lle-exact's correction and the dataset's FBP; per case the
   parameter error per view.

Writes ``realdata.md``, ``realdata.json`` and the figures into ``--out``.

    .venv/bin/python bench/bench_realdata.py --out docs/results           # see realdata.md for the time
    .venv/bin/python bench/bench_realdata.py --phantoms 01a --view-step 8 --methods none,ncc-lle-exact
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from robot_ct_ros.bag import read_scan  # noqa: E402
from robot_ct_ros.ct import calibration  # noqa: E402
from robot_ct_ros.ct.field_of_view import field_of_view_mask  # noqa: E402
from robot_ct_ros.ct.metrics import edge_sharpness, reprojection_error, roi_points  # noqa: E402
from robot_ct_ros.ct.opposed_rays import opposed_ray_offset  # noqa: E402
from robot_ct_ros.ct.reconstruction import WINDOWS, fdk  # noqa: E402
from robot_ct_ros.ct.scan_weights import source_angles  # noqa: E402
from robot_ct_ros.jobs.figures import COLUMNS, markdown_table, plot_param_error, summarize  # noqa: E402
from robot_ct_ros.jobs.htc2022 import import_htc2022  # noqa: E402

DATA = Path("/work/shared/realdata/htc2022")
ONE_PRIOR = "ncc-lle-exact (one translation prior)"
"""ncc-lle-exact with the source's sigma on the detector's translations too: what stating each arm's
accuracy (prior_detector_mm) changes."""
METHODS = ("none", "l2-lle", "ncc-lle", "ncc-lle-exact", ONE_PRIOR, "gdc", "gdc-log", "documented geometry")
TRUTH = "documented geometry"
CASES = {"independent": "independent per-view errors", "drift": "independent per-view errors plus a slow d_u drift",
         "documented": "no errors injected: every method started at the documented geometry",
         "twin": "synthetic twin (data the documented geometry explains exactly), the independent case's errors",
         "twin-documented": "synthetic twin, no errors injected: every method started at the documented geometry"}
TWIN_OF = {"twin": "independent", "twin-documented": "documented"}
"""The twin cases: the measured case whose injected errors (kind and seed) they repeat on the twin's data."""
FIGURE_ALT = {"slices": "slices", "param_error": "parameter error"}
"""The alt text of each figure kind in realdata.md."""
ORACLE = "oracle floor"
"""The error left when the centre's projection shift of every view is known exactly and the rest, the
s_u / d_u split (a rotation about the centre, which one row hardly sees), is taken at its MAP under the
prior (:func:`oracle_floor`)."""
ORIENTATIONS = {"as is": lambda a: a, "rows flipped": lambda a: a[::-1], "columns flipped": lambda a: a[:, ::-1],
                "transposed": lambda a: a.T}
"""Ways to lay our slice (volume[0], row j = increasing y) over the dataset's image."""
_AFTER_SSIM = [key for key, *_ in COLUMNS].index("ssim") + 1
COLUMNS_REAL = (COLUMNS[:_AFTER_SSIM] + (("sharpness_rel", "edge sharpness / documented", "{:.3f}"),)
                + COLUMNS[_AFTER_SSIM:])
"""realdata.md's columns: the edge sharpness relative to the documented geometry's right after the SSIM."""


def pearson(a, b) -> float:
    return float(np.corrcoef(np.ravel(a), np.ravel(b))[0, 1])


def read_dataset_fbp(data: Path, phantom: str) -> np.ndarray:
    import scipy.io

    return np.asarray(scipy.io.loadmat(data / f"htc2022_{phantom}_recon_fbp.mat", squeeze_me=True)["reconFullFbp"],
                      np.float64)


def injected_errors(geom, case: str, *, base_seed: int, px: float, drift_px: float, sigma_src_mm: float) -> np.ndarray:
    """(n, 9) parameters taking the documented geometry to the perturbed nominal one: d_u with sigma
    ``px`` pixels, s_u with sigma ``sigma_src_mm``; the drift case adds ``drift_px`` * sin(pi t) to d_u.
    Each case draws from its own seed, ``base_seed`` + 17 x its place in CASES, so every bench that
    injects a case (bench_realdata_halves, bench_embedding) injects the same errors."""
    n = geom.n_views
    rng = np.random.default_rng(base_seed + 17 * list(CASES).index(case))
    p = np.zeros((n, 9))
    p[:, 3] = rng.standard_normal(n) * px * geom.col_pitch_mm
    p[:, 0] = rng.standard_normal(n) * sigma_src_mm
    if case == "drift":
        t = (np.arange(n) + 0.5) / n
        p[:, 3] += drift_px * geom.col_pitch_mm * np.sin(np.pi * t)
    if case == "documented":
        p[:] = 0.0
    return p


def noise_sigma(line_integrals, mask=None) -> float:
    """The data's white-noise standard deviation along the row, from the median absolute second
    difference over valid pixels (a second difference of white noise has variance 6 sigma^2;
    edges are rare)."""
    p = np.asarray(line_integrals, np.float64)
    d2 = np.diff(p, 2, axis=-1)
    if mask is not None:
        m = np.broadcast_to(np.asarray(mask, bool), p.shape)
        d2 = d2[m[..., 2:] & m[..., 1:-1] & m[..., :-2]]
    d2 = d2.ravel()
    return float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / np.sqrt(6.0))


def synthetic_twin(li, mask, geom, grid, *, seed: int, upsample: int = 2):
    """Data the documented geometry explains exactly, as close to the measured ones as we can make them.

    The object: our FDK of the measured data (documented geometry, every view) on ``grid``, zero
    outside the field of view (:func:`~robot_ct_ros.ct.field_of_view.field_of_view_mask`: the square
    grid's corners, where FDK's incomplete data leave streaks that are no object), resampled
    ``upsample`` times finer across the slice (cubic spline, negatives cut) and three slices thick
    so that the fan plane lies inside it. Its line integrals through ``geom`` come from RTK's Joseph
    projector (not ours), plus white Gaussian noise at the measured data's level (:func:`noise_sigma`). Returns the twin's line integrals, the noise sigma and their
    Pearson correlation with the measured ones."""
    from scipy import ndimage

    from robot_ct_ros.ct.geometry import VolumeGrid
    from robot_ct_ros.ct.rtk_bridge import rtk_forward_project

    vol = np.where(field_of_view_mask(geom, grid), fdk(li, geom, grid, valid_mask=mask), np.float32(0.0))
    fine = np.clip(ndimage.zoom(np.asarray(vol[0], np.float64), upsample, order=3), 0.0, None).astype(np.float32)
    vx, vy, vz = grid.voxel_size_mm
    fine_grid = VolumeGrid.centered((3, *fine.shape), (vx / upsample, vy / upsample, vz), grid.center_mm, grid.direction)
    proj = rtk_forward_project(np.ascontiguousarray(np.broadcast_to(fine, (3, *fine.shape))), fine_grid, geom)
    sigma = noise_sigma(li, mask)
    rng = np.random.default_rng(seed)
    twin = (proj + rng.standard_normal(proj.shape) * sigma).astype(np.float32)
    return twin, sigma, pearson(twin, li)


def load_phantom(data: Path, phantom: str, tmp: Path, say=lambda m: None):
    """A phantom's ``htc2022_<phantom>_full.mat`` imported as a scan bag under ``tmp`` (``say``: the
    import's progress) and read back: (scan, its default grid, line integrals, valid mask, the source
    shift in mm that moves the rotation centre's projection by one detector pixel)."""
    bag = import_htc2022(Path(data) / f"htc2022_{phantom}_full.mat", Path(tmp) / f"htc2022_{phantom}", say=say)
    scan = read_scan(bag)
    li_all, mask_all = scan.to_line_integrals()
    dso = float(np.median(scan.geom.sod_mm()))
    pixel_src_mm = scan.geom.col_pitch_mm * dso / (float(np.median(scan.geom.sdd_mm)) - dso)
    return scan, scan.default_grid(), li_all, mask_all, pixel_src_mm


def view_mask(mask, views):
    """The valid mask of ``views`` (a per-view mask is cut, a shared one kept; None stays None)."""
    if mask is None:
        return None
    return np.ascontiguousarray(mask[views] if np.ndim(mask) == 3 else mask)


def oracle_floor(true, injected: np.ndarray, points, source_mm: float, detector_mm: float) -> dict:
    """Reprojection error (metrics.reprojection_error) of the best a per-view estimate can do when the
    data fix only the shift of the rotation centre's projection, c = d_u + k s_u (k = (SDD - SOD) / SOD),
    exactly: the remaining direction (s_u, d_u) ~ (1, -k), a rotation of the view about the centre,
    is taken at its MAP under the prior (``source_mm`` on s_u, ``detector_mm`` on d_u), as an
    estimator with that prior would."""
    dso = float(np.median(true.sod_mm()))
    k = (float(np.median(true.sdd_mm)) - dso) / dso
    c = injected[:, 3] + k * injected[:, 0]
    vs, vd = source_mm ** 2, detector_mm ** 2  # min s^2 / vs + d^2 / vd subject to d + k s = c
    s_hat = c * k * vs / (vd + k * k * vs)
    d_hat = c * vd / (vd + k * k * vs)
    left = np.array(injected, float)
    left[:, 0] -= s_hat
    left[:, 3] -= d_hat
    return reprojection_error(true.perturbed(left), true, points)


def geometry_check(scan, li, mask, fbp_ref: np.ndarray, say) -> dict:
    """Correlation of our FDK (documented geometry, every view: the scan's line integrals ``li`` and
    valid ``mask``) with the dataset's FBP."""
    grid = scan.default_grid()
    rows = []
    best = default_image = None
    for window in WINDOWS:
        for truncation in ("extrapolate", None):
            img = fdk(li, scan.geom, grid, valid_mask=mask, window=window, truncation=truncation)[0].astype(np.float64)
            corr = {name: pearson(f(img), fbp_ref) for name, f in ORIENTATIONS.items()}
            flipped = ORIENTATIONS["rows flipped"](img)
            slope = float(np.polyfit(fbp_ref.ravel(), flipped.ravel(), 1)[0])
            row = {"window": window, "truncation": str(truncation), "correlation": corr, "slope_per_mm": slope,
                   "default": window == "hann" and truncation == "extrapolate"}
            rows.append(row)
            if best is None or corr["rows flipped"] > best[0]["correlation"]["rows flipped"]:
                best = (row, flipped)
            if row["default"]:
                default_image = flipped
            say(f"    FDK {window}, truncation {truncation}: " + ", ".join(f"{k} {v:.5f}" for k, v in corr.items()))
    return {"grid": grid.to_dict(), "rows": rows, "best": best[0], "best_image": best[1],
            "default_image": default_image}


def plot_slices_real(path, images: dict, *, title: str = "", zoom: float | None = None) -> Path:
    """One row of slices (the dataset's image orientation: row 0 at the largest y), one grey window
    per image (its 0.5-99.5 % range: the dataset's FBP has other units); with ``zoom`` a second row
    showing the central ``zoom`` fraction."""
    from robot_ct_ros.jobs.figures import _plt, _save

    plt = _plt()
    n = len(images)
    nrows = 1 if zoom is None else 2
    fig, axes = plt.subplots(nrows, n, figsize=(2.9 * n + 0.3, 3.1 * nrows + 0.3), squeeze=False)
    for k, (name, img) in enumerate(images.items()):
        lo, hi = np.percentile(img, [0.5, 99.5])
        axes[0, k].imshow(img, cmap="gray", vmin=lo, vmax=hi, interpolation="nearest")
        axes[0, k].set_title(name, fontsize=9)
        if zoom is not None:
            h, w = img.shape
            a, b = int(h * (0.5 - zoom / 2)), int(w * (0.5 - zoom / 2))
            axes[1, k].imshow(img[a:h - a, b:w - b], cmap="gray", vmin=lo, vmax=hi, interpolation="nearest")
        for r in range(nrows):
            axes[r, k].set_xticks([])
            axes[r, k].set_yticks([])
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(fig, path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(DATA), help="folder with htc2022_<phantom>_full.mat and _recon_fbp.mat")
    ap.add_argument("--phantoms", default="01a,02a")
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--view-step", type=int, default=2, help="calibrate every N-th view of the 720")
    ap.add_argument("--error-px", type=float, default=1.0, help="sigma of the injected d_u and of the source shift's "
                    "displacement of the centre's projection, detector pixels")
    ap.add_argument("--drift-px", type=float, default=3.0, help="amplitude of the drift case's d_u drift, pixels")
    ap.add_argument("--prior-mm", type=float, default=None,
                    help="prior sigma of the source's translations (default: the injected source-shift sigma)")
    ap.add_argument("--prior-detector-mm", type=float, default=None,
                    help="prior sigma of the detector's translations (default: the injected d_u sigma)")
    ap.add_argument("--prior-deg", type=float, default=0.01, help="prior rotation sigma (no rotation is injected)")
    ap.add_argument("--iterations", type=int, default=None, help="default: the settings' default")
    ap.add_argument("--arc-deg", type=float, default=360.0,
                    help="calibrate the views within this arc from the first only (a short scan; default 360)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="out/bench_realdata")
    args = ap.parse_args(argv)
    data = Path(args.data)
    phantoms = [p.strip() for p in args.phantoms.split(",") if p.strip()]
    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    for c in cases:
        if c not in CASES:
            ap.error(f"unknown case {c!r}; choose from {', '.join(CASES)}")
    if not 180.0 < args.arc_deg <= 360.0:
        ap.error(f"--arc-deg must lie in (180, 360], got {args.arc_deg:g}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()

    def say(msg):
        print(f"[{time.perf_counter() - t_all:7.1f} s] {msg}", flush=True)

    settings = calibration.CalibrationSettings()
    if args.iterations is not None:
        settings = settings.replace(iterations=args.iterations)
    source_text = (data / "SOURCE.txt").read_text() if (data / "SOURCE.txt").exists() else ""
    report = {"bench": "bench/bench_realdata.py", "argv": sys.argv[1:] if argv is None else list(argv),
              "machine": f"{platform.machine()}, {os.cpu_count()} cores",
              "numba_threads": os.environ.get("NUMBA_NUM_THREADS"), "data": str(data), "source": source_text,
              "phantoms": {}}
    sections = []
    check_rows = []
    first = None
    with tempfile.TemporaryDirectory() as tmp:
        for ph in phantoms:
            say(f"phantom {ph}: import")
            scan, grid, li_all, mask_all, pixel_src_mm = load_phantom(data, ph, tmp, say)
            ref = read_dataset_fbp(data, ph)
            say(f"phantom {ph}: geometry check against the dataset's FBP")
            chk = geometry_check(scan, li_all, mask_all, ref, say)
            best_img, default_img = chk.pop("best_image"), chk.pop("default_image")
            check_rows.append((ph, chk))
            say(f"phantom {ph}: opposed rays")
            orc = opposed_ray_offset(li_all, scan.geom, reach_px=1.0, steps=21, smooth_px=1.0)
            chk["opposed_rays"] = {"best_shift_px": orc.best_shift_px, "best_shift_mm": orc.best_shift_mm,
                                   "shifts_mm": orc.shifts_mm, "mismatch": orc.mismatch}
            g0 = scan.geom
            dso = float(np.median(g0.sod_mm()))
            odd = float(np.median(g0.sdd_mm)) - dso
            sigma_src = args.error_px * pixel_src_mm  # moves the centre's projection by error_px
            prior_mm = sigma_src if args.prior_mm is None else args.prior_mm
            prior_det_mm = (args.error_px * g0.col_pitch_mm if args.prior_detector_mm is None
                            else args.prior_detector_mm)
            if first is None:
                first = {"n_views": scan.n_views, "n_cols": g0.n_cols, "pitch": g0.col_pitch_mm, "dso": dso,
                         "dsd": dso + odd, "grid": grid, "sigma_src": sigma_src, "prior_mm": prior_mm,
                         "prior_det_mm": prior_det_mm}
            views = np.arange(0, scan.n_views, args.view_step)
            if args.arc_deg < 360.0:  # a short scan: the views within the arc from the first
                phi = np.degrees(source_angles(scan.geom, scan.scan_center_mm()))
                views = views[np.mod(phi[views] - phi[0], 360.0) <= args.arc_deg + 1e-6]
            li = np.ascontiguousarray(li_all[views])
            mask = view_mask(mask_all, views)
            true = g0.subset(views)
            pts = roi_points(grid)

            ph_report = {"n_views_file": scan.n_views, "views_used": int(views.size), "grid": grid.to_dict(),
                         "geometry_check": chk, "sigma_detector_mm": args.error_px * g0.col_pitch_mm,
                         "sigma_source_mm": sigma_src, "cases": {}}
            report["phantoms"][ph] = ph_report
            sources = {"measured": li}  # the calibrated views of each data source
            if any(c in TWIN_OF for c in cases):
                say(f"phantom {ph}: synthetic twin (RTK Joseph projector)")
                twin_all, twin_sigma, twin_corr = synthetic_twin(li_all, mask_all, g0, grid, seed=args.seed + 99)
                ph_report["twin"] = {"noise_sigma": twin_sigma, "correlation_with_measured": twin_corr}
                sources["twin"] = np.ascontiguousarray(twin_all[views])
            truth = {}  # per data source: the FDK with the documented geometry, its wall time and sharpness
            for case in cases:
                kind = TWIN_OF.get(case, case)  # the injection: the measured case's kind and seed
                source = "twin" if case in TWIN_OF else "measured"
                li = sources[source]

                def reconstruct(geom, li=li, mask=mask):
                    return fdk(li, geom, grid, valid_mask=mask)

                if source not in truth:
                    t0 = time.perf_counter()
                    vol = reconstruct(true)
                    truth[source] = (vol, time.perf_counter() - t0, edge_sharpness(vol))
                true_vol, true_wall, sharp_true = truth[source]
                params_inj = injected_errors(true, kind, base_seed=args.seed,
                                             px=args.error_px, drift_px=args.drift_px, sigma_src_mm=sigma_src)
                nominal = true.perturbed(params_inj)
                run_settings = settings.with_prior(prior_mm, args.prior_deg, detector_mm=prior_det_mm)
                results = {}
                for method in methods:
                    say(f"phantom {ph}, {case}: {method}")
                    if method == TRUTH:
                        results[method] = (true, true_vol, (), true_wall)
                        continue
                    this = (run_settings.replace(method="ncc-lle-exact", prior_detector_mm=None) if method == ONE_PRIOR
                            else run_settings.replace(method=method))
                    results[method] = calibration.calibrate(li, nominal, grid, this,
                                                            valid_mask=mask, progress=lambda m: say(f"    {m}"))
                rows = summarize(results, grid, (true, true_vol, None), pts, reconstruct=reconstruct)
                for r in rows:
                    r["sharpness_rel"] = None if r["sharpness"] is None else r["sharpness"] / sharp_true
                if kind != "documented":
                    fl = oracle_floor(true, params_inj, pts, prior_mm, prior_det_mm)
                    rows.insert(1, {k: None for k in rows[0]} | {"method": ORACLE, "reproj_mean_px": fl["mean_px"],
                                                                 "reproj_p95_px": fl["p95_px"]})
                notes = {m: list(getattr(r, "notes", ())) for m, r in results.items() if getattr(r, "notes", ())}
                for m, r in results.items():  # what the guard kept at nominal: the estimate before it
                    if getattr(r, "params_unguarded", None) is not None:
                        e = reprojection_error(nominal.perturbed(r.params_unguarded), true, pts)
                        notes.setdefault(m, []).append(f"before the guard {e['mean_px']:.3f} px mean, "
                                                       f"{e['p95_px']:.3f} px p95")
                name = f"realdata_{ph}_{case}"
                title = f"HTC2022 {ph}, {views.size} views, {CASES[case]}"
                images = {"documented geometry": true_vol[0][::-1]}
                if "none" in results:
                    images["perturbed nominal"] = np.asarray(results["none"].volume)[0][::-1]
                if "ncc-lle-exact" in results:
                    images["ncc-lle-exact"] = np.asarray(results["ncc-lle-exact"].volume)[0][::-1]
                images["dataset FBP (720 views)"] = ref
                figs = ({} if case in TWIN_OF else  # the twin's slices look like the measured ones
                        {"slices": plot_slices_real(out / f"{name}_slices.png", images, title=title, zoom=0.4).name})
                geoms = {m: r for m, r in results.items() if m != TRUTH}
                if geoms:
                    figs["param_error"] = plot_param_error(out / f"{name}_param_error.png", geoms, true, pts,
                                                           title=title).name
                inj = reprojection_error(nominal, true, pts)
                ph_report["cases"][case] = {"title": title, "rows": rows, "notes": notes, "figures": figs,
                                            "injected_reprojection_px": {"mean": inj["mean_px"], "p95": inj["p95_px"]},
                                            "injected_rms_mm": {"s_u": float(np.sqrt((params_inj[:, 0] ** 2).mean())),
                                                                "d_u": float(np.sqrt((params_inj[:, 3] ** 2).mean()))},
                                            "settings": run_settings.to_dict()}
                table = markdown_table(rows, COLUMNS_REAL)
                say("\n" + table)
                sec = [f"### {title}", "",
                       "Nothing injected: the calibration starts at the documented geometry." if kind == "documented"
                       else f"Injected: s_u RMS {ph_report['cases'][case]['injected_rms_mm']['s_u']:.3f} mm, d_u RMS "
                       f"{ph_report['cases'][case]['injected_rms_mm']['d_u']:.3f} mm; the perturbed nominal lies "
                       f"{inj['mean_px']:.3f} px (mean), {inj['p95_px']:.3f} px (p95) from the documented geometry "
                       f"(gauge removed).", "", table]
                sec += [f"- {m}: {'; '.join(n)}" for m, n in notes.items()]
                sec += ["", " ".join(f"![{FIGURE_ALT[k]}]({v})" for k, v in figs.items()), ""]
                sections.append(sec)
            # the geometry check's figure: our best match next to the dataset's image
            plot_slices_real(out / f"realdata_{ph}_check.png",
                             {f"ours: FDK {chk['best']['window']}, truncation {chk['best']['truncation']}": best_img,
                              "ours: default FDK (hann)": default_img,
                              "dataset FBP": ref, "difference (ours / slope - dataset)":
                              best_img / chk["best"]["slope_per_mm"] - ref},
                             title=f"HTC2022 {ph}, all {scan.n_views} views, documented geometry")
    report["wall_s"] = time.perf_counter() - t_all
    f = first
    g = f["grid"]
    lines = ["# Real data: HTC2022 fan-beam scans (bench/bench_realdata.py)", "",
             "**Data.** Helsinki Tomography Challenge 2022 (HTC2022) open tomographic dataset, test phantoms "
             + ", ".join(phantoms) + " (acrylic discs, 70 mm, laser-cut holes), University of Helsinki Industrial "
             "Mathematics CT Laboratory (Meaney et al.), Zenodo records 6984868 / 8041800; cite the dataset when you "
             "use it (licence: the Zenodo page says \"Dataset Open\"). Files: `htc2022_<phantom>_full.mat` (sinogram "
             "of line integrals, flat/dark corrected by the authors, and parameters) and `htc2022_<phantom>_recon_fbp"
             ".mat` (the dataset's own 512 x 512 FBP), imported with `robot-ct import htc2022` "
             "(robot_ct_ros.jobs.htc2022.import_htc2022).", "",
             f"**Geometry.** Circular fan beam (ASTRA fanflat about +z, the import's convention): {f['n_views']} views "
             f"over 360 deg (the repeated last angle of 721 dropped), 1 x {f['n_cols']} detector of {f['pitch']:g} mm, "
             f"source to centre {f['dso']:g} mm, source to detector {f['dsd']:g} mm. Grid: the bag's default, i.e. "
             f"the dataset's reconstruction grid, {g.shape_zyx[2]} x {g.shape_zyx[1]} x {g.shape_zyx[0]} voxels of "
             f"{g.voxel_size_mm[0]:.6f} mm (effectivePixelSizePost) about the rotation centre.", "",
             "**1. Geometry check.** Our FDK with the documented geometry and every view against the dataset's FBP: "
             "Pearson correlation over all 512 x 512 pixels, for each filter window of our FDK, with its default "
             "truncation handling (`extrapolate`) and without (`None`), our slice laid over the dataset's image as "
             "is, rows flipped, columns flipped or transposed. Slope: our value (1/mm) per dataset unit, the "
             "least-squares line of ours (rows flipped) against theirs.", "",
             f"**2. Calibration.** The documented geometry is taken as the true one; the data stay the measured "
             f"sinogram, every {args.view_step}{'nd' if args.view_step == 2 else 'th'} view "
             f"({f['n_views'] // args.view_step if f['n_views'] % args.view_step == 0 else '~' + str(f['n_views'] // args.view_step)}"
             f" of {f['n_views']}) to keep the run short"
             + (f", and of those only the views within {args.arc_deg:g} degrees of the first (a short scan, "
                f"{report['phantoms'][phantoms[0]]['views_used']} views; its FDK volumes take Parker's weights)"
                if args.arc_deg < 360.0 else "")
             + f". The calibration starts from a perturbed nominal geometry: "
             f"per view, independent Gaussian errors (seed {args.seed}, another per case) of the detector shift "
             f"d_u with sigma {args.error_px:g} px ({args.error_px * f['pitch']:g} mm) and of the source shift s_u "
             f"with sigma {f['sigma_src']:.4f} mm, which moves the projection of the rotation centre by "
             f"{args.error_px:g} px ({args.error_px * f['pitch']:g} mm x SOD / (SDD - SOD)). Case `drift` adds "
             f"{args.drift_px:g} px x sin(pi t) to d_u (t = 0..1 over the scan: a slow drift out and back). Every "
             f"method through calibration.calibrate with the default settings (the full list in realdata.json) "
             f"except the prior, each arm's injected accuracy: {f['prior_mm']:.4f} mm on the source's translations, "
             f"{f['prior_det_mm']:.4f} mm on the detector's (prior_detector_mm; row `{ONE_PRIOR}` puts "
             f"{f['prior_mm']:.4f} mm on both) and {args.prior_deg:g} deg on every rotation (none injected; 0 would turn "
             f"the prior off); the guard takes the same values as the robots' stated accuracy. `gdc` and `gdc-log` "
             f"have no prior. The disc lies inside the field of view (the detector's edges see air), so every "
             f"estimation volume's FDK is kept to it (fov_support auto: zero in the square grid's corners, whose "
             f"incomplete data leave streaks). A one-row detector estimates only s_u, s_w, d_u, d_w and r_v. "
             f"Case `documented` injects "
             f"nothing: each method starts at the documented geometry, and its error says how far the data (and "
             f"the method's own scatter) move it from there. Row `{ORACLE}`: the error left if every view's shift "
             f"of the rotation centre's projection (d_u + k s_u, k = (SDD - SOD) / SOD) were known exactly and "
             f"the one direction a row hardly sees, s_u and d_u in the ratio 1 : -k (a rotation of the view about "
             f"the centre), were set at its MAP under the same prior (bench_realdata.oracle_floor): a floor for "
             f"per-view estimation with this prior.", ""]
    lines += [] if not any(c in TWIN_OF for c in cases) else [
             "**Synthetic twin.** Cases `twin` and `twin-documented` repeat `independent` and `documented` (the same "
             "injected errors) on data that the documented geometry explains exactly: our FDK of the measured data "
             "(every view, documented geometry), zero outside the field of view (the grid's corners, which not every "
             "direction's rays reach: field_of_view.field_of_view_mask), resampled twice as fine across the slice "
             "(cubic spline, three slices "
             "thick), projected through the documented geometry by RTK's Joseph projector (not ours), plus white "
             "Gaussian noise at the measured data's level (median absolute second difference along the row; "
             "bench_realdata.synthetic_twin). What a method loses on the measured data against the twin is what "
             "the measured data hold beyond the documented geometry and this forward model: per-view deviations of "
             "the real scanner from its documented geometry, and physics the model lacks (beam hardening, scatter, "
             "detector blur); this bench cannot tell those apart. "
             + "; ".join(f"{ph}: noise sigma {r['twin']['noise_sigma']:.5f}, correlation of the twin with the measured "
                         f"sinogram {r['twin']['correlation_with_measured']:.5f}"
                         for ph, r in report["phantoms"].items() if "twin" in r) + ".", ""]
    lines += [
             "**Metrics.** *reproj. error*: gauge-aligned reprojection error (robot_ct_ros.ct.metrics."
             "reprojection_error) of 125 points filling the inner 80 % of the grid (roi_points), in detector pixels "
             "(0.2 mm), against the documented geometry, after removing the best global rigid motion; mean and 95th "
             "percentile over views and points. *SSIM*: against the FDK with the documented geometry (same views, "
             "same grid), each estimate moved into the documented gauge first. *edge sharpness*: the 99th percentile "
             "of the gradient magnitude over the 1-99 % intensity range (metrics.edge_sharpness); the next column "
             "divides it by the documented geometry's. *model NCC*: the last iteration's estimation volume "
             "reprojected against the data (the guard's first test). Wall time: this machine "
             f"({report['machine']}, NUMBA_NUM_THREADS={report['numba_threads']}), shared with other jobs. "
             "Each method's notes (the guard's verdict) below its table.", ""]
    lines += ["## 1. Our reconstruction against the dataset's FBP", "",
              "| phantom | FDK window | truncation | as is | rows flipped | columns flipped | transposed | slope (1/mm per unit) |",
              "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for ph, chk in check_rows:
        for r in chk["rows"]:
            c = r["correlation"]
            lines.append(f"| {ph} | {r['window']}{' (default)' if r['default'] else ''} | {r['truncation']} | "
                         f"{c['as is']:.5f} | {c['rows flipped']:.5f} | {c['columns flipped']:.5f} | "
                         f"{c['transposed']:.5f} | {r['slope_per_mm']:.4f} |")
    lines += [""]
    for ph, chk in check_rows:
        b = chk["best"]
        d = next(r for r in chk["rows"] if r["default"])
        lines.append(f"- {ph}: best {b['correlation']['rows flipped']:.5f} (FDK {b['window']}, truncation "
                     f"{b['truncation']}, rows flipped); our default FDK {d['correlation']['rows flipped']:.5f}; "
                     f"slope {b['slope_per_mm']:.4f} against 1 / effectivePixelSizePost = {1.0 / g.voxel_size_mm[0]:.4f} "
                     f"(the dataset's image is in 1/pixel, ours in 1/mm). "
                     f"![check](realdata_{ph}_check.png)")
    lines += ["", "## 1b. The documented centre of rotation, by opposed rays", "",
              "Over a full circle every line is measured from both sides (robot_ct_ros.ct.opposed_rays: no "
              "projector, no reconstruction). The table gives the detector shift along u, the same for every view, "
              "at which the two measurements agree best (all 720 views, 1 px Gaussian smoothing along the row, "
              "shifts of -1 to 1 px in 0.1 px steps, a parabola through the smallest three): how far the documented "
              "centre of rotation is from the one the data hold. It is 0 for a perfect documented geometry.", "",
              "| phantom | best shift (px) | best shift (mm) | RMS mismatch at 0 | RMS mismatch, least |",
              "| --- | --- | --- | --- | --- |"]
    for ph, chk in check_rows:
        o = chk["opposed_rays"]
        z = o["mismatch"][len(o["mismatch"]) // 2]
        lines.append(f"| {ph} | {o['best_shift_px']:.3f} | {o['best_shift_mm']:.4f} | {z:.6f} | {min(o['mismatch']):.6f} |")
    lines += ["", "## 2. Calibration from a perturbed nominal geometry", ""]
    for sec in sections:
        lines += sec
    with open(out / "realdata.json", "w") as fh:
        json.dump(report, fh, indent=2, default=lambda o: o.tolist() if isinstance(o, np.ndarray) else str(o))
    with open(out / "realdata.md", "w") as fh:
        fh.write("\n".join(lines) + f"\nTotal {report['wall_s'] / 60:.1f} min.\n")
    say(f"wrote {out}/realdata.md, realdata.json ({report['wall_s'] / 60:.1f} min)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
