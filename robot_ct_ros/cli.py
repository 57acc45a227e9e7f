"""robot-ct: the jobs that need no ROS plumbing (simulate, inspect, reconstruct, calibrate a scan bag,
compare calibration methods on it).

  robot-ct simulate --phantom carotid --views 360 --out scan_bag
  robot-ct info scan_bag
  robot-ct reconstruct scan_bag --out out/recon
  robot-ct calibrate scan_bag --method ncc-lle-exact --iterations 2 --out out/calib
  robot-ct report scan_bag --methods none,ncc-lle-exact,gdc-log --out out/report
  robot-ct demo --out out/demo
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

PHANTOMS = ("mouse", "battery", "carotid")


# ------------------------------------------------------------------------------ helpers
def _say(message: str) -> None:
    print(f"[robot-ct] {message}", flush=True)


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    return repr(o)


def write_volume(volume: np.ndarray, grid, out: Path, stem: str = "volume") -> list:
    """``volume.npy`` and ``volume.tif`` (float32 z-stack, ImageJ spacing in mm) plus the grid JSON."""
    import tifffile

    out.mkdir(parents=True, exist_ok=True)
    vol = np.ascontiguousarray(volume, dtype=np.float32)
    np.save(out / f"{stem}.npy", vol)
    vx, vy, vz = grid.voxel_size_mm
    tifffile.imwrite(out / f"{stem}.tif", vol, imagej=True, resolution=(1.0 / vx, 1.0 / vy),
                     metadata={"spacing": vz, "unit": "mm", "axes": "ZYX"})
    (out / f"{stem}_grid.json").write_text(json.dumps(grid.to_dict(), indent=2))
    return [str(out / f"{stem}.npy"), str(out / f"{stem}.tif"), str(out / f"{stem}_grid.json")]


def _grid_for(scan, voxel_mm=None, shape=None):
    return scan.default_grid(voxel_size_mm=voxel_mm, shape_zyx=None if shape is None else tuple(shape)[::-1])


def _geometry_error(scan, geom) -> dict | None:
    """RMS of the 9 parameters between ``geom`` and the bag's true geometry (simulated bags only)."""
    if scan.geom_true is None:
        return None
    d = geom.params_relative_to(scan.geom_true)
    return {"rms_translation_mm": float(np.sqrt((d[:, :6] ** 2).mean())),
            "rms_rotation_deg": float(np.rad2deg(np.sqrt((d[:, 6:] ** 2).mean()))),
            "note": "raw difference to /ct/geometry_true, global (gauge) motion not removed"}


def _base_report(scan, grid) -> dict:
    return {"bag": str(scan.path), "format": scan.info.get("format"), "n_views": scan.n_views,
            "detector": [scan.geom.n_rows, scan.geom.n_cols], "projection_units": scan.units,
            "recovered": scan.recovered, "bag_warnings": list(scan.warnings), "grid": grid.to_dict()}


def reconstruct_bag(bag, out, *, geometry: str = "auto", voxel_mm=None, shape=None, say=_say) -> dict:
    """FDK of a scan bag with its geometry (``auto``: corrected if present, else nominal).

    Writes ``volume.npy``, ``volume.tif``, ``volume_grid.json`` and ``report.json`` in ``out``.
    """
    from robot_ct_ros.bag import read_scan
    from robot_ct_ros.ct.reconstruction import fdk

    t0 = time.perf_counter()
    out = Path(out)
    scan = read_scan(bag)
    for w in scan.warnings:
        say(f"warning: {w}")
    if geometry == "corrected" and scan.geom_corrected is None:
        raise SystemExit(f"{bag} has no /ct/geometry_corrected")
    use_corrected = geometry == "corrected" or (geometry == "auto" and scan.geom_corrected is not None)
    geom = scan.geom_corrected if use_corrected else scan.geom
    li, mask = scan.to_line_integrals()
    grid = _grid_for(scan, voxel_mm, shape)
    say(f"{scan.n_views} views, detector {geom.n_rows}x{geom.n_cols}; FDK on {grid.shape_zyx[::-1]} voxels of "
        f"{grid.voxel_size_mm[0] * 1000:.1f} um ({'corrected' if use_corrected else 'nominal'} geometry)")
    vol = fdk(li, geom, grid, valid_mask=mask)
    files = write_volume(vol, grid, out)
    report = _base_report(scan, grid)
    report.update({"job": "reconstruct", "geometry": "corrected" if use_corrected else "nominal",
                   "geometry_error": _geometry_error(scan, geom), "files": files,
                   "wall_s": time.perf_counter() - t0})
    (out / "report.json").write_text(json.dumps(report, indent=2, default=_json_default))
    say(f"wrote {out}/volume.npy, volume.tif, report.json ({report['wall_s']:.1f} s)")
    return report


