"""bench/bench_guard.py: each verdict the benches wrote is classified from the errors and the guard's notes."""

from __future__ import annotations

import json

import pytest


def _row(method, error, ncc=0.9):
    return {"method": method, "reproj_mean_px": error, "model_ncc": ncc}


def test_every_outcome_is_told_from_the_errors_and_the_notes(tmp_path, load_bench):
    bench = load_bench("bench_guard")
    applied = "guard: the correction is {:.2f} times the robots' stated accuracy (limit {:g})"
    refused = ("guard: the correction moved the views {:.2f} times as far as the robots' stated accuracy explains "
               "(limit {:g}); the data do not support it and the nominal geometry is kept")
    truncated = "strongly truncated (truncation level 0.640 > 0.3), yet the object outside the ROI was not modelled"
    results = {"scenarios": [{"key": "x", "rows": [_row("none", 3.0), _row("good", 0.5), _row("bad", 3.5),
                                                   _row("refused-bad", 3.0), _row("refused-good", 3.0),
                                                   _row("poor-model", 3.0, 0.3), _row("undone", 3.0),
                                                   _row("true geometry", 0.0)],
                              "notes": {"good": [applied.format(0.9, 1.5)], "bad": [truncated, applied.format(0.95, 1)],
                                        "undone": ["undo_inconsistent: iteration 1 lowered the FDK's data consistency "
                                                   "(reprojection NCC 0.9 -> 0.8) and was undone; no correction "
                                                   "was made", applied.format(0, 1.5)],
                                        "refused-bad": [truncated, refused.format(1.09, 1),
                                                        "before the guard 3.338 px mean, 6.0 px p95"],
                                        "refused-good": [refused.format(1.6, 1.5),
                                                         "before the guard 1.2 px mean, 2 px p95"],
                                        "poor-model": [truncated, "guard: the estimation model explains the data "
                                                       "poorly (projection NCC 0.300 < 0.5); the nominal geometry is "
                                                       "kept", "before the guard 5.0 px mean, 9 px p95"]}}]}
    (tmp_path / "results.json").write_text(json.dumps(results))
    records, read = bench.collect(str(tmp_path))
    assert read == ["results.json"]
    by = {r["method"]: r for r in records}
    assert set(by) == {"good", "bad", "refused-bad", "refused-good", "poor-model", "undone"}  # no 'none', no truth
    assert by["undone"]["outcome"] == "made no correction"  # ended where it started: neither a miss nor a keep
    assert by["good"]["outcome"] == "kept a helpful correction" and by["good"]["ratio"] == 0.9
    assert by["good"]["regime"] == "ROI model, not strongly truncated" and by["good"]["limit"] == 1.5
    assert by["bad"]["outcome"] == "applied a harmful correction" and by["bad"]["limit"] == 1.0
    assert by["refused-bad"]["outcome"] == "refused a harmful correction"
    assert by["refused-bad"]["ratio"] == 1.09 and by["refused-bad"]["before_px"] == 3.338
    assert by["refused-bad"]["regime"] == "strongly truncated, not modelled"
    assert by["refused-good"]["outcome"] == "refused a helpful correction"
    assert by["poor-model"]["verdict"] == "scan kept nominal (model NCC)"
    assert by["poor-model"]["outcome"] == "refused a harmful correction"
    summary = {s["regime"]: s for s in bench.summary(records)}
    assert summary["strongly truncated, not modelled"]["refused a harmful correction"] == 2
    assert summary["strongly truncated, not modelled"]["R of harmful corrections"] == "0.95-1.09"
    # the model NCC the floors read, over the harmful corrections (before the guard) of that regime
    assert summary["strongly truncated, not modelled"]["model NCC of harmful corrections"] == "0.300-0.900"
    assert summary["ROI model, not strongly truncated"]["model NCC of helpful corrections"] == "0.900-0.900"
    assert summary["ROI model, not strongly truncated"]["made no correction"] == 1
    out = tmp_path / "out"
    assert bench.main(["--results", str(tmp_path), "--out", str(out)]) == 0
    text = (out / "guard.md").read_text()
    assert "Misses and losses: 2 of 6" in text and "refused-good" in text
    # a miss is told by where it ended, a loss by what the refused correction would have reached
    assert "bad (applied a harmful correction, ended at 3.5 against 3.0 px nominal)" in text
    assert "refused-good (refused a helpful correction, would have reached 1.2 against 3.0 px nominal)" in text


