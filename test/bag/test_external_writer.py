"""Another lab's bag: written with rosbags alone, following docs/bag-format.md, then read and calibrated.

The writing part imports nothing from robot_ct_ros.bag (only the simulation, to have data).
"""

from __future__ import annotations

import json

import numpy as np
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation


def _write_like_the_docs(path, frames, flat, stamps_ns, sources_m, detectors_m, us, vs, info):
    # --- the recipe of docs/bag-format.md, "Writing a scan bag with rosbags alone" ---
    ts = get_typestore(Stores.ROS2_JAZZY)
    T = ts.types
    String, Image, PoseArray = T["std_msgs/msg/String"], T["sensor_msgs/msg/Image"], T["geometry_msgs/msg/PoseArray"]
    Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
    Pose, Point, Quaternion = T["geometry_msgs/msg/Pose"], T["geometry_msgs/msg/Point"], T["geometry_msgs/msg/Quaternion"]

    def hdr(ns, frame):
        return Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame)

    def image(a, ns, encoding="32FC1", frame="pcd_detector"):
        a = np.ascontiguousarray(a, dtype={"32FC1": "<f4", "mono8": "u1"}[encoding])
        return Image(header=hdr(ns, frame), height=a.shape[0], width=a.shape[1], encoding=encoding,
                     is_bigendian=0, step=a.shape[1] * a.itemsize, data=a.view(np.uint8).ravel())

    def geometry(source_m, detector_m, u, v, ns):
        q = Rotation.from_matrix(np.column_stack([u, v, np.cross(u, v)])).as_quat()  # x, y, z, w
        return PoseArray(header=hdr(ns, "world"), poses=[
            Pose(position=Point(x=source_m[0], y=source_m[1], z=source_m[2]),
                 orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
            Pose(position=Point(x=detector_m[0], y=detector_m[1], z=detector_m[2]),
                 orientation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))])

    never = QosTime(9223372036, 854775807)  # rmw's "infinite" duration, as rosbag2 writes it

    def qos(depth, latched=False):  # offered QoS recorded per topic: reliable, keep-last; latched: transient-local
        return [Qos(QosHistory.KEEP_LAST, depth, QosReliability.RELIABLE,
                    QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE,
                    never, never, QosLiveliness.AUTOMATIC, never, False)]

    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c_info = w.add_connection("/ct/scan_info", "std_msgs/msg/String", typestore=ts,
                                  offered_qos_profiles=qos(1, latched=True))
        c_flat = w.add_connection("/ct/flat_field", "sensor_msgs/msg/Image", typestore=ts,
                                  offered_qos_profiles=qos(1, latched=True))
        c_proj = w.add_connection("/ct/projection", "sensor_msgs/msg/Image", typestore=ts,
                                  offered_qos_profiles=qos(100))
        c_geom = w.add_connection("/ct/geometry", "geometry_msgs/msg/PoseArray", typestore=ts,
                                  offered_qos_profiles=qos(100))
        t0 = stamps_ns[0] - 1
        w.write(c_info, t0, ts.serialize_cdr(String(data=json.dumps(info)), "std_msgs/msg/String"))
        w.write(c_flat, t0, ts.serialize_cdr(image(flat, t0), "sensor_msgs/msg/Image"))
        for frame, ns, s, d, u, v in zip(frames, stamps_ns, sources_m, detectors_m, us, vs):
            w.write(c_proj, ns, ts.serialize_cdr(image(frame, ns), "sensor_msgs/msg/Image"))
            w.write(c_geom, ns, ts.serialize_cdr(geometry(s, d, u, v, ns), "geometry_msgs/msg/PoseArray"))


