"""Benchmark evidence: the guard's verdict on every calibration the other benches ran.

The guard (robot_ct_ros.ct.calibration.guard, docs/calibration.md section 11) keeps the nominal
geometry where the data do not support a correction. It must refuse harmful corrections and keep
helpful ones. This script runs no calibration: it reads what the benches already wrote into
``--results`` (results.json, sweep.json, interior.json, exterior_reach.json, reach_guess.json, realdata.json
and fullsize.json, each also from every folder there that holds one: a run with a setting or the seed changed) and,
for each method and scan, takes:

* the nominal geometry's error and the final error (gauge-aligned reprojection error of ROI
  points, mean, px), and the error before the guard where the guard changed anything (the
  benches write it into the notes, or as exterior_reach's ``unguarded_mean_px``, reach_guess's
  ``unguarded_px`` and fullsize's ``unguarded_error_px``);
* the guard's inputs from the notes: the model NCC, R (how far the correction moved the views
  against random errors of the stated accuracy), the limit applied;
* the regime: the exterior modelled, strongly truncated without it, or not strongly truncated.

Each verdict is then one of: kept a helpful correction, refused a harmful one (right); applied a
harmful one (a miss); refused a helpful one (lost); or, where undo_inconsistent undid the first
iteration (its note says so), made no correction. Scans started at their true geometry (the
real-data cases ``documented`` and ``twin-documented``, bench_fullsize ``--from-true``) have nothing to correct
and are left out.
Cells whose bench predates a note (no regime or R in them) say so instead of guessing. Writes
``guard.md`` and ``guard.json`` into ``--out``.

    .venv/bin/python bench/bench_guard.py --results docs/results --out docs/results    # seconds
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from robot_ct_ros.jobs.figures import markdown_table  # noqa: E402

OUTCOMES = ("kept a helpful correction", "refused a harmful correction", "applied a harmful correction",
            "refused a helpful correction")
"""The verdicts: the first two are right, the third a miss, the fourth a loss."""
NO_CORRECTION = "made no correction"
"""A calibration that ended where it started (undo_inconsistent undid its first iteration): nothing to judge."""


def _number(pattern: str, notes) -> float | None:
    for note in notes:
        m = re.search(pattern, note)
        if m:
            return float(m.group(1))
    return None


def regime(notes) -> str:
    """Where the scan stands, from the calibration's own notes."""
    text = " ".join(notes)
    if "exterior model" in text:
        return "exterior modelled"
    if "strongly truncated" in text:
        return "strongly truncated, not modelled"
    return "ROI model, not strongly truncated" if "guard" in text else "unknown (no notes)"


def record(source: str, scan: str, method: str, nominal_px: float, after_px: float, notes,
           model_ncc=None, before_px=None) -> dict:
    """One calibration's verdict (see the module docstring)."""
    notes = list(notes or ())
    before = before_px if before_px is not None else _number(r"before the guard ([\d.]+) px mean", notes)
    scan_kept = any("nominal geometry is kept" in n for n in notes)
    views_kept = _number(r"(\d+) view\(s\) moved beyond", notes)
    changed = scan_kept or bool(views_kept)
    if before is None:
        before = after_px if not changed else None
    verdict = ("scan kept nominal (model NCC)" if any("explains the data poorly" in n for n in notes)
               else "scan kept nominal (R)" if scan_kept
               else f"applied, {int(views_kept)} view(s) kept nominal" if views_kept else "applied")
    if before is None:
        outcome = "unknown (no error before the guard)"
    elif any("no correction was made" in n for n in notes):
        outcome = NO_CORRECTION
    elif scan_kept:
        outcome = OUTCOMES[1] if before >= nominal_px else OUTCOMES[3]
    else:
        outcome = OUTCOMES[0] if after_px < nominal_px else OUTCOMES[2]
    return {"source": source, "scan": scan, "method": method, "regime": regime(notes),
            "model_ncc": None if model_ncc is None else round(float(model_ncc), 3),
            "ratio": _number(r"([\d.]+) times the robots", notes) or _number(r"moved the views ([\d.]+) times", notes),
            "limit": _number(r"\(limit ([\d.]+)\)", notes), "verdict": verdict,
            "nominal_px": round(nominal_px, 3), "before_px": None if before is None else round(before, 3),
            "after_px": round(after_px, 3), "outcome": outcome}