def _calibrate_kwargs(scan, prior_sigma, stop_update_px, drift_order=None, seed: int = 0, padding=None) -> dict:
    """calibrate()'s ``prior_sigma`` (``"default"``: calibration.DEFAULT_PRIOR_SIGMA),
    ``drift_order`` (None: off) with ``drift_times``, ``seed``, ``padding`` (None:
    calibration.DEFAULT_PADDING), and, when given, ``stop_update_px`` (None keeps calibrate's
    default). The drift model's time axis is the
    frames' stamps (s): a pause in the scan is then a gap in time, not one view's step (the
    view index without usable stamps)."""
    from robot_ct_ros.ct.calibration import DEFAULT_PADDING, DEFAULT_PRIOR_SIGMA

    prior = DEFAULT_PRIOR_SIGMA if isinstance(prior_sigma, str) and prior_sigma == "default" else prior_sigma
    times = None
    if drift_order is not None:
        t = (np.asarray(scan.stamps_ns, np.int64) - int(scan.stamps_ns[0])).astype(np.float64) * 1e-9
        times = t if np.ptp(t) > 0 else None
    return ({"prior_sigma": prior, "drift_order": None if drift_order is None else int(drift_order),
             "drift_times": times, "seed": int(seed),
             "padding": DEFAULT_PADDING if padding is None else float(padding)}
            | ({} if stop_update_px is None else {"stop_update_px": float(stop_update_px)}))


def _estimate(li, geom, grid, *, method: str, ensemble: int = 1, **kwargs):
    """calibration.calibrate, or for an LLE method with ``ensemble`` > 1 calibrate_ensemble (the
    mean of that many runs with different sampling seeds; the baselines draw no samples, so
    they run once)."""
    from robot_ct_ros.ct.calibration import LLE_METHODS, calibrate, calibrate_ensemble

    if ensemble > 1 and method in LLE_METHODS:
        return calibrate_ensemble(li, geom, grid, method=method, members=ensemble, **kwargs)
    return calibrate(li, geom, grid, method=method, **kwargs)


def _prior_json(prior):
    return None if prior is None else [float(x) for x in prior]


REPORT_METHODS = ("none", "ncc-lle-exact", "gdc-log")
"""Default columns of ``robot-ct report``: the nominal geometry, this system's method, and the
strongest published baseline."""


