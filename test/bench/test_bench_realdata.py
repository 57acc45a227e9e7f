"""bench/bench_realdata.py on a cut-down run of the real HTC2022 data (skipped where the shared data are absent):
our FDK matches the dataset's own FBP, the opposed rays agree with the documented centre of rotation, and
ncc-lle-exact undoes most of the injected geometry error, on the measured data and on their synthetic twin."""

from __future__ import annotations

import json

import numpy as np
import pytest



def test_noise_sigma_finds_white_noise_under_edges_and_skips_masked_pixels(load_bench):
    bench = load_bench("bench_realdata")
    rng = np.random.default_rng(3)
    u = np.linspace(-1.0, 1.0, 400)
    clean = np.where(np.abs(u) < 0.7, 2.0 * np.sqrt(np.clip(0.49 - u ** 2, 0, None)), 0.0)  # a disc with sharp edges
    clean = clean - 0.3 * ((u > 0.1) & (u < 0.2))  # and a hole
    data = np.broadcast_to(clean, (50, 1, 400)) + rng.standard_normal((50, 1, 400)) * 0.01
    assert bench.noise_sigma(data) == pytest.approx(0.01, rel=0.05)
    spoiled = data.copy()
    spoiled[:, :, 50:350] += rng.standard_normal((50, 1, 300)) * 1.0  # dead and hot pixels, masked out
    mask = np.ones(400, bool)
    mask[50:350] = False
    assert bench.noise_sigma(spoiled) > 0.05
    assert bench.noise_sigma(spoiled, mask) == pytest.approx(0.01, rel=0.05)


@pytest.mark.slow
def test_bench_realdata_matches_the_dataset_and_corrects_injected_errors(tmp_path, load_bench, htc2022_01a):
    bench = load_bench("bench_realdata")
    assert bench.main(["--data", str(htc2022_01a), "--phantoms", "01a", "--cases", "independent,twin", "--view-step", "24",
                       "--methods", "none,ncc-lle-exact,documented geometry", "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "realdata.json").read_text())
    ph = report["phantoms"]["01a"]
    best = ph["geometry_check"]["best"]
    assert best["correlation"]["rows flipped"] > 0.999
    assert max(best["correlation"].values()) == best["correlation"]["rows flipped"]
    rows = {r["method"]: r for r in ph["cases"]["independent"]["rows"]}
    assert rows["none"]["reproj_mean_px"] > 0.5  # 30 views: 0.80 px injected
    assert rows["ncc-lle-exact"]["reproj_mean_px"] < 0.6 * rows["none"]["reproj_mean_px"]
    assert rows["documented geometry"]["reproj_mean_px"] == pytest.approx(0.0, abs=1e-6)
    # the one-row floor lies between the truth and the nominal; the opposed rays find the documented
    # centre of rotation within a fraction of a pixel (all 720 views)
    assert 0.0 < rows["oracle floor"]["reproj_mean_px"] < 0.3 * rows["none"]["reproj_mean_px"]
    assert abs(ph["geometry_check"]["opposed_rays"]["best_shift_px"]) < 0.2
    assert (tmp_path / "realdata.md").read_text().startswith("# Real data: HTC2022")
    assert (tmp_path / "realdata_01a_independent_slices.png").stat().st_size > 0
    # the twin: data the documented geometry explains exactly, close to the measured ones; the same
    # injected errors; no slice figure (it would look like the measured case's)
    assert ph["twin"]["correlation_with_measured"] > 0.99
    assert 0.0 < ph["twin"]["noise_sigma"] < 0.05
    twin = {r["method"]: r for r in ph["cases"]["twin"]["rows"]}
    assert twin["none"]["reproj_mean_px"] == pytest.approx(rows["none"]["reproj_mean_px"], rel=1e-9)
    assert twin["ncc-lle-exact"]["reproj_mean_px"] < 0.6 * twin["none"]["reproj_mean_px"]
    assert "slices" not in ph["cases"]["twin"]["figures"]
    assert (tmp_path / "realdata_01a_twin_param_error.png").stat().st_size > 0


def test_bench_realdata_calibrates_a_short_arc_of_the_views(tmp_path, load_bench, htc2022_01a):
    """``--arc-deg 210`` keeps the views within 210 degrees of the first (a short scan: 18 of the 30 views that
    ``--view-step 24`` keeps over the full circle), says so in realdata.md, and refuses an arc of half a turn or
    less in one line."""
    bench = load_bench("bench_realdata")
    assert bench.main(["--data", str(htc2022_01a), "--phantoms", "01a", "--cases", "independent", "--view-step", "24",
                       "--methods", "none,documented geometry", "--arc-deg", "210", "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "realdata.json").read_text())
    assert report["phantoms"]["01a"]["views_used"] == 18  # 0, 12, ..., 204 degrees
    assert "only the views within 210 degrees of the first (a short scan, 18 views" in (
        tmp_path / "realdata.md").read_text()
    with pytest.raises(SystemExit):
        bench.main(["--data", str(htc2022_01a), "--arc-deg", "180", "--out", str(tmp_path)])
