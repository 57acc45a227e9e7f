"""Benchmark: per-view geometry calibration methods on three simulated robotic interior scans.

Scenarios (seeded; the seed system's ROI trajectory, robotic_roi_scan, on a reduced
detector; photon-counting noise, flat field and dead pixels from DetectorModel):

  a  mouse phantom (scaled to a 9 mm body, mildly truncated), ROI in the thorax; independent
     robot errors on all 9 DOF (0.3 mm, 0.3 deg)
  b  battery (Li-ion cell, scaled to 5 mm radius: can and outer turns truncated), ROI in the
     jelly roll; slow linear detector drift
     (about 0.6 mm and 0.15 deg over the scan, on all 6 detector parameters)
  c  carotid plaque with a 60 um fibrous cap, ROI on the cap; independent robot errors

Every other setting of CalibrationSettings has its option, as on ``robot-ct calibrate`` (e.g.
``--fov-support on``, ``--padding 2``), applied to every correcting method and named in results.md.

Methods: none (nominal geometry), l2-lle, ncc-lle, ncc-lle-exact, gdc, gdc-log (all through
calibration.calibrate, one alternating loop), true geometry; on the drift scenario (b) also
ncc-lle-exact with the drift model (calibrate(drift_order=3), no per-view prior), and on the
strongly truncated neck (c) ncc-lle-exact with the exterior model (calibrate(exterior="on")
reaching the neck's far side). Per method:
gauge-aligned reprojection error of ROI points (mean, p95, px), SSIM against the true-geometry
reconstruction, edge sharpness, cap thickness (c, on a full-resolution strip: CapStrip), outer
iterations, wall time; with --repeats N each LLE method again with N - 1 more sampling seeds on
the same scan (calibrate(seed=); their scatter, and the mean of their geometries as
calibrate(ensemble=K) makes it, below each table). Writes results.md,
results.json and figures (report.py) into --out (default out/bench_calibration; the published
ones, docs/results, only when named, as ``make bench-calibration`` does).

    .venv/bin/python bench/bench_calibration.py --out docs/results   # defaults: about 7 min on 2 cores (15 with --repeats 3)
    .venv/bin/python bench/bench_calibration.py --views 60 --det 48x64 --vol 48 --scenarios a
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from types import SimpleNamespace

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from robot_ct_ros.ct import calibration  # noqa: E402
from robot_ct_ros.ct.calibration.volume import projection_consistency  # noqa: E402
from robot_ct_ros.ct import simulation as sim  # noqa: E402
from robot_ct_ros.ct.geometry import VolumeGrid  # noqa: E402
from robot_ct_ros.ct.reconstruction import fdk  # noqa: E402
from robot_ct_ros.ct.metrics import roi_points  # noqa: E402
from robot_ct_ros.jobs.figures import markdown_table, method_notes, plot_cap_slabs, summarize, write_report  # noqa: E402
from robot_ct_ros.ct.trajectory import SeedSystem, fov_radius_mm, robotic_roi_scan  # noqa: E402
from robot_ct_ros.cli import add_settings_arguments, settings_from_args  # noqa: E402

DRIFT_METHOD = "ncc-lle-exact + drift(3)"
"""ncc-lle-exact with the geometry fitted as a cubic drift in acquisition order
(calibrate(drift_order=3)) and without the robots' per-view prior, which the drift model
replaces (with it: 0.79 against 0.69 px on (b)). Only where the errors are a drift."""
DRIFT_SCENARIOS = ("b",)
EXTERIOR_SUFFIX = " + exterior"
EXTERIOR_METHOD = "ncc-lle-exact" + EXTERIOR_SUFFIX
"""ncc-lle-exact registering the views against the ROI and a coarse model of the object around it
(calibrate(exterior="on"), reaching from the ROI centre to the object's far side). In the
results table only on the strongly truncated scenario (c); the truncation sweep runs it at
every width. Any other correcting method takes the same suffix (``--methods "gdc + exterior"``),
run only where this one is."""
EXTERIOR_SCENARIOS = ("c",)
ALL_METHODS = ("none", "l2-lle", "ncc-lle", "ncc-lle-exact", "gdc", "gdc-log", DRIFT_METHOD, EXTERIOR_METHOD,
               "true geometry")
EXTERIOR_METHODS = tuple(m + EXTERIOR_SUFFIX for m in calibration.method_names() if m != calibration.NO_CORRECTION)
"""Every correcting method with the exterior model (the ``--methods`` names; EXTERIOR_METHOD is the default's)."""
SCENARIOS = {
    "a": "mouse (9 mm body) thorax, independent 9-DOF robot errors (0.3 mm, 0.3 deg)",
    "b": "battery (5 mm radius), slow detector drift (0.6 mm, 0.15 deg over the scan)",
    "c": "carotid plaque in a full neck (strongly truncated), 60 um cap, independent 9-DOF robot errors (0.3 mm, 0.3 deg)",
}


SIM_BINNING = 2  # the scans are simulated on 110 um pixels, then binned to the readout's
PHOTONS_PER_MM2 = 4000.0 / (SIM_BINNING * SeedSystem.raw_pixel_mm) ** 2
"""Flat-field photons per mm^2 behind 130 mm of water: 4000 per simulated (110 um) pixel."""


def _det(text: str) -> tuple[int, int]:
    parts = [int(x) for x in text.lower().replace(",", "x").split("x") if x]
    if len(parts) == 1:
        parts = parts * 2
    if len(parts) != 2:
        raise argparse.ArgumentTypeError("detector is ROWSxCOLS")
    return parts[0], parts[1]


def far_side_mm(phantom, center_mm) -> float:
    """How far ``phantom`` reaches from ``center_mm`` across the z axis (its bounding box's farthest side
    in x or y, mm): the reach a user states for the exterior model (exterior_half_width_mm)."""
    lo, hi = (np.asarray(b, float) for b in phantom.bounds_mm())
    c = np.asarray(center_mm, float)
    return float(np.max(np.maximum(c[:2] - lo[:2], hi[:2] - c[:2])))


def make_scenario(key: str, views: int, det: tuple[int, int], vol: int, binning: int, seed: int, say,
                  sim_oversample: int = 2, phantom_scale: float = 1.0, n_axial: int | None = None, errors_of=None):
    """Nominal and true geometry, simulated scan, ROI grid, phantom and truth reconstruction.

    The ROI grid has ``vol`` voxels across and ``n_axial`` along the axis (default: 90 % of
    what the central ray's cone covers, at most ``vol``). The field of view is simulated on a
    grid ``sim_oversample`` times finer than the reconstruction's. ``phantom_scale`` scales the
    mouse and the battery (a larger detector at the same pixel size needs a larger object for
    the same truncation). ``errors_of`` (nominal geometry -> (views, 9) parameters) replaces the
    scenario's robot errors (bench_conjugate_modes: one angular harmonic)."""
    system = SeedSystem()
    rows, cols = det
    pitch = system.raw_pixel_mm * binning
    fov = centred_fov_mm(system, cols, pitch)
    if key == "a":
        phantom = sim.mouse_phantom(body_width_mm=9.0 * phantom_scale, length_mm=40.0 * phantom_scale, seed=seed)  # scaled with the detector
        center = np.array([0.0, 0.0, 0.0])  # thorax
        errors = sim.robot_coordination(0.3, 0.3, seed=seed).sample(views)
    elif key == "b":
        phantom = sim.battery_phantom(radius_mm=5.0 * phantom_scale, height_mm=12.0 * phantom_scale, seed=seed)  # scaled with the detector
        center = np.array([1.0, 0.0, 0.0])  # in the jelly roll, off the mandrel
        errors = sim.detector_drift(0.6 / views, 0.15 / views, kind="linear", seed=seed).sample(views)
    elif key == "c":
        phantom = sim.carotid_plaque_phantom(cap_thickness_mm=0.060, seed=seed)
        cap = phantom.cap
        center = np.asarray(cap.lumen_point_mm) + 0.5 * cap.thickness_mm * np.asarray(cap.direction)
        errors = sim.robot_coordination(0.3, 0.3, seed=seed + 1).sample(views)
    else:
        raise ValueError(f"unknown scenario {key!r}")
    # the exterior model's grid (a square about the ROI centre across the axis) reaches the object's far side
    exterior_half_width_mm = far_side_mm(phantom, center)
    nominal = robotic_roi_scan(system, roi_center_mm=tuple(center), fov_diameter_mm=fov, n_views=views,
                               binning=binning, n_rows=rows, n_cols=cols)
    if errors_of is not None:
        errors = np.asarray(errors_of(nominal), np.float64)
    true = nominal.perturbed(errors)
    voxel = pitch / system.magnification
    axial = rows * pitch / system.magnification
    nxy = vol
    nz = max(8, min(vol, int(0.9 * axial / voxel))) if n_axial is None else int(n_axial)
    vs = 0.95 * fov / nxy  # the grid covers the field of view
    grid = VolumeGrid.centered((nz, nxy, nxy), vs, center)
    # simulation: a fine grid over the field of view (1/sim_oversample of the reconstruction voxel), coarse elsewhere
    sim_roi = VolumeGrid.centered((max(1, round(axial * 1.2 / vs)), round(fov * 1.1 / vs), round(fov * 1.1 / vs)),
                                  vs, center)
    detector = sim.DetectorModel.from_transmitted(PHOTONS_PER_MM2 * (SIM_BINNING * system.raw_pixel_mm) ** 2,
                                                  130.0, binning=SIM_BINNING, seed=seed)
    t0 = time.perf_counter()
    scan = sim.simulate_scan(phantom, true, detector, voxel_size_mm=vs / sim_oversample, roi_grid=sim_roi,
                             outer_voxel_size_mm=0.4, rng=seed, chunk_views=8)
    say(f"  simulated {views} views {rows}x{cols} at {pitch * 1000:.0f} um, grid {grid.shape_zyx[::-1]} of "
        f"{vs * 1000:.1f} um, FOV {fov:.2f} mm ({time.perf_counter() - t0:.1f} s)")
    sc = SimpleNamespace(key=key, phantom=phantom, nominal=nominal, true=true, errors=errors, grid=grid,
                         li=scan.line_integrals, mask=scan.valid_mask, fov_mm=fov, pitch_mm=pitch,
                         exterior_half_width_mm=exterior_half_width_mm)
    sc.reconstruct = lambda geom: fdk(sc.li, geom, sc.grid, valid_mask=sc.mask)  # FDK of the scan onto the ROI grid
    return sc


CAP_STRIP_ROWS = 192       # unbinned detector rows around the cap: ±2 mm along the vessel at the ROI
CAP_VOXEL_MM = 0.020       # about the unbinned pixel at the ROI (55 um / 2.67)
CAP_SIM_VOXEL_MM = 0.0125  # phantom voxels of the strip's simulation near the cap


class CapStrip:
    """Scenario (c)'s cap at the detector's full resolution.

    The cap (60 um) is thinner than the calibration's binned pixels (82 um at the ROI) and its
    grid's voxels (115 um), so it is measured as a user would after calibrating: a fine
    reconstruction (``CAP_VOXEL_MM``) of a small box around the cap from the unbinned
    detector (55 um), with each method's geometry. Simulated here as a strip of
    ``CAP_STRIP_ROWS`` unbinned rows across the full detector width, with the binned scan's
    photons per area (its own Poisson noise, dead pixels and chip gaps) and the phantom on
    ``CAP_SIM_VOXEL_MM`` voxels near the cap. Calling it with a (gauge-aligned) binned
    geometry returns the fine reconstruction and its grid, and keeps the volume (``volumes``,
    by ``label``) for the figure (report.plot_cap_slabs).
    """

    def __init__(self, sc, photons_per_mm2: float, seed: int, say):
        raw = SeedSystem().raw_pixel_mm
        self.cols = int(round(sc.nominal.n_cols * sc.nominal.col_pitch_mm / raw))
        self.raw_mm = raw
        center = sc.grid.center_mm
        self.grid = VolumeGrid.centered((150, 100, 100), CAP_VOXEL_MM, center)  # 3 x 2 x 2 mm (z, y, x)
        t0 = time.perf_counter()
        true = self.crop(sc.true)
        box = VolumeGrid.centered(tuple(int(round(e / CAP_SIM_VOXEL_MM)) for e in (3.6, 3.0, 3.0)),
                                  CAP_SIM_VOXEL_MM, center)
        parts = sim.scan_volumes(sc.phantom, true, CAP_SIM_VOXEL_MM, box, 0.4, max_voxels=120_000_000)
        det = sim.DetectorModel.from_transmitted(photons_per_mm2 * raw * raw, 130.0, binning=1, seed=seed)
        scan = sim.simulate_scan(sc.phantom, true, det, parts=parts, rng=seed + 100, chunk_views=8)
        self.li, self.mask = scan.line_integrals, scan.valid_mask
        self.volumes = {}
        say(f"  cap strip: {true.n_views} views {CAP_STRIP_ROWS}x{self.cols} unbinned ({raw * 1000:.0f} um), "
            f"fine grid {self.grid.shape_zyx[::-1]} of {CAP_VOXEL_MM * 1000:.0f} um "
            f"({time.perf_counter() - t0:.1f} s)")

    def crop(self, geom):
        """The unbinned strip of ``geom``'s detector: same detector centre and frame."""
        return geom.with_detector(CAP_STRIP_ROWS, self.cols, self.raw_mm, self.raw_mm)

    def __call__(self, geom, label=None):
        vol = fdk(self.li, self.crop(geom), self.grid, valid_mask=self.mask)
        if label is not None:
            self.volumes[label] = vol
        return vol, self.grid


SAMPLED_METHODS = tuple(m.name for m in calibration.METHODS.values() if m.samples) + (DRIFT_METHOD,)
"""The methods that draw random samples (calibrate(seed=)); the baselines draw nothing."""
SCATTER_METRICS = ("reproj_mean_px", "reproj_p95_px", "ssim")  # the table's columns that --repeats repeats
REPEAT_SEED_STEP = calibration.ENSEMBLE_SEED_STEP  # --repeats: seeds 0, 1000, ..., an ensemble's members


def run_method(method: str, sc, iterations: int, say, seed: int = 0, base=None):
    """One method on the scenario ``sc``: ((geometry, volume, notes, wall s) or calibrate's result, how it ran).
    ``base`` (CalibrationSettings, default: the defaults) holds the settings every correcting method starts from."""
    t0 = time.perf_counter()
    if method == "none":
        v = sc.reconstruct(sc.nominal)
        return (sc.nominal, v, (), time.perf_counter() - t0), "fdk"
    if method == "true geometry":
        v = sc.reconstruct(sc.true)
        return (sc.true, v, (), time.perf_counter() - t0), "fdk"
    prog = (lambda m: say(f"    {m}"))
    base = calibration.CalibrationSettings() if base is None else base
    if method == DRIFT_METHOD:
        settings = base.replace(method="ncc-lle-exact", iterations=iterations, drift_order=3, seed=seed).without_prior()
        return calibration.calibrate(sc.li, sc.nominal, sc.grid, settings, valid_mask=sc.mask,
                                     progress=prog), "calibration.calibrate(drift_order=3, no prior)"
    if method in EXTERIOR_METHODS:
        settings = base.replace(method=method[:-len(EXTERIOR_SUFFIX)], iterations=iterations, seed=seed,
                                exterior="on", exterior_half_width_mm=sc.exterior_half_width_mm)
        return calibration.calibrate(sc.li, sc.nominal, sc.grid, settings, valid_mask=sc.mask,
                                     progress=prog), (f"calibration.calibrate(exterior=on, half-width "
                                                      f"{sc.exterior_half_width_mm:.0f} mm)")
    if method in calibration.METHODS:
        settings = base.replace(method=method, iterations=iterations, seed=seed)
        return calibration.calibrate(sc.li, sc.nominal, sc.grid, settings, valid_mask=sc.mask,
                                     progress=prog), "calibration.calibrate"
    raise ValueError(f"unknown method {method!r}")


def sampling_scatter(sc, results: dict, rows: list, truth_vol, repeats: int, iterations: int, say,
                     base=None) -> dict:
    """Each sampling method of ``results`` again with ``repeats - 1`` more sampling seeds on the
    same scan, and the mean of all its seeds' geometries (calibration.average_estimates, what
    calibrate(ensemble=K) returns): {method: {"seeds": [{"seed", "reproj_mean_px",
    "reproj_p95_px", "ssim"}, ...] (the table's own run, seed 0, first), "mean_of_seeds": {the
    same metrics, "spread_px"}}}. Same metrics as the table (report.summarize), without the cap."""
    def metrics(res):
        row = summarize({"run": res}, sc.grid, (sc.true, truth_vol, None),
                        reconstruct=sc.reconstruct)[0]
        return {k: row[k] for k in SCATTER_METRICS}

    out = {}
    for row in rows:
        method = row["method"]
        if method not in SAMPLED_METHODS or repeats < 2:
            continue
        runs = [{"seed": 0, **{k: row[k] for k in SCATTER_METRICS}}]
        estimates = [results[method]]
        for r in range(1, repeats):
            seed = r * REPEAT_SEED_STEP
            res, _ = run_method(method, sc, iterations, lambda m: None, seed=seed, base=base)
            estimates.append(res)
            runs.append({"seed": seed, **metrics(res)})
            say(f"  {method}, sampling seed {seed}: {runs[-1]['reproj_mean_px']:.3f} px, SSIM "
                f"{runs[-1]['ssim']:.4f} ({res.wall_s:.1f} s)")
        mean = calibration.average_estimates(estimates, sc.li, sc.nominal, sc.grid, valid_mask=sc.mask)
        out[method] = {"seeds": runs, "mean_of_seeds": {**metrics(mean), "spread_px": mean.spread_px}}
        say(f"  {method}, mean of the {repeats} seeds' geometries: "
            f"{out[method]['mean_of_seeds']['reproj_mean_px']:.3f} px (the seeds lie {mean.spread_px:.3f} px from it)")
    return out


def scatter_lines(scatter: dict) -> list:
    """Markdown lines for :func:`sampling_scatter`'s result (none when it is empty)."""
    if not scatter:
        return []
    seeds = [r["seed"] for r in next(iter(scatter.values()))["seeds"]]
    lines = [f"Sampling scatter: each LLE method again on the same scan with the sampling seeds "
             f"{', '.join(str(x) for x in seeds)} (the table's run is seed 0), and the mean of their geometries "
             f"(calibration.average_estimates, as calibrate(ensemble=K); spread: the seeds' mean distance from it):",
             "", "| method | error mean (px), per seed | mean ± sd | mean geometry: error (px), spread (px) | "
             "SSIM, per seed | SSIM, mean geometry |", "| --- | --- | --- | --- | --- | --- |"]

    def ssim_text(r):
        return "-" if r["ssim"] is None else f"{r['ssim']:.4f}"

    for method, entry in scatter.items():
        runs, mean = entry["seeds"], entry["mean_of_seeds"]
        e = np.array([r["reproj_mean_px"] for r in runs], float)
        errors = " / ".join(f"{x:.3f}" for x in e)
        ssims = " / ".join(ssim_text(r) for r in runs)
        lines.append(f"| {method} | {errors} | {e.mean():.3f} ± {e.std(ddof=1):#.2g} | "
                     f"{mean['reproj_mean_px']:.3f}, {mean['spread_px']:.3f} | {ssims} | {ssim_text(mean)} |")
    return lines + [""]


BENCH_OWNS = ("method", "iterations", "seed")
"""Settings the bench sets itself (--methods, --iterations, the sampling seeds); every other field of
CalibrationSettings has its command-line option here (--fov-support on, --padding 2, ...), applied to
every correcting method."""
EXTERIOR_OWNS = (*BENCH_OWNS, "exterior", "exterior_half_width_mm")
"""What a bench whose rows set the exterior model and its reach themselves owns besides (bench_truncation_sweep.py,
bench_exterior_reach.py)."""


def centred_fov_mm(system: SeedSystem, cols: int, pitch_mm: float) -> float:
    """The field of view (mm) the benches give a centred detector of ``cols`` pixels of ``pitch_mm``: 98 % of the
    circle its edges reach (trajectory.fov_radius_mm), so that robotic_roi_scan needs no offset."""
    return 0.98 * 2 * fov_radius_mm(0.5 * cols * pitch_mm, system.sod_mm, system.sdd_mm)


def changed_settings(settings) -> dict:
    """The fields of ``settings`` that differ from the defaults: {name: value}."""
    default = calibration.CalibrationSettings().to_dict()
    return {k: v for k, v in settings.to_dict().items() if default.get(k) != v}


def bench_settings(args, owns=BENCH_OWNS):
    """(settings, changed): the CalibrationSettings of a bench's parsed options (add_settings_arguments with
    ``skip=owns``), the fields in ``owns``, which the bench sets itself, at their defaults; and
    :func:`changed_settings` of them."""
    default = calibration.CalibrationSettings()
    settings = settings_from_args(args, **{k: getattr(default, k) for k in owns})
    return settings, changed_settings(settings)


def changed_sentence(changed: dict, applied_to: str | None = None) -> str:
    """The report's sentence naming the settings a bench changed ("" when none), e.g. "Settings changed from
    the defaults for every method: `padding` 2."."""
    if not changed:
        return ""
    return (f"Settings changed from the defaults{' for ' + applied_to if applied_to else ''}: "
            + ", ".join(f"`{k}` {v}" for k, v in changed.items()) + ".")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--views", type=int, default=90, help="views per scan (default 90)")
    ap.add_argument("--det", type=_det, default=(64, 96), help="detector ROWSxCOLS after binning (default 64x96)")
    ap.add_argument("--binning", type=int, default=4,
                    help="binning of the 55 um pixels (default 4: 220 um, a scaled-down detector with twice the "
                         "seed system's field of view per pixel; 2 = the seed system's 110 um)")
    ap.add_argument("--vol", type=int, default=64, help="ROI grid voxels across (default 64; axial from the cone)")
    ap.add_argument("--iterations", type=int, default=3, help="outer iterations per method at most (default 3)")
    ap.add_argument("--scenarios", default="abc", help="subset of 'abc' (default abc)")
    ap.add_argument("--methods", default=",".join(ALL_METHODS),
                    help="comma-separated subset of " + ", ".join(ALL_METHODS) + "; any other correcting method with the exterior model: "
                    + ", ".join(m for m in EXTERIOR_METHODS if m != EXTERIOR_METHOD))
    ap.add_argument("--seed", type=int, default=0, help="scenario seed: phantom, errors, noise (default 0)")
    ap.add_argument("--repeats", type=int, default=1,
                    help="run each sampling method (LLE) with this many sampling seeds on the same scan and "
                         "report their scatter below each table (default 1: the table's run only)")
    ap.add_argument("--out", default="out/bench_calibration",
                    help="where results.md, results.json and the figures go (default out/bench_calibration; "
                         "make bench-calibration: docs/results)")
    ap.add_argument("--no-figures", action="store_true", help="write the tables alone (e.g. for a run with a setting changed)")
    add_settings_arguments(ap, skip=BENCH_OWNS)
    args = ap.parse_args(argv)
    base, changed = bench_settings(args)  # --iterations, --seed: the bench's
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    for m in methods:
        if m not in ALL_METHODS and m not in EXTERIOR_METHODS:
            ap.error(f"unknown method {m!r}")
    for s in args.scenarios:
        if s not in SCENARIOS:
            ap.error(f"unknown scenario {s!r}")
    if args.repeats < 1:
        ap.error("--repeats must be >= 1")
    out = os.path.abspath(args.out)
    os.makedirs(out, exist_ok=True)
    t_all = time.perf_counter()

    def say(msg):
        print(f"[{time.perf_counter() - t_all:7.1f} s] {msg}", flush=True)

    import numba
    say(f"bench_calibration: {len(args.scenarios)} scenario(s) x {len(methods)} method(s); {args.views} views, "
        f"detector {args.det[0]}x{args.det[1]}, grid {args.vol}, {args.iterations} iteration(s); "
        f"{os.cpu_count()} CPU(s), numba threads {numba.get_num_threads()}. The defaults take about 7 min "
        f"on a quiet 2-core machine.")
    scenarios = []
    for key in args.scenarios:
        say(f"scenario {key}: {SCENARIOS[key]}")
        sc = make_scenario(key, args.views, args.det, args.vol, args.binning, args.seed, say)
        results, via = {}, {}
        for m in methods:
            if m == DRIFT_METHOD and key not in DRIFT_SCENARIOS:
                continue  # a drift model for independent per-view errors would be the wrong model
            if m in EXTERIOR_METHODS and key not in EXTERIOR_SCENARIOS:
                continue  # the exterior model is for objects much wider than the field of view
            res, via[m] = run_method(m, sc, args.iterations, say, base=base)
            results[m] = res
            wall = res.wall_s if hasattr(res, "wall_s") else res[3]
            say(f"  {m}: {wall:.1f} s ({via[m]})")
        truth_vol = (results["true geometry"][1] if "true geometry" in results
                     else sc.reconstruct(sc.true))
        cap = getattr(sc.phantom, "cap", None)
        truth = (sc.true, truth_vol, SimpleNamespace(cap=cap) if cap is not None else None)
        strip = CapStrip(sc, PHOTONS_PER_MM2, args.seed, say) if cap is not None else None
        initial = projection_consistency(results["none"][1], sc.grid, sc.nominal, sc.li, sc.mask)[0] \
            if "none" in results else None
        title = f"({key}) {SCENARIOS[key]}"
        paths = write_report(out, results, sc.grid, truth, sc.nominal, name=f"scenario_{key}", title=title,
                             initial_rmse=initial, notes={"via": via},
                             reconstruct=sc.reconstruct,
                             reconstruct_cap=strip, figures=not args.no_figures)
        rows = paths["rows"]
        if strip is not None and not args.no_figures:
            paths["cap"] = plot_cap_slabs(
                os.path.join(out, f"scenario_{key}_cap.png"), strip.volumes, strip.grid, cap,
                reference=strip.volumes.get("true geometry"),
                title=f"cap, unbinned strip, {CAP_VOXEL_MM * 1000:.0f} um voxels, axial mean over "
                      f"{strip.grid.extent_mm[2]:.0f} mm of vessel")
        say("\n" + markdown_table(rows))
        notes = method_notes(results, sc.nominal, sc.true, roi_points(sc.grid))
        scatter = sampling_scatter(sc, results, rows, truth_vol, args.repeats, args.iterations, say, base=base)
        scenarios.append({"key": key, "title": title, "rows": rows, "via": via, "notes": notes,
                          "sampling_scatter": scatter,
                          "true_cap_um": None if cap is None else 1000 * cap.thickness_mm,
                          "initial_projection_rmse": initial,
                          "figures": [os.path.basename(str(paths[k])) for k in ("slices", "cap", "rmse", "param_error")
                                      if k in paths],
                          "grid": sc.grid.to_dict(), "fov_mm": sc.fov_mm, "pitch_mm": sc.pitch_mm,
                          "true_error_rms": {"translation_mm": float(np.sqrt((sc.errors[:, :6] ** 2).mean())),
                                             "rotation_deg": float(np.rad2deg(np.sqrt((sc.errors[:, 6:] ** 2).mean())))}})
    total = time.perf_counter() - t_all
    settings = {"views": args.views, "detector": list(args.det), "binning": args.binning, "vol": args.vol,
                "iterations": args.iterations, "seed": args.seed, "repeats": args.repeats, "methods": methods,
                "calibration_settings_changed": changed, "total_wall_s": total, "cpus": os.cpu_count(), "machine": platform.platform(),
                "load_at_end": os.getloadavg()}
    with open(os.path.join(out, "results.json"), "w") as f:
        json.dump({"settings": settings, "scenarios": scenarios}, f, indent=2,
                  default=lambda o: o.item() if isinstance(o, np.generic) else str(o))
    lines = ["# Calibration benchmark (bench/bench_calibration.py)", "",
             f"Simulated robotic interior scans (seed-system ROI trajectory, reduced detector): {args.views} views, "
             f"detector {args.det[0]}x{args.det[1]} at {args.binning * 55} um, photon-counting noise; ROI grid "
             f"{args.vol} voxels across; at most {args.iterations} outer iteration(s) per method (fewer where one "
             f"moved the views less than {base.stop_update_px} px); seed {args.seed}. "
             f"GDC methods: Gauss-Newton variant, see ct/calibration/gdc.py. Reprojection error: ROI "
             f"points, best global rigid motion (gauge) removed, pixels. SSIM against the FDK reconstruction with "
             f"the true geometry, each estimate moved into the true gauge first. Total {total / 60:.1f} min on {os.cpu_count()} CPU(s) "
             f"(load at end {os.getloadavg()[0]:.2f}).", ""]
    if changed:
        lines += [changed_sentence(changed, "every correcting method"), ""]
    for s in scenarios:
        lines += [f"## {s['title']}", ""]
        if s["true_cap_um"] is not None:
            lines += [f"True cap thickness {s['true_cap_um']:.0f} um. Measured as the FWHM of the cap ridge in a "
                      f"{CAP_VOXEL_MM * 1000:.0f} um reconstruction of the unbinned detector strip around the cap "
                      f"({CAP_STRIP_ROWS} rows of {SeedSystem().raw_pixel_mm * 1000:.0f} um) with each method's "
                      f"gauge-aligned geometry (bench_calibration.CapStrip); '-': no ridge 3 standard errors above "
                      f"its surroundings at the cap (metrics.cap_thickness_mm).", ""]
        lines += [markdown_table(s["rows"]), ""] + [f"- {m}: {'; '.join(n)}" for m, n in s["notes"].items()] \
            + [""] + scatter_lines(s["sampling_scatter"]) \
            + [f"![{f}]({f})" for f in s["figures"]] + [""]
    with open(os.path.join(out, "results.md"), "w") as f:
        f.write("\n".join(lines) + "\n")
    say(f"wrote {out}/results.md, results.json{'' if args.no_figures else ' and figures'}; total {total / 60:.1f} min")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
