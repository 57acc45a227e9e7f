"""Benchmark: a full-size scan of the seed system, end to end, with wall time and peak memory per stage.

The seed system's scan as it is read out (issue #21 item 1): 360 views of 636 x 272 pixels
(70 x 30 mm at 55 um, 2 x 2 binned: 110 um), the robotic ROI trajectory (robotic_roi_scan) with
the detector offset that widens the field of view to 50 mm, the rotation axis along +y (RTK's,
so that RTK's FDK of the same scan is a fair yardstick). The object: interior_neck_phantom
scaled to a 60 mm neck (``--body``, 1.2 times the field of view: the scan is truncated) with the
carotid plaque at the ROI centre (a 110 mm neck, 2.2 times the field of view, is explained too
poorly by the ROI model: the guard keeps the nominal geometry, as on bench_interior's neck; that
needs the exterior model); exact line integrals (simulation.ellipsoid_line_integrals, numba; the
same numbers as RTK's ray-quadric intersection, test_rtk_bridge) on the raw 55 um detector (a
chunk of views at a time), photon counting (4,000 counts behind the body, chip gaps, dead pixels) and 2 x 2 binning (simulate_scan with keep_intermediates=False: one
float32 stack). Independent robot errors of 0.3 mm / 0.3 deg per view.

Stages, each printed as it runs, with its wall time and its peak resident memory (a thread
samples VmRSS in /proc/self/status every 20 ms, reset at the start of each stage; ru_maxrss, the
process's peak so far, next to it):

  simulate   the scan above
  calibrate  calibration.calibrate(ncc-lle-exact, 2 iterations, schedule "fast": 4x then 2x binned
             estimation volumes), without its final full-size FDK (final_volume=False)
  fdk        the full-resolution FDK of the ROI with the calibrated geometry: 45 um voxels, the
             50 mm field of view across (1,111^2) and the detector's axial extent at the centre
             (249 planes), float32 (1.2 GB)
  write      that volume as a tiled BigTIFF OME-TIFF, slab by slab (jobs.output.write_ome_tiff)
  rtk-fdk    one RTK FDK (itk-rtk, CPU) of the same scan onto the same grid, in a child process
             (its memory is its own; ``--rtk-binning N`` runs it on the N-times binned grid, runs ours
             on that grid too, and scales RTK's time by the voxel count for the ratios)

Writes ``fullsize.md``, ``fullsize.json`` and ``fullsize.log`` (the printed lines) into ``--out``
and the volume into ``--volume-out`` (not committed: 1.2 GB). ``--scale s`` (2/s an integer) keeps the field of view and the object
and coarsens the scan: pixels of 110/s um (the same detector binned 2/s x 2/s), voxels of 45/s
um; the report then says CUT-DOWN in its title.

    .venv/bin/python bench/bench_fullsize.py --rtk-binning 2 --out docs/results   # ~35 min on 2 shared cores
    .venv/bin/python bench/bench_fullsize.py --views 36 --scale 0.25 --out /tmp/fullsize
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import sys
import threading
import time
from contextlib import contextmanager

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from bench_calibration import BENCH_OWNS, bench_settings, centred_fov_mm, changed_sentence  # noqa: E402

from robot_ct_ros.cli import add_settings_arguments  # noqa: E402
from robot_ct_ros.ct import calibration  # noqa: E402
from robot_ct_ros.ct import simulation as sim  # noqa: E402
from robot_ct_ros.ct.geometry import VolumeGrid  # noqa: E402
from robot_ct_ros.ct.metrics import gauge_aligned_reprojection_error, roi_points  # noqa: E402
from robot_ct_ros.ct.trajectory import SeedSystem, robotic_roi_scan, roi_scan_offset_mm  # noqa: E402

AXIS_Y = Rotation.from_rotvec([-np.pi / 2, 0.0, 0.0]).as_matrix()  # the scan's z axis becomes +y (RTK)
PHOTONS_BEHIND_BODY = 4000.0
VOXEL_MM = 0.045
FOV_MM = 50.0
TARGETS = {"calibrate_s": 600.0, "peak_rss_gb": 8.0}
"""The issue's targets: calibration within 10 minutes, peak resident memory within 8 GB."""
GB = 1e9
FULLSIZE_OWNS = (*BENCH_OWNS, "schedule")
"""Settings this bench sets itself (--method, --iterations, --schedule, --seed; the prior is --sigma); every other
field of CalibrationSettings has its command-line option (--exterior on --exterior-half-width-mm 80, ...)."""