def test_no_bench_results_is_an_error(tmp_path, load_bench):
    with pytest.raises(SystemExit):
        load_bench("bench_guard").main(["--results", str(tmp_path), "--out", str(tmp_path / "out")])


def test_runs_with_another_seed_are_read_from_their_folders(tmp_path, load_bench):
    bench = load_bench("bench_guard")
    applied = "guard: the correction is 0.80 times the robots' stated accuracy (limit 1.5)"
    for folder, final in (("", 1.4), ("interior_seed_1", 1.6)):
        (tmp_path / folder).mkdir(exist_ok=True)
        scans = {"scans": [{"sigma": 0.1, "rows": [_row("none", 2.2), _row("ncc-lle-exact", final)],
                            "notes": {"ncc-lle-exact": [applied]}}]}
        (tmp_path / folder / "interior.json").write_text(json.dumps(scans))
    sweep = {"scales": {"2": {"errors_px": {"none": 3.0, "gdc": 0.5}, "notes": {"gdc": [applied]},
                              "model_ncc": {"gdc": 0.97}}}}
    (tmp_path / "sweep_seed_1").mkdir()
    (tmp_path / "sweep_seed_1" / "sweep.json").write_text(json.dumps(sweep))
    reach = {"sigma": 0.1, "nominal_mean_px": 2.1, "rows": [{"half_width_mm": 0, "mean_px": 2.5, "model_ncc": 0.89,
                                                             "notes": [applied]}]}
    (tmp_path / "exterior_reach_seed_1").mkdir()
    (tmp_path / "exterior_reach_seed_1" / "exterior_reach.json").write_text(json.dumps(reach))
    real = {"phantoms": {"01a": {"cases": {"independent": {"rows": [_row("none", 1.15), _row("gdc", 0.2)],
                                                           "notes": {"gdc": [applied]}}}}}}
    (tmp_path / "realdata_seed_1").mkdir()
    (tmp_path / "realdata_seed_1" / "realdata.json").write_text(json.dumps(real))
    records, read = bench.collect(str(tmp_path))
    assert read == ["interior.json", "interior_seed_1/interior.json", "sweep_seed_1/sweep.json",
                    "exterior_reach_seed_1/exterior_reach.json", "realdata_seed_1/realdata.json"]
    real_record = next(r for r in records if r["source"] == "realdata_seed_1/realdata.json")
    assert real_record["scan"] == "HTC2022 01a independent" and real_record["outcome"] == "kept a helpful correction"
    reached = next(r for r in records if r["source"] == "exterior_reach_seed_1/exterior_reach.json")
    assert reached["outcome"] == "applied a harmful correction" and reached["scan"] == "neck 0.1 mm / 0.1 deg"
    by_source = {r["source"]: r for r in records}
    assert by_source["interior.json"]["after_px"] == 1.4
    assert by_source["interior_seed_1/interior.json"]["after_px"] == 1.6
    assert by_source["sweep_seed_1/sweep.json"]["outcome"] == "kept a helpful correction"


def test_a_guessed_reach_is_read_as_an_exterior_modelled_calibration(tmp_path, load_bench):
    """reach_guess.json: one row per scan, its error before the guard as ``unguarded_px``."""
    bench = load_bench("bench_guard")
    refused = ("guard: the correction moved the views 1.60 times as far as the robots' stated accuracy explains "
               "(limit 1.5); the data do not support it and the nominal geometry is kept")
    rows = [{"title": "the interior neck", "guessed_reach_mm": 15.337, "nominal_px": 2.2, "error_px": 1.8,
             "unguarded_px": 1.8, "model_ncc": 0.95,
             "notes": ["the object outside the ROI was modelled (exterior model)",
                       "guard: the correction is 0.90 times the robots' stated accuracy (limit 1.5)"]},
            {"title": "(c)", "guessed_reach_mm": 36.8, "nominal_px": 3.4, "error_px": 3.4, "unguarded_px": 4.0,
             "notes": ["the object outside the ROI was modelled (exterior model)", refused]}]
    (tmp_path / "reach_guess.json").write_text(json.dumps({"rows": rows}))
    records, read = bench.collect(str(tmp_path))
    assert read == ["reach_guess.json"]
    neck, c = records
    assert neck["method"] == "ncc-lle-exact, reach guessed (15.3 mm)" and neck["regime"] == "exterior modelled"
    assert neck["outcome"] == "kept a helpful correction" and neck["model_ncc"] == 0.95
    assert c["outcome"] == "refused a harmful correction" and c["before_px"] == 4.0 and c["ratio"] == 1.6
