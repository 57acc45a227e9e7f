"""Benchmark on real measured data: short scans of the HTC2022 fan-beam phantoms, reconstructed with Parker's weights.

Data: the Helsinki Tomography Challenge 2022 (HTC2022) open dataset, phantoms 01a and 02a (``htc2022_0?a_full.mat``,
``htc2022_0?a_recon_fbp.mat``), read from ``--data`` (default /work/shared/realdata/htc2022; SOURCE.txt there says
where they come from and how to cite them), imported with the job behind ``robot-ct import htc2022`` as in
bench_realdata.py (720 views over 360 degrees, one row of 560 pixels, the documented geometry).

For each phantom and each short arc (``--arcs``: degrees beyond half a turn; the fan spans 11.5 degrees here)
starting at each of ``--starts`` (degrees), the views whose angle from the start lies within the arc are
reconstructed by FDK with the documented geometry on the dataset's grid (the default settings: Hann window,
truncation handling), once with Parker's weights (``short_scan``, the default; reconstruction.short_scan_weights)
and once weighted as a full circle (``short_scan=False``, what FDK did before). Reported: the Pearson correlation
with the dataset's own FBP (rows flipped onto its orientation, as bench_realdata finds) and with our FDK of all
720 views, and the mean attenuation inside the disc (where the full-circle FDK exceeds half its maximum) relative
to the full circle's.

Writes ``short_scan.md`` and ``short_scan.json`` into ``--out``.

    .venv/bin/python bench/bench_short_scan.py --out docs/results      # about a minute on 2 cores
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from bench_realdata import DATA, ORIENTATIONS, load_phantom, pearson, read_dataset_fbp, view_mask  # noqa: E402
from robot_ct_ros.ct.reconstruction import fdk, scan_arc  # noqa: E402
from robot_ct_ros.ct.scan_weights import source_angles  # noqa: E402
from robot_ct_ros.jobs.figures import markdown_table  # noqa: E402

COLUMNS = (("phantom", "phantom", "{}"), ("arc_deg", "arc (deg)", "{:.1f}"), ("start_deg", "start (deg)", "{:g}"),
           ("views", "views", "{}"), ("weights", "weights", "{}"),
           ("corr_dataset", "correlation with the dataset's FBP", "{:.5f}"),
           ("corr_full", "correlation with our full circle", "{:.5f}"),
           ("mean_rel", "mean in the disc / full circle's", "{:.4f}"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(DATA), help="folder with htc2022_<phantom>_full.mat and _recon_fbp.mat")
    ap.add_argument("--phantoms", default="01a,02a")
    ap.add_argument("--arcs", default="15,30,60", help="degrees beyond half a turn (comma-separated)")
    ap.add_argument("--starts", default="0,90,180,270", help="start angles, degrees (comma-separated)")
    ap.add_argument("--out", default="out/bench_short_scan")
    args = ap.parse_args(argv)
    data, out = Path(args.data), Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    arcs = [180.0 + float(a) for a in args.arcs.split(",") if a.strip()]
    starts = [float(s) for s in args.starts.split(",") if s.strip()]
    t_all = time.perf_counter()

    def say(msg):
        print(f"[{time.perf_counter() - t_all:7.1f} s] {msg}", flush=True)

    flip = ORIENTATIONS["rows flipped"]
    rows, fans = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        for ph in [p.strip() for p in args.phantoms.split(",") if p.strip()]:
            scan, grid, li, mask, _ = load_phantom(data, ph, tmp)
            ref = read_dataset_fbp(data, ph)
            g = scan.geom
            fans[ph] = float(2 * np.degrees(np.arctan(0.5 * g.n_cols * g.col_pitch_mm / np.median(g.sdd_mm))))
            full = flip(fdk(li, g, grid, valid_mask=mask)[0].astype(np.float64))
            disc = full > 0.5 * full.max()
            rows.append({"phantom": ph, "arc_deg": 360.0, "start_deg": 0.0, "views": g.n_views,
                         "weights": "full circle", "corr_dataset": pearson(full, ref), "corr_full": 1.0,
                         "mean_rel": 1.0})
            say(f"{ph}: full circle, correlation with the dataset's FBP {rows[-1]['corr_dataset']:.5f}")
            phi = np.degrees(source_angles(g, scan.scan_center_mm()))
            for arc in arcs:
                for start in starts:
                    views = np.flatnonzero(np.mod(phi - phi[0] - start, 360.0) <= arc + 1e-6)
                    sub = g.subset(views)
                    for weights, short in (("Parker", True), ("full-circle 1/2", False)):
                        with warnings.catch_warnings():
                            warnings.simplefilter("ignore", RuntimeWarning)  # the 1/2 on a partial arc warns
                            img = flip(fdk(li[views], sub, grid, valid_mask=view_mask(mask, views),
                                           short_scan=short)[0].astype(np.float64))
                        covered = float(np.degrees(scan_arc(sub, scan.scan_center_mm())[0]))
                        rows.append({"phantom": ph, "arc_deg": covered, "start_deg": start, "views": int(views.size),
                                     "weights": weights, "corr_dataset": pearson(img, ref), "corr_full": pearson(img, full),
                                     "mean_rel": float(img[disc].mean() / full[disc].mean())})
                        say(f"{ph}: arc {rows[-1]['arc_deg']:.1f} from {start:g}, {weights}: correlation "
                            f"{rows[-1]['corr_dataset']:.5f} (dataset), {rows[-1]['corr_full']:.5f} (full circle), "
                            f"mean {rows[-1]['mean_rel']:.4f}")
    wall = time.perf_counter() - t_all
    report = {"bench": "bench/bench_short_scan.py", "argv": sys.argv[1:] if argv is None else list(argv),
              "machine": f"{platform.machine()}, {os.cpu_count()} cores", "data": str(data), "fan_deg": fans,
              "rows": rows, "wall_s": wall}
    parker = [r for r in rows if r["weights"] == "Parker"]
    plain = [r for r in rows if r["weights"] == "full-circle 1/2"]
    lines = ["# Short scans of measured fan-beam data (bench/bench_short_scan.py)", "",
             "HTC2022 phantoms " + ", ".join(fans) + " (Meaney et al., Zenodo 6984868), imported as scan bags; "
             "the views within each arc, from each start angle, reconstructed by FDK with the documented geometry "
             "on the dataset's grid, with Parker's weights and weighted as a full circle. The fan spans "
             + ", ".join(f"{v:.1f} deg ({k})" for k, v in fans.items()) + ". Correlations: Pearson, over the whole "
             "slice; mean: inside the disc (where the full circle's FDK exceeds half its maximum), relative to the "
             "full circle's.", "",
             f"With Parker's weights: correlation with the dataset's FBP {min(r['corr_dataset'] for r in parker):.5f}"
             f"-{max(r['corr_dataset'] for r in parker):.5f}, with our full circle "
             f"{min(r['corr_full'] for r in parker):.5f}-{max(r['corr_full'] for r in parker):.5f}, mean "
             f"{min(r['mean_rel'] for r in parker):.4f}-{max(r['mean_rel'] for r in parker):.4f}. Weighted as a full "
             f"circle: {min(r['corr_dataset'] for r in plain):.5f}-{max(r['corr_dataset'] for r in plain):.5f}, "
             f"{min(r['corr_full'] for r in plain):.5f}-{max(r['corr_full'] for r in plain):.5f}, mean "
             f"{min(r['mean_rel'] for r in plain):.4f}-{max(r['mean_rel'] for r in plain):.4f}.", "",
             markdown_table(rows, COLUMNS), f"Total {wall:.1f} s on this machine ({report['machine']}).", ""]
    with open(out / "short_scan.json", "w") as f:
        json.dump(report, f, indent=2)
    with open(out / "short_scan.md", "w") as f:
        f.write("\n".join(lines))
    say(f"wrote {out}/short_scan.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
