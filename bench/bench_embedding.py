"""Benchmark: the LLE embedding's neighbours K and ridge (settings ``lle_neighbours``, ``lle_ridge``).

``ncc-lle-exact`` embeds each view's projection in its K = 24 nearest samples with a ridge of
1e-5 (times the Gram matrix's trace / K) by default (lle/estimator.py, EMBEDDING_SETTINGS). This
bench runs it with those defaults and with a stronger ridge and fewer neighbours, on:

* (a) the mouse of bench_calibration.py at its default size (90 views, 64 x 96, 3 iterations),
  scenario seed 0, three sampling seeds;
* (b) the battery with its detector drift, the same size, sampling seed 0;
* the HTC2022 measured fan-beam scans, bench_realdata.py's case ``independent`` (360 of the 720
  views, the documented geometry as the truth, per-view d_u and s_u errors of 1 px at the centre,
  the prior at each arm's injected accuracy), and the synthetic twin of each (RTK's Joseph
  projection of our FDK of the measured data, bench_realdata.synthetic_twin) with the same errors.
  ``ncc-lle`` and ``gdc`` run beside them with their defaults, as references.

Metric: the gauge-aligned mean reprojection error (metrics.reprojection_error, ROI points) of the
applied estimate against the true (documented) geometry, in detector pixels; its 95th
percentile; wall time. Writes ``embedding.md`` and ``.json`` into ``--out``.

    .venv/bin/python bench/bench_embedding.py --out docs/results     # about 35 min on 2 cores
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

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from bench_calibration import SCENARIOS, make_scenario  # noqa: E402
from bench_realdata import DATA, injected_errors, load_phantom, synthetic_twin, view_mask  # noqa: E402
from robot_ct_ros.ct import calibration  # noqa: E402
from robot_ct_ros.ct.metrics import reprojection_error, roi_points  # noqa: E402
from robot_ct_ros.jobs.figures import markdown_table  # noqa: E402

VARIANTS = {
    "ncc-lle-exact, K 24, ridge 1e-5 (default)": {},
    "ncc-lle-exact, K 24, ridge 1e-4": {"lle_ridge": 1e-4},
    "ncc-lle-exact, K 24, ridge 1e-3": {"lle_ridge": 1e-3},
    "ncc-lle-exact, K 16, ridge 1e-3": {"lle_neighbours": 16, "lle_ridge": 1e-3},
}
"""Row label -> settings changes of ncc-lle-exact."""

REFERENCES = {"ncc-lle (default)": "ncc-lle", "gdc": "gdc"}
"""Methods run with their defaults beside the variants on the HTC2022 cases."""

COLUMNS = (("variant", "variant", "{}"), ("mean_px", "reproj. error mean (px)", "{:.3f}"),
           ("p95_px", "reproj. error p95 (px)", "{:.3f}"), ("per_seed", "per sampling seed (px)", "{}"),
           ("wall_s", "wall time (s)", "{:.1f}"))


def run(li, nominal, true, grid, mask, settings, points) -> dict:
    """One calibration; the applied estimate's error against ``true`` and its wall time."""
    t0 = time.perf_counter()
    res = calibration.calibrate(li, nominal, grid, settings, valid_mask=mask)
    err = reprojection_error(res.geom, true, points)
    return {"mean_px": float(err["mean_px"]), "p95_px": float(err["p95_px"]),
            "wall_s": time.perf_counter() - t0, "notes": list(res.notes)}


def simulated_cases(keys: str, seeds: list, say) -> list:
    """bench_calibration's scenarios at their default size, every variant over the sampling ``seeds``
    ((a); (b) the first seed only)."""
    cases = []
    for key in keys:
        sc = make_scenario(key, 90, (64, 96), 64, 4, seed=0, say=say)
        pts = roi_points(sc.grid)
        none = reprojection_error(sc.nominal, sc.true, pts)
        rows = []
        for label, change in VARIANTS.items():
            runs = []
            for s in (seeds if key == "a" else seeds[:1]):
                settings = calibration.CalibrationSettings(method="ncc-lle-exact", iterations=3, seed=s, **change)
                runs.append(run(sc.li, sc.nominal, sc.true, sc.grid, sc.mask, settings, pts))
                say(f"  ({key}) {label} seed {s}: {runs[-1]['mean_px']:.3f} px, {runs[-1]['wall_s']:.0f} s")
            rows.append({"variant": label, "mean_px": float(np.mean([r["mean_px"] for r in runs])),
                         "p95_px": float(np.mean([r["p95_px"] for r in runs])),
                         "per_seed": " / ".join(f"{r['mean_px']:.3f}" for r in runs) if len(runs) > 1 else None,
                         "wall_s": float(np.mean([r["wall_s"] for r in runs])), "changes": change,
                         "seeds": seeds if key == "a" else seeds[:1]})
        cases.append({"case": f"({key}) {SCENARIOS[key]}", "nominal_px": float(none["mean_px"]), "rows": rows})
    return cases