def report_bag(bag, out, *, methods=REPORT_METHODS, iterations: int = 2, voxel_mm=None, shape=None,
               schedule: str = "accurate", prior_sigma="default", stop_update_px: float | None = None,
               drift_order: int | None = None, seed: int = 0, ensemble: int = 1, padding: float | None = None,
               say=_say) -> dict:
    """Compare calibration methods on one scan bag: figures like the NCC-LLE paper's and a table.

    ``methods``: ``"none"`` (FDK with the nominal geometry) and any of calibration.METHODS, each
    run on the same data with the same settings (:func:`calibrate_bag`'s). Added by themselves:
    ``"bag corrected"`` when the bag holds /ct/geometry_corrected (e.g. from recon_service), and
    ``"true geometry"`` when it holds /ct/geometry_true (simulated scans): then the table also
    has the gauge-aligned reprojection error and the SSIM against the true-geometry
    reconstruction, and a figure the per-view parameter error. Writes into ``out``
    (:func:`robot_ct_ros.ct.report.write_report`, name ``report``): ``report_slices.png``,
    ``report_rmse.png``, ``report_param_error.png`` (truth known), ``report.md``,
    ``report.json``. Returns the table rows and the paths.
    """
    from robot_ct_ros.bag import read_scan
    from robot_ct_ros.ct.calibration import METHODS, projection_consistency
    from robot_ct_ros.ct.reconstruction import fdk
    from robot_ct_ros.ct.report import markdown_table, write_report

    methods = tuple(methods)
    unknown = [m for m in methods if m not in ("none",) + METHODS]
    if unknown or not methods:
        raise ValueError(f"methods must be among none, {', '.join(METHODS)}; "
                         + (f"unknown: {', '.join(unknown)}" if unknown else "none given"))
    t0 = time.perf_counter()
    scan = read_scan(bag)
    for w in scan.warnings:
        say(f"warning: {w}")
    li, mask = scan.to_line_integrals()
    grid = _grid_for(scan, voxel_mm, shape)
    kwargs = _calibrate_kwargs(scan, prior_sigma, stop_update_px, drift_order, seed, padding)
    say(f"{scan.n_views} views, detector {scan.geom.n_rows}x{scan.geom.n_cols}, grid {grid.shape_zyx[::-1]} of "
        f"{grid.voxel_size_mm[0] * 1000:.1f} um; methods {', '.join(methods)}; at most {iterations} iteration(s), "
        f"schedule {schedule}")

    def reconstruct(geom):
        return fdk(li, geom, grid, valid_mask=mask)

    def timed_fdk(geom):
        t = time.perf_counter()
        return geom, reconstruct(geom), (), time.perf_counter() - t

    results = {}
    for method in methods:
        if method == "none":
            results[method] = timed_fdk(scan.geom)
        else:
            say(f"{method}:")
            results[method] = _estimate(li, scan.geom, grid, method=method, ensemble=ensemble, n_iter=iterations,
                                        valid_mask=mask, schedule=schedule, progress=lambda m: say(f"  {m}"),
                                        **kwargs)
    if scan.geom_corrected is not None:
        results["bag corrected"] = timed_fdk(scan.geom_corrected)
    truth = None
    if scan.geom_true is not None:
        results["true geometry"] = timed_fdk(scan.geom_true)
        truth = (scan.geom_true, results["true geometry"][1], None)
    initial = projection_consistency(results["none"][1], grid, scan.geom, li, mask)[0] if "none" in results else None
    name = Path(bag).name.removesuffix(".mcap")
    paths = write_report(out, results, grid, truth, scan.geom, name="report", title=f"{name}: {scan.n_views} views",
                         initial_rmse=initial, reconstruct=reconstruct if truth is not None else None,
                         notes={"bag": str(bag), "iterations": iterations, "schedule": schedule,
                                "prior_sigma": _prior_json(kwargs["prior_sigma"]),
                                "drift_order": kwargs["drift_order"], "seed": kwargs["seed"], "ensemble": ensemble,
                                "padding": kwargs["padding"],
                                "grid": grid.to_dict(), "bag_warnings": list(scan.warnings)})
    say("\n" + markdown_table(paths["rows"]))
    say(f"wrote {', '.join(str(paths[k]) for k in ('slices', 'rmse', 'param_error', 'markdown', 'json') if k in paths)}"
        f" ({time.perf_counter() - t0:.1f} s)")
    return paths


def calibration_methods() -> tuple:
    """The methods ``robot-ct calibrate`` accepts: the calibration module's, and ``fdk`` (no correction)."""
    from robot_ct_ros.ct.calibration import METHODS

    return METHODS + ("fdk",)


