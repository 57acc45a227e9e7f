"""bench/bench_short_scan.py on a cut-down run of the real HTC2022 data (skipped where the shared data are absent):
half a turn plus the fan and 15 degrees of phantom 01a reconstructs with Parker's weights as the full circle does,
and weighted as a full circle it loses about half its attenuation."""

from __future__ import annotations

import json

import pytest


def test_a_short_arc_of_measured_data_reconstructs_as_the_full_circle(tmp_path, load_bench, htc2022_01a):
    bench = load_bench("bench_short_scan")
    assert bench.main(["--data", str(htc2022_01a), "--phantoms", "01a", "--arcs", "15", "--starts", "90",
                       "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "short_scan.json").read_text())
    rows = {r["weights"]: r for r in report["rows"]}
    assert set(rows) == {"full circle", "Parker", "full-circle 1/2"}
    assert 190.0 < rows["Parker"]["arc_deg"] <= 195.0 and rows["Parker"]["views"] < 0.6 * rows["full circle"]["views"]
    assert rows["full circle"]["corr_dataset"] > 0.99
    assert rows["Parker"]["corr_dataset"] > 0.99 and rows["Parker"]["corr_full"] > 0.995
    assert rows["Parker"]["mean_rel"] == pytest.approx(1.0, abs=0.02)
    assert rows["full-circle 1/2"]["mean_rel"] < 0.7
    assert (tmp_path / "short_scan.md").read_text().startswith("# Short scans of measured fan-beam data")