def rss_bytes(pid: str = "self") -> int:
    """Resident memory (VmRSS) of a process, bytes; 0 where /proc is not there."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def maxrss_bytes(who=resource.RUSAGE_SELF) -> int:
    return resource.getrusage(who).ru_maxrss * 1024  # Linux: KiB


class MemorySampler:
    """A daemon thread sampling this process's VmRSS every ``interval_s``; :meth:`stage` measures a
    stage's wall time and the peak of those samples (reset at its start)."""

    def __init__(self, interval_s: float = 0.02):
        self.interval_s = interval_s
        self.peak = rss_bytes()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        self.stages = []

    def _run(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, rss_bytes())
            self._stop.wait(self.interval_s)

    def close(self):
        self._stop.set()
        self._thread.join()

    @contextmanager
    def stage(self, name: str, say, **extra):
        start_rss = rss_bytes()
        self.peak = start_rss
        say(f"stage {name}: start (resident {start_rss / GB:.2f} GB)")
        t0 = time.perf_counter()
        record = {"stage": name, **extra}
        yield record
        record.update(wall_s=time.perf_counter() - t0, start_rss_gb=start_rss / GB,
                      peak_rss_gb=max(self.peak, rss_bytes()) / GB, end_rss_gb=rss_bytes() / GB,
                      ru_maxrss_gb=maxrss_bytes() / GB, loadavg_1min=os.getloadavg()[0])
        self.stages.append(record)
        say(f"stage {name}: {record['wall_s']:.1f} s, peak resident {record['peak_rss_gb']:.2f} GB "
            f"(end {record['end_rss_gb']:.2f} GB, ru_maxrss {record['ru_maxrss_gb']:.2f} GB, load {record['loadavg_1min']:.1f})")


