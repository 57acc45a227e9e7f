"""The correction job on bags in any world frame: a scan about +y (RTK's convention) is a scan."""

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from robot_ct_ros.bag import read_scan, write_scan
from robot_ct_ros.ct.calibration import CalibrationSettings
from robot_ct_ros.ct.geometry import VolumeGrid
from robot_ct_ros.ct.metrics import reprojection_error, roi_points
from robot_ct_ros.ct.projector import forward_project
from robot_ct_ros.ct.simulation import mouse_phantom, robot_coordination, voxelize
from robot_ct_ros.ct.trajectory import circular_scan
from robot_ct_ros.jobs.calibrate import calibrate_bag, correct_scan


def _bag(path, rotation):
    n = 24
    nominal = circular_scan(n, 60.0, 150.0, 40, 40, 0.8, 0.8)
    true = nominal.perturbed(robot_coordination(0.3, 0.3, seed=4).sample(n))
    fine = VolumeGrid.centered((64, 64, 64), 0.2)
    li = forward_project(voxelize(mouse_phantom(body_width_mm=9.0, length_mm=10.0), fine), fine, true)
    return write_scan(path, li, nominal.moved(rotation), geom_true=true.moved(rotation),
                      projection_units="line_integral", roi_center_mm=[0.0, 0.0, 0.0], roi_size_mm=[12.0, 12.0, 10.0])


def test_a_scan_about_y_calibrates_as_the_same_scan_about_z(tmp_path):
    to_y = Rotation.from_rotvec([-np.pi / 2, 0.0, 0.0]).as_matrix()  # world z -> +y
    about_z, about_y = read_scan(_bag(tmp_path / "z", np.eye(3))), read_scan(_bag(tmp_path / "y", to_y))
    grid_y = about_y.default_grid()
    np.testing.assert_allclose(grid_y.direction_matrix[:, 2], [0.0, 1.0, 0.0], atol=1e-9)  # z along the scan axis
    assert about_z.default_grid().axis_aligned and grid_y.shape_zyx == about_z.default_grid().shape_zyx
    settings = CalibrationSettings(iterations=1)
    z = correct_scan(about_z, settings, say=lambda s: None)
    said = []
    y = correct_scan(about_y, settings, say=said.append)
    pts = roi_points(grid_y)
    before = reprojection_error(about_y.geom, about_y.geom_true, pts)["mean_px"]
    after = reprojection_error(y.geom, about_y.geom_true, pts)["mean_px"]
    assert after < 0.6 * before, (before, after)
    # report.json's figures against /ct/geometry_true are these, gauge removed (the raw RMS counts the gauge)
    report = y.report
    assert report["geometry_error_nominal"]["reprojection_error_px"]["mean"] == pytest.approx(before, rel=1e-9)
    assert report["geometry_error_corrected"]["reprojection_error_px"]["mean"] == pytest.approx(after, rel=1e-9)
    # and said: a user of a simulated bag saw no figure to judge the correction by unless they opened report.json
    assert f"nominal {before:.3f} px mean" in " ".join(said) and f"corrected {after:.3f} px" in " ".join(said)
    np.testing.assert_allclose(y.result.params, z.result.params, atol=1e-3)
    np.testing.assert_allclose(y.volume, z.volume, atol=1e-3 * np.abs(z.volume).max())


def test_the_job_writes_the_oriented_grid_and_a_corrected_bag(tmp_path):
    to_y = Rotation.from_rotvec([-np.pi / 2, 0.0, 0.0]).as_matrix()
    bag = _bag(tmp_path / "y", to_y)
    correction = calibrate_bag(bag, tmp_path / "out", CalibrationSettings(method="none"), say=lambda s: None)
    grid = VolumeGrid.from_dict(correction.report["grid"])
    np.testing.assert_allclose(grid.direction_matrix, correction.grid.direction_matrix)
    assert read_scan(correction.report["corrected_bag"]).geom_corrected.allclose(read_scan(bag).geom, atol=1e-6)


