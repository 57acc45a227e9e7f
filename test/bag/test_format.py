"""Message conversions of the scan bag contract: units, image encodings, scan_info validation."""

from __future__ import annotations

import json

import numpy as np
import pytest

from robot_ct_ros.bag import format as fmt
from robot_ct_ros.bag.format import ScanBagError


def test_geometry_pose_array_round_trip_converts_mm_to_m(tiny_scan):
    geom = tiny_scan[0].perturbed(np.random.default_rng(1).normal(0, [0.3] * 6 + [0.01] * 3, (12, 9)))
    msgs = fmt.geometry_pose_arrays(geom, range(100, 112))
    m = msgs[3]
    assert m.header.frame_id == "world" and fmt.stamp_to_ns(m.header.stamp) == 103
    assert m.poses[0].position.x == pytest.approx(geom.source_mm[3, 0] * 1e-3)
    assert m.poses[1].position.z == pytest.approx(geom.detector_mm[3, 2] * 1e-3)
    views = [fmt.view_from_pose_array(fmt.deserialize(fmt.serialize(x, fmt.POSE_ARRAY), fmt.POSE_ARRAY))
             for x in msgs]
    back = fmt.geometry_from_views(views, geom.n_rows, geom.n_cols, geom.row_pitch_mm, geom.col_pitch_mm)
    assert back.allclose(geom, atol=1e-9)
    # the orientation's matrix columns are (u, v, u x v)
    from scipy.spatial.transform import Rotation
    o = m.poses[1].orientation
    R = Rotation.from_quat([o.x, o.y, o.z, o.w]).as_matrix()
    np.testing.assert_allclose(R[:, 0], geom.u[3], atol=1e-12)
    np.testing.assert_allclose(R[:, 1], geom.v[3], atol=1e-12)
    np.testing.assert_allclose(R[:, 2], geom.w[3], atol=1e-12)


def test_bad_geometry_messages_are_rejected(tiny_scan):
    m = fmt.view_pose_array(*[np.asarray(x)[0] for x in (tiny_scan[0].source_mm, tiny_scan[0].detector_mm,
                                                         tiny_scan[0].u, tiny_scan[0].v)], 5)
    m.poses[1].orientation.w *= 2.0
    with pytest.raises(ValueError, match="normalised"):
        fmt.view_from_pose_array(m)
    m.poses = m.poses[:1]
    with pytest.raises(ValueError, match="2 poses"):
        fmt.view_from_pose_array(m)


@pytest.mark.parametrize("encoding,dtype", [("32FC1", "<f4"), ("16UC1", "<u2"), ("mono16", ">u2"), ("32SC1", ">i4")])
def test_image_encodings_byte_order_and_step(encoding, dtype):
    a = np.arange(12, dtype=np.float64).reshape(3, 4) * 7
    raw = np.ascontiguousarray(a.astype(dtype))
    step = 4 * raw.itemsize + 3  # padded rows
    data = np.zeros(3 * step, np.uint8)
    for r in range(3):
        data[r * step:r * step + 4 * raw.itemsize] = raw[r].view(np.uint8)
    msg = fmt.typestore().types[fmt.IMAGE](header=fmt.header(1, "pcd_detector"), height=3, width=4, encoding=encoding,
                                           is_bigendian=int(dtype[0] == ">"), step=step, data=data)
    out = fmt.array_from_image(msg, fmt.READ_ENCODINGS)
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out, a)


def test_image_writer_layout_and_rejections():
    a = np.arange(6, dtype=np.float32).reshape(2, 3)
    msg = fmt.image_from_array(a, 7)
    assert (msg.height, msg.width, msg.step, msg.encoding, msg.is_bigendian) == (2, 3, 12, "32FC1", 0)
    assert msg.header.frame_id == "pcd_detector"
    np.testing.assert_array_equal(np.frombuffer(msg.data.tobytes(), "<f4").reshape(2, 3), a)
    msg.encoding = "rgb8"
    with pytest.raises(ValueError, match="unsupported image encoding"):
        fmt.array_from_image(msg, fmt.READ_ENCODINGS)
    msg.encoding, msg.data = "32FC1", msg.data[:10]
    with pytest.raises(ValueError, match="bytes"):
        fmt.array_from_image(msg)


def test_scan_info_in_metres_and_validated():
    info = fmt.make_scan_info(8, 12, 0.11, 0.11, binning=2, roi_center_mm=(1, 2, 3), voxel_size_mm=0.04)
    assert info["row_pitch_m"] == pytest.approx(110e-6) and info["roi_center_m"] == pytest.approx([1e-3, 2e-3, 3e-3])
    assert info["format"] == "robot_ct_ros.scan/1" and info["projection_units"] == "counts"
    msg = fmt.scan_info_to_msg(info)
    assert fmt.scan_info_from_msg(msg) == json.loads(msg.data)
    np.testing.assert_allclose(fmt.info_mm(info, "voxel_size_m"), [0.04] * 3)
    for bad, match in [({**info, "format": "other/1"}, "format"), ({**info, "format": "robot_ct_ros.scan/2"}, "not supported"),
                       ({k: v for k, v in info.items() if k != "n_rows"}, "lacks n_rows"),
                       ({**info, "col_pitch_m": 0.11}, "metres"), ({**info, "projection_units": "hu"}, "projection_units"),
                       ({**info, "roi_center_m": [1, 2]}, "roi_center_m")]:
        with pytest.raises(ScanBagError, match=match):
            fmt.validate_scan_info(dict(bad))
    with pytest.raises(ScanBagError, match="JSON"):
        fmt.scan_info_from_msg(fmt.typestore().types[fmt.STRING](data="{not json"))
