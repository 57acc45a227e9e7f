"""Calibration report: figures and a table whose numbers equal independently computed metrics."""

import json

import numpy as np
import pytest

from robot_ct_ros.ct.calibration import CalibrationResult, IterationRecord
from robot_ct_ros.ct.geometry import VolumeGrid
from robot_ct_ros.ct.metrics import cap_thickness_mm, edge_sharpness, reprojection_error, roi_points, ssim
from robot_ct_ros.jobs.figures import markdown_table, method_notes, write_report
from robot_ct_ros.ct.simulation import carotid_plaque_phantom, robot_coordination, voxelize
from robot_ct_ros.ct.trajectory import circular_scan

PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def inputs():
    phantom = carotid_plaque_phantom(cap_thickness_mm=0.06)
    # a small slab around the cap (along -y from the lumen): fine in x-y, coarse along the vessel
    grid = VolumeGrid.centered((8, 48, 24), (0.03, 0.03, 0.5), (0.0, -2.75, 0.0))
    truth_vol = voxelize(phantom, grid)
    rng = np.random.default_rng(0)
    blurred = truth_vol + rng.normal(0, 0.002, truth_vol.shape).astype(np.float32)
    nominal = circular_scan(12, 128.0, 342.4, 20, 24, 0.11, 0.11, center_mm=grid.center_mm)
    true = nominal.perturbed(robot_coordination(0.3, 0.3, seed=2).sample(12))
    est = nominal.perturbed(0.2 * robot_coordination(0.3, 0.3, seed=2).sample(12) + true.params_relative_to(nominal))
    hist = (IterationRecord(1, 0.05, 0.99, 0.2, 0.1, 1.5), IterationRecord(2, 0.03, 0.995, 0.05, 0.02, 1.4))
    results = {
        "none": (nominal, blurred, ()),
        "m1": CalibrationResult("m1", est.params_relative_to(nominal), est, blurred * 0.9, hist, 3.25),
        "true geometry": (true, truth_vol, (), 0.5),
    }
    return phantom, grid, truth_vol, nominal, true, results


def test_report_files_and_numbers(tmp_path, inputs):
    phantom, grid, truth_vol, nominal, true, results = inputs
    paths = write_report(tmp_path, results, grid, truth=(true, truth_vol, phantom), nominal=nominal, name="s",
                         title="tiny", initial_rmse=0.08)
    for key in ("slices", "rmse", "param_error"):
        data = paths[key].read_bytes()
        assert data.startswith(PNG) and len(data) > 1000, key
    table = json.loads(paths["json"].read_text())
    md = paths["markdown"].read_text()
    assert md.startswith("## tiny") and "| method |" in md and "![slices](s_slices.png)" in md
    assert len(md.strip().splitlines()[2:]) >= 5  # header, separator, 3 rows
    pts = roi_points(grid)
    rows = {r["method"]: r for r in table["rows"]}
    assert list(rows) == ["none", "m1", "true geometry"]
    for m, res in results.items():
        geom = res.geom if hasattr(res, "geom") else res[0]
        vol = res.volume if hasattr(res, "volume") else res[1]
        err = reprojection_error(geom, true, pts)
        r = rows[m]
        assert r["reproj_mean_px"] == pytest.approx(err["mean_px"], rel=1e-9, abs=1e-12)
        assert r["reproj_p95_px"] == pytest.approx(err["p95_px"], rel=1e-9, abs=1e-12)
        assert r["ssim"] == pytest.approx(ssim(vol, truth_vol), rel=1e-9)
        assert r["sharpness"] == pytest.approx(edge_sharpness(vol), rel=1e-9)
        cap = cap_thickness_mm(vol, grid, phantom.cap)
        assert np.isfinite(cap)
        assert r["cap_um"] == pytest.approx(1000 * cap, rel=1e-9)
        # and the Markdown shows the same numbers, rounded
        line = next(ln for ln in md.splitlines() if ln.startswith(f"| {m} |"))
        assert f"{err['mean_px']:.3f}" in line and f"{1000 * cap:.1f}" in line
    assert rows["m1"]["iterations"] == 2 and rows["m1"]["wall_s"] == pytest.approx(3.25)
    assert rows["m1"]["projection_rmse"] == [0.05, 0.03]
    assert rows["none"]["wall_s"] is None and rows["true geometry"]["wall_s"] == pytest.approx(0.5)
    assert rows["true geometry"]["reproj_mean_px"] < 1e-6 and rows["true geometry"]["ssim"] == pytest.approx(1.0)
    assert rows["none"]["reproj_mean_px"] > rows["m1"]["reproj_mean_px"]


