"""robot-ct command line: simulate -> info -> reconstruct (and calibrate) on a tiny scan."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from robot_ct_ros.cli import main


def _read_with_rosbags_and_mcap(bag) -> int:
    import warnings

    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        from mcap_ros2.reader import read_ros2_messages
    ts = get_typestore(Stores.ROS2_JAZZY)
    with Reader(bag) as reader:
        n = sum(1 for conn, _, raw in reader.messages() if ts.deserialize_cdr(raw, conn.msgtype) is not None)
    assert n == sum(1 for _ in read_ros2_messages(str(next(bag.glob("*.mcap")))))
    return n


def test_simulate_info_reconstruct_calibrate(tmp_path, capsys):
    bag = tmp_path / "scan"
    assert main(["simulate", "--phantom", "mouse", "--views", "24", "--rows", "32", "--cols", "48",
                 "--binning", "2", "--sigma-mm", "0.05", "--seed", "3", "--out", str(bag)]) == 0
    assert _read_with_rosbags_and_mcap(bag) == 3 + 3 * 24  # info, flat, dead; frame, geometry, true geometry
    out = capsys.readouterr().out
    assert "simulate" in out and "24" in out

    assert main(["info", str(bag)]) == 0
    out = capsys.readouterr().out
    assert "24 paired frames" in out and "32 x 48 pixels" in out and "true geometry: yes" in out
    assert main(["info", "--json", str(bag)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["scan_info"]["phantom"] == "mouse" and summary["topics"]["/ct/projection"]["messages"] == 24

    recon = tmp_path / "recon"
    assert main(["reconstruct", str(bag), "--out", str(recon)]) == 0
    vol = np.load(recon / "volume.npy")
    report = json.loads((recon / "report.json").read_text())
    assert vol.shape == tuple(report["grid"]["shape_zyx"]) and vol.dtype == np.float32
    assert np.isfinite(vol).all() and 0.005 < float(np.median(vol)) < 0.2  # tissue (~0.02 /mm) plus truncation offset
    assert report["geometry"] == "nominal" and report["geometry_error"]["rms_translation_mm"] > 0
    import tifffile
    assert tifffile.imread(recon / "volume.tif").shape == vol.shape

    calib = tmp_path / "calib"
    assert main(["calibrate", str(bag), "--method", "none", "--out", str(calib)]) == 0
    report = json.loads((calib / "report.json").read_text())
    assert report["method_used"] == "none" and (calib / "scan_corrected" / "metadata.yaml").exists()
    assert _read_with_rosbags_and_mcap(calib / "scan_corrected") == 3 + 4 * 24
    assert main(["info", str(calib / "scan_corrected")]) == 0
    assert "corrected geometry: yes" in capsys.readouterr().out

    # this tiny scan of a whole mouse is truncated enough for the guard to distrust its model; the runs below test
    # the sampling and settings mechanics, so they turn it off (--no-guard); the guard's own verdict first:
    guarded = tmp_path / "calib_guarded"
    assert main(["calibrate", str(bag), "--method", "ncc-lle", "--iterations", "1", "--out", str(guarded)]) == 0
    notes = json.loads((guarded / "report.json").read_text())["notes"]
    assert any(note.startswith("guard:") for note in notes), notes
    mapped = tmp_path / "calib_prior"
    assert main(["calibrate", str(bag), "--method", "ncc-lle", "--iterations", "3", "--prior-sigma", "0.2,0.25",
                 "--stop-px", "1000", "--seed", "3", "--no-guard", "--out", str(mapped)]) == 0
    report = json.loads((mapped / "report.json").read_text())
    np.testing.assert_allclose(report["prior_sigma"], [0.2] * 6 + [np.deg2rad(0.25)] * 3)
    assert report["seed"] == 3 and report["padding"] == 1.25  # calibration.DEFAULT_PADDING
    assert report["drift_order"] is None  # independent per-view errors unless asked
    assert 0.0 < report["history"][0]["independent_fraction"] <= 1.0
    # every iteration moves the views less than 1000 px: one of at most three ran
    assert report["iterations"] == 3 and report["iterations_run"] == len(report["history"]) == 1
    assert report["history"][0]["update_px"] > 0.0
    data_alone = tmp_path / "calib_gdc"  # GDC has no independent-pixel fraction: NaN in the record
    # the mechanism under test is the drift model: the guard, which rightly distrusts a model this small scan's
    # truncation leaves poor, is off
    assert main(["calibrate", str(bag), "--method", "gdc", "--iterations", "1", "--prior-sigma", "none",
                 "--drift-order", "2", "--no-guard", "--out", str(data_alone)]) == 0

    def no_nan(token):
        raise AssertionError(f"report.json is not strict JSON: {token}")

    report = json.loads((data_alone / "report.json").read_text(), parse_constant=no_nan)
    assert report["prior_sigma"] is None and report["history"][0]["independent_fraction"] is None
    assert report["drift_order"] == 2
    from robot_ct_ros.bag import read_scan
    from robot_ct_ros.ct.calibration import fit_drift

    drifted = read_scan(data_alone / "scan_corrected")  # a drift model: the correction is a polynomial in time
    params = drifted.geom_corrected.params_relative_to(drifted.geom)
    assert np.abs(params).max() > 1e-4
    np.testing.assert_allclose(fit_drift(params, 2), params, atol=1e-5)  # polynomials, alternated with the gauge fix to 10 nm

    def rejected(option, value, message):
        """``calibrate`` refuses the option's value with a message naming it, and writes nothing."""
        with pytest.raises(SystemExit):
            main(["calibrate", str(bag), option, value, "--out", str(tmp_path / "never")])
        return message in capsys.readouterr().err and not (tmp_path / "never").exists()

    assert rejected("--prior-sigma", "0.2", "MM,DEG")
    assert rejected("--drift-order", "-1", "drift order must be >= 0")
    averaged = tmp_path / "calib_ensemble"  # two sampling seeds, averaged: the report says how far apart
    assert main(["calibrate", str(bag), "--method", "ncc-lle", "--iterations", "1", "--ensemble", "2", "--no-guard",
                 "--out", str(averaged)]) == 0
    report = json.loads((averaged / "report.json").read_text())
    assert report["ensemble"] == 2 and report["ensemble_spread_px"] > 0.0
    from robot_ct_ros.ct.calibration import calibrate
    from robot_ct_ros.jobs.calibrate import scan_grid

    scan = read_scan(bag)
    li, mask = scan.to_line_integrals()
    once = calibrate(li, scan.geom, scan_grid(scan, None, (24, 24, 12)), method="gdc", ensemble=3, iterations=1,
                     valid_mask=mask)
    assert once.members == 1  # a baseline draws no samples: its ensemble would be one run three times
    assert rejected("--ensemble", "0", "ensemble must be >= 1")
    assert rejected("--padding", "0.8", "padding must be >= 1")

    # compare methods on the corrected bag: its own corrected and true geometries join the table
    compared = tmp_path / "report"
    assert main(["report", str(mapped / "scan_corrected"), "--methods", "none,ncc-lle", "--iterations", "1",
                 "--prior-sigma", "0.2,0.25", "--seed", "3", "--no-guard", "--out", str(compared)]) == 0
    table = json.loads((compared / "report.json").read_text())
    rows = {r["method"]: r for r in table["rows"]}
    assert list(rows) == ["none", "ncc-lle", "bag corrected", "true geometry"]
    assert rows["true geometry"]["reproj_mean_px"] == 0.0 and rows["none"]["reproj_mean_px"] > 0.0
    # same data, settings and seed as the calibrate run that wrote the bag's corrected geometry
    assert rows["ncc-lle"]["reproj_mean_px"] == pytest.approx(rows["bag corrected"]["reproj_mean_px"], rel=1e-6)
    # the seed reaches the estimate: another one samples another correction
    assert main(["report", str(mapped / "scan_corrected"), "--methods", "ncc-lle", "--iterations", "1",
                 "--prior-sigma", "0.2,0.25", "--no-guard", "--out", str(tmp_path / "seed0")]) == 0
    seed0 = {r["method"]: r for r in json.loads((tmp_path / "seed0" / "report.json").read_text())["rows"]}
    assert seed0["ncc-lle"]["reproj_mean_px"] != pytest.approx(rows["ncc-lle"]["reproj_mean_px"], rel=1e-6)
    # so does the estimation grid's width (same seed, a wider grid: another volume to register against)
    assert main(["report", str(mapped / "scan_corrected"), "--methods", "ncc-lle", "--iterations", "1",
                 "--prior-sigma", "0.2,0.25", "--seed", "3", "--padding", "2", "--no-guard",
                 "--out", str(tmp_path / "wide")]) == 0
    wide = json.loads((tmp_path / "wide" / "report.json").read_text())
    assert wide["notes"]["padding"] == 2.0 and table["notes"]["padding"] == 1.25
    wide_row = {r["method"]: r for r in wide["rows"]}["ncc-lle"]
    assert wide_row["reproj_mean_px"] != pytest.approx(rows["ncc-lle"]["reproj_mean_px"], rel=1e-6)
    assert rows["ncc-lle"]["iterations"] == 1 and rows["none"]["iterations"] == 0
    for figure in ("report_slices.png", "report_rmse.png", "report_param_error.png", "report.md"):
        assert (compared / figure).stat().st_size > 0
    assert "| ncc-lle |" in (compared / "report.md").read_text()
    # each column's method and its notes (the guard's verdict...), not one method for all
    assert table["notes"]["methods"] == ["none", "ncc-lle"] and "method" not in table["notes"]["settings"]
    assert table["method_notes"]["ncc-lle"], table["method_notes"]
    assert f"- ncc-lle: {'; '.join(table['method_notes']['ncc-lle'])}" in (compared / "report.md").read_text()
    assert main(["report", str(bag), "--methods", "none,ncc-lle-fast", "--out", str(tmp_path / "never2")]) == 2
    assert "ncc-lle-fast" in capsys.readouterr().err and not (tmp_path / "never2").exists()