def _outcome_px(r: dict) -> str:
    """What a miss or a loss cost: the error a harmful correction ended at (after any views the guard reverted),
    or the one a refused helpful correction would have reached."""
    return f"ended at {r['after_px']}" if r["outcome"].startswith("applied") else f"would have reached {r['before_px']}"


def _rows_source(source: str, scan: str, rows: list, notes: dict) -> list:
    by = {r["method"]: r for r in rows}
    nominal = by["none"]["reproj_mean_px"]
    return [record(source, scan, m, nominal, r["reproj_mean_px"], notes.get(m, ()), r.get("model_ncc"))
            for m, r in by.items() if m not in ("none", "true geometry", "documented geometry", "oracle floor")]


def collect(results_dir: str) -> tuple[list, list]:
    """Every verdict found in the bench files of ``results_dir``, and the files read."""
    out, read = [], []

    def load(name):
        path = os.path.join(results_dir, name)
        if not os.path.exists(path):
            return None
        read.append(name)
        with open(path) as f:
            return json.load(f)

    def with_variants(name):
        """``name`` at the top, then in each folder that holds one: a bench run with a setting or the
        seed changed (docs/results/padding_2/results.json, docs/results/interior_seed_1/interior.json)."""
        folders = sorted(n for n in os.listdir(results_dir) if os.path.isfile(os.path.join(results_dir, n, name)))
        return [name] + [f"{n}/{name}" for n in folders]

    for name in with_variants("results.json"):
        d = load(name)
        for sc in (d or {}).get("scenarios", []):
            out += _rows_source(name, f"({sc['key']})", sc["rows"], sc.get("notes", {}))
    for name in with_variants("interior.json"):
        d = load(name)
        for sc in (d or {}).get("scans", []):
            out += _rows_source(name, f"neck {sc['sigma']:g} mm / {sc['sigma']:g} deg", sc["rows"],
                                sc.get("notes", {}))
    for name in with_variants("sweep.json"):
        d = load(name)
        for scale, cell in sorted((d or {}).get("scales", {}).items(), key=lambda kv: float(kv[0])):
            nominal = cell["errors_px"]["none"]
            for m, e in cell["errors_px"].items():
                if m != "none":
                    out.append(record(name, f"mouse {float(scale):g}x", m, nominal, e, cell["notes"].get(m, ()),
                                      cell["model_ncc"].get(m)))
    for name in with_variants("exterior_reach.json"):
        d = load(name)
        sigma = (d or {}).get("sigma", 0.1)
        for r in (d or {}).get("rows", []):
            reach = "up to the sources" if not r["half_width_mm"] else f"{r['half_width_mm']:g} mm"
            out.append(record(name, f"neck {sigma:g} mm / {sigma:g} deg", f"ncc-lle-exact, exterior reach {reach}",
                              d["nominal_mean_px"], r["mean_px"], r.get("notes", ()) if isinstance(r.get("notes"), list)
                              else [r.get("notes", "")], r.get("model_ncc"), r.get("unguarded_mean_px")))
    for name in with_variants("reach_guess.json"):
        for r in (load(name) or {}).get("rows", []):
            out.append(record(name, r["title"], f"ncc-lle-exact, reach guessed ({r['guessed_reach_mm']:.1f} mm)",
                              r["nominal_px"], r["error_px"], r.get("notes", ()), r.get("model_ncc"),
                              r.get("unguarded_px")))
    for name in with_variants("fullsize.json"):
        d = load(name)
        c, g = (d or {}).get("calibration"), (d or {}).get("geometry", {})
        if c and not c.get("from_true") and c["error_before_px"] > 0:  # a run started at the truth has nothing to correct
            out.append(record(name, f"seed system, {g.get('body_mm', 0):g} mm neck, {g.get('fov_mm', 0):.0f} mm field of "
                                    f"view", c["method"], c["error_before_px"], c["error_after_px"], c.get("notes", ()),
                              c.get("model_ncc"), c.get("unguarded_error_px")))
    for name in with_variants("realdata.json"):
        d = load(name)
        for ph, p in (d or {}).get("phantoms", {}).items():
            for case, c in p.get("cases", {}).items():
                nominal = {r["method"]: r for r in c["rows"]}.get("none", {}).get("reproj_mean_px", 0.0)
                if nominal > 0:  # a scan started at its true geometry has nothing to correct
                    out += _rows_source(name, f"HTC2022 {ph} {case}", c["rows"], c.get("notes", {}))
    return out, read