def test_report_without_figures_writes_the_same_table_alone(tmp_path, inputs):
    phantom, grid, truth_vol, nominal, true, results = inputs
    with_figures = write_report(tmp_path / "a", results, grid, truth=(true, truth_vol, phantom), nominal=nominal,
                                name="s", title="tiny")
    table_only = write_report(tmp_path / "b", results, grid, truth=(true, truth_vol, phantom), nominal=nominal,
                              name="s", title="tiny", figures=False)
    assert sorted(f.name for f in (tmp_path / "b").iterdir()) == ["s.json", "s.md"]
    assert not {"slices", "rmse", "param_error"} & set(table_only)
    md = table_only["markdown"].read_text()
    assert "![" not in md and md == with_figures["markdown"].read_text().split("![")[0]
    assert table_only["rows"] == with_figures["rows"]


def test_report_without_truth(tmp_path, inputs):
    phantom, grid, truth_vol, nominal, true, results = inputs
    paths = write_report(tmp_path, results, grid, name="u")
    assert "param_error" not in paths and paths["slices"].read_bytes().startswith(PNG)
    rows = json.loads(paths["json"].read_text())["rows"]
    assert all(r["reproj_mean_px"] is None and r["ssim"] is None and r["cap_um"] is None for r in rows)
    md = markdown_table(rows)
    assert "SSIM" not in md and "edge sharpness" in md


def test_ssim_is_taken_in_the_true_gauge_when_a_reconstruction_is_given(inputs):
    """An estimate that differs from the truth by the gauge alone (a rigid motion) reconstructs
    the true image once moved back: SSIM 1 with ``reconstruct``, not without."""
    from robot_ct_ros.ct.metrics import rigidly_moved
    from robot_ct_ros.jobs.figures import summarize

    phantom, grid, truth_vol, nominal, true, _ = inputs
    pts = roi_points(grid)
    moved = rigidly_moved(true, [0.0, 0.0, 0.02], [0.05, -0.03, 0.0], pts.mean(axis=0))
    shifted = np.roll(truth_vol, 2, axis=1)  # what the moved geometry reconstructs: the object elsewhere
    calls = []

    def reconstruct(geom):
        calls.append(geom)
        return truth_vol if np.allclose(geom.source_mm, true.source_mm, atol=1e-5) else shifted

    results = {"gauge only": (moved, shifted, (), 1.0)}
    plain = summarize(results, grid, (true, truth_vol, None), pts)[0]["ssim"]
    aligned = summarize(results, grid, (true, truth_vol, None), pts, reconstruct=reconstruct)[0]["ssim"]
    assert len(calls) == 1 and aligned == pytest.approx(1.0) and plain < 0.9, (plain, aligned)


def test_the_true_geometry_row_is_not_reconstructed_again(inputs):
    """The true geometry needs no move into the true gauge: its row keeps its volume, and
    ``reconstruct`` runs only for the rows that differ from it."""
    from robot_ct_ros.jobs.figures import summarize

    phantom, grid, truth_vol, nominal, true, _ = inputs
    calls = []

    def reconstruct(geom):
        calls.append(geom)
        return truth_vol

    results = {"true geometry": (true, truth_vol, (), 0.0), "none": (nominal, truth_vol, (), 0.0)}
    rows = summarize(results, grid, (true, truth_vol, None), reconstruct=reconstruct)
    assert len(calls) == 1 and not calls[0].allclose(true)
    assert rows[0]["ssim"] == pytest.approx(1.0)


