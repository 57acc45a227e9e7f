"""Scan bags written by the project read back identically, with rosbags and mcap-ros2-support too."""

from __future__ import annotations

import numpy as np
import pytest

from robot_ct_ros.bag import ScanBagWriter, read_raw_messages, read_scan, scan_info_for, summarize, write_scan
from robot_ct_ros.bag import format as fmt
from robot_ct_ros.bag.writer import default_stamps, write_corrected_bag


def test_write_scan_round_trip(tmp_path, tiny_scan, check_bag):
    geom, frames, flat, dead = tiny_scan
    stamps = default_stamps(12)
    bag = write_scan(tmp_path / "scan", frames, geom, flat=flat, dead_pixels=dead, stamps_ns=stamps, binning=2,
                     roi_center_mm=(0, 0, 0), voxel_size_mm=0.05)
    counts = check_bag(bag)
    assert counts == {"/ct/scan_info": 1, "/ct/flat_field": 1, "/ct/dead_pixels": 1, "/ct/projection": 12,
                      "/ct/geometry": 12}
    scan = read_scan(bag)
    assert scan.warnings == [] and not scan.recovered
    assert scan.n_views == 12 and scan.counts.dtype == np.float32
    np.testing.assert_array_equal(scan.counts, frames)
    np.testing.assert_array_equal(scan.stamps_ns, stamps)
    assert scan.geom.allclose(geom, atol=1e-9)
    np.testing.assert_array_equal(scan.flat, flat)
    assert scan.pixel_mask.sum() == 8 * 12 - 1 and not scan.pixel_mask[2, 3]
    assert scan.valid_mask.shape == (12, 8, 12) and not scan.valid_mask[:, 2, 3].any()
    assert scan.info["binning"] == 2 and scan.geom_corrected is None
    li, mask = scan.to_line_integrals()
    np.testing.assert_allclose(li[mask], np.log(1000.0 / frames[mask]), rtol=1e-5)
    grid = scan.default_grid()
    assert grid.voxel_size_mm == pytest.approx((0.05,) * 3)
    s = summarize(bag)
    assert s["paired_views"] == 12 and s["reader"] == "rosbags"


def test_incremental_writer_frame_order_and_extra_topics(tmp_path, tiny_scan, check_bag):
    geom, frames, flat, _ = tiny_scan
    stamps = default_stamps(12)
    order = np.random.default_rng(3).permutation(12)  # frames arrive in any order: stamps decide
    with ScanBagWriter(tmp_path / "b", scan_info_for(geom, projection_units="counts")) as w:
        for i in order:
            w.write_frame(frames[i], geom, int(stamps[i]), int(i), corrected=geom.perturbed([0.1] * 6 + [0] * 3))
        w.write_flat(flat, int(stamps[-1]) + 1)  # anywhere in the bag
        T = fmt.typestore().types
        pose = T[fmt.POSE_STAMPED](header=fmt.header(5, "world"), pose=T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=0.1, y=0.0, z=0.0),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)))
        w.write_msg(fmt.TOPIC_SOURCE_POSE, pose, int(stamps[0]))
        with pytest.raises(ValueError, match="shape"):
            w.write_frame(frames[0][:4], geom, 1)
    assert w.closed
    check_bag(tmp_path / "b")
    scan = read_scan(tmp_path / "b")
    np.testing.assert_array_equal(scan.counts, frames)
    assert scan.geom_corrected.allclose(geom.perturbed([0.1] * 6 + [0] * 3), atol=1e-9)
    assert read_raw_messages(tmp_path / "b").topics()[fmt.TOPIC_SOURCE_POSE] == (fmt.POSE_STAMPED, 1)


def test_corrected_bag_copies_everything_and_adds_geometry(tmp_path, tiny_scan, check_bag):
    geom, frames, flat, dead = tiny_scan
    src = write_scan(tmp_path / "s", frames, geom, flat=flat, dead_pixels=dead)
    scan = read_scan(src)
    corrected = geom.perturbed([0.0, 0.2, 0.0] + [0.0] * 6)
    dst = write_corrected_bag(src, tmp_path / "c", corrected, scan.stamps_ns)
    counts = check_bag(dst)
    assert counts[fmt.TOPIC_GEOMETRY_CORRECTED] == 12 and counts[fmt.TOPIC_PROJECTION] == 12
    again = read_scan(dst)
    assert again.geom.allclose(geom, 1e-9) and again.geom_corrected.allclose(corrected, 1e-9)
    np.testing.assert_array_equal(again.counts, frames)


def test_line_integral_bag_needs_no_flat(tmp_path, tiny_scan):
    geom, frames, _, _ = tiny_scan
    li = np.log(1000.0 / frames).astype(np.float32)
    bag = write_scan(tmp_path / "li", li, geom, projection_units="line_integral")
    scan = read_scan(bag)
    assert scan.flat is None and scan.units == "line_integral"
    out, mask = scan.to_line_integrals()
    np.testing.assert_array_equal(out, li)
    assert mask.all()


def test_rejected_frames_are_never_projections(tmp_path, tiny_scan, check_bag):
    """A stamp on /ct/projection_rejected (docs/bag-format.md) is not a view, even if a writer
    also put that frame and a geometry for it on /ct/projection and /ct/geometry."""
    geom, frames, flat, _ = tiny_scan
    stamps = default_stamps(12)
    with ScanBagWriter(tmp_path / "b", scan_info_for(geom, projection_units="counts")) as w:
        w.write_flat(flat, int(stamps[0]) - 1)
        for i in range(12):
            if i != 7:  # 7: rejected only; 4: rejected and (wrongly) also recorded as a projection
                w.write_frame(frames[i], geom, int(stamps[i]), i)
        for i in (4, 7):
            w.write_msg(fmt.TOPIC_PROJECTION_REJECTED, fmt.image_from_array(frames[i] * 0.3, int(stamps[i])),
                        int(stamps[i]))
    assert check_bag(tmp_path / "b")[fmt.TOPIC_PROJECTION_REJECTED] == 2
    scan = read_scan(tmp_path / "b")
    keep = [i for i in range(12) if i not in (4, 7)]
    np.testing.assert_array_equal(scan.stamps_ns, stamps[keep])
    np.testing.assert_array_equal(scan.counts, frames[keep])
    assert scan.geom.allclose(geom.subset(keep), atol=1e-9)
    assert any("2 frame(s) on /ct/projection_rejected" in w and "1 of them also on /ct/projection" in w
               for w in scan.warnings), scan.warnings
