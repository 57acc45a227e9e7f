"""ScanBag.default_grid for a detector turned in its own plane (no ROI in the bag)."""

from __future__ import annotations

import numpy as np
import pytest

from robot_ct_ros.bag import read_scan, write_scan
from robot_ct_ros.ct.trajectory import circular_scan


@pytest.mark.parametrize("axis", [(0.0, 0.0, 1.0), (0.0, 1.0, 0.0)])
def test_default_grid_of_a_portrait_detector_is_the_landscape_one(tmp_path, axis):
    """Columns along the scan axis (a valid right-handed frame, the same rays): the default grid is
    the landscape detector's, not one with its transaxial and axial sizes swapped."""
    g = circular_scan(8, 100.0, 200.0, 16, 40, 0.5, 0.5, axis=axis)
    gp = g.replace(u=g.v, v=-g.u, n_rows=g.n_cols, n_cols=g.n_rows)
    frames = np.full((8, 16, 40), 500.0, np.float32)
    grids = []
    for name, geom, f in (("land", g, frames), ("port", gp, np.ascontiguousarray(frames.transpose(0, 2, 1)))):
        bag = write_scan(tmp_path / name, f, geom, flat=np.full(f.shape[1:], 1000.0, np.float32))
        grids.append(read_scan(bag).default_grid())
    land, port = grids
    assert port.shape_zyx == land.shape_zyx
    assert port.shape_zyx[0] < port.shape_zyx[1]  # 16 rows along the axis, 40 columns across it
    np.testing.assert_allclose(port.voxel_size_mm, land.voxel_size_mm)
    np.testing.assert_allclose(port.center_mm, land.center_mm, atol=1e-9)


def test_positions_in_mm_on_the_wire_are_refused_naming_the_topic(tmp_path, capsys):
    """Positions written in mm on a wire in metres: info said "SDD 500000.0 mm" without a word, and
    reconstruct ended in a memory refusal suggesting a 0.73 mm voxel. The reader refuses a source-to-detector
    distance above 10 m and says the positions look like mm."""
    from robot_ct_ros.bag.format import ScanBagError
    from robot_ct_ros.cli import main

    g = circular_scan(8, 300.0, 500.0, 8, 12, 0.5, 0.5)
    frames = np.full((8, 8, 12), 500.0, np.float32)
    flat = np.full((8, 12), 1000.0, np.float32)
    read_scan(write_scan(tmp_path / "ok", frames, g, flat=flat))  # 0.5 m: fine
    big = g.replace(source_mm=g.source_mm * 1000.0, detector_mm=g.detector_mm * 1000.0)  # mm on the wire
    bag = write_scan(tmp_path / "mm", frames, big, flat=flat)
    with pytest.raises(ScanBagError, match=r"/ct/geometry: source-to-detector distance 500 m .* above 10 m: the "
                                           r"positions look like mm"):
        read_scan(bag)
    for cmd in (["info", str(bag)], ["reconstruct", str(bag), "--out", str(tmp_path / "rec")]):
        assert main(cmd) != 0
        said = capsys.readouterr()
        said = said.out + said.err
        assert "/ct/geometry" in said and "500 m" in said and "look like mm" in said, said
        assert "Traceback" not in said and "memory" not in said, said
    # a corrected geometry in mm is dropped with the reason, the scan kept
    bag2 = write_scan(tmp_path / "corr_mm", frames, g, flat=flat, geom_corrected=big)
    scan = read_scan(bag2)
    assert scan.geom_corrected is None
    assert any("/ct/geometry_corrected ignored" in w and "look like mm" in w for w in scan.warnings), scan.warnings