def test_the_cap_is_measured_in_the_true_gauge_and_in_reconstruct_cap_when_given(inputs):
    """The cap row uses the gauge-aligned reconstruction, and ``reconstruct_cap`` (a fine
    grid of its own) gets the gauge-aligned geometry: a rigidly moved truth measures as the truth."""
    from robot_ct_ros.ct.metrics import rigidly_moved
    from robot_ct_ros.jobs.figures import summarize

    phantom, grid, truth_vol, nominal, true, _ = inputs
    pts = roi_points(grid)
    moved = rigidly_moved(true, [0.0, 0.0, 0.0], [0.0, 0.3, 0.0], pts.mean(axis=0))
    shifted = np.roll(truth_vol, 10, axis=1)  # the cap 0.3 mm away: no ridge where it should be
    sharp = 1000 * cap_thickness_mm(truth_vol, grid, phantom.cap)
    assert np.isnan(cap_thickness_mm(shifted, grid, phantom.cap))

    def reconstruct(geom):
        return truth_vol if np.allclose(geom.source_mm, true.source_mm, atol=1e-5) else shifted

    results = {"gauge only": (moved, shifted, (), 1.0)}
    truth = (true, truth_vol, phantom)
    assert summarize(results, grid, truth, pts)[0]["cap_um"] is None
    assert summarize(results, grid, truth, pts, reconstruct=reconstruct)[0]["cap_um"] == pytest.approx(sharp)
    fine = VolumeGrid.centered((8, 110, 40), (0.015, 0.015, 0.5), (0.0, -2.53, 0.0))  # holds the whole profile
    fine_vol = voxelize(phantom, fine)
    seen = []

    def reconstruct_cap(geom, method):
        seen.append((geom, method))
        return (fine_vol, fine) if np.allclose(geom.source_mm, true.source_mm, atol=1e-5) else (shifted, grid)

    row = summarize(results, grid, truth, pts, reconstruct=reconstruct, reconstruct_cap=reconstruct_cap)[0]
    assert [m for _, m in seen] == ["gauge only"] and row["cap_um"] == pytest.approx(1000 * cap_thickness_mm(fine_vol, fine, phantom.cap))
    assert row["cap_um"] == pytest.approx(60.0, abs=15.0)


def test_cap_slab_figure(tmp_path, inputs):
    from robot_ct_ros.jobs.figures import plot_cap_slabs

    phantom, grid, truth_vol, *_ = inputs
    path = plot_cap_slabs(tmp_path / "cap.png", {"a": truth_vol, "b": truth_vol[::-1]}, grid, phantom.cap,
                          reference=truth_vol, title="cap")
    data = path.read_bytes()
    assert data.startswith(PNG) and len(data) > 1000


def test_method_notes_carry_the_guard_verdict_and_the_error_of_the_estimate_before_it(inputs):
    _, grid, _, nominal, true, results = inputs
    m1 = results["m1"]
    kept = CalibrationResult("m2", np.zeros_like(m1.params), nominal, m1.volume, m1.history, 1.0,
                             notes=("guard: kept",), params_unguarded=m1.params)
    notes = method_notes({**results, "m2": kept}, nominal, true, roi_points(grid))
    assert set(notes) == {"m2"}  # nothing to say for the others
    e = reprojection_error(nominal.perturbed(m1.params), true, roi_points(grid))
    assert notes["m2"] == ["guard: kept", f"before the guard {e['mean_px']:.3f} px mean, {e['p95_px']:.3f} px p95"]