def calibrate_bag(bag, out, *, method: str = "ncc-lle-exact", iterations: int = 2, voxel_mm=None, shape=None,
                  schedule: str = "accurate", prior_sigma="default", stop_update_px: float | None = None,
                  drift_order: int | None = None, seed: int = 0, ensemble: int = 1, padding: float | None = None,
                  say=_say) -> dict:
    """Calibrate the per-view geometry of a scan bag offline and reconstruct it.

    Runs :func:`robot_ct_ros.ct.calibration.calibrate` (method, at most ``iterations``
    outer iterations, schedule, stop_update_px (None: calibrate's default),
    prior_sigma: ``"default"`` for calibration.DEFAULT_PRIOR_SIGMA, None for the data alone;
    drift_order: None for independent per-view errors, a degree for a slowly drifting geometry;
    seed: the LLE methods' sampling seed; ensemble: average that many runs with different
    seeds, calibration.calibrate_ensemble; padding: the estimation grid's widening across (None:
    calibration.DEFAULT_PADDING); ``"fdk"`` only reconstructs with the nominal
    geometry). Writes into ``out``: the corrected bag (``<bag name>_corrected``: every message
    of the input plus /ct/geometry_corrected), ``volume.npy``/``.tif``/``_grid.json`` and
    ``report.json``.
    """
    from robot_ct_ros.bag import read_scan, write_corrected_bag
    from robot_ct_ros.ct.reconstruction import fdk

    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scan = read_scan(bag)
    for w in scan.warnings:
        say(f"warning: {w}")
    li, mask = scan.to_line_integrals()
    grid = _grid_for(scan, voxel_mm, shape)
    say(f"{scan.n_views} views, detector {scan.geom.n_rows}x{scan.geom.n_cols}, grid {grid.shape_zyx[::-1]} of "
        f"{grid.voxel_size_mm[0] * 1000:.1f} um; method {method}, {iterations} iteration(s), schedule {schedule}")
    report = _base_report(scan, grid)
    report.update({"job": "calibrate", "method": method, "iterations": iterations, "schedule": schedule})
    geom, volume, history, notes = scan.geom, None, [], []
    if method != "fdk":
        kwargs = _calibrate_kwargs(scan, prior_sigma, stop_update_px, drift_order, seed, padding)
        report["prior_sigma"] = _prior_json(kwargs["prior_sigma"])
        report["drift_order"] = kwargs["drift_order"]
        report["seed"] = kwargs["seed"]
        report["padding"] = kwargs["padding"]
        result = _estimate(li, scan.geom, grid, method=method, ensemble=ensemble, n_iter=iterations, valid_mask=mask,
                           schedule=schedule, progress=say, **kwargs)
        geom, volume = result.geom, result.volume
        report["ensemble"] = result.members
        if result.members > 1:  # the members' spread around their mean: the estimate's sampling noise
            report["ensemble_spread_px"] = result.spread_px
        report["iterations_run"] = len(result.history)
        # strict JSON: a quantity an iteration did not measure (NaN) is null
        history = [{k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in h.__dict__.items()}
                   for h in result.history]
    if volume is None:
        volume = fdk(li, geom, grid, valid_mask=mask)
    report["method_used"] = method
    name = Path(bag).name.removesuffix(".mcap")
    corrected_bag = out / f"{name}_corrected"
    if corrected_bag.exists():
        import shutil
        shutil.rmtree(corrected_bag)
    write_corrected_bag(bag, corrected_bag, geom, scan.stamps_ns,
                        notes=f"calibrated with {report['method_used']}, {iterations} iteration(s)")
    files = write_volume(volume, grid, out)
    d = geom.params_relative_to(scan.geom)
    report.update({
        "history": history, "notes": notes, "corrected_bag": str(corrected_bag), "files": files,
        "correction_rms_translation_mm": float(np.sqrt((d[:, :6] ** 2).mean())),
        "correction_rms_rotation_deg": float(np.rad2deg(np.sqrt((d[:, 6:] ** 2).mean()))),
        "geometry_error_nominal": _geometry_error(scan, scan.geom),
        "geometry_error_corrected": _geometry_error(scan, geom),
        "wall_s": time.perf_counter() - t0})
    (out / "report.json").write_text(json.dumps(report, indent=2, default=_json_default))
    say(f"wrote {corrected_bag}, {out}/volume.npy, volume.tif, report.json ({report['wall_s']:.1f} s)")
    return report


