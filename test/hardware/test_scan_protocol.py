"""Scan protocols without ROS: keys, checks, trajectory and scan info."""

import math

import numpy as np
import pytest
import yaml

from robot_ct_ros.hardware.scan_protocol import PROTOCOL_ERRORS, ScanProtocol

SMALL = {"name": "small", "n_views": 6, "roi_center_m": [0.4, 0.0, 0.3], "fov_diameter_m": 0.004,
         "detector": {"n_rows": 6, "n_cols": 8, "binning": 2, "raw_pixel_m": 0.0005},
         "exposure_s": 0.02, "settle_s": 0.01, "move_timeout_s": 5.0, "exposure_timeout_s": 1.0}


def test_keys_detector_mapping_and_vectors():
    p = ScanProtocol.from_dict({"scan_protocol": dict(SMALL, axis=1.0, roi_size_m=0.002)})
    assert (p.n_rows, p.n_cols, p.binning, p.raw_pixel_m) == (6, 8, 2, 0.0005)
    assert p.roi_center_m == (0.4, 0.0, 0.3) and p.axis == (1.0, 1.0, 1.0) and p.roi_size_m == (0.002,) * 3
    assert ScanProtocol.from_dict(SMALL) == ScanProtocol.from_dict({"scan_protocol": SMALL})
    with pytest.raises(ValueError, match="unknown scan protocol keys: colour"):
        ScanProtocol.from_dict(dict(SMALL, colour="red"))
    with pytest.raises(ValueError, match="unknown scan protocol keys: gain"):
        ScanProtocol.from_dict(dict(SMALL, detector=dict(SMALL["detector"], gain=2)))
    with pytest.raises(ValueError, match="mapping"):
        ScanProtocol.from_dict([1, 2])


@pytest.mark.parametrize("change, words", [({"n_views": 0}, "n_views"), ({"exposure_s": 0.0}, "exposure_s"),
                                           ({"settle_s": -1.0}, "settle_s"), ({"move_timeout_s": 0.0}, "move_timeout"),
                                           ({"magnification": 1.0}, "magnification"), ({"sdd_m": -0.3}, "sdd_m")])
def test_checks(change, words):
    with pytest.raises(ValueError, match=words):
        ScanProtocol.from_dict(dict(SMALL, **change))


def test_trajectory_follows_the_protocol():
    p = ScanProtocol.from_dict(dict(SMALL, start_deg=90.0, arc_deg=180.0))
    g = p.geometry()
    assert g.n_views == 6 and g.det_shape == (6, 8)
    # sources on a circle about the z axis through the ROI centre, SDD / magnification from it, over 180 deg
    rel = g.source_mm - np.array([400.0, 0.0, 300.0])
    np.testing.assert_allclose(np.linalg.norm(rel, axis=1), 342.4 / 2.67, rtol=1e-6)
    angles = np.unwrap(np.arctan2(rel[:, 1], rel[:, 0]))
    assert abs(abs(angles[-1] - angles[0]) - math.pi) < 1e-6  # a partial arc spans the whole arc_deg
    np.testing.assert_allclose(g.detector_mm[:, 2], 300.0, atol=1e-9)


def test_scan_info_records_the_protocol():
    p = ScanProtocol.from_dict(dict(SMALL, voxel_size_m=4e-5, roi_size_m=[0.002, 0.002, 0.001], kvp=80.0,
                                    notes={"operator": "test"}))
    info = p.scan_info(p.geometry(), "scan-1")
    assert info["n_views"] == 6 and info["n_rows"] == 6 and info["n_cols"] == 8
    notes = info["notes"]
    assert notes["scan_id"] == "scan-1" and notes["protocol"] == "small" and notes["kvp"] == 80.0
    assert notes["operator"] == "test" and notes["exposure_s"] == 0.02
    np.testing.assert_allclose(info["voxel_size_m"], [4e-5] * 3)
    np.testing.assert_allclose(info["roi_size_m"], [0.002, 0.002, 0.001])
    assert "voxel_size_m" not in ScanProtocol.from_dict(SMALL).scan_info(p.geometry(), "scan-2")


def test_scan_info_states_the_grid_orientation_about_the_protocol_axis():
    """A live reconstruction starts from the first views, whose short arc tells the axis poorly: the scan info
    states the grid's orientation, z along the protocol's axis, and the bag's default grid follows it."""
    from robot_ct_ros.bag.reader import ScanData

    for axis in ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (1.0, -2.0, 0.5)):
        p = ScanProtocol.from_dict(dict(SMALL, n_views=360, axis=list(axis)))
        info = p.scan_info(p.geometry(), "scan-1")
        d = np.asarray(info["roi_direction"]).reshape(3, 3)
        np.testing.assert_allclose(d.T @ d, np.eye(3), atol=1e-12)
        assert abs(d[:, 2] @ np.asarray(axis)) == pytest.approx(np.linalg.norm(axis))
        first = p.geometry().subset(np.arange(4))
        ones = np.ones((4, 6, 8), bool)
        scan = ScanData(None, ones.astype(np.float32), np.arange(4, dtype=np.int64), first, None, ones[0], ones, info)
        np.testing.assert_allclose(scan.default_grid().direction_matrix, d)


def test_yaml_files_and_bad_files(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump({"scan_protocol": SMALL}))
    assert ScanProtocol.from_yaml(path).name == "small"
    path.write_text("scan_protocol: {n_views: [unclosed")
    with pytest.raises(PROTOCOL_ERRORS):
        ScanProtocol.from_yaml(path)
    with pytest.raises(PROTOCOL_ERRORS):
        ScanProtocol.from_yaml(tmp_path / "missing.yaml")
