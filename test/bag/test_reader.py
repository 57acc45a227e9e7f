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
