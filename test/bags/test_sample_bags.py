"""The sample bags shipped in bags/ (README, "Sample bags") read as the scans they claim to be."""

from pathlib import Path

import numpy as np
import pytest

from robot_ct_ros.bag.reader import read_scan

BAGS = Path(__file__).resolve().parents[2] / "bags"


def test_the_htc2022_bag_is_a_one_row_fan_beam_scan_of_line_integrals():
    scan = read_scan(BAGS / "htc2022_01a")
    assert scan.geom.n_views == len(scan.stamps_ns) == 720
    assert scan.geom.det_shape == (1, 560)
    assert scan.info["projection_units"] == "line_integral"
    np.testing.assert_allclose(scan.geom.col_pitch_mm, 0.2)
    assert np.isfinite(scan.counts).all() and scan.counts.max() > 1.0  # line integrals of a 70 mm disc


def test_the_simulated_bag_holds_its_true_geometry_and_errors_of_the_stated_size():
    scan = read_scan(BAGS / "sim_mouse_80")
    assert scan.geom.n_views == 80 and scan.geom.det_shape == (64, 128)
    assert scan.geom_true is not None
    errors = scan.geom_true.params_relative_to(scan.geom)
    # robot errors of 0.1 mm / 0.1 deg per view (make_bags.py): the sample's spread, within sampling scatter
    assert 0.05 < np.std(errors[:, :6]) < 0.2
    assert 0.05 < np.rad2deg(np.std(errors[:, 6:])) < 0.2


@pytest.mark.parametrize("name", ["htc2022_01a", "sim_mouse_80"])
def test_each_sample_bag_stays_small(name):
    assert sum(f.stat().st_size for f in (BAGS / name).iterdir()) <= 3_000_000