def simulate_bag(out, *, phantom: str = "carotid", views: int = 360, rows: int = 272, cols: int = 636,
                 binning: int = 2, sigma_mm: float = 0.1, sigma_deg: float = 0.1, seed: int = 0,
                 drift_mm: float = 0.0, drift_deg: float = 0.0, photons: float | None = None,
                 fov_mm: float | None = None, sim_voxel_mm: float | None = None, chunk_views: int = 8,
                 progress: bool = True, say=_say) -> Path:
    """Simulate a seed-system robotic ROI scan of a phantom and record it as a scan bag at ``out``.

    The nominal geometry (/ct/geometry) is :func:`robotic_roi_scan`; the frames are
    simulated along it perturbed by independent per-view robot errors (``sigma_mm`` on the
    6 translations, ``sigma_deg`` on the 3 rotations) plus, optionally, a detector that drifts
    linearly by ``drift_mm`` (its 3 translations) and ``drift_deg`` (its 3 rotations) over the
    scan; the bag keeps the true geometry on /ct/geometry_true. Frames are photon counts
    (``photons`` per binned pixel per frame unattenuated; default: 4,000 behind 13 cm of
    water) with flat field and dead pixels.
    """
    from tqdm import tqdm

    from robot_ct_ros.bag import ScanBagWriter, default_stamps, scan_info_for
    from robot_ct_ros.ct import simulation as sim
    from robot_ct_ros.ct.geometry import VolumeGrid
    from robot_ct_ros.ct.trajectory import SeedSystem, fov_radius_mm, robotic_roi_scan

    system = SeedSystem()
    pitch = system.raw_pixel_mm * binning
    if fov_mm is None:
        fov_mm = 0.999 * 2 * fov_radius_mm(0.5 * cols * pitch, system.sod_mm, system.sdd_mm)
    nominal = robotic_roi_scan(system, n_views=views, binning=binning, n_rows=rows, n_cols=cols,
                               fov_diameter_mm=fov_mm)
    model = sim.robot_coordination(sigma_mm, sigma_deg, seed=seed)
    if drift_mm or drift_deg:
        model = model + sim.detector_drift(drift_mm / max(views - 1, 1), drift_deg / max(views - 1, 1), kind="linear")
    errors = model.sample(views)
    true = nominal.perturbed(errors)
    factories = {"mouse": sim.mouse_phantom, "battery": sim.battery_phantom, "carotid": sim.carotid_plaque_phantom}
    ph = factories[phantom](seed=seed)
    det = (sim.DetectorModel.from_transmitted(4000.0, 130.0, binning=binning, seed=seed) if photons is None
           else sim.DetectorModel(photons_per_pixel=photons, binning=binning, seed=seed))
    voxel = pitch / system.magnification
    axial = rows * pitch / system.magnification
    roi = VolumeGrid.centered((max(1, round(axial / voxel)), max(1, round(fov_mm / voxel)),
                               max(1, round(fov_mm / voxel))), voxel)
    say(f"{phantom} phantom, {views} views, detector {rows}x{cols} at {pitch * 1000:.0f} um (binning {binning}), "
        f"FOV {fov_mm:.2f} mm, robot errors {sigma_mm} mm / {sigma_deg} deg"
        + (f", detector drift {drift_mm} mm / {drift_deg} deg over the scan" if drift_mm or drift_deg else "")
        + f", seed {seed}")
    gproj = sim.raw_geometry(true, binning)
    if sim_voxel_mm is None:  # half the reconstruction voxel, coarser when the ROI would need > 200^3 voxels
        sim_voxel_mm = max(0.5 * voxel, float(np.prod(roi.extent_mm)) ** (1 / 3) / 200)
    say(f"phantom voxelised at {sim_voxel_mm * 1000:.1f} um in the ROI, {max(0.4, 4 * sim_voxel_mm):.2f} mm outside")
    parts = sim.scan_volumes(ph, gproj, sim_voxel_mm, roi_grid=roi, outer_voxel_size_mm=max(0.4, 4 * sim_voxel_mm))
    rng = np.random.default_rng(seed)
    raw_shape = (rows * binning, cols * binning)
    flat, valid = sim.simulate_flat(raw_shape, det, rng)
    info = scan_info_for(nominal, binning=binning, projection_units="counts", roi_center_mm=roi.center_mm,
                         roi_size_mm=roi.extent_mm, voxel_size_mm=roi.voxel_size_mm, phantom=phantom,
                         notes={"simulated": True, "seed": seed, "photons_per_pixel": det.photons_per_pixel,
                                "robot_error_sigma_mm": sigma_mm, "robot_error_sigma_deg": sigma_deg,
                                "detector_drift_mm": drift_mm, "detector_drift_deg": drift_deg,
                                "generator": "robot-ct simulate"})
    stamps = default_stamps(views)
    t0 = int(stamps[0]) - 1_000_000
    out = Path(out)
    if out.exists():
        raise ValueError(f"{out} exists already; a bag is never overwritten")
    with ScanBagWriter(out, info, start_ns=t0) as w:
        w.write_flat(flat, t0)
        w.write_dead_pixels(~valid, t0)
        bar = tqdm(total=views, desc="simulate", unit="view", disable=not progress, file=sys.stdout)
        for v0 in range(0, views, chunk_views):
            sel = np.arange(v0, min(views, v0 + chunk_views))
            li = sim.project_parts(parts, gproj.subset(sel))
            counts = sim.simulate_counts(li, det, rng, flat=flat)[0]
            for k, i in enumerate(sel):
                w.write_frame(counts[k], nominal, int(stamps[i]), int(i), true=true)
            bar.update(len(sel))
        bar.close()
    say(f"wrote {out} ({views} frames)")
    return out