def test_a_grid_too_large_for_memory_is_refused_before_the_work_in_the_starter_s_words(tmp_path, monkeypatch):
    """recon_service and replay call calibrate_bag too: before, only the command line checked the memory, and
    a node given too large a grid was ended by the system instead."""
    from robot_ct_ros.jobs import output

    bag = _bag(tmp_path / "z", np.eye(3))
    monkeypatch.setattr(output, "available_memory_bytes", lambda: 64 * 2 ** 20)
    for options, hints in (("ROS parameters", ("roi_shape:=[", "voxel_size_m:=")),  # recon_service and replay
                           ("command line", ("--shape ", "--voxel-mm "))):
        with pytest.raises(ValueError, match="not enough memory") as err:
            calibrate_bag(bag, tmp_path / "out", CalibrationSettings(iterations=1), voxel_mm=0.001,
                          options=options, say=lambda s: None)
        assert all(h in str(err.value) for h in hints), str(err.value)
    assert not (tmp_path / "out" / "report.json").exists()


def test_a_one_row_bag_reconstructs_and_calibrates(tmp_path):
    """A fan-beam scan bag (one detector row) through the command line: reconstruct gives the slice
    the row sees on a grid one voxel thick, and calibrate corrects the in-plane errors (the detector
    shift along the row, about a pixel, and the source in the plane) while the other parameters stay
    nominal."""
    from robot_ct_ros.cli import main
    from robot_ct_ros.ct.geometry import FAN_BEAM_PARAMS, PARAM_NAMES
    from robot_ct_ros.ct.simulation import Phantom, elliptic_cylinder

    n = 48
    nominal = circular_scan(n, 60.0, 150.0, 1, 64, 0.4, 0.4)
    rng = np.random.default_rng(1)
    errors = np.zeros((n, 9))
    errors[:, 3] = rng.normal(0.0, 0.4, n)
    errors[:, [0, 2]] = rng.normal(0.0, 0.3, (n, 2))
    true = nominal.perturbed(errors)
    phantom = Phantom("slab", (elliptic_cylinder((0, 0, 0), (4.5, 3.8), 30.0, 0.02),
                               elliptic_cylinder((1.5, 0.8, 0), (1.0, 1.4), 30.0, 0.05),
                               elliptic_cylinder((-1.8, -0.6, 0), (0.8, 0.8), 30.0, 0.035)))
    fine = VolumeGrid.centered((4, 100, 100), 0.1)
    li = forward_project(voxelize(phantom, fine), fine, true)
    bag = write_scan(tmp_path / "fan", li, nominal, geom_true=true, projection_units="line_integral")
    assert main(["reconstruct", str(bag), "--out", str(tmp_path / "recon")]) == 0
    volume = np.load(tmp_path / "recon" / "volume.npy")
    assert volume.shape[0] == 1 and np.isfinite(volume).all() and volume.max() > 0.03
    # a grid far wider than the fan: the report says how much of it no complete data reach
    assert main(["reconstruct", str(bag), "--shape", "300,300,1", "--out", str(tmp_path / "wide")]) == 0
    wide = json.loads((tmp_path / "recon" / "report.json").read_text())["outside_field_of_view_fraction"]
    assert wide < 0.3 < json.loads((tmp_path / "wide" / "report.json").read_text())["outside_field_of_view_fraction"]
    # a grid whose slices all miss the fan plane: FDK's warning reaches the report and the user (the command line
    # ignores RuntimeWarnings, and the report said nothing about a volume of zeros)
    assert main(["reconstruct", str(bag), "--shape", "32,32,2", "--voxel-mm", "0.3", "--out",
                 str(tmp_path / "even")]) == 0
    assert not np.load(tmp_path / "even" / "volume.npy").any()
    notes = json.loads((tmp_path / "even" / "report.json").read_text())["notes"]
    assert any("put nothing into the grid" in n for n in notes), notes
    correction = calibrate_bag(bag, tmp_path / "calib", CalibrationSettings(iterations=2), evaluate_truth=True,
                               say=lambda s: None)
    truth = correction.report["truth"]
    before, after = truth["reprojection_error_nominal_px"]["mean"], truth["reprojection_error_corrected_px"]["mean"]
    assert before > 0.8 and after < 0.4 * before, (before, after)
    # the report gives the part of the error along the row, which is what a fan beam corrects; here every error
    # lies in the fan plane, so it is most of the distance
    along = [correction.report[k]["reprojection_error_px"]["mean_along_row"]
             for k in ("geometry_error_nominal", "geometry_error_corrected")]
    assert 0.8 * before < along[0] <= before and along[1] < 0.4 * along[0], (before, along)
    # report.json says that the scan was calibrated as a fan beam (it had no word of it)
    notes = json.loads((tmp_path / "calib" / "report.json").read_text())["notes"]
    assert any(n.startswith("one-row detector (fan beam): only the 5 parameters") for n in notes), notes
    held = [PARAM_NAMES.index(p) for p in PARAM_NAMES if p not in FAN_BEAM_PARAMS]
    assert np.abs(correction.result.params[:, held]).max() < 1e-9
    assert read_scan(correction.report["corrected_bag"]).geom_corrected.det_shape == (1, 64)


