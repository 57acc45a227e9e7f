"""Benchmark: the calibration's two heavy steps in-process and as Dask tasks, in one run.

On one simulated scan (a circular scan of a few balls with 0.3 mm / 0.3 deg robot errors per
view), in this process on the same data:

  estimation  one LLE pass over all views (ncc-lle-exact, the fine level's settings: 192 samples,
              2 sample sets, the robots' prior) against an FDK of the scan
  FDK         one fdk of the scan: filtering, then back-projection

each timed in-process with numba on N threads, and on a dask.distributed LocalCluster of N
worker processes with one thread each (numba threads per worker = threads per worker = 1), for
N = 1 and 2. The ratio is the Dask time over the in-process time with the same number of
threads. The Dask estimation times include sending the measured projections (a fresh cache
each run: the loop sends them once per level and calibration, the volume once per pass), the
FDK times the filtering in the client process (on N threads) and sending the filtered
projections. Each figure is the fastest of ``--repeats`` runs after a warm-up run (numba
compiles in each worker on its first task), the four kinds of run taking turns so that other
jobs on the machine slow them alike. Writes dask.md and dask.json to ``--out`` (default
out/bench_dask; the published ones, docs/results, only when named, as ``make bench-dask`` does).

    .venv/bin/python bench/bench_dask.py --out docs/results          # about 5 min on 2 cores
    .venv/bin/python bench/bench_dask.py --views 48 --det 64 --repeats 1
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

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from robot_ct_ros.ct.calibration.distributed import DaskExecutor, InProcess, transfer_bytes  # noqa: E402
from robot_ct_ros.ct.calibration.lle.estimator import default_lle_configs, estimate_views  # noqa: E402
from robot_ct_ros.ct.calibration.settings import DEFAULT_PRIOR_SIGMA, CalibrationSettings  # noqa: E402
from robot_ct_ros.ct.geometry import VolumeGrid  # noqa: E402
from robot_ct_ros.ct.projector import forward_project  # noqa: E402
from robot_ct_ros.ct.simulation import robot_coordination  # noqa: E402
from robot_ct_ros.ct.trajectory import circular_scan  # noqa: E402
from robot_ct_ros.jobs.figures import markdown_table  # noqa: E402

BALLS = (((0, 0, 0), 0.38, 0.02), ((0.12, -0.08, 0.15), 0.12, 0.03), ((-0.15, 0.12, -0.08), 0.1, -0.01),
         ((0.05, 0.2, -0.2), 0.06, 0.04))
"""(centre, radius, attenuation 1/mm) as fractions of the grid's width."""


def scan(n_views: int, n_det: int, n_vox: int, seed: int = 0):
    """Nominal and true geometry, grid, line integrals of the ball phantom (on the true geometry)."""
    nominal = circular_scan(n_views, 60.0, 150.0, n_det, n_det, 32.0 / n_det, 32.0 / n_det)
    grid = VolumeGrid.centered((n_vox,) * 3, 12.0 / n_vox)
    axis = (np.arange(n_vox) - 0.5 * (n_vox - 1)) / n_vox
    z, y, x = np.meshgrid(axis, axis, axis, indexing="ij")
    phantom = np.zeros(grid.shape_zyx, np.float32)
    for (cz, cy, cx), r, mu in BALLS:
        phantom[(z - cz) ** 2 + (y - cy) ** 2 + (x - cx) ** 2 < r * r] += mu
    true = nominal.perturbed(robot_coordination(0.3, 0.3, seed=seed).sample(n_views))
    return nominal, true, grid, forward_project(phantom, grid, true)