# ------------------------------------------------------------------------------ commands
def _cmd_simulate(args) -> int:
    simulate_bag(args.out, phantom=args.phantom, views=args.views, rows=args.rows, cols=args.cols,
                 binning=args.binning, sigma_mm=args.sigma_mm, sigma_deg=args.sigma_deg, seed=args.seed,
                 drift_mm=args.drift_mm, drift_deg=args.drift_deg,
                 photons=args.photons, fov_mm=args.fov_mm, sim_voxel_mm=args.sim_voxel_mm, progress=not args.quiet)
    return 0


def _cmd_info(args) -> int:
    from robot_ct_ros.bag import summarize

    s = summarize(args.bag)
    if args.json:
        print(json.dumps(s, indent=2, default=_json_default))
        return 0 if "scan_error" not in s else 1
    print(f"bag        {s['path']} (read with {s['reader']}{', RECOVERED' if s['recovered'] else ''})")
    if "duration_s" in s:
        print(f"duration   {s['duration_s']:.2f} s")
    for t, d in s["topics"].items():
        print(f"topic      {t:<28} {d['type']:<36} {d['messages']:>6} msgs")
    if "scan_error" in s:
        print(f"NOT A USABLE SCAN: {s['scan_error']}")
        return 1
    info = s["scan_info"]
    print(f"format     {info['format']}, projection units {info['projection_units']}, binning {info['binning']}")
    print(f"views      {s['paired_views']} paired frames")
    print(f"detector   {s['detector']}")
    print(f"geometry   SDD {s['source_to_detector_mm']:.1f} mm, magnification {s['magnification']:.3f}, "
          f"centre {np.round(s['scan_center_mm'], 3).tolist()} mm")
    print(f"pixels     {100 * s['valid_pixel_fraction']:.2f} % valid")
    print(f"extras     corrected geometry: {'yes' if s['has_geometry_corrected'] else 'no'}, "
          f"true geometry: {'yes' if s['has_geometry_true'] else 'no'}")
    if info.get("phantom"):
        print(f"phantom    {info['phantom']}")
    for w in s["warnings"]:
        print(f"warning    {w}")
    return 0


def _number_at_least(minimum, what: str, whole: bool = True):
    """An argparse type: a number (a whole one with ``whole``) >= ``minimum``, with ``what``
    named in the error."""
    def parse(text: str):
        try:
            value = int(text) if whole else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what} must be a {'whole ' if whole else ''}number, "
                                             f"got {text!r}") from None
        if not value >= minimum:
            raise argparse.ArgumentTypeError(f"{what} must be >= {minimum}")
        return value
    return parse