def test_an_interrupted_rerun_leaves_no_report_that_vouches_for_a_mix(tmp_path, monkeypatch, capsys):
    """A second run into the same folder, stopped while it wrote its volume, left the first run's report.json
    beside the second run's volume (a folder that looked complete); Ctrl-C printed a traceback."""
    from robot_ct_ros.cli import main
    from robot_ct_ros.jobs import calibrate as job

    bag = _bag(tmp_path / "z", np.eye(3))
    out = tmp_path / "out"
    assert main(["calibrate", str(bag), "--method", "none", "--shape", "16,16,16", "--out", str(out)]) == 0
    assert (out / "report.json").is_file()

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(job, "write_volume", interrupted)
    assert main(["calibrate", str(bag), "--method", "none", "--shape", "24,24,24", "--out", str(out)]) == 130
    assert not (out / "report.json").exists() and not (out / "report.md").exists()
    err = capsys.readouterr().err
    assert "interrupted" in err and "Traceback" not in err
    assert not list(out.glob("*.tmp"))


def test_a_folder_holds_one_bags_calibration_and_export_takes_only_its_own(tmp_path, capsys):
    """Two simulated bags of one protocol (same stamps) calibrated into one folder left both corrected bags and the
    second's report.json; export of the first bag with that folder took the second's correction."""
    from robot_ct_ros.cli import main

    a = write_scan(tmp_path / "a", np.ones((4, 6, 8), np.float32), circular_scan(4, 60.0, 150.0, 6, 8, 1.0, 1.0),
                   projection_units="line_integral")
    b = write_scan(tmp_path / "b", np.full((4, 6, 8), 2.0, np.float32), circular_scan(4, 60.0, 150.0, 6, 8, 1.0, 1.0),
                   projection_units="line_integral")
    out = tmp_path / "out"
    assert main(["calibrate", str(a), "--method", "none", "--shape", "8,8,8", "--out", str(out)]) == 0
    assert main(["calibrate", str(a), "--method", "none", "--shape", "8,8,8", "--out", str(out)]) == 0  # a rerun
    capsys.readouterr()
    assert main(["calibrate", str(b), "--method", "none", "--shape", "8,8,8", "--out", str(out)]) == 2
    assert "holds the calibration of another bag (a)" in capsys.readouterr().err
    assert main(["calibrate", str(b), "--method", "none", "--shape", "8,8,8", "--out", str(tmp_path / "out_b")]) == 0
    capsys.readouterr()
    assert main(["export", str(a), "--corrected", str(tmp_path / "out_b"), "--format", "astra", "--out",
                 str(tmp_path / "v.txt")]) == 2
    assert "correction of another scan" in capsys.readouterr().err
    assert main(["export", str(a), "--corrected", str(out), "--format", "astra", "--out", str(tmp_path / "v.txt")]) == 0