def fastest_interleaved(fns: dict, repeats: int) -> tuple[dict, dict]:
    """Per name, the wall time of the fastest of ``repeats`` calls of ``fns[name]`` after one warm-up
    call each, and its last result. The calls take turns (a, b, a, b, ...), so a load that comes and
    goes on the machine falls on all of them alike."""
    out = {k: f() for k, f in fns.items()}
    best = {k: float("inf") for k in fns}
    for _ in range(repeats):
        for k, f in fns.items():
            t0 = time.perf_counter()
            out[k] = f()
            best[k] = min(best[k], time.perf_counter() - t0)
    return best, out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--views", type=int, default=96, help="views of the estimation scan")
    ap.add_argument("--det", type=int, default=96, help="detector pixels across (estimation scan)")
    ap.add_argument("--vox", type=int, default=64, help="grid voxels across (estimation scan)")
    ap.add_argument("--fdk-views", type=int, default=240, help="views of the FDK scan")
    ap.add_argument("--fdk-det", type=int, default=160, help="detector pixels across (FDK scan)")
    ap.add_argument("--fdk-vox", type=int, default=160, help="grid voxels across (FDK scan)")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="worker counts (= in-process threads)")
    ap.add_argument("--repeats", type=int, default=4)
    ap.add_argument("--out", default="out/bench_dask",
                    help="folder for dask.md and dask.json (default out/bench_dask; make bench-dask: docs/results)")
    args = ap.parse_args(argv)
    import numba

    say = lambda s: print(s, flush=True)  # noqa: E731
    load_start = os.getloadavg()  # other jobs on the machine take cores from both sides alike
    nominal, true, grid, measured = scan(args.views, args.det, args.vox)
    vol = InProcess().fdk(measured, nominal, grid)
    cfg = replace(default_lle_configs("ncc-exact", prior_sigma=DEFAULT_PRIOR_SIGMA)[1],
                  source_positions=CalibrationSettings().plan()["fine_source"])
    params0 = np.zeros((nominal.n_views, 9))
    f_nom, _, f_grid, f_meas = scan(args.fdk_views, args.fdk_det, args.fdk_vox, seed=1)
    say(f"estimation: {args.views} views of {args.det}^2 on {args.vox}^3; FDK: {args.fdk_views} views of "
        f"{args.fdk_det}^2 onto {args.fdk_vox}^3; {os.cpu_count()} cores")
    rows = []
    for n in args.workers:
        numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))  # in-process, and the Dask client's part
        with DaskExecutor("local", workers=n, threads=1) as ex:
            def estimate_dask():
                ex._cache.clear()  # the measured views travel in every timed run
                return ex.estimate(estimate_views, measured, nominal, params0, vol, grid, cfg, None)

            t, res = fastest_interleaved({
                "est_in": lambda: InProcess().estimate(estimate_views, measured, nominal, params0, vol, grid, cfg, None),
                "est_dask": estimate_dask,
                "fdk_in": lambda: InProcess().fdk(f_meas, f_nom, f_grid),
                "fdk_dask": lambda: ex.fdk(f_meas, f_nom, f_grid)}, args.repeats)
        dp = float(np.abs(res["est_dask"][0] - res["est_in"][0]).max())
        dv = float(np.abs(res["fdk_dask"] - res["fdk_in"]).max() / np.abs(res["fdk_in"]).max())
        say(f"in-process, {n} thread(s): estimation {t['est_in']:.2f} s, FDK {t['fdk_in']:.2f} s")
        say(f"dask LocalCluster, {n} worker(s) x 1 thread: estimation {t['est_dask']:.2f} s "
            f"({t['est_dask'] / t['est_in']:.3f}x), FDK {t['fdk_dask']:.2f} s ({t['fdk_dask'] / t['fdk_in']:.3f}x); "
            f"max difference to in-process: params {dp:.1e}, volume {dv:.1e} of its max")
        for step, key, diff in (("estimation pass", "est", dp), ("FDK", "fdk", dv)):
            rows += [{"method": step, "mode": "in-process threads", "n": n, "wall_s": t[key + "_in"], "ratio": 1.0},
                     {"method": step, "mode": "dask LocalCluster (1 thread/worker)", "n": n,
                      "wall_s": t[key + "_dask"], "ratio": t[key + "_dask"] / t[key + "_in"], "max_diff": diff}]
    rows.sort(key=lambda r: (r["method"] != "estimation pass", r["n"], r["mode"]))
    columns = [("method", "step", "{}"), ("mode", "runs on", "{}"), ("n", "threads / workers", "{:d}"),
               ("wall_s", "wall s (fastest of %d, interleaved)" % args.repeats, "{:.2f}"),
               ("ratio", "/ in-process", "{:.3f}"),
               ("max_diff", "max diff to in-process", "{:.1e}")]
    setup = {"estimation_scan": {"views": args.views, "det": args.det, "vox": args.vox,
                                 "config": "ncc-lle-exact fine level (192 samples, 2 sets, star source, prior)"},
             "fdk_scan": {"views": args.fdk_views, "det": args.fdk_det, "vox": args.fdk_vox},
             "repeats": args.repeats, "cores": os.cpu_count(),
             "load_average_1min": [load_start[0], os.getloadavg()[0]], "machine": platform.platform(),
             "python": platform.python_version()}
    sizes = []  # what the executor sends (transfer_bytes), for these scans and the speed benchmark's
    for name, (n, det, vox) in {"estimation scan": (args.views, args.det, args.vox),
                                "FDK scan": (args.fdk_views, args.fdk_det, args.fdk_vox),
                                "speed benchmark scan (bench_calibration_speed.py)": (360, 256, 256)}.items():
        b = transfer_bytes(n, (det, det), (vox,) * 3)
        sizes.append({"method": name, "views": n, "det": det, "vox": vox,
                      **{k: v / 2 ** 20 for k, v in b.items() if k in ("volume_per_worker", "filtered_per_worker")},
                      **{k: v / 2 ** 10 for k, v in b.items() if k in ("measured_per_view", "per_view_per_pass")}})
    size_columns = [("method", "scan", "{}"), ("views", "views", "{:d}"), ("det", "detector px across", "{:d}"),
                    ("vox", "grid voxels across", "{:d}"), ("volume_per_worker", "volume MiB / worker / pass", "{:.2f}"),
                    ("measured_per_view", "KiB / view / level", "{:.1f}"),
                    ("per_view_per_pass", "KiB / view / pass", "{:.1f}"),
                    ("filtered_per_worker", "filtered MiB / worker / FDK", "{:.1f}")]
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "dask.json"), "w") as f:
        json.dump({"setup": setup, "rows": rows, "sizes": sizes}, f, indent=2)
    md = ["# Dask scale-out: in-process threads and LocalCluster workers", "",
          f"Written by `bench/bench_dask.py` ({os.cpu_count()} cores, {platform.platform()}). Estimation: one "
          f"ncc-lle-exact pass (fine-level settings) over {args.views} views of {args.det} x {args.det} pixels "
          f"against a {args.vox}^3 volume. FDK: {args.fdk_views} views of {args.fdk_det} x {args.fdk_det} onto "
          f"{args.fdk_vox}^3. In-process with N numba threads next to a LocalCluster of N worker processes of one "
          f"thread each; the ratio is Dask over in-process at the same N. Dask estimation times include sending "
          f"the measured views, FDK times the filtering in the client and sending the filtered projections. Load "
          f"average (1 min) {setup['load_average_1min'][0]:.2f} at the start, {setup['load_average_1min'][1]:.2f} at "
          f"the end: other jobs on the machine take cores from both sides alike.", "",
          markdown_table(rows, columns), "",
          "What the Dask executor sends (`distributed.transfer_bytes`; float32 projections and volumes, bool masks, "
          "the ROI grid without the estimation padding):", "", markdown_table(sizes, size_columns)]
    with open(os.path.join(args.out, "dask.md"), "w") as f:
        f.write("\n".join(md))
    say(markdown_table(rows, columns))
    say(markdown_table(sizes, size_columns))
    say(f"wrote {os.path.join(args.out, 'dask.md')} and dask.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