def field_of_view_mm(args, system: SeedSystem, binning: int) -> float:
    """The scan's field of view (mm): ``--fov``, or with ``--fov 0`` the centred detector's own (no offset; as
    bench_calibration's scenarios, centred_fov_mm)."""
    if args.fov > 0:
        return float(args.fov)
    return centred_fov_mm(system, system.n_cols_raw // binning, system.raw_pixel_mm * binning)


def scan_layout(args, system: SeedSystem) -> tuple[int, float]:
    """(binning, field of view in mm) of the options; ValueError naming the option when the scale is not 2/k or the
    field of view is not one the detector reaches (robotic_roi_scan's offset limit)."""
    if not (args.scale > 0 and math.isfinite(args.scale)):
        raise ValueError("--scale must be 2/k for an integer k (0.5, 0.25, ...)")
    binning = int(round(system.binning / args.scale))
    if binning < 1 or abs(binning * args.scale - system.binning) > 1e-9:
        raise ValueError("--scale must be 2/k for an integer k (0.5, 0.25, ...)")
    if not (args.fov >= 0 and math.isfinite(args.fov)):
        raise ValueError("--fov must be 0 (the centred detector's own) or a positive diameter in mm")
    fov_mm = field_of_view_mm(args, system, binning)
    half_width_mm = 0.5 * (system.n_cols_raw // binning) * system.raw_pixel_mm * binning
    try:
        roi_scan_offset_mm(fov_mm, half_width_mm, system.sod_mm, system.sdd_mm)
    except ValueError as exc:
        raise ValueError(f"--fov: {exc}") from None
    return binning, fov_mm


def make_scan(args, say):
    """Nominal and true geometry, the simulated scan (line integrals, valid mask), the ROI grid."""
    system = SeedSystem()
    binning, fov_mm = scan_layout(args, system)
    pitch = system.raw_pixel_mm * binning
    nominal = robotic_roi_scan(system, fov_diameter_mm=fov_mm, n_views=args.views, binning=binning).moved(AXIS_Y)
    errors = sim.robot_coordination(args.sigma, args.sigma, seed=args.seed).sample(args.views)
    true = nominal.perturbed(errors)
    phantom = sim.interior_neck_phantom(args.seed, body_width_mm=args.body).moved(AXIS_Y)
    voxel = VOXEL_MM / args.scale
    nxy = int(round(fov_mm / voxel))
    axial_mm = nominal.n_rows * pitch / system.magnification  # the detector's axial extent at the centre
    nz = int(math.floor(axial_mm / voxel))
    grid = VolumeGrid.centered((nz, nxy, nxy), voxel).moved(AXIS_Y)
    sim_binning = 2
    raw = sim.raw_geometry(true, sim_binning)
    detector = sim.DetectorModel.from_transmitted(PHOTONS_BEHIND_BODY, args.body, binning=sim_binning,
                                                  raw_pitch_mm=raw.col_pitch_mm, seed=args.seed)
    done = [0]

    def projector(g):  # exact line integrals of one chunk of views on the raw detector
        out = sim.ellipsoid_line_integrals(phantom.primitives, g)
        done[0] += g.n_views
        if done[0] % 40 < g.n_views or done[0] == args.views:
            say(f"  simulated {done[0]}/{args.views} views")
        return out

    scan = sim.simulate_scan(phantom, true, detector, projector=projector, rng=np.random.default_rng(args.seed + 12345),
                             chunk_views=8, keep_intermediates=False)
    offset = roi_scan_offset_mm(fov_mm, 0.5 * nominal.n_cols * pitch, system.sod_mm, system.sdd_mm)
    geo = {"views": args.views, "detector_rows": nominal.n_rows, "detector_cols": nominal.n_cols,
           "pixel_um": pitch * 1000, "raw_simulation_pixel_um": raw.col_pitch_mm * 1000,
           "fov_mm": fov_mm, "detector_offset_mm": offset, "body_mm": args.body, "voxel_um": voxel * 1000, "grid_xyz": [nxy, nxy, nz],
           "axial_mm": axial_mm, "stack_mb": scan.line_integrals.nbytes / 1e6,
           "volume_gb": 4.0 * nxy * nxy * nz / GB, "scan_binning": binning}
    return nominal, true, scan.line_integrals, scan.valid_mask, grid, geo


def _rtk_child(stack_path, geom, grid, queue):
    """One RTK FDK in a child process: wall time and the child's own peak memory."""
    from robot_ct_ros.ct.rtk_bridge import _rtk, rtk_fdk

    _rtk()  # import itk/RTK and instantiate the templates outside the timing
    rtk_fdk(np.zeros((2, 8, 8), np.float32), geom.subset(slice(0, 2)).with_detector(8, 8),
            VolumeGrid.centered((8, 8, 8), 1.0))
    li = np.load(stack_path, mmap_mode="r")
    sampler = MemorySampler()
    start = rss_bytes()
    t0 = time.perf_counter()
    vol = rtk_fdk(li, geom, grid, hann_cutoff=1.0)
    wall = time.perf_counter() - t0
    peak = max(sampler.peak, rss_bytes())
    sampler.close()
    queue.put({"wall_s": wall, "start_rss_gb": start / GB, "peak_rss_gb": peak / GB, "ru_maxrss_gb": maxrss_bytes() / GB,
               "volume_shape": list(vol.shape), "finite": bool(np.isfinite(vol).all())})


def run_rtk(li, geom, grid, scratch, say) -> dict:
    import multiprocessing as mp

    path = os.path.join(scratch, "stack_for_rtk.npy")
    np.save(path, li)
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    p = ctx.Process(target=_rtk_child, args=(path, geom, grid, queue))
    p.start()
    try:
        out = queue.get()
    finally:
        p.join()
        os.remove(path)
    say(f"  RTK FDK onto {grid.shape_zyx[::-1]} (x, y, z): {out['wall_s']:.1f} s, child peak resident "
        f"{out['peak_rss_gb']:.2f} GB")
    return out


def report_markdown(out: dict) -> str:
    g, s = out["geometry"], {r["stage"]: r for r in out["stages"]}
    cut = out["cut_down"]
    rtk = out.get("rtk")
    changed = out["calibration"].get("settings_changed") or {}
    title = ("# CUT-DOWN full-size scan benchmark (bench/bench_fullsize.py)" if cut
             else "# Full-size scan, end to end (bench/bench_fullsize.py)")
    lines = [title, ""]
    if cut:
        lines += [f"**Cut-down run, not the full size**: {g['views']} views, scale {out['settings']['scale']:g} "
                  f"(pixels {g['pixel_um']:.0f} um, voxels {g['voxel_um']:.0f} um). The full size is "
                  "`--views 360 --scale 1`.", ""]
    lines += [
        f"The seed system's robotic ROI scan: {g['views']} views of {g['detector_cols']} x {g['detector_rows']} pixels "
        f"of {g['pixel_um']:.0f} um (simulated on {g['raw_simulation_pixel_um']:.0f} um raw pixels: exact "
        f"ray-ellipsoid line integrals, photon counting, binned), "
        + (f"offset detector for a {g['fov_mm']:.0f} mm field of view (detector offset {g['detector_offset_mm']:.1f} mm)"
           if g["detector_offset_mm"] > 0 else f"centred detector, its own {g['fov_mm']:.1f} mm field of view")
        + f", rotation axis +y; interior_neck_phantom as a {g['body_mm']:.0f} mm neck "
        f"({g['body_mm'] / g['fov_mm']:.1f} times the field of view); robot errors {out['settings']['sigma']:g} mm / "
        f"{out['settings']['sigma']:g} deg per view. Calibration: {out['calibration']['method']}, "
        f"{out['calibration']['iterations']} iterations, schedule {out['calibration']['schedule']!r}, the prior the "
        f"robots' accuracy"
        + (", **started at the true geometry** (how far the loop leaves it)" if out["calibration"].get("from_true")
           else "")
        + ". " + (changed_sentence(changed) + " " if changed else "The other settings at their defaults. ")
        + f"Full-resolution ROI grid {g['grid_xyz'][0]} x {g['grid_xyz'][1]} x "
        f"{g['grid_xyz'][2]} voxels of {g['voxel_um']:.0f} um ({g['volume_gb']:.2f} GB float32); projection stack "
        f"{g['stack_mb']:.0f} MB.", "",
        f"Machine: {out['machine']}, numba threads {out['numba_threads']}, {out['memory_total_gb']:.0f} GB; "
        f"1-min load average {out['loadavg_start']:.1f} at the start and per stage below (where it stands above the "
        "cores' count, other jobs shared the machine and the wall times read high). Peak resident memory: VmRSS sampled every 20 ms "
        "by a thread, reset per stage; ru_maxrss is the process's peak so far. RTK ran in a spawned child process "
        "(its memory is its own; the child's ru_maxrss starts from the parent's resident size at the fork, so its "
        "sampled peak is the figure to read).", "",
        "| stage | wall (s) | / RTK FDK | peak resident (GB) | resident after (GB) | ru_maxrss so far (GB) | load |",
        "| --- | --- | --- | --- | --- | --- | --- |"]
    for r in out["stages"]:
        ratio = f"{r['wall_s'] / rtk['full_grid_s']:.2f}" if rtk else "-"
        lines.append(f"| {r['stage']} | {r['wall_s']:.1f} | {ratio} | {r['peak_rss_gb']:.2f} | {r['end_rss_gb']:.2f} | "
                     f"{r['ru_maxrss_gb']:.2f} | {r['loadavg_1min']:.1f} |")
    if rtk:
        binned = out["settings"]["rtk_binning"] > 1
        if binned:
            lines.append(f"| RTK FDK, scaled to the full grid | {rtk['full_grid_s']:.1f} | 1.00 | - | - | - | - |")
        lines.append(f"| RTK FDK{' (measured on the grid binned %d: %s)' % (out['settings']['rtk_binning'], ' x '.join(map(str, rtk['grid_zyx'][::-1]))) if binned else ''} "
                     f"| {rtk['wall_s']:.1f} | {rtk['wall_s'] / rtk['full_grid_s']:.2f} | {rtk['peak_rss_gb']:.2f} (child) | - | "
                     f"{rtk['ru_maxrss_gb']:.2f} (child) | - |")
        if binned:
            lines.append(f"| our FDK on that binned grid | {rtk['ours_same_grid_s']:.1f} | "
                         f"{rtk['ours_same_grid_s'] / rtk['full_grid_s']:.2f} | - | - | - | - |")
    c = out["calibration"]
    lines += ["", f"- Calibration: {c['wall_s']:.1f} s (target <= {TARGETS['calibrate_s']:.0f} s: "
              f"{'met' if c['wall_s'] <= TARGETS['calibrate_s'] else 'MISSED'}); gauge-aligned reprojection error of ROI "
              f"points {c['error_before_px']:.3f} px -> {c['error_after_px']:.3f} px mean (p95 {c['p95_before_px']:.3f} -> "
              f"{c['p95_after_px']:.3f})"
              + (f", {c['unguarded_error_px']:.3f} px before the guard" if c.get("unguarded_error_px") is not None else "")
              + (f"; model NCC {c['model_ncc']:.3f}" if c.get("model_ncc") is not None else "")
              + "; per iteration: "
              + "; ".join(f"{h['iteration']}: NCC {h['projection_ncc']:.4f}, {h['wall_s']:.0f} s" for h in c["history"]),
              f"- Peak resident memory over all stages: {out['peak_rss_gb']:.2f} GB (target <= {TARGETS['peak_rss_gb']:g} "
              f"GB: {'met' if out['peak_rss_gb'] <= TARGETS['peak_rss_gb'] else 'MISSED'}); ru_maxrss at the end "
              f"{out['ru_maxrss_gb']:.2f} GB.",
              f"- Volume file: {os.path.basename(out['volume_file'])}, {out['volume_file_gb']:.2f} GB, tiled "
              f"{out['tile'][0]} x {out['tile'][1]} BigTIFF OME-TIFF, written slab by slab (edge tiles are stored whole, "
              f"zero-padded: {out['volume_file_gb'] / g['volume_gb']:.2f} x the volume's bytes).",
              f"- Calibration + full-resolution FDK + write: {out['pipeline_s']:.1f} s"
              + (f" = {out['pipeline_s'] / rtk['full_grid_s']:.2f} RTK FDKs"
                 + (" (RTK's time on the binned grid scaled by the voxel count: RTK at full size did not fit this run's "
                    "time; RTK and ours on the same binned grid in the table)" if out["settings"]["rtk_binning"] > 1 else "")
                 + "." if rtk else ".")]
    lines += [f"- Note: {n}" for n in c["notes"]]
    if c["history"]:
        first = c["wall_s"] - sum(h["wall_s"] for h in c["history"])
        lines.append(f"- Of the calibration's {c['wall_s']:.0f} s, {first:.0f} s went to the estimation volume entering the "
                     "first iteration (coarse level: FDK and SIRT), the rest to the iterations above (each: the coarse "
                     "estimate, the finer level's FDK and estimate, the next coarse volume).")
    if c.get("log"):
        lines += ["", "The calibration's progress lines (seconds into the stage):", "", "```"]
        lines += [f"{t:7.1f} s  {m}" for t, m in c["log"]] + ["```"]
    lines += ["", f"Total {out['wall_s'] / 60:.1f} min. Command: `python bench/bench_fullsize.py "
              f"{' '.join(out['argv'])}`.", ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--views", type=int, default=360)
    ap.add_argument("--scale", type=float, default=1.0, help="1: the seed system's readout; 0.5, 0.25: coarser")
    ap.add_argument("--body", type=float, default=60.0, help="neck width, mm (default 60)")
    ap.add_argument("--sigma", type=float, default=0.3, help="robot error per view, mm and deg")
    ap.add_argument("--method", default="ncc-lle-exact")
    ap.add_argument("--iterations", type=int, default=2)
    ap.add_argument("--schedule", default="fast", choices=tuple(calibration.SCHEDULES))
    ap.add_argument("--rtk-binning", type=int, default=1, help="run RTK's FDK on the grid binned this much")
    ap.add_argument("--no-rtk", action="store_true")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="out/bench_fullsize", help="where fullsize.md and fullsize.json go")
    ap.add_argument("--volume-out", default="out/bench_fullsize", help="where the OME-TIFF goes")
    ap.add_argument("--render", default=None, metavar="JSON",
                    help="only rewrite fullsize.md (into --out) from a fullsize.json this bench wrote")
    ap.add_argument("--fov", type=float, default=FOV_MM,
                    help=f"field of view, mm (default {FOV_MM:g}: the offset detector; 0: the centred detector's own)")
    ap.add_argument("--from-true", action="store_true",
                    help="start the calibration at the true geometry: how far the loop leaves it (its floor)")
    add_settings_arguments(ap, skip=FULLSIZE_OWNS)
    args = ap.parse_args(argv)
    if args.prior_sigma is not None:
        ap.error("--prior-sigma: the prior is the robots' accuracy (--sigma), as a user states it")
    try:  # a scale or field of view the seed detector cannot give: one line, before anything runs
        scan_layout(args, SeedSystem())
    except ValueError as exc:
        ap.error(str(exc))
    base, changed = bench_settings(args, FULLSIZE_OWNS)
    if args.render:
        with open(args.render) as f:
            out = json.load(f)
        with open(os.path.join(args.out, "fullsize.md"), "w") as f:
            f.write(report_markdown(out))
        return 0
    os.makedirs(args.out, exist_ok=True)
    os.makedirs(args.volume_out, exist_ok=True)
    t_all = time.perf_counter()

    printed = []

    def say(msg):
        printed.append(f"[{time.perf_counter() - t_all:7.1f} s] {msg}")
        print(printed[-1], flush=True)

    import numba

    from robot_ct_ros.ct.reconstruction import fdk
    from robot_ct_ros.jobs.output import available_memory_bytes, write_ome_tiff

    with open("/proc/meminfo") as f:
        mem_total = int(f.readline().split()[1]) * 1024
    out = {"bench": "bench/bench_fullsize.py", "argv": sys.argv[1:] if argv is None else list(argv),
           "settings": vars(args), "cut_down": args.views != 360 or args.scale != 1.0,
           "machine": f"{platform.machine()}, {os.cpu_count()} cores", "numba_threads": numba.get_num_threads(),
           "memory_total_gb": mem_total / GB, "memory_available_gb_start": available_memory_bytes() / GB,
           "loadavg_start": os.getloadavg()[0], "targets": TARGETS}
    say(f"bench_fullsize: {args.views} views, scale {args.scale:g}; {os.cpu_count()} CPU(s), numba threads "
        f"{numba.get_num_threads()}, load {out['loadavg_start']:.1f}")
    mem = MemorySampler()
    with mem.stage("simulate", say):
        nominal, true, li, mask, grid, geo = make_scan(args, say)
    out["geometry"] = geo
    say(f"  {geo['views']} views {geo['detector_cols']} x {geo['detector_rows']} of {geo['pixel_um']:.0f} um; grid "
        f"{geo['grid_xyz']} of {geo['voxel_um']:.0f} um ({geo['volume_gb']:.2f} GB); stack {geo['stack_mb']:.0f} MB")
    settings = base.replace(method=args.method, iterations=args.iterations,
                            schedule=args.schedule).with_prior(args.sigma, args.sigma)
    start = true if args.from_true else nominal
    pts = roi_points(grid)
    log = []

    def progress(message):  # the calibration's own lines, kept with the time into the stage
        log.append([round(time.perf_counter() - t_cal, 1), message])
        say(f"    {message}")

    t_cal = time.perf_counter()
    with mem.stage("calibrate", say):
        res = calibration.calibrate(li, start, grid, settings, valid_mask=mask, final_volume=False,
                                    progress=progress)
    e0 = gauge_aligned_reprojection_error(start, true, pts)
    e1 = gauge_aligned_reprojection_error(res.geom, true, pts)
    unguarded = (gauge_aligned_reprojection_error(start.perturbed(res.params_unguarded), true, pts)["mean_px"]
                 if res.params_unguarded is not None else None)
    out["calibration"] = {"method": args.method, "iterations": args.iterations, "schedule": args.schedule,
                          "settings": res.settings.to_dict(), "settings_changed": changed,
                          "from_true": bool(args.from_true), "wall_s": mem.stages[-1]["wall_s"],
                          "error_before_px": e0["mean_px"], "error_after_px": e1["mean_px"],
                          "p95_before_px": e0["p95_px"], "p95_after_px": e1["p95_px"],
                          "unguarded_error_px": unguarded,
                          "model_ncc": res.history[-1].projection_ncc if res.history else None,
                          "history": [vars(h) for h in res.history], "notes": list(res.notes), "log": log}
    say(f"  error {e0['mean_px']:.3f} -> {e1['mean_px']:.3f} px mean (gauge-aligned, ROI points)")
    with mem.stage("fdk", say):
        volume = fdk(li, res.geom, grid, valid_mask=mask)
    tile = (256, 256)
    path = os.path.join(args.volume_out, "fullsize_volume.ome.tif")
    with mem.stage("write", say):
        write_ome_tiff(volume, grid, path, tile=tile)
    out["volume_file"] = path
    out["tile"] = list(tile)
    out["volume_file_gb"] = os.path.getsize(path) / GB
    out["volume_stats"] = {"min": float(volume.min()), "max": float(volume.max()), "mean": float(volume.mean())}
    del volume
    out["pipeline_s"] = sum(r["wall_s"] for r in mem.stages if r["stage"] in ("calibrate", "fdk", "write"))
    out["peak_rss_gb"] = max(r["peak_rss_gb"] for r in mem.stages)
    out["ru_maxrss_gb"] = maxrss_bytes() / GB
    mem.close()
    if not args.no_rtk:
        say("stage rtk-fdk: start (child process)")
        rgrid = grid.binned(args.rtk_binning) if args.rtk_binning > 1 else grid
        rtk = run_rtk(li, res.geom, rgrid, args.volume_out, say) | {"grid_zyx": list(rgrid.shape_zyx)}
        rtk["full_grid_s"] = rtk["wall_s"]
        if args.rtk_binning > 1:  # RTK on the binned grid; ours on it too, and RTK scaled to the full grid
            t0 = time.perf_counter()
            fdk(li, res.geom, rgrid, valid_mask=mask)
            rtk["ours_same_grid_s"] = time.perf_counter() - t0
            rtk["full_grid_s"] = rtk["wall_s"] * float(np.prod(grid.shape_zyx)) / float(np.prod(rgrid.shape_zyx))
            say(f"  our FDK onto the same binned grid: {rtk['ours_same_grid_s']:.1f} s; RTK scaled by the voxel count to "
                f"the full grid: {rtk['full_grid_s']:.1f} s")
        out["rtk"] = rtk
    out["stages"] = mem.stages
    out["loadavg_end"] = os.getloadavg()[0]
    out["wall_s"] = time.perf_counter() - t_all
    with open(os.path.join(args.out, "fullsize.json"), "w") as f:
        json.dump(out, f, indent=2, default=lambda o: o.tolist() if isinstance(o, np.ndarray) else
                  (o.item() if isinstance(o, np.generic) else str(o)))
    md = report_markdown(out)
    with open(os.path.join(args.out, "fullsize.md"), "w") as f:
        f.write(md)
    print("\n" + md, flush=True)
    say(f"wrote {args.out}/fullsize.md, fullsize.json, fullsize.log")
    with open(os.path.join(args.out, "fullsize.log"), "w") as f:
        f.write("\n".join(printed) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