def htc_cases(phantoms: list, data: Path, twin: bool, say) -> list:
    """bench_realdata's case ``independent`` on the measured scans (and their twins): every variant and
    the references."""
    cases = []
    with tempfile.TemporaryDirectory() as tmp:
        for ph in phantoms:
            scan, grid, li_all, mask_all, sigma_src = load_phantom(data, ph, tmp)  # sigma_src: 1 px at the centre
            g0 = scan.geom
            views = np.arange(0, scan.n_views, 2)
            mask = view_mask(mask_all, views)
            true = g0.subset(views)
            nominal = true.perturbed(injected_errors(true, "independent", base_seed=0, px=1.0, drift_px=0.0,
                                                     sigma_src_mm=sigma_src))
            pts = roi_points(grid)
            base = calibration.CalibrationSettings().with_prior(sigma_src, 0.01, detector_mm=g0.col_pitch_mm)
            sources = {"measured": np.ascontiguousarray(li_all[views])}
            if twin:
                say(f"  {ph}: synthetic twin")
                sources["synthetic twin"] = np.ascontiguousarray(
                    synthetic_twin(li_all, mask_all, g0, grid, seed=99)[0][views])
            for source, li in sources.items():
                rows = []
                labelled = [(k, base.replace(method="ncc-lle-exact", **c)) for k, c in VARIANTS.items()]
                labelled += [(k, base.replace(method=m)) for k, m in REFERENCES.items()]
                for label, settings in labelled:
                    r = run(li, nominal, true, grid, mask, settings, pts)
                    say(f"  HTC2022 {ph} {source}: {label}: {r['mean_px']:.3f} px, {r['wall_s']:.0f} s")
                    rows.append({"variant": label, **r})
                cases.append({"case": f"HTC2022 {ph}, {source}", "nominal_px": float(
                    reprojection_error(nominal, true, pts)["mean_px"]), "rows": rows})
    return cases


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenarios", default="ab", help="subset of 'ab' (bench_calibration's scenarios)")
    ap.add_argument("--seeds", default="0,1,2", help="sampling seeds of (a) (b runs the first)")
    ap.add_argument("--phantoms", default="01a,02a", help="HTC2022 phantoms ('' for none)")
    ap.add_argument("--data", default=str(DATA), help="folder with htc2022_<phantom>_full.mat")
    ap.add_argument("--no-twin", action="store_true", help="skip the synthetic twins")
    ap.add_argument("--out", default="out/bench_embedding")
    args = ap.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    phantoms = [p.strip() for p in args.phantoms.split(",") if p.strip()]
    if not seeds:
        ap.error("--seeds needs at least one seed")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()

    def say(msg):
        print(f"[{time.perf_counter() - t_all:7.1f} s] {msg}", flush=True)

    cases = simulated_cases(args.scenarios, seeds, say)
    if phantoms:
        cases += htc_cases(phantoms, Path(args.data), not args.no_twin, say)
    total = time.perf_counter() - t_all
    report = {"bench": "bench/bench_embedding.py", "argv": sys.argv[1:] if argv is None else list(argv),
              "machine": f"{platform.machine()}, {os.cpu_count()} cores",
              "numba_threads": os.environ.get("NUMBA_NUM_THREADS"), "variants": VARIANTS,
              "references": REFERENCES, "cases": cases, "total_s": total}
    (out / "embedding.json").write_text(json.dumps(report, indent=1))
    md = ["# The embedding's neighbours and ridge (bench/bench_embedding.py)", "",
          "`ncc-lle-exact` with its default embedding (K = 24 nearest samples, ridge 1e-5 times the Gram "
          "matrix's trace / K) against a stronger ridge and fewer neighbours (settings `lle_neighbours`, "
          "`lle_ridge`). (a), (b): bench_calibration.py's mouse and battery at its default size (90 views, "
          "64 x 96, 3 iterations; (a) over the sampling seeds " + ", ".join(map(str, seeds)) + ", their "
          "mean in the first columns). HTC2022: bench_realdata.py's case `independent` (measured data, 360 "
          "views, per-view d_u and s_u errors of 1 px at the centre, the prior at each arm's injected "
          "accuracy) and the same errors on its synthetic twin, with `ncc-lle` and `gdc` at their defaults "
          "beside them. Error: gauge-aligned mean reprojection error of ROI points against the true "
          "(documented) geometry, detector pixels.", ""]
    for case in cases:
        md += [f"## {case['case']} (nominal {case['nominal_px']:.3f} px)", "", markdown_table(case["rows"], COLUMNS)]
    md += [f"Total {total / 60:.1f} min on this machine ({platform.machine()}, {os.cpu_count()} cores), "
           "shared with other jobs.", ""]
    (out / "embedding.md").write_text("\n".join(md))
    say(f"wrote {out / 'embedding.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
