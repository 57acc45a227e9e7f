"""Benchmark: our Joseph forward/back projector against RTK's JosephForwardProjectionImageFilter.

Builds a robotic-like geometry (a circular scan at the design's magnification, every view
perturbed by random 9-DOF errors), a phantom of a few ellipsoids, and times, in one process:
our ``forward_project`` (after a warm-up compile) alternating with RTK's Joseph forward
projector on the same inputs (only RTK's ``Update()`` is timed, not the image conversions),
then our ``back_project`` (and RTK's Joseph back-projector with ``--rtk-back``). Prints wall
and process CPU times, throughput (rays/s), the RTK/ours ratio and the relative RMSE between
the two projection stacks. On a shared machine, CPU time and the alternating order keep the
comparison fair when other processes take cores. With ``--out`` it also writes what it printed to
``projector.json`` and ``projector.md`` there (``make bench``: docs/results).

    .venv/bin/python bench/bench_projector.py --size 128 --views 90
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numba
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from robot_ct_ros.ct.geometry import ConeGeometry, VolumeGrid  # noqa: E402
from robot_ct_ros.ct.projector import back_project, forward_project  # noqa: E402

SDD_MM = 342.4  # the seed system (arXiv 2406.18063): source-to-detector distance
SOD_MM = 128.0  # the seed system: source-to-ROI distance (magnification 2.67)


def robotic_geometry(n_views: int, n_pix: int, pitch_mm: float, seed: int = 0) -> ConeGeometry:
    """Circular orbit about z, every view perturbed by independent 9-DOF errors (robot-like)."""
    a = np.linspace(0.0, 2 * np.pi, n_views, endpoint=False)
    c, s, zero = np.cos(a), np.sin(a), np.zeros(n_views)
    src = SOD_MM * np.stack([c, s, zero], axis=1)
    det = -(SDD_MM - SOD_MM) * np.stack([c, s, zero], axis=1)
    u = np.stack([-s, c, zero], axis=1)
    v = np.tile([0.0, 0.0, 1.0], (n_views, 1))
    nominal = ConeGeometry(src, det, u, v, n_pix, n_pix, pitch_mm, pitch_mm)
    rng = np.random.default_rng(seed)
    params = rng.normal(size=(n_views, 9)) * np.array([0.3, 0.3, 0.5, 0.3, 0.3, 0.5, 0.005, 0.005, 0.005])
    return nominal.perturbed(params)


def phantom(grid: VolumeGrid, seed: int = 0) -> np.ndarray:
    """Ellipsoids of different densities inside a cylinder; zero in the outer two voxel layers."""
    nz, ny, nx = grid.shape_zyx
    z, y, x = np.meshgrid(np.linspace(-1, 1, nz), np.linspace(-1, 1, ny), np.linspace(-1, 1, nx),
                          indexing="ij", sparse=True)
    vol = np.zeros(grid.shape_zyx, dtype=np.float32)
    vol[(x ** 2 + y ** 2 <= 0.8 ** 2) & (np.abs(z) <= 0.85)] = 0.2
    rng = np.random.default_rng(seed)
    for _ in range(8):
        c = rng.uniform(-0.4, 0.4, 3)
        r = rng.uniform(0.05, 0.3, 3)
        vol[((x - c[0]) / r[0]) ** 2 + ((y - c[1]) / r[1]) ** 2 + ((z - c[2]) / r[2]) ** 2 <= 1] += rng.uniform(0.2, 1)
    vol[:2], vol[-2:], vol[:, :2], vol[:, -2:], vol[:, :, :2], vol[:, :, -2:] = 0, 0, 0, 0, 0, 0
    return vol


def timed(fn):
    """Run ``fn`` once; return (result, wall seconds, process CPU seconds of all threads)."""
    w0, c0 = time.perf_counter(), time.process_time()
    result = fn()
    return result, time.perf_counter() - w0, time.process_time() - c0


def fmt(wall, cpu):
    return " ".join(f"{w:.2f}" for w in wall) + " s wall (" + " ".join(f"{c:.2f}" for c in cpu) + " s CPU)"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256, help="volume N^3 and detector N x N (default 256)")
    ap.add_argument("--views", type=int, default=360, help="number of views (default 360)")
    ap.add_argument("--repeat", type=int, default=1, help="timed repetitions of each projector (default 1)")
    ap.add_argument("--no-rtk", action="store_true", help="skip RTK")
    ap.add_argument("--rtk-back", action="store_true", help="also time RTK's Joseph back-projector")
    ap.add_argument("--out", help="folder for projector.json and projector.md (default: print only)")
    args = ap.parse_args(argv)

    n = args.size
    voxel_mm = 25.6 / n  # a 25.6 mm ROI cube
    grid = VolumeGrid.centered((n, n, n), voxel_mm)
    # detector just covering the projection of the ROI cube's circumscribed cylinder
    pitch_mm = 56.3 / n
    geom = robotic_geometry(args.views, n, pitch_mm)
    vol = phantom(grid)
    n_rays = geom.n_views * n * n
    print(f"volume {n}^3 ({voxel_mm:.4f} mm voxels), {geom.n_views} views of {n} x {n} "
          f"({pitch_mm:.4f} mm pixels), {n_rays / 1e6:.2f} M rays; numba threads {numba.get_num_threads()}")

    t0 = time.perf_counter()
    forward_project(vol, grid, geom.subset([0, 1]))
    back_project(np.ones((2, n, n), np.float32), geom.subset([0, 1]), grid)
    print(f"warm-up (compile or cache load): {time.perf_counter() - t0:.2f} s")

    fp = None
    if not args.no_rtk:
        t0 = time.perf_counter()
        import itk
        from itk import RTK as rtk

        from robot_ct_ros.ct import rtk_bridge

        img_type = itk.Image[itk.F, 3]
        rtk_geom = rtk_bridge.to_rtk_geometry(geom)
        vol_img = rtk_bridge.volume_to_itk(vol, grid)
        print(f"itk import + conversions: {time.perf_counter() - t0:.2f} s; "
              f"ITK threads {itk.MultiThreaderBase.GetGlobalDefaultNumberOfThreads()}")

    # ours and RTK alternate, so that load from other processes hits both alike
    w_fp, c_fp, w_rtk, c_rtk = [], [], [], []
    for _ in range(args.repeat):
        ours, w, c = timed(lambda: forward_project(vol, grid, geom))
        w_fp.append(w)
        c_fp.append(c)
        if not args.no_rtk:
            fp = rtk.JosephForwardProjectionImageFilter[img_type, img_type].New()
            fp.SetInput(0, rtk_bridge.projections_to_itk(None, geom))
            fp.SetInput(1, vol_img)
            fp.SetGeometry(rtk_geom)
            _, w, c = timed(fp.Update)
            w_rtk.append(w)
            c_rtk.append(c)
    print(f"ours  forward: {fmt(w_fp, c_fp)}  -> {n_rays / min(w_fp) / 1e6:.2f} M rays/s")
    record = {"views": geom.n_views, "size": n, "voxel_mm": voxel_mm, "pitch_mm": pitch_mm, "rays": n_rays,
              "repeat": args.repeat, "numba_threads": numba.get_num_threads(),
              "machine": f"{platform.machine()}, {os.cpu_count()} cores",
              "ours_forward_wall_s": w_fp, "ours_forward_cpu_s": c_fp}
    if fp is not None:
        record.update(rtk_forward_wall_s=w_rtk, rtk_forward_cpu_s=c_rtk)
        print(f"RTK   forward: {fmt(w_rtk, c_rtk)}  -> {n_rays / min(w_rtk) / 1e6:.2f} M rays/s")
        print(f"speed-up RTK/ours (forward): {min(w_rtk) / min(w_fp):.2f}x wall, "
              f"{min(c_rtk) / min(c_fp):.2f}x CPU time")
        ref = rtk_bridge.itk_to_projections(fp.GetOutput())
        rel = np.sqrt(np.mean((ours.astype(np.float64) - ref) ** 2) / np.mean(ref.astype(np.float64) ** 2))
        print(f"relative RMSE ours vs RTK: {rel:.2e}  (max |diff| {np.abs(ours - ref).max():.2e}, "
              f"max {ref.max():.3f})")
        record["forward_relative_rmse"] = float(rel)

    w_bp, c_bp = [], []
    for _ in range(args.repeat):
        ours_bp, w, c = timed(lambda: back_project(ours, geom, grid))
        w_bp.append(w)
        c_bp.append(c)
    print(f"ours  back:    {fmt(w_bp, c_bp)}  -> {n_rays / min(w_bp) / 1e6:.2f} M rays/s")
    record.update(ours_back_wall_s=w_bp, ours_back_cpu_s=c_bp)
    if fp is not None and args.rtk_back:
        bp = rtk.JosephBackProjectionImageFilter[img_type, img_type].New()
        bp.SetInput(0, rtk_bridge.volume_to_itk(np.zeros(grid.shape_zyx, np.float32), grid))
        bp.SetInput(1, rtk_bridge.projections_to_itk(ours, geom))
        bp.SetGeometry(rtk_geom)
        _, w, c = timed(bp.Update)
        ref_bp = rtk_bridge.itk_to_volume(bp.GetOutput())[0]
        inner = (slice(2, -2),) * 3  # RTK clips to the voxel-centre box: compare inside
        rel_bp = np.sqrt(np.mean((ours_bp[inner].astype(np.float64) - ref_bp[inner]) ** 2)
                         / np.mean(ref_bp[inner].astype(np.float64) ** 2))
        print(f"RTK   back:    {w:.2f} s wall ({c:.2f} s CPU)  -> {n_rays / w / 1e6:.2f} M rays/s; "
              f"speed-up RTK/ours (back): {w / min(w_bp):.2f}x wall; "
              f"relative RMSE inside the outer 2 voxels {rel_bp:.2e}")
        record.update(rtk_back_wall_s=[w], rtk_back_cpu_s=[c], back_relative_rmse=float(rel_bp))
    if args.out:
        write(Path(args.out), record)


def write(out: Path, r: dict) -> None:
    """projector.json (every timing) and projector.md (the best of each, rays per second, RTK / ours)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "projector.json").write_text(json.dumps(r, indent=1) + "\n")
    rows = []
    for kind in ("forward", "back"):
        ours_w, ours_c = min(r[f"ours_{kind}_wall_s"]), min(r[f"ours_{kind}_cpu_s"])
        rtk = f"rtk_{kind}_wall_s" in r
        rtk_w = min(r[f"rtk_{kind}_wall_s"]) if rtk else None
        rtk_c = min(r[f"rtk_{kind}_cpu_s"]) if rtk else None
        rel = r.get(f"{kind}_relative_rmse")
        rows.append(f"| {kind} | {ours_w:.2f} | {ours_c:.2f} | {r['rays'] / ours_w / 1e6:.2f} | "
                    + (f"{rtk_w:.2f} | {rtk_c:.2f} | {r['rays'] / rtk_w / 1e6:.2f} | {rtk_w / ours_w:.2f} | "
                       f"{rtk_c / ours_c:.2f} | {rel:.2e} |" if rtk else "- | - | - | - | - | - |"))
    (out / "projector.md").write_text("\n".join([
        "# Joseph projector beside RTK's (bench/bench_projector.py)", "",
        f"{r['size']}^3 volume of {r['voxel_mm']:.4f} mm voxels, {r['views']} views of {r['size']} x {r['size']} "
        f"pixels of {r['pitch_mm']:.4f} mm ({r['rays'] / 1e6:.2f} M rays), a circular orbit at the design's "
        "magnification with independent 9-DOF errors per view; our numba kernels and RTK's "
        "JosephForwardProjectionImageFilter / JosephBackProjectionImageFilter on the same inputs in one process, "
        "alternating (only RTK's Update() timed). Best of "
        f"{r['repeat']} run(s) (RTK's back-projection once). This machine: {r['machine']}, numba threads "
        f"{r['numba_threads']}, shared with other jobs. *relative RMSE*: ours against RTK's output (the "
        "back-projection inside the outer 2 voxels, which RTK clips).", "",
        "| projection | ours wall (s) | ours CPU (s) | ours M rays/s | RTK wall (s) | RTK CPU (s) | RTK M rays/s | "
        "RTK / ours wall | RTK / ours CPU | relative RMSE |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |", *rows, ""]))
    print(f"wrote {out / 'projector.md'} and projector.json")


if __name__ == "__main__":
    main()