def test_clear_errors(tmp_path, capsys):
    assert main(["info", str(tmp_path / "missing")]) == 2
    assert "no such bag" in capsys.readouterr().err
    (tmp_path / "nodata").mkdir()
    (tmp_path / "nodata" / "nodata.mcap").write_bytes(b"\x89MCAP0\r\n")
    assert main(["info", str(tmp_path / "nodata")]) == 2
    assert "no readable message" in capsys.readouterr().err
    assert main(["reconstruct", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 2
    assert "no such bag" in capsys.readouterr().err


def test_info_reports_an_unusable_scan(tmp_path, capsys):
    from robot_ct_ros.bag import ScanBagWriter
    from robot_ct_ros.ct.trajectory import robotic_roi_scan

    geom = robotic_roi_scan(n_views=2, n_rows=4, n_cols=6, fov_diameter_mm=0.3)
    with ScanBagWriter(tmp_path / "noinfo", None) as w:
        w.write_frame(np.ones((4, 6), np.float32), geom, 10)
    assert main(["info", str(tmp_path / "noinfo")]) == 1
    out = capsys.readouterr().out
    assert "NOT A USABLE SCAN" in out and "no /ct/scan_info" in out and "/ct/projection" in out


def test_simulate_a_drifting_detector_and_calibrate_it_as_a_drift(tmp_path):
    """``simulate --drift-mm/--drift-deg`` adds a linear detector drift to the robots' errors;
    ``calibrate --drift-order`` returns a correction that is a polynomial in the frames' time."""
    from robot_ct_ros.bag import read_scan
    from robot_ct_ros.ct.calibration import fit_drift

    bag = tmp_path / "drift"
    assert main(["simulate", "--phantom", "mouse", "--views", "24", "--rows", "32", "--cols", "48", "--binning", "2",
                 "--sigma-mm", "0", "--sigma-deg", "0", "--drift-mm", "0.3", "--drift-deg", "0.1", "--quiet",
                 "--out", str(bag)]) == 0
    scan = read_scan(bag)
    true = scan.geom_true.params_relative_to(scan.geom)
    ramp = np.linspace(0.0, 1.0, 24)[:, None]
    np.testing.assert_allclose(true[:, :3], 0.0, atol=1e-9)  # the source stays
    np.testing.assert_allclose(true[:, 3:6], 0.3 * ramp * np.ones(3), atol=1e-6)
    np.testing.assert_allclose(true[:, 6:], np.deg2rad(0.1) * ramp * np.ones(3), atol=1e-8)
    assert scan.info["notes"]["detector_drift_mm"] == 0.3

    out = tmp_path / "calib"
    assert main(["calibrate", str(bag), "--method", "ncc-lle-exact", "--iterations", "1", "--drift-order", "1",
                 "--prior-sigma", "none", "--out", str(out)]) == 0
    corrected = read_scan(out / "drift_corrected")
    params = corrected.geom_corrected.params_relative_to(corrected.geom)
    t = (corrected.stamps_ns - corrected.stamps_ns[0]).astype(float)
    np.testing.assert_allclose(fit_drift(params, 1, t), params, atol=1e-5)  # polynomials, alternated with the gauge fix to 10 nm
    assert json.loads((out / "report.json").read_text())["drift_order"] == 1


@pytest.fixture(scope="module")
def small_bag(tmp_path_factory):
    bag = tmp_path_factory.mktemp("cli") / "scan"
    assert main(["simulate", "--phantom", "mouse", "--views", "12", "--rows", "16", "--cols", "24", "--quiet",
                 "--out", str(bag)]) == 0
    return bag


def _one_line_error(capsys, *words):
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert all(w in err for w in words), err
    return err


def test_bad_output_places_are_refused_in_one_line_before_any_work(tmp_path, capsys, small_bag, monkeypatch):
    afile = tmp_path / "afile"
    afile.write_text("x")
    for command in ("reconstruct", "calibrate", "report"):
        extra = ["--method", "none"] if command == "calibrate" else ["--methods", "none"] if command == "report" else []
        assert main([command, str(small_bag), "--out", str(afile), *extra]) == 2
        _one_line_error(capsys, "is a file, not a folder")
        assert main([command, str(small_bag), "--out", str(afile / "sub"), *extra]) == 2
        _one_line_error(capsys, "cannot create")
    assert afile.read_text() == "x"
    assert main(["simulate", "--views", "12", "--out", str(afile / "bag")]) == 2
    _one_line_error(capsys, "simulate")

    # a folder that cannot be written to (as root, chmod does not stop us: the check itself is exercised)
    import os
    import tempfile

    readonly = tmp_path / "readonly"
    readonly.mkdir()
    readonly.chmod(0o555)

    def refused(*args, **kwargs):
        raise PermissionError(13, "Permission denied")
    if os.access(readonly, os.W_OK):
        monkeypatch.setattr(tempfile, "TemporaryFile", refused)
    try:
        assert main(["reconstruct", str(small_bag), "--out", str(readonly)]) == 2
        _one_line_error(capsys, "cannot write into", "ermission denied")
        assert not (readonly / "volume.npy").exists()
    finally:
        readonly.chmod(0o755)


def test_a_grid_too_large_for_memory_is_refused_with_what_would_fit(tmp_path, capsys, small_bag, monkeypatch):
    from robot_ct_ros.jobs import output

    assert main(["reconstruct", str(small_bag), "--out", str(tmp_path / "r"), "--shape", "5000,5000,5000"]) == 2
    err = _one_line_error(capsys, "not enough memory", "5000 x 5000 x 5000", "would fit", "--shape")
    fit = [int(x) for x in err.split("--shape ")[1].split()[0].split(",")]
    assert "--voxel-mm" not in err  # with --shape given, a voxel size alone fits nothing (an outside check)
    assert main(["reconstruct", str(small_bag), "--out", str(tmp_path / "v"), "--voxel-mm", "0.00001"]) == 2
    _one_line_error(capsys, "not enough memory", "would fit", "--shape", "or the same field of view with --voxel-mm")
    monkeypatch.setattr(output, "available_memory_bytes", lambda: 64 * 2 ** 20)  # a small machine: 64 MiB
    for command, extra in (("reconstruct", []), ("calibrate", ["--method", "ncc-lle"]), ("report", [])):
        assert main([command, str(small_bag), "--out", str(tmp_path / command), "--shape", "400,400,400",
                     *extra]) == 2
        _one_line_error(capsys, "not enough memory", "64 MiB are available")
    assert fit[0] < 5000 and not (tmp_path / "r" / "volume.npy").exists()


def test_reports_name_their_files_independently_of_the_current_directory(tmp_path, capsys, small_bag, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["calibrate", str(small_bag), "--method", "none", "--out", "rel"]) == 0
    report = json.loads((tmp_path / "rel" / "report.json").read_text())
    for key, value in report["paths"].items():
        assert value.startswith("/") and (tmp_path / "rel").as_posix() in value or key == "input_bag", (key, value)
    assert report["bag"] == str(small_bag)
    assert main(["reconstruct", "../" + tmp_path.name + "/rel/scan_corrected", "--out", "rel2"]) == 0
    report = json.loads((tmp_path / "rel2" / "report.json").read_text())
    assert report["bag"] == str(tmp_path / "rel" / "scan_corrected") or report["bag"].startswith("/")
    assert all(f.startswith("/") for f in report["files"])


def test_a_scan_with_every_stamp_equal_is_not_reconstructed(tmp_path, capsys):
    """It used to give one view, "reconstructed" with exit status 0."""
    from robot_ct_ros.bag import ScanBagWriter, scan_info_for
    from robot_ct_ros.bag import format as fmt
    from robot_ct_ros.ct.trajectory import robotic_roi_scan

    geom = robotic_roi_scan(n_views=12, n_rows=8, n_cols=12, fov_diameter_mm=0.5)
    with ScanBagWriter(tmp_path / "zero", scan_info_for(geom)) as w:
        w.write_msg(fmt.TOPIC_FLAT_FIELD, fmt.image_from_array(np.full((8, 12), 1000.0, np.float32), 0), 1)
        for i in range(12):
            w.write_msg(fmt.TOPIC_PROJECTION, fmt.image_from_array(np.full((8, 12), 900.0, np.float32), 0), 10 + i)
            w.write_geometry(geom, 0, view=i)
    assert main(["reconstruct", str(tmp_path / "zero"), "--out", str(tmp_path / "o")]) == 2
    _one_line_error(capsys, "a scan needs at least", "stamp 0 ns")
    assert not (tmp_path / "o" / "volume.npy").exists()


def test_every_setting_is_an_option_and_switches_turn_both_ways():
    import argparse

    from robot_ct_ros.cli import add_settings_arguments, settings_from_args
    from robot_ct_ros.ct.calibration import CalibrationSettings
    from robot_ct_ros.parameters import specs

    p = argparse.ArgumentParser()
    add_settings_arguments(p, skip=())
    options = {a.dest for a in p._actions}
    missing = [s.name for s in specs(CalibrationSettings)
               if s.name not in options and s.name not in ("prior_translation_mm", "prior_rotation_deg")]
    assert not missing, missing
    assert settings_from_args(p.parse_args([])) == CalibrationSettings()
    s = settings_from_args(p.parse_args(["--no-guard", "--undo-inconsistent", "--exterior", "on", "--stop-px", "0.1",
                                         "--prior-sigma", "0.1,0.05"]))
    assert not s.guard and s.undo_inconsistent and s.exterior == "on" and s.stop_update_px == 0.1
    assert s.prior_translation_mm == 0.1 and s.prior_rotation_deg == 0.05
    assert settings_from_args(p.parse_args(["--prior-sigma", "none"])).prior_sigma is None


def test_off_is_taken_where_the_help_says_off(capsys):
    """calibrate --help shows [off] and "off: the schedule's" (or "off or 0") for the options left unset by
    default, but --iterations off was refused ("must be a whole number"): off is now what leaving them out is."""
    import argparse

    from robot_ct_ros.cli import add_settings_arguments, main, settings_from_args
    from robot_ct_ros.ct.calibration import CalibrationSettings
    from robot_ct_ros.parameters import specs

    p = argparse.ArgumentParser()
    add_settings_arguments(p, skip=())
    unset = [s for s in specs(CalibrationSettings) if s.default is None and s.kind is not bool]
    assert {"iterations", "prior_source_mm", "drift_order", "lle_neighbours", "stop_ncc_gain",
            "exterior_iterations", "fine_volume"} <= {s.name for s in unset}
    for s in unset:
        option = "--" + s.name.replace("_", "-")
        assert "off" in next(a.help for a in p._actions if a.dest == s.name), s.name
        assert settings_from_args(p.parse_args([option, "OFF"])) == CalibrationSettings(), option
    assert settings_from_args(p.parse_args(["--prior-source-mm", "0"])).prior_source_mm is None
    with pytest.raises(SystemExit) as exited:  # no off in its help: refused as before
        main(["calibrate", "bag", "--padding", "off", "--out", "o"])
    assert exited.value.code == 2
    assert "padding must be a number, got 'off'" in capsys.readouterr().err


def test_info_checks_a_fan_beam_scans_centre_of_rotation_by_opposed_rays(tmp_path, capsys):
    """`info` on a one-row full-circle scan says how far its stated centre of rotation is from the one
    its opposed rays agree on (the real HTC2022 sample: within 0.2 px); a shifted copy says so; a
    several-row scan gets no such line."""
    from robot_ct_ros.bag import read_scan, write_scan

    bags = Path(__file__).resolve().parents[1] / "bags"
    assert main(["info", "--json", str(bags / "htc2022_01a")]) == 0
    opposed = json.loads(capsys.readouterr().out)["opposed_rays"]
    found = opposed["best_shift_px"]
    assert abs(found) < 0.2
    assert sorted(opposed["by_ray_distance"]) == ["0.4", "0.8", "0.95"]
    assert opposed["by_ray_distance"]["0.8"] == found  # the default rays
    scan = read_scan(bags / "htc2022_01a")
    g = scan.geom
    shifted = g.replace(detector_mm=g.detector_mm - 0.5 * g.col_pitch_mm * g.u)  # stated half a pixel off
    write_scan(tmp_path / "shifted", scan.counts, shifted, info=scan.info)
    assert main(["info", str(tmp_path / "shifted")]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("centre"))
    assert "opposed rays agree best with every detector shifted +0." in line
    assert float(line.split("shifted ")[1].split(" px")[0]) == pytest.approx(found + 0.5, abs=0.05)
    assert main(["info", "--json", str(tmp_path / "shifted")]) == 0
    moved = json.loads(capsys.readouterr().out)["opposed_rays"]["by_ray_distance"]
    for fraction, shift_px in opposed["by_ray_distance"].items():  # a stated shift moves every ray alike
        assert moved[fraction] == pytest.approx(shift_px + 0.5, abs=0.05)
    assert main(["info", str(bags / "sim_mouse_80")]) == 0
    assert "opposed rays" not in capsys.readouterr().out


def test_info_checks_the_centre_of_rotation_by_opposed_rays_only_where_views_lie_close_enough(tmp_path, capsys):
    """Outside test F finding 7: at 60 views (6 degrees apart) `info` read a stated centre that was exact as
    +0.257 px off (the opposed ray is interpolated between views); it now says why it does not check there, and
    still checks at 180 views (2 degrees apart)."""
    from robot_ct_ros.bag import write_scan
    from robot_ct_ros.ct.geometry import VolumeGrid
    from robot_ct_ros.ct.projector import forward_project
    from robot_ct_ros.ct.simulation import Phantom, elliptic_cylinder, voxelize
    from robot_ct_ros.ct.trajectory import circular_scan

    phantom = Phantom("slab", (elliptic_cylinder((0, 0, 0), (6.0, 4.5), 30.0, 0.02),
                               elliptic_cylinder((2.0, 1.0, 0), (1.5, 2.0), 30.0, 0.05)))
    fine = VolumeGrid.centered((4, 100, 100), 0.15)
    volume = voxelize(phantom, fine)
    said = {}
    for n in (60, 180):
        g = circular_scan(n, 200.0, 400.0, 1, 64, 0.8, 0.8)
        bag = write_scan(tmp_path / f"v{n}", forward_project(volume, fine, g), g, projection_units="line_integral")
        assert main(["info", "--json", str(bag)]) == 0
        said[n] = json.loads(capsys.readouterr().out)["opposed_rays"]
    assert said[60]["not_checked"].startswith("its views lie 6 degrees apart, more than 2"), said[60]
    assert abs(said[180]["best_shift_px"]) < 0.05, said[180]


def test_the_venv_that_make_makes_runs_robot_ct_from_any_folder(tmp_path):
    """`make venv` (and so `make test` and `make demo`) writes .venv/bin/robot-ct and lets the venv's Python
    find this checkout, so the README's `robot-ct ...` lines work from a user's own data folder."""
    import os
    import subprocess
    import sys

    repo = Path(__file__).resolve().parents[1]
    venv = repo / ".venv"
    if Path(sys.prefix).resolve() != venv.resolve():
        pytest.skip("not running in the venv that make makes")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # make exports it; a user's shell does not
    for cmd in ([str(venv / "bin" / "robot-ct"), "simulate", "--help"],
                [str(venv / "bin" / "python"), "-m", "robot_ct_ros.cli", "info", "--help"]):
        done = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stderr
        assert "usage: robot-ct" in done.stdout


def test_simulate_takes_a_short_arc_and_info_says_so(tmp_path, capsys):
    """`simulate --arc-deg 200` spreads the views over 200 degrees; `info` names the arc (a full circle
    otherwise), and an arc outside (0, 360] is refused in one line."""
    bag = tmp_path / "short"
    assert main(["simulate", "--phantom", "mouse", "--views", "30", "--rows", "8", "--cols", "32", "--arc-deg", "200",
                 "--quiet", "--out", str(bag)]) == 0
    capsys.readouterr()
    assert main(["info", str(bag)]) == 0
    assert "30 paired frames, an arc of 200.0 deg (a short scan" in capsys.readouterr().out  # views 0 .. 200
    with pytest.raises(SystemExit):
        main(["simulate", "--arc-deg", "361", "--out", str(tmp_path / "x")])
    assert "arc-deg must be at most 360" in capsys.readouterr().err


def test_a_refused_command_leaves_no_empty_out_folder(tmp_path, capsys):
    """calibrate of a bag that does not exist created --out (to check it could be written) and left it empty."""
    out = tmp_path / "new" / "out"
    assert main(["calibrate", str(tmp_path / "nonexistent"), "--out", str(out)]) == 2
    assert not out.exists() and "nonexistent" in capsys.readouterr().err
    kept = tmp_path / "kept"
    kept.mkdir()
    assert main(["calibrate", str(tmp_path / "nonexistent"), "--out", str(kept)]) == 2
    assert kept.is_dir()  # a folder that was there before stays


def test_a_signal_while_the_parser_is_built_ends_with_one_line(monkeypatch, capsys):
    """Building the parser imports the settings (numba, seconds on a loaded machine); a Ctrl-C or SIGTERM then gave a
    traceback (and for Ctrl-C death by the signal) instead of one line and 130 or 143."""
    from robot_ct_ros import cli

    for exc, status, words in ((KeyboardInterrupt, 130, "robot-ct: interrupted"),
                               (cli.Terminated, 143, "robot-ct: terminated (SIGTERM)")):
        def build(exc=exc):
            raise exc()

        monkeypatch.setattr(cli, "build_parser", build)
        assert cli.main(["info", "x"]) == status
        err = capsys.readouterr().err
        assert err.strip() == words, err


def test_a_reader_that_goes_away_ends_the_command_silently():
    """`robot-ct info BAG | head -1` printed "cannot access: Broken pipe" and exit status 2 for a sound bag; it now
    ends as Unix tools do on a closed pipe (no message, status 141)."""
    import os
    import subprocess
    import sys

    repo = Path(__file__).resolve().parents[1]
    proc = subprocess.Popen([sys.executable, "-m", "robot_ct_ros.cli", "info", str(repo / "bags" / "sim_mouse_80")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=repo,
                            env=dict(os.environ, PYTHONPATH=str(repo)))
    proc.stdout.close()  # before it writes a line
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 141 and err == "", err


def test_simulate_help_names_the_default_phantom(capsys):
    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    assert "(default carotid)" in " ".join(capsys.readouterr().out.split())


def test_binnings_schedule_auto_would_refuse_are_refused_before_the_bag_is_read(tmp_path, capsys):
    """--fine-binning 4 under schedule auto was accepted, and the run failed once the bag was read and its truncation
    measured, on the ROI model only: it is refused at once now, before the bag is opened (none exists here)."""
    assert main(["calibrate", str(tmp_path / "no_bag"), "--fine-binning", "4", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "coarse_binning (2) must be at least fine_binning (4)" in err and "no_bag" not in err, err
    assert not (tmp_path / "o").exists()


def test_prior_sigma_takes_0_for_either_value_as_the_settings_and_ros_do(capsys):
    """--prior-sigma 0.3,0 was refused ("must be positive"), while the settings and ROS take 0 for either (no prior)."""
    import argparse

    from robot_ct_ros.cli import add_settings_arguments, settings_from_args

    p = argparse.ArgumentParser()
    add_settings_arguments(p)
    s = settings_from_args(p.parse_args(["--prior-sigma", "0.3,0"]))
    assert (s.prior_translation_mm, s.prior_rotation_deg) == (0.3, 0.0) and s.prior_sigma is None
    assert settings_from_args(p.parse_args(["--prior-sigma", "0,0.2"])).prior_sigma is None
    for value in ("-0.1,0.3", "0.3,inf"):
        with pytest.raises(SystemExit):
            p.parse_args([f"--prior-sigma={value}"])
        assert "prior sigmas must be >= 0 and finite" in capsys.readouterr().err



def test_report_reads_the_bag_once(tmp_path, small_bag, monkeypatch):
    """The command line read the whole bag for the report's memory check, then the job read it again."""
    from robot_ct_ros.bag import reader
    from robot_ct_ros.jobs import report

    reads, real = [], reader.read_scan

    def counted(*args, **kwargs):
        reads.append(args[0])
        return real(*args, **kwargs)

    monkeypatch.setattr(reader, "read_scan", counted)
    monkeypatch.setattr(report, "read_scan", counted)
    assert main(["report", str(small_bag), "--methods", "none", "--out", str(tmp_path / "r")]) == 0
    assert len(reads) == 1, reads


def test_a_stop_signal_that_a_c_extension_turned_into_its_own_error_ends_as_the_stop(monkeypatch, capsys):
    """From an outside check: a SIGTERM during `robot-ct demo` raised Terminated inside rclpy's take_message, which
    came out as "RuntimeError: Unable to convert call argument '0'": a traceback and exit status 1 instead of the
    documented one line and 143. The command now reports the stop it received."""
    import signal

    from robot_ct_ros import cli

    for signum, status, words in ((signal.SIGTERM, 143, "terminated (SIGTERM)"), (signal.SIGINT, 130, "interrupted")):
        def command(args, signum=signum):
            cli._stop_signal.append(signum)  # what the handler records before it raises
            raise RuntimeError("Unable to convert call argument '0' to Python object")

        monkeypatch.setitem(cli._main.__globals__, "_cmd_info", command)
        assert cli.main(["info", "x"]) == status
        err = capsys.readouterr().err
        assert err.strip() == f"robot-ct info: {words}", err
    # without a stop signal the same error is not taken for one
    monkeypatch.setitem(cli._main.__globals__, "_cmd_info", lambda args: (_ for _ in ()).throw(RuntimeError("x")))
    with pytest.raises(RuntimeError):
        cli.main(["info", "x"])


def test_the_command_records_the_stop_signals_it_handles():
    """Both handlers record the signal before raising, and main() restores the handlers it replaced."""
    import signal

    from robot_ct_ros import cli

    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    seen = {}

    def command(args):
        seen["int"], seen["term"] = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
        return 0

    import unittest.mock

    with unittest.mock.patch.dict(cli._main.__globals__, {"_cmd_info": command}):
        assert cli.main(["info", "x"]) == 0
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before
    if before[0] is signal.default_int_handler:
        assert seen["int"] is cli._raise_interrupted
    assert seen["term"] is cli._raise_terminated
    with pytest.raises(KeyboardInterrupt):
        cli._raise_interrupted(signal.SIGINT, None)
    assert cli._stop_signal[-1] == signal.SIGINT


def test_info_never_reads_100_percent_valid_with_an_invalid_pixel(tmp_path, capsys):
    """An outside tester's `info` printed `pixels 100.00 % valid` under `5 non-finite pixel values in 2 frames are
    marked invalid` (the share rounded to two decimals)."""
    from robot_ct_ros.bag import write_scan
    from robot_ct_ros.ct.trajectory import circular_scan

    g = circular_scan(60, 60.0, 150.0, 48, 64, 0.8, 0.8)
    li = np.zeros((60, 48, 64), np.float32)
    li[3, 10, 10:13] = np.nan
    li[7, 0, :2] = np.inf
    bag = write_scan(tmp_path / "nan5", li, g, projection_units="line_integral")
    assert main(["info", str(bag)]) == 0
    out = capsys.readouterr().out
    assert "5 non-finite pixel values in 2 frames are marked invalid" in out, out
    assert "pixels     99.997 % valid" in out, out
