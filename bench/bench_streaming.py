"""Benchmark: how long the simulated scan takes with streaming correction on and off, in one run.

The whole graph in-process (robot_ct_ros.testing.graph.run_scan_graph: simulated arms and
photon-counting detector, orchestrator, recorder, recon_service) scans the same protocol in
turns, ``--repeats`` times each:

  off        no correction during the scan (the whole-scan run after it)
  stream     stream=true: each frame estimated as it arrives, in one worker process at nice
             +``--nice`` (robot_ct_ros.jobs.streaming), live geometry on /ct/geometry_live
  stream0    the same with the worker at the node's own priority (nice +0; ``--no-nice0`` leaves it out)
  streamall  stream at nice +``--nice`` with the worker on numba's default threads, every core
             (``--no-all-threads`` leaves it out)
  every_n    every_n_views=N: the earlier online mode, the whole calibration re-run on the frames so
             far on a thread of the node's process (``--every``; 0 leaves it out)

and reports the scan's duration (scan start to scan/status done, the orchestrator's clock), the
live figures (views whose live geometry arrived before the scan ended, latency from a frame's
pairing to its live geometry, the running projection NCC) and the whole-scan run's time. Each
figure is the median over the repeats. Writes streaming.md and streaming.json to ``--out``.

    .venv/bin/python bench/bench_streaming.py --out docs/results      # about 4 min on 2 cores
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def protocol(views: int, exposure_s: float) -> dict:
    return {"name": "bench_streaming", "n_views": views, "roi_center_m": [0.4, 0.0, 0.3], "fov_diameter_m": 0.005,
            "detector": {"n_rows": 32, "n_cols": 64, "binning": 2, "raw_pixel_m": 0.00011},
            "exposure_s": exposure_s, "settle_s": 0.01, "move_timeout_s": 10.0, "exposure_timeout_s": 5.0}


GRABBER = {"sim_phantom": "mouse", "sim_voxel_size_m": 0.0005, "sim_region_size_m": [0.004, 0.004, 0.1],
           "sim_roi_size_m": [0.0, 0.0, 0.0]}


def one_run(kind: str, args, out: Path) -> dict:
    from robot_ct_ros.testing.graph import run_scan_graph

    recon = {"method": args.method, "iterations": 1, "evaluate_truth": False}
    if kind.startswith("stream"):
        recon.update(stream=True, stream_warmup_views=args.warmup, stream_nice=0 if kind == "stream0" else args.nice,
                     stream_threads=0 if kind == "streamall" else args.threads)
    elif kind == "every_n":
        recon.update(every_n_views=args.every)
    r = run_scan_graph(out, protocol(args.views, args.exposure), grabber=GRABBER, quiet=True, say=lambda s: None,
                       scan_timeout_s=600.0, recon=recon, recon_timeout_s=900.0)
    row = {"kind": kind, "scan_s": r.timings_s["scan_s"], "recon_s": r.timings_s["recon_s"], "frames": r.frames}
    if kind.startswith("stream"):
        live = r.report.get("live", {})
        row.update(live_views_during_scan=sum(1 for _, during in r.live.values() if during),
                   live_views=len(r.live), latency_s_median=live.get("latency_s_median"),
                   latency_s_max=live.get("latency_s_max"), mean_projection_ncc=live.get("mean_projection_ncc"),
                   live_error=live.get("error"))
    if kind == "every_n":
        row["partial_runs"] = len(list((out / "recon").glob("partial_*")))
    return row


def median(rows, key):
    vals = [r[key] for r in rows if r.get(key) is not None]
    return statistics.median(vals) if vals else None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--views", type=int, default=32)
    ap.add_argument("--exposure", type=float, default=0.1, help="exposure per frame (s)")
    ap.add_argument("--method", default="ncc-lle-exact")
    ap.add_argument("--warmup", type=int, default=8, help="stream_warmup_views")
    ap.add_argument("--nice", type=int, default=10, help="stream_nice: the worker's niceness increment")
    ap.add_argument("--threads", type=int, default=1, help="stream_threads: the worker's numba threads (0: numba's "
                    "default)")
    ap.add_argument("--no-nice0", action="store_true", help="leave out the stream run at nice +0")
    ap.add_argument("--no-all-threads", action="store_true", help="leave out the stream run on every core")
    ap.add_argument("--every", type=int, default=8, help="every_n_views of the earlier online mode (0: not run)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None, help="write streaming.md and streaming.json here")
    args = ap.parse_args()

    kinds = (["off", "stream"] + ([] if args.no_nice0 else ["stream0"])
             + ([] if args.no_all_threads or args.threads == 0 else ["streamall"])
             + (["every_n"] if args.every > 0 else []))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(args.repeats):
            for kind in kinds:  # in turns: other jobs on the machine slow every kind alike
                t0 = time.monotonic()
                row = one_run(kind, args, Path(tmp) / f"{kind}_{rep}")
                row["repeat"] = rep
                row["load_average"] = os.getloadavg()[0]
                rows.append(row)
                print(f"{kind:8s} repeat {rep}: scan {row['scan_s']:.2f} s, correction after it {row['recon_s']:.1f} s"
                      + (f", live {row['live_views_during_scan']}/{row['frames']} views before the scan ended, "
                         f"{row['live_views']} by the end of the run, latency median {row['latency_s_median']} s"
                         if kind.startswith("stream") else "")
                      + f" ({time.monotonic() - t0:.0f} s)", flush=True)
    summary = {}
    for kind in kinds:
        rs = [r for r in rows if r["kind"] == kind]
        summary[kind] = {k: median(rs, k) for k in rs[0] if k not in ("kind", "repeat", "live_error")}
    off = summary["off"]["scan_s"]
    for kind in kinds:
        summary[kind]["speed_vs_off"] = off / summary[kind]["scan_s"]
    env = {"python": platform.python_version(), "cpus": os.cpu_count(), "machine": platform.machine(),
           "load_average_at_end": list(os.getloadavg())}
    result = {"bench": "streaming", "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
              "environment": env, "summary": summary, "runs": rows}
    lines = ["# Streaming online correction: scan duration with it on and off", "",
             f"`bench/bench_streaming.py`: the simulated graph, {args.views} views of 32 x 64 pixels (binning 2), "
             f"exposure {args.exposure} s, method {args.method}, 1 iteration; medians of {args.repeats} runs per kind, "
             f"taken in turns; {env['cpus']} CPUs (load average at the end {env['load_average_at_end'][0]:.1f}).", "",
             "| mode | scan (s) | scan speed vs off | live views before the scan ended (by the end of the run) | live latency median / max (s) "
             "| running projection NCC | whole-scan run after the scan (s) |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    threads = f"{args.threads} numba thread(s)" if args.threads else "numba's default threads"
    names = {"off": "off", "stream": f"stream (1 worker, nice +{args.nice}, {threads}, warm-up {args.warmup} views)",
             "stream0": f"stream (1 worker, nice +0, {threads}, warm-up {args.warmup} views)",
             "streamall": f"stream (1 worker, nice +{args.nice}, numba's default threads, warm-up {args.warmup} views)",
             "every_n": f"every_n_views={args.every} (earlier mode)"}
    for kind in kinds:
        s = summary[kind]
        st = kind.startswith("stream")
        live = (f"{s['live_views_during_scan']:.0f} / {s['frames']:.0f} ({s['live_views']:.0f} by the end)" if st
                else "-")
        lat = (f"{s['latency_s_median']:.2f} / {s['latency_s_max']:.2f}" if st and s.get("latency_s_max")
               is not None else "-")
        ncc = f"{s['mean_projection_ncc']:.3f}" if st and s.get("mean_projection_ncc") is not None else "-"
        lines.append(f"| {names[kind]} | {s['scan_s']:.2f} | {s['speed_vs_off']:.2f} | {live} | {lat} | {ncc} | "
                     f"{s['recon_s']:.1f} |")
    lines += ["", "Scan: scan start to scan/status done. Latency: from the frame's pairing in recon_service to its "
              "live geometry. The running projection NCC is the mean over the views after the warm-up of the NCC of "
              "the running volume's reprojection at a view's live estimate against that view (coarse level). "
              "The runs per kind, with the machine's load average at each run's end, are in streaming.json.", ""]
    text = "\n".join(lines)
    print(text)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "streaming.md").write_text(text)
        (args.out / "streaming.json").write_text(json.dumps(result, indent=2) + "\n")
        print(f"wrote {args.out / 'streaming.md'} and {args.out / 'streaming.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