def summary(records: list) -> list:
    """Per regime: how many verdicts of each outcome, and the ranges of R and model NCC of the
    helpful and the harmful corrections (before the guard)."""
    rows = []
    for reg in sorted({r["regime"] for r in records}):
        rs = [r for r in records if r["regime"] == reg]
        row = {"regime": reg, "calibrations": len(rs)}
        for o in OUTCOMES + (NO_CORRECTION,):
            row[o] = sum(r["outcome"] == o for r in rs)
        for key, name, fmt in (("ratio", "R", "{:.2f}"), ("model_ncc", "model NCC", "{:.3f}")):
            for label, good in ((f"{name} of helpful corrections", True), (f"{name} of harmful corrections", False)):
                vals = [r[key] for r in rs if r[key] is not None and r["before_px"] is not None
                        and (r["before_px"] < r["nominal_px"]) == good]
                row[label] = f"{fmt.format(min(vals))}-{fmt.format(max(vals))}" if vals else "-"
        rows.append(row)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--results", default="docs/results", help="where the other benches wrote their json")
    ap.add_argument("--out", default="out/bench_guard")
    args = ap.parse_args(argv)
    records, read = collect(args.results)
    if not records:
        ap.error(f"no bench results in {args.results}")
    os.makedirs(args.out, exist_ok=True)
    cols = [(k, k.replace("_", " "), "{}") for k in records[0]]
    summ = summary(records)
    wrong = [r for r in records if r["outcome"] in OUTCOMES[2:]]
    lines = ["# The guard's verdicts across the benches (bench/bench_guard.py)", "",
             "Every calibration that the other benches ran and wrote into " + ", ".join(f"`{n}`" for n in read)
             + " (no calibration runs here). Errors: gauge-aligned reprojection error of ROI points, mean, px, of the "
             "nominal geometry, of the estimate before the guard and of the final geometry. R: how far the correction "
             "moved the views against random errors of the robots' stated accuracy; limit: the scan-level limit the "
             "guard applied (guard_max_ratio, or guard_max_ratio_unmodelled on a strongly truncated scan without the "
             "exterior model). Outcome: a helpful correction kept or a harmful one refused is right; a harmful one "
             "applied is a miss, a helpful one refused a loss; a calibration that undid its first iteration "
             "(undo_inconsistent) made no correction and is not judged. Scans started at their true geometry are left "
             "out.", "",
             "## Summary", "", markdown_table(summ, [(k, k, "{}") for k in summ[0]]), "",
             f"Misses and losses: {len(wrong)} of {len(records)}"
             + (": " + "; ".join(f"{r['source']} {r['scan']} {r['method']} ({r['outcome']}, {_outcome_px(r)} against "
                                 f"{r['nominal_px']} px nominal)" for r in wrong) if wrong else "") + ".", "",
             "## Every calibration", "", markdown_table(records, cols), ""]
    with open(os.path.join(args.out, "guard.md"), "w") as f:
        f.write("\n".join(lines))
    with open(os.path.join(args.out, "guard.json"), "w") as f:
        json.dump({"bench": "bench/bench_guard.py", "read": read, "summary": summ, "records": records}, f, indent=2)
    print(f"wrote {args.out}/guard.md: {len(records)} calibrations, {len(wrong)} misses or losses")
    return 0


if __name__ == "__main__":
    sys.exit(main())
