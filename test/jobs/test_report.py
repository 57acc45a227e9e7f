"""The comparison job (robot-ct report): what it refuses before the work, and what its report.json records."""

import json

import numpy as np
import pytest

from robot_ct_ros.bag import write_scan
from robot_ct_ros.ct.calibration import CalibrationSettings
from robot_ct_ros.ct.geometry import VolumeGrid
from robot_ct_ros.ct.projector import forward_project
from robot_ct_ros.ct.simulation import mouse_phantom, robot_coordination, voxelize
from robot_ct_ros.ct.trajectory import circular_scan
from robot_ct_ros.jobs.report import report_bag


def _bag(path, with_truth: bool):
    """A small simulated scan (12 views, 24 x 24 pixels of 1.3 mm, 0.52 mm at the isocentre), its true geometry
    recorded or not."""
    n = 12
    nominal = circular_scan(n, 60.0, 150.0, 24, 24, 1.3, 1.3)
    true = nominal.perturbed(robot_coordination(0.3, 0.3, seed=4).sample(n))
    fine = VolumeGrid.centered((32, 32, 32), 0.4)
    li = forward_project(voxelize(mouse_phantom(body_width_mm=9.0, length_mm=10.0), fine), fine, true)
    return write_scan(path, li, nominal, geom_true=true if with_truth else None, projection_units="line_integral",
                      roi_center_mm=[0.0, 0.0, 0.0], roi_size_mm=[12.0, 12.0, 10.0])


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    return _bag(tmp_path_factory.mktemp("report") / "scan", True)


def test_a_grid_too_large_for_memory_is_refused_by_the_job_itself(tmp_path, bag, monkeypatch):
    """Only the command line checked the report's memory (reading the bag once more for it): report_bag called from
    Python allocated what did not fit."""
    from robot_ct_ros.jobs import output

    monkeypatch.setattr(output, "available_memory_bytes", lambda: 64 * 2 ** 20)  # a small machine: 64 MiB
    with pytest.raises(ValueError, match="not enough memory.*64 MiB are available"):
        report_bag(bag, tmp_path / "r", ("none",), shape_xyz=(400, 400, 400), say=lambda s: None)
    assert not (tmp_path / "r" / "report.json").exists()


def test_the_report_records_each_methods_resolved_settings_as_a_calibration_does(tmp_path, bag):
    """report.json recorded the settings as given (iterations None, schedule auto) and a prior for every method,
    where a calibration's records what ran: the schedule's iterations, the schedule chosen, no prior for a method
    without one."""
    settings = CalibrationSettings(prior_translation_mm=0.2, stop_update_px=1e3)
    notes = json.loads(report_bag(bag, tmp_path / "r", ("none", "ncc-lle"), settings,
                                  say=lambda s: None)["json"].read_text())["notes"]
    assert notes["settings"]["iterations"] is None and notes["settings"]["schedule"] == "auto"  # as given
    assert notes["iterations"] == {"none": 2, "ncc-lle": 2} and notes["ensemble"] == {"none": 1, "ncc-lle": 1}
    assert notes["schedule"] == {"none": "accurate", "ncc-lle": "accurate"}
    assert notes["prior_sigma"]["none"] is None  # no estimate, no prior
    np.testing.assert_allclose(notes["prior_sigma"]["ncc-lle"], settings.prior_sigma)


def test_the_report_notes_voxels_in_the_wrong_unit_and_what_fdk_approximates(tmp_path, monkeypatch):
    """The other jobs say and keep a voxel size that looks like the wrong unit and FDK's warnings; the report did
    neither."""
    import warnings

    from robot_ct_ros.ct import reconstruction
    from robot_ct_ros.ct.scan_weights import FDKWarning

    real = reconstruction.fdk

    def warned(*args, **kwargs):
        warnings.warn("short scan weights approximate 1.5 views", FDKWarning)
        return real(*args, **kwargs)

    monkeypatch.setattr(reconstruction, "fdk", warned)
    said = []
    measured = _bag(tmp_path / "scan", False)  # (no true geometry: no SSIM against a one-voxel reference)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)  # matplotlib's on a one-voxel grid's slices (identical limits)
        paths = report_bag(measured, tmp_path / "r", ("none",), voxel_mm=60.0, say=said.append)  # 60 um meant
    notes = json.loads(paths["json"].read_text())["notes"]["notes"]
    assert "wrong unit" in notes[0] and "--voxel-mm" in notes[0] and any(notes[0] in line for line in said)
    assert notes[1:] == ["FDK: short scan weights approximate 1.5 views"], notes
    assert any("warning: short scan weights" in line for line in said)