def test_bag_written_with_rosbags_alone_is_read_and_calibrated(tmp_path, check_bag):
    from robot_ct_ros.ct import simulation as sim
    from robot_ct_ros.ct.geometry import VolumeGrid
    from robot_ct_ros.ct.trajectory import robotic_roi_scan

    # data: an ellipsoid inside the field of view of a 24-view robotic ROI scan (mm inside the core)
    geom = robotic_roi_scan(n_views=24, n_rows=16, n_cols=24, fov_diameter_mm=1.0)
    phantom = sim.Phantom("blob", (sim.ellipsoid((0.0, 0.0, 0.0), (0.4, 0.3, 0.25), 0.5),))
    det = sim.DetectorModel(photons_per_pixel=20000.0, binning=1, poisson=False, flat_field_sigma=0.0,
                            dead_pixel_fraction=0.0, hot_pixel_fraction=0.0)
    scan = sim.simulate_scan(phantom, geom, det, voxel_size_mm=0.02)
    stamps = [1_800_000_000_000_000_000 + 100_000_000 * i + 50_000_000 for i in range(24)]
    info = {"format": "robot_ct_ros.scan/1", "n_rows": 16, "n_cols": 24, "row_pitch_m": geom.row_pitch_mm * 1e-3,
            "col_pitch_m": geom.col_pitch_mm * 1e-3, "binning": 1, "projection_units": "counts", "n_views": 24,
            "notes": "written by another lab"}
    bag = tmp_path / "other_lab"
    _write_like_the_docs(bag, scan.counts, scan.flat, stamps, geom.source_mm * 1e-3, geom.detector_mm * 1e-3,
                         geom.u, geom.v, info)
    check_bag(bag)
    # the QoS profiles bag-format.md says every topic records (a player reaches the transient-local scan_info)
    from rosbags.rosbag2 import Reader

    from robot_ct_ros.bag import format as fmt

    with Reader(bag) as reader:
        recorded = {c.topic: c.ext.offered_qos_profiles for c in reader.connections}
    assert recorded == {t: [fmt.offered_qos(t)] for t in (fmt.TOPIC_SCAN_INFO, fmt.TOPIC_FLAT_FIELD,
                                                        fmt.TOPIC_PROJECTION, fmt.TOPIC_GEOMETRY)}, recorded

    # the project reads it...
    from robot_ct_ros.bag import read_scan
    from robot_ct_ros.ct.calibration import CalibrationSettings
    from robot_ct_ros.jobs.calibrate import calibrate_bag
    from robot_ct_ros.ct.reconstruction import fdk

    data = read_scan(bag)
    assert data.warnings == [] and data.n_views == 24
    assert data.geom.allclose(geom, atol=1e-9)
    np.testing.assert_array_equal(data.stamps_ns, stamps)
    li, mask = data.to_line_integrals()
    np.testing.assert_allclose(li, scan.line_integrals, atol=1e-5)

    # ... reconstructs it ...
    grid = VolumeGrid.centered((16, 32, 32), 0.04)
    vol = fdk(li, data.geom, grid, valid_mask=mask)
    centre = vol[6:10, 13:19, 13:19].mean()
    assert abs(centre - 0.5) < 0.1, centre
    assert abs(vol[:, :3, :3].mean()) < 0.1

    # ... and calibrates it (FDK only until robot_ct_ros.ct.calibration.calibrate runs)
    report = calibrate_bag(bag, tmp_path / "out", CalibrationSettings(iterations=1), shape_xyz=(32, 32, 16),
                           voxel_mm=0.04, say=lambda s: None).report
    assert (tmp_path / "out" / "volume.npy").exists() and (tmp_path / "out" / "report.json").exists()
    corrected = read_scan(report["corrected_bag"])
    assert corrected.geom_corrected is not None and corrected.n_views == 24
    check_bag(report["corrected_bag"])


def test_a_cut_bag_written_with_rosbags_alone_keeps_every_complete_frame(tmp_path):
    """rosbags' writer packs a scan into 1 MiB chunks without a CRC: a file cut inside its last chunk once
    recovered nothing of it (0 messages from a bag cut at 90 %). Every complete message before the cut is kept,
    the pixels exactly, and the cut is reported; a chunk with a CRC (the project's writer) stays all or nothing."""
    from robot_ct_ros.bag import read_scan
    from robot_ct_ros.ct.trajectory import robotic_roi_scan

    n = 24
    geom = robotic_roi_scan(n_views=n, n_rows=16, n_cols=24, fov_diameter_mm=1.0)
    frames = np.random.default_rng(0).uniform(100.0, 1000.0, (n, 16, 24)).astype(np.float32)
    stamps = [1_800_000_000_000_000_000 + 100_000_000 * i for i in range(n)]
    info = {"format": "robot_ct_ros.scan/1", "n_rows": 16, "n_cols": 24, "row_pitch_m": geom.row_pitch_mm * 1e-3,
            "col_pitch_m": geom.col_pitch_mm * 1e-3, "binning": 1, "projection_units": "counts", "n_views": n}
    bag = tmp_path / "whole"
    _write_like_the_docs(bag, frames, np.full((16, 24), 1000.0, np.float32), stamps, geom.source_mm * 1e-3,
                         geom.detector_mm * 1e-3, geom.u, geom.v, info)
    (mcap,) = sorted(bag.glob("*.mcap"))
    data = mcap.read_bytes()
    for fraction in (0.8, 0.5):  # inside the one chunk: the summary (channels with their QoS) is the last 13 %
        cut = tmp_path / f"cut_{fraction}"
        cut.mkdir()
        (cut / mcap.name).write_bytes(data[:int(fraction * len(data))])
        scan = read_scan(cut)
        assert scan.recovered
        # each view's frame and geometry take about 1/n of the file: all but the one being cut survive
        assert scan.n_views >= int(fraction * n) - 2, (fraction, scan.n_views)
        for k, s in enumerate(scan.stamps_ns):
            np.testing.assert_array_equal(scan.counts[k], frames[stamps.index(int(s))])
        assert scan.geom.allclose(geom.subset([stamps.index(int(s)) for s in scan.stamps_ns]), atol=1e-9)
        assert any("complete messages recovered from its start" in w for w in scan.warnings), scan.warnings
