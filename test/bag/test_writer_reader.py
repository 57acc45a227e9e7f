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
    # and lists no empty /ct/flat_field topic (ros2 bag info and Foxglove showed one with 0 messages)
    from rosbags.rosbag2 import Reader

    with Reader(bag) as reader:
        assert fmt.TOPIC_FLAT_FIELD not in {c.topic for c in reader.connections}


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


def test_a_metadata_yaml_whose_qos_differs_from_the_mcaps_channels_loses_no_frame(tmp_path):
    """rosbags pairs metadata.yaml's topics with the MCAP's channels QoS included: with /ct/projection's QoS
    edited in metadata.yaml (as a tool regenerating it would), it returned no frame, without an error, and the
    scan was unreadable. The contract says readers ignore QoS: the reader now reads the MCAP itself."""
    import yaml

    from robot_ct_ros.ct.trajectory import circular_scan

    frames = np.random.default_rng(0).random((4, 6, 8)).astype(np.float32)
    bag = write_scan(tmp_path / "bag", frames, circular_scan(4, 60.0, 150.0, 6, 8, 1.0, 1.0),
                     projection_units="line_integral")
    meta_path = bag / "metadata.yaml"
    meta = yaml.safe_load(meta_path.read_text())
    for topic in meta["rosbag2_bagfile_information"]["topics_with_message_count"]:
        if topic["topic_metadata"]["name"] == "/ct/projection":
            topic["topic_metadata"]["offered_qos_profiles"][0].update(depth=7, reliability="best_effort")
    meta_path.write_text(yaml.safe_dump(meta))
    scan = read_scan(bag)
    assert scan.n_views == 4
    np.testing.assert_array_equal(scan.counts, frames)
    assert any("read from the MCAP file instead" in w for w in scan.warnings), scan.warnings


def test_geometries_in_more_than_one_frame_are_warned(tmp_path):
    """The contract: all geometry messages of one bag use the same frame. A bag alternating world and base_link was
    read without a word."""
    from dataclasses import replace as dc_replace

    from robot_ct_ros.bag.reader import scan_from_raw
    from robot_ct_ros.ct.trajectory import circular_scan

    bag = write_scan(tmp_path / "bag", np.ones((4, 6, 8), np.float32), circular_scan(4, 60.0, 150.0, 6, 8, 1.0, 1.0),
                     projection_units="line_integral")
    raw = read_raw_messages(bag)
    assert not any("frames (" in w for w in read_scan(bag).warnings)
    messages, k = [], 0
    for m in raw.messages:
        if m.topic == fmt.TOPIC_GEOMETRY:
            msg = fmt.deserialize(m.data, fmt.POSE_ARRAY)
            if k % 2:
                msg.header.frame_id = "base_link"
            k += 1
            m = dc_replace(m, data=fmt.serialize(msg, fmt.POSE_ARRAY))
        messages.append(m)
    scan = scan_from_raw(dc_replace(raw, messages=messages), bag)
    assert scan.n_views == 4
    assert any("name 2 frames ('base_link': 2, 'world': 2)" in w for w in scan.warnings), scan.warnings


def test_the_corrected_geometry_carries_the_scans_frame_and_mixed_topics_are_warned(tmp_path, tiny_scan):
    """Outside test 27 A #1: /ct/geometry_corrected always named "world", whatever the frame of the scan's
    /ct/geometry, and the reader compared the frames within one topic only."""
    from dataclasses import replace as dc_replace

    from robot_ct_ros.bag.reader import scan_from_raw

    geom, frames, flat, dead = tiny_scan
    src = write_scan(tmp_path / "lab", frames, geom, flat=flat, frame_id="lab")
    scan = read_scan(src)
    assert scan.frame_id == "lab" and scan.warnings == []
    dst = write_corrected_bag(src, tmp_path / "c", geom, scan.stamps_ns)
    frames_of = {}
    for m in read_raw_messages(dst).messages:
        if m.msgtype == fmt.POSE_ARRAY:
            frames_of.setdefault(m.topic, set()).add(fmt.deserialize(m.data, fmt.POSE_ARRAY).header.frame_id)
    assert frames_of == {fmt.TOPIC_GEOMETRY: {"lab"}, fmt.TOPIC_GEOMETRY_CORRECTED: {"lab"}}
    assert read_scan(dst).warnings == []
    # a bag whose true geometry names another frame than /ct/geometry is warned, and still read
    mixed = write_scan(tmp_path / "mixed", frames, geom, flat=flat, geom_true=geom, frame_id="lab")
    raw = read_raw_messages(mixed)
    relabelled = []
    for m in raw.messages:
        if m.topic == fmt.TOPIC_GEOMETRY_TRUE:
            msg = fmt.deserialize(m.data, fmt.POSE_ARRAY)
            msg.header.frame_id = "world"
            m = dc_replace(m, data=fmt.serialize(msg, fmt.POSE_ARRAY))
        relabelled.append(m)
    scan = scan_from_raw(dc_replace(raw, messages=relabelled), mixed)
    assert scan.geom_true is not None and scan.frame_id == "lab"
    assert any("/ct/geometry: 'lab'" in w and "/ct/geometry_true: 'world'" in w for w in scan.warnings), scan.warnings


def test_a_scan_info_that_is_not_cdr_and_a_bare_sqlite_file_are_named_as_such(tmp_path):
    """A bag compressed per message and read without its metadata.yaml failed with "no /ct/scan_info message
    (found: ..., /ct/scan_info (1))", and an sqlite3 file given alone was described as a damaged MCAP."""
    from dataclasses import replace as dc_replace

    from robot_ct_ros.bag import ScanBagError
    from robot_ct_ros.bag.reader import scan_from_raw
    from robot_ct_ros.ct.trajectory import circular_scan

    bag = write_scan(tmp_path / "bag", np.ones((4, 6, 8), np.float32), circular_scan(4, 60.0, 150.0, 6, 8, 1.0, 1.0),
                     projection_units="line_integral")
    raw = read_raw_messages(bag)
    garbled = [dc_replace(m, data=b"\x28\xb5\x2f\xfd" + m.data[4:]) if m.topic == fmt.TOPIC_SCAN_INFO else m
               for m in raw.messages]  # a zstd frame's magic where CDR's header is
    with pytest.raises(ScanBagError, match="no decodable /ct/scan_info message.*not CDR"):
        scan_from_raw(dc_replace(raw, messages=garbled), bag)
    (tmp_path / "x.db3").write_bytes(b"SQLite format 3\x00")
    with pytest.raises(ScanBagError, match="sqlite3 bag file is read through its bag folder"):
        read_scan(tmp_path / "x.db3")