def test_the_table_gives_the_error_before_the_guard_where_the_guard_changed_anything(tmp_path, inputs):
    """A result the guard kept at its nominal geometry shows, with the truth and the nominal geometry, the
    error its estimate had before the guard (as method_notes computes it); the others show none, and a
    table where the guard changed nothing has no such column."""
    from robot_ct_ros.jobs.figures import summarize

    _, grid, truth_vol, nominal, true, results = inputs
    m1 = results["m1"]
    kept = CalibrationResult("m2", np.zeros_like(m1.params), nominal, m1.volume, m1.history, 1.0,
                             notes=("guard: kept",), params_unguarded=m1.params)
    truth = (true, truth_vol, None)
    rows = {r["method"]: r for r in summarize({**results, "m2": kept}, grid, truth, nominal=nominal)}
    e = reprojection_error(nominal.perturbed(m1.params), true, roi_points(grid))["mean_px"]
    assert rows["m2"]["unguarded_mean_px"] == pytest.approx(e)
    assert rows["m2"]["reproj_mean_px"] == pytest.approx(reprojection_error(nominal, true, roi_points(grid))["mean_px"])
    assert all(rows[k]["unguarded_mean_px"] is None for k in results)
    # without the nominal geometry the error before the guard cannot be told
    assert summarize({"m2": kept}, grid, truth)[0]["unguarded_mean_px"] is None
    paths = write_report(tmp_path / "g", {**results, "m2": kept}, grid, truth, nominal, figures=False)
    assert "before the guard, mean (px)" in paths["markdown"].read_text()
    paths = write_report(tmp_path / "n", results, grid, truth, nominal, figures=False)
    assert "before the guard" not in paths["markdown"].read_text()


def test_a_one_slice_grid_and_no_iterations_leave_no_blank_panels_and_no_warnings(tmp_path, inputs, monkeypatch):
    """A fan-beam (one-row) scan's report: the sagittal panels were blank and matplotlib warned (identical
    ylims); with --methods none the RMSE plot was empty. Now the slices are the axial row alone, the RMSE panel
    says that no method ran an iteration, and nothing is warned."""
    import warnings

    from robot_ct_ros.jobs import figures

    _, grid, _, nominal, _, _ = inputs
    thin = VolumeGrid.centered((1, 48, 24), (0.03, 0.03, 0.5), grid.center_mm)
    vol = np.random.default_rng(0).random(thin.shape_zyx).astype(np.float32)
    drawn = []
    save = figures._save
    monkeypatch.setattr(figures, "_save", lambda fig, path: drawn.append(fig) or save(fig, path))
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        paths = write_report(tmp_path, {"none": (nominal, vol, ())}, thin, initial_rmse=0.08)
    assert not [w for w in seen if issubclass(w.category, UserWarning)], [str(w.message) for w in seen]
    slices, rmse = drawn
    assert len(slices.axes) == 1 and not any("sagittal" in ax.get_ylabel() for ax in slices.axes)
    assert any("no outer iterations" in t.get_text() for t in rmse.axes[0].texts)
    assert paths["slices"].read_bytes().startswith(PNG) and paths["rmse"].read_bytes().startswith(PNG)


def test_the_rmse_figure_labels_a_method_whose_guard_changed_its_estimate(tmp_path, inputs, monkeypatch):
    """The RMSE-per-iteration figure showed a method improving where the guard had kept the nominal geometry, with
    nothing to tell it from an applied correction; its line is now labelled as the estimate's."""
    from robot_ct_ros.jobs import figures

    _, grid, truth_vol, nominal, true, results = inputs
    m1 = results["m1"]
    kept = CalibrationResult("m2", np.zeros_like(m1.params), nominal, m1.volume, m1.history, 1.0,
                             notes=("guard: kept",), params_unguarded=m1.params)
    labels = []
    monkeypatch.setattr(figures, "_save", lambda fig, path: labels.extend(
        line.get_label() for ax in fig.axes for line in ax.lines) or path)
    figures.plot_rmse(tmp_path / "rmse.png", {"m1": m1, "m2": kept})
    assert labels == ["m1", "m2 (estimate: the guard changed it)"]
