"""The reconstruction job (jobs/reconstruct.py): what it says is kept in report.json's notes."""

import json
from pathlib import Path

import pytest

from robot_ct_ros.bag import write_scan
from robot_ct_ros.ct.geometry import VolumeGrid
from robot_ct_ros.ct.projector import forward_project
from robot_ct_ros.ct.simulation import mouse_phantom, voxelize
from robot_ct_ros.ct.trajectory import circular_scan
from robot_ct_ros.jobs.reconstruct import reconstruct_bag


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    geom = circular_scan(96, 60.0, 150.0, 16, 40, 0.8, 0.8)  # enough views for the field of view's direction bins
    fine = VolumeGrid.centered((32, 48, 48), 0.3)
    li = forward_project(voxelize(mouse_phantom(body_width_mm=9.0, length_mm=10.0), fine), fine, geom)
    return write_scan(tmp_path_factory.mktemp("bags") / "scan", li, geom, projection_units="line_integral")


def _run(bag, out, **kwargs):
    said = []
    report = reconstruct_bag(bag, out, say=said.append, **kwargs)
    assert json.loads((Path(out) / "report.json").read_text())["notes"] == report["notes"]
    return report, said


def test_the_default_grid_gets_no_notes_and_the_line_names_every_file_written(bag, tmp_path):
    report, said = _run(bag, tmp_path / "r")
    assert report["notes"] == [] and 0.15 < report["outside_field_of_view_fraction"] < 0.3
    written = sorted(p.name for p in (tmp_path / "r").iterdir())
    assert written == ["report.json", "volume.npy", "volume.tif", "volume_grid.json"]
    assert all(name in said[-1] for name in written), said[-1]  # volume_grid.json was left out


def test_a_grid_mostly_outside_the_field_of_view_is_noted_in_the_report(bag, tmp_path):
    """The note was printed but report.json's notes were empty."""
    report, said = _run(bag, tmp_path / "r", shape_xyz=(120, 120, 4))
    assert report["outside_field_of_view_fraction"] > 0.3
    assert any("outside the field of view" in n for n in report["notes"]), report["notes"]
    assert any("outside the field of view" in line for line in said)


@pytest.mark.parametrize("voxel_mm, shape_xyz", [(41.2, None), (100.0, (4, 4, 4))])
def test_voxels_in_the_wrong_unit_are_noted_not_refused(bag, tmp_path, voxel_mm, shape_xyz):
    """--voxel-mm 41.2 meant as um made a 1x1x1 grid of 41 mm voxels, silently. Voxels far larger than the
    detector pixel at the isocentre (here 0.32 mm), or a few voxels across the field of view, are noted."""
    report, said = _run(bag, tmp_path / "r", voxel_mm=voxel_mm, shape_xyz=shape_xyz)
    notes = [n for n in report["notes"] if "wrong unit" in n]
    assert len(notes) == 1 and f"--voxel-mm {voxel_mm / 1000:g}" in notes[0], report["notes"]
    assert any(notes[0] in line for line in said)


@pytest.mark.parametrize("voxel_mm, shape_xyz", [(0.5, None), (None, (4, 4, 4)), (0.4, (4, 4, 4)), (2.0, None),
                                              (8.0, (4, 4, 4))])
def test_a_coarser_voxel_or_a_small_grid_asked_for_is_no_wrong_unit(bag, tmp_path, voxel_mm, shape_xyz):
    """A deliberately coarse voxel (2 mm: 6 pixels, a grid of 5 voxels; 8 mm: 25 pixels) reads as an implausible
    2 or 8 um (0.006 and 0.025 of the 0.32 mm pixel): no note. The first version noted them, and advised
    --voxel-mm 0.002."""
    report, _ = _run(bag, tmp_path / "r", voxel_mm=voxel_mm, shape_xyz=shape_xyz)
    assert not any("wrong unit" in n for n in report["notes"]), report["notes"]


def test_a_voxel_that_leaves_one_voxel_across_the_detector_is_noted_whatever_the_unit(bag, tmp_path):
    """20 mm voxels on a scan whose pixel at the isocentre is 0.32 mm read as 20 um, 1/16 of a pixel: no unit to
    suspect, and the 1 x 1 x 1 grid went without a word (an outside tester)."""
    report, said = _run(bag, tmp_path / "r", voxel_mm=20.0)
    notes = [n for n in report["notes"] if "one voxel across" in n]
    assert len(notes) == 1 and "1 x 1 x 1" in notes[0] and "wrong unit" not in notes[0], report["notes"]
    assert any(notes[0] in line for line in said)


