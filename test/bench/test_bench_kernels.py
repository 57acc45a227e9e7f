"""bench_projector.py and bench_fdk.py write what they print (projector.md / fdk.md and their json) where --out says."""

from __future__ import annotations

import json


def test_the_projector_and_fdk_benches_write_their_timings_and_ratios(load_bench, tmp_path):
    load_bench("bench_projector").main(["--size", "16", "--views", "4", "--no-rtk", "--out", str(tmp_path)])
    load_bench("bench_fdk").main(["--size", "16", "--views", "8", "--no-rtk", "--out", str(tmp_path)])
    projector = json.loads((tmp_path / "projector.json").read_text())
    assert projector["views"] == 4 and projector["rays"] == 4 * 16 * 16
    assert all(t > 0 for t in projector["ours_forward_wall_s"] + projector["ours_back_wall_s"])
    assert "| forward |" in (tmp_path / "projector.md").read_text()
    fdk = json.loads((tmp_path / "fdk.json").read_text())
    assert fdk["views"] == 8 and fdk["ours_s"] > 0 and fdk["ours_rmse"] < fdk["ours_nominal_geometry_rmse"] * 10
    fdk_md = (tmp_path / "fdk.md").read_text()
    assert "| ours (numba) |" in fdk_md and "RTK / ours" not in fdk_md