def test_a_folder_holds_one_jobs_results_and_none_goes_into_the_bag(tmp_path, capsys):
    """report into a calibration's folder replaced its report.json (the corrected bag and volume stayed, described by
    nothing), and calibrate --out inside the input bag wrote into the scan's folder. Both are refused before any work,
    in one line; the same job into its own folder still runs."""
    from robot_ct_ros.cli import main

    n = 8
    geom = circular_scan(n, 60.0, 150.0, 8, 12, 1.0, 1.0)
    bag = write_scan(tmp_path / "scan", np.random.default_rng(0).poisson(500.0, (n, 8, 12)).astype(np.float32), geom,
                     flat=np.full((8, 12), 900.0, np.float32))
    calib = tmp_path / "calib"
    assert main(["calibrate", str(bag), "--method", "none", "--out", str(calib)]) == 0
    assert main(["calibrate", str(bag), "--method", "none", "--out", str(calib)]) == 0  # its own job again
    report = calib / "report.json"
    before = report.read_text()
    capsys.readouterr()
    assert main(["report", str(bag), "--methods", "none", "--out", str(calib)]) == 2
    assert "holds the results of robot-ct calibrate" in capsys.readouterr().err
    assert report.read_text() == before
    assert main(["reconstruct", str(bag), "--out", str(calib)]) == 2
    assert main(["report", str(bag), "--methods", "none", "--out", str(tmp_path / "rep")]) == 0
    assert main(["calibrate", str(bag), "--method", "none", "--out", str(tmp_path / "rep")]) == 2
    files = sorted(p.name for p in bag.iterdir())
    for out in (bag / "inside", bag):
        capsys.readouterr()
        assert main(["calibrate", str(bag), "--method", "none", "--out", str(out)]) == 2
        assert "lies in the input bag" in capsys.readouterr().err
    assert sorted(p.name for p in bag.iterdir()) == files  # nothing written into the bag, no folder left there


def test_voxels_in_the_wrong_unit_are_noted_in_the_calibration_report(tmp_path):
    """--voxel-mm 41.2 meant as um: a 1x1x1 grid, silently; now said and kept in the report's notes."""
    said = []
    report = calibrate_bag(_bag(tmp_path / "scan", np.eye(3)), tmp_path / "cal", CalibrationSettings(method="none"),
                           voxel_mm=41.2, say=said.append).report
    assert "wrong unit" in report["notes"][0] and any(report["notes"][0] in line for line in said)
    assert json.loads((tmp_path / "cal" / "report.json").read_text())["notes"] == report["notes"]
    assert "volume_grid.json" in said[-1]  # the 'wrote' line names every file written (it left this one out)


def test_report_md_explains_a_low_independent_pixel_fraction_only():
    """report.md said '0.981 (near 0: the data explain little ... leans on the prior ...)': the remark came with
    every value. It now comes with a low one only."""
    from robot_ct_ros.jobs.calibrate import markdown_report

    prior = [0.1] * 6 + [np.deg2rad(0.1)] * 3
    for fraction, remark in ((0.981, False), (0.12, True)):
        text = markdown_report({"history": [{"projection_ncc": 0.9, "independent_fraction": fraction}],
                                "prior_sigma": prior})
        assert f"independent pixels {fraction:.3f}" in text
        assert ("leans on the prior" in text) == remark, text


def test_the_truth_of_an_uncorrected_scan_reuses_its_volume_as_the_nominal_one(tmp_path, monkeypatch):
    """truth_metrics reused the volume of method none as the nominal reconstruction only when given the scan's own
    geometry object, which correct_scan never passed (it passes the geometry as transmitted): method none paid for
    a third FDK, of the geometry it had just reconstructed with."""
    from robot_ct_ros.ct import reconstruction

    scan = read_scan(_bag(tmp_path / "scan", np.eye(3)))
    real, grids = reconstruction.fdk, []

    def counted(li, geom, grid, **kwargs):
        grids.append(grid.shape_zyx)
        return real(li, geom, grid, **kwargs)

    monkeypatch.setattr(reconstruction, "fdk", counted)
    truth = correct_scan(scan, CalibrationSettings(method="none"), evaluate_truth=True, say=lambda s: None).report
    assert len(grids) == 2, grids  # the nominal volume and the true geometry's, once each
    assert truth["truth"]["ssim_nominal"] == truth["truth"]["ssim_corrected"]