def test_a_grid_taller_than_the_cone_is_noted_with_a_shape_that_fits(tmp_path):
    """robot-ct reconstruct of a 4-row bag on a 64-slice grid gave 4 non-zero slices, notes [] and an
    outside_field_of_view_fraction of 0 (it looked across the axis only); calibrate said nothing either."""
    import numpy as np

    from robot_ct_ros.jobs.calibrate import calibrate_bag

    geom = circular_scan(24, 60.0, 150.0, 4, 40, 0.8, 0.8)
    fine = VolumeGrid.centered((16, 48, 48), 0.3)
    li = forward_project(voxelize(mouse_phantom(body_width_mm=9.0, length_mm=10.0), fine), fine, geom)
    thin = write_scan(tmp_path / "thin4", li, geom, projection_units="line_integral")
    report, said = _run(thin, tmp_path / "r", shape_xyz=(32, 32, 32), voxel_mm=0.2)
    filled = np.flatnonzero(np.abs(np.load(tmp_path / "r" / "volume.npy")).max(axis=(1, 2)) > 0)
    cone = [n for n in report["notes"] if n.startswith("most of the grid lies beyond every view's cone")]
    assert len(cone) == 1, report["notes"]
    assert f"the rays reach {len(filled)} of its 32 slices along z" in cone[0], (cone, filled)
    assert f"slices {filled[0]}-{filled[-1]}" in cone[0] and cone[0].endswith(f"--shape 32,32,{len(filled)}")
    assert any(line == f"note: {cone[0]}" for line in said)
    assert report["beyond_cone"] == {"fraction": pytest.approx(1 - len(filled) / 32), "axis": "z",
                                     "slices_reached": len(filled), "slices": 32}
    assert report["outside_field_of_view_fraction"] >= report["beyond_cone"]["fraction"] > 0.5
    # the suggested grid fits: no note
    fits, _ = _run(thin, tmp_path / "f", shape_xyz=(32, 32, len(filled)), voxel_mm=0.2)
    assert not any("beyond every view's cone" in n for n in fits["notes"]) and "slices_reached" in fits["beyond_cone"]
    calibrated = calibrate_bag(thin, tmp_path / "c", settings=None, shape_xyz=(32, 32, 32), voxel_mm=0.2,
                               say=said.append).report
    assert calibrated["notes"][0] == cone[0]
    assert json.loads((tmp_path / "c" / "report.json").read_text())["notes"][0] == cone[0]


def test_a_grid_that_misses_the_field_of_view_reads_wholly_outside_and_calibrate_refuses_it(tmp_path):
    """An outside tester's ROI 40 mm off the axis (field of view 12.8 mm in radius) read outside_field_of_view_fraction
    0.0 with no note; calibrate of one 700 mm off said its FDK was zero in 0 % of the grid and advised
    exterior_half_width_mm. Now 100 % outside, a note locating the field of view, and a clear refusal."""
    import numpy as np

    from robot_ct_ros.ct.calibration.loop import calibrate

    geom = circular_scan(60, 200.0, 400.0, 4, 64, 0.8, 0.8)
    li = np.zeros((60, 4, 64), np.float32)
    off = write_scan(tmp_path / "off40", li, geom, projection_units="line_integral", roi_center_mm=(40.0, 0.0, 0.0),
                     roi_size_mm=(20.0, 20.0, 2.0), voxel_size_mm=1.0)
    report, said = _run(off, tmp_path / "r")
    assert report["outside_field_of_view_fraction"] == 1.0
    notes = [n for n in report["notes"] if n.startswith("the grid misses the field of view")]
    assert len(notes) == 1 and "40.0 mm from that axis" in notes[0], report["notes"]
    assert any(line == f"note: {notes[0]}" for line in said)
    grid = VolumeGrid.centered((2, 20, 20), 1.0, center_mm=(500.0, 500.0, 0.0))
    with pytest.raises(ValueError, match="the grid misses the field of view") as err:
        calibrate(li, geom, grid, iterations=1)
    assert "exterior_half_width" not in str(err.value)