_ensemble = _number_at_least(1, "ensemble")
_drift_order = _number_at_least(0, "drift order")
_padding = _number_at_least(1, "padding", whole=False)  # the estimation grid holds the ROI grid


def _prior_sigma(text: str):
    """``MM,DEG`` -> the 9 prior standard deviations (mm x6, rad x3); ``none`` -> None;
    ``default`` -> calibration.DEFAULT_PRIOR_SIGMA."""
    if text.strip().lower() == "none":
        return None
    if text.strip().lower() == "default":
        from robot_ct_ros.ct.calibration import DEFAULT_PRIOR_SIGMA

        return DEFAULT_PRIOR_SIGMA
    try:
        mm, deg = (float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError("prior sigma is MM,DEG (e.g. 0.3,0.3) or none") from None
    if mm <= 0 or deg <= 0:
        raise argparse.ArgumentTypeError("prior sigmas must be positive")
    from robot_ct_ros.ct.calibration import prior_sigma_from

    return prior_sigma_from(mm, deg)


def _shape(text: str):
    parts = [int(x) for x in text.lower().replace("x", ",").split(",") if x]
    if len(parts) != 3:
        raise argparse.ArgumentTypeError("shape is NX,NY,NZ (or NXxNYxNZ)")
    return tuple(parts)


def _cmd_reconstruct(args) -> int:
    reconstruct_bag(args.bag, args.out, geometry=args.geometry, voxel_mm=args.voxel_mm, shape=args.shape)
    return 0


def _cmd_report(args) -> int:
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    report_bag(args.bag, args.out, methods=methods, iterations=args.iterations, voxel_mm=args.voxel_mm,
               shape=args.shape, schedule=args.schedule, prior_sigma=args.prior_sigma,
               stop_update_px=args.stop_update_px, drift_order=args.drift_order, seed=args.seed,
               ensemble=args.ensemble, padding=args.padding)
    return 0


def _cmd_calibrate(args) -> int:
    calibrate_bag(args.bag, args.out, method=args.method, iterations=args.iterations, voxel_mm=args.voxel_mm,
                  shape=args.shape, schedule=args.schedule, prior_sigma=args.prior_sigma,
                  stop_update_px=args.stop_update_px, drift_order=args.drift_order, seed=args.seed,
                  ensemble=args.ensemble, padding=args.padding)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="robot-ct", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="scan, record and correct a simulated robotic interior scan end to end")
    from robot_ct_ros.demo import add_demo_arguments

    add_demo_arguments(demo)

    p = sub.add_parser("simulate", help="simulate a robotic ROI scan of a phantom into a scan bag")
    p.add_argument("--phantom", choices=PHANTOMS, default="carotid")
    p.add_argument("--views", type=int, default=360, help="number of views (default 360)")
    p.add_argument("--rows", type=int, default=272, help="detector rows after binning (default 272)")
    p.add_argument("--cols", type=int, default=636, help="detector columns after binning (default 636)")
    p.add_argument("--binning", type=int, default=2, help="readout binning of the 55 um pixels (default 2)")
    p.add_argument("--sigma-mm", type=float, default=0.1, help="robot error per view, translations (mm)")
    p.add_argument("--sigma-deg", type=float, default=0.1, help="robot error per view, detector rotations (deg)")
    p.add_argument("--drift-mm", type=float, default=0.0,
                   help="detector drift over the whole scan, linear, each of its translations (mm; default 0)")
    p.add_argument("--drift-deg", type=float, default=0.0,
                   help="detector drift over the whole scan, linear, each of its rotations (deg; default 0)")
    p.add_argument("--photons", type=float, default=None,
                   help="unattenuated counts per binned pixel per frame (default: 4,000 behind 13 cm of water)")
    p.add_argument("--fov-mm", type=float, default=None, help="field-of-view diameter (default: the centred detector's)")
    p.add_argument("--sim-voxel-mm", type=float, default=None,
                   help="voxel of the phantom in the ROI (default: half the reconstruction voxel, at most 200^3 voxels)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--out", required=True, help="output bag directory (must not exist)")

    p = sub.add_parser("info", help="summarise a bag (topics, scan, pairing, damage)")
    p.add_argument("bag")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")

    for name, helptext in (("reconstruct", "FDK of a scan bag with its geometry"),
                           ("calibrate", "correct the per-view geometry of a scan bag offline and reconstruct"),
                           ("report", "compare calibration methods on a scan bag: slice, RMSE and parameter-error "
                                      "figures and a table")):
        p = sub.add_parser(name, help=helptext)
        p.add_argument("bag")
        p.add_argument("--out", required=True, help="output folder")
        p.add_argument("--voxel-mm", type=float, default=None, help="voxel size (default: scan_info or pitch/M)")
        p.add_argument("--shape", type=_shape, default=None, help="grid NX,NY,NZ (default: scan_info ROI or FOV)")
        if name == "reconstruct":
            p.add_argument("--geometry", choices=("auto", "nominal", "corrected"), default="auto",
                           help="auto: /ct/geometry_corrected when present")
        else:
            if name == "calibrate":
                p.add_argument("--method", default="ncc-lle-exact",
                               help=f"one of {', '.join(calibration_methods())} (fdk: no correction)")
            else:
                p.add_argument("--methods", default=",".join(REPORT_METHODS),
                               help="comma-separated: none (nominal geometry) and calibration methods "
                                    f"(default {','.join(REPORT_METHODS)}); the bag's corrected and true "
                                    "geometries are added when it holds them")
            p.add_argument("--iterations", type=int, default=2,
                           help="outer iterations at most (default 2; fewer when one moves the views < --stop-px)")
            p.add_argument("--stop-px", type=float, default=None, dest="stop_update_px",
                           help="stop when an iteration moves the views less than this (gauge-aligned mean px; "
                                "default 0.05; 0: always --iterations)")
            from robot_ct_ros.ct.calibration import DEFAULT_PADDING, SCHEDULES

            p.add_argument("--schedule", choices=tuple(SCHEDULES), default="accurate",
                           help="accurate: 2x binned then full size with SIRT; fast (large scans): 4x then 2x "
                                "binned, SIRT on the coarse level only (default accurate)")
            p.add_argument("--prior-sigma", type=_prior_sigma, default="default", metavar="MM,DEG",
                           help="the robots' per-view coordination error (translations in mm, rotations in deg), "
                                "the prior of the MAP estimate; 'none': the data alone (default 0.3,0.3)")
            p.add_argument("--drift-order", type=_drift_order, default=None, metavar="DEGREE",
                           help="the geometry drifts slowly (e.g. a detector warming up): fit every parameter "
                                "with a polynomial of this degree in time (the frames' stamps) after each iteration "
                                "(default: off, independent per-view errors; 3 suits a smooth drift)")
            p.add_argument("--seed", type=int, default=0,
                           help="the LLE methods' sampling seed (default 0): another seed is another estimate of "
                                "the same scan, and their spread the estimate's own scatter")
            p.add_argument("--ensemble", type=_ensemble, default=1, metavar="K",
                           help="average K runs of an LLE method with the sampling seeds SEED, SEED+1000, ... "
                                "(K times the time, less sampling noise; the report gives their spread; default 1)")
            p.add_argument("--padding", type=_padding, default=None, metavar="FACTOR",
                           help="widen the ROI grid this many times across for the volume the views are registered "
                                f"against (default {DEFAULT_PADDING:g}; about 2 helped objects several times wider than the field "
                                "of view and hurt mildly truncated ones: README)")

    args = parser.parse_args(argv)
    if args.command == "demo":
        from robot_ct_ros.demo import run_demo

        return run_demo(args)
    from robot_ct_ros.bag import ScanBagError

    try:
        return {"simulate": _cmd_simulate, "info": _cmd_info, "reconstruct": _cmd_reconstruct,
                "calibrate": _cmd_calibrate, "report": _cmd_report}[args.command](args)
    except ScanBagError as exc:
        print(f"robot-ct {args.command}: {exc}", file=sys.stderr)
        return 2
    except ValueError as exc:
        print(f"robot-ct {args.command}: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
